"""The deformation stats through the Python client: the real palpsim-server (from
$PALPSIM_BUILD_DIR) on the phantom at 4 mm with ChainMail, relaxation and inversion at
VOI 32 reports per-session deformation and per-stage figures; a haptics-only scene
reports the deformation stages as not built, holding 0 bytes."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from palpsim.client import Client
from palpsim.server import LocalServer

ROOT = Path(__file__).resolve().parents[3]

SCENE = """
name: "phantom 4 mm, deformation (python stats test)"
phantom { voxel_mm: 4.0 }
deform { voi_edge: 32 relax_iterations: 10 backend: "cpu" }
effects { haptics: true chainmail: true relaxation: true inversion: true }
"""
ELASTIC = """
name: "phantom 4 mm, elastic force (python stats test)"
phantom { voxel_mm: 4.0 }
haptics { force_model: "elastic" }
deform { voi_edge: 32 relax_method: "elastic" grab_radius_mm: 8 backend: "cpu" }
effects { haptics: true chainmail: true relaxation: true }
"""
HAPTICS_ONLY = """
name: "phantom 4 mm, haptics only (python stats test)"
phantom { voxel_mm: 4.0 }
"""
# how long the test waits for the deformation worker (a loaded 2-core machine)
WORKER_WAIT_S = 30.0


def _binary() -> Path | None:
    d = os.environ.get("PALPSIM_BUILD_DIR")
    p = Path(d) / "palpsim-server" if d else ROOT / "build" / "palpsim-server"
    return p if p.is_file() and os.access(p, os.X_OK) else None


def _server(tmp_path: Path, text: str) -> LocalServer:
    binary = _binary()
    if binary is None:
        reason = f"SKIPPED: no palpsim-server in $PALPSIM_BUILD_DIR={os.environ.get('PALPSIM_BUILD_DIR')}"
        print(reason)
        pytest.skip(reason)
    scene = tmp_path / "scene.textproto"
    scene.write_text(text)
    return LocalServer(binary, scene=scene, startup_timeout_s=120, log_path=tmp_path / "server.log")


def _press(s, info, poses: int = 200) -> int:
    """Presses 10 mm into the back (+y) at the middle of the body; returns the last seq."""
    lo, hi = info.patient.body_min_mm, info.patient.body_max_mm
    x, z = 0.5 * (lo.x + hi.x), 0.5 * (lo.z + hi.z)
    seq = 0
    for i in range(poses + 1):
        r = s.pose((x, hi.y + 5 - 15 * i / poses, z), client_time_s=1 + i / 1000)
        seq = r.seq
    assert r.contact
    return seq


def test_deformation_stats_come_through_the_client(tmp_path):
    srv = _server(tmp_path, SCENE)
    srv.start()
    try:
        with Client(srv.address) as c, c.open_session("deform-stats") as s:
            last = _press(s, s.server_info)
            deadline = time.monotonic() + WORKER_WAIT_S
            st = s.stats()
            while st.deform.last_contact_seq != last and time.monotonic() < deadline:
                time.sleep(0.02)
                st = s.stats()
            d = st.deform
            assert st.HasField("deform") and d.last_contact_seq == last
            assert d.backend == "cpu" and d.steps >= 1 and d.converged and d.deformed
            assert d.last.chainmail_ms > 0 and d.last.relax_ms > 0 and d.last.invert_ms > 0
            assert d.mean.total_ms > 0 and d.moved > 0 and d.bytes_allocated > 0
            stages = {g.name: g for g in st.stages}
            assert all(stages[n].built and stages[n].bytes_allocated > 0
                       for n in ("chainmail", "relaxation", "inversion"))
            server = c.stats().server
            assert server.deform_backend == "cpu" and server.deform_steps >= d.steps
    finally:
        assert srv.stop() == 0


def test_haptics_only_scene_builds_no_deformation(tmp_path):
    srv = _server(tmp_path, HAPTICS_ONLY)
    srv.start()
    try:
        with Client(srv.address) as c, c.open_session("haptics-only") as s:
            _press(s, s.server_info, poses=50)
            st = s.stats()
            assert not st.HasField("deform")
            for stages in (st.stages, c.stats().server.stages):
                g = {x.name: x for x in stages}
                assert g["haptics"].built
                for n in ("chainmail", "relaxation", "inversion"):
                    assert not g[n].built and g[n].bytes_allocated == 0 and g[n].runs == 0
            assert c.stats().server.deform_backend == ""
    finally:
        assert srv.stop() == 0


def test_elastic_force_stats_come_through_the_client(tmp_path):
    """A press held 8 mm under the body's top: once the worker has stepped on the held tip,
    the pose reply's force is the step's force in the stats (the same doubles: 1e-9 N)."""
    srv = _server(tmp_path, ELASTIC)
    srv.start()
    try:
        with Client(srv.address) as c, c.open_session("elastic-stats") as s:
            info = s.server_info
            lo, hi = info.patient.body_min_mm, info.patient.body_max_mm
            x, z = 0.5 * (lo.x + hi.x), 0.5 * (lo.z + hi.z)
            y = hi.y - 8
            t = 1.0
            for i in range(201):
                t += 1e-3
                s.pose((x, hi.y + 5 - 13 * i / 200, z), client_time_s=t)
            t += 1e-3
            hold = s.pose((x, y, z), client_time_s=t)
            deadline = time.monotonic() + WORKER_WAIT_S
            e = s.stats().deform.elastic
            while e.model_pose_seq < hold.seq and time.monotonic() < deadline:
                time.sleep(0.02)
                e = s.stats().deform.elastic
            assert e.model_pose_seq >= hold.seq and e.contact
            # a jump is taken in steps of 0.05 N (the default elastic_max_jump_n) a pose, and no
            # force is above max_force_n = 3.3 N: 66 poses take any jump
            for i in range(70):
                t += 1e-3
                r = s.pose((x, y, z), client_time_s=t)
            e = s.stats().deform.elastic
            assert r.contact and r.force_n[1] > 0 and e.stiffness_n_per_mm > 0
            assert abs(r.force_n[1] - e.force_n.y) < 1e-9 and abs(r.force_n[0] - e.force_n.x) < 1e-9
            assert e.models_taken >= 1 and e.models_published >= e.models_taken
    finally:
        assert srv.stop() == 0
