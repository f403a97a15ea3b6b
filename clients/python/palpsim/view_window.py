"""palpsim-view's live window: whether one can open here (and what is missing when not),
the keys as view changes, and the matplotlib figure that shows the newest image."""

from __future__ import annotations

import os
import sys
from typing import Any, Callable

import numpy as np

from .proto import wire

PRESETS = ("skin", "bone", "soft_tissue")  # server/render/view.h, in the order p cycles them

# the live window's steps: 10 degrees a key (the brief's orbit step), 1.25x zoom a key,
# elevation kept inside the server's -89..89 and zoom inside 0.1..20 (view.h)
ORBIT_STEP_DEG = 10.0
ZOOM_STEP = 1.25
ELEVATION_LIMIT_DEG = 89.0
ZOOM_RANGE = (0.1, 20.0)


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


def collect_gui_garbage() -> None:
    """Frees a closed figure's toolkit objects now, in this (the GUI's) thread. Tk's
    variables and images sit in reference cycles; left to the cycle collector, they may be
    freed in whatever thread allocates next, where each one's Tcl call waits about a second
    for a main loop that is not running and then fails, or Tcl aborts the process."""
    import gc

    gc.collect()


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
            plt.close(plt.figure())
            collect_gui_garbage()
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
        """Closes the window and frees its toolkit objects in this thread; again, nothing
        (plt.close(None) would close whichever figure is current)."""
        if self.fig is None:
            return
        fig, self.fig, self.ax, self.image = self.fig, None, None, None
        self.closed = True
        self._plt.close(fig)
        del fig
        collect_gui_garbage()
