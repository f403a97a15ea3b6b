"""The batch plan end to end: the real palpsim-server (from $PALPSIM_BUILD_DIR) on the
phantom, on a free loopback port, with parallel sessions; a haptics-only run builds
nothing else (no deformation, no render thread, no EGL context)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from palpsim.batch import main as batch_main
from palpsim.batch import run_plan
from palpsim.client import Client, ServerError
from palpsim.plan import parse_plan
from palpsim.results import TIMING_COLUMNS, read_table, result_digest
from palpsim.server import LocalServer

ROOT = Path(__file__).resolve().parents[3]

# the phantom at 2 mm voxels with haptics only: the same anatomy as the demo's scene,
# prepared in a few seconds (the 1 mm demo scene takes longer to prepare)
SCENE = """
name: "phantom 2 mm, haptics only (python end-to-end test)"
phantom { voxel_mm: 2.0 }
haptics { stiffness_n_per_mm: 0.25 friction: 0.2 max_force_n: 3.3 }
effects { haptics: true }
"""

# a 3 x 2 grid on the back over L4 (the phantom's back is the ellipse y = 110 mm at x = 0;
# the spinous process tip of L4 lies near z = -38 mm, 26 mm under the skin), pressed
# 10 mm deep along -y, twice each
PLAN = {
    "name": "e2e",
    "sample_rate_hz": 400.0,
    "repetitions": 2,
    "grid": {"center_mm": [0.0, 110.0, -38.0], "axis_u": [1, 0, 0], "axis_v": [0, 0, 1],
             "size_u_mm": 30.0, "size_v_mm": 16.0, "count_u": 3, "count_v": 2},
    "press": {"direction": [0, -1, 0], "reference": "skin", "depth_mm": 10.0,
              "speed_mm_per_s": 40.0, "approach_mm": 6.0, "max_travel_mm": 20.0, "hold_s": 0.01},
}


def _binary() -> Path | None:
    d = os.environ.get("PALPSIM_BUILD_DIR")
    p = Path(d) / "palpsim-server" if d else ROOT / "build" / "palpsim-server"
    return p if p.is_file() and os.access(p, os.X_OK) else None


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    binary = _binary()
    if binary is None:
        reason = ("SKIPPED: no palpsim-server in $PALPSIM_BUILD_DIR="
                  f"{os.environ.get('PALPSIM_BUILD_DIR', '(unset, looked in build/)')}")
        print(reason)
        pytest.skip(reason)
    tmp = tmp_path_factory.mktemp("e2e")
    scene = tmp / "scene.textproto"
    scene.write_text(SCENE)
    srv = LocalServer(binary, scene=scene, bind="tcp://127.0.0.1:*", startup_timeout_s=120,
                      log_path=tmp / "server.log")
    srv.start()
    yield srv
    assert srv.stop() == 0, f"the server did not stop cleanly:\n{srv.tail()}"


def _results(df: pd.DataFrame) -> pd.DataFrame:
    return df.drop(columns=list(TIMING_COLUMNS))


def test_same_plan_same_numbers_with_parallel_sessions(server):
    plan = parse_plan(PLAN, source="e2e")
    a = run_plan(plan, server.address, sessions=2, progress=False).table
    b = run_plan(plan, server.address, sessions=2, progress=False).table
    c = run_plan(plan, server.address, sessions=1, progress=False).table
    # identical, not merely close: no wall clock enters the poses or the forces
    pd.testing.assert_frame_equal(_results(a), _results(b), check_exact=True)
    pd.testing.assert_frame_equal(_results(a), _results(c), check_exact=True)
    assert result_digest(a) == result_digest(b) == result_digest(c)
    # both sessions did work in the parallel run
    assert set(a["session"]) == {0, 1}
    # every press ran; sequence numbers are unique
    assert a.groupby(["point_id", "rep"]).ngroups == 12
    assert a["seq"].is_unique


def test_forces_make_physical_sense(server):
    plan = parse_plan(PLAN, source="e2e")
    df = run_plan(plan, server.address, sessions=2, progress=False).table
    # every press met the skin, about 6 mm in (the back is the ellipse y = 110 at x = 0,
    # y = 108.5 at x = 15; first contact within a voxel (2 mm) of the true skin)
    first = df[df["contact"]].groupby(["point_id", "rep"]).first()
    assert len(first) == 12
    skin_true = 110.0 * np.sqrt(1 - (first["tip_x_mm"] / 155.0) ** 2)
    assert np.all(np.abs(first["tip_y_mm"] - skin_true) <= 2.0)
    # force is exactly zero out of contact (before contact, and after the retraction)
    assert (df.loc[~df["contact"], ["force_x_n", "force_y_n", "force_z_n"]] == 0).all().all()
    # in contact the force pushes the tip back out (against the press direction)
    pressing = df[df["contact"] & (df["depth_mm"] > 1.0)]
    assert (pressing["press_force_n"] > 0).all()
    # the force grows with depth: mean force in 2 mm depth bins rises bin by bin
    inward = df[df["phase"].isin(["approach", "press"]) & df["contact"]]
    bins = pd.cut(inward["depth_mm"], np.arange(0.0, 12.01, 2.0))
    means = inward.groupby(bins, observed=True)["force_n"].mean().to_numpy()
    assert len(means) >= 5 and np.all(np.diff(means) > 0), means
    # and stays within the device's maximum force
    assert df["force_n"].max() <= 3.3 + 1e-9
    # repetitions start from a reset proxy: identical peaks
    peaks = df.groupby(["point_id", "rep"])["force_n"].max().unstack()
    assert (peaks[0] == peaks[1]).all()


def test_errors_are_clear_and_sessions_survive(server):
    with Client(server.address, timeout_s=5) as c:
        s = c.open_session("e2e-errors")
        with pytest.raises(ServerError) as e:
            s.set_parameter("stiffness", 1.0)
        assert e.value.code_name == "ERROR_BAD_PARAMETER" and "stiffness" in str(e.value)
        with pytest.raises(ServerError) as e:
            s.pose((float("nan"), 0.0, 0.0))
        assert e.value.code_name == "ERROR_BAD_POSE"
        # the session keeps working after refusals
        r = s.pose((0.0, 200.0, 0.0), client_time_s=1.0)
        assert not r.contact and np.all(r.force_n == 0)
        st = s.stats()
        assert st.poses >= 1 and st.errors >= 1
        s.close()
        # a closed session's id is refused from then on
        with pytest.raises(ServerError) as e:
            s.reset()
        assert e.value.code_name == "ERROR_UNKNOWN_SESSION"


def test_pipelined_poses_come_back_in_order(server):
    # 4000 poses pressing in and out over L4 with up to 64 in flight: every reply comes
    # back once, in order, and with the same forces as the same poses sent one by one
    n, window = 4000, 64
    y = 115.0 - 12.5 * (1 - np.cos(np.arange(n) * 2 * np.pi / 800))  # 115 mm down to 90 mm
    with Client(server.address, timeout_s=5) as c, c.open_session("pipeline") as s:
        sent, got = [], []
        for i in range(n):
            sent.append(s.send_pose((0.0, y[i], -38.0), client_time_s=1 + i / 1000,
                                    reset_proxy=(i == 0)))
            if len(sent) - len(got) >= window:
                got.append(s.recv_reply())
        while len(got) < n:
            got.append(s.recv_reply())
        assert [r.seq for r in got] == sent
        assert s.stats().poses == n
        one_by_one = [s.pose((0.0, y[i], -38.0), client_time_s=1 + i / 1000, reset_proxy=(i == 0))
                      for i in range(0, n)]
    assert all(np.array_equal(a.force_n, b.force_n) for a, b in zip(got, one_by_one))
    assert any(r.contact for r in got) and any(not r.contact for r in got)


def test_batch_command_writes_table_summary_and_plots(server, tmp_path, capsys):
    plan_file = tmp_path / "plan.json"
    plan_file.write_text(json.dumps(PLAN))
    out = tmp_path / "out"
    rc = batch_main([str(plan_file), "--connect", server.address, "--sessions", "2",
                     "--out", str(out), "--table", "steps.csv", "--no-progress"])
    printed = capsys.readouterr().out
    assert rc == 0
    summary = json.loads((out / "summary.json").read_text())
    df = read_table(out / "steps.csv")
    assert summary["digest"] == result_digest(df)
    assert summary["presses"] == 12 and summary["presses_without_contact"] == 0
    assert summary["force"]["max_force_out_of_contact_n"] == 0
    assert summary["digest"][:16] in printed
    for png in ("force_vs_depth.png", "peak_force_map.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"


# the phantom's spinous processes L5..L1 along z (mm): each is a plate sloping down from
# its tip (its posterior-most point, server/prep/phantom.cpp) over about 14 mm of z
PHANTOM_TIPS_Z_MM = [-69.9, -38.3, -4.6, 28.2, 61.3]
PROCESS_LENGTH_MM = 14.0


def _over_process(z: float, tip: float) -> bool:
    """z lies over the process's posterior edge, with 3 mm of slack: a 2 mm voxel plus
    half of the line's 3 mm spacing."""
    return tip - PROCESS_LENGTH_MM - 3.0 <= z <= tip + 3.0


def test_demo_finds_the_spinous_processes(server, tmp_path, capsys):
    from palpsim.demo import main as demo_main
    import subprocess

    args = ["--connect", server.address, "--out", str(tmp_path / "demo"), "--step-mm", "3",
            "--speed-mm-per-s", "40", "--rate-hz", "400", "--no-progress"]
    # the same scene's bone mask, when palpsim-prep is built beside the server
    prep = server.binary.parent / "palpsim-prep"
    if prep.is_file():
        scene = tmp_path / "scene.textproto"
        scene.write_text(SCENE)
        subprocess.run([str(prep), "phantom", "--scene", str(scene), "--out",
                        str(tmp_path / "patient")], check=True, capture_output=True, timeout=120)
        args += ["--patient", str(tmp_path / "patient")]
    else:
        print(f"(no {prep}: the bone-mask comparison is not exercised)")
    assert demo_main(args) == 0
    report = json.loads((tmp_path / "demo" / "spine.json").read_text())
    found = sorted(p["z_mm"] for p in report["peaks"])
    # one force peak per lumbar process, each over its process
    assert len(found) == 5, found
    for z, tip in zip(found, PHANTOM_TIPS_Z_MM):
        assert _over_process(z, tip), (found, PHANTOM_TIPS_Z_MM)
    if prep.is_file():
        # the bone mask finds the same five processes, and each peak matches one
        exp = report["expected"]
        assert exp["found"] == 5 and exp["extra_peaks"] == 0, exp["processes"]
        for e, tip in zip(sorted(x["z_mm"] for x in exp["processes"]), PHANTOM_TIPS_Z_MM):
            assert _over_process(e, tip)
    assert (tmp_path / "demo" / "spine_profile.png").read_bytes()[:4] == b"\x89PNG"
    assert "spinous processes found as force peaks: 5" in capsys.readouterr().out


def test_haptics_only_batch_run_builds_no_gpu_buffer_and_no_egl_context(server):
    # a scene that asks for haptics only: after a whole batch run the server made no
    # deformation (no device buffer, no backend), no render thread, no EGL context and no
    # publisher; only the haptics stage is built and holds memory
    plan = parse_plan(PLAN, source="e2e")
    result = run_plan(plan, server.address, sessions=2, progress=False)
    assert len(result.table) > 0
    with Client(server.address) as c:
        st = c.stats().server
    stages = {g.name: g for g in st.stages}
    assert stages["haptics"].built and stages["haptics"].runs > 0
    for name in ("chainmail", "relaxation", "inversion", "frames", "bricks"):
        assert not stages[name].built, name
        assert stages[name].bytes_allocated == 0 and stages[name].runs == 0, name
    assert st.deform_backend == "" and st.deform_steps == 0
    assert not st.HasField("stream") or not (st.stream.render_thread or st.stream.egl_context
                                             or st.stream.publisher_thread)
