"""Issue 9, section 3: palpsim-server and palpsim-haptic over impaired links made in network
namespaces (scripts/netem_matrix.py: tc netem where the kernel has it, else its packet delay
line in a middle namespace). Three of the matrix's cases, one press cycle each (~7 s): the
plain link (0 ms), 100 ms round trip, and 100 ms with 1 % loss each way. At 100 ms the
issue's goal holds: the force the client renders is within 5 % (RMS) of the peak of the
force the server computes for the same poses, the force does not oscillate and the client
gives back no more energy than it took; a case that misses while the machine stalled the
client's loop runs once more. Needs root (ip netns, veth); skips with the reason
where it is not root or namespaces cannot be made. The full matrix stays a script."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


def _matrix():
    """scripts/netem_matrix.py as a module (its cases, goals and runner)."""
    spec = importlib.util.spec_from_file_location("netem_matrix", ROOT / "scripts" / "netem_matrix.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _build() -> Path:
    d = Path(os.environ.get("PALPSIM_BUILD_DIR", ROOT / "build"))
    for exe in ("palpsim-server", "palpsim-haptic"):
        p = d / exe
        if not (p.is_file() and os.access(p, os.X_OK)):
            reason = f"SKIPPED: no {exe} in {d} ($PALPSIM_BUILD_DIR)"
            print(reason)
            pytest.skip(reason)
    return d


def test_impaired_links_meet_the_goal_at_100_ms(tmp_path):
    build = _build()
    nm = _matrix()
    link, why = nm.pick_link("auto")
    if why:
        print("SKIPPED: " + why)
        pytest.skip(why)
    wanted = ("rtt 0 ms", "rtt 100 ms", "rtt 100 ms, loss 1 %")
    cases = [c for c in nm.CASES if c[0] in wanted]
    assert len(cases) == len(wanted), "netem_matrix.CASES lost a case this test runs"
    scene = tmp_path / "scene.textproto"
    scene.write_text(nm.SCENE)
    # the server and the client under SCHED_FIFO where allowed: the test measures the link, and
    # on a loaded 2-core machine a client descheduled for 0.4 s (seen once in about a dozen
    # runs beside builds) trips its watchdog whatever the link does
    realtime = nm.realtime_ok()
    print("server and client under SCHED_FIFO: %s" % ("yes" if realtime else "no (chrt refused)"))
    results = {}
    try:
        for case in cases:
            log = tmp_path / ("client-%d.csv" % len(results))
            s = nm.run_case(str(build), 4.8, case, str(scene), str(log), link, realtime=realtime)
            # a case that misses a goal while the machine stalled the client's loop in contact
            # (netem_matrix.STALL_MS says why that is not the link) runs once more; the second
            # run's figures stand, goals and all
            if case[1] == nm.GOAL_RTT_MS and nm.misses(s) and s["stall_ms"] > nm.STALL_MS:
                print("%s: the client's loop stalled %.1f ms in contact and the case missed: %s; once more" % (
                    case[0], s["stall_ms"], "; ".join(nm.misses(s))))
                s = nm.run_case(str(build), 4.8, case, str(scene), str(log) + ".again.csv", link, realtime=realtime)
            results[case[0]] = s
    finally:
        nm.teardown()
    for name, s in results.items():
        print("%-22s %s: mode %s, local %.0f %%, rms %.4f N of peak %.3f N, max %.3f N, missed %d, watchdog %d "
              "(%d in the warm-up), reversals %d, energy %.3f mJ (server %.3f), longest stall %.1f ms" % (
                  name, link.name, s["mode"], s["local"], s["rms"], s["peak"], s["max"], s["missed"], s["wdog"],
                  s["warm_trips"], s["revs"], s["e_rend"], s["e_srv"], s["stall_ms"]))

    # the plain link: a near client renders the server's force (remote), for most of the run:
    # a stall of over 64 ms on a loaded machine is a slow link for that moment and may take
    # it local for the 0.5 s dwell (palpsim-test-local-model allows a fifth of the steps
    # too). Its watchdog trips, missed deadlines and force reversals follow the machine's
    # load (2 ms of grace at 1 kHz; SCHED_FIFO makes them fewer, not none): printed only
    s0 = results["rtt 0 ms"]
    assert s0["local"] <= 20.0
    assert s0["e_rend"] >= nm.GOAL_MIN_ENERGY_MJ

    for name in ("rtt 100 ms", "rtt 100 ms, loss 1 %"):
        s = results[name]
        # a far client renders locally, from well before the press reaches the skin
        assert s["mode"] == "local", name
        assert s["peak"] > 1.0, name  # the press really pressed (the phantom reaches the 3.3 N clamp)
        # the goal: RMS within 5 % of the peak
        assert s["rms"] <= nm.GOAL_RMS_OF_PEAK * s["peak"], name
        # no oscillation: the force's magnitude turns by more than 0.05 N at most twice in
        # the press (once at its top, once more for a patch blend or the passivity cut at
        # the release; netem_matrix.REVERSAL_SWING_N says why 0.05 N)
        assert s["revs"] <= nm.GOAL_MAX_REVERSALS, name
        # passive: no more energy given back than taken, up to the controller's one-step
        # prediction error summed over a few steps (netem_matrix.GOAL_MIN_ENERGY_MJ)
        assert s["e_rend"] >= nm.GOAL_MIN_ENERGY_MJ, name
