"""A recorded press: a session of a palpsim-server is pressed into the back in depth
steps, and at each step the frame the server renders of exactly that step is kept; then
the frames become an MP4 and a contact sheet (PNG).

    with Client(address) as c:
        rec = record_press(c, top_mm=(0.0, 119.0, -5.0), direction=(0, -1, 0),
                           depths_mm=press_depths(15.0, steps=5))
    paths = write_recording(rec, "out/demo/palpation", title="press over L3")
    print(summary(rec, paths))

Frames are slow where the server renders on a CPU (Mesa llvmpipe: seconds a frame), so
the recording is stepped rather than timed: the tip moves to a depth (at
`speed_mm_per_s`) and stays there, poses still going out at `rate_hz` (the session must
not time out, and a haptic loop keeps its pace), until a frame arrives that shows that
depth: its `pose_seq` is at least the seq of the first pose at that depth and, in
contact with a scene that deforms, its `deform_pose_seq` is too (the deformation drawn
was computed at that depth); out of contact, its deformation has been released
(`deformed` false). The poses are a function of the depths and of the contact flag at
the skin only (the device clock `client_time_s` counts poses, so the force-rate clamp
does not depend on the wall clock), so the same press gives the same tips, depths and
forces on every run; only how long each step waits for its frame varies.

The skin is found as the batch runner finds it: moving along `direction` from `top_mm`
until the server reports contact; depths are measured from there. That is done before
the session is watched, so the server renders nothing for it. Units: mm, N, s; points
in the patient's physical space (LPS).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .client import Client, PalpsimError, PoseReply, Session
from .proto import wire
from .stream import StreamClient, decode_frame

# The camera of a recorded press (the scene's render settings give the rest; the server
# checks the ranges, server/render/view.h). It looks at a fixed point, LOOK_AT_DEPTH_MM
# under the skin point of the press (record_press sets center_mm), rather than at the tip:
# the body stays put and the tip is seen going in, in the 3D view and in the slices, and
# the slices through that point show the spinous process under the tip (the coronal one
# cuts through the processes) with the dent of the skin above it. Azimuth 75, elevation
# 15: from the patient's left and a little above, so the press direction (-y, anterior)
# lies almost in the image plane and the processes are seen in profile, the tip coming
# onto one of them (azimuth 0 looks from posterior, along the press); 15 degrees lifts
# the camera over the iliac crest, which hides the lower lumbar processes in a pure side
# view. Zoom 1.7 (1 frames the whole patient grid): T12 to the sacrum fill the height of
# the 3D view, while a 1280x720 frame renders in 0.6-1.1 s on Mesa llvmpipe with 2 cores
# (the ray cast's time grows with the pixels the body covers; a step waits about two
# frames). Slices 100 mm wide (the default 120): from above the skin to the laminae.
DEFAULT_VIEW: dict[str, Any] = {
    "preset": "bone",
    "show_tip": True,
    "azimuth_deg": 75.0,
    "elevation_deg": 15.0,
    "zoom": 1.7,
    "slice_fov_mm": 100.0,
}
LOOK_AT_DEPTH_MM = 35.0

DEFAULT_RATE_HZ = 200.0          # poses a second, throughout (the haptic loop's pace)
DEFAULT_SPEED_MM_PER_S = 20.0    # between steps, and while looking for the skin
DEFAULT_STEP_TIMEOUT_S = 90.0    # a step whose frame does not come within this fails
MAX_LATE_S = 0.1                 # a pose loop this far behind restarts its clock (no burst)


class RecordError(PalpsimError):
    """The press could not be recorded (no skin, no frame of a step, the session ended)."""


def press_depths(max_depth_mm: float = 15.0, steps: int = 5, above_mm: float = 5.0) -> list[float]:
    """The depths (mm under the skin) of a stepped press: `above_mm` above the skin (a
    negative depth: out of contact), `steps` even steps down to `max_depth_mm`, the same
    depths back up, and above the skin again. steps=3, 15 mm: -5, 5, 10, 15, 10, 5, -5."""
    if steps < 1:
        raise ValueError(f"press_depths: steps = {steps}, expected 1 or more")
    if not (math.isfinite(max_depth_mm) and max_depth_mm > 0):
        raise ValueError(f"press_depths: max_depth_mm = {max_depth_mm}, expected > 0")
    down = [max_depth_mm * (i + 1) / steps for i in range(steps)]
    return [-abs(above_mm), *down, *down[-2::-1], -abs(above_mm)]


def frame_shows_step(frame: "wire.Frame", first_seq: int, contact: bool, deforms: bool) -> str | None:
    """Whether `frame` shows the step whose first pose (at its depth) had seq `first_seq`
    and contact flag `contact`, on a scene that deforms (`deforms`) or not: None when it
    does, else why not ("pose": it shows an earlier pose; "deformation": its J was
    computed before the tip reached this depth; "release": the tip is out of the body
    but the frame still shows a deformation)."""
    if frame.pose_seq < first_seq:
        return "pose"
    if deforms:
        if contact and frame.deform_pose_seq < first_seq:
            return "deformation"
        if not contact and frame.deformed:
            return "release"
    return None


@dataclass
class RecordedFrame:
    """One step of the press and the frame that shows it."""

    index: int                  # step 0, 1, ...
    depth_mm: float             # the step's depth under the skin (negative: above it)
    tip_mm: np.ndarray          # the tip held during the step
    first_seq: int              # seq of the first pose at this depth (the hold's first)
    reply: PoseReply            # the server's answer to the pose the frame shows
    frame: "wire.Frame"         # the frame (its JPEG included)
    rgb: np.ndarray             # the frame decoded, (height, width, 3) uint8
    wait_s: float               # from reaching this depth (or the step's start) to the frame
    poses: int                  # poses sent while moving to this depth and holding it
    rejected: dict[str, int] = field(default_factory=dict)  # frames seen meanwhile, by reason

    @property
    def force_n(self) -> float:
        """|force| of the pose the frame shows (N)."""
        return float(np.linalg.norm(self.reply.force_n))

    @property
    def render_ms(self) -> float:
        return float(self.frame.times.total_ms)


@dataclass
class Recording:
    """A recorded press: its frames, where it was, and how it went."""

    frames: list[RecordedFrame]
    session_id: int
    top_mm: np.ndarray           # where the tip started, above the body
    direction: np.ndarray        # unit press direction
    skin_travel_mm: float        # travel from top_mm to the first contact
    view: "wire.ViewSettings"    # the session's view as the watch reply gave it
    deforms: bool                # the scene deforms (stage "chainmail" built)
    scene_name: str
    poses: int                   # poses sent in all
    max_pose_gap_s: float        # the longest time between two poses (the loop's pace)
    wall_s: float                # the whole recording, from opening the session
    rate_hz: float

    @property
    def skin_mm(self) -> np.ndarray:
        return self.top_mm + self.skin_travel_mm * self.direction

    @property
    def max_depth_mm(self) -> float:
        return max((f.depth_mm for f in self.frames), default=0.0)


class _Pacer:
    """Poses at `rate_hz` on the wall clock, and the stream drained between them. Keeps
    the hold: the replies since the tip last moved (or the proxy was reset), the first of
    them being the first pose at the tip's present place."""

    def __init__(self, session: Session, rate_hz: float):
        self.session = session
        self.period_s = 1.0 / rate_hz
        self.next_s = time.monotonic()
        self.last_pose_s: float | None = None
        self.max_gap_s = 0.0
        self.count = 0
        self.tip: tuple[float, ...] | None = None
        self.hold_first: PoseReply | None = None
        self.hold_first_s = 0.0
        self.hold: dict[int, PoseReply] = {}

    def pose(self, tip_mm: np.ndarray, reset_proxy: bool = False) -> PoseReply:
        """Sends one pose at its time (the device clock is the pose count / rate)."""
        now = time.monotonic()
        if now < self.next_s:
            time.sleep(self.next_s - now)
            now = time.monotonic()
        if self.last_pose_s is not None:
            self.max_gap_s = max(self.max_gap_s, now - self.last_pose_s)
        self.last_pose_s = now
        self.count += 1
        reply = self.session.pose(tip_mm, client_time_s=self.count * self.period_s,
                                  reset_proxy=reset_proxy)
        self.next_s += self.period_s
        if now - self.next_s > MAX_LATE_S:
            self.next_s = now + self.period_s
        tip = tuple(float(v) for v in tip_mm)
        if tip != self.tip or reset_proxy:
            self.tip, self.hold_first, self.hold_first_s, self.hold = tip, reply, now, {}
        self.hold[reply.seq] = reply
        return reply

    def wait(self, stream: StreamClient | None) -> list["wire.Frame"]:
        """Until the next pose is due: the frames the stream hands over meanwhile."""
        frames = []
        while True:
            left = self.next_s - time.monotonic()
            if stream is None:
                if left > 0:
                    time.sleep(left)
                return frames
            update = stream.receive(max(left, 0.0))
            if update is not None and update.frame is not None:
                frames.append(update.frame)
            if left <= 0 or update is None:
                return frames


def record_press(client: Client, top_mm: Sequence[float], direction: Sequence[float],
                 depths_mm: Sequence[float], *, view: dict[str, Any] | None = None,
                 look_at_depth_mm: float | None = LOOK_AT_DEPTH_MM,
                 rate_hz: float = DEFAULT_RATE_HZ, speed_mm_per_s: float = DEFAULT_SPEED_MM_PER_S,
                 max_travel_mm: float = 150.0, step_timeout_s: float = DEFAULT_STEP_TIMEOUT_S,
                 client_name: str = "palpsim-record",
                 progress: Callable[[RecordedFrame, int], None] | None = None) -> Recording:
    """Opens a session on `client`'s server, finds the skin along `direction` from
    `top_mm` (a point outside the body), watches the session's frames with `view`
    (DEFAULT_VIEW when None; the scene's render settings fill what it leaves out) looking
    at the point `look_at_depth_mm` under the skin point (None: the view's own look-at,
    e.g. look_at_tip), and presses to each of `depths_mm` (mm under the skin; negative:
    above it) in turn, keeping at each depth the first frame that shows it
    (frame_shows_step). Poses go out at `rate_hz` the whole time. `progress(frame, steps)` is called after each step.
    Raises RecordError (no skin within max_travel_mm, no frame within step_timeout_s),
    the stream's SessionClosed (the session timed out) and the client's ServerError (a
    refused watch: the scene asks for no frames, a bad view), all PalpsimError."""
    t_start = time.monotonic()
    top = np.asarray(top_mm, dtype=float)
    d = np.asarray(direction, dtype=float)
    if (top.shape != (3,) or d.shape != (3,) or not np.all(np.isfinite(top))
            or not np.linalg.norm(d) > 0):
        raise ValueError(f"record_press: top_mm {tuple(top)} and direction {tuple(d)} must be "
                         "finite 3-vectors, the direction non-zero")
    d = d / np.linalg.norm(d)
    depths = [float(x) for x in depths_mm]
    if not depths or not all(math.isfinite(x) for x in depths):
        raise ValueError(f"record_press: depths_mm {depths_mm!r}: expected finite depths")
    step_mm = speed_mm_per_s / rate_hz
    info = client.info()
    deforms = "chainmail" in info.stages

    with client.open_session(client_name) as session:
        pacer = _Pacer(session, rate_hz)
        first = pacer.pose(top, reset_proxy=True)
        if first.contact:
            raise RecordError(f"record_press: the start point {tuple(np.round(top, 1))} mm is inside "
                              "the body; start above the skin")
        # the skin: the first contact moving along the direction (nothing is watched yet);
        # travel is the pose index times the step, so it does not drift
        travel, skin, k = 0.0, None, 0
        while skin is None:
            if travel >= max_travel_mm:
                raise RecordError(f"record_press: no skin within {max_travel_mm:g} mm of "
                                  f"{tuple(np.round(top, 1))} mm along {tuple(np.round(d, 3))}")
            k += 1
            travel = min(k * step_mm, max_travel_mm)
            if pacer.pose(top + travel * d).contact:
                skin = travel
            pacer.wait(None)

        # back above the skin (out of contact, with a fresh proxy and J = I), then watch
        above = max(skin - max(5.0, -min(depths)), 0.0)
        while travel > above:
            travel = max(travel - step_mm, above)
            pacer.pose(top + travel * d, reset_proxy=travel == above)
            pacer.wait(None)
        view = dict(DEFAULT_VIEW if view is None else view)
        if look_at_depth_mm is not None:
            view["look_at_tip"] = False
            view["center_mm"] = tuple(top + (skin + look_at_depth_mm) * d)
        reply = client.watch(session_id=session.id, frames=True, view=view)
        frames: list[RecordedFrame] = []
        with StreamClient.from_watch(reply, client.address, curve=client.curve) as stream:
            for i, depth in enumerate(depths):
                frames.append(_step(i, depth, pacer, stream, top, d, skin, travel, step_mm,
                                    deforms, step_timeout_s))
                travel = skin + depth
                if progress is not None:
                    progress(frames[-1], len(depths))
            # out of the body again before the session closes
            while travel > 0.0:
                travel = max(travel - 4 * step_mm, 0.0)
                pacer.pose(top + travel * d)
        poses = pacer.count
    return Recording(frames=frames, session_id=session.id, top_mm=top, direction=d,
                     skin_travel_mm=skin, view=reply.view, deforms=deforms,
                     scene_name=info.scene_name, poses=poses, max_pose_gap_s=pacer.max_gap_s,
                     wall_s=time.monotonic() - t_start, rate_hz=rate_hz)


def _step(index: int, depth: float, pacer: _Pacer, stream: StreamClient, top: np.ndarray,
          d: np.ndarray, skin: float, travel: float, step_mm: float, deforms: bool,
          timeout_s: float) -> RecordedFrame:
    """Moves to `depth` under the skin (from `travel` along d) and holds it, a pose each
    period, until a frame shows it; returns that frame with the reply of its pose. The
    step's first pose is the first at the tip's place: one sent before the step began
    when the tip was already there (the render thread may have drawn that one, and then
    nothing changes that would make it draw another)."""
    target = skin + depth
    poses0 = pacer.count
    t_step = time.monotonic()
    rejected: dict[str, int] = {}
    while True:
        if travel != target:
            travel = (min(travel + step_mm, target) if target > travel
                      else max(travel - step_mm, target))
        r = pacer.pose(top + travel * d)
        first = pacer.hold_first if travel == target else None
        t_first = max(t_step, pacer.hold_first_s)
        for f in pacer.wait(stream):
            why = "pose" if first is None else frame_shows_step(f, first.seq, first.contact, deforms)
            if why is not None:
                rejected[why] = rejected.get(why, 0) + 1
                continue
            assert first is not None
            return RecordedFrame(index=index, depth_mm=depth, tip_mm=top + target * d,
                                 first_seq=first.seq, reply=pacer.hold.get(f.pose_seq, r), frame=f,
                                 rgb=decode_frame(f), wait_s=time.monotonic() - t_first,
                                 poses=pacer.count - poses0, rejected=rejected)
        if first is not None and time.monotonic() - t_first > timeout_s:
            seen = ", ".join(f"{n} {why}" for why, n in sorted(rejected.items())) or "none"
            raise RecordError(
                f"record_press: step {index + 1} (depth {depth:g} mm, first pose seq {first.seq}, "
                f"{'in' if first.contact else 'out of'} contact): no frame showing it within "
                f"{timeout_s:g} s (frames seen and passed over, by reason: {seen}); is the "
                "server rendering (stats: render_failures, last_error)?"
                f"{_session_state(pacer.session)}")


def _session_state(session: Session) -> str:
    """The session's deformation and frames as the server counts them, for an error that
    says where a step's frame stopped (empty where the server does not answer)."""
    try:
        st = session.stats()
    except Exception:  # the error being raised matters more than this detail
        return ""
    parts = []
    if st.HasField("deform"):
        d = st.deform
        parts.append(f"deformation: {d.steps} steps, {getattr(d, 'contacts_current', 0)} contacts already "
                     f"current, {d.contacts_dropped} dropped, J stands for pose {d.last_contact_seq}"
                     + (f", last error {d.last_error!r}" if d.last_error else ""))
    if st.HasField("stream"):
        parts.append(f"frames: {st.stream.frames_rendered} rendered, {st.stream.frames_published} published")
        if st.stream.frames_watched and st.stream.frames_rendered == 0:
            # wanted, yet never drawn: the render thread had no CPU time (seen on a 2-core
            # machine with two busy processes beside the server), or it is stuck
            parts.append("its frames are wanted but none was drawn: the server's render thread runs "
                         "at the lowest priority (palpsim-server --background idle, the default), so "
                         "other busy processes on the server's machine can leave it no time "
                         "(--background nice gives it a share)")
    return f" The session now: {'; '.join(parts)}." if parts else ""


# ---------------------------------------------------------------------------------------
# Labels, the MP4 and the contact sheet


def frame_label(rf: RecordedFrame, steps: int) -> list[str]:
    """Two lines about a recorded step: where the tip is and what the frame drew."""
    r, f = rf.reply, rf.frame
    where = (f"depth {r.depth_mm:.1f} mm" if r.contact else
             f"{-rf.depth_mm:g} mm above the skin" if rf.depth_mm < 0 else "at the skin")
    first = f"step {rf.index + 1}/{steps}  {where}  force {rf.force_n:.2f} N"
    if f.deformed:
        second = f"deformation step {f.deform_step} (pose {f.deform_pose_seq})"
    else:
        second = "undeformed"
    return [first, f"{second}  frame {f.frame_seq}, {rf.render_ms / 1000:.1f} s to render"]


def _font(size: int) -> Any:
    """Pillow's default font at `size` pixels (the bitmap one where FreeType is missing)."""
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ValueError, OSError, ImportError):  # Pillow < 10.1 or no FreeType
        return ImageFont.load_default()


CAPTION_BG = (16, 18, 24)
CAPTION_FG = (235, 235, 235)


def _text_block(width: int, lines: Sequence[str], font_px: int, bg=CAPTION_BG, fg=CAPTION_FG,
                pad: int | None = None) -> np.ndarray:
    """`lines` drawn left-aligned on a strip `width` pixels wide, as an RGB array."""
    from PIL import Image, ImageDraw

    pad = max(2, font_px // 3) if pad is None else pad
    line_h = int(round(font_px * 1.25))
    height = _block_height(font_px, len(lines), pad)
    img = Image.new("RGB", (width, height), bg)
    draw = ImageDraw.Draw(img)
    font = _font(font_px)
    for n, text in enumerate(lines):
        draw.text((pad + 2, pad + n * line_h), text, fill=fg, font=font)
    return np.asarray(img)


def captioned(rgb: np.ndarray, lines: Sequence[str]) -> np.ndarray:
    """The frame with `lines` in a strip below it (the frame's own pixels untouched)."""
    h, w = rgb.shape[:2]
    strip = _text_block(w, lines, font_px=max(10, h // 30))
    return np.concatenate([rgb, strip], axis=0)


def write_mp4(images: Sequence[np.ndarray], captions: Sequence[Sequence[str]], path: str | Path,
              fps: float = 10.0, frames_per_image: int = 6) -> int:
    """An MP4 (h264, yuv420p, through palpsim-view's writer) showing each image with its
    caption below it for `frames_per_image` video frames at `fps`; returns the number
    of video frames. Odd edges are padded to even ones."""
    from .view_outputs import Mp4Sink

    if len(images) != len(captions):
        raise ValueError(f"write_mp4: {len(images)} images but {len(captions)} captions")
    if not images:
        raise ValueError("write_mp4: no images")
    sink = Mp4Sink(Path(path), fps=fps)
    try:
        for rgb, lines in zip(images, captions):
            frame = captioned(rgb, lines)
            for _ in range(frames_per_image):
                sink.add(frame, 0.0)
    finally:
        sink.close()
    return sink.count


def pick_frames(n: int, count: int = 6, keep: Sequence[int] = ()) -> list[int]:
    """`count` indices of 0..n-1, evenly spread, first and last included, and each of
    `keep` too (it replaces the nearest pick): the frames a contact sheet shows."""
    if n <= count:
        return list(range(n))
    picks = [int(round(x)) for x in np.linspace(0, n - 1, count)]
    for k in keep:
        if k not in picks and 0 <= k < n:
            j = min(range(1, count - 1), key=lambda j: abs(picks[j] - k))
            picks[j] = k
    return sorted(set(picks))


SHEET_MARGIN = 10


@dataclass(frozen=True)
class SheetLayout:
    """Where contact_sheet puts things (pixels): a title line, then rows of tiles, each
    under its label block, SHEET_MARGIN apart."""

    cols: int
    rows: int
    tile_w: int
    tile_h: int
    label_h: int
    title_h: int
    font_px: int
    margin: int = SHEET_MARGIN

    @property
    def width(self) -> int:
        return self.cols * self.tile_w + (self.cols + 1) * self.margin

    @property
    def height(self) -> int:
        return 2 * self.margin + self.title_h + self.rows * (self.label_h + self.tile_h + self.margin)

    def label_xy(self, i: int) -> tuple[int, int]:
        """Top-left corner of tile i's label block; the tile itself is label_h below."""
        r, c = divmod(i, self.cols)
        return (self.margin + c * (self.tile_w + self.margin),
                2 * self.margin + self.title_h + r * (self.label_h + self.tile_h + self.margin))


def _block_height(font_px: int, lines: int, pad: int) -> int:
    return 2 * pad + int(round(font_px * 1.25)) * lines


def sheet_layout(n: int, frame_w: int, frame_h: int, cols: int = 3, tile_width: int = 640,
                 label_lines: int = 2) -> SheetLayout:
    """The layout of a contact sheet of n frames of frame_w x frame_h pixels."""
    font_px = max(12, tile_width // 34)
    return SheetLayout(cols=cols, rows=(n + cols - 1) // cols, tile_w=tile_width,
                       tile_h=max(1, int(round(tile_width * frame_h / frame_w))),
                       label_h=_block_height(font_px, label_lines, 4),
                       title_h=_block_height(int(font_px * 1.3), 1, 6), font_px=font_px)


def contact_sheet(images: Sequence[np.ndarray], labels: Sequence[Sequence[str]], title: str,
                  cols: int = 3, tile_width: int = 640) -> np.ndarray:
    """A grid of the images (`cols` a row, each scaled to `tile_width` pixels wide), each
    with its label lines above it, under a title line; an RGB array (sheet_layout says
    where everything is)."""
    from PIL import Image

    if not images or len(images) != len(labels):
        raise ValueError(f"contact_sheet: {len(images)} images and {len(labels)} labels")
    h0, w0 = images[0].shape[:2]
    lay = sheet_layout(len(images), w0, h0, cols, tile_width, max(len(lab) for lab in labels))
    sheet = np.empty((lay.height, lay.width, 3), dtype=np.uint8)
    sheet[:] = CAPTION_BG
    title_block = _text_block(lay.width - 2 * lay.margin, [title], int(lay.font_px * 1.3), pad=6)
    sheet[lay.margin:lay.margin + lay.title_h, lay.margin:lay.width - lay.margin] = title_block
    for i, (rgb, lab) in enumerate(zip(images, labels)):
        x, y = lay.label_xy(i)
        block = _text_block(lay.tile_w, lab, lay.font_px, pad=4)
        sheet[y:y + block.shape[0], x:x + lay.tile_w] = block
        tile = Image.fromarray(rgb)
        if tile.size != (lay.tile_w, lay.tile_h):
            tile = tile.resize((lay.tile_w, lay.tile_h), Image.LANCZOS)
        sheet[y + lay.label_h:y + lay.label_h + lay.tile_h, x:x + lay.tile_w] = np.asarray(tile)
    return sheet


def write_recording(rec: Recording, out_dir: str | Path, title: str, name: str = "press",
                    fps: float = 10.0, seconds_per_step: float = 0.6, sheet_frames: int = 6,
                    tile_width: int = 640) -> dict[str, Path]:
    """Writes NAME.mp4 (every step, `seconds_per_step` each), NAME_contact_sheet.png
    (`sheet_frames` steps, the deepest included) and NAME.json (the steps: depth,
    force, seqs, times) into out_dir; returns their paths."""
    from PIL import Image

    from .results import write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = len(rec.frames)
    labels = [frame_label(f, n) for f in rec.frames]
    mp4 = out / f"{name}.mp4"
    per = max(1, int(round(seconds_per_step * fps)))
    write_mp4([f.rgb for f in rec.frames], [[title, *lab] for lab in labels], mp4, fps=fps,
              frames_per_image=per)
    deepest = max(range(n), key=lambda i: rec.frames[i].depth_mm)
    picks = pick_frames(n, sheet_frames, keep=(deepest,))
    sheet = contact_sheet([rec.frames[i].rgb for i in picks], [labels[i] for i in picks],
                          f"{title} ({len(picks)} of {n} steps)", tile_width=tile_width)
    png = out / f"{name}_contact_sheet.png"
    tmp = png.with_name(png.name + ".tmp")
    Image.fromarray(sheet).save(tmp, format="PNG")
    tmp.replace(png)
    table = out / f"{name}.json"
    write_json(recording_dict(rec, title), table)
    return {"mp4": mp4, "sheet": png, "json": table}


def recording_dict(rec: Recording, title: str = "") -> dict[str, Any]:
    """The recording as plain data (for NAME.json)."""
    v = rec.view
    return {
        "title": title, "scene": rec.scene_name, "session": f"{rec.session_id:016x}",
        "top_mm": rec.top_mm.tolist(), "direction": rec.direction.tolist(),
        "skin_mm": rec.skin_mm.tolist(), "deforms": rec.deforms,
        "view": {"width": v.width, "height": v.height, "preset": v.preset,
                 "azimuth_deg": v.azimuth_deg, "elevation_deg": v.elevation_deg, "zoom": v.zoom,
                 "slice_fov_mm": v.slice_fov_mm},
        "poses": rec.poses, "rate_hz": rec.rate_hz, "max_pose_gap_ms": 1000 * rec.max_pose_gap_s,
        "wall_s": rec.wall_s,
        "steps": [{
            "step": f.index + 1, "depth_mm": f.depth_mm, "tip_mm": f.tip_mm.tolist(),
            "contact": f.reply.contact, "server_depth_mm": f.reply.depth_mm,
            "force_n": f.force_n, "first_pose_seq": f.first_seq, "pose_seq": f.frame.pose_seq,
            "frame_seq": f.frame.frame_seq, "deformed": f.frame.deformed,
            "deform_step": f.frame.deform_step, "deform_pose_seq": f.frame.deform_pose_seq,
            "render_ms": f.render_ms, "pose_to_frame_ms": f.frame.pose_to_frame_ms,
            "wait_s": f.wait_s, "poses": f.poses, "frames_passed_over": dict(f.rejected),
        } for f in rec.frames],
    }


def summary(rec: Recording, paths: dict[str, Path] | None = None) -> str:
    """A few lines: frames, render and wait times, the pose loop's pace, the files."""
    fr = rec.frames
    render = np.array([f.render_ms / 1000 for f in fr])
    wait = np.array([f.wait_s for f in fr])
    passed = sum(sum(f.rejected.values()) for f in fr)
    v = rec.view
    lines = [
        f"recorded {len(fr)} steps to {rec.max_depth_mm:g} mm in {rec.wall_s:.1f} s "
        f"({v.width}x{v.height}, preset {v.preset}, azimuth {v.azimuth_deg:g}, elevation "
        f"{v.elevation_deg:g}, zoom {v.zoom:g}); skin at "
        f"({', '.join(f'{x:.1f}' for x in rec.skin_mm)}) mm",
        f"  render per frame {render.min():.1f}-{render.max():.1f} s (median {np.median(render):.1f} s); "
        f"wait per step {wait.min():.1f}-{wait.max():.1f} s (median {np.median(wait):.1f} s); "
        f"{passed} frames passed over (earlier poses or deformations)",
        f"  {rec.poses} poses at {rec.rate_hz:g} Hz, longest gap {1000 * rec.max_pose_gap_s:.0f} ms",
        "  " + "  ".join(f"{f.depth_mm:g}mm:{f.force_n:.2f}N" for f in fr),
    ]
    if paths:
        lines.append("  wrote " + ", ".join(str(p) for p in paths.values()))
    return "\n".join(lines)
