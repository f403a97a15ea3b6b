"""A Ray cluster of several nodes on this one machine, for tests and benchmarks of studies.

    with LocalRayCluster(nodes=2, cpus_per_node=1) as cluster:
        run_study(study, out, ray_address=cluster.address)

Each node is a `ray start` of its own (the head with `--head`, the others with
`--address`) on its own loopback address, 127.0.0.2, 127.0.0.3, ... (Ray replaces
127.0.0.1 by the machine's outward address, so the nodes take other addresses of the
loopback range; nothing leaves the machine). A node may get its own environment (say its
own PALPSIM_CACHE, as a separate machine would have). stop() ends exactly the processes
of this cluster: those whose command line names its temporary folder, and their children.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Mapping

_ADDRESS = re.compile(r"--address='([^']+)'")


class RayClusterError(RuntimeError):
    """`ray start` failed or is not installed; the message quotes its output."""


def ray_command() -> str | None:
    """The `ray` command of this Python environment (or on PATH); None without one."""
    beside = Path(sys.executable).parent / "ray"
    if beside.is_file():
        return str(beside)
    return shutil.which("ray")


class LocalRayCluster:
    """Ray nodes on this machine, each a separate `ray start`; a context manager."""

    def __init__(self, nodes: int = 2, cpus_per_node: int = 1,
                 node_env: list[Mapping[str, str]] | None = None, object_store_mb: int = 100,
                 gpus_per_node: int = 0, first_ip: int = 2):
        """gpus_per_node: GPUs each node declares to Ray (a machine without GPUs can
        declare some to exercise one-worker-per-GPU scheduling: Ray then gives each
        worker its CUDA_VISIBLE_DEVICES, and the servers fall back to the CPU);
        first_ip: node n listens on 127.0.0.(first_ip + n), so two clusters can coexist."""
        self.nodes = nodes
        self.cpus_per_node = cpus_per_node
        self.gpus_per_node = gpus_per_node
        self.first_ip = first_ip
        self.node_env = list(node_env or [])
        self.object_store_mb = object_store_mb
        # Ray's socket paths must stay short: a folder directly under /tmp
        self.temp_dir = tempfile.mkdtemp(prefix="psray-", dir="/tmp")
        self.address: str | None = None
        self.started = 0

    def _start(self, args: list[str], index: int) -> str:
        """Runs one `ray start` for node `index`; returns its output."""
        ray = ray_command()
        if ray is None:
            raise RayClusterError("the `ray` command is missing (pip install 'ray==2.60.0')")
        env = dict(os.environ)
        env.update(self.node_env[index] if index < len(self.node_env) else {})
        cmd = [ray, "start", "--node-ip-address", f"127.0.0.{self.first_ip + index}",
               "--num-cpus", str(self.cpus_per_node), "--num-gpus", str(self.gpus_per_node),
               "--object-store-memory", str(self.object_store_mb * 1024 * 1024),
               "--disable-usage-stats"] + args
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
        if p.returncode != 0:
            raise RayClusterError(f"{' '.join(cmd)} failed ({p.returncode}):\n"
                                  f"{(p.stdout + p.stderr)[-3000:]}")
        return p.stdout + p.stderr

    def start(self) -> str:
        """Starts the head and the other nodes; returns the cluster's address."""
        out = self._start(["--head", "--port", "0", "--include-dashboard=false",
                           "--temp-dir", self.temp_dir], 0)
        m = _ADDRESS.search(out)
        if not m:
            self.stop()
            raise RayClusterError(f"ray start --head printed no address:\n{out[-3000:]}")
        self.address = m.group(1)
        self.started = 1
        for _ in range(1, self.nodes):
            self.add_node()
        return self.address

    def add_node(self) -> None:
        """Starts one more node of the cluster."""
        self._start(["--address", self.address], self.started)
        self.started += 1

    def pids(self, node: int | None = None) -> list[int]:
        """The processes of this cluster (of one node: its raylet's children and itself)."""
        procs = _processes()
        ours = {pid for pid, (_, args) in procs.items()
                if self.temp_dir in args and pid != os.getpid()}
        if node is not None:
            ip = f"--node_ip_address=127.0.0.{self.first_ip + node}"
            ours = {pid for pid in ours if ip in procs[pid][1] and "raylet" in procs[pid][1]}
        # their children, grandchildren (workers, agents, palpsim-servers)
        grown = True
        while grown:
            kids = {pid for pid, (ppid, _) in procs.items() if ppid in ours} - ours
            grown = bool(kids)
            ours |= kids
        return sorted(ours)

    def kill_node(self, node: int) -> None:
        """Kills one node (not the head) at once: its raylet and everything under it."""
        for pid in self.pids(node):
            _signal(pid, signal.SIGKILL)

    def stop(self) -> None:
        """Ends this cluster's processes (SIGTERM, then SIGKILL) and removes its folder."""
        pids = self.pids()
        for pid in pids:
            _signal(pid, signal.SIGTERM)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(_running(p) for p in pids):
            time.sleep(0.1)
        for pid in self.pids():
            _signal(pid, signal.SIGKILL)
        shutil.rmtree(self.temp_dir, ignore_errors=True)

    def __enter__(self) -> "LocalRayCluster":
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _processes() -> dict[int, tuple[int, str]]:
    """pid -> (parent pid, command line) of every process (Linux /proc)."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            args = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        out[int(d.name)] = (ppid, args)
    return out


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def _running(pid: int) -> bool:
    """The process exists and has not exited (a zombie waiting for its parent has)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False
