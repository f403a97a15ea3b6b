#!/usr/bin/env python3
"""Prints palpsim-server's resident memory over scene reloads and watch/close cycles, and
where it is: the glibc arenas, blocks mapped for themselves, code and the rest.

    .venv/bin/python scripts/memory_bench.py                                  # the shipped 1 mm phantom scene
    .venv/bin/python scripts/memory_bench.py --reloads 20 --cycles 20 --width 3840 --height 2160
    .venv/bin/python scripts/memory_bench.py --server /tmp/old/palpsim-server --json old.json

It starts the server on --scene (default config/scenes/lumbar_phantom.textproto), lets it
settle, reloads the same scene --reloads times (LoadScene by path), then runs --cycles
watch/close cycles: a session watched at --width x --height (frames and float32 bricks)
by --subscribers SUB sockets that never read, pressed into the back until the server has
rendered a frame of it, then closed with its subscribers. After every --every reloads or
cycles, and at the end, it waits for the memory to settle (the least resident memory over
--settle-s seconds) and prints one row: resident memory (MB) and its parts from
/proc/PID/smaps, by mapping: "arenas" (the main heap and 64 MB-aligned anonymous heaps of
the other threads' arenas: freed memory the allocator keeps is here), "mapped" (other
anonymous mappings: blocks of 4 MB and more, textures, thread stacks), "files" (code and
libraries). The last column is the growth over the first row (the server settled after
start and one watch cycle, so that the render thread's shaders exist). --json writes
every row. The server runs with --background nice (an idle-class render thread may wait
long for a core on a busy machine before it frees a viewer's buffers).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def smaps_parts(pid: int) -> dict[str, float]:
    """Resident memory of `pid` (MB) by kind of mapping, from /proc/PID/smaps."""
    parts = {"arenas": 0.0, "mapped": 0.0, "files": 0.0}
    kind = None
    with open(f"/proc/{pid}/smaps") as f:
        for line in f:
            m = re.match(r"^([0-9a-f]+)-([0-9a-f]+) (\S+) \S+ \S+ \S+\s*(.*)$", line)
            if m:
                start, perms, name = int(m.group(1), 16), m.group(3), m.group(4).strip()
                if name == "[heap]" or (not name and "rw" in perms and start % (64 << 20) == 0):
                    kind = "arenas"
                elif not name or name.startswith("["):
                    kind = "mapped"
                else:
                    kind = "files"
            elif line.startswith("Rss:") and kind:
                parts[kind] += int(line.split()[1]) / 1024
    return parts


def rss_mb(pid: int) -> float:
    """Resident memory of `pid` (MB)."""
    with open(f"/proc/{pid}/status") as f:
        return int(re.search(r"VmRSS:\s+(\d+)", f.read()).group(1)) / 1024


def settled(pid: int, seconds: float) -> float:
    """The least resident memory of `pid` (MB) over `seconds`."""
    least = float("inf")
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        least = min(least, rss_mb(pid))
        time.sleep(0.1)
    return least


def watch_cycle(client, info, width: int, height: int, subscribers: int) -> None:
    """One session watched by subscribers that never read, pressed until a frame of it
    is rendered, then closed with them."""
    import zmq
    session = client.open_session("memory_bench")
    w = client.watch(session.id, frames=True, bricks=True, view={"width": width, "height": height},
                     brick_encoding="float32")
    ctx = zmq.Context.instance()
    subs = []
    for _ in range(subscribers):
        s = ctx.socket(zmq.SUB)
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.RCVHWM, 1)
        s.setsockopt(zmq.RCVBUF, 4096)
        s.connect(w.stream_endpoint)
        s.setsockopt(zmq.SUBSCRIBE, bytes(w.frame_topic))
        s.setsockopt(zmq.SUBSCRIBE, bytes(w.brick_topic))
        subs.append(s)
    p = info.patient
    x = 0.5 * (p.body_min_mm.x + p.body_max_mm.x)
    z = 0.5 * (p.body_min_mm.z + p.body_max_mm.z)
    session.pose([x, p.body_max_mm.y + 5, z])
    session.pose([x, p.body_max_mm.y - 5, z])
    end = time.monotonic() + 120
    while session.stats().stream.frames_rendered == 0 and time.monotonic() < end:
        time.sleep(0.1)
    for s in subs:
        s.close(0)
    session.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", help="palpsim-server (default: $PALPSIM_BUILD_DIR or build/)")
    ap.add_argument("--scene", default=str(ROOT / "config/scenes/lumbar_phantom.textproto"))
    ap.add_argument("--reloads", type=int, default=20)
    ap.add_argument("--cycles", type=int, default=20)
    ap.add_argument("--width", type=int, default=3840)
    ap.add_argument("--height", type=int, default=2160)
    ap.add_argument("--subscribers", type=int, default=3, help="SUB sockets per watched session that never read")
    ap.add_argument("--every", type=int, default=5, help="a row after this many reloads or cycles")
    ap.add_argument("--settle-s", type=float, default=10.0, help="seconds over which a row takes the least RSS")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()

    sys.path.insert(0, str(ROOT / "clients/python"))
    from palpsim.client import Client
    from palpsim.server import LocalServer, find_server

    binary = Path(args.server) if args.server else find_server()
    if binary is None:
        print("memory_bench.py: no palpsim-server (give --server or set PALPSIM_BUILD_DIR)", file=sys.stderr)
        return 2
    scene = Path(args.scene).resolve()
    rows = []
    with LocalServer(binary, scene, extra_args=["--stream-bind", "tcp://127.0.0.1:*", "--background", "nice"]) as srv:
        pid = srv.proc.pid
        client = Client(srv.address, timeout_s=600)
        info = client.info()
        print(f"{binary} on {scene.name}: {info.patient.size_i}x{info.patient.size_j}x{info.patient.size_k} voxels "
              f"at {info.patient.spacing_mm:g} mm; views {args.width}x{args.height}, "
              f"{args.subscribers} subscribers that never read")
        print(f"{'after':<22}{'RSS MB':>8}{'arenas':>8}{'mapped':>8}{'files':>8}{'growth':>9}")

        def row(what: str) -> None:
            rss = settled(pid, args.settle_s)
            parts = smaps_parts(pid)
            growth = rss / rows[0]["rss_mb"] - 1 if rows else 0.0
            rows.append({"after": what, "rss_mb": rss, **{k + "_mb": v for k, v in parts.items()},
                         "growth": growth})
            print(f"{what:<22}{rss:8.0f}{parts['arenas']:8.0f}{parts['mapped']:8.0f}{parts['files']:8.0f}"
                  f"{100 * growth:8.1f}%", flush=True)

        watch_cycle(client, info, args.width, args.height, args.subscribers)
        row("start, 1 watch cycle")
        for i in range(1, args.reloads + 1):
            t0 = time.monotonic()
            client.load_scene(path=str(scene))
            if i % args.every == 0 or i == args.reloads:
                row(f"{i} reloads ({time.monotonic() - t0:.1f} s)")
        for i in range(1, args.cycles + 1):
            watch_cycle(client, info, args.width, args.height, args.subscribers)
            if i % args.every == 0 or i == args.cycles:
                row(f"{i} watch cycles")
        client.close()
    if args.json:
        # what a committed result needs to be read again: when, where and which code
        import platform
        import subprocess
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True).stdout.strip()
        meta = {"date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "commit": commit,
                "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f} at the end",
                "args": vars(args)}
        Path(args.json).write_text(json.dumps({**meta, "server": str(binary), "scene": str(scene), "rows": rows},
                                              indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
