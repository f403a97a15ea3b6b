#!/usr/bin/env python3
"""Issue 9, section 3: palpsim-server and palpsim-haptic over impaired networks.

Makes two network namespaces joined by a veth pair, runs palpsim-server in one and the
haptic client (one press cycle of the built-in press, local/remote mode chosen by the
client) in the other, and for each case shapes both ends with tc netem (half the round
trip each way, jitter, loss). Prints per case the client's rendered force against the
force the server computed for the same poses (RMS, max, % of peak), missed deadlines,
watchdog trips, force reversals (oscillation) and the energy over the press cycle.

Needs root (ip netns, veth) and the sch_netem qdisc. Where either is missing it prints
"SKIPPED: <reason>" and exits 0; with --allow-no-netem it still runs the 0 ms case
across the namespaces (the plumbing) and skips the rest. About 7 s a case, 50 s in all.
The same cases run on loopback without privileges through a user-space delay line:
    build/palpsim-test-local-model "[.matrix]"

    python3 scripts/netem_matrix.py [--build build] [--seconds 4.8] [--allow-no-netem]
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
NS_SERVER, NS_CLIENT = "palpsim-srv-%d" % os.getpid(), "palpsim-cli-%d" % os.getpid()
DEV_SERVER, DEV_CLIENT = "pvs%d" % os.getpid(), "pvc%d" % os.getpid()
IP_SERVER, IP_CLIENT = "10.77.0.1", "10.77.0.2"
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


def run(*cmd, check=True):
    """Runs a command; returns (returncode, combined output)."""
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if check and p.returncode != 0:
        raise RuntimeError(" ".join(cmd) + ": " + p.stdout.strip())
    return p.returncode, p.stdout.strip()


def teardown():
    """Removes the namespaces (and with them the veth pair); quiet when absent."""
    for ns in (NS_SERVER, NS_CLIENT):
        run("ip", "netns", "del", ns, check=False)


def setup():
    """Two namespaces, a veth pair between them with addresses, loopback up."""
    teardown()
    run("ip", "netns", "add", NS_SERVER)
    run("ip", "netns", "add", NS_CLIENT)
    run("ip", "link", "add", DEV_SERVER, "type", "veth", "peer", "name", DEV_CLIENT)
    run("ip", "link", "set", DEV_SERVER, "netns", NS_SERVER)
    run("ip", "link", "set", DEV_CLIENT, "netns", NS_CLIENT)
    for ns, dev, ip in ((NS_SERVER, DEV_SERVER, IP_SERVER), (NS_CLIENT, DEV_CLIENT, IP_CLIENT)):
        run("ip", "-n", ns, "addr", "add", ip + "/24", "dev", dev)
        run("ip", "-n", ns, "link", "set", dev, "up")
        run("ip", "-n", ns, "link", "set", "lo", "up")


def shape(rtt_ms, jitter_ms, loss_pct):
    """netem on both ends: half the round trip each way, jitter and loss per direction."""
    for ns, dev in ((NS_SERVER, DEV_SERVER), (NS_CLIENT, DEV_CLIENT)):
        args = ["ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root", "netem",
                "delay", f"{rtt_ms / 2:g}ms"]
        if jitter_ms:
            args.append(f"{jitter_ms:g}ms")
        if loss_pct:
            args += ["loss", f"{loss_pct:g}%"]
        run(*args)


def why_not_runnable():
    """None when namespaces and netem work here, else the reason (the namespaces are left set up)."""
    if os.geteuid() != 0:
        return "needs root for ip netns and veth (running as uid %d)" % os.geteuid(), False
    try:
        setup()
    except (RuntimeError, FileNotFoundError) as e:
        teardown()
        return "cannot make network namespaces: %s" % e, False
    try:
        shape(0, 0, 0)
    except RuntimeError as e:
        return "tc netem is not available (kernel module sch_netem): %s" % e, True
    return None, True


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
        "wdog": num(r"(\d+) watchdog trips", 1, int)[0],
        "e_rend": e_rend, "e_srv": e_srv,
    }


def reversals(log_path, swing_n=0.05):
    """Turns of the rendered force's magnitude by more than swing_n (a clean press: one)."""
    count, rising, extreme = 0, True, 0.0
    with open(log_path) as f:
        next(f)
        for line in f:
            c = line.split(",")
            if len(c) < 8:
                continue
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


def run_case(build, seconds, case, scene_path, log_path, netem):
    """One case: shape (where netem exists), the server in one namespace, the client in the other."""
    name, rtt, jitter, loss = case
    if netem:
        shape(rtt, jitter, loss)
    # plain text beyond loopback needs --insecure: this link exists only between the two
    # namespaces this script made
    # the server's log goes to a file (a pipe nobody drains could fill and stop it)
    srv_log = open(log_path + ".server.log", "w")
    srv = subprocess.Popen(["ip", "netns", "exec", NS_SERVER, os.path.join(build, "palpsim-server"), "--bind",
                            f"tcp://{IP_SERVER}:7420", "--pose-bind", f"tcp://{IP_SERVER}:7421", "--scene",
                            scene_path, "--insecure"], stdout=subprocess.PIPE, stderr=srv_log, text=True)
    try:
        line = ""
        deadline = time.time() + 300
        while "ready on" not in line and time.time() < deadline and srv.poll() is None:
            line = srv.stdout.readline()
        if "ready on" not in line:
            raise RuntimeError("palpsim-server did not start: " + line)
        cli = subprocess.run(["ip", "netns", "exec", NS_CLIENT, os.path.join(build, "palpsim-haptic"), "--connect",
                              f"tcp://{IP_SERVER}:7420", "--seconds", str(seconds), "--log", log_path],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=120)
        s = summary(cli.stdout)
        s["revs"] = reversals(log_path)
        s["name"] = name
        return s
    finally:
        srv.terminate()
        srv.wait(timeout=20)
        srv_log.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    ap.add_argument("--build", default=os.environ.get("PALPSIM_BUILD_DIR", os.path.join(root, "build")))
    ap.add_argument("--seconds", type=float, default=4.8, help="client run: one press cycle ends at 4.5 s")
    ap.add_argument("--allow-no-netem", action="store_true",
                    help="without netem, still run the 0 ms case across the namespaces")
    args = ap.parse_args()
    why, have_ns = why_not_runnable()
    cases = CASES
    if why:
        if not (have_ns and args.allow_no_netem):
            teardown()
            print("SKIPPED: " + why)
            return 0
        print("netem missing (%s): only the 0 ms case runs" % why)
        cases = CASES[:1]
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        scene = os.path.join(tmp, "scene.textproto")
        with open(scene, "w") as f:
            f.write(SCENE)
        print("%-26s %-6s %7s %8s %8s %7s %6s %5s %5s %10s %10s" % (
            "case", "mode", "local", "rms N", "max N", "rms/pk", "missed", "wdog", "revs", "E rend mJ", "E srv mJ"))
        try:
            for case in cases:
                s = run_case(args.build, args.seconds, case, scene, os.path.join(tmp, "client.csv"), not why)
                pct = 100 * s["rms"] / s["peak"] if s["peak"] > 0 else float("nan")
                print("%-26s %-6s %6.1f%% %8.4f %8.4f %6.2f%% %6d %5d %5d %10.3f %10.3f" % (
                    s["name"], s["mode"], s["local"], s["rms"], s["max"], pct, s["missed"], s["wdog"], s["revs"],
                    s["e_rend"], s["e_srv"]), flush=True)
        finally:
            teardown()
    print("%d cases in %.0f s" % (len(cases), time.time() - t0))
    return 0


if __name__ == "__main__":
    sys.exit(main())
