"""Viewer side of the server's stream path (PROTOCOL.md, "Frames and bricks"): connects
SUB sockets to the XPUB endpoint a WatchReply names, receives two-frame messages
[topic, StreamMessage] newest-wins, decodes frames (JPEG into an RGB array) and bricks
(int16 HU or float32, optionally zstd), rebuilds the deformed volume J from the
whole-volume key and the newest VOI brick, and keeps the statistics a viewer reports.

    with Client(addr) as c:
        reply = c.watch(frames=True, bricks=True)
        with StreamClient.from_watch(reply, c.address) as sc:
            volume = DeformedVolume()
            while True:
                update = sc.receive(timeout_s=5.0)   # None: nothing came within 5 s
                if update is None:
                    continue
                if update.frame is not None:
                    rgb = decode_frame(update.frame)  # (height, width, 3) uint8
                for brick in update.bricks:
                    volume.apply(brick)
                # a "closed" notice raises SessionClosed, "unknown_session" UnknownSession

Nothing here needs a display; palpsim-view (view.py) is built on it. Units: mm, ms;
points in the patient's physical space (LPS).
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import zmq

from .client import PalpsimError, resolve_endpoint
from .keys import CurveKeys
from .proto import SCHEMA_VERSION, wire

FRAME_TOPIC_PREFIX = b"frame."
BRICK_TOPIC_PREFIX = b"brick."

# Receive queue lengths (messages) of the two SUB sockets. Frames: a short queue, so a
# slow viewer's backlog stays small and what it drains is recent (ZeroMQ drops what
# arrives at a full queue). Bricks: long enough for a whole key (at most 16 slabs) and
# some VOI bricks behind it, so no key part is dropped while the viewer is busy.
FRAME_RCVHWM = 8
BRICK_RCVHWM = 256

# most messages one receive() drains per socket before it hands over what it has (a
# bound, so a publisher faster than the drain cannot keep receive() from returning)
MAX_DRAIN = 1000


class StreamError(PalpsimError):
    """Base of the errors about the stream path."""


class MalformedMessage(StreamError):
    """A stream message that breaks the protocol; the text names the message and field."""


class SessionClosed(StreamError):
    """The watched session closed or timed out (notice "closed"): a viewer's normal end."""

    def __init__(self, session_id: int, message: str):
        self.session_id, self.message = session_id, message
        super().__init__(message or f"session {session_id:016x} closed")


class UnknownSession(StreamError):
    """The topic names no open session (notice "unknown_session", ERROR_UNKNOWN_SESSION)."""

    def __init__(self, session_id: int, message: str, code: int = wire.ERROR_UNKNOWN_SESSION):
        self.session_id, self.message, self.code = session_id, message, code
        super().__init__(message or f"session {session_id:016x} is not open")


def frame_topic(session_id: int) -> bytes:
    """The frame topic of a session: b"frame." + 16 lowercase hex digits."""
    return FRAME_TOPIC_PREFIX + f"{session_id:016x}".encode()


def brick_topic(session_id: int) -> bytes:
    """The brick topic of a session: b"brick." + 16 lowercase hex digits."""
    return BRICK_TOPIC_PREFIX + f"{session_id:016x}".encode()


# ---------------------------------------------------------------------------------------
# Messages


def parse_message(parts: Sequence[bytes]) -> tuple[bytes, "wire.StreamMessage"]:
    """Checks and parses one stream message: exactly two frames, the topic and a
    StreamMessage of this schema version with a body. Raises MalformedMessage."""
    if len(parts) != 2:
        raise MalformedMessage(f"stream message: {len(parts)} ZeroMQ frames, expected 2 "
                               "(topic, StreamMessage)")
    topic, payload = bytes(parts[0]), parts[1]
    msg = wire.StreamMessage()
    try:
        msg.ParseFromString(bytes(payload))
    except Exception as e:  # protobuf's DecodeError
        raise MalformedMessage(f"StreamMessage on topic {topic!r}: does not parse ({e})") from None
    if msg.schema_version != SCHEMA_VERSION:
        raise MalformedMessage(f"StreamMessage.schema_version = {msg.schema_version} on topic "
                               f"{topic!r}, expected {SCHEMA_VERSION}")
    body = msg.WhichOneof("body")
    if body is None:
        raise MalformedMessage(f"StreamMessage.body on topic {topic!r}: none of frame, brick, "
                               "notice is set")
    if body == "frame" and not topic.startswith(FRAME_TOPIC_PREFIX):
        raise MalformedMessage(f"StreamMessage.frame on topic {topic!r}, expected a "
                               f"{FRAME_TOPIC_PREFIX.decode()} topic")
    if body == "brick" and not topic.startswith(BRICK_TOPIC_PREFIX):
        raise MalformedMessage(f"StreamMessage.brick on topic {topic!r}, expected a "
                               f"{BRICK_TOPIC_PREFIX.decode()} topic")
    return topic, msg


def decode_frame(frame: "wire.Frame") -> np.ndarray:
    """The frame's JPEG as an RGB array of shape (height, width, 3), uint8; checks that
    the image has the size the frame states. Raises MalformedMessage."""
    from PIL import Image, UnidentifiedImageError

    if not frame.jpeg:
        raise MalformedMessage(f"Frame.jpeg of frame_seq {frame.frame_seq}: empty")
    try:
        with Image.open(io.BytesIO(frame.jpeg)) as img:
            if img.format != "JPEG":
                raise MalformedMessage(f"Frame.jpeg of frame_seq {frame.frame_seq}: a {img.format} "
                                       "image, expected JPEG")
            rgb = np.asarray(img.convert("RGB"))
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise MalformedMessage(f"Frame.jpeg of frame_seq {frame.frame_seq}: not a readable JPEG "
                               f"({e})") from None
    h, w = rgb.shape[:2]
    if (w, h) != (frame.width, frame.height):
        raise MalformedMessage(f"Frame.width x height = {frame.width}x{frame.height} of frame_seq "
                               f"{frame.frame_seq}, but its JPEG is {w}x{h}")
    return rgb


_ITEMSIZE = {wire.BRICK_INT16: 2, wire.BRICK_FLOAT32: 4}
_DTYPE = {wire.BRICK_INT16: np.dtype("<i2"), wire.BRICK_FLOAT32: np.dtype("<f4")}


def check_brick(brick: "wire.Brick") -> None:
    """Checks a brick's geometry: encoding, compression, a box inside the grid, a 3x3
    direction, a positive spacing, key part numbers, and the box origin against the grid
    origin. Raises MalformedMessage naming the field."""
    b = brick
    where = f"brick_seq {b.brick_seq}"
    if b.encoding not in _ITEMSIZE:
        raise MalformedMessage(f"Brick.encoding = {b.encoding} of {where}: expected BRICK_INT16 "
                               "or BRICK_FLOAT32")
    if b.compression not in (wire.COMPRESSION_NONE, wire.COMPRESSION_ZSTD):
        raise MalformedMessage(f"Brick.compression = {b.compression} of {where}: expected "
                               "COMPRESSION_NONE or COMPRESSION_ZSTD")
    grid = (b.grid_size_i, b.grid_size_j, b.grid_size_k)
    if min(grid) == 0:
        raise MalformedMessage(f"Brick.grid_size_i/j/k = {grid} of {where}: an empty grid")
    for axis, lo, size, n in zip("ijk", (b.lo_i, b.lo_j, b.lo_k), (b.size_i, b.size_j, b.size_k),
                                 grid):
        if lo + size > n:
            raise MalformedMessage(f"Brick.lo_{axis} + size_{axis} = {lo} + {size} of {where} is "
                                   f"past grid_size_{axis} = {n}")
    if not (math.isfinite(b.spacing_mm) and b.spacing_mm > 0):
        raise MalformedMessage(f"Brick.spacing_mm = {b.spacing_mm} of {where}: expected > 0")
    if len(b.direction) != 9 or not all(math.isfinite(d) for d in b.direction):
        raise MalformedMessage(f"Brick.direction of {where}: {len(b.direction)} values, expected "
                               "9 finite ones (3x3 row-major)")
    if b.key:
        if b.key_parts == 0 or b.key_part >= b.key_parts:
            raise MalformedMessage(f"Brick.key_part = {b.key_part} of {where}: expected "
                                   f"0..key_parts-1 (key_parts = {b.key_parts})")
        if (b.lo_i, b.lo_j, b.size_i, b.size_j) != (0, 0, grid[0], grid[1]) or b.size_k == 0:
            raise MalformedMessage(f"Brick.lo/size of key part {b.key_part} ({where}): a key part "
                                   "is a slab of whole k-slices, got "
                                   f"lo ({b.lo_i}, {b.lo_j}, {b.lo_k}) size ({b.size_i}, "
                                   f"{b.size_j}, {b.size_k}) on grid {grid}")
    elif b.deformed and b.size_i * b.size_j * b.size_k == 0:
        raise MalformedMessage(f"Brick.size_i/j/k of {where}: a deformed VOI brick with an "
                               "empty box")
    n = b.size_i * b.size_j * b.size_k
    if n:
        # the box's first voxel in physical space, from the grid (0.001 mm: far below a
        # voxel, far above rounding)
        d = np.asarray(b.direction, dtype=float).reshape(3, 3)
        want = (np.array([b.grid_origin_mm.x, b.grid_origin_mm.y, b.grid_origin_mm.z])
                + d @ (np.array([b.lo_i, b.lo_j, b.lo_k], dtype=float) * b.spacing_mm))
        got = np.array([b.origin_mm.x, b.origin_mm.y, b.origin_mm.z])
        if not np.allclose(got, want, rtol=0, atol=1e-3):
            raise MalformedMessage(f"Brick.origin_mm = {tuple(got)} of {where}: the grid puts voxel "
                                   f"({b.lo_i}, {b.lo_j}, {b.lo_k}) at {tuple(want)}")


def decode_brick(brick: "wire.Brick") -> np.ndarray:
    """The brick's values as an array of shape (size_k, size_j, size_i) (i fastest, as on
    the wire), int16 (HU) or float32, zstd decompressed where compressed. Checks the
    brick (check_brick) and its data size. Raises MalformedMessage naming the field."""
    check_brick(brick)
    b = brick
    where = f"brick_seq {b.brick_seq}"
    n = b.size_i * b.size_j * b.size_k
    want = n * _ITEMSIZE[b.encoding]
    data = b.data
    if b.compression == wire.COMPRESSION_ZSTD:
        if b.raw_bytes != want:
            raise MalformedMessage(f"Brick.raw_bytes = {b.raw_bytes} of {where}: expected "
                                   f"size_i*size_j*size_k*{_ITEMSIZE[b.encoding]} = {want}")
        if n == 0:
            data = b""
        else:
            import zstandard

            try:
                data = zstandard.ZstdDecompressor().decompress(data, max_output_size=want)
            except zstandard.ZstdError as e:
                raise MalformedMessage(f"Brick.data of {where}: zstd does not decompress it "
                                       f"({e})") from None
    elif b.raw_bytes not in (0, want):
        raise MalformedMessage(f"Brick.raw_bytes = {b.raw_bytes} of {where}: expected {want} "
                               "(or 0) for uncompressed data")
    if len(data) != want:
        raise MalformedMessage(f"Brick.data of {where}: {len(data)} bytes"
                               f"{' after zstd' if b.compression == wire.COMPRESSION_ZSTD else ''}, "
                               f"expected size_i*size_j*size_k*{_ITEMSIZE[b.encoding]} = {want}")
    values = np.frombuffer(data, dtype=_DTYPE[b.encoding])
    return values.reshape(b.size_k, b.size_j, b.size_i).astype(values.dtype.newbyteorder("="))


# ---------------------------------------------------------------------------------------
# The deformed volume


@dataclass(frozen=True)
class Grid:
    """The patient grid of a brick: voxels per axis, isotropic spacing, the physical point
    of voxel (0, 0, 0) and the 3x3 direction (columns are the grid axes), LPS mm."""

    size: tuple[int, int, int]          # (i, j, k) voxels
    spacing_mm: float
    origin_mm: tuple[float, float, float]
    direction: tuple[float, ...]        # 9 values, row-major

    @staticmethod
    def of(brick: "wire.Brick") -> "Grid":
        o = brick.grid_origin_mm
        return Grid((brick.grid_size_i, brick.grid_size_j, brick.grid_size_k), brick.spacing_mm,
                    (o.x, o.y, o.z), tuple(brick.direction))

    @property
    def matrix(self) -> np.ndarray:
        """Index (i, j, k) -> mm: origin + direction @ (index * spacing)."""
        return np.asarray(self.direction, dtype=float).reshape(3, 3) * self.spacing_mm

    def index_to_mm(self, ijk: Sequence[float]) -> np.ndarray:
        """The physical point (mm) of a (continuous) voxel index (i, j, k)."""
        return np.asarray(self.origin_mm) + self.matrix @ np.asarray(ijk, dtype=float)

    def mm_to_index(self, point_mm: Sequence[float]) -> np.ndarray:
        """The continuous voxel index (i, j, k) of a physical point (mm)."""
        return np.linalg.solve(self.matrix, np.asarray(point_mm, dtype=float)
                               - np.asarray(self.origin_mm))

    def same_as(self, other: "Grid") -> bool:
        return (self.size == other.size and math.isclose(self.spacing_mm, other.spacing_mm)
                and np.allclose(self.origin_mm, other.origin_mm, atol=1e-6)
                and np.allclose(self.direction, other.direction, atol=1e-9))

    @property
    def center_mm(self) -> np.ndarray:
        return self.index_to_mm([(n - 1) / 2 for n in self.size])


@dataclass
class Slices:
    """Three slices of J through one voxel: axial (k fixed, array [j, i]), coronal
    (j fixed, [k, i]) and sagittal (i fixed, [k, j]) of the patient grid."""

    index: tuple[int, int, int]   # the voxel (i, j, k) they pass through
    point_mm: np.ndarray          # its physical point
    axial: np.ndarray
    coronal: np.ndarray
    sagittal: np.ndarray


class DeformedVolume:
    """The deformed image J of one session rebuilt from bricks: the whole-volume key (the
    undeformed image I, in slabs along k) with the newest VOI brick written over it.

    apply() takes bricks in arrival order. A key part with a new key_id starts a new key
    (and drops the VOI brick until the server sends it again after the key); a VOI brick
    replaces the previous one (its box is put back to I first), and one with
    deformed = false means J = I everywhere. Values are kept as float32 whatever the
    encoding (int16 HU are exact in float32), so a viewer may switch encodings.

    `volume` is J as an array of shape (size_k, size_j, size_i); it is complete
    (`complete`) once every part of the current key has arrived."""

    def __init__(self) -> None:
        self.grid: Grid | None = None
        self.volume: np.ndarray | None = None   # J, float32, (k, j, i)
        self.key_id: int | None = None
        self.key_parts: int = 0
        self._parts_seen: set[int] = set()
        self._k_filled: np.ndarray | None = None
        self.key_bytes = 0                       # raw bytes of the current key's parts
        self.key_parts_received = 0              # over all keys
        self.voi_bricks = 0                      # VOI bricks applied
        self.voi: "wire.Brick | None" = None     # the newest VOI brick (header; data dropped)
        self._voi_values: np.ndarray | None = None
        self._voi_box: tuple[slice, slice, slice] | None = None
        self._under: np.ndarray | None = None    # I on the VOI box, to put back
        self.encoding: int | None = None

    # -- state ----------------------------------------------------------------------------

    @property
    def complete(self) -> bool:
        """Every part of the current key arrived and every k-slice is filled."""
        return (self.key_id is not None and len(self._parts_seen) == self.key_parts
                and self._k_filled is not None and bool(self._k_filled.all()))

    @property
    def key_parts_seen(self) -> int:
        """Parts of the current key that have arrived (of `key_parts`)."""
        return len(self._parts_seen)

    @property
    def deformed(self) -> bool:
        """The newest VOI brick carries a deformation (J differs from I in its box)."""
        return self._voi_box is not None

    def voi_center_mm(self) -> np.ndarray | None:
        """The physical centre of the newest deformed VOI box (the VOI is a cube centred
        on the tip voxel, shifted or clipped at the volume's border), None without one."""
        if self.voi is None or not self.voi.deformed or self.grid is None:
            return None
        b = self.voi
        c = [b.lo_i + (b.size_i - 1) / 2, b.lo_j + (b.size_j - 1) / 2, b.lo_k + (b.size_k - 1) / 2]
        return self.grid.index_to_mm(c)

    def key_shape(self) -> tuple[int, int, int] | None:
        """(i, j, k) voxels of the key's grid."""
        return self.grid.size if self.grid else None

    # -- bricks ---------------------------------------------------------------------------

    def apply(self, brick: "wire.Brick") -> None:
        """Takes one brick (key part or VOI brick). Raises MalformedMessage for a brick
        that does not fit (bad data, a box outside the grid, a VOI brick on another grid)."""
        values = decode_brick(brick)
        self.encoding = brick.encoding
        if brick.key:
            self._apply_key(brick, values)
        else:
            self._apply_voi(brick, values)

    def _apply_key(self, b: "wire.Brick", values: np.ndarray) -> None:
        grid = Grid.of(b)
        if self.key_id != b.key_id or self.grid is None or not self.grid.same_as(grid):
            # a new key: a new grid maybe (scene changed); the old VOI is stale
            self._drop_voi()
            if self.grid is None or not self.grid.same_as(grid) or self.volume is None:
                self.volume = np.zeros(grid.size[::-1], dtype=np.float32)
            self.grid = grid
            self.key_id, self.key_parts = b.key_id, b.key_parts
            self._parts_seen = set()
            self._k_filled = np.zeros(grid.size[2], dtype=bool)
            self.key_bytes = 0
        elif b.key_parts != self.key_parts:
            raise MalformedMessage(f"Brick.key_parts = {b.key_parts} of key {b.key_id} part "
                                   f"{b.key_part}: earlier parts of that key said {self.key_parts}")
        assert self.volume is not None and self._k_filled is not None
        ks = slice(b.lo_k, b.lo_k + b.size_k)
        # I changes under the VOI box: put the box back to I, write the slab, redo the box
        voi = self._voi_values is not None
        if voi:
            self._restore_voi_box()
        self.volume[ks] = values
        self._k_filled[ks] = True
        if b.key_part not in self._parts_seen:
            self._parts_seen.add(b.key_part)
            self.key_bytes += values.nbytes
        self.key_parts_received += 1
        if voi:
            self._paste_voi()

    def _apply_voi(self, b: "wire.Brick", values: np.ndarray) -> None:
        grid = Grid.of(b)
        if self.grid is not None and not self.grid.same_as(grid):
            raise MalformedMessage(f"Brick.grid_size_i/j/k, spacing_mm, grid_origin_mm or direction "
                                   f"of VOI brick_seq {b.brick_seq}: not the grid of key "
                                   f"{self.key_id} ({grid} vs {self.grid})")
        self._drop_voi()
        self.voi_bricks += 1
        header = wire.Brick()
        header.CopyFrom(b)
        header.ClearField("data")
        self.voi = header
        if b.deformed and values.size:
            self._voi_values = values.astype(np.float32, copy=False)
            self._voi_box = (slice(b.lo_k, b.lo_k + b.size_k), slice(b.lo_j, b.lo_j + b.size_j),
                             slice(b.lo_i, b.lo_i + b.size_i))
            if self.volume is not None:
                self._paste_voi()

    def _paste_voi(self) -> None:
        assert self.volume is not None and self._voi_box is not None
        self._under = self.volume[self._voi_box].copy()
        self.volume[self._voi_box] = self._voi_values

    def _restore_voi_box(self) -> None:
        if self.volume is not None and self._under is not None and self._voi_box is not None:
            self.volume[self._voi_box] = self._under
        self._under = None

    def _drop_voi(self) -> None:
        """J = I again: the VOI box back to the key's values, the VOI forgotten."""
        self._restore_voi_box()
        self._voi_values, self._voi_box = None, None

    # -- reading --------------------------------------------------------------------------

    def point_to_voxel(self, point_mm: Sequence[float]) -> tuple[int, int, int]:
        """The nearest voxel (i, j, k) to a physical point, clamped into the grid."""
        if self.grid is None:
            raise StreamError("DeformedVolume: no key has arrived yet (no grid)")
        ijk = np.rint(self.grid.mm_to_index(point_mm)).astype(int)
        return tuple(int(np.clip(v, 0, n - 1)) for v, n in zip(ijk, self.grid.size))  # type: ignore[return-value]

    def slices(self, point_mm: Sequence[float] | None = None) -> Slices:
        """Axial, coronal and sagittal slices of J through the voxel nearest `point_mm`
        (default: the centre of the newest deformed VOI box, else of the grid)."""
        if self.grid is None or self.volume is None:
            raise StreamError("DeformedVolume: no key has arrived yet, nothing to slice")
        if point_mm is None:
            c = self.voi_center_mm()
            point_mm = c if c is not None else self.grid.center_mm
        i, j, k = self.point_to_voxel(point_mm)
        v = self.volume
        return Slices(index=(i, j, k), point_mm=self.grid.index_to_mm((i, j, k)),
                      axial=v[k, :, :], coronal=v[:, j, :], sagittal=v[:, :, i])


# ---------------------------------------------------------------------------------------
# Statistics


def _percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, dtype=float), q)) if len(values) else float("nan")


@dataclass
class StreamStats:
    """What a viewer received. Frames: `frames_received` (arrived), `frames_delivered`
    (handed to the viewer: the newest of each drain), `frames_skipped` (arrived but
    replaced by a newer one in the same drain, never decoded), `frames_missed` (gaps in
    frame_seq: frames the server published or replaced that never arrived here).
    `fps` is the arrival rate of received frames (viewer clock). Bricks: VOI bricks
    received and delivered, key parts."""

    frames_received: int = 0
    frames_delivered: int = 0
    frames_skipped: int = 0
    frames_missed: int = 0
    last_frame_seq: int | None = None
    first_frame_s: float | None = None    # time.monotonic() of the first and last frame
    last_frame_s: float | None = None
    pose_to_frame_ms: list[float] = field(default_factory=list)
    bricks_received: int = 0              # VOI bricks
    bricks_skipped: int = 0               # VOI bricks replaced by a newer one in a drain
    key_parts_received: int = 0
    bytes_received: int = 0
    notices: list[str] = field(default_factory=list)

    def note_frame(self, frame: "wire.Frame", now_s: float) -> None:
        self.frames_received += 1
        if self.last_frame_seq is not None and frame.frame_seq > self.last_frame_seq + 1:
            self.frames_missed += frame.frame_seq - self.last_frame_seq - 1
        if self.last_frame_seq is None or frame.frame_seq > self.last_frame_seq:
            self.last_frame_seq = frame.frame_seq
        if self.first_frame_s is None:
            self.first_frame_s = now_s
        self.last_frame_s = now_s
        # a frame drawn before the session's first pose shows no pose (pose_seq 0): it has
        # no pose-to-frame latency (the server leaves it out of its percentiles too)
        if frame.pose_seq and math.isfinite(frame.pose_to_frame_ms):
            self.pose_to_frame_ms.append(frame.pose_to_frame_ms)

    @property
    def fps(self) -> float:
        """Frames received per second between the first and the last (nan below two)."""
        if self.frames_received < 2 or self.first_frame_s is None or self.last_frame_s is None:
            return float("nan")
        span = self.last_frame_s - self.first_frame_s
        return (self.frames_received - 1) / span if span > 0 else float("nan")

    @property
    def pose_to_frame_p50_ms(self) -> float:
        return _percentile(self.pose_to_frame_ms, 50)

    @property
    def pose_to_frame_p99_ms(self) -> float:
        return _percentile(self.pose_to_frame_ms, 99)


@dataclass
class Update:
    """What one receive() drained: the newest frame (None when none came; older ones of
    the same drain are counted in `frames_skipped` and never decoded), the bricks to
    apply in order (every key part, and the newest VOI brick of the drain), and the
    notices that do not end the stream ("scene_changed", unknown events)."""

    frame: "wire.Frame | None" = None
    frames_skipped: int = 0
    bricks: list = field(default_factory=list)
    notices: list = field(default_factory=list)

    def __bool__(self) -> bool:
        return self.frame is not None or bool(self.bricks) or bool(self.notices)


# ---------------------------------------------------------------------------------------
# The client


class StreamClient:
    """SUB sockets on a stream endpoint subscribed to one session's frame and/or brick
    topic. Frames and bricks get a socket each, so a burst of frames can never push a
    key part out of a full queue (each SUB is its own pipe with its own high-water mark
    on the server's XPUB). receive() drains both sockets and hands over the newest frame.

    A "closed" notice raises SessionClosed and an "unknown_session" notice raises
    UnknownSession, after the messages that arrived before the notice were handed over
    (the next receive() raises). Malformed messages raise MalformedMessage. With `curve`
    the sockets speak CURVE (the server admits the subscription only from the key that
    opened the session; another key's subscription stays silent)."""

    def __init__(self, endpoint: str, frame_topic: bytes = b"", brick_topic: bytes = b"",
                 session_id: int | None = None, context: zmq.Context | None = None,
                 frame_rcvhwm: int = FRAME_RCVHWM, brick_rcvhwm: int = BRICK_RCVHWM,
                 curve: CurveKeys | None = None):
        if not endpoint:
            raise StreamError("StreamClient: no stream endpoint (the scene asks for neither "
                              "frames nor bricks?)")
        if not frame_topic and not brick_topic:
            raise StreamError("StreamClient: give a frame topic, a brick topic or both")
        self.endpoint = endpoint
        self.session_id = session_id
        self.frame_topic, self.brick_topic = bytes(frame_topic), bytes(brick_topic)
        self.stats = StreamStats()
        self._ctx = context or zmq.Context.instance()
        self._socks: list[zmq.Socket] = []
        self._poller = zmq.Poller()
        self._pending: StreamError | None = None
        for topic, hwm in ((self.frame_topic, frame_rcvhwm), (self.brick_topic, brick_rcvhwm)):
            if not topic:
                continue
            s = self._ctx.socket(zmq.SUB)
            s.setsockopt(zmq.LINGER, 0)
            if curve is not None:
                curve.apply(s)
            s.setsockopt(zmq.RCVHWM, hwm)
            s.connect(endpoint)
            s.setsockopt(zmq.SUBSCRIBE, topic)
            self._socks.append(s)
            self._poller.register(s, zmq.POLLIN)

    @classmethod
    def from_watch(cls, reply: "wire.WatchReply", control_address: str | None = None,
                   **kwargs: Any) -> "StreamClient":
        """A StreamClient for what a WatchReply names (its endpoint, with a wildcard host
        replaced by the control address's host, and its topics)."""
        return cls(resolve_endpoint(reply.stream_endpoint, control_address),
                   frame_topic=reply.frame_topic, brick_topic=reply.brick_topic,
                   session_id=reply.session_id, **kwargs)

    def receive(self, timeout_s: float | None = None) -> Update | None:
        """Waits up to `timeout_s` (None: forever) for a message, then drains what has
        arrived and returns it as an Update (newest frame only); None when nothing came.
        Raises SessionClosed / UnknownSession for the notices, MalformedMessage."""
        if self._pending is not None:
            raise self._pending
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            left_ms = None if deadline is None else max(0, int((deadline - time.monotonic()) * 1000))
            ready = dict(self._poller.poll(left_ms))
            if not ready:
                return None
            update = self._drain()
            if update:
                return update
            if self._pending is not None:
                raise self._pending
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def _drain(self) -> Update:
        update = Update()
        voi_at: int | None = None  # index of the newest VOI brick in update.bricks
        for sock in self._socks:
            for _ in range(MAX_DRAIN):
                if self._pending is not None:
                    break
                try:
                    parts = sock.recv_multipart(zmq.NOBLOCK, copy=True)
                except zmq.Again:
                    break
                now = time.monotonic()
                self.stats.bytes_received += sum(len(p) for p in parts)
                topic, msg = parse_message(parts)
                if topic not in (self.frame_topic, self.brick_topic):
                    continue  # not ours (a shorter subscription elsewhere); ignore
                body = msg.WhichOneof("body")
                if body == "frame":
                    f = msg.frame
                    self._check_session("Frame", f.session_id, topic)
                    # the server sends a quiet session's newest frame once more (PROTOCOL.md):
                    # a frame already received is not a new one
                    if self.stats.last_frame_seq is not None and f.frame_seq <= self.stats.last_frame_seq:
                        continue
                    self.stats.note_frame(f, now)
                    if update.frame is not None:
                        update.frames_skipped += 1
                        self.stats.frames_skipped += 1
                    update.frame = f
                elif body == "brick":
                    b = msg.brick
                    self._check_session("Brick", b.session_id, topic)
                    if b.key:
                        self.stats.key_parts_received += 1
                        update.bricks.append(b)
                    else:
                        self.stats.bricks_received += 1
                        if voi_at is not None:
                            # newest wins: the older VOI brick of this drain is never applied
                            update.bricks.pop(voi_at)
                            self.stats.bricks_skipped += 1
                        update.bricks.append(b)
                        voi_at = len(update.bricks) - 1
                else:
                    self._notice(msg.notice, update)
        if update.frame is not None:
            self.stats.frames_delivered += 1
        return update

    def _check_session(self, what: str, session_id: int, topic: bytes) -> None:
        if self.session_id and session_id != self.session_id:
            raise MalformedMessage(f"{what}.session_id = {session_id:016x} on topic {topic!r}, "
                                   f"but the watched session is {self.session_id:016x}")

    def _notice(self, n: "wire.StreamNotice", update: Update) -> None:
        self.stats.notices.append(n.event)
        if n.event == "closed":
            self._pending = SessionClosed(n.session_id or (self.session_id or 0), n.message)
        elif n.event == "unknown_session":
            code = n.error.code if n.HasField("error") and n.error.code else wire.ERROR_UNKNOWN_SESSION
            self._pending = UnknownSession(n.session_id or (self.session_id or 0),
                                           n.message or n.error.message, code)
        else:
            update.notices.append(n)  # "scene_changed" (a new key follows) or newer events

    def close(self) -> None:
        for s in self._socks:
            self._poller.unregister(s)
            s.close(0)
        self._socks = []

    def __enter__(self) -> "StreamClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def summary_line(stats: StreamStats, volume: DeformedVolume | None = None,
                 frames: bool = True, bricks: bool = False) -> str:
    """One line: frames received, shown, fps, missed (seq gaps), skipped (newest wins),
    pose-to-frame p50/p99 (ms); for bricks the VOI bricks and the key's size."""
    out = []
    if frames:
        fps = stats.fps
        out.append(f"{stats.frames_received} frames received, {stats.frames_delivered} shown, "
                   f"{fps:.1f} fps, {stats.frames_missed} missed, {stats.frames_skipped} skipped, "
                   f"pose-to-frame p50 {stats.pose_to_frame_p50_ms:.1f} ms "
                   f"p99 {stats.pose_to_frame_p99_ms:.1f} ms")
    if bricks:
        key = "no key"
        if volume is not None and volume.grid is not None:
            i, j, k = volume.grid.size
            key = (f"key {i}x{j}x{k} voxels in {volume.key_parts} parts, "
                   f"{volume.key_bytes / 1e6:.2f} MB{'' if volume.complete else ' (incomplete)'}")
        out.append(f"{stats.bricks_received} bricks received"
                   f" ({stats.bricks_skipped} skipped), {stats.key_parts_received} key parts, {key}")
    return "; ".join(out)
