"""palpsim-web: a browser station. A gateway between palpsim-server and one page of plain
JavaScript modules (palpsim/web_static), so a training station palpates and watches with
nothing installed but a browser.

    palpsim-web --connect tcp://SERVER:7420 [--port 8080]
    # prints "serving on http://127.0.0.1:8080"; open it in a browser

Each browser (a WebSocket) gets a session of its own: the gateway opens it with the
station's keys or client token, watches its frames and forwards them as binary JPEG,
newest wins (a slow browser skips frames; nothing queues). A click on the body asks the
server for the skin point under that pixel (PickRequest), the wheel or a drag sets the
depth, and the gateway (not the browser) sends poses at 1 kHz along a smooth path to the
press, so the server sees a device. With --watch or --session the page only watches a
session another client palpates (a haptic client with the same --client-token or keys).

Security: it binds loopback by default; on any other address it needs --tls-cert,
--tls-key and a station token (--station-token-file), which the page asks for once (a
cookie then holds a random login, never the token). The CURVE keys and client token stay
in the gateway: no secret reaches the page. Messages from the page are JSON of at most
MAX_WS_MESSAGE_BYTES; bad ones get an error message naming the field. A browser that
disconnects ends its session after --idle-s seconds. The login and TLS pieces are in
palpsim/web_access.py.

Wire format to the page: text messages are JSON ({"type": ...}); a binary message is a
frame: 4 bytes big-endian header length, the header as JSON, then the JPEG. The header
names the frame and the pose it shows, the server's and the gateway's pose-to-frame
latency, the wall-clock time the gateway sent that pose (pose_sent_unix_ms: a page on
the same machine measures pose to frame against performance.timeOrigin + now) and the
newest page input that pose reflects.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import math
import signal
import ssl
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from . import keys
from .client import Client, PalpsimError, ServerError, ServerTimeout, view_settings
from .keys import CurveKeys
from .proto import wire
from .stream import SessionClosed, StreamClient, StreamError
from .view import _session, _size, positive_number
from .web_access import (MAX_FORM_BYTES, StationLogin, check_exposure, is_loopback,  # noqa: F401 (palpsim.web's names)
                         read_token, tls_context)

PROG = "palpsim-web"
STATIC = Path(__file__).with_name("web_static")

POSE_RATE_HZ = 1000.0          # poses the gateway sends per second while a browser palpates
MAX_SPEED_MM_S = 60.0          # the tip's top speed along its path (a hand's careful press)
SMOOTHING_S = 0.04             # time constant of the path's approach to its goal (s)
HOVER_MM = 15.0                # where a pick starts the tip: this far outside the skin along the ray
DEPTH_RANGE_MM = (-30.0, 40.0) # depths a page may ask for along the pixel's ray (negative: outside)
DEFAULT_DEPTH_MM = 6.0         # the press a click starts
STATE_RATE_HZ = 30.0           # force and contact messages to the page per second
MAX_WS_MESSAGE_BYTES = 4096    # a page's message (JSON) is far smaller; larger ones close the socket

# view fields a page may set (client.VIEW_FIELDS less what the gateway decides)
PAGE_VIEW_FIELDS = ("preset", "azimuth_deg", "elevation_deg", "zoom", "look_at_tip", "center_mm",
                    "show_tip", "show_proxy", "slice_fov_mm")
PRESETS = ("skin", "bone", "soft_tissue")

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def _say(text: str) -> None:
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


class PageError(ValueError):
    """A page's message that the gateway refuses; the text names the field."""


def _vec(v: "wire.Vec3") -> list[float]:
    return [v.x, v.y, v.z]


def view_dict(v: "wire.ViewSettings") -> dict[str, Any]:
    """A ViewSettings message as JSON for the page."""
    return {"width": v.width, "height": v.height, "preset": v.preset, "azimuth_deg": v.azimuth_deg,
            "elevation_deg": v.elevation_deg, "zoom": v.zoom, "look_at_tip": v.look_at_tip,
            "center_mm": _vec(v.center_mm), "show_tip": v.show_tip, "show_proxy": v.show_proxy,
            "slice_fov_mm": v.slice_fov_mm}


def _number(msg: dict[str, Any], name: str, lo: float | None = None, hi: float | None = None) -> float:
    """A finite number field of a page's message within [lo, hi]; raises PageError."""
    v = msg.get(name)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise PageError(f"{msg.get('type')}.{name} = {v!r}: expected a finite number")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise PageError(f"{msg.get('type')}.{name} = {v!r} is outside {lo:g}..{hi:g}")
    return float(v)


def page_view(msg: dict[str, Any]) -> dict[str, Any]:
    """The view changes of a page's {"type": "view", "view": {...}} message, checked for
    field names and types (the server checks ranges: ERROR_BAD_VIEW); raises PageError."""
    v = msg.get("view")
    if not isinstance(v, dict) or not v:
        raise PageError("view.view: expected an object of view fields")
    unknown = sorted(set(v) - set(PAGE_VIEW_FIELDS))
    if unknown:
        raise PageError(f"view.view: unknown field(s) {', '.join(unknown)}; a page may set "
                        f"{', '.join(PAGE_VIEW_FIELDS)}")
    for name, value in v.items():
        if name == "preset":
            if value not in PRESETS:
                raise PageError(f"view.preset = {value!r}: expected one of {', '.join(PRESETS)}")
        elif name in ("look_at_tip", "show_tip", "show_proxy"):
            if not isinstance(value, bool):
                raise PageError(f"view.{name} = {value!r}: expected true or false")
        elif name == "center_mm":
            if (not isinstance(value, list) or len(value) != 3 or
                    not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c)
                            for c in value)):
                raise PageError(f"view.center_mm = {value!r}: expected three finite numbers (mm)")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise PageError(f"view.{name} = {value!r}: expected a finite number")
    return dict(v)


class TipPath:
    """The tip's path to its goal, stepped once per pose: an exponential approach (time
    constant SMOOTHING_S) whose speed is capped at MAX_SPEED_MM_S, so a click or a wheel
    notch becomes a smooth press and never a jump (mm, s)."""

    def __init__(self, start_mm: Sequence[float]):
        self.tip = np.asarray(start_mm, dtype=float).copy()
        self.goal = self.tip.copy()

    def step(self, dt_s: float) -> np.ndarray:
        """Advances the tip by `dt_s` toward the goal and returns it."""
        delta = self.goal - self.tip
        dist = float(np.linalg.norm(delta))
        if dist > 1e-9:
            move = min(dist * (1.0 - math.exp(-dt_s / SMOOTHING_S)), MAX_SPEED_MM_S * dt_s)
            self.tip = self.tip + delta * (move / dist)
        return self.tip


class Station:
    """One browser's link to the server: its client, session, frame thread and (when it
    palpates) the 1 kHz device thread. Control requests (pick, watch, close) go through
    `control()` one at a time (a ZeroMQ socket is not thread-safe)."""

    def __init__(self, gateway: "Gateway", loop: asyncio.AbstractEventLoop):
        self.gw = gateway
        self.loop = loop
        self.client: Client | None = None
        self.session = None
        self.session_id = 0
        self.watch_reply: "wire.WatchReply | None" = None
        self.max_force_n = 10.0
        self._ctl_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        # newest frame for the page (set from the frame thread, taken by the sender task)
        self.frame_msg: bytes | None = None
        self.frame_ready = asyncio.Event()
        self.frames_skipped = 0
        # the press, written by the page's handler, read by the device thread
        self.skin_mm: np.ndarray | None = None
        self.path_start: np.ndarray | None = None  # where the first press starts (hovering)
        self.ray_dir: np.ndarray | None = None
        self.depth_mm = DEFAULT_DEPTH_MM
        self.hovering = True                    # before the first click the tip waits outside
        self.pending_input = 0
        self.inputs: collections.deque[tuple[int, int]] = collections.deque(maxlen=64)  # (first seq, input)
        self.sent_at = np.zeros(4096)           # gateway clock (s) of pose seq % 4096
        self.sent_unix = np.zeros(4096)         # and wall clock (s), for the page's clock on one machine
        self.state: dict[str, Any] = {}          # newest pose reply, for the page
        self.poses = 0
        self.errors: collections.deque[str] = collections.deque(maxlen=8)  # for the page

    # -- control path ---------------------------------------------------------------------

    def control(self, fn, *args):
        """Runs one control request under the control socket's lock (executor threads)."""
        with self._ctl_lock:
            return fn(*args)

    def open(self) -> dict[str, Any]:
        """Connects, opens (or picks) the session and watches its frames; the hello message."""
        a = self.gw.args
        self.client = Client(a.connect, timeout_s=a.timeout, name=PROG, curve=self.gw.curve,
                             client_token=a.client_token)
        view = dict(self.gw.initial_view)
        if self.gw.watch_only:
            self.watch_reply = self.client.watch(session_id=a.session or 0, frames=True, view=view)
            self.session_id = self.watch_reply.session_id
        else:
            self.session = self.client.open_session(PROG)
            self.session_id = self.session.id
            self.max_force_n = self.session.params.max_force_n or self.max_force_n
            self.watch_reply = self.client.watch(session_id=self.session_id, frames=True, view=view)
        p = self.client.info().patient
        self._start(self._frames, "palpsim-web-frames")
        if self.session is not None:
            self._park(p)
            self._start(self._device, "palpsim-web-device")
        return {"type": "hello", "mode": "watch" if self.gw.watch_only else "palpate",
                "session": f"{self.session_id:016x}", "view": view_dict(self.watch_reply.view),
                "body_min_mm": _vec(p.body_min_mm), "body_max_mm": _vec(p.body_max_mm),
                "max_force_n": self.max_force_n, "depth_range_mm": list(DEPTH_RANGE_MM),
                "depth_mm": self.depth_mm}

    def _park(self, patient: "wire.PatientInfo") -> None:
        """Where the tip waits for the first click: HOVER_MM outside the skin under the
        centre of the 3D view, so the device's poses flow from the start (a session
        without poses would be freed by the server's idle timeout)."""
        v = self.watch_reply.view
        view_w = v.width - min(v.height // 3, v.width)
        r = self.client.pick(self.session_id, view_w / 2, v.height / 2)
        if r.hit:
            self.ray_dir = np.array(_vec(r.ray_direction))
            self.skin_mm = np.array(_vec(r.point_mm))
        else:  # the centre misses the body: wait on the ray's side of the body's bounding box
            lo, hi = np.array(_vec(patient.body_min_mm)), np.array(_vec(patient.body_max_mm))
            self.ray_dir = np.array(_vec(r.ray_direction))
            self.skin_mm = (lo + hi) / 2 - self.ray_dir * (np.linalg.norm(hi - lo) / 2)
        self.path_start = self.skin_mm - self.ray_dir * HOVER_MM

    def set_view(self, changes: dict[str, Any]) -> dict[str, Any]:
        """Sends view changes to the server (WatchSession); the view it now renders."""
        reply = self.client.watch(session_id=self.session_id, frames=True, view=view_settings(changes))
        return {"type": "view", "view": view_dict(reply.view)}

    def pick(self, x: float, y: float, input_id: int) -> dict[str, Any]:
        """The skin point under a pixel; on a hit the press moves there."""
        r = self.client.pick(self.session_id, x, y)
        out: dict[str, Any] = {"type": "pick", "hit": r.hit, "input": input_id,
                               "ray_direction": _vec(r.ray_direction)}
        if r.hit:
            skin = np.array(_vec(r.point_mm))
            d = np.array(_vec(r.ray_direction))
            self.ray_dir, self.skin_mm = d, skin
            self.hovering = False
            self.pending_input = input_id
            out["point_mm"] = skin.tolist()
        return out

    def close_session(self) -> None:
        """Stops the threads and closes the session and sockets (best effort)."""
        self.stop_threads()
        if self.client is not None:
            try:
                with self._ctl_lock:
                    self.client.close()
            except PalpsimError:
                pass

    # -- threads --------------------------------------------------------------------------

    def _start(self, target, name: str) -> None:
        t = threading.Thread(target=self._guarded, args=(target,), name=name, daemon=True)
        self._threads.append(t)
        t.start()

    def _guarded(self, target) -> None:
        try:
            target()
        except SessionClosed as e:
            self._note(f"session ended: {e.message or e}")
        except (PalpsimError, OSError) as e:
            self._note(str(e))

    def _note(self, text: str) -> None:
        self.errors.append(text)
        self.loop.call_soon_threadsafe(self.frame_ready.set)

    def stop_threads(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()

    def _frames(self) -> None:
        """The frame thread: newest frame of the session into `frame_msg`."""
        with StreamClient.from_watch(self.watch_reply, self.gw.args.connect, curve=self.gw.curve) as sc:
            while not self._stop.is_set():
                update = sc.receive(timeout_s=0.2)
                if update is None or update.frame is None:
                    continue
                f = update.frame
                now = time.monotonic()
                seq = f.pose_seq
                ours = bool(seq) and self.session is not None and seq > self.poses - 4096
                gateway_ms = (now - self.sent_at[seq % 4096]) * 1e3 if ours else None
                sent_unix_ms = self.sent_unix[seq % 4096] * 1e3 if ours else None
                input_id = 0
                for first_seq, k in reversed(self.inputs):
                    if seq >= first_seq:
                        input_id = k
                        break
                header = {"frame_seq": f.frame_seq, "pose_seq": seq, "width": f.width,
                          "height": f.height, "pose_to_frame_ms": f.pose_to_frame_ms,
                          "gateway_pose_to_frame_ms": gateway_ms, "pose_sent_unix_ms": sent_unix_ms,
                          "input": input_id,
                          "contact": f.contact, "deformed": f.deformed, "tip_mm": _vec(f.tip_mm),
                          "view": view_dict(f.view)}
                head = json.dumps(header).encode()
                msg = struct.pack(">I", len(head)) + head + f.jpeg
                self.loop.call_soon_threadsafe(self._offer, msg)

    def _offer(self, msg: bytes) -> None:
        if self.frame_msg is not None:
            self.frames_skipped += 1  # newest wins: the page has not taken the last one
        self.frame_msg = msg
        self.frame_ready.set()

    def _device(self) -> None:
        """The device thread: a pose every 1/POSE_RATE_HZ s along the tip's path."""
        s = self.session
        path: TipPath | None = None
        period = 1.0 / POSE_RATE_HZ
        next_t = time.monotonic()
        last = next_t
        while not self._stop.is_set():
            now = time.monotonic()
            if now < next_t:
                time.sleep(next_t - now)
                now = time.monotonic()
            # a late loop catches up by at most one period (it never bursts)
            next_t = max(next_t + period, now)
            if path is None:
                path = TipPath(self.path_start)
            lo, hi = DEPTH_RANGE_MM
            depth = -HOVER_MM if self.hovering else min(max(self.depth_mm, lo), hi)
            path.goal = self.skin_mm + self.ray_dir * depth
            tip = path.step(min(now - last, 0.01))
            last = now
            seq = s.send_pose(tip, client_time_s=now)
            self.sent_at[seq % 4096] = now
            self.sent_unix[seq % 4096] = time.time()
            if self.pending_input:
                self.inputs.append((seq, self.pending_input))
                self.pending_input = 0
            try:
                r = s.recv_reply(timeout_s=2.0)
            except ServerError as e:
                self.errors.append(str(e))
                continue
            self.poses = seq
            self.state = {"force_n": r.force_n.tolist(), "contact": r.contact, "depth_mm": r.depth_mm,
                          "tip_mm": tip.tolist(), "seq": r.seq, "rtt_ms": r.rtt_s * 1e3}


class Gateway:
    """The web server: the page, the login, and one Station per WebSocket."""

    def __init__(self, args: argparse.Namespace, curve: CurveKeys | None, token: str | None):
        self.args = args
        self.curve = curve
        self.access = StationLogin(PROG, token, secure=args.tls_cert is not None)
        self.stations = 0
        self.live: set[Station] = set()          # stations with a session (closed at exit)
        self._endings: set[asyncio.Task] = set()  # idle-time ends of left browsers
        self.watch_only = bool(args.watch or args.session)
        w, h = args.size
        self.initial_view: dict[str, Any] = {"width": w, "height": h, "look_at_tip": False,
                                             "azimuth_deg": args.azimuth, "elevation_deg": args.elevation}
        if self.watch_only:
            self.initial_view = {"width": w, "height": h}

    # -- HTTP -----------------------------------------------------------------------------

    def app(self):
        from aiohttp import web

        app = web.Application(client_max_size=MAX_FORM_BYTES)
        app.router.add_get("/", self.index)
        app.router.add_get("/login", self.access.page)
        app.router.add_post("/login", self.access.login)
        app.router.add_get("/ws", self.websocket)
        app.router.add_get("/static/{name}", self.static)
        return app

    async def index(self, request):
        from aiohttp import web

        if not self.access.logged_in(request):
            raise web.HTTPFound("/login")
        return web.FileResponse(STATIC / "index.html", headers=_NO_STORE)

    async def static(self, request):
        from aiohttp import web

        if not self.access.logged_in(request):
            raise web.HTTPUnauthorized(text=f"{PROG}: log in first (/login)")
        name = request.match_info["name"]
        path = STATIC / name
        if "/" in name or name.startswith(".") or not path.is_file() or name == "index.html":
            raise web.HTTPNotFound(text=f"{PROG}: no file {name!r} here (the page is at /)")
        return web.FileResponse(path, headers=_NO_STORE)

    # -- WebSocket ------------------------------------------------------------------------

    async def websocket(self, request):
        from aiohttp import WSMsgType, web

        if not self.access.logged_in(request):
            raise web.HTTPUnauthorized(text=f"{PROG}: log in first (/login)")
        origin = request.headers.get("Origin")
        if origin is not None and origin.split("://", 1)[-1] != request.host:
            raise web.HTTPForbidden(text=f"{PROG}: a WebSocket from origin {origin!r}, not from this "
                                         f"gateway's page ({request.host})")
        if self.stations >= self.args.max_stations:
            raise web.HTTPServiceUnavailable(text=f"{PROG}: {self.stations} browsers are connected, "
                                                  f"the most --max-stations allows")
        ws = web.WebSocketResponse(max_msg_size=MAX_WS_MESSAGE_BYTES, heartbeat=5.0)
        await ws.prepare(request)
        self.stations += 1
        loop = asyncio.get_running_loop()
        st = Station(self, loop)
        self.live.add(st)
        tasks: list[asyncio.Task] = []
        try:
            try:
                hello = await loop.run_in_executor(None, st.open)
            except (PalpsimError, OSError) as e:
                await ws.send_json({"type": "error", "fatal": True, "message": _refusal(e)})
                return ws
            await ws.send_json(hello)
            tasks = [asyncio.create_task(self._send_frames(ws, st)),
                     asyncio.create_task(self._send_state(ws, st))]
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    reply = await self._handle(st, msg.data)
                    if reply is not None:
                        await ws.send_json(reply)
                elif msg.type == WSMsgType.BINARY:
                    await ws.send_json({"type": "error", "message": "a binary message from the page: the "
                                        "gateway takes JSON text messages only"})
                elif msg.type == WSMsgType.ERROR:
                    break
            return ws
        finally:
            self.stations -= 1
            for t in tasks:
                t.cancel()
            # the browser is gone: no more poses now, the session ends after the idle time
            st._stop.set()
            task = asyncio.create_task(self._end_later(st))
            self._endings.add(task)
            task.add_done_callback(self._endings.discard)

    async def _end_later(self, st: Station) -> None:
        await asyncio.sleep(self.args.idle_s)
        await asyncio.get_running_loop().run_in_executor(None, st.close_session)
        self.live.discard(st)

    async def close_all(self) -> None:
        """Ends every session (at exit)."""
        loop = asyncio.get_running_loop()
        await asyncio.gather(*(loop.run_in_executor(None, st.close_session) for st in list(self.live)))
        self.live.clear()

    async def _handle(self, st: Station, text: str) -> dict[str, Any] | None:
        loop = asyncio.get_running_loop()
        try:
            try:
                msg = json.loads(text)
            except json.JSONDecodeError as e:
                raise PageError(f"a message that is not JSON ({e.msg} at character {e.pos})") from None
            if not isinstance(msg, dict):
                raise PageError("a message that is not a JSON object")
            kind = msg.get("type")
            input_id = int(_number(msg, "input", 0, 2 ** 53)) if "input" in msg else 0
            if kind == "view":
                return await loop.run_in_executor(None, st.control, st.set_view, page_view(msg))
            if kind in ("pick", "depth", "lift") and st.session is None:
                raise PageError(f"{kind}: this gateway watches session {st.session_id:016x}; "
                                "palpation is off (--watch / --session)")
            if kind == "pick":
                x, y = _number(msg, "x", 0, 1e5), _number(msg, "y", 0, 1e5)
                return await loop.run_in_executor(None, st.control, st.pick, x, y, input_id)
            if kind == "depth":
                st.depth_mm = _number(msg, "depth_mm", *DEPTH_RANGE_MM)
                st.pending_input = input_id
                return None
            if kind == "lift":
                st.depth_mm = DEPTH_RANGE_MM[0]
                st.pending_input = input_id
                return None
            raise PageError(f"type = {kind!r}: expected one of view, pick, depth, lift")
        except PageError as e:
            return {"type": "error", "message": str(e)}
        except ValueError as e:  # view_settings' refusals
            return {"type": "error", "message": str(e)}
        except (PalpsimError, OSError) as e:
            return {"type": "error", "message": _refusal(e)}

    async def _send_frames(self, ws, st: Station) -> None:
        try:
            await self._frames_to(ws, st)
        except (ConnectionResetError, RuntimeError):
            pass  # the browser left; the WebSocket handler ends the station

    async def _frames_to(self, ws, st: Station) -> None:
        while True:
            await st.frame_ready.wait()
            st.frame_ready.clear()
            while st.errors:
                await ws.send_json({"type": "error", "message": st.errors.popleft()})
            msg, st.frame_msg = st.frame_msg, None
            if msg is not None:
                await ws.send_bytes(msg)  # waits for a slow browser; newer frames replace msg meanwhile

    async def _send_state(self, ws, st: Station) -> None:
        try:
            await self._state_to(ws, st)
        except (ConnectionResetError, RuntimeError):
            pass  # the browser left

    async def _state_to(self, ws, st: Station) -> None:
        last_poses, last_t = 0, time.monotonic()
        while True:
            await asyncio.sleep(1.0 / STATE_RATE_HZ)
            now = time.monotonic()
            if st.state:
                rate = (st.poses - last_poses) / max(now - last_t, 1e-6)
                last_poses, last_t = st.poses, now
                await ws.send_json({"type": "state", **st.state, "depth_goal_mm": st.depth_mm,
                                    "poses_per_s": rate, "frames_skipped": st.frames_skipped})


def headless_chromium(width: int = 1100, height: int = 800, accept_insecure_certs: bool = False):
    """A selenium WebDriver of Debian's headless chromium through chromium-driver, for the
    browser test, the benchmark and scripts/docker-test.sh; raises RuntimeError naming what
    is missing. accept_insecure_certs lets it open a gateway whose TLS certificate is
    self-signed (the container test's)."""
    import shutil

    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        raise RuntimeError("selenium is not installed (pip install selenium; scripts/setup.sh "
                           "installs it)") from None
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not browser or not driver:
        raise RuntimeError("Debian's chromium and chromium-driver are not installed (apt-get install "
                           "chromium chromium-driver; scripts/setup.sh installs them)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = browser
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}"):
        opts.add_argument(a)
    if accept_insecure_certs:
        opts.set_capability("acceptInsecureCerts", True)
    return webdriver.Chrome(service=Service(driver), options=opts)


def _refusal(e: Exception) -> str:
    if isinstance(e, ServerError):
        return f"{e.code_name}: {e.message}"
    return str(e)


_NO_STORE = {"Cache-Control": "no-store"}


# ---------------------------------------------------------------------------------------
# Command line


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description="A browser station for palpsim-server: "
                                "serves one page that shows the live frame and palpates with the mouse.")
    p.add_argument("--connect", metavar="ADDR", required=True,
                   help="the server's control address (tcp://HOST:7420)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve the page on (default 127.0.0.1; any other needs --tls-cert, "
                        "--tls-key and --station-token-file)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 picks a free one)")
    keys.add_arguments(p)
    sec = p.add_argument_group("serving beyond loopback")
    sec.add_argument("--tls-cert", metavar="FILE", help="TLS certificate (PEM)")
    sec.add_argument("--tls-key", metavar="FILE", help="TLS private key (PEM)")
    sec.add_argument("--station-token-file", metavar="FILE",
                     help="a file whose first line is the station's login token (the page asks for it)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--watch", action="store_true",
                       help="only watch the newest session of this client's keys or --client-token (a haptic "
                            "client palpates); no palpation from the page")
    which.add_argument("--session", metavar="ID", type=_session, help="only watch this session")
    p.add_argument("--size", metavar="WxH", type=_size, default=(960, 540), help="frame size (default 960x540)")
    p.add_argument("--azimuth", metavar="DEG", type=float, default=0.0,
                   help="the first view's azimuth (default 0: from posterior, the back)")
    p.add_argument("--elevation", metavar="DEG", type=float, default=10.0, help="the first view's elevation")
    p.add_argument("--idle-s", metavar="S", type=positive_number("seconds"), default=10.0,
                   help="a browser that disconnects ends its session after this long (default 10)")
    p.add_argument("--max-stations", metavar="N", type=int, default=4,
                   help="browsers served at once (each has a session; default 4)")
    p.add_argument("--timeout", metavar="S", type=positive_number("seconds"), default=10.0,
                   help="how long to wait for the server's answers (default 10)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """palpsim-web's entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    why = check_exposure(args)
    if why:
        _say(why)
        return EXIT_USAGE
    if args.max_stations < 1:
        _say(f"--max-stations {args.max_stations}: at least 1")
        return EXIT_USAGE
    try:
        curve = keys.from_arguments(args)
        token = read_token(args.station_token_file) if args.station_token_file else None
        tls = tls_context(args)
    except (keys.KeyFileError, ValueError, RuntimeError) as e:
        _say(str(e))
        return EXIT_USAGE
    except (OSError, ssl.SSLError) as e:
        _say(f"--tls-cert {args.tls_cert} / --tls-key {args.tls_key}: {e}")
        return EXIT_USAGE
    # the server must answer before the page is served
    try:
        with Client(args.connect, timeout_s=args.timeout, name=PROG, curve=curve,
                    client_token=args.client_token) as c:
            info = c.info()
    except PalpsimError as e:
        _say(str(e))
        return EXIT_FAIL
    if not info.stream_endpoint:
        _say(f"the server at {args.connect} serves scene '{info.scene_name}', which asks for no frames "
             "(effects.frames): there is nothing to show")
        return EXIT_FAIL
    return asyncio.run(_serve(args, curve, token, tls))


async def _serve(args: argparse.Namespace, curve: CurveKeys | None, token: str | None,
                 tls: ssl.SSLContext | None) -> int:
    from aiohttp import web

    gw = Gateway(args, curve, token)
    runner = web.AppRunner(gw.app(), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, args.host, args.port, ssl_context=tls)
    try:
        await site.start()
    except OSError as e:
        _say(f"cannot serve on {args.host}:{args.port}: {e.strerror}")
        await runner.cleanup()
        return EXIT_FAIL
    port = site._server.sockets[0].getsockname()[1]
    host = f"[{args.host}]" if ":" in args.host else args.host
    print(f"serving on {'https' if tls else 'http'}://{host}:{port}", flush=True)
    # SIGTERM and SIGINT end the sessions before the gateway exits
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await gw.close_all()
        await runner.cleanup()
    return EXIT_OK


def run() -> None:
    """The console script: Ctrl-C ends it quietly."""
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        sys.exit(EXIT_OK)


if __name__ == "__main__":
    run()
