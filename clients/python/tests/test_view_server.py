"""palpsim-view end to end against the real build/palpsim-server (skipped where it does
not serve a stream): frames, bricks and the rebuilt volume, and the live window on Xvfb
turning the frame with the arrow keys.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
from stream_fakes import read_png, skip, start_stream_server, start_xvfb, summary_numbers

from palpsim.client import Client
from palpsim.stream import DeformedVolume, StreamClient



@pytest.fixture(scope="module")
def xvfb():
    """An X display of this module's own (":N"), or a skip with the reason."""
    yield from start_xvfb()


# ---------------------------------------------------------------------------------------
# End to end: the real palpsim-server (skipped until it serves frames and bricks)

E2E_SCENE = """
name: "phantom 2 mm, frames and bricks (palpsim-view end-to-end test)"
phantom { voxel_mm: 2.0 }
effects { haptics: true chainmail: true relaxation: true inversion: true frames: true bricks: true }
render { width: 320 height: 180 }
deform { backend: "cpu" }
"""

# bricks need no OpenGL: this scene serves them where frames cannot be rendered
E2E_BRICKS_SCENE = """
name: "phantom 2 mm, bricks only (palpsim-view end-to-end test)"
phantom { voxel_mm: 2.0 }
effects { haptics: true chainmail: true relaxation: true inversion: true bricks: true }
deform { backend: "cpu" }
"""



@pytest.fixture(scope="module")
def stream_server(tmp_path_factory):
    yield from start_stream_server(tmp_path_factory.mktemp("view-e2e"), E2E_SCENE)


@pytest.fixture(scope="module")
def bricks_server(tmp_path_factory):
    yield from start_stream_server(tmp_path_factory.mktemp("view-e2e-bricks"), E2E_BRICKS_SCENE)


def _press_while(proc: subprocess.Popen, session, seconds: float = 60.0) -> int:
    """Presses the back over L4 (x = 0, z = -38 mm, skin near y = 110 mm) in and out at
    ~200 poses a second until `proc` exits; returns the poses sent."""
    poses = 0
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < seconds:
        phase = (poses % 400) / 400.0
        depth_mm = 12.0 * (1 - abs(2 * phase - 1))       # 0 -> 12 -> 0 mm
        session.pose((0.0, 118.0 - 8.0 - depth_mm, -38.0), client_time_s=poses * 0.005)
        poses += 1
        time.sleep(0.005)
    return poses


def _view_cmd(address: str, *args: str) -> list[str]:
    return [sys.executable, "-m", "palpsim.view", "--connect", address, *args]


def test_end_to_end_frames(stream_server, tmp_path):
    out_dir = tmp_path / "frames"
    # the viewer acts as this client through its token (the session is the token's)
    with Client(stream_server.address, client_token="e2e") as c, c.open_session("view-e2e") as s:
        s.pose((0.0, 130.0, -38.0))                      # a first pose, out of contact
        proc = subprocess.Popen(_view_cmd(stream_server.address, "--session", f"{s.id:016x}",
                                          "--client-token", "e2e",
                                          "--frames", "3", "--out", str(out_dir),
                                          "--timeout", "60"),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        poses = _press_while(proc, s)
        out, err = proc.communicate(timeout=60)
        stats = s.stats()
    assert proc.returncode == 0, f"{err}\n{stream_server.tail()}"
    pngs = sorted(out_dir.glob("frame_*.png"))
    assert len(pngs) == 3, (out, err)
    for p in pngs:
        rgb = read_png(p)
        assert rgb.shape == (180, 320, 3)
        assert rgb.std() > 5.0                           # a picture, not a blank frame
    n = summary_numbers(out)
    assert n["shown"] == 3 and n["p50"] >= 0
    assert poses > 0 and stats.HasField("stream") and stats.stream.frames_published >= 3


def test_end_to_end_bricks(bricks_server, tmp_path):
    out_dir = tmp_path / "bricks"
    with Client(bricks_server.address, client_token="e2e-bricks") as c, \
            c.open_session("view-e2e-bricks") as s:
        s.pose((0.0, 130.0, -38.0))
        proc = subprocess.Popen(_view_cmd(bricks_server.address, "--session", f"{s.id:016x}",
                                          "--client-token", "e2e-bricks", "--bricks", "--zstd", "--frames", "2", "--out",
                                          str(out_dir), "--timeout", "60"),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _press_while(proc, s)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, f"{err}\n{bricks_server.tail()}"
    assert len(sorted(out_dir.glob("bricks_*.png"))) == 2
    assert "(incomplete)" not in out and re.search(r"key \d+x\d+x\d+ voxels", out), out


def test_end_to_end_bricks_rebuild_the_volume(bricks_server):
    """The library on the real stream: the key is the patient grid of the Info reply, a
    press brings a deformed VOI brick (J differs from the key inside its box only), and
    lifting the tip out brings an undeformed one (J equals the key again, exactly)."""
    addr = bricks_server.address
    with Client(addr) as c, c.open_session("view-e2e-library") as s:
        patient = c.info().patient
        s.pose((0.0, 130.0, -38.0))
        reply = c.watch(session_id=s.id, frames=False, bricks=True, brick_encoding="float32",
                        compression="zstd")
        vol, key, deformed_box, released = DeformedVolume(), None, None, False
        with StreamClient.from_watch(reply, addr) as sc:
            deadline = time.monotonic() + 60
            while not released and time.monotonic() < deadline:
                # 10 mm into the back over L4 until a deformed brick came, then out of the body
                s.pose((0.0, 100.0, -38.0) if deformed_box is None else (0.0, 130.0, -38.0))
                u = sc.receive(0.01)
                for b in (u.bricks if u else []):
                    vol.apply(b)
                    if b.key and vol.complete:
                        key = vol.volume.copy()
                    elif not b.key and key is not None and b.deformed and deformed_box is None:
                        deformed_box = (slice(b.lo_k, b.lo_k + b.size_k),
                                        slice(b.lo_j, b.lo_j + b.size_j),
                                        slice(b.lo_i, b.lo_i + b.size_i))
                        outside = vol.volume.copy()
                        outside[deformed_box] = key[deformed_box]
                        assert np.array_equal(outside, key)
                        assert np.abs(vol.volume[deformed_box] - key[deformed_box]).max() > 0
                    elif not b.key and deformed_box is not None and not b.deformed:
                        assert np.array_equal(vol.volume, key)
                        released = True
    assert key is not None, "no complete key within 60 s"
    assert deformed_box is not None, "no deformed VOI brick within 60 s of pressing"
    assert released, "no undeformed VOI brick after the tip left the body"
    assert vol.grid.size == (patient.size_i, patient.size_j, patient.size_k)
    assert vol.grid.spacing_mm == pytest.approx(patient.spacing_mm)
    np.testing.assert_allclose(vol.grid.origin_mm, (patient.origin_mm.x, patient.origin_mm.y,
                                                    patient.origin_mm.z), atol=1e-9)


# ---------------------------------------------------------------------------------------
# The live window on a real X display (Xvfb): keys typed into it turn the server's frame


def _xdotool(display: str, *args: str) -> str:
    proc = subprocess.run(["xdotool", *args], env={**os.environ, "DISPLAY": display},
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, f"xdotool {' '.join(args)}: {proc.stderr}"
    return proc.stdout


def _window_frame(display: str, window: str) -> np.ndarray:
    """A screenshot of the window's picture (the X server's pixels, through Pillow's XCB
    grab) as (h, w, 3) uint8: its title line (frame numbers, latency) and matplotlib's
    toolbar at the bottom are cut off, so only the rendered frame is compared."""
    from PIL import ImageGrab

    geo = dict(line.split("=", 1) for line in
               _xdotool(display, "getwindowgeometry", "--shell", window).split())
    x, y, w, h = (int(geo[k]) for k in ("X", "Y", "WIDTH", "HEIGHT"))
    shot = np.asarray(ImageGrab.grab(xdisplay=display).convert("RGB"))
    window_px = shot[y:y + h, x:x + w]
    return window_px[int(0.1 * h):int(0.85 * h)]


# screenshots of the same view and pose: the server renders the same JPEG, so the window
# shows the same pixels (a mean difference of 0); 1 grey level is far below any change
# of the picture. A 10 degree orbit moves the spine, ribs and pelvis across many pixels:
# 6.9 grey levels of mean difference on the 2 mm phantom at 320x180 here, so 3 tells a
# turned frame from the same one with room on both sides.
SAME_PICTURE = 1.0
TURNED = 3.0


def _diff(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference per channel, grey levels (0..255)."""
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


def _find_window(display: str, proc: subprocess.Popen, timeout_s: float = 20.0) -> str:
    """The X id of palpsim-view's window once it is shown; fails with the viewer's
    messages (why it opened none) when none appears within `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while proc.poll() is None and time.monotonic() < deadline:
        found = subprocess.run(["xdotool", "search", "--onlyvisible", "--name", "^palpsim-view "],
                               env={**os.environ, "DISPLAY": display}, capture_output=True,
                               text=True, timeout=30)
        if found.stdout.split():
            return found.stdout.split()[0]
        time.sleep(0.2)
    if proc.poll() is None:
        proc.kill()
    err = proc.communicate()[1]
    pytest.fail(f"no palpsim-view window on {display} within {timeout_s:g} s:\n{err}")


def test_live_window_on_xvfb_turns_the_frame_with_the_arrow_keys(stream_server, xvfb, tmp_path):
    """The real server renders a session watched by palpsim-view's window on Xvfb; the
    Right arrow typed into the window (xdotool) orbits the camera, and Left brings it
    back: screenshots of the window show the frame turn and return. The tip stays at one
    pose out of the body, so nothing but the view changes the picture."""
    from PIL import Image

    if shutil.which("xdotool") is None:
        skip("no xdotool on $PATH (Debian's xdotool package; scripts/setup.sh installs it)")
    env = {k: v for k, v in os.environ.items() if k not in ("WAYLAND_DISPLAY", "MPLBACKEND")}
    env["DISPLAY"] = xvfb
    with Client(stream_server.address, client_token="e2e-window") as c, \
            c.open_session("view-e2e-window") as s:
        s.pose((0.0, 130.0, -38.0))                      # above the back, out of contact
        proc = subprocess.Popen(_view_cmd(stream_server.address, "--session", f"{s.id:016x}",
                                          "--client-token", "e2e-window", "--size", "320x180",
                                          "--azimuth", "0", "--timeout", "60"),
                                env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            window = _find_window(xvfb, proc)

            def settle(name: str, until) -> np.ndarray:
                """Screenshots every 0.2 s until `until(shot)` holds for two in a row that
                are the same picture (the newest frame drawn) at the same size (the window may
                still grow to its canvas after its first draw); kept as name.png."""
                deadline = time.monotonic() + 20
                last = None
                while time.monotonic() < deadline:
                    assert proc.poll() is None, proc.communicate()
                    s.pose((0.0, 130.0, -38.0))
                    shot = _window_frame(xvfb, window)
                    if (last is not None and last.shape == shot.shape and until(shot)
                            and _diff(shot, last) < SAME_PICTURE):
                        Image.fromarray(shot).save(tmp_path / f"{name}.png")
                        return shot
                    last = shot
                    time.sleep(0.2)
                pytest.fail(f"the window did not show {name} within 20 s")

            # a picture first (the blank canvas is one colour, std 0; the phantom's frame
            # measured std 40 here), then one turned by Right, then Left's
            first = settle("first", lambda shot: shot.std() > 20.0)
            # keys as a person types them (XTEST) into the focused window
            _xdotool(xvfb, "windowfocus", "--sync", window)
            _xdotool(xvfb, "key", "Right")
            turned = settle("right", lambda shot: _diff(shot, first) > TURNED)
            _xdotool(xvfb, "key", "Left")
            back = settle("left", lambda shot: _diff(shot, first) < SAME_PICTURE)
            _xdotool(xvfb, "key", "q")
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, f"{err}\n{stream_server.tail()}"
    assert "no live window" not in err
    assert _diff(turned, first) > TURNED and _diff(back, first) < SAME_PICTURE
    assert summary_numbers(out)["shown"] >= 3
