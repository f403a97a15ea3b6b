"""Starts a local palpsim-server, waits for its "ready on ADDR" line, and stops it again.

    with LocalServer("build/palpsim-server", scene="config/scenes/lumbar_phantom.textproto") as srv:
        run_plan(plan, srv.address)

The server binds loopback on a port the system picks (tcp://127.0.0.1:*) unless told
otherwise; its output goes to a log file (or is kept in memory) and its last lines are
quoted when it fails to start.
"""

from __future__ import annotations

import collections
import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Iterator, Sequence

READY = re.compile(r"ready on (\S+)")


class ServerStartError(RuntimeError):
    """palpsim-server could not be started, or exited before it was ready."""


def find_server(build_dir: str | Path | None = None) -> Path | None:
    """palpsim-server in `build_dir` (or $PALPSIM_BUILD_DIR, or build/ beside the repository
    root), else on PATH; None when there is none."""
    candidates = []
    for d in (build_dir, os.environ.get("PALPSIM_BUILD_DIR")):
        if d:
            candidates.append(Path(d) / "palpsim-server")
    root = Path(__file__).resolve().parents[3]
    candidates.append(root / "build" / "palpsim-server")
    for c in candidates:
        if c.is_file() and os.access(c, os.X_OK):
            return c
    found = shutil.which("palpsim-server")
    return Path(found) if found else None


class LocalServer:
    """A palpsim-server child process, ready to serve once start() returns."""

    def __init__(self, binary: str | Path, scene: str | Path | None = None,
                 bind: str = "tcp://127.0.0.1:*", extra_args: Sequence[str] = (),
                 startup_timeout_s: float = 300.0, log_path: str | Path | None = None,
                 die_with_parent: bool = False):
        self.binary = Path(binary)
        self.scene = scene
        self.bind = bind
        self.extra_args = list(extra_args)
        self.startup_timeout_s = startup_timeout_s
        self.log_path = Path(log_path) if log_path else None
        # a server started by a worker that may be killed (a Ray actor) must not outlive it
        self.die_with_parent = die_with_parent
        self.address: str | None = None
        self.proc: subprocess.Popen[str] | None = None
        self._tail: collections.deque[str] = collections.deque(maxlen=40)
        self._ready = threading.Event()
        self._reader: threading.Thread | None = None
        self._log: IO[str] | None = None

    def command(self) -> list[str]:
        """The command line that starts the server."""
        cmd = [str(self.binary), "--bind", self.bind]
        if self.scene:
            cmd += ["--scene", str(self.scene)]
        return cmd + self.extra_args

    def start(self) -> str:
        """Starts the server and returns its control address once it says it is ready."""
        if not (self.binary.is_file() and os.access(self.binary, os.X_OK)):
            raise ServerStartError(f"{self.binary}: no palpsim-server executable there "
                                   "(build it, or give its path)")
        if self.log_path:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(self.command(), stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1,
                                     preexec_fn=_term_with_parent if self.die_with_parent else None)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        deadline = time.monotonic() + self.startup_timeout_s
        while not self._ready.wait(0.1):
            if self.proc.poll() is not None:
                self._reader.join(2)
                raise ServerStartError(f"{self.binary} exited with status {self.proc.returncode} "
                                       f"before it was ready; its last output:\n{self.tail()}")
            if time.monotonic() > deadline:
                self.stop()
                raise ServerStartError(f"{self.binary} did not say 'ready on ADDR' within "
                                       f"{self.startup_timeout_s:g} s; its last output:\n{self.tail()}")
        return self.address  # type: ignore[return-value]

    def _read(self) -> None:
        """Drains the server's output (so it never blocks on a full pipe), watching for ready."""
        assert self.proc and self.proc.stdout
        for line in self.proc.stdout:
            self._tail.append(line.rstrip("\n"))
            if self._log:
                self._log.write(line)
                self._log.flush()
            if not self._ready.is_set():
                m = READY.search(line)
                if m:
                    self.address = m.group(1)
                    self._ready.set()

    def tail(self) -> str:
        """The server's last output lines."""
        return "\n".join(self._tail) or "(no output)"

    def stop(self, timeout_s: float = 10.0) -> int | None:
        """Asks the server to stop (SIGINT), kills it if it does not within timeout_s;
        returns its exit status."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if self._reader:
            self._reader.join(2)
        if self._log:
            self._log.close()
            self._log = None
        return self.proc.returncode

    def __enter__(self) -> "LocalServer":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _term_with_parent() -> None:
    """In the child before exec: Linux sends it SIGTERM (a clean stop) when the thread that
    started it exits, so a killed worker leaves no server behind (elsewhere: nothing)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)


@contextlib.contextmanager
def serving(address: str | None, binary: str | Path | None, scene: str | Path | None = None,
            log_path: str | Path | None = None) -> Iterator[str]:
    """The control address of a server for the block: `address` as given, or else that of a
    LocalServer of `binary` (with `scene`, output to `log_path`) started on entry and
    stopped on leaving, also when its start or the block fails. The batch runner and the
    demo both run their plans inside it."""
    if address:
        yield address
        return
    if binary is None:
        raise ValueError("serving: give a server address or a palpsim-server binary")
    server = LocalServer(binary, scene=scene, log_path=log_path)
    try:
        yield server.start()
    finally:
        server.stop()
