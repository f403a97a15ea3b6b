"""palpsim-view: watch a session of a palpsim-server: its rendered frames (JPEG from the
server's stream endpoint) or, with --bricks, the deformed volume J rebuilt from bricks
and shown as three slices through the tip.

    palpsim-view --connect tcp://127.0.0.1:7420                         # newest session, live window
    palpsim-view --connect ADDR --session 3f2a... --out out/view --frames 100
    palpsim-view --connect ADDR --mp4 press.mp4 --size 960x540 --preset skin
    palpsim-view --connect ADDR --bricks --zstd --out out/bricks --frames 10

Where a display exists ($DISPLAY or $WAYLAND_DISPLAY) with a GUI toolkit for matplotlib
(tkinter, or a Qt binding) and neither --out nor --mp4 is given, it opens a window: arrows
orbit the camera (azimuth, elevation, 10 degrees a key), + and - zoom, p cycles the
presets, q quits; each key sends the session a new view (WatchSession). Otherwise it says
what is missing (the display, or the toolkit and how to install it) and writes PNG files
(--out DIR: frame_000001.png ..., or bricks_000001.png ... with --bricks; out/view when
neither --out nor --mp4 is given) and/or an MP4 (--mp4 FILE: h264, yuv420p, at the frame
rate measured on the server's clock, else 30 fps), until --frames N frames (or VOI bricks)
are written, the session ends, or Ctrl-C. At exit it prints one summary line.

Exit status: 0 when done (N frames, the session closed, q or Ctrl-C); 1 when the server
did not answer, the stream went silent for --timeout seconds, a message was malformed or
an output could not be written; 2 for a bad command line and for the server's refusals
(ERROR_BAD_VIEW, ERROR_UNKNOWN_SESSION, ERROR_NOT_BUILT, ERROR_NO_SESSION_OPEN, ...) and
an "unknown_session" notice, with the server's sentence.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from . import keys
from .client import Client, PalpsimError, ServerError, ServerTimeout
from .proto import wire
from .stream import (DeformedVolume, MalformedMessage, SessionClosed, Slices, StreamClient,
                     StreamError, UnknownSession, decode_frame, summary_line)

PROG = "palpsim-view"
PRESETS = ("skin", "bone", "soft_tissue")  # server/render/view.h, in the order p cycles them

# HU windows (level, width) of the brick slices per preset: what each preset looks at
SLICE_WINDOWS_HU = {"skin": (-200.0, 1000.0), "bone": (400.0, 1800.0),
                    "soft_tissue": (40.0, 400.0)}

# the live window's steps: 10 degrees a key (the brief's orbit step), 1.25x zoom a key,
# elevation kept inside the server's -89..89 and zoom inside 0.1..20 (view.h)
ORBIT_STEP_DEG = 10.0
ZOOM_STEP = 1.25
ELEVATION_LIMIT_DEG = 89.0
ZOOM_RANGE = (0.1, 20.0)

DEFAULT_CONTROL_TIMEOUT_S = 10.0
DEFAULT_MP4_FPS = 30.0
MP4_FPS_PROBE_FRAMES = 30   # frames (or 2 s of server time) buffered to measure the frame rate
MP4_FPS_PROBE_S = 2.0

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def _say(text: str) -> None:
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------
# Command line


def _size(text: str) -> tuple[int, int]:
    """WxH in pixels; the server checks the range (ERROR_BAD_VIEW)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT in pixels (e.g. 1280x720)")
    w, h = int(m.group(1)), int(m.group(2))
    if max(w, h) > 0xFFFFFFFF:
        raise argparse.ArgumentTypeError(f"{text!r}: a size past 2^32-1 pixels")
    return w, h


def _center(text: str) -> tuple[float, float, float]:
    """X,Y,Z in mm (LPS)."""
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"{text!r} is not X,Y,Z in mm (three numbers, e.g. 0,110,-38)")
    return values  # type: ignore[return-value]


def _session(text: str) -> int:
    """A session id: decimal, 0x-prefixed hex, or the 16 hex digits of a topic."""
    t = text.strip().lower()
    try:
        if t.startswith("0x"):
            v = int(t, 16)
        elif len(t) == 16 and re.fullmatch(r"[0-9a-f]{16}", t):
            v = int(t, 16)
        else:
            v = int(t, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a session id (decimal, 0x hex, or the "
                                         "16 hex digits of a topic)") from None
    if not 0 < v < 2 ** 64:
        raise argparse.ArgumentTypeError(f"{text!r}: a session id is 1..2^64-1 "
                                         "(use --any for the newest session)")
    return v


def positive_int(text: str) -> int:
    """argparse type: a whole number of at least 1 (also used by palpsim-demo)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 1 or more")
    return v


def positive_number(what: str):
    """argparse type: a finite number above 0; `what` ends the message ("seconds", "a depth in mm")."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"{text!r}: expected a positive number of {what}")
        return v
    return parse


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def add_watch_arguments(p: argparse.ArgumentParser, any_help: str) -> None:
    """Adds --connect, --session / --any (`any_help` says what --any picks) and the keys
    (keys.add_arguments): how a watching tool (palpsim-view, palpsim-igtl) names the
    server and the session."""
    p.add_argument("--connect", metavar="ADDR", required=True,
                   help="control address the server printed (e.g. tcp://127.0.0.1:7420)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--session", metavar="ID", type=_session,
                       help="session id (decimal, 0x hex, or the 16 hex digits of its topic)")
    which.add_argument("--any", action="store_true", help=any_help)
    keys.add_arguments(p)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Watch a palpsim-server session: its rendered frames, or (--bricks) the "
                    "deformed volume as slices through the tip. A live window where a display "
                    "exists; PNG files (--out) and/or an MP4 (--mp4) otherwise.",
        epilog="Keys in the live window: arrows orbit (10 deg), + and - zoom, p cycles presets, "
               "q quits. Exit status: 0 done, 1 no answer / silent stream / malformed message, "
               "2 bad command line or refused by the server.")
    add_watch_arguments(p, any_help="the newest open session of this client (its key or "
                                    "--client-token; the default)")
    out = p.add_argument_group("output")
    out.add_argument("--out", metavar="DIR", type=Path,
                     help="write PNG files here: frame_000001.png ... (bricks_000001.png ... "
                          "with --bricks)")
    out.add_argument("--mp4", metavar="FILE", type=Path,
                     help="write an MP4 (h264, yuv420p) at the measured frame rate (else 30 fps)")
    out.add_argument("--frames", metavar="N", type=positive_int,
                     help="stop after N frames (with --bricks: N VOI bricks) "
                          "(default: until the session ends or Ctrl-C)")
    out.add_argument("--timeout", metavar="S", type=positive_number("seconds"),
                     help="seconds to wait for the server's reply (default %g) and for each "
                          "stream message (default: forever)" % DEFAULT_CONTROL_TIMEOUT_S)
    v = p.add_argument_group("view (sent to the server; options left out keep the session's view)")
    v.add_argument("--preset", metavar="P",
                   help="transfer-function preset: skin, bone or soft_tissue (with --bricks: "
                        "the slices' HU window, default bone)")
    v.add_argument("--size", metavar="WxH", type=_size, help="frame size in pixels (e.g. 1280x720)")
    v.add_argument("--azimuth", metavar="DEG", type=float,
                   help="camera azimuth about the superior axis (0 = from posterior)")
    v.add_argument("--elevation", metavar="DEG", type=float,
                   help="camera elevation towards superior (-89..89)")
    v.add_argument("--zoom", metavar="Z", type=float, help="zoom (0.1..20; 1 frames the patient)")
    v.add_argument("--quality", metavar="Q", type=_int, help="JPEG quality (1..100)")
    v.add_argument("--center", metavar="X,Y,Z", type=_center,
                   help="look at this fixed point (mm, LPS) instead of following the tip "
                        "(with --bricks: the slices' point); write --center=-1,2,3 when X is "
                        "negative")
    v.add_argument("--no-tip-marker", action="store_true", help="no marker at the device tip")
    v.add_argument("--show-proxy", action="store_true", help="a marker at the proxy")
    b = p.add_argument_group("bricks")
    b.add_argument("--bricks", action="store_true",
                   help="rebuild the deformed volume J from bricks and show three slices of it "
                        "through the tip (the centre of the newest deformed VOI), instead of frames")
    b.add_argument("--encoding", choices=("int16", "float32"), default="int16",
                   help="brick values: int16 HU or float32 (default %(default)s)")
    b.add_argument("--zstd", action="store_true", help="zstd-compressed bricks")
    return p


def view_changes(args: argparse.Namespace) -> dict[str, Any]:
    """The ViewSettings fields the command line sets (the others keep the session's value)."""
    view: dict[str, Any] = {}
    if args.size is not None:
        view["width"], view["height"] = args.size
    if args.preset is not None:
        view["preset"] = args.preset
    if args.azimuth is not None:
        view["azimuth_deg"] = args.azimuth
    if args.elevation is not None:
        view["elevation_deg"] = args.elevation
    if args.zoom is not None:
        view["zoom"] = args.zoom
    if args.quality is not None:
        view["jpeg_quality"] = args.quality
    if args.center is not None:
        view["look_at_tip"] = False
        view["center_mm"] = args.center
    if args.no_tip_marker:
        view["show_tip"] = False
    if args.show_proxy:
        view["show_proxy"] = True
    return view


# ---------------------------------------------------------------------------------------
# Outputs


class PngSink:
    """Numbered PNG files in a folder: PREFIX_000001.png, PREFIX_000002.png, ..."""

    def __init__(self, folder: Path, prefix: str):
        self.folder, self.prefix, self.count = Path(folder), prefix, 0
        self.folder.mkdir(parents=True, exist_ok=True)

    def add(self, rgb: np.ndarray) -> Path:
        from PIL import Image

        self.count += 1
        path = self.folder / f"{self.prefix}_{self.count:06d}.png"
        # compress_level 2: a 1280x720 frame in a few ms, so the viewer keeps up
        Image.fromarray(rgb).save(path, compress_level=2)
        return path


class Mp4Sink:
    """An MP4 (h264, yuv420p) written with imageio-ffmpeg. The first frames (up to
    MP4_FPS_PROBE_FRAMES or MP4_FPS_PROBE_S of server time) are held back to measure the
    frame rate on the server's clock (the times the frames were published), so the video
    lasts as long as what it shows; with fewer than two frames it is 30 fps. yuv420p needs
    even sizes: an odd edge is padded by one repeated pixel row or column. Frames of
    another size than the first (someone changed the session's view) are resized to it."""

    def __init__(self, path: Path, fps: float | None = None):
        self.path = Path(path)
        self.fps = fps
        self.count = 0
        self._held: list[tuple[np.ndarray, float]] = []
        self._writer: Any = None
        self._size: tuple[int, int] | None = None  # (width, height) of the video
        self._resized_warned = False
        self.path.parent.mkdir(parents=True, exist_ok=True)

    def add(self, rgb: np.ndarray, time_s: float) -> None:
        if self._writer is None and self.fps is None:
            self._held.append((rgb, time_s))
            span = self._held[-1][1] - self._held[0][1]
            if len(self._held) >= MP4_FPS_PROBE_FRAMES or span >= MP4_FPS_PROBE_S:
                self._open()
            return
        if self._writer is None:
            self._open()
        self._write(rgb)

    def _measured_fps(self) -> float:
        times = [t for _, t in self._held]
        if len(times) >= 2 and times[-1] > times[0]:
            return float(min(max((len(times) - 1) / (times[-1] - times[0]), 1.0), 240.0))
        return DEFAULT_MP4_FPS

    def _open(self) -> None:
        import imageio.v2 as imageio

        if self.fps is None:
            self.fps = round(self._measured_fps(), 3)
        self._writer = imageio.get_writer(
            str(self.path), format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
            pixelformat="yuv420p", macro_block_size=1, ffmpeg_log_level="error")
        held, self._held = self._held, []
        for rgb, _ in held:
            self._write(rgb)

    def _write(self, rgb: np.ndarray) -> None:
        h, w = rgb.shape[:2]
        if self._size is None:
            self._size = (w + w % 2, h + h % 2)
        vw, vh = self._size
        if (w + w % 2, h + h % 2) != (vw, vh):
            from PIL import Image

            if not self._resized_warned:
                _say(f"{self.path}: frames changed size to {w}x{h}; resized to the video's {vw}x{vh}")
                self._resized_warned = True
            rgb = np.asarray(Image.fromarray(rgb).resize((vw, vh), Image.BILINEAR))
            h, w = vh, vw
        if (w, h) != (vw, vh):
            rgb = np.pad(rgb, ((0, vh - h), (0, vw - w), (0, 0)), mode="edge")
        self._writer.append_data(np.ascontiguousarray(rgb))
        self.count += 1

    def close(self) -> None:
        """Writes what is held back and finishes the file (nothing is written without frames)."""
        if self._writer is None and self._held:
            self._open()
        if self._writer is not None:
            self._writer.close()
            self._writer = None


# ---------------------------------------------------------------------------------------
# Brick slices as an image


def _window(values: np.ndarray, preset: str) -> np.ndarray:
    level, width = SLICE_WINDOWS_HU.get(preset, SLICE_WINDOWS_HU["bone"])
    g = (values.astype(np.float32) - (level - width / 2)) / width
    return (np.clip(g, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def slices_image(slices: Slices, preset: str = "bone", min_edge_px: int = 256,
                 title: str = "") -> np.ndarray:
    """The three slices side by side as one RGB image: axial (rows j, columns i), coronal
    (rows k upwards, columns i) and sagittal (rows k upwards, columns j), each in the
    preset's HU window, scaled up by a whole factor to at least `min_edge_px`, with a red
    cross at the slices' voxel and a label."""
    from PIL import Image, ImageDraw

    i, j, k = slices.index
    panels = [("axial k=%d" % k, slices.axial, (i, j)),                           # [j, i]
              ("coronal j=%d" % j, slices.coronal[::-1], (i, slices.coronal.shape[0] - 1 - k)),
              ("sagittal i=%d" % i, slices.sagittal[::-1], (j, slices.sagittal.shape[0] - 1 - k))]
    largest = max(max(a.shape) for _, a, _ in panels)
    scale = max(1, math.ceil(min_edge_px / max(largest, 1)))
    images = []
    for label, a, (cx, cy) in panels:
        g = _window(a, preset)
        img = Image.fromarray(g).convert("RGB").resize((a.shape[1] * scale, a.shape[0] * scale),
                                                      Image.NEAREST)
        d = ImageDraw.Draw(img)
        x, y = cx * scale + scale // 2, cy * scale + scale // 2
        r = max(6, 3 * scale)
        d.line([(x - r, y), (x + r, y)], fill=(255, 40, 40), width=1)
        d.line([(x, y - r), (x, y + r)], fill=(255, 40, 40), width=1)
        d.text((4, 2), label, fill=(255, 255, 0))
        images.append(img)
    gap = 4
    head = 14 if title else 0
    w = sum(im.width for im in images) + gap * (len(images) - 1)
    h = max(im.height for im in images) + head
    canvas = Image.new("RGB", (w, h), (0, 0, 0))
    x = 0
    for im in images:
        canvas.paste(im, (x, head))
        x += im.width + gap
    if title:
        ImageDraw.Draw(canvas).text((4, 1), title, fill=(255, 255, 255))
    return np.asarray(canvas)


# ---------------------------------------------------------------------------------------
# The live window


# interactive matplotlib backends to try when the current one draws no window (another
# module may have picked Agg): Tk first, the toolkit scripts/setup.sh installs (a Qt
# wheel whose xcb plugin lacks a system library aborts the process instead of raising)
GUI_BACKENDS = ("tkagg", "qtagg", "gtk4agg", "gtk3agg", "wxagg")

# what Qt's xcb platform plugin (PyQt6's wheel) needs from Debian besides the wheel
QT_XCB_DEBS = "libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1 libxkbcommon-x11-0"

# the Python modules of those backends' toolkits: one of them must import for a window
GUI_TOOLKIT_MODULES = ("_tkinter", "PyQt6", "PySide6", "PyQt5", "PySide2", "gi", "wx")


def _display_name() -> str:
    """$DISPLAY (or $WAYLAND_DISPLAY) as the messages name it."""
    if os.environ.get("DISPLAY"):
        return f"$DISPLAY={os.environ['DISPLAY']}"
    return f"$WAYLAND_DISPLAY={os.environ.get('WAYLAND_DISPLAY', '')}"


def _toolkit_present(module: str) -> bool:
    """Whether the toolkit module `module` imports in this interpreter."""
    import importlib

    try:
        importlib.import_module(module)
        return True
    except Exception:  # ImportError, or a broken binding that fails while loading
        return False


def missing_toolkit_hint() -> str:
    """How to give this interpreter a GUI toolkit for matplotlib: Debian's python3-tk for
    Debian's python3 (and the venvs made from it, as scripts/setup.sh makes .venv), else a
    Python built with Tk; or PyQt6 from PyPI (its wheels bring Qt) with the few X
    libraries its xcb plugin loads."""
    exe = sys.executable or "python"
    qt = (f"or '{exe} -m pip install PyQt6' for matplotlib's QtAgg (with "
          f"'apt-get install {QT_XCB_DEBS}' for its xcb plugin)")
    if os.path.realpath(sys.base_prefix) == "/usr" and os.path.isfile("/etc/debian_version"):
        return (f"{exe} (Debian's python3) has no tkinter: install it with "
                f"'apt-get install python3-tk' (scripts/setup.sh does), {qt}")
    return (f"{exe} has no tkinter (a Python built without Tk: with pyenv, "
            f"'apt-get install tk-dev' and install the version again), {qt}")


def gui_problem() -> str | None:
    """None where the live window can open: a display exists and matplotlib has an
    interactive backend that opens a figure on it. Otherwise the sentence saying what is
    missing: the display, a GUI toolkit (with how to install one), or the display's
    refusal. The current backend is kept when it is interactive; otherwise GUI_BACKENDS
    are tried ($MPLBACKEND naming a non-interactive one is the user's choice)."""
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display ($DISPLAY and $WAYLAND_DISPLAY are unset)"
    try:
        import matplotlib
        import matplotlib.pyplot as plt

        try:
            from matplotlib.backends import BackendFilter, backend_registry
            interactive = {b.lower() for b in backend_registry.list_builtin(BackendFilter.INTERACTIVE)}
        except ImportError:  # matplotlib < 3.9
            from matplotlib import rcsetup
            interactive = {b.lower() for b in rcsetup.interactive_bk}
    except Exception as e:
        return f"matplotlib cannot be imported: {e}"
    env = os.environ.get("MPLBACKEND", "").lower()
    if env and env not in interactive:
        return f"$MPLBACKEND={env} is a matplotlib backend that draws no window"
    failures = []
    for backend in (matplotlib.get_backend().lower(), *GUI_BACKENDS):
        if backend not in interactive:
            continue
        try:
            if backend != matplotlib.get_backend().lower():
                plt.switch_backend(backend)
            fig = plt.figure()
            plt.close(fig)
            return None
        except Exception as e:  # the toolkit is missing or cannot reach the display
            failures.append(f"{backend}: {e}")
    if not any(_toolkit_present(m) for m in GUI_TOOLKIT_MODULES):
        return (f"{_display_name()} is there, but matplotlib has no GUI toolkit: "
                f"{missing_toolkit_hint()}")
    return (f"cannot open a window on {_display_name()} (is its X server or compositor "
            f"running and open to this user?): {'; '.join(failures) or 'no backend tried'}")


class ViewController:
    """The live window's keys as view changes: arrows orbit (azimuth, elevation) by
    ORBIT_STEP_DEG, + and - zoom by ZOOM_STEP, p cycles the presets; q (or escape) quits.
    Starts from the session's effective view (WatchReply.view); `key()` returns the
    fields to send, or None for a key that changes nothing."""

    def __init__(self, view: "wire.ViewSettings"):
        self.azimuth_deg = view.azimuth_deg
        self.elevation_deg = view.elevation_deg
        self.zoom = view.zoom if view.zoom > 0 else 1.0
        self.preset = view.preset or "bone"
        self.quit = False

    def key(self, key: str | None) -> dict[str, Any] | None:
        if key in ("q", "escape"):
            self.quit = True
            return None
        if key in ("left", "right"):
            self.azimuth_deg += ORBIT_STEP_DEG if key == "right" else -ORBIT_STEP_DEG
            self.azimuth_deg = (self.azimuth_deg + 180.0) % 360.0 - 180.0
            return {"azimuth_deg": self.azimuth_deg}
        if key in ("up", "down"):
            step = ORBIT_STEP_DEG if key == "up" else -ORBIT_STEP_DEG
            self.elevation_deg = float(np.clip(self.elevation_deg + step, -ELEVATION_LIMIT_DEG,
                                               ELEVATION_LIMIT_DEG))
            return {"elevation_deg": self.elevation_deg}
        if key in ("+", "=", "-", "_"):
            f = ZOOM_STEP if key in ("+", "=") else 1.0 / ZOOM_STEP
            self.zoom = float(np.clip(self.zoom * f, *ZOOM_RANGE))
            return {"zoom": self.zoom}
        if key == "p":
            i = PRESETS.index(self.preset) if self.preset in PRESETS else -1
            self.preset = PRESETS[(i + 1) % len(PRESETS)]
            return {"preset": self.preset}
        return None


class LiveWindow:
    """A matplotlib figure showing the newest image; keys go to `on_key`."""

    def __init__(self, title: str, on_key: Callable[[str], None]):
        import matplotlib
        import matplotlib.pyplot as plt

        # the default key bindings that would fight ours (back/forward, pan, zoom, save, quit)
        for name in ("keymap.back", "keymap.forward", "keymap.pan", "keymap.zoom",
                     "keymap.quit", "keymap.fullscreen", "keymap.save"):
            if name in matplotlib.rcParams:
                matplotlib.rcParams[name] = []
        self._plt = plt
        self.fig = plt.figure(title, figsize=(10, 6))
        self.ax = self.fig.add_axes((0, 0, 1, 0.95))
        self.ax.set_axis_off()
        self.image: Any = None
        self.closed = False
        self.fig.canvas.mpl_connect("key_press_event", lambda e: on_key(e.key))
        self.fig.canvas.mpl_connect("close_event", lambda e: setattr(self, "closed", True))
        plt.show(block=False)

    def show(self, rgb: np.ndarray, caption: str) -> None:
        if self.image is None or self.image.get_array().shape != rgb.shape:
            self.ax.clear()
            self.ax.set_axis_off()
            self.image = self.ax.imshow(rgb, interpolation="nearest")
        else:
            self.image.set_data(rgb)
        self.ax.set_title(caption, fontsize=9)
        self.fig.canvas.draw_idle()

    def pump(self, seconds: float = 0.001) -> None:
        """Runs the GUI's event loop a moment (draws, delivers keys)."""
        if not self.closed:
            self.fig.canvas.flush_events()
            self.fig.canvas.start_event_loop(seconds)

    def close(self) -> None:
        self._plt.close(self.fig)


# ---------------------------------------------------------------------------------------
# The viewer


class Viewer:
    """One watch: the stream, the volume (with --bricks) and the outputs."""

    def __init__(self, args: argparse.Namespace, client: Client, reply: "wire.WatchReply"):
        self.args = args
        self.client = client
        self.reply = reply
        self.bricks = bool(args.bricks)
        self.stream = StreamClient.from_watch(reply, args.connect, curve=client.curve)
        self.volume = DeformedVolume() if self.bricks else None
        self.shown = 0                      # frames (or VOI bricks) written / shown
        self.png: PngSink | None = None
        self.mp4: Mp4Sink | None = None
        self.window: LiveWindow | None = None
        self.controller = ViewController(reply.view)
        self.slice_preset = args.preset or "bone"
        self.slice_point_mm: np.ndarray | None = (np.asarray(args.center, dtype=float)
                                                  if args.center is not None else None)
        self._warned_incomplete = False
        self.interrupted = False

    def open_outputs(self, live: bool) -> None:
        if self.args.out is not None:
            self.png = PngSink(self.args.out, "bricks" if self.bricks else "frame")
        if self.args.mp4 is not None:
            self.mp4 = Mp4Sink(self.args.mp4)
        if live:
            what = "bricks" if self.bricks else "frames"
            self.window = LiveWindow(f"{PROG} {self.reply.session_id:016x} {what}", self._on_key)

    def _on_key(self, key: str) -> None:
        if self.bricks:
            if key in ("q", "escape"):
                self.controller.quit = True
            elif key == "p":
                i = PRESETS.index(self.slice_preset) if self.slice_preset in PRESETS else -1
                self.slice_preset = PRESETS[(i + 1) % len(PRESETS)]
            return
        changes = self.controller.key(key)
        if changes:
            self.send_view(changes)

    def send_view(self, changes: dict[str, Any]) -> None:
        """Sends the session a new view; a refusal is printed and the viewer goes on."""
        try:
            self.client.watch(session_id=self.reply.session_id, frames=True, view=changes)
        except ServerError as e:
            _say(f"view change {changes} refused: {e.code_name}: {e.message}")
        except ServerTimeout as e:
            _say(f"view change {changes}: {e}")

    def run(self) -> int:
        """Receives until done; returns the exit status. Waits in short slices so that
        Ctrl-C (`interrupted`, set by main's SIGINT handler) ends it between two frames,
        never half-way through writing one."""
        args = self.args
        live = self.window is not None
        slice_s = 0.03 if live else 0.2
        last_message_s = time.monotonic()
        while True:
            if self.interrupted:
                _say("interrupted")
                return EXIT_OK
            if live:
                self.window.pump()
                if self.window.closed or self.controller.quit:
                    return EXIT_OK
            update = self.stream.receive(slice_s)
            if update is None:
                if args.timeout and time.monotonic() - last_message_s >= args.timeout:
                    _say(f"no stream message within {args.timeout:g} s (--timeout); giving up")
                    return EXIT_FAIL
                continue
            last_message_s = time.monotonic()
            if update.frame is not None and not self.bricks:
                self._frame(update.frame)
                if args.frames and self.shown >= args.frames:
                    return EXIT_OK
            for n in update.notices:
                _say(f"notice {n.event}: {n.message}")
            for b in update.bricks:
                assert self.volume is not None
                self.volume.apply(b)
                if not b.key:
                    self._brick(b)
                    if args.frames and self.shown >= args.frames:
                        return EXIT_OK

    def _frame(self, frame: "wire.Frame") -> None:
        rgb = decode_frame(frame)
        self.shown += 1
        if self.png:
            self.png.add(rgb)
        if self.mp4:
            self.mp4.add(rgb, frame.server_time_s)
        if self.window:
            self.window.show(rgb, f"frame {frame.frame_seq}  pose {frame.pose_seq}  "
                                  f"step {frame.deform_step}  pose-to-frame "
                                  f"{frame.pose_to_frame_ms:.1f} ms  {self.controller.preset}")

    def _brick(self, brick: "wire.Brick") -> None:
        v = self.volume
        assert v is not None
        if v.grid is None:
            _say(f"VOI brick {brick.brick_seq} before any key part: not drawn")
            return
        if not v.complete and not self._warned_incomplete:
            _say(f"the key is incomplete ({v.key_parts_seen} of {v.key_parts} parts): "
                 "missing slabs are drawn as 0")
            self._warned_incomplete = True
        if self.args.center is None:
            c = v.voi_center_mm()
            if c is not None:
                self.slice_point_mm = c
        s = v.slices(self.slice_point_mm)
        title = (f"brick {brick.brick_seq}  pose {brick.pose_seq}  step {brick.deform_step}  "
                 f"{'deformed' if brick.deformed else 'undeformed'}  at "
                 f"({s.point_mm[0]:.1f}, {s.point_mm[1]:.1f}, {s.point_mm[2]:.1f}) mm")
        rgb = slices_image(s, self.slice_preset, title=title)
        self.shown += 1
        if self.png:
            self.png.add(rgb)
        if self.mp4:
            self.mp4.add(rgb, brick.server_time_s)
        if self.window:
            self.window.show(rgb, title)

    def close(self) -> None:
        """Finishes the outputs (the MP4's held frames included) and the sockets."""
        errors = []
        if self.mp4:
            try:
                self.mp4.close()
            except Exception as e:  # an ffmpeg failure must not hide the summary
                errors.append(f"{self.args.mp4}: {e}")
        if self.window:
            self.window.close()
        self.stream.close()
        for e in errors:
            _say(e)
        if errors:
            raise OSError("; ".join(errors))

    def summary(self) -> str:
        line = summary_line(self.stream.stats, self.volume, frames=not self.bricks,
                            bricks=self.bricks)
        outs = []
        if self.png:
            outs.append(f"{self.png.count} PNG in {self.args.out}")
        if self.mp4:
            outs.append(f"{self.mp4.count} MP4 frames at {self.mp4.fps or 0:g} fps in {self.args.mp4}")
        return f"{PROG}: {line}" + (f"; {', '.join(outs)}" if outs else "")


def main(argv: Sequence[str] | None = None) -> int:
    """palpsim-view's entry point; returns the exit status (module docstring)."""
    args = build_parser().parse_args(argv)
    try:
        return _watch(args)
    except KeyboardInterrupt:  # before the stream started (the stream loop has its own)
        _say("interrupted")
        return EXIT_OK


def _watch(args: argparse.Namespace) -> int:
    session_id = args.session or 0
    problem = gui_problem() if args.out is None and args.mp4 is None else None
    live = args.out is None and args.mp4 is None and problem is None
    if problem is not None:
        args.out = Path("out/view")
        _say(f"no live window: {problem}; writing PNG files into {args.out} "
             "(give --out or --mp4)")
    view = view_changes(args)
    control_timeout_s = args.timeout or DEFAULT_CONTROL_TIMEOUT_S
    try:
        curve = keys.from_arguments(args)
    except (keys.KeyFileError, RuntimeError) as e:
        _say(str(e))
        return EXIT_USAGE
    with Client(args.connect, timeout_s=control_timeout_s, name=PROG, curve=curve,
                client_token=args.client_token) as client:
        try:
            reply = client.watch(session_id=session_id, frames=not args.bricks, bricks=args.bricks,
                                 view=(view or None) if not args.bricks else None,
                                 brick_encoding=args.encoding,
                                 compression="zstd" if args.zstd else "none")
        except ServerError as e:
            _say(f"{e.code_name}: {e.message}")
            return EXIT_USAGE
        except ServerTimeout as e:
            _say(str(e))
            return EXIT_FAIL
        except PalpsimError as e:
            _say(str(e))
            return EXIT_FAIL
        if not reply.stream_endpoint:
            _say("the server's WatchReply has no stream_endpoint (the scene asks for neither "
                 "frames nor bricks?)")
            return EXIT_FAIL
        v = reply.view
        what = (f"bricks ({args.encoding}{', zstd' if args.zstd else ''})" if args.bricks else
                f"frames {v.width}x{v.height} preset {v.preset}")
        _say(f"watching session {reply.session_id:016x} on {reply.stream_endpoint}: {what}")
        viewer = Viewer(args, client, reply)
        status = EXIT_FAIL
        # Ctrl-C sets a flag that the loop checks between frames (outputs stay whole);
        # without the main thread (an embedding program) KeyboardInterrupt is caught below
        previous = None
        if threading.current_thread() is threading.main_thread():
            previous = signal.signal(signal.SIGINT,
                                     lambda *_: setattr(viewer, "interrupted", True))
        try:
            viewer.open_outputs(live)
            status = viewer.run()
        except SessionClosed as e:
            _say(f"session ended: {e.message or e}")
            status = EXIT_OK
        except UnknownSession as e:
            _say(f"ERROR_UNKNOWN_SESSION: {e.message or e}")
            status = EXIT_USAGE
        except MalformedMessage as e:
            _say(f"malformed stream message: {e}")
            status = EXIT_FAIL
        except StreamError as e:
            _say(str(e))
            status = EXIT_FAIL
        except OSError as e:
            _say(f"cannot write the output: {e}")
            status = EXIT_FAIL
        except KeyboardInterrupt:
            _say("interrupted")
            status = EXIT_OK
        finally:
            try:
                viewer.close()
            except KeyboardInterrupt:
                pass
            except OSError:
                status = EXIT_FAIL
            finally:
                if previous is not None:
                    signal.signal(signal.SIGINT, previous)
            print(viewer.summary(), flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
