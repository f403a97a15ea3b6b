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
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from . import keys
from .client import Client, PalpsimError, ServerError, ServerTimeout
from .proto import wire
from .stream import (DeformedVolume, MalformedMessage, SessionClosed, StreamClient,
                     StreamError, UnknownSession, decode_frame, summary_line)
from .view_outputs import PROG, Mp4Sink, PngSink, _say, slices_image
from .view_window import PRESETS, LiveWindow, ViewController, gui_problem


DEFAULT_CONTROL_TIMEOUT_S = 10.0

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


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
        title = (f"frame {frame.frame_seq}  pose {frame.pose_seq}  step {frame.deform_step}  "
                 f"pose-to-frame {frame.pose_to_frame_ms:.1f} ms  {self.controller.preset}")
        self._show(decode_frame(frame), frame.server_time_s, title)

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
        self._show(slices_image(s, self.slice_preset, title=title), brick.server_time_s, title)

    def _show(self, rgb: np.ndarray, server_time_s: float, title: str) -> None:
        """Counts one image shown and hands it to each output asked for: PNG, MP4, window."""
        self.shown += 1
        if self.png:
            self.png.add(rgb)
        if self.mp4:
            self.mp4.add(rgb, server_time_s)
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
