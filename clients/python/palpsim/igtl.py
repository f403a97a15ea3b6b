"""palpsim-igtl: a bridge between a palpsim-server and 3D Slicer over OpenIGTLink
(pyigtl). Slicer's OpenIGTLinkIF connects to it (or, with --igtl-connect, it connects to a
server connector of Slicer) and receives:

- IMAGE `PalpsimVolume`: the deformed volume J rebuilt from the streamed bricks, with its
  IJK-to-RAS matrix (our space is LPS, Slicer's RAS: the first two axes flip);
- TRANSFORM `PalpsimTip` and `PalpsimProxy`: translations to the device tip x and the
  proxy p (RAS, mm);
- POINT `PalpsimSkinPoint`: the skin point X;
- STRING `PalpsimForce`: the force on the device, e.g.
  "force_n=1.234 fx=0.000 fy=-1.234 fz=0.000 depth_mm=8.50 contact=1" (RAS, N, mm).

    palpsim-igtl --connect tcp://127.0.0.1:7420                          # palpate from Slicer
    palpsim-igtl --connect ADDR --client-token station1 --any            # watch a haptic client
    palpsim-igtl --connect ADDR --igtl-connect 192.168.1.20:18944        # Slicer is the server

Without --session / --any the bridge opens a session of its own and palpates it: a
TRANSFORM named `PalpsimDevice` (--pose-name) from Slicer is the device pose (its
translation, RAS mm, is the tip), sent to the server --rate times a second (the newest
one each time; until the first one, the tip waits behind the body's back), and each
pose's reply goes back to Slicer as the tip, proxy, skin point and force. With --session
or --any it watches another client's session (its key or --client-token, as
palpsim-view): the tip and proxy come from the stream (its frames, else its VOI bricks:
at most render.max_fps a second), the stream carries no skin point or force, and poses
from Slicer are not sent (docs/slicer.md says why). Images go at most --image-hz times a
second, each time the volume changed.

Exit status: 0 on Ctrl-C, SIGTERM or the end of the watched session; 1 when the server
did not answer, a stream message was malformed or the OpenIGTLink port could not be
opened; 2 for a bad command line and the server's refusals.
"""

from __future__ import annotations

import argparse
import math
import re
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from . import keys
from .client import Client, PalpsimError, PoseReply, ServerError, ServerTimeout, Session
from .proto import wire
from .stream import (DeformedVolume, Grid, MalformedMessage, SessionClosed, StreamClient,
                     StreamError, UnknownSession)
from .view import DEFAULT_CONTROL_TIMEOUT_S, add_watch_arguments, positive_number

PROG = "palpsim-igtl"
DEFAULT_PORT = 18944          # OpenIGTLink's own port
DEFAULT_RATE_HZ = 200.0       # poses, transforms, points and strings a second (own session)
DEFAULT_IMAGE_HZ = 10.0       # most images a second

# the device names Slicer's nodes take
VOLUME = "PalpsimVolume"
TIP = "PalpsimTip"
PROXY = "PalpsimProxy"
SKIN_POINT = "PalpsimSkinPoint"
FORCE = "PalpsimForce"
POSE = "PalpsimDevice"

# a message that takes longer than this to go out drops the connection (s): 41 MB (the
# 1 mm phantom's image) needs 1.4 MB/s; the bridge itself never waits for Slicer
# (pyigtl sends on its own thread)
SEND_TIMEOUT_S = 30.0

# where the tip waits until Slicer sends a pose: this far behind the body's back (+y, LPS)
PARK_MM = 20.0

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2

# LPS <-> RAS: x and y change sign (the same map both ways)
FLIP = np.diag([-1.0, -1.0, 1.0])


def _say(text: str) -> None:
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------
# Geometry


def flip_lps_ras(point_mm: Sequence[float]) -> np.ndarray:
    """A point (mm) from LPS to RAS, or from RAS to LPS: x and y change sign."""
    return FLIP @ np.asarray(point_mm, dtype=float)


def ijk_to_ras(grid: Grid) -> np.ndarray:
    """The 4x4 matrix from a voxel index (i, j, k) of the patient grid to RAS mm: the
    grid's LPS matrix (direction times spacing, origin) with its first two rows negated."""
    m = np.eye(4)
    m[:3, :3] = FLIP @ grid.matrix
    m[:3, 3] = flip_lps_ras(grid.origin_mm)
    return m


def translation(point_lps_mm: Sequence[float]) -> np.ndarray:
    """A 4x4 RAS transform that moves the origin to an LPS point (mm)."""
    m = np.eye(4)
    m[:3, 3] = flip_lps_ras(point_lps_mm)
    return m


def pose_of(matrix: Any) -> np.ndarray | None:
    """The tip (LPS mm) a TRANSFORM from Slicer puts the device at: its translation,
    converted from RAS; None for a matrix that is not 4x4 or holds a NaN or Inf."""
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        return None
    return flip_lps_ras(m[:3, 3])


def park_point(patient: "wire.PatientInfo") -> np.ndarray:
    """Where the tip waits before Slicer's first pose (LPS mm): the middle of the body's
    bounding box in x and z, PARK_MM behind its back (+y)."""
    lo, hi = patient.body_min_mm, patient.body_max_mm
    return np.array([(lo.x + hi.x) / 2, hi.y + PARK_MM, (lo.z + hi.z) / 2])


def force_text(reply: PoseReply) -> str:
    """The STRING sent as PalpsimForce: magnitude and RAS components (N), depth (mm), contact."""
    f = flip_lps_ras(reply.force_n)
    return (f"force_n={float(np.linalg.norm(f)):.3f} fx={f[0]:.3f} fy={f[1]:.3f} fz={f[2]:.3f} "
            f"depth_mm={reply.depth_mm:.2f} contact={int(reply.contact)}")


# ---------------------------------------------------------------------------------------
# Messages to Slicer


@dataclass
class Counts:
    """What the bridge sent and received, for the summary line."""

    poses: int = 0                # poses answered by the server
    poses_refused: int = 0
    slicer_poses: int = 0         # TRANSFORMs named --pose-name taken from Slicer
    transforms: int = 0           # tip and proxy TRANSFORMs sent
    images: int = 0
    started_s: float = field(default_factory=time.monotonic)


class Outlet:
    """Sends to Slicer through a pyigtl server or client; messages are queued only while
    Slicer is connected (pyigtl keeps the newest 100 and drops older ones, so a slow
    Slicer never holds the bridge up). Safe to use from two threads (pyigtl locks)."""

    def __init__(self, igtl: Any, counts: Counts):
        self.igtl, self.counts = igtl, counts

    @property
    def connected(self) -> bool:
        return bool(self.igtl.is_connected())

    @property
    def connection(self) -> int:
        """Which connection this is: serving, it grows by one with each Slicer that
        connects (a reconnection can come faster than `connected` is looked at); as a
        client of Slicer's server connector, 0."""
        return int(getattr(self.igtl, "connections", 0))

    def send(self, message: Any) -> bool:
        if not self.connected:
            return False
        return bool(self.igtl.send_message(message, wait=False))

    def tip_and_proxy(self, tip_mm: Sequence[float], proxy_mm: Sequence[float]) -> None:
        import pyigtl

        now = time.time()
        for name, p in ((TIP, tip_mm), (PROXY, proxy_mm)):
            if self.send(pyigtl.TransformMessage(translation(p), timestamp=now, device_name=name)):
                self.counts.transforms += 1

    def pose_reply(self, tip_mm: Sequence[float], r: PoseReply) -> None:
        import pyigtl

        self.tip_and_proxy(tip_mm, r.proxy_mm)
        now = time.time()
        self.send(pyigtl.PointMessage(positions=[flip_lps_ras(r.skin_point_mm)], names=["X"],
                                      rgba_colors=[255, 64, 64, 255], diameters=[3.0],
                                      timestamp=now, device_name=SKIN_POINT))
        self.send(pyigtl.StringMessage(force_text(r), timestamp=now, device_name=FORCE))

    def image(self, volume: DeformedVolume, encoding: str) -> bool:
        import pyigtl

        assert volume.grid is not None and volume.volume is not None
        values = volume.volume.astype(np.int16 if encoding == "int16" else np.float32)
        msg = pyigtl.ImageMessage(values, ijk_to_world_matrix=ijk_to_ras(volume.grid),
                                  world_coordinate_system="ras", device_name=VOLUME)
        if self.send(msg):
            self.counts.images += 1
            return True
        return False


# ---------------------------------------------------------------------------------------
# The stream: the volume (and, watching another client's session, the tip and proxy)


class StreamWorker(threading.Thread):
    """Receives the watched session's stream on a thread of its own, rebuilds J and sends
    it as an image when it changed (at most `image_hz` a second, and again to a Slicer
    that connects); with `watch_pose` also the tip and proxy of its frames and VOI bricks.
    A stream error or the session's end is kept in `error` and sets `done`."""

    def __init__(self, reply: "wire.WatchReply", control_address: str, client: Client,
                 outlet: Outlet, image_hz: float, encoding: str, watch_pose: bool,
                 done: threading.Event):
        super().__init__(name="palpsim-igtl-stream", daemon=True)
        self.stream = StreamClient.from_watch(reply, control_address, curve=client.curve)
        self.outlet, self.image_period_s = outlet, 1.0 / image_hz
        self.encoding, self.watch_pose, self.done = encoding, watch_pose, done
        self.volume = DeformedVolume()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._loop()
        except BaseException as e:  # handed to the main thread, which reports it
            self.error = e
        finally:
            self.stream.close()
            self.done.set()

    def _loop(self) -> None:
        changed, was_connected, last_connection, last_image_s = False, False, 0, -math.inf
        pose: tuple[np.ndarray, np.ndarray] | None = None   # the newest tip and proxy seen
        while not self.done.is_set():
            update = self.stream.receive(0.02)
            for b in (update.bricks if update else []):
                self.volume.apply(b)
                changed = True
                if self.watch_pose and not b.key and b.deformed:
                    pose = (_xyz(b.tip_mm), _xyz(b.proxy_mm))
                    self.outlet.tip_and_proxy(*pose)
            if update is not None and update.frame is not None and self.watch_pose:
                f = update.frame
                if f.pose_seq:
                    pose = (_xyz(f.tip_mm), _xyz(f.proxy_mm))
                    self.outlet.tip_and_proxy(*pose)
            connected, connection = self.outlet.connected, self.outlet.connection
            if connected and (not was_connected or connection != last_connection):
                # a Slicer that just connected gets the volume and the newest tip at once
                changed = True
                if pose is not None:
                    self.outlet.tip_and_proxy(*pose)
            was_connected, last_connection = connected, connection
            now = time.monotonic()
            if (changed and self.volume.complete and connected
                    and now - last_image_s >= self.image_period_s):
                if self.outlet.image(self.volume, self.encoding):
                    changed, last_image_s = False, now


def _xyz(v: "wire.Vec3") -> np.ndarray:
    return np.array((v.x, v.y, v.z), dtype=float)


# ---------------------------------------------------------------------------------------
# The pose loop (the bridge's own session)


def pose_loop(session: Session, igtl: Any, outlet: Outlet, counts: Counts, rate_hz: float,
              pose_name: str, park_mm: np.ndarray, done: threading.Event) -> None:
    """Sends the newest pose from Slicer (or the park point) to the server `rate_hz` times a
    second and each reply to Slicer, until `done` is set. A refused pose is reported once
    per error code and the loop goes on; a server that stops answering ends it with
    ServerTimeout."""
    period_s = 1.0 / rate_hz
    tip = np.asarray(park_mm, dtype=float)
    refused: int | None = None
    bad_warned = False
    t0 = next_s = time.monotonic()
    while not done.is_set():
        # the newest pose Slicer sent (pyigtl keeps the newest per device name)
        for msg in igtl.get_latest_messages():
            if msg.device_name != pose_name or getattr(msg, "_message_type", "") != "TRANSFORM":
                continue
            p = pose_of(msg.matrix)
            if p is None:
                if not bad_warned:
                    _say(f"TRANSFORM {pose_name}: not a finite 4x4 matrix; ignored")
                    bad_warned = True
                continue
            tip = p
            counts.slicer_poses += 1
        try:
            r = session.pose(tip, client_time_s=time.monotonic() - t0)
        except ServerError as e:
            counts.poses_refused += 1
            if e.code != refused:
                _say(f"pose at ({tip[0]:.1f}, {tip[1]:.1f}, {tip[2]:.1f}) mm LPS refused: "
                     f"{e.code_name}: {e.message}")
                refused = e.code
        else:
            counts.poses += 1
            refused = None
            outlet.pose_reply(tip, r)
        # pace on a fixed schedule; after a stall (a slow reply), start again from now
        next_s += period_s
        wait_s = next_s - time.monotonic()
        if wait_s > 0:
            done.wait(wait_s)
        elif wait_s < -period_s:
            next_s = time.monotonic()


# ---------------------------------------------------------------------------------------
# Command line


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 < v < 65536:
        raise argparse.ArgumentTypeError(f"{text!r}: a port is 1..65535")
    return v


def _igtl_address(text: str) -> tuple[str, int]:
    """HOST or HOST:PORT of an OpenIGTLink server (port 18944 by default)."""
    m = re.fullmatch(r"\s*\[?([^\]\s]*?)\]?(?::(\d+))?\s*", text)
    if not m or not m.group(1):
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST or HOST:PORT")
    return m.group(1), _port(m.group(2)) if m.group(2) else DEFAULT_PORT


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Bridge a palpsim-server session to 3D Slicer over OpenIGTLink: the "
                    "deformed volume (IMAGE), the tip and proxy (TRANSFORM), the skin point "
                    "(POINT) and the force (STRING); a TRANSFORM from Slicer is the device pose.",
        epilog="Without --session / --any the bridge opens a session of its own and palpates "
               "it from Slicer. Exit status: 0 done (Ctrl-C, SIGTERM, the session ended), "
               "1 no answer / malformed message / port not opened, 2 bad command line or "
               "refused by the server. Slicer's side: docs/slicer.md.")
    add_watch_arguments(p, any_help="watch the newest open session of this client (its key or "
                                    "--client-token) instead of palpating a session of its own")
    g = p.add_argument_group("OpenIGTLink")
    g.add_argument("--port", metavar="P", type=_port, default=DEFAULT_PORT,
                   help="serve OpenIGTLink on 127.0.0.1:P (default %(default)s)")
    g.add_argument("--igtl-connect", metavar="HOST[:PORT]", type=_igtl_address,
                   help="connect to an OpenIGTLink server (a server connector in Slicer) "
                        "instead of serving")
    g.add_argument("--pose-name", metavar="NAME", default=POSE,
                   help="device name of the TRANSFORM from Slicer that moves the tip "
                        "(default %(default)s)")
    g.add_argument("--rate", metavar="HZ", type=positive_number("poses a second"),
                   default=DEFAULT_RATE_HZ,
                   help="poses sent and transforms, points and strings returned a second, "
                        "own session (default %(default)g)")
    g.add_argument("--image-hz", metavar="HZ", type=positive_number("images a second"),
                   default=DEFAULT_IMAGE_HZ,
                   help="most images a second: one each time the volume changed "
                        "(default %(default)g)")
    g.add_argument("--encoding", choices=("int16", "float32"), default="int16",
                   help="brick and image values: int16 HU or float32 (default %(default)s)")
    g.add_argument("--zstd", action="store_true", help="zstd-compressed bricks")
    g.add_argument("--timeout", metavar="S", type=positive_number("seconds"),
                   default=DEFAULT_CONTROL_TIMEOUT_S,
                   help="seconds to wait for the server's replies (default %(default)g)")
    return p


class _Connection:
    """Mixin for pyigtl's server and client. Each message may take SEND_TIMEOUT_S to go
    out: pyigtl polls its socket with a 10 ms timeout, and Python applies a socket's
    timeout to a whole sendall, so without this an image of a few MB (which takes longer
    than 10 ms to go out) fails and drops the connection. And a Slicer that closed the
    connection is noticed on the receiving side: pyigtl reads the end of the stream as
    "nothing yet" and would notice only when a send fails, so with nothing to send (a
    quiet watched session) its server would spin on the dead socket and never take the
    next Slicer."""

    def _receive_message_from_socket(self, sock: Any) -> bool:
        import socket

        try:
            if not sock.recv(1, socket.MSG_PEEK):
                raise ConnectionResetError("Slicer closed the OpenIGTLink connection")
        except socket.timeout:
            return False  # nothing came within pyigtl's poll
        return super()._receive_message_from_socket(sock)  # type: ignore[misc]

    def _send_queued_message_from_socket(self, sock: Any) -> bool:
        poll_s = sock.gettimeout()
        sock.settimeout(SEND_TIMEOUT_S)
        try:
            return super()._send_queued_message_from_socket(sock)  # type: ignore[misc]
        finally:
            sock.settimeout(poll_s)


def open_igtl(args: argparse.Namespace) -> tuple[Any, str]:
    """The pyigtl server (or client, --igtl-connect) and where it is, as words."""
    import pyigtl

    if args.igtl_connect:
        class IgtlClient(_Connection, pyigtl.OpenIGTLinkClient):
            pass

        host, port = args.igtl_connect
        return IgtlClient(host=host, port=port), f"connecting to {host}:{port}"

    class IgtlServer(_Connection, pyigtl.OpenIGTLinkServer):
        """pyigtl's server (one Slicer at a time) that counts the connections it took."""

        connections = 0

        def process_request(self, request: Any, client_address: Any) -> None:
            self.connections += 1
            super().process_request(request, client_address)

    server = IgtlServer(port=args.port, local_server=True)
    host, port = server.server_address[:2]
    return server, f"serving OpenIGTLink on {host}:{port}"


def close_igtl(igtl: Any) -> None:
    igtl.stop()


class _Stop(Exception):
    """SIGTERM: stop as on Ctrl-C."""


# set by SIGTERM's handler before it raises _Stop: a library that catches every exception
# (pyigtl's message constructors turn any into ValueError) may hand the stop on as its own
# error, which is then still the stop (_stopped)
_STOPPING = threading.Event()


def _stopped(e: BaseException) -> bool:
    """Whether exception `e` ends the bridge as Ctrl-C or SIGTERM does: KeyboardInterrupt,
    _Stop, or any error raised while a SIGTERM is being handled."""
    return isinstance(e, (KeyboardInterrupt, _Stop)) or _STOPPING.is_set()


def main(argv: Sequence[str] | None = None) -> int:
    """palpsim-igtl's entry point; returns the exit status (module docstring)."""
    args = build_parser().parse_args(argv)
    try:
        curve = keys.from_arguments(args)
    except (keys.KeyFileError, RuntimeError) as e:
        _say(str(e))
        return EXIT_USAGE
    # SIGTERM ends the bridge as Ctrl-C does (pyigtl's server hands the signal on to us)
    previous_term = None
    _STOPPING.clear()
    if threading.current_thread() is threading.main_thread():
        def on_term(*_: Any) -> None:
            _STOPPING.set()
            raise _Stop()
        previous_term = signal.signal(signal.SIGTERM, on_term)
    try:
        with Client(args.connect, timeout_s=args.timeout, name=PROG, curve=curve,
                    client_token=args.client_token) as client:
            return _bridge(args, client)
    except BaseException as e:
        if not _stopped(e):
            raise
        return EXIT_OK
    finally:
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)


def _bridge(args: argparse.Namespace, client: Client) -> int:
    own = args.session is None and not args.any
    session: Session | None = None
    try:
        if own:
            session = client.open_session(PROG)
        reply = _watch(client, session.id if session else (args.session or 0), args,
                       frames=not own)
    except ServerError as e:
        _say(f"{e.code_name}: {e.message}")
        return EXIT_USAGE
    except PalpsimError as e:  # ServerTimeout, a reply that does not parse
        _say(str(e))
        return EXIT_FAIL
    if not reply.stream_endpoint:
        _say("the server's WatchReply has no stream_endpoint (the scene asks for no bricks?)")
        return EXIT_FAIL
    try:
        igtl, where = open_igtl(args)
    except OSError as e:
        _say(f"cannot open OpenIGTLink port {args.port}: {e}")
        return EXIT_FAIL
    counts = Counts()
    outlet = Outlet(igtl, counts)
    done = threading.Event()
    worker = StreamWorker(reply, client.address, client, outlet, args.image_hz, args.encoding,
                          watch_pose=not own, done=done)
    what = (f"palpating its own session {reply.session_id:016x} from TRANSFORM {args.pose_name}"
            if own else f"watching session {reply.session_id:016x}")
    print(f"{PROG}: {where}; {what}", flush=True)
    status = EXIT_OK
    worker.start()
    try:
        if own:
            assert session is not None
            pose_loop(session, igtl, outlet, counts, args.rate, args.pose_name,
                      park_point(session.server_info.patient), done)
        else:
            while not done.wait(0.1):
                pass
    except ServerTimeout as e:
        if not _stopped(e):
            _say(str(e))
            status = EXIT_FAIL
    except BaseException as e:
        if not _stopped(e):
            raise
    finally:
        done.set()
        worker.join(5)
        close_igtl(igtl)
    status = max(status, _stream_status(worker.error))
    print(summary_line(counts, worker.volume), flush=True)
    return status


def _watch(client: Client, session_id: int, args: argparse.Namespace,
           frames: bool) -> "wire.WatchReply":
    """Watches the session's bricks and, with `frames` (another client's session), its
    frames too: their tip and proxy move with every pose shown, while VOI bricks come only
    while it deforms. A scene that renders no frames keeps the bricks alone."""
    compression = "zstd" if args.zstd else "none"
    try:
        return client.watch(session_id=session_id, frames=frames, bricks=True,
                            brick_encoding=args.encoding, compression=compression)
    except ServerError as e:
        if not frames or e.code != wire.ERROR_NOT_BUILT:
            raise
        _say(f"no frames ({e.message}): the tip and proxy follow the VOI bricks only")
    return client.watch(session_id=session_id, frames=False, bricks=True,
                        brick_encoding=args.encoding, compression=compression)


def _stream_status(error: BaseException | None) -> int:
    """The exit status for what ended the stream thread, reported in one line."""
    if error is None:
        return EXIT_OK
    if isinstance(error, SessionClosed):
        _say(f"session ended: {error.message or error}")
        return EXIT_OK
    if isinstance(error, UnknownSession):
        _say(f"ERROR_UNKNOWN_SESSION: {error.message or error}")
        return EXIT_USAGE
    if isinstance(error, MalformedMessage):
        _say(f"malformed stream message: {error}")
        return EXIT_FAIL
    if isinstance(error, StreamError):
        _say(str(error))
        return EXIT_FAIL
    _say(f"stream thread failed: {type(error).__name__}: {error}")
    return EXIT_FAIL


def summary_line(counts: Counts, volume: DeformedVolume) -> str:
    """One line: poses (answered, refused, from Slicer), transforms and images with their
    rates over the run, and the volume's size."""
    span_s = max(time.monotonic() - counts.started_s, 1e-9)
    grid = "no volume"
    if volume.grid is not None:
        i, j, k = volume.grid.size
        grid = f"volume {i}x{j}x{k}{'' if volume.complete else ' (incomplete)'}"
    return (f"{PROG}: {counts.poses} poses answered ({counts.poses_refused} refused, "
            f"{counts.slicer_poses} from Slicer), {counts.transforms} transforms "
            f"({counts.transforms / 2 / span_s:.1f} Hz per node), {counts.images} images "
            f"({counts.images / span_s:.2f} Hz) in {span_s:.1f} s; {grid}")


if __name__ == "__main__":
    sys.exit(main())
