#!/usr/bin/env python3
"""Issue 9, section 3: palpsim-server and palpsim-haptic over impaired networks.

Makes network namespaces joined by veth pairs, runs palpsim-server in one and the haptic
client (one press cycle of the built-in press, local/remote mode chosen by the client) in
another, and impairs the link per case: half the round trip each way, jitter, loss. Prints
per case the client's rendered force against the force the server computed for the same
poses (RMS, max, % of peak), missed deadlines, watchdog trips, force reversals
(oscillation), the energy over the press cycle, and the link's start (when the first reply
and the first patch came, watchdog trips before the press); --check fails (exit 1) where
a case misses the issue's goals (RMS and oscillation at 100 ms round trip, energy in all).

The press starts when the link is up (the first reply; on a far link the first patch and
local mode; --warmup: at most that long, default 5 s): a cold TCP link takes about 5 round trips (TCP and ZMTP handshakes, slow start, a 29 KiB patch
through the initial window) before the first patch, and a tip that reaches the body
before the client renders any force cannot get back, on the way out, the force that the
passivity controller will not return (energy the hand never put in). --warmup 0 shows
that cold start. The watchdog trips of the 0 ms case follow the machine's load (remote
mode allows 2 ms without a reply); --realtime runs both under SCHED_FIFO to tell the two
apart.

The impairment is tc netem on both ends of one veth pair where the kernel has sch_netem.
Where it has not, a third namespace sits between the two with a veth pair to each, and
scripts/packet_delay_line.py forwards the frames between them late, jittered and lost:
the same packets, delayed in user space instead of in a qdisc ("--link delay-line" forces
it); the unimpaired case gets a kernel bridge there instead. Needs root (ip netns, veth);
without it prints "SKIPPED: <reason>" and exits 0. About 7 s a case. The same cases run on
loopback without privileges, with the delay at the message level:
build/palpsim-test-local-model "[.matrix]". clients/python/tests/test_netem.py runs three
of them in CI.

    python3 scripts/netem_matrix.py [--build build] [--seconds 4.8] [--link auto|netem|delay-line]
                                    [--cases 0,100] [--check] [--warmup S] [--realtime]
                                    [--log-dir DIR] [--client-args "--patch-edge 8"]
"""
import argparse
import math
import os
import re
import subprocess
import sys
import tempfile
import time

# names of this run's own (with the process id: two runs side by side do not meet)
PID = os.getpid()
NS_SERVER, NS_CLIENT, NS_MIDDLE = "palpsim-srv-%d" % PID, "palpsim-cli-%d" % PID, "palpsim-mid-%d" % PID
DEV_SERVER, DEV_CLIENT = "pvs%d" % PID, "pvc%d" % PID
DEV_MID_SERVER, DEV_MID_CLIENT = "pms%d" % PID, "pmc%d" % PID  # the middle's ends of the two pairs
DEV_BRIDGE = "pbr%d" % PID  # the middle's bridge for an unimpaired case
IP_SERVER, IP_CLIENT = "10.77.0.1", "10.77.0.2"
HERE = os.path.dirname(os.path.abspath(__file__))
# (name, round trip ms, jitter ms per direction, loss % per direction)
CASES = [
    ("rtt 0 ms", 0, 0, 0),
    ("rtt 20 ms", 20, 0, 0),
    ("rtt 50 ms", 50, 0, 0),
    ("rtt 100 ms", 100, 0, 0),
    ("rtt 200 ms", 200, 0, 0),
    ("rtt 100 ms, jitter 10 ms", 100, 10, 0),
    ("rtt 100 ms, loss 1 %", 100, 0, 1),
]
SCENE = 'name: "netem"\nphantom { voxel_mm: 2.0 }\nserver { session_timeout_s: 30 max_sessions: 8 }\n'
# the goal at 100 ms round trip: RMS force error within 5 % of the peak
GOAL_RTT_MS = 100
GOAL_RMS_OF_PEAK = 0.05
# a clean press cycle turns the force's magnitude once (up, then down) by more than
# REVERSAL_SWING_N (0.05 N: 1.5 % of the 3.3 N peak, far above a blend's few mN and the
# rounding of the log, far below a ring's swings); "no oscillation" allows one more turn
# (a patch blend or the passivity cut near the release)
REVERSAL_SWING_N = 0.05
GOAL_MAX_REVERSALS = 2
# passive: the rendered force gives back no more than it took over the press (energy the
# hand put in, -sum f . dx, >= 0); the passivity controller predicts the next step's motion
# by the last one's, an error under 1e-3 mJ a step at 20 mm/s, and a few such steps may
# add up: the same 0.01 mJ as palpsim-test-local-model allows
GOAL_MIN_ENERGY_MJ = -0.01
# the longest warm-up (s): the client holds the press until its link is up (the first
# reply; on a far link the first patch and local mode), about 5 round trips, but a lost
# SYN costs TCP's initial retransmission timeout of 1 s (and 2 s more for a second)
MAX_WARMUP_S = 5.0


def run(*cmd, check=True):
    """Runs a command; returns (returncode, combined output)."""
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if check and p.returncode != 0:
        raise RuntimeError(" ".join(cmd) + ": " + p.stdout.strip())
    return p.returncode, p.stdout.strip()


def teardown():
    """Removes the namespaces (and with them the veth pairs); quiet when absent."""
    for ns in (NS_SERVER, NS_CLIENT, NS_MIDDLE):
        run("ip", "netns", "del", ns, check=False)


def add_ends():
    """The two endpoint namespaces."""
    run("ip", "netns", "add", NS_SERVER)
    run("ip", "netns", "add", NS_CLIENT)


def address_ends():
    """Each end its address on the link, the link and loopback up."""
    for ns, dev, ip in ((NS_SERVER, DEV_SERVER, IP_SERVER), (NS_CLIENT, DEV_CLIENT, IP_CLIENT)):
        run("ip", "-n", ns, "addr", "add", ip + "/24", "dev", dev)
        run("ip", "-n", ns, "link", "set", dev, "up")
        run("ip", "-n", ns, "link", "set", "lo", "up")


def setup_direct():
    """Two namespaces joined by one veth pair (for tc netem on both ends)."""
    teardown()
    add_ends()
    run("ip", "link", "add", DEV_SERVER, "type", "veth", "peer", "name", DEV_CLIENT)
    run("ip", "link", "set", DEV_SERVER, "netns", NS_SERVER)
    run("ip", "link", "set", DEV_CLIENT, "netns", NS_CLIENT)
    address_ends()


def setup_middle():
    """Three namespaces: server - middle - client, a veth pair on each side of the middle,
    whose ends carry no address (the delay line forwards the frames between them)."""
    teardown()
    add_ends()
    run("ip", "netns", "add", NS_MIDDLE)
    # the middle sends nothing of its own (no IPv6 autoconfiguration either)
    run("ip", "netns", "exec", NS_MIDDLE, "sysctl", "-q", "-w", "net.ipv6.conf.all.disable_ipv6=1")
    run("ip", "netns", "exec", NS_MIDDLE, "sysctl", "-q", "-w", "net.ipv6.conf.default.disable_ipv6=1")
    for end_dev, end_ns, mid_dev in ((DEV_SERVER, NS_SERVER, DEV_MID_SERVER), (DEV_CLIENT, NS_CLIENT, DEV_MID_CLIENT)):
        run("ip", "link", "add", end_dev, "type", "veth", "peer", "name", mid_dev)
        run("ip", "link", "set", end_dev, "netns", end_ns)
        run("ip", "link", "set", mid_dev, "netns", NS_MIDDLE)
        run("ip", "-n", NS_MIDDLE, "link", "set", mid_dev, "promisc", "on", "up")
    address_ends()


class NetemLink:
    """tc netem on both ends of one veth pair."""
    name = "tc netem"

    def setup(self):
        setup_direct()

    def shape(self, rtt_ms, jitter_ms, loss_pct):
        """Half the round trip each way, jitter and loss per direction."""
        for ns, dev in ((NS_SERVER, DEV_SERVER), (NS_CLIENT, DEV_CLIENT)):
            args = ["ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "netem",
                    "delay", f"{rtt_ms / 2:g}ms"]
            if jitter_ms:
                args.append(f"{jitter_ms:g}ms")
            if loss_pct:
                args += ["loss", f"{loss_pct:g}%"]
            run(*args)

    def unshape(self):
        pass


class DelayLineLink:
    """scripts/packet_delay_line.py in a middle namespace between the two ends."""
    name = "packet delay line (no sch_netem in this kernel)"

    def __init__(self):
        self.proc = None
        self.log = None
        self.bridged = False

    def setup(self):
        setup_middle()

    def shape(self, rtt_ms, jitter_ms, loss_pct):
        """Starts the delay line for one case: half the round trip each way. An unimpaired
        case gets a kernel bridge instead (a plain link: a user-space forwarder on a loaded
        machine would add its own scheduling delays to the 0 ms case)."""
        if not (rtt_ms or jitter_ms or loss_pct):
            run("ip", "-n", NS_MIDDLE, "link", "add", DEV_BRIDGE, "type", "bridge")
            for dev in (DEV_MID_SERVER, DEV_MID_CLIENT):
                run("ip", "-n", NS_MIDDLE, "link", "set", dev, "master", DEV_BRIDGE)
            run("ip", "-n", NS_MIDDLE, "link", "set", DEV_BRIDGE, "up")
            self.bridged = True
            return
        self.log = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            ["ip", "netns", "exec", NS_MIDDLE, sys.executable, os.path.join(HERE, "packet_delay_line.py"),
             DEV_MID_SERVER, DEV_MID_CLIENT, "--delay-ms", f"{rtt_ms / 2:g}", "--jitter-ms", f"{jitter_ms:g}",
             "--loss-pct", f"{loss_pct:g}"], stdout=self.log, stderr=subprocess.STDOUT, text=True)
        # up when it says so (its first line), or failed
        deadline = time.time() + 10
        while time.time() < deadline:
            self.log.seek(0)
            if self.log.read().startswith("packet_delay_line:"):
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        self.log.seek(0)
        raise RuntimeError("the packet delay line did not start: " + self.log.read().strip())

    def unshape(self):
        """Stops the delay line (or removes the bridge); returns its counts line."""
        if self.bridged:
            run("ip", "-n", NS_MIDDLE, "link", "del", DEV_BRIDGE)
            self.bridged = False
            return "kernel bridge (no delay line): a plain link"
        if not self.proc:
            return ""
        self.proc.terminate()
        self.proc.wait(timeout=10)
        self.log.seek(0)
        counts = self.log.read().strip().splitlines()[-1:]
        self.log.close()
        self.proc = None
        return counts[0] if counts else ""


def realtime_ok():
    """True when processes may run under SCHED_FIFO here (chrt -f 10; root, or CAP_SYS_NICE)."""
    try:
        return run("chrt", "-f", "10", "true", check=False)[0] == 0
    except FileNotFoundError:
        return False


def set_up(link):
    """None once `link`'s namespaces are made, else why not (what was made is torn down)."""
    try:
        link.setup()
    except (RuntimeError, FileNotFoundError) as e:
        teardown()
        return "cannot make network namespaces: %s" % e
    return None


def pick_link(which):
    """(link, None) when namespaces and the asked impairment work here, else (None, reason)."""
    if os.geteuid() != 0:
        return None, "needs root for ip netns and veth (running as uid %d)" % os.geteuid()
    if which in ("auto", "netem"):
        link = NetemLink()
        why = set_up(link)
        if why:
            return None, why
        try:
            link.shape(0, 0, 0)
            return link, None
        except RuntimeError as e:
            teardown()
            if which == "netem":
                return None, "tc netem is not available (kernel module sch_netem): %s" % e
    link = DelayLineLink()
    why = set_up(link)
    return (None, why) if why else (link, None)


def summary(out):
    """The numbers of palpsim-haptic's summary (stdout)."""
    def num(pattern, n=1, conv=float):
        m = re.search(pattern, out)
        return tuple(conv(g) for g in m.groups()[:n]) if m else (float("nan"),) * n
    mode = re.search(r"mode (\w+) at exit, local for (\d+) of (\d+) steps", out)
    rms, mx, peak = num(r"rms ([-\d.]+) N, max ([-\d.]+) N, server peak ([-\d.]+) N", 3)
    e_rend, e_srv = num(r"rendered last [-\d.]+, min ([-\d.]+) over \d+ cycles, min running [-\d.]+; "
                        r"server last [-\d.]+, min ([-\d.]+)", 2)
    return {
        "mode": mode.group(1) if mode else "?",
        "local": 100.0 * int(mode.group(2)) / max(1, int(mode.group(3))) if mode else float("nan"),
        "rms": rms, "max": mx, "peak": peak,
        "missed": num(r"missed deadlines (\d+) of", 1, int)[0],
        "lost": num(r"(\d+) lost", 1, int)[0],
        "wdog": num(r"(\d+) watchdog trips", 1, int)[0],
        "e_rend": e_rend, "e_srv": e_srv,
        "first_reply": num(r"first reply at ([-\d.]+) s")[0],
        "first_patch": num(r"first patch at ([-\d.]+) s")[0],
        "warm_trips": num(r"(\d+) watchdog trips in it", 1, int)[0],
        "warmup": num(r"warm-up ([-\d.]+) s")[0],
    }


def log_rows(log_path, columns):
    """The client's CSV log (palpsim-haptic --log) a step at a time, as its fields, past the
    header; rows with fewer than `columns` fields (a line cut at exit) are left out."""
    with open(log_path) as f:
        next(f)
        for line in f:
            c = line.split(",")
            if len(c) >= columns:
                yield c


def reversals(log_path, swing_n=REVERSAL_SWING_N):
    """Turns of the rendered force's magnitude by more than swing_n (a clean press: one)."""
    count, rising, extreme = 0, True, 0.0
    for c in log_rows(log_path, 8):
        m = math.sqrt(sum(float(v) ** 2 for v in c[5:8]))
        if rising:
            extreme = max(extreme, m)
            if m < extreme - swing_n:
                count, rising, extreme = count + 1, False, m
        else:
            extreme = min(extreme, m)
            if m > extreme + swing_n:
                count, rising, extreme = count + 1, True, m
    return count


# the client's loop steps every 1 ms; a gap of STALL_MS between two steps in contact is the
# machine descheduling the client (a link delays replies, never the loop): the force is
# then held over STALL_MS of motion, which a release turns into energy given back and a
# dip of the passivity cut, whatever the link did
STALL_MS = 5.0


def longest_stall_ms(log_path):
    """The longest gap (ms) between two of the client's loop steps in contact (its CSV log)."""
    worst, prev_t = 0.0, None
    for c in log_rows(log_path, 11):
        t = float(c[1])
        if prev_t is not None and c[10] == "1":
            worst = max(worst, 1000.0 * (t - prev_t))
        prev_t = t
    return worst


def run_case(build, seconds, case, scene_path, log_path, link, client_args=(), warmup=None, realtime=False):
    """One case: shape the link, the server in one namespace, the client in the other; the
    press starts after the warm-up (None: when the link is up, at most MAX_WARMUP_S; 0: a
    cold start). realtime:
    both run under SCHED_FIFO (chrt), which tells a loaded CPU's delays from the link's."""
    rt = ["chrt", "-f", "10"] if realtime else []
    name, rtt, jitter, loss = case
    link.shape(rtt, jitter, loss)
    # plain text beyond loopback needs --insecure: this link exists only between the
    # namespaces this script made
    # the server's log goes to a file (a pipe nobody drains could fill and stop it)
    srv_log = open(log_path + ".server.log", "w")
    srv = subprocess.Popen(["ip", "netns", "exec", NS_SERVER, *rt, os.path.join(build, "palpsim-server"), "--bind",
                            f"tcp://{IP_SERVER}:7420", "--pose-bind", f"tcp://{IP_SERVER}:7421", "--scene",
                            scene_path, "--insecure"], stdout=subprocess.PIPE, stderr=srv_log, text=True)
    try:
        line = ""
        deadline = time.time() + 300
        while "ready on" not in line and time.time() < deadline and srv.poll() is None:
            line = srv.stdout.readline()
        if "ready on" not in line:
            raise RuntimeError("palpsim-server did not start: " + line)
        warm = MAX_WARMUP_S if warmup is None else warmup
        cli = subprocess.run(["ip", "netns", "exec", NS_CLIENT, *rt, os.path.join(build, "palpsim-haptic"), "--connect",
                              f"tcp://{IP_SERVER}:7420", "--seconds", str(seconds), "--log", log_path,
                              "--warmup", "%g" % warm, *client_args],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=120)
        # 3: some replies came back after the client's 1 s drain, or not at all (counted as
        # lost in the summary); the press itself ran
        if cli.returncode not in (0, 3):
            raise RuntimeError("palpsim-haptic failed (%d) in case '%s': %s" % (
                cli.returncode, name, (cli.stderr or cli.stdout).strip()[-400:]))
        s = summary(cli.stdout)
        s["revs"] = reversals(log_path)
        s["stall_ms"] = longest_stall_ms(log_path)
        s["name"] = name
        s["rtt"] = rtt

        return s
    finally:
        srv.terminate()
        srv.wait(timeout=20)
        srv_log.close()
        s_link = link.unshape()
        if s_link:
            print("    " + s_link, flush=True)


def misses(s):
    """What in a case misses the issue's goals (empty when none)."""
    out = []
    pct = s["rms"] / s["peak"] if s["peak"] > 0 else float("nan")
    if s["rtt"] == GOAL_RTT_MS and not pct <= GOAL_RMS_OF_PEAK:
        out.append("RMS force error %.2f %% of peak (goal <= %g %%)" % (100 * pct, 100 * GOAL_RMS_OF_PEAK))
    if s["rtt"] == GOAL_RTT_MS and s["revs"] > GOAL_MAX_REVERSALS:
        out.append("%d force reversals (oscillation; a press turns once)" % s["revs"])
    if not s["e_rend"] >= GOAL_MIN_ENERGY_MJ:
        out.append("energy over the press %.4f mJ < %g mJ (the client gave back more than it took)" % (
            s["e_rend"], GOAL_MIN_ENERGY_MJ))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    root = os.path.dirname(HERE)
    ap.add_argument("--build", default=os.environ.get("PALPSIM_BUILD_DIR", os.path.join(root, "build")))
    ap.add_argument("--seconds", type=float, default=4.8, help="client run: one press cycle ends at 4.5 s")
    ap.add_argument("--link", choices=("auto", "netem", "delay-line"), default="auto",
                    help="auto: tc netem where the kernel has it, else the packet delay line")
    ap.add_argument("--cases", default="", help="round trips (ms) to run, comma-separated (default: all cases)")
    ap.add_argument("--check", action="store_true", help="exit 1 when a case misses the goals")
    ap.add_argument("--warmup", type=float, default=None,
                    help="the longest wait for the link before the press starts (default 5 s; 0: a cold start)")
    ap.add_argument("--realtime", action="store_true",
                    help="run server and client under SCHED_FIFO (chrt -f 10): a diagnosis of CPU load")
    ap.add_argument("--client-args", default="", help="more palpsim-haptic arguments, e.g. '--patch-edge 8'")
    ap.add_argument("--log-dir", default="", help="keep each case's client log (palpsim-haptic --log) here")
    args = ap.parse_args()
    cases = CASES
    if args.cases:
        try:
            want = {float(v) for v in args.cases.split(",")}
        except ValueError:
            ap.error("--cases takes round trips in ms, comma-separated, e.g. 0,100")
        cases = [c for c in CASES if c[1] in want]
        if not cases:
            ap.error("--cases %s matches none of the round trips %s" % (args.cases, sorted({c[1] for c in CASES})))
    link, why = pick_link(args.link)
    if why:
        print("SKIPPED: " + why)
        return 0
    print("link: " + link.name, flush=True)
    t0 = time.time()
    load0 = os.getloadavg()[0]
    failures = []
    with tempfile.TemporaryDirectory() as tmp:
        scene = os.path.join(tmp, "scene.textproto")
        with open(scene, "w") as f:
            f.write(SCENE)
        print("%-26s %-6s %7s %8s %8s %7s %6s %5s %5s %10s %10s %6s %7s %7s %5s %5s" % (
            "case", "mode", "local", "rms N", "max N", "rms/pk", "missed", "wdog", "revs", "E rend mJ", "E srv mJ",
            "warm s", "reply s", "patch s", "wdogW", "lost"))
        try:
            for case in cases:
                log = os.path.join(args.log_dir or tmp, "client-%s.csv" % re.sub(r"\W+", "_", case[0]))
                s = run_case(args.build, args.seconds, case, scene, log, link, args.client_args.split(), args.warmup,
                             args.realtime)
                pct = 100 * s["rms"] / s["peak"] if s["peak"] > 0 else float("nan")
                print("%-26s %-6s %6.1f%% %8.4f %8.4f %6.2f%% %6d %5d %5d %10.3f %10.3f %6.2f %7.3f %7.3f %5d %5d" % (
                    s["name"], s["mode"], s["local"], s["rms"], s["max"], pct, s["missed"], s["wdog"], s["revs"],
                    s["e_rend"], s["e_srv"], s["warmup"], s["first_reply"], s["first_patch"], s["warm_trips"],
                    s["lost"]),
                    flush=True)
                failures += ["%s: %s" % (s["name"], m) for m in misses(s)]
        finally:
            teardown()
    print("%d cases in %.0f s over %s; load average %.2f at the start, %.2f at the end (%d CPUs)" % (
        len(cases), time.time() - t0, link.name, load0, os.getloadavg()[0], os.cpu_count()))
    for f in failures:
        print("MISSED: " + f)
    return 1 if (args.check and failures) else 0


if __name__ == "__main__":
    sys.exit(main())
