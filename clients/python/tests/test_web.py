"""palpsim-web (palpsim/web.py): its refusals without a server, then against the real
build/palpsim-server (skipped where there is none or it cannot render): the page's bad
messages over a WebSocket, no secret in what the page gets, a disconnected browser's
session ending after the idle time, and a real browser (Debian's chromium driven by
selenium; skipped with the reason where either is missing) that sees frames, clicks the
patient's back and gets contact and a force above 0.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
from stream_fakes import skip, start_stream_server

from palpsim import web
from palpsim.client import Client

SCREENSHOTS = Path(os.environ.get("PALPSIM_WEB_SHOTS", "/tmp/palpsim-web-shots"))
TOKEN = "station-client-token-not-for-pages"

# frames of 480 x 270: the 3D view is the left 480 - 270/3 = 390 pixels
WEB_SCENE = """name: "web test"
phantom { voxel_mm: 2.0 }
effects { haptics: true frames: true }
render { width: 480 height: 270 max_fps: 20 jpeg_encoder: "cpu" }
server { session_timeout_s: 30 }
"""
FRAME_W, FRAME_H, VIEW_W = 480, 270, 390


# ---------------------------------------------------------------------------------------
# Without a server


@pytest.mark.parametrize("argv, words", [
    (["--host", "0.0.0.0"], ["--host 0.0.0.0", "--tls-cert", "--tls-key", "--station-token-file"]),
    (["--host", "192.168.1.5", "--tls-cert", "c.pem", "--tls-key", "k.pem"], ["--station-token-file"]),
    (["--tls-cert", "c.pem"], ["--tls-cert and --tls-key go together"]),
])
def test_beyond_loopback_needs_tls_and_a_token(argv, words, capsys):
    status = web.main(["--connect", "tcp://127.0.0.1:1"] + argv)
    err = capsys.readouterr().err
    assert status == web.EXIT_USAGE
    for w in words:
        assert w in err


def test_a_short_station_token_is_refused(tmp_path, capsys):
    f = tmp_path / "token"
    f.write_text("short\n")
    status = web.main(["--connect", "tcp://127.0.0.1:1", "--station-token-file", str(f)])
    assert status == web.EXIT_USAGE
    assert "at least 16" in capsys.readouterr().err


def test_loopback_names():
    assert web.is_loopback("127.0.0.1") and web.is_loopback("::1") and web.is_loopback("localhost")
    assert not web.is_loopback("0.0.0.0") and not web.is_loopback("10.0.0.1")


def test_tip_path_is_smooth_and_reaches_its_goal():
    """Stepped at 1 kHz toward a goal 20 mm away, the tip never moves more than the top
    speed allows in a step, and arrives (to 0.01 mm) within 1 s."""
    p = web.TipPath([0.0, 0.0, 0.0])
    p.goal = np.array([0.0, 20.0, 0.0])
    prev = p.tip.copy()
    for _ in range(1000):
        tip = p.step(0.001)
        # 1e-12 mm: rounding of the step's sum
        assert np.linalg.norm(tip - prev) <= web.MAX_SPEED_MM_S * 0.001 + 1e-12
        prev = tip.copy()
    assert np.linalg.norm(p.tip - p.goal) < 0.01


@pytest.mark.parametrize("msg, words", [
    ({"type": "view", "view": {"width": 10}}, ["unknown field(s) width"]),
    ({"type": "view", "view": {"preset": "x"}}, ["view.preset = 'x'", "skin, bone, soft_tissue"]),
    ({"type": "view", "view": {"zoom": "big"}}, ["view.zoom = 'big'", "finite number"]),
    ({"type": "view", "view": {"center_mm": [1, 2]}}, ["view.center_mm", "three finite numbers"]),
    ({"type": "view", "view": {"look_at_tip": 1}}, ["view.look_at_tip = 1", "true or false"]),
    ({"type": "view"}, ["view.view: expected an object"]),
])
def test_page_view_refusals_name_the_field(msg, words):
    with pytest.raises(web.PageError) as e:
        web.page_view(msg)
    for w in words:
        assert w in str(e.value)


# ---------------------------------------------------------------------------------------
# Against the real server


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator:
    yield from start_stream_server(tmp_path_factory.mktemp("web"), WEB_SCENE)


class Gateway:
    """palpsim-web as a child process on a free loopback port."""

    def __init__(self, address: str, *extra: str):
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "palpsim.web", "--connect", address, "--port", "0", "--client-token", TOKEN,
             "--size", f"{FRAME_W}x{FRAME_H}", *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        m = re.match(r"serving on (http://127\.0\.0\.1:\d+)", line)
        if not m:
            self.proc.kill()
            raise AssertionError(f"palpsim-web did not start: {line!r} {self.proc.stderr.read()}")
        self.url = m.group(1)

    def stop(self) -> str:
        self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
        return err


@pytest.fixture
def gateway(server) -> Iterator[Gateway]:
    g = Gateway(server.address, "--idle-s", "1")
    yield g
    g.stop()


def sessions_open(address: str) -> int:
    with Client(address) as c:
        return c.stats().server.sessions_open


def server_poses(address: str) -> int:
    with Client(address) as c:
        return c.stats().server.poses


def wait_for(cond, timeout_s: float, what: str):
    """cond()'s first true value, polled every 50 ms; the timeout only bounds a failure
    (this shared machine under a full ctest run renders a few frames a second)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError(f"no {what} within {timeout_s:g} s")


def test_page_messages_errors_secrets_and_idle_end(server, gateway):
    """Over a WebSocket as the page speaks: the hello carries no secret, bad messages get
    an error naming what is wrong and the link stays up, an oversized one closes it with
    1009, a WebSocket from another origin is refused, and the session of a browser that
    left ends after --idle-s (1 s)."""
    import aiohttp

    async def session_of_a_page():
        async with aiohttp.ClientSession() as http:
            page = await (await http.get(gateway.url + "/")).text()
            js = await (await http.get(gateway.url + "/static/app.js")).text()
            assert TOKEN not in page and TOKEN not in js
            missing = await http.get(gateway.url + "/static/../web.py")
            assert missing.status == 404
            forbidden = await http.get(gateway.url + "/ws", headers={"Origin": "http://evil.example",
                                                                     "Upgrade": "websocket",
                                                                     "Connection": "Upgrade",
                                                                     "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
                                                                     "Sec-WebSocket-Version": "13"})
            assert forbidden.status == 403
            assert "origin" in (await forbidden.text())
            texts = []
            async with http.ws_connect(gateway.url + "/ws") as ws:
                hello = await ws.receive_json(timeout=30)
                texts.append(json.dumps(hello))
                assert hello["type"] == "hello" and hello["mode"] == "palpate"
                assert sessions_open(server.address) == 1
                # the device's poses flow before any click (the tip waits outside the
                # skin), so the server's idle timeout never frees a page's session
                poses = server_poses(server.address)
                wait_for(lambda: server_poses(server.address) > poses + 100, 30, "poses before a click")

                async def error_for(text: str) -> str:
                    await ws.send_str(text)
                    while True:
                        m = await ws.receive(timeout=10)
                        if m.type == aiohttp.WSMsgType.TEXT:
                            texts.append(m.data)
                            d = json.loads(m.data)
                            if d["type"] == "error":
                                return d["message"]

                assert "not JSON" in await error_for("{nope")
                assert "type = 'teleport'" in await error_for(json.dumps({"type": "teleport"}))
                assert "pick.x = -5" in await error_for(json.dumps({"type": "pick", "x": -5, "y": 3}))
                assert "ERROR_BAD_PARAMETER: PickRequest.x_px" in await error_for(
                    json.dumps({"type": "pick", "x": 450, "y": 10}))
                assert "ERROR_BAD_VIEW" in await error_for(json.dumps({"type": "view", "view": {"zoom": 99}}))
                assert "depth.depth_mm = 500" in await error_for(json.dumps({"type": "depth", "depth_mm": 500}))
                for t in texts:
                    assert TOKEN not in t
                # an oversized message closes the link with 1009 (message too big)
                await ws.send_str("x" * (web.MAX_WS_MESSAGE_BYTES + 1))
                while not ws.closed:
                    await ws.receive(timeout=10)
                assert ws.close_code == 1009

    asyncio.run(session_of_a_page())
    # the browser is gone: its session ends after --idle-s
    wait_for(lambda: sessions_open(server.address) == 0, 30, "session end after the idle time")


def chromium_driver():
    """A headless chromium driven by selenium, or a skip naming what is missing."""
    try:
        return web.headless_chromium()
    except RuntimeError as e:
        skip(str(e))


def canvas_png(driver) -> np.ndarray:
    import io

    from PIL import Image

    png = driver.find_element("id", "frame").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(float)


def test_browser_sees_frames_and_palpates(server, gateway):
    """Headless chromium opens the page, sees frames, clicks the centre of the 3D view
    (azimuth 0: the camera looks at the patient's back) and gets a contact and a force
    above 0 while the frames change; screenshots go to $PALPSIM_WEB_SHOTS."""
    from PIL import Image
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.wheel_input import ScrollOrigin

    driver = chromium_driver()
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    stats = lambda: driver.execute_script("return window.palpsimStats")  # noqa: E731
    try:
        driver.get(gateway.url + "/")
        wait_for(lambda: stats()["frames"] >= 1, 60, "frame in the browser")  # one: nothing moves yet
        first = canvas_png(driver)
        driver.save_screenshot(str(SCREENSHOTS / "1-first-frame.png"))
        frames_before = stats()["frames"]
        # the canvas shows the frame at its own size (1100 px window): the centre of the 3D
        # view is (195, 135), offset from the canvas's centre (240, 135) by -45 px
        canvas = driver.find_element("id", "frame")
        scale = driver.execute_script("const r = arguments[0].getBoundingClientRect();"
                                      "return r.width / arguments[0].width;", canvas)
        ActionChains(driver).move_to_element_with_offset(canvas, int((VIEW_W / 2 - FRAME_W / 2) * scale), 0) \
            .click().perform()
        s = wait_for(lambda: (lambda v: v if v["maxForce"] > 0 and v["contact"] else None)(stats()), 60,
                     "contact with a force above 0 in the page")
        assert s["lastPick"]["hit"]
        assert s["errors"] == []
        # the press runs: more frames came, and they show the tip moved in
        wait_for(lambda: stats()["frames"] >= frames_before + 3, 60, "frames during the press")
        time.sleep(1.0)  # the path reaches its depth (6 mm at up to 60 mm/s) and a frame shows it
        pressed = canvas_png(driver)
        driver.save_screenshot(str(SCREENSHOTS / "2-pressed.png"))
        # neither blank nor the same: a frame of the phantom has structure (a blank one has
        # a pixel spread of 0), and the tip's markers appeared on the back and in the
        # slices: pixels more than 30 grey levels apart (far above JPEG noise, and an
        # unchanged view re-encodes byte for byte) number at least 20, about a quarter of
        # one marker's disc
        assert first.std() > 10 and pressed.std() > 10
        changed = int((np.abs(pressed - first).max(axis=2) > 30).sum())
        assert changed >= 20, f"{changed} pixels of the frame changed"
        page1, page2 = (np.asarray(Image.open(SCREENSHOTS / n).convert("RGB")).astype(float)
                        for n in ("1-first-frame.png", "2-pressed.png"))
        assert page2.std() > 10 and np.abs(page2 - page1).max(axis=2).sum() > 0
        # three wheel notches down push 3 mm deeper (6 -> 9 mm): the tip's depth under the
        # skin follows (more than 2 mm deeper: the depth is measured to the skin's nearest
        # point, within a voxel of the path's ray)
        depth_before = stats()["depth"]
        for _ in range(3):
            ActionChains(driver).scroll_from_origin(ScrollOrigin.from_element(canvas), 0, 100).perform()
        wait_for(lambda: stats()["depthGoal"] == 9, 30, "depth goal of 9 mm after 3 wheel notches")
        wait_for(lambda: stats()["depth"] > depth_before + 2, 30, "a deeper tip after the wheel")
        latencies = stats()["inputLatencies"]
        print(f"browser: {stats()['frames']} frames, {stats()['fps']:.1f} frames/s, input-to-frame "
              f"{[round(x) for x in latencies]} ms; screenshots in {SCREENSHOTS}")
    finally:
        driver.quit()


def test_watch_only_station_shows_the_haptic_clients_session(server):
    """With --watch the page watches the newest session of the gateway's client token
    (a haptic client's), gets its frames, and palpation is refused naming the mode."""
    import aiohttp

    g = Gateway(server.address, "--watch")
    try:
        with Client(server.address, client_token=TOKEN) as c, c.open_session("haptic client") as s:
            p = c.info().patient
            s.pose((p.body_max_mm.x + 20, p.body_max_mm.y + 20, p.body_max_mm.z + 20))

            async def page():
                async with aiohttp.ClientSession() as http, http.ws_connect(g.url + "/ws") as ws:
                    hello = await ws.receive_json(timeout=30)
                    assert hello["mode"] == "watch" and hello["session"] == f"{s.id:016x}"
                    frame = await ws.receive(timeout=30)
                    assert frame.type == aiohttp.WSMsgType.BINARY
                    await ws.send_str(json.dumps({"type": "pick", "x": 10, "y": 10}))
                    while True:
                        m = await ws.receive_json(timeout=10)
                        if m["type"] == "error":
                            assert "palpation is off" in m["message"]
                            break

            asyncio.run(page())
    finally:
        g.stop()


def test_station_token_login(server, tmp_path):
    """With a station token the page, its scripts and the WebSocket need the login; a
    wrong token is refused, the right one sets a cookie that is not the token."""
    import aiohttp

    token = "a-station-token-of-some-length"
    f = tmp_path / "token"
    f.write_text(token + "\n")
    g = Gateway(server.address, "--station-token-file", str(f))
    try:
        async def page():
            # unsafe: keep cookies of an IP address host, as browsers do
            async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
                r = await http.get(g.url + "/")
                assert r.url.path == "/login" and "Station token" in await r.text()
                assert (await http.get(g.url + "/static/app.js")).status == 401
                assert (await http.get(g.url + "/ws")).status == 401
                r = await http.post(g.url + "/login", data={"token": "wrong"})
                assert r.status == 403
                r = await http.post(g.url + "/login", data={"token": token})
                assert r.status == 200 and r.url.path == "/"
                cookies = [c.value for c in http.cookie_jar]
                assert cookies and token not in cookies
                async with http.ws_connect(g.url + "/ws") as ws:
                    assert (await ws.receive_json(timeout=30))["type"] == "hello"
                # a form past its size limit is refused
                r = await http.post(g.url + "/login", data={"token": "x" * (web.MAX_FORM_BYTES + 10)})
                assert r.status == 413

        asyncio.run(page())
    finally:
        g.stop()
