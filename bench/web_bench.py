#!/usr/bin/env python3
"""palpsim-web in a real browser: frames per second and pose-to-frame latency as the page
measures them, with the real server, gateway and headless chromium on this machine.

    .venv/bin/python bench/web_bench.py --size 1280x720 --seconds 15     # writes bench/results/web-DATE-MACHINE-COMMIT.json

The page clicks the centre of the 3D view (the phantom's back), then the depth goal
alternates between 3 and 9 mm every `--period` s, so the tip keeps moving and every
frame is new. Measured in the browser over the last `--seconds`:
- frames/s: frames drawn into the page's canvas per second;
- pose to frame: performance.timeOrigin + performance.now() when a frame is drawn, minus
  the wall-clock time the gateway sent the pose it shows (one machine, one clock), p50,
  p90 and p99 (ms), beside the server's own pose_to_frame_ms (pose answered to frame
  published) and the input-to-frame latency (a depth change to the first frame of a pose
  sent after it).
The issue's goals are for a GPU server: 30 frames/s at 1280x720 and pose to frame p50
at most 50 ms on loopback; here the server renders with whatever EGL gives (llvmpipe on a
machine without a GPU), named in the results as the server reports it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "clients" / "python"))

from palpsim.client import Client  # noqa: E402
from palpsim.server import LocalServer  # noqa: E402
from palpsim.web import headless_chromium  # noqa: E402

SCENE = """name: "web bench"
phantom {{ voxel_mm: 2.0 }}
effects {{ haptics: true frames: true }}
render {{ width: {w} height: {h} max_fps: 60 }}
server {{ session_timeout_s: 60 }}
"""


def quantile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def machine() -> str:
    model = "unknown cpu"
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            model = line.split(":", 1)[1].strip()
            break
    return f"{socket.gethostname()}, {model}, {os.cpu_count()} cores"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="1280x720", help="frame size WxH (default 1280x720)")
    p.add_argument("--seconds", type=float, default=15.0, help="measured time (default 15)")
    p.add_argument("--period", type=float, default=0.25, help="depth changes every this long (s)")
    p.add_argument("--build", type=Path, default=ROOT / "build", help="build folder with palpsim-server")
    p.add_argument("--label", default="", help="machine label in the file name (default: cpu-Ncore or gpu)")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results", help="results folder")
    args = p.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip() or "unknown"

    tmp = Path(tempfile.mkdtemp(prefix="palpsim-web-bench-"))
    (tmp / "scene.textproto").write_text(SCENE.format(w=w, h=h))
    srv = LocalServer(args.build / "palpsim-server", scene=tmp / "scene.textproto", log_path=tmp / "server.log")
    srv.start()
    gw = subprocess.Popen([sys.executable, "-m", "palpsim.web", "--connect", srv.address, "--port", "0",
                           "--size", f"{w}x{h}"], stdout=subprocess.PIPE, text=True,
                          cwd=ROOT / "clients" / "python")
    driver = None
    try:
        m = re.match(r"serving on (\S+)", gw.stdout.readline())
        if not m:
            raise SystemExit("palpsim-web did not start")
        driver = headless_chromium(w + 500, h + 300)
        driver.get(m.group(1) + "/")
        stats = lambda: driver.execute_script("return window.palpsimStats")  # noqa: E731
        end = time.monotonic() + 60
        while stats()["frames"] < 1:
            if time.monotonic() > end:
                raise SystemExit("no frame in the browser within 60 s")
            time.sleep(0.1)
        view_w = w - min(h // 3, w)
        driver.execute_script(f"window.palpsim.pick({view_w / 2}, {h / 2})")
        time.sleep(1.0)  # the tip reaches the skin
        # warm up, then measure
        depth = 3.0
        t0 = None
        start_frames = start_inputs = start_p2f = 0
        begin = time.monotonic()
        while True:
            now = time.monotonic()
            if t0 is None and now - begin > 2.0:
                s = stats()
                t0, start_frames = s["recent"][-1][0] if s["recent"] else 0, s["frames"]
                start_inputs, start_p2f = len(s["inputLatencies"]), len(s["poseToFrame"])
                mono0 = now
            if t0 is not None and now - mono0 > args.seconds:
                break
            depth = 9.0 if depth == 3.0 else 3.0
            driver.execute_script(f"window.palpsim.setDepth({depth})")
            time.sleep(args.period)
        s = stats()
        with Client(srv.address) as c:
            st = c.stats().server.stream
        recent = [r for r in s["recent"] if r[0] > t0]
        elapsed_s = (recent[-1][0] - recent[0][0]) / 1e3 if len(recent) > 1 else float("nan")
        p2f = s["poseToFrame"][start_p2f:]
        server_p2f = [r[3] for r in recent if r[3]]
        inputs = s["inputLatencies"][start_inputs:]
        result = {
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(), "platform": platform.platform(), "commit": commit,
            "gl_renderer": st.gl_renderer, "jpeg_encoder": st.jpeg_encoder,
            "size": [w, h], "seconds": args.seconds,
            "load_average_1min": os.getloadavg()[0],  # other work on this machine meanwhile
            "frames_in_browser": len(recent),
            "frames_per_s": (len(recent) - 1) / elapsed_s if len(recent) > 1 else 0.0,
            "pose_to_frame_browser_ms": {"p50": quantile(p2f, 0.5), "p90": quantile(p2f, 0.9),
                                         "p99": quantile(p2f, 0.99), "n": len(p2f)},
            "pose_to_frame_server_ms": {"p50": quantile(server_p2f, 0.5), "p90": quantile(server_p2f, 0.9)},
            "input_to_frame_ms": {"p50": quantile(inputs, 0.5), "p90": quantile(inputs, 0.9), "n": len(inputs)},
        }
        print(json.dumps(result, indent=2))
        label = args.label or (("gpu" if "llvmpipe" not in st.gl_renderer.lower() else f"cpu-{os.cpu_count()}core")
                               + f"-{w}x{h}")
        args.out.mkdir(parents=True, exist_ok=True)
        out = args.out / f"web-{datetime.date.today().isoformat()}-{label}-{commit}.json"
        out.write_text(json.dumps(result, indent=2) + "\n")
        print(f"written {out}")
        print(f"{w}x{h}: {result['frames_per_s']:.1f} frames/s in the browser, pose to frame p50 "
              f"{result['pose_to_frame_browser_ms']['p50']:.1f} ms (server's part "
              f"{result['pose_to_frame_server_ms']['p50']:.1f} ms), input to frame p50 "
              f"{result['input_to_frame_ms']['p50']:.0f} ms; {st.gl_renderer}")
        return 0
    finally:
        if driver is not None:
            driver.quit()
        gw.terminate()
        gw.wait(10)
        srv.stop()


if __name__ == "__main__":
    sys.exit(main())
