"""palpsim-view and the stream library against a fake server (stream_fakes.py): a ROUTER
that answers ControlRequest.info and .watch as palpsim-server does (PROTOCOL.md, "Frames
and bricks": session 0 = newest, the error codes, the view ranges of
server/render/view.h) and an XPUB that publishes two-frame [topic, StreamMessage]
messages when it sees a subscription, with the server's small send high-water mark. The
end-to-end tests against the real build/palpsim-server are in test_view_server.py.

Frames carry their frame_seq as 16 bars (stream_fakes.seq_image), so a test can read
from a PNG or an MP4 which frame it shows.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from typing import Any, Iterator

import numpy as np
import pytest
import zmq
from stream_fakes import (SID, OTHER_SID, FakeServer, GridSpec, Script, brick_parts,
                          frame_parts, jpeg, key_bricks, make_brick, notice_parts, read_mp4,
                          read_png, read_seq, seq_image, skip, start_xvfb, stream_message,
                          summary_numbers)

from palpsim import view as view_mod
from palpsim import view_window
from palpsim.client import Client
from palpsim.proto import wire
from palpsim.stream import DeformedVolume, StreamClient, brick_topic

# ---------------------------------------------------------------------------------------
# Scripts


def frames_forever(fps: float = 50.0, last_seq: int | None = None) -> Script:
    """Frames 1, 2, ... at `fps` in the session's view size (the server's renderer)."""
    def script(fake: FakeServer, topic: bytes) -> Iterator[Any]:
        if not topic.startswith(b"frame."):
            return
        sid = int(topic[6:], 16)
        seq = 0
        while last_seq is None or seq < last_seq:
            seq += 1
            v = fake.views[sid]
            yield frame_parts(sid, seq, v.width, v.height)
            yield 1.0 / fps
    return script


def run_view(argv: list[str], capsys) -> tuple[int, str, str]:
    """palpsim-view in this process; (exit status, stdout, stderr)."""
    try:
        rc = view_mod.main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


# ---------------------------------------------------------------------------------------
# Frames: PNG, MP4, newest wins


def test_png_frames_and_view_fields(tmp_path, capsys):
    with FakeServer(script=frames_forever(fps=50)) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--any", "--frames", "3",
                                 "--out", str(tmp_path), "--size", "320x180", "--preset", "skin",
                                 "--azimuth", "30", "--center", "1,2,-3.5", "--no-tip-marker",
                                 "--timeout", "10"], capsys)
    assert rc == 0, err
    pngs = sorted(tmp_path.glob("frame_*.png"))
    assert [p.name for p in pngs] == ["frame_000001.png", "frame_000002.png", "frame_000003.png"]
    seqs = []
    for p in pngs:
        rgb = read_png(p)
        assert rgb.shape == (180, 320, 3)           # the size the view asked for
        seqs.append(read_seq(rgb))
    assert seqs == sorted(seqs) and len(set(seqs)) == 3 and seqs[0] >= 1
    n = summary_numbers(out)
    assert n["shown"] == 3 and n["received"] >= 3
    assert n["p50"] == pytest.approx(5.0) and n["p99"] == pytest.approx(5.0)  # the fake's 5 ms
    # what was sent: session 0 (any), frames only, exactly the fields the options set
    (w,) = fake.watches
    assert w.session_id == 0 and w.frames and not w.bricks
    v = w.view
    assert (v.width, v.height, v.preset, v.azimuth_deg) == (320, 180, "skin", 30.0)
    assert v.HasField("look_at_tip") and not v.look_at_tip and not v.show_tip
    assert (v.center_mm.x, v.center_mm.y, v.center_mm.z) == (1.0, 2.0, -3.5)
    for unset in ("elevation_deg", "zoom", "jpeg_quality", "show_proxy", "slice_fov_mm"):
        assert not v.HasField(unset), unset        # left as the session has them
    assert f"{SID:016x}" in err


def test_mp4_readable_with_frame_count_size_and_fps(tmp_path, capsys):
    mp4 = tmp_path / "v.mp4"
    # an odd size: the video is padded to even edges (yuv420p); the fake's server clock
    # puts frames 0.05 s apart, so the measured rate is 20 fps exactly
    with FakeServer(script=frames_forever(fps=25)) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--frames", "12", "--size", "321x181",
                                 "--mp4", str(mp4), "--out", str(tmp_path / "png"),
                                 "--timeout", "10"], capsys)
    assert rc == 0, err
    n = summary_numbers(out)
    assert n["shown"] == 12
    frames, meta = read_mp4(mp4)
    assert len(frames) == 12
    assert frames[0].shape == (182, 322, 3)
    assert float(meta["fps"]) == pytest.approx(20.0, abs=1e-3)
    assert "12 MP4 frames at 20 fps" in out
    # the same frames as the PNGs, in order: the bars read the same seq (h264 is lossy, the
    # bars' threshold has ~100 levels of margin), and the pixels differ by a few levels
    pngs = sorted((tmp_path / "png").glob("frame_*.png"))
    assert len(pngs) == 12
    for f, p in zip(frames, pngs):
        ref = read_png(p)
        assert read_seq(f[:181, :321]) == read_seq(ref)
        assert np.abs(f[:181, :321].astype(int) - ref).mean() < 6.0


def test_newest_wins_under_a_burst(tmp_path, capsys):
    """The fake publishes 300 frames as fast as it can (a viewer writes ~100 PNG a second),
    then, 1 s later, frame 301, then the closed notice: the viewer shows far fewer frames
    than were sent, each newer than the last, the last one is 301, and every frame is
    accounted for as shown, skipped (drained but replaced) or missed (a seq gap)."""
    w, h, burst = 640, 360, 300
    jpegs = {s: jpeg(seq_image(s, w, h)) for s in range(1, burst + 2)}

    def script(fake: FakeServer, topic: bytes) -> Iterator[Any]:
        for s in range(1, burst + 1):
            yield frame_parts(SID, s, w, h, data=jpegs[s])
        yield 1.0
        yield frame_parts(SID, burst + 1, w, h, data=jpegs[burst + 1])
        yield 1.0
        yield notice_parts(topic, SID, "closed", f"session {SID:016x} closed by its client")

    with FakeServer(script=script) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--out", str(tmp_path),
                                 "--timeout", "10"], capsys)
    published = fake.published  # read once the fake's thread has ended
    assert rc == 0, err
    assert published == burst + 2
    assert "closed by its client" in err
    pngs = sorted(tmp_path.glob("frame_*.png"))
    seqs = [read_seq(read_png(p)) for p in pngs]
    assert seqs == sorted(set(seqs)), seqs            # strictly newer each time
    assert seqs[-1] == burst + 1                        # the newest frame is shown
    n = summary_numbers(out)
    assert n["shown"] == len(pngs)
    assert len(pngs) <= (burst + 1) / 2                 # newest wins: most frames never shown
    assert n["received"] == n["shown"] + n["skipped"]
    # frame 1 meets an empty queue, so it arrives; every later one arrived or is a gap
    assert n["received"] + n["missed"] == burst + 1
    # the viewer drains: while it writes a PNG, the burst queues up at its socket, so a
    # drain finds several frames and decodes only the newest
    assert n["skipped"] > 0


def test_stream_timeout_exits_1(capsys):
    with FakeServer(script=None) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--out", "/tmp/unused-palpsim-view",
                                 "--timeout", "0.5"], capsys)
    assert rc == 1
    assert "no stream message within 0.5 s" in err
    assert "0 frames received" in out


# ---------------------------------------------------------------------------------------
# Notices and refusals


def test_closed_notice_exits_0_with_message(tmp_path, capsys):
    def script(fake, topic):
        yield frame_parts(SID, 1, 320, 180)
        yield frame_parts(SID, 2, 320, 180)
        yield 0.3
        yield notice_parts(topic, SID, "closed", "session timed out after 5 s without a message")

    with FakeServer(script=script) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--out", str(tmp_path)], capsys)
    assert rc == 0, err
    assert "session ended: session timed out after 5 s without a message" in err
    assert summary_numbers(out)["received"] == 2
    assert len(list(tmp_path.glob("frame_*.png"))) >= 1


def test_unknown_session_notice_exits_2(tmp_path, capsys):
    def script(fake, topic):
        yield notice_parts(topic, SID, "unknown_session", f"topic {topic.decode()} names no open "
                           "session", code=wire.ERROR_UNKNOWN_SESSION)

    with FakeServer(script=script) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--out", str(tmp_path),
                                 "--timeout", "10"], capsys)
    assert rc == 2
    assert f"ERROR_UNKNOWN_SESSION: topic frame.{SID:016x} names no open session" in err


def test_unknown_session_reply_exits_2(tmp_path, capsys):
    with FakeServer(script=frames_forever()) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--session", f"{OTHER_SID:016x}",
                                 "--out", str(tmp_path)], capsys)
    assert rc == 2
    assert f"ERROR_UNKNOWN_SESSION: WatchSession.session_id: no open session {OTHER_SID:016x}" in err
    assert fake.watches[0].session_id == OTHER_SID     # the 16-hex-digit form was parsed as hex


@pytest.mark.parametrize("size,message", [
    ("0x0", "WatchSession.view.width = 0 is outside 64..3840 pixels"),
    ("100000x100000", "WatchSession.view.width = 100000 is outside 64..3840 pixels"),
    ("640x4000", "WatchSession.view.height = 4000 is outside 64..2160 pixels"),
])
def test_bad_view_size_is_the_servers_refusal(size, message, tmp_path, capsys):
    with FakeServer(script=frames_forever()) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--size", size, "--out", str(tmp_path)],
                                capsys)
    assert rc == 2
    assert f"ERROR_BAD_VIEW: {message}" in err
    assert len(fake.watches) == 1 and not fake.subscriptions   # refused before any subscription


def test_other_refusals_exit_2(tmp_path, capsys):
    with FakeServer(sessions=(), script=None) as fake:
        rc, _, err = run_view(["--connect", fake.address, "--out", str(tmp_path)], capsys)
    assert rc == 2 and "ERROR_NO_SESSION_OPEN" in err
    with FakeServer(frames=True, bricks=False, script=None) as fake:
        rc, _, err = run_view(["--connect", fake.address, "--bricks", "--out", str(tmp_path)], capsys)
    assert rc == 2 and "ERROR_NOT_BUILT: WatchSession.bricks" in err


@pytest.mark.parametrize("argv,words", [
    (["--size", "abc"], ["--size", "WIDTHxHEIGHT"]),
    (["--size=-5x10"], ["--size", "WIDTHxHEIGHT"]),
    (["--center=-1,2"], ["--center", "X,Y,Z"]),
    (["--center", "1,2"], ["--center", "X,Y,Z"]),
    (["--session", "nope"], ["--session", "not a session id"]),
    (["--frames", "0"], ["--frames", "1 or more"]),
    (["--encoding", "int8"], ["--encoding", "int16"]),
    (["--session", "5", "--any"], ["not allowed with"]),
])
def test_command_line_errors_exit_2(argv, words, capsys):
    rc, _, err = run_view(["--connect", "tcp://127.0.0.1:1", *argv], capsys)
    assert rc == 2
    for w in words:
        assert w in err, err


def test_no_server_answer_exits_1(tmp_path, capsys):
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.ROUTER)    # bound, never answers
    s.setsockopt(zmq.LINGER, 0)
    port = s.bind_to_random_port("tcp://127.0.0.1")
    try:
        rc, _, err = run_view(["--connect", f"tcp://127.0.0.1:{port}", "--timeout", "0.3",
                               "--out", str(tmp_path)], capsys)
    finally:
        s.close(0)
    assert rc == 1 and "no reply to watch" in err


def test_malformed_stream_message_exits_1(tmp_path, capsys):
    def script(fake, topic):
        yield [topic, stream_message(), b"extra"]

    with FakeServer(script=script) as fake:
        rc, _, err = run_view(["--connect", fake.address, "--out", str(tmp_path),
                               "--timeout", "10"], capsys)
    assert rc == 1
    assert "3 ZeroMQ frames, expected 2" in err


def test_frame_size_mismatch_names_the_field(tmp_path, capsys):
    def script(fake, topic):
        f = frame_parts(SID, 1, 320, 180, data=jpeg(seq_image(1, 160, 90)))
        yield f

    with FakeServer(script=script) as fake:
        rc, _, err = run_view(["--connect", fake.address, "--out", str(tmp_path),
                               "--timeout", "10"], capsys)
    assert rc == 1 and "Frame.width x height = 320x180" in err and "160x90" in err


# ---------------------------------------------------------------------------------------
# Bricks


def brick_volume(grid: GridSpec, encoding: int, rng: np.random.Generator) -> np.ndarray:
    """An image I: whole HU for int16, fractional values for float32."""
    shape = grid.size[::-1]
    if encoding == wire.BRICK_INT16:
        return rng.integers(-1024, 3000, size=shape).astype(np.int16)
    return (rng.standard_normal(shape) * 300.0).astype(np.float32)


ENC = {"int16": wire.BRICK_INT16, "float32": wire.BRICK_FLOAT32}
COMP = {"none": wire.COMPRESSION_NONE, "zstd": wire.COMPRESSION_ZSTD}


@pytest.mark.parametrize("encoding", ["int16", "float32"])
@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_brick_reconstruction_is_exact_over_the_stream(encoding, compression):
    """Key in 4 slabs, a deformed VOI brick, then an undeformed one, through the fake's
    XPUB in the encoding the watch asked for: J equals I with the VOI box written over it,
    then I, exactly (int16 and float32 values are exact in the viewer's float32 volume,
    and nothing is computed on them)."""
    rng = np.random.default_rng(7)
    grid = GridSpec(direction=(0, 1, 0, -1, 0, 0, 0, 0, 1))  # a rotated grid
    enc = ENC[encoding]
    image = brick_volume(grid, enc, rng)
    lo, box = (3, 4, 5), (6, 7, 8)                              # (i, j, k)
    voi = brick_volume(GridSpec(size=box), enc, rng)

    def script(fake, topic):
        e, c = fake.encoding[SID]
        assert (e, c) == (enc, COMP[compression])
        for b in key_bricks(SID, grid, image, 4, encoding=e, compression=c):
            yield brick_parts(b)
        yield brick_parts(make_brick(SID, 5, grid, voi, lo, encoding=e, compression=c,
                                     pose_seq=42, deform_step=1))
        yield 0.3
        yield brick_parts(make_brick(SID, 6, grid, np.zeros((0, 0, 0)), (0, 0, 0), encoding=e,
                                     compression=c, deformed=False, deform_step=2))

    with FakeServer(script=script) as fake, Client(fake.address) as c:
        reply = c.watch(frames=False, bricks=True, brick_encoding=encoding, compression=compression)
        assert reply.brick_topic == brick_topic(SID) and reply.frame_topic == b""
        vol = DeformedVolume()
        deformed_seen = False
        with StreamClient.from_watch(reply, fake.address) as sc:
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                u = sc.receive(0.5)
                for b in (u.bricks if u else []):
                    vol.apply(b)
                    if not b.key and b.deformed:
                        assert vol.complete and vol.key_parts == 4
                        want = image.astype(np.float32)
                        want[5:13, 4:11, 3:9] = voi
                        assert vol.volume.dtype == np.float32
                        assert np.array_equal(vol.volume, want)
                        np.testing.assert_allclose(vol.voi_center_mm(),
                                                   grid.box_origin((5.5, 7.0, 8.5)), atol=1e-9)
                        deformed_seen = True
                    elif not b.key:
                        assert deformed_seen
                        assert np.array_equal(vol.volume, image.astype(np.float32))
                        assert not vol.deformed
                        return
    pytest.fail("the undeformed brick never came")


def test_bricks_cli_writes_slices(tmp_path, capsys):
    rng = np.random.default_rng(3)
    grid = GridSpec()
    image = np.full(grid.size[::-1], -100, dtype=np.float32)
    voi = (rng.random((8, 8, 8)) * 50 + 900).astype(np.float32)   # bright: bone in the VOI

    def script(fake, topic):
        e, c = fake.encoding[SID]
        for b in key_bricks(SID, grid, image, 3, encoding=e, compression=c):
            yield brick_parts(b)
        yield brick_parts(make_brick(SID, 4, grid, voi, (6, 5, 7), encoding=e, compression=c))
        yield 0.2
        yield brick_parts(make_brick(SID, 5, grid, np.zeros((0, 0, 0)), encoding=e, compression=c,
                                     deformed=False))
        yield 0.2
        yield brick_parts(make_brick(SID, 6, grid, voi, (6, 5, 7), encoding=e, compression=c))

    with FakeServer(script=script) as fake:
        rc, out, err = run_view(["--connect", fake.address, "--bricks", "--frames", "2",
                                 "--encoding", "float32", "--zstd", "--out", str(tmp_path),
                                 "--timeout", "10"], capsys)
    assert rc == 0, err
    (w,) = fake.watches
    assert w.bricks and not w.frames
    assert (w.brick_encoding, w.brick_compression) == (wire.BRICK_FLOAT32, wire.COMPRESSION_ZSTD)
    assert not w.HasField("view")                       # bricks only: the frames' view untouched
    pngs = sorted(tmp_path.glob("bricks_*.png"))
    assert [p.name for p in pngs] == ["bricks_000001.png", "bricks_000002.png"]
    a, b = read_png(pngs[0]).astype(int), read_png(pngs[1]).astype(int)
    assert a.shape == b.shape
    # the deformed slices show the bright VOI (bone window: 900 HU -> ~178 grey), the
    # undeformed ones only -100 HU (0 in the bone window) at the same place
    assert (np.abs(a - b) > 100).sum() > 1000
    assert "2 bricks received" in out and "key 20x17x23 voxels in 3 parts" in out


# ---------------------------------------------------------------------------------------
# The live window's keys (no display needed: the controller and the view it sends)


def test_keys_send_views():
    with FakeServer(script=None) as fake, Client(fake.address) as c:
        reply = c.watch(frames=True)
        args = view_mod.build_parser().parse_args(["--connect", fake.address])
        viewer = view_mod.Viewer(args, c, reply)
        try:
            for key in ("right", "up", "up", "up", "up", "up", "up", "up", "+", "p", "x", "q"):
                viewer._on_key(key)
        finally:
            viewer.close()
        sent = fake.watches[1:]
        assert [w.session_id for w in sent] == [SID] * len(sent)
        assert sent[0].view.azimuth_deg == 45.0 and not sent[0].view.HasField("zoom")
        # elevation 25 + 7 x 10 would be 95: held at 89, inside the server's range
        assert [w.view.elevation_deg for w in sent[1:8]] == [35, 45, 55, 65, 75, 85, 89]
        assert sent[8].view.zoom == pytest.approx(1.25)
        assert sent[9].view.preset == "soft_tissue"      # bone -> soft_tissue
        assert len(sent) == 10 and viewer.controller.quit  # "x" sends nothing, q quits
        assert fake.views[SID].elevation_deg == 89


def test_live_window_shows_frames_and_sends_keys(capsys, xvfb, monkeypatch):
    """On the module's Xvfb: the window opens (no --out/--mp4), key events on its canvas
    reach the server as WatchSession views, and --frames ends it."""
    import matplotlib
    import matplotlib.pyplot as plt

    monkeypatch.setenv("DISPLAY", xvfb)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("MPLBACKEND", raising=False)
    backend = matplotlib.get_backend()   # palpsim.plots picks Agg for the other tests
    problem = view_mod.gui_problem()
    if problem is not None:
        skip(f"no live window here: {problem}")
    try:
        _live_window(capsys)
    finally:
        plt.close("all")
        plt.switch_backend(backend)
        view_window.collect_gui_garbage()   # Tk's objects die here, not in a later fake's thread


def _live_window(capsys):
    from matplotlib.backend_bases import KeyEvent

    sent_keys = []
    original = view_mod.Viewer.open_outputs

    def open_outputs(self, live):
        original(self, live)
        assert live and self.window is not None
        canvas = self.window.fig.canvas
        for key in ("left", "p"):
            canvas.callbacks.process("key_press_event", KeyEvent("key_press_event", canvas, key))
            sent_keys.append(key)

    with FakeServer(script=frames_forever(fps=30)) as fake:
        view_mod.Viewer.open_outputs = open_outputs
        try:
            rc, out, err = run_view(["--connect", fake.address, "--frames", "5", "--size", "320x180",
                                     "--timeout", "10"], capsys)
        finally:
            view_mod.Viewer.open_outputs = original
    assert rc == 0, err
    assert summary_numbers(out)["shown"] == 5
    assert sent_keys == ["left", "p"]
    views = [w.view for w in fake.watches[1:]]
    assert [v.azimuth_deg for v in views[:1]] == [25.0] and views[1].preset == "soft_tissue"


@pytest.fixture(scope="module")
def xvfb():
    """An X display of this module's own (":N"), or a skip with the reason."""
    yield from start_xvfb()


def _view_without_window(tmp_path, env: dict[str, str], block: tuple[str, ...] = ()) -> str:
    """palpsim-view in a process of its own with `env` over this one's (and the modules in
    `block` made unimportable, as in a Python without them), on a fake server, without
    --out or --mp4 until one frame is written; returns its stderr."""
    with FakeServer(script=frames_forever(fps=30)) as fake:
        code = ("import sys\n"
                f"for m in {block!r}: sys.modules[m] = None\n"
                "from palpsim import view\n"
                f"sys.exit(view.main(['--connect', {fake.address!r}, '--frames', '1', "
                "'--size', '320x180', '--timeout', '10']))")
        full_env = {k: v for k, v in os.environ.items()
                    if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")}
        full_env.update(env)
        proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=full_env,
                              capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert len(list((tmp_path / "out" / "view").glob("frame_*.png"))) == 1, proc.stderr
    return proc.stderr


def test_without_a_display_the_viewer_says_so(tmp_path):
    err = _view_without_window(tmp_path, {})
    assert ("no live window: no display ($DISPLAY and $WAYLAND_DISPLAY are unset); writing "
            "PNG files into out/view") in err


def test_a_display_without_a_toolkit_names_the_toolkit(tmp_path, xvfb):
    """A display is there but this Python has no GUI toolkit for matplotlib (a Debian
    python3 without python3-tk): the message names tkinter and how to install it."""
    toolkits = ("_tkinter", "PyQt6", "PySide6", "PyQt5", "PySide2", "gi", "wx")
    err = _view_without_window(tmp_path, {"DISPLAY": xvfb}, block=toolkits)
    assert "no display" not in err
    assert f"no live window: $DISPLAY={xvfb} is there, but matplotlib has no GUI toolkit" in err
    assert "has no tkinter" in err and "PyQt6" in err
    if os.path.realpath(sys.base_prefix) == "/usr" and os.path.isfile("/etc/debian_version"):
        assert "apt-get install python3-tk" in err


def test_closed_windows_leave_no_toolkit_objects_to_other_threads(tmp_path, xvfb):
    """gui_problem()'s probe figure and a closed LiveWindow free their Tk objects in the
    thread that made them. Left to the cycle collector they die in whatever thread runs it
    next: there each Tcl call waits about 1 s for a main loop and fails (a fake server's
    thread stalled past a client's 10 s timeout so), or Tcl aborts the process. In a
    process of its own (an abort must not take pytest down), the collector then runs in
    a second thread; it must find nothing of Tk's and take well under those seconds."""
    code = (
        "import gc, sys, threading, time\n"
        "import numpy as np\n"
        "from palpsim.view_window import LiveWindow, collect_gui_garbage, gui_problem\n"
        "gc.disable()\n"
        "problems = []\n"
        "sys.unraisablehook = lambda u: problems.append(repr(u.exc_value))\n"
        "problem = gui_problem()\n"
        "if problem is not None: print('SKIP', problem); sys.exit(0)\n"
        "w = LiveWindow('t', lambda key: None)\n"
        "w.show(np.zeros((8, 8, 3), np.uint8), 'x')\n"
        "w.pump()\n"
        "import matplotlib.pyplot as plt\n"
        "other = plt.figure().number\n"
        "w.close(); w.close()\n"  # the second closes nothing, not the current figure
        "assert plt.fignum_exists(other), 'a second close() closed another figure'\n"
        "plt.close(other)\n"
        "collect_gui_garbage()\n"
        "t0 = time.monotonic()\n"
        "th = threading.Thread(target=gc.collect)\n"
        "th.start(); th.join()\n"
        "print(f'{time.monotonic() - t0:.3f}', len(problems), problems[:2])\n")
    env = {k: v for k, v in os.environ.items() if k not in ("WAYLAND_DISPLAY", "MPLBACKEND")}
    env["DISPLAY"] = xvfb
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    if proc.stdout.startswith("SKIP"):
        skip(f"no live window here: {proc.stdout[5:].strip()}")
    seconds, count, _ = proc.stdout.split(" ", 2)
    assert int(count) == 0, proc.stdout
    # one stalled Tcl call costs ~1 s; a collection of plain objects takes milliseconds
    assert float(seconds) < 0.5, proc.stdout


def test_a_display_that_cannot_be_reached_is_named(tmp_path):
    """$DISPLAY names a display with no X server behind it (:65000, far above the numbers
    X servers take): the message says the window cannot open there."""
    err = _view_without_window(tmp_path, {"DISPLAY": ":65000"})
    assert "no live window: cannot open a window on $DISPLAY=:65000" in err


# ---------------------------------------------------------------------------------------
# Ctrl-C


def test_ctrl_c_exits_cleanly_with_summary_and_a_finished_mp4(tmp_path):
    with FakeServer(script=frames_forever(fps=30)) as fake:
        out_dir, mp4 = tmp_path / "png", tmp_path / "v.mp4"
        cmd = [sys.executable, "-m", "palpsim.view", "--connect", fake.address, "--size", "320x180",
               "--out", str(out_dir), "--mp4", str(mp4)]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while len(list(out_dir.glob("frame_*.png"))) < 5:
                assert proc.poll() is None, proc.communicate()
                assert time.monotonic() < deadline, "no frames written within 30 s"
                time.sleep(0.05)
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "interrupted" in err
    n = summary_numbers(out)
    pngs = len(list(out_dir.glob("frame_*.png")))
    assert n["shown"] == pngs >= 5
    assert len(read_mp4(mp4)[0]) == pngs
