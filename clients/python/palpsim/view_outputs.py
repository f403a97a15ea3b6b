"""palpsim-view's outputs: numbered PNG files, an MP4 at the rate measured on the server's
clock, and the VOI brick's three slices as one image (palpsim.view writes them;
palpsim.record's videos use the MP4 writer)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .stream import Slices

PROG = "palpsim-view"

# HU windows (level, width) of the brick slices per preset: what each preset looks at
SLICE_WINDOWS_HU = {"skin": (-200.0, 1000.0), "bone": (400.0, 1800.0),
                    "soft_tissue": (40.0, 400.0)}

DEFAULT_MP4_FPS = 30.0
MP4_FPS_PROBE_FRAMES = 30   # frames (or 2 s of server time) buffered to measure the frame rate
MP4_FPS_PROBE_S = 2.0


def _say(text: str) -> None:
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


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
