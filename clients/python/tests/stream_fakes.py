"""Fakes and helpers shared by the stream tests (test_view.py, test_record.py): a fake
palpsim-server written here, pictures that say which frame they are, stream messages
as the server builds them, and the start of a real palpsim-server for end-to-end tests.

The fake server is a ROUTER that answers ControlRequest.info, .watch, .open and .close
as palpsim-server does (PROTOCOL.md, "Frames and bricks": session 0 = newest, the error
codes, the view ranges of server/render/view.h), a second ROUTER on the pose path that
answers PoseRequests with a closed-form body (`pose_model`), and an XPUB that publishes
two-frame [topic, StreamMessage] messages when it sees a subscription, with the
server's small send high-water mark.

Frames carry their frame_seq as 16 bars (bit b of seq: a light or a dark bar), so a test
can read from a PNG or an MP4 which frame it shows: the bars are 20+ pixels wide and
light (230) or dark (25), so JPEG and h264 errors (a few levels inside a bar) are far
from the threshold of 128 that reads them.
"""

from __future__ import annotations

import math
import os
import re
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest
import zmq

from palpsim.client import Client
from palpsim.proto import SCHEMA_VERSION, wire
from palpsim.stream import brick_topic, frame_topic

ROOT = Path(__file__).resolve().parents[3]
SID = 0x1234ABCD5678EF01
OTHER_SID = 0x0FEDCBA987654321

# ---------------------------------------------------------------------------------------
# Pictures that say which frame they are


def seq_image(seq: int, width: int, height: int) -> np.ndarray:
    """An RGB image whose 16 vertical bars spell `seq` (bit 0 leftmost): light bars for
    ones, dark bars for zeros, on a mid-grey background."""
    img = np.full((height, width, 3), 90, dtype=np.uint8)
    bw = width // 16
    for b in range(16):
        img[height // 4: 3 * height // 4, b * bw:(b + 1) * bw] = 230 if (seq >> b) & 1 else 25
    return img


def read_seq(rgb: np.ndarray) -> int:
    """The seq a seq_image shows (each bar's mean inside a 4-pixel margin, against 128)."""
    h, w = rgb.shape[:2]
    bw = w // 16
    seq = 0
    for b in range(16):
        bar = rgb[h // 4 + 4: 3 * h // 4 - 4, b * bw + 4:(b + 1) * bw - 4]
        if bar.mean() > 128:
            seq |= 1 << b
    return seq


def jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def read_mp4(path: Path) -> tuple[list[np.ndarray], dict]:
    """Every frame of a video and its metadata (fps, size), read back with imageio-ffmpeg."""
    import imageio.v2 as imageio

    with imageio.get_reader(str(path), format="FFMPEG") as r:
        return [np.asarray(f) for f in r], dict(r.get_meta_data())


def read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


# ---------------------------------------------------------------------------------------
# Messages


def stream_message(**body: Any) -> bytes:
    m = wire.StreamMessage(schema_version=SCHEMA_VERSION)
    for k, v in body.items():
        getattr(m, k).CopyFrom(v)
    return m.SerializeToString()


def frame_parts(sid: int, seq: int, width: int, height: int, *, t_s: float | None = None,
                pose_to_frame_ms: float = 5.0, data: bytes | None = None,
                pose_seq: int | None = None, **fields: Any) -> list[bytes]:
    """A frame message; `fields` sets further Frame fields (deform_pose_seq, deformed,
    deform_step, contact, ...). pose_seq defaults to 10 * seq."""
    f = wire.Frame(session_id=sid, frame_seq=seq, pose_seq=10 * seq if pose_seq is None else pose_seq,
                   server_time_s=seq * 0.05 if t_s is None else t_s,
                   pose_to_frame_ms=pose_to_frame_ms, width=width, height=height,
                   jpeg=data if data is not None else jpeg(seq_image(seq, width, height)),
                   encoder="turbojpeg", **fields)
    return [frame_topic(sid), stream_message(frame=f)]


def notice_parts(topic: bytes, sid: int, event: str, message: str,
                 code: int = wire.ERROR_NONE) -> list[bytes]:
    n = wire.StreamNotice(session_id=sid, event=event, message=message)
    if code:
        n.error.code, n.error.message = code, message
    return [topic, stream_message(notice=n)]


class GridSpec:
    """A patient grid for fake bricks (voxels (i, j, k), spacing, origin, direction)."""

    def __init__(self, size=(20, 17, 23), spacing_mm=2.0, origin_mm=(-19.0, -16.0, -22.0),
                 direction=(1, 0, 0, 0, 1, 0, 0, 0, 1)):
        self.size, self.spacing_mm = tuple(size), spacing_mm
        self.origin_mm, self.direction = np.asarray(origin_mm, float), tuple(float(d) for d in direction)

    def box_origin(self, lo) -> np.ndarray:
        d = np.asarray(self.direction).reshape(3, 3)
        return self.origin_mm + d @ (np.asarray(lo, float) * self.spacing_mm)


def make_brick(sid: int, seq: int, grid: GridSpec, values: np.ndarray, lo=(0, 0, 0), *,
               encoding=wire.BRICK_INT16, compression=wire.COMPRESSION_NONE, key=False,
               key_id=0, key_part=0, key_parts=0, deformed=True, pose_seq=0, deform_step=0,
               t_s=0.0) -> wire.Brick:
    """A Brick as the server makes it: values (k, j, i) on the box at lo, encoded."""
    import zstandard

    size_k, size_j, size_i = values.shape
    raw = values.astype("<i2" if encoding == wire.BRICK_INT16 else "<f4").tobytes()
    data = zstandard.ZstdCompressor().compress(raw) if compression == wire.COMPRESSION_ZSTD else raw
    o = grid.box_origin(lo)
    b = wire.Brick(session_id=sid, brick_seq=seq, pose_seq=pose_seq, deform_step=deform_step,
                   key=key, key_id=key_id, key_part=key_part, key_parts=key_parts,
                   deformed=deformed, lo_i=lo[0], lo_j=lo[1], lo_k=lo[2], size_i=size_i,
                   size_j=size_j, size_k=size_k, grid_size_i=grid.size[0],
                   grid_size_j=grid.size[1], grid_size_k=grid.size[2], spacing_mm=grid.spacing_mm,
                   encoding=encoding, compression=compression, data=data, raw_bytes=len(raw),
                   server_time_s=t_s)
    b.grid_origin_mm.CopyFrom(wire.Vec3(x=grid.origin_mm[0], y=grid.origin_mm[1], z=grid.origin_mm[2]))
    b.origin_mm.CopyFrom(wire.Vec3(x=o[0], y=o[1], z=o[2]))
    b.direction.extend(grid.direction)
    return b


def key_bricks(sid: int, grid: GridSpec, volume: np.ndarray, parts: int, key_id: int = 1,
               first_seq: int = 1, **enc: Any) -> list[wire.Brick]:
    """The whole-volume key in `parts` slabs along k (np.array_split sizes)."""
    out, k0 = [], 0
    for p, slab in enumerate(np.array_split(volume, parts, axis=0)):
        out.append(make_brick(sid, first_seq + p, grid, slab, (0, 0, k0), key=True, key_id=key_id,
                              key_part=p, key_parts=parts, deformed=False, **enc))
        k0 += slab.shape[0]
    return out


def brick_parts(b: wire.Brick) -> list[bytes]:
    return [brick_topic(b.session_id), stream_message(brick=b)]


# ---------------------------------------------------------------------------------------
# The fake server

DEFAULT_VIEW = dict(width=1280, height=720, preset="bone", azimuth_deg=35.0, elevation_deg=25.0,
                    zoom=1.0, look_at_tip=True, jpeg_quality=85, show_tip=True, show_proxy=False,
                    slice_fov_mm=120.0)
PRESETS = ("skin", "bone", "soft_tissue")


def check_view(v: wire.ViewSettings) -> str:
    """server/render/view.h's check_view: "" or a sentence naming the field and its range."""
    def rng(name, lo, hi, unit=""):
        if v.HasField(name):
            x = getattr(v, name)
            if not (math.isfinite(x) and lo <= x <= hi):
                return f"WatchSession.view.{name} = {x:g} is outside {lo:g}..{hi:g}{unit}"
        return ""
    for msg in (rng("width", 64, 3840, " pixels"), rng("height", 64, 2160, " pixels"),
                rng("elevation_deg", -89, 89, " degrees"), rng("zoom", 0.1, 20),
                rng("jpeg_quality", 1, 100), rng("slice_fov_mm", 10, 2000, " mm")):
        if msg:
            return msg
    if v.HasField("preset") and v.preset not in PRESETS:
        return f"WatchSession.view.preset = '{v.preset}' is not one of {', '.join(PRESETS)}"
    if v.HasField("azimuth_deg") and not math.isfinite(v.azimuth_deg):
        return f"WatchSession.view.azimuth_deg = {v.azimuth_deg} is not finite"
    c = v.center_mm
    if not all(math.isfinite(x) for x in (c.x, c.y, c.z)):
        return "WatchSession.view.center_mm is not finite"
    return ""


Script = Callable[["FakeServer", bytes], Iterator[Any]]
PoseModel = Callable[[wire.PoseRequest, wire.PoseReply], None]


def flat_skin(skin_y_mm: float = 100.0, k_n_per_mm: float = 0.1) -> PoseModel:
    """A body below the plane y = skin_y_mm: in contact below it, depth skin_y - y, force
    k * depth along +y, the proxy and the skin point on the plane above the tip."""
    def model(req: wire.PoseRequest, rep: wire.PoseReply) -> None:
        t = req.tip_mm
        depth = max(skin_y_mm - t.y, 0.0)
        rep.contact = depth > 0
        rep.depth_mm = depth
        rep.force_n.CopyFrom(wire.Vec3(x=0.0, y=k_n_per_mm * depth, z=0.0))
        top = wire.Vec3(x=t.x, y=max(t.y, skin_y_mm) if depth > 0 else t.y, z=t.z)
        rep.proxy_mm.CopyFrom(top)
        rep.skin_point_mm.CopyFrom(top)
    return model


# the first session id the fake's OpenSession hands out (then +1 each)
FIRST_OPENED_SID = 0x5E55000000000001


def _drain(recv: Callable[[int], Any], handle: Callable[[Any], None]) -> None:
    """Hands every message that `recv` has ready (without waiting) to `handle`."""
    while True:
        try:
            m = recv(zmq.NOBLOCK)
        except zmq.Again:
            return
        handle(m)


class FakeServer:
    """A fake palpsim-server: control ROUTER, pose ROUTER and stream XPUB on free loopback
    ports, one thread. `script(fake, topic)` is started when the XPUB sees the first
    subscription to a topic; it yields message part lists to publish, or a float to sleep
    that many seconds (other scripts, control requests and poses go on meanwhile).

    OpenSession hands out FIRST_OPENED_SID, +1, ...; poses of an open session are
    answered by `pose_model(request, reply)` (default: out of contact, no force) and kept
    in `poses[session]` as (time.monotonic() at arrival, PoseRequest, PoseReply), so a
    script can draw what the session's client did. `stages` is what Info reports as
    built (a recorder reads "chainmail" there as "the scene deforms")."""

    def __init__(self, sessions=(SID,), frames=True, bricks=True, script: Script | None = None,
                 sndhwm: int = 64, pose_model: PoseModel | None = None,
                 stages=("haptics", "frames", "bricks")):
        self.sessions = list(sessions)        # open sessions, newest last
        self.frames_built, self.bricks_built = frames, bricks
        self.script = script
        self.pose_model = pose_model
        self.stages = list(stages)
        self.views = {s: wire.ViewSettings(**DEFAULT_VIEW) for s in self.sessions}
        self.encoding = {s: (wire.BRICK_INT16, wire.COMPRESSION_NONE) for s in self.sessions}
        self.watches: list[wire.WatchSession] = []
        self.watch_times: list[float] = []     # time.monotonic() of each WatchSession
        self.subscriptions: list[bytes] = []
        self.published = 0
        self.opened: list[int] = []
        self.closed: list[int] = []
        self.poses: dict[int, list[tuple[float, wire.PoseRequest, wire.PoseReply]]] = {}
        self._ctx = zmq.Context()
        self.router = self._ctx.socket(zmq.ROUTER)
        self.router.setsockopt(zmq.LINGER, 0)
        self.router.bind("tcp://127.0.0.1:*")
        self.address = self.router.getsockopt_string(zmq.LAST_ENDPOINT)
        self.pose_router = self._ctx.socket(zmq.ROUTER)
        self.pose_router.setsockopt(zmq.LINGER, 0)
        self.pose_router.bind("tcp://127.0.0.1:*")
        self.pose_endpoint = self.pose_router.getsockopt_string(zmq.LAST_ENDPOINT)
        self._t0 = time.monotonic()
        self.xpub = self._ctx.socket(zmq.XPUB)
        self.xpub.setsockopt(zmq.LINGER, 0)
        self.xpub.setsockopt(zmq.SNDHWM, sndhwm)  # the server's "64 message parts"
        self.xpub.bind("tcp://127.0.0.1:*")
        self.stream_endpoint = self.xpub.getsockopt_string(zmq.LAST_ENDPOINT)
        self._gens: list[list[Any]] = []      # [wake_time, generator]
        self._stop = threading.Event()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> "FakeServer":
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join(10)
        self._ctx.destroy(linger=0)
        if self.error is not None and exc[0] is None:
            raise self.error

    # -- the thread -----------------------------------------------------------------------

    def _loop(self) -> None:
        poller = zmq.Poller()
        poller.register(self.router, zmq.POLLIN)
        poller.register(self.pose_router, zmq.POLLIN)
        poller.register(self.xpub, zmq.POLLIN)
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                wait = min([max(0.0, g[0] - now) for g in self._gens] + [0.02])
                events = dict(poller.poll(int(wait * 1000)))
                if self.router in events:
                    _drain(self.router.recv_multipart, self._control)
                if self.pose_router in events:
                    _drain(self.pose_router.recv_multipart, self._pose)
                if self.xpub in events:
                    _drain(self.xpub.recv, self._subscription)
                self._step()
        except BaseException as e:  # surfaced by __exit__
            self.error = e

    def _subscription(self, ev: bytes) -> None:
        """A subscribe event from the XPUB (first byte 1): the topic noted, its script started."""
        if ev[:1] == b"\x01":
            self.subscriptions.append(ev[1:])
            if self.script is not None:
                self._gens.append([0.0, self.script(self, ev[1:])])

    def _step(self) -> None:
        now = time.monotonic()
        for g in list(self._gens):
            if g[0] > now:
                continue
            while True:
                try:
                    item = next(g[1])
                except StopIteration:
                    self._gens.remove(g)
                    break
                if isinstance(item, (int, float)):
                    g[0] = time.monotonic() + item
                    break
                self.xpub.send_multipart(item)  # a PUB drops at its high-water mark, never blocks
                self.published += 1

    def _control(self, parts: list[bytes]) -> None:
        ident, payload = parts[0], parts[-1]
        req = wire.ControlRequest()
        req.ParseFromString(payload)
        rep = wire.ControlReply(schema_version=SCHEMA_VERSION, request_id=req.request_id)
        body = req.WhichOneof("body")
        if body == "info":
            self._info(rep.info)
        elif body == "open":
            sid = FIRST_OPENED_SID + len(self.opened)
            self.opened.append(sid)
            self.sessions.append(sid)
            self.views[sid] = wire.ViewSettings(**DEFAULT_VIEW)
            self.encoding[sid] = (wire.BRICK_INT16, wire.COMPRESSION_NONE)
            self.poses[sid] = []
            rep.open.session_id, rep.open.pose_endpoint = sid, self.pose_endpoint
            self._info(rep.open.server)
        elif body == "close":
            sid = req.close.session_id
            if sid not in self.sessions:
                rep.error.code = wire.ERROR_UNKNOWN_SESSION
                rep.error.message = f"CloseSession.session_id: no open session {sid:016x}"
            else:
                self.sessions.remove(sid)
                self.closed.append(sid)
                rep.close.session_id, rep.close.poses = sid, len(self.poses.get(sid, []))
        elif body == "stats" and req.stats.session_id in self.sessions:
            # a session's counters as far as a fake has them: its poses, the frames it
            # published, and a deformation that never steps
            sid = req.stats.session_id
            poses = self.poses.get(sid, [])
            ss = rep.stats.session
            ss.session_id, ss.poses = sid, len(poses)
            if poses:
                ss.last_seq = poses[-1][1].seq
            if "chainmail" in self.stages:
                ss.deform.steps = 0
                ss.deform.backend = "fake"
            ss.stream.frames_rendered = ss.stream.frames_published = self.published
            ss.stream.frames_watched = bool(self.watches)  # watched since its WatchSession
        elif body == "watch":
            self.watch_times.append(time.monotonic())
            self.watches.append(wire.WatchSession())
            self.watches[-1].CopyFrom(req.watch)
            self._watch(req.watch, rep)
        else:
            rep.error.code, rep.error.message = wire.ERROR_INTERNAL, f"fake: {body} not served"
        self.router.send_multipart([ident, *parts[1:-1], rep.SerializeToString()])

    def _info(self, info: wire.ServerInfo) -> None:
        info.scene_name = "fake"
        info.stream_endpoint = self.stream_endpoint
        info.control_endpoint = self.address
        info.pose_endpoint = self.pose_endpoint
        info.stages.extend(self.stages)

    def _pose(self, parts: list[bytes]) -> None:
        ident, payload = parts[0], parts[-1]
        req = wire.PoseRequest()
        req.ParseFromString(payload)
        rep = wire.PoseReply(schema_version=SCHEMA_VERSION, session_id=req.session_id,
                             seq=req.seq, client_time_s=req.client_time_s)
        if req.session_id not in self.sessions:
            rep.error.code = wire.ERROR_UNKNOWN_SESSION
            rep.error.message = f"PoseRequest.session_id: no open session {req.session_id:016x}"
        else:
            rep.proxy_mm.CopyFrom(req.tip_mm)
            rep.skin_point_mm.CopyFrom(req.tip_mm)
            if self.pose_model is not None:
                self.pose_model(req, rep)
            rep.server_time_s = time.monotonic() - self._t0
            self.poses.setdefault(req.session_id, []).append((time.monotonic(), req, rep))
        self.pose_router.send_multipart([ident, *parts[1:-1], rep.SerializeToString()])

    def _watch(self, w: wire.WatchSession, rep: wire.ControlReply) -> None:
        def refuse(code: int, msg: str) -> None:
            rep.error.code, rep.error.message = code, msg
        sid = w.session_id
        if sid == 0:
            if not self.sessions:
                return refuse(wire.ERROR_NO_SESSION_OPEN, "WatchSession.session_id = 0 (any): no "
                                                          "session is open")
            sid = self.sessions[-1]
        elif sid not in self.sessions:
            return refuse(wire.ERROR_UNKNOWN_SESSION, f"WatchSession.session_id: no open session "
                                                      f"{sid:016x}")
        if not (w.frames or w.bricks):
            return refuse(wire.ERROR_BAD_PARAMETER, "WatchSession: neither frames nor bricks asked")
        if w.frames and not self.frames_built:
            return refuse(wire.ERROR_NOT_BUILT, "WatchSession.frames: the scene does not ask for "
                                                "frames (effects.frames)")
        if w.bricks and not self.bricks_built:
            return refuse(wire.ERROR_NOT_BUILT, "WatchSession.bricks: the scene does not ask for "
                                                "bricks (effects.bricks)")
        bad = check_view(w.view)
        if bad:
            return refuse(wire.ERROR_BAD_VIEW, bad)
        self.views[sid].MergeFrom(w.view)
        if w.bricks:
            self.encoding[sid] = (w.brick_encoding, w.brick_compression)
        r = rep.watch
        r.session_id, r.stream_endpoint = sid, self.stream_endpoint
        r.frame_topic = frame_topic(sid) if w.frames else b""
        r.brick_topic = brick_topic(sid) if w.bricks else b""
        r.view.CopyFrom(self.views[sid])
        r.brick_encoding, r.brick_compression = self.encoding[sid]


# ---------------------------------------------------------------------------------------
# A real palpsim-server for end-to-end tests


def server_binary() -> Path | None:
    d = os.environ.get("PALPSIM_BUILD_DIR")
    p = Path(d) / "palpsim-server" if d else ROOT / "build" / "palpsim-server"
    return p if p.is_file() and os.access(p, os.X_OK) else None


def skip(reason: str) -> None:
    print(f"SKIPPED: {reason}")
    pytest.skip(reason)


def start_stream_server(tmp: Path, scene_text: str) -> Iterator[Any]:
    """A real palpsim-server on `scene_text`, or a skip with the reason when there is none,
    when it predates the stream path (it does not know the scene's new fields), when it
    cannot render here (EGL / OpenGL), or when its Info reply has no stream endpoint."""
    from palpsim.server import LocalServer, ServerStartError

    binary = server_binary()
    if binary is None:
        skip("no palpsim-server in $PALPSIM_BUILD_DIR="
             f"{os.environ.get('PALPSIM_BUILD_DIR', '(unset, looked in build/)')}")
    scene = tmp / "scene.textproto"
    scene.write_text(scene_text)
    srv = LocalServer(binary, scene=scene, startup_timeout_s=180, log_path=tmp / "server.log")
    try:
        srv.start()
    except ServerStartError as e:
        srv.stop()  # closes its log
        text = str(e)
        if re.search(r"(frames|bricks|render)\b.*(unknown|no field|not.*found)|"
                     r"(unknown|no field).*(frames|bricks|render)|EGL|OpenGL", text, re.I | re.S):
            last = (srv.tail().splitlines() or ["(no output)"])[-1]
            skip(f"{binary} does not serve this stream here (a build from before the stream "
                 f"path, or no OpenGL): {last}")
        raise
    try:
        with Client(srv.address) as c:
            info = c.info()
        if not info.stream_endpoint:
            skip(f"{binary}'s Info reply has an empty stream_endpoint (a server without the "
                 "stream path)")
        yield srv
    finally:
        status = srv.stop()
    assert status == 0, f"the server did not stop cleanly:\n{srv.tail()}"


def start_xvfb(timeout_s: float = 20.0) -> Iterator[str]:
    """An X display of its own: Xvfb (Debian's xvfb, which scripts/setup.sh installs) on
    a free display number with a 1280x800 24-bit screen; yields ":N". Skips with the
    reason where Xvfb is missing or does not start."""
    import select
    import shutil
    import subprocess

    exe = shutil.which("Xvfb")
    if exe is None:
        skip("no Xvfb on $PATH (Debian's xvfb package; scripts/setup.sh installs it)")
    r, w = os.pipe()
    proc = subprocess.Popen([exe, "-displayfd", str(w), "-screen", "0", "1280x800x24",
                             "-nolisten", "tcp", "-noreset"], pass_fds=(w,),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    os.close(w)
    try:
        # Xvfb writes the display number it took to -displayfd once it accepts clients
        number = b""
        deadline = time.monotonic() + timeout_s
        while not number.endswith(b"\n") and time.monotonic() < deadline:
            ready, _, _ = select.select([r], [], [], 0.1)
            if ready:
                chunk = os.read(r, 16)
                if not chunk:
                    break
                number += chunk
        if not number.strip().isdigit():
            proc.kill()
            err = proc.communicate(timeout=10)[1].decode(errors="replace").strip()
            skip(f"Xvfb did not start within {timeout_s:g} s: "
                 f"{(err.splitlines() or ['(no output)'])[-1]}")
        yield f":{number.strip().decode()}"
    finally:
        os.close(r)
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def summary_numbers(out: str) -> dict[str, float]:
    """The numbers of the summary line: received, shown, fps, missed, skipped, p50, p99."""
    m = re.search(r"(\d+) frames received, (\d+) shown, ([\d.na]+) fps, (\d+) missed, (\d+) skipped, "
                  r"pose-to-frame p50 ([\d.na]+) ms p99 ([\d.na]+) ms", out)
    assert m, f"no summary line in {out!r}"
    keys = ("received", "shown", "fps", "missed", "skipped", "p50", "p99")
    return {k: float(v) for k, v in zip(keys, m.groups())}
