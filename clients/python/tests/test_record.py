"""palpsim.record: the stepped recording of a press and its MP4 and contact sheet.

- The writers on synthetic frames (stream_fakes.seq_image: 16 bars that spell a number,
  so the frame a tile or a video frame shows can be read back).
- The stepped logic against the fake server of stream_fakes.py with a renderer written
  here that behaves like the server's render thread (it draws whenever the tip or J
  changed, taking a while per frame, with J lagging the tip), so frames that show an
  earlier pose, or the new tip over an older deformation, really arrive and must be
  passed over.
- End to end on the real palpsim-server ($PALPSIM_BUILD_DIR), a 3-step press on the 2 mm
  phantom with 320x180 frames (skipped, with the reason printed, where there is none).
"""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Iterator

import numpy as np
import pytest
from stream_fakes import (FakeServer, flat_skin, frame_parts, read_mp4, read_png, read_seq,
                          seq_image, start_stream_server)

from palpsim import record as rec_mod
from palpsim.client import Client, ServerError
from palpsim.proto import wire
from palpsim.record import (RecordError, contact_sheet, frame_shows_step, pick_frames,
                            press_depths, record_press, sheet_layout, write_mp4, write_recording)

# ---------------------------------------------------------------------------------------
# Depths and the rule that picks a step's frame


def test_press_depths():
    assert press_depths(15.0, 3) == [-5.0, 5.0, 10.0, 15.0, 10.0, 5.0, -5.0]
    assert press_depths(12.0, 1, above_mm=2.0) == [-2.0, 12.0, -2.0]
    for bad in (dict(steps=0), dict(max_depth_mm=0.0), dict(max_depth_mm=float("nan"))):
        with pytest.raises(ValueError):
            press_depths(**{"max_depth_mm": 15.0, "steps": 3, **bad})


def _frame(pose_seq, deform_pose_seq=0, deformed=False):
    return wire.Frame(pose_seq=pose_seq, deform_pose_seq=deform_pose_seq, deformed=deformed)


@pytest.mark.parametrize("frame,contact,deforms,why", [
    (_frame(99, 99, True), True, True, "pose"),              # an earlier pose
    (_frame(100, 99, True), True, True, "deformation"),       # this tip over an older J
    (_frame(100, 100, True), True, True, None),
    (_frame(140, 120, True), True, True, None),               # a later pose of the same hold
    (_frame(100, 99, True), False, True, "release"),          # out of the body, still deformed
    (_frame(100, 99, False), False, True, None),
    (_frame(100, 0, False), True, False, None),               # a scene without deformation
    (_frame(99, 0, False), True, False, "pose"),
])
def test_frame_shows_step(frame, contact, deforms, why):
    assert frame_shows_step(frame, first_seq=100, contact=contact, deforms=deforms) == why


def test_pick_frames():
    assert pick_frames(4, 6) == [0, 1, 2, 3]
    assert pick_frames(7, 6) == [0, 1, 2, 4, 5, 6]
    # the demo's 7 steps: the deepest (index 3) replaces its nearest pick
    assert pick_frames(7, 6, keep=(3,)) == [0, 1, 3, 4, 5, 6]
    for n, keep in ((11, 5), (11, 7), (30, 13)):
        picks = pick_frames(n, 6, keep=(keep,))
        assert keep in picks and picks[0] == 0 and picks[-1] == n - 1 and len(picks) == 6


# ---------------------------------------------------------------------------------------
# The writers on synthetic frames


def _labels(n):
    return [[f"step {i + 1}/{n}  depth {i:.1f} mm  force 0.{i}0 N", f"deformation step {10 * i}"]
            for i in range(n)]


def test_contact_sheet_layout_tiles_and_labels():
    n, w, h = 6, 320, 180
    images = [seq_image(100 + i, w, h) for i in range(n)]
    sheet = contact_sheet(images, _labels(n), "synthetic press", cols=3, tile_width=w)
    lay = sheet_layout(n, w, h, cols=3, tile_width=w)
    # 3 x 2 tiles of 320x180 under two label lines each, a title line, 10-pixel margins
    assert (lay.cols, lay.rows, lay.tile_w, lay.tile_h) == (3, 2, 320, 180)
    assert sheet.shape == (lay.height, lay.width, 3)
    assert lay.width == 3 * 320 + 4 * 10
    assert lay.height == 2 * 10 + lay.title_h + 2 * (lay.label_h + 180 + 10)
    assert sheet.std() > 20                                  # not blank
    bg = np.array(rec_mod.CAPTION_BG)
    # the title line has text: light pixels (> 150) on the dark background; a line of 15
    # characters at 14 pixels has several hundred of them
    title = sheet[10:10 + lay.title_h, 10:lay.width - 10]
    assert (title.max(axis=2) > 150).sum() > 200
    labels = []
    for i in range(n):
        x, y = lay.label_xy(i)
        label = sheet[y:y + lay.label_h, x:x + w]
        tile = sheet[y + lay.label_h:y + lay.label_h + h, x:x + w]
        # each tile is its own frame, at full size here (the bars spell its number) ...
        assert read_seq(tile) == 100 + i
        # ... under its label: two lines of text (well over 200 light pixels), with the
        # caption background around it
        assert (label.max(axis=2) > 150).sum() > 200, i
        assert np.all(label[0, :] == bg) and np.all(label[:, 0] == bg)
        labels.append(label.astype(int))
    # the labels differ as their text does (the text is drawn from each label)
    assert all(np.abs(labels[0] - lab).sum() > 1000 for lab in labels[1:])
    # between the tiles: the background
    x, y = lay.label_xy(1)
    assert np.all(sheet[y:y + lay.label_h + h, x - 10:x] == bg)


def test_contact_sheet_scales_tiles():
    images = [seq_image(7, 1280, 720), seq_image(8, 1280, 720)]
    sheet = contact_sheet(images, _labels(2), "t", cols=3, tile_width=640)
    lay = sheet_layout(2, 1280, 720, cols=3, tile_width=640)
    assert sheet.shape == (lay.height, lay.width, 3) and lay.tile_h == 360
    # downscaled by 2, the bars still read
    for i in range(2):
        x, y = lay.label_xy(i)
        assert read_seq(sheet[y + lay.label_h:y + lay.label_h + 360, x:x + 640]) == 7 + i


def test_mp4_frames_size_fps_and_order(tmp_path):
    # odd sizes: the video is padded to even edges (yuv420p)
    n, per, w, h = 5, 3, 321, 181
    images = [seq_image(200 + i, w, h) for i in range(n)]
    path = tmp_path / "press.mp4"
    count = write_mp4(images, _labels(n), path, fps=10.0, frames_per_image=per)
    frames, meta = read_mp4(path)
    assert count == len(frames) == n * per
    assert float(meta["fps"]) == pytest.approx(10.0, abs=1e-3)
    vh, vw = frames[0].shape[:2]
    cap_h = rec_mod.captioned(images[0], _labels(n)[0]).shape[0] - h
    assert (vw, vh) == (w + 1, h + cap_h + (h + cap_h) % 2)
    # each image for `per` frames, in order: h264 is lossy, but the bars read the same
    # (about 100 grey levels of margin against a few levels of error)
    assert [read_seq(f[:h, :w]) for f in frames] == [200 + i for i in range(n) for _ in range(per)]
    # the caption strip under the frame carries text (light pixels on dark)
    strip = frames[0][h + 2:h + cap_h - 2, :w]
    assert (strip.max(axis=2) > 150).sum() > 100
    with pytest.raises(ValueError):
        write_mp4(images, _labels(n - 1), tmp_path / "x.mp4")


# ---------------------------------------------------------------------------------------
# The stepped logic against a fake renderer

SKIN_Y_MM = 100.0
K_N_PER_MM = 0.1


def fake_renderer(render_s: float, deform_lag_s: float, frames: bool = True):
    """A render thread like the server's: it draws a session when its newest tip or its
    deformation changed, capturing both when it starts and publishing `render_s` later,
    and begins the next one at once. The deformation lags the poses by `deform_lag_s`
    (a worker stepping on the newest contact): it is that of the newest pose at least
    that old (deformed when it was in contact), so a frame started just after the tip
    moved shows the new tip over the old deformation."""
    def script(fake: FakeServer, topic: bytes) -> Iterator[Any]:
        if not topic.startswith(b"frame."):
            return
        sid = int(topic[6:], 16)
        seq, drawn, steps = 0, None, 0
        deform_seq, deformed = 0, False
        while sid in fake.sessions:
            poses = fake.poses.get(sid, [])
            if not poses or not frames:
                yield 0.005
                continue
            cutoff = time.monotonic() - deform_lag_s
            for t, req, rep in poses:
                if t > cutoff:
                    break
                if req.seq > deform_seq or (not rep.contact and deformed):
                    if rep.contact:
                        deform_seq, deformed = req.seq, True
                        steps += 1
                    elif deformed:
                        deformed = False
            _, req, rep = poses[-1]
            state = ((req.tip_mm.x, req.tip_mm.y, req.tip_mm.z), deform_seq, deformed)
            if state == drawn:
                yield 0.005
                continue
            yield render_s
            seq += 1
            v = fake.views[sid]
            yield frame_parts(sid, seq, v.width, v.height, pose_seq=req.seq,
                              deform_pose_seq=deform_seq, deformed=deformed, deform_step=steps,
                              contact=rep.contact)
            drawn = state
    return script


def _record_on_fake(depths, render_s=0.3, deform_lag_s=0.2, step_timeout_s=20.0, **kw):
    fake = FakeServer(sessions=(), pose_model=flat_skin(SKIN_Y_MM, K_N_PER_MM),
                      stages=("haptics", "chainmail", "frames"),
                      script=fake_renderer(render_s, deform_lag_s))
    with fake, Client(fake.address) as c:
        rec = record_press(c, (0.0, SKIN_Y_MM + 10.0, -5.0), (0, -1, 0), depths,
                           view={"width": 320, "height": 180, "preset": "bone"},
                           step_timeout_s=step_timeout_s, **kw)
    return fake, rec


def test_stepped_recording_keeps_the_frame_of_each_step():
    depths = press_depths(6.0, 2)                         # -5, 3, 6, 3, -5 mm
    fake, rec = _record_on_fake(depths)
    assert [f.depth_mm for f in rec.frames] == depths
    # the skin of the flat body at y = 100, found within one approach step (20 mm/s at
    # 200 poses/s: 0.1 mm) from 10 mm above it
    assert rec.skin_travel_mm == pytest.approx(10.1, abs=1e-9)
    assert rec.deforms
    passed_over = {"pose": 0, "deformation": 0, "release": 0}
    for f in rec.frames:
        fr = f.frame
        # the frame shows this step: a pose at its depth, its deformation computed there
        # (in contact) or released (out of contact) ...
        assert fr.pose_seq >= f.first_seq
        assert f.reply.seq == fr.pose_seq
        if f.depth_mm > 0:
            assert f.reply.contact and fr.deformed and fr.deform_pose_seq >= f.first_seq
            assert f.reply.depth_mm == pytest.approx(f.depth_mm + 0.1, abs=1e-9)
            assert f.force_n == pytest.approx(K_N_PER_MM * (f.depth_mm + 0.1), abs=1e-9)
        else:
            assert not f.reply.contact and not fr.deformed and f.force_n == 0.0
        # ... the tip held is the one asked for ...
        np.testing.assert_allclose(f.tip_mm, (0.0, SKIN_Y_MM + 10.0 - 10.1 - f.depth_mm, -5.0),
                                   atol=1e-9)
        # ... and the picture kept is that frame's (its bars spell its frame_seq)
        assert read_seq(f.rgb) == fr.frame_seq and f.rgb.shape == (180, 320, 3)
        for why, n in f.rejected.items():
            passed_over[why] += n
    # frames that showed the new tip over the older deformation did come and were passed
    # over: the rule on deform_pose_seq is what kept them out
    assert passed_over["deformation"] > 0 and passed_over["pose"] > 0, passed_over
    # the frames are distinct and in order
    seqs = [f.frame.frame_seq for f in rec.frames]
    assert seqs == sorted(set(seqs))
    # the session was opened, watched with the view asked for (and the fixed look-at
    # point 35 mm under the skin point) and closed
    assert fake.opened == fake.closed == [rec.session_id]
    (w,) = fake.watches
    assert w.frames and w.view.width == 320 and not w.view.look_at_tip
    assert (w.view.center_mm.x, w.view.center_mm.y, w.view.center_mm.z) == pytest.approx(
        (0.0, SKIN_Y_MM + 10.0 - 10.1 - rec_mod.LOOK_AT_DEPTH_MM, -5.0))


def test_poses_keep_their_pace_while_frames_are_awaited():
    """Each step waits a frame or two of 0.6 s and a deformation lag of 0.2 s; the poses
    go on at 200 a second meanwhile. The largest gap between two poses the fake received
    stays under 0.3 s: 60 periods, room for a loaded 2-core machine (the fake shares this
    process, and so the GIL, with the recorder), while a recorder that waited on the
    stream instead of posing would leave gaps of a frame, 0.6 s or more."""
    fake, rec = _record_on_fake(press_depths(4.0, 1), render_s=0.6, deform_lag_s=0.2)
    times = [t for t, _, _ in fake.poses[rec.session_id]]
    gaps = np.diff(times)
    assert gaps.max() < 0.3, gaps.max()
    assert rec.max_pose_gap_s < 0.3
    # and at about the rate asked for: at least half of 200 a second overall
    assert len(times) / (times[-1] - times[0]) > 100


def test_same_press_same_tips_depths_and_forces():
    """Only the waits vary between runs: the tips, depths, contacts and forces of the
    steps come out the same (the device clock counts poses, not seconds)."""
    depths = press_depths(4.0, 2)
    runs = []
    for _ in range(2):
        _, rec = _record_on_fake(depths, render_s=0.05, deform_lag_s=0.05)
        runs.append([(f.depth_mm, tuple(f.tip_mm), f.reply.contact, f.reply.depth_mm,
                      tuple(f.reply.force_n)) for f in rec.frames])
    assert runs[0] == runs[1]


def test_a_frame_of_the_hold_before_the_step_counts():
    """The render thread draws a session when it is first watched, with its newest pose,
    and then only when something changes. The first step (above the skin) holds the tip
    where the approach left it: the frame drawn at the watch shows a pose from before the
    step began at that very place, and no other frame comes while the tip stays (a scene
    without deformation: nothing else changes). That frame shows the step."""
    def once_then_on_moves(fake: FakeServer, topic: bytes) -> Iterator[Any]:
        sid = int(topic[6:], 16)
        watched = fake.watch_times[-1]
        seq, drawn = 0, None
        while sid in fake.sessions:
            poses = fake.poses[sid]
            # the first frame: the newest pose before the watch; then the newest pose
            t, req, rep = (poses[-1] if seq else
                           next(p for p in reversed(poses) if p[0] <= watched))
            tip = (req.tip_mm.x, req.tip_mm.y, req.tip_mm.z)
            if tip != drawn:
                seq += 1
                yield frame_parts(sid, seq, 320, 180, pose_seq=req.seq, contact=rep.contact)
                drawn = tip
            yield 0.01

    fake = FakeServer(sessions=(), pose_model=flat_skin(SKIN_Y_MM), stages=("haptics", "frames"),
                      script=once_then_on_moves)
    with fake, Client(fake.address) as c:
        rec = record_press(c, (0.0, SKIN_Y_MM + 10.0, 0.0), (0, -1, 0), [-5.0, 3.0, -5.0],
                           step_timeout_s=3.0, view={"width": 320, "height": 180})
    first = rec.frames[0]
    assert first.frame.frame_seq == 1 and first.frame.pose_seq == first.first_seq
    assert first.frame.pose_seq < rec.frames[1].first_seq and not rec.deforms
    seqs = [f.frame.frame_seq for f in rec.frames]      # the moves drew frames between
    assert seqs == sorted(set(seqs))


def test_a_step_without_its_frame_fails_with_the_reason():
    fake = FakeServer(sessions=(), pose_model=flat_skin(SKIN_Y_MM), stages=("chainmail", "frames"),
                      script=fake_renderer(0.05, 0.05, frames=False))
    with fake, Client(fake.address) as c:
        t0 = time.monotonic()
        with pytest.raises(RecordError) as e:
            record_press(c, (0.0, SKIN_Y_MM + 10.0, 0.0), (0, -1, 0), [-5.0, 5.0],
                         step_timeout_s=0.5, view={"width": 320, "height": 180})
        assert time.monotonic() - t0 < 10
    assert "step 1 (depth -5 mm" in str(e.value) and "within 0.5 s" in str(e.value)
    # and where the step stopped, as the server counts it (the fake's deformation never steps)
    assert "The session now: deformation: 0 steps" in str(e.value) and "frames: 0 rendered" in str(e.value)
    # frames wanted and none drawn: the hint at a render thread left no CPU time
    assert "wanted but none was drawn" in str(e.value) and "--background nice" in str(e.value)
    assert fake.closed == fake.opened                       # the session was still closed


def test_no_skin_and_refused_watch():
    with FakeServer(sessions=(), pose_model=None) as fake, Client(fake.address) as c:
        with pytest.raises(RecordError, match="no skin within 3 mm"):
            record_press(c, (0.0, 0.0, 0.0), (0, -1, 0), [1.0], max_travel_mm=3.0)
    with FakeServer(sessions=(), frames=False, pose_model=flat_skin(SKIN_Y_MM)) as fake, \
            Client(fake.address) as c:
        with pytest.raises(ServerError) as e:
            record_press(c, (0.0, SKIN_Y_MM + 2.0, 0.0), (0, -1, 0), [1.0])
    assert e.value.code_name == "ERROR_NOT_BUILT"


def test_demo_press_site():
    from palpsim.demo import PHANTOM_L3_Z_MM, press_site

    plan = SimpleNamespace(grid=SimpleNamespace(center_mm=(1.5, 110.0, 0.0)))
    args = SimpleNamespace(record_z_mm=None)
    report = {"peaks": [{"z_mm": 30.0, "prominence_n": 0.5}, {"z_mm": -12.0, "prominence_n": 1.2}]}
    phantom = SimpleNamespace(patient=SimpleNamespace(source="phantom"))
    ct = SimpleNamespace(patient=SimpleNamespace(source="/data/ct.nii.gz"))
    assert press_site(phantom, plan, report, args)[:2] == (1.5, PHANTOM_L3_Z_MM)
    assert press_site(ct, plan, report, args)[:2] == (1.5, -12.0)    # the most prominent peak
    assert press_site(ct, plan, {"peaks": []}, args)[:2] == (1.5, 0.0)
    assert press_site(ct, plan, report, SimpleNamespace(record_z_mm=7.0))[:2] == (1.5, 7.0)


# ---------------------------------------------------------------------------------------
# End to end: the real palpsim-server

E2E_SCENE = """
name: "phantom 2 mm, frames and bricks (palpsim.record end-to-end test)"
phantom { voxel_mm: 2.0 }
effects { haptics: true chainmail: true relaxation: true inversion: true frames: true bricks: true }
render { width: 320 height: 180 }
deform { backend: "cpu" }
"""


@pytest.fixture(scope="module")
def record_server(tmp_path_factory):
    yield from start_stream_server(tmp_path_factory.mktemp("record-e2e"), E2E_SCENE)


def test_end_to_end_recorded_press(record_server, tmp_path: Path):
    """A 3-step press over L3 of the 2 mm phantom (x = 0, z = -5 mm; its back is near
    y = 110 mm, the process tip about 24 mm under the skin), 320x180 frames."""
    depths = press_depths(15.0, 3)
    with Client(record_server.address) as c:
        info = c.info()
        top = (0.5 * (info.patient.body_min_mm.x + info.patient.body_max_mm.x),
               info.patient.body_max_mm.y + 10.0, -5.0)
        rec = record_press(c, top, (0, -1, 0), depths)
    assert [f.depth_mm for f in rec.frames] == depths
    assert 105.0 < rec.skin_mm[1] < 112.0                # the phantom's back at x = 0
    for f in rec.frames:
        assert f.rgb.shape == (180, 320, 3) and f.rgb.std() > 5.0   # a picture, not blank
        assert f.frame.pose_seq >= f.first_seq
        if f.depth_mm > 0:
            assert f.reply.contact and f.frame.deformed
            assert f.frame.deform_pose_seq >= f.first_seq
            # the server's depth: the asked one to within a voxel (2 mm) of the skin found
            assert f.reply.depth_mm == pytest.approx(f.depth_mm, abs=2.0)
        else:
            assert not f.reply.contact and not f.frame.deformed and f.force_n == 0.0
    down = [f.force_n for f in rec.frames[1:4]]
    assert down[0] > 0 and down[0] < down[1] < down[2], down   # pressing harder, deeper
    assert rec.max_pose_gap_s < 0.5
    paths = write_recording(rec, tmp_path, title="e2e press", fps=10.0, seconds_per_step=0.5)
    frames, meta = read_mp4(paths["mp4"])
    assert len(frames) == 5 * len(depths) and float(meta["fps"]) == pytest.approx(10.0)
    assert frames[0].shape[1] == 320
    sheet = read_png(paths["sheet"])
    lay = sheet_layout(6, 320, 180)
    assert sheet.shape == (lay.height, lay.width, 3)
    assert sheet.std() > 10
    import json
    table = json.loads(paths["json"].read_text())
    assert [s["depth_mm"] for s in table["steps"]] == depths
