#!/usr/bin/env python3
"""Makes the frames shown in the documentation (docs/frame-*.png): starts palpsim-server
on a scene, presses the back at one point (along -y, from above the body: +y is
posterior in LPS, whether the patient lay prone or supine), waits for the frame that
shows the press with its deformation, and writes it as PNG (the server's JPEG decoded,
then stored losslessly).

    .venv/bin/python scripts/docs_frames.py --scene config/scenes/lumbar_phantom.textproto \\
        --z-mm -5 --azimuth 80 --elevation 20 --zoom 2.1 --out docs/frame-phantom.png
    .venv/bin/python scripts/docs_frames.py --scene config/scenes/lumbar_ct.textproto \\
        --find-near 364 --azimuth 55 --elevation 15 --zoom 2 --out docs/frame-ct.png

--find-near Z palpates a line along the back first, as palpsim-demo does (2 mm apart,
22 mm under the skin, from Z - 40 to Z + 40 mm at --x-mm), and presses at the force
peak (a spinous process) nearest to Z. The press itself is palpsim.record's: the skin is
found along the press line, the tip goes --depth-mm under it, and the frame kept is the
first whose pose and deformation are at that depth. The camera and the slices look at
the point --look-at-depth-mm under the skin point (default 50: the spine nearer the
middle of the 3D view, the slices from just above the skin to the vertebral arch); the
other view settings default to the demo recording's (palpsim.record.DEFAULT_VIEW) with
110 mm slices. A zoomed 1280x720 frame takes a few seconds on a CPU (Mesa llvmpipe).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def build_parser() -> argparse.ArgumentParser:
    from palpsim.record import DEFAULT_VIEW

    p = argparse.ArgumentParser(prog="docs_frames.py", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--server", help="palpsim-server (default: $PALPSIM_BUILD_DIR or build/)")
    p.add_argument("--scene", required=True, help="scene file (with effects.frames)")
    p.add_argument("--out", required=True, type=Path, help="PNG to write")
    where = p.add_argument_group("where to press (mm, LPS)")
    where.add_argument("--x-mm", type=float, help="x of the press (default: the body's mid x)")
    z = where.add_mutually_exclusive_group(required=True)
    z.add_argument("--z-mm", type=float, help="z of the press")
    z.add_argument("--find-near", type=float, metavar="Z",
                   help="palpate Z-40..Z+40 mm along the back and press at the force peak "
                        "nearest to Z")
    where.add_argument("--depth-mm", type=float, default=15.0,
                       help="depth under the skin (default %(default)g)")
    v = p.add_argument_group("view (default: palpsim.record's)")
    v.add_argument("--size", default="1280x720", help="WxH (default %(default)s)")
    v.add_argument("--azimuth", type=float, default=DEFAULT_VIEW["azimuth_deg"])
    v.add_argument("--elevation", type=float, default=DEFAULT_VIEW["elevation_deg"])
    v.add_argument("--zoom", type=float, default=DEFAULT_VIEW["zoom"])
    v.add_argument("--slice-fov-mm", type=float, default=110.0)
    v.add_argument("--look-at-depth-mm", type=float, default=50.0,
                   help="the camera and slices look at the point this far under the skin "
                        "point (default %(default)g)")
    v.add_argument("--preset", default=DEFAULT_VIEW["preset"])
    v.add_argument("--quality", type=int, default=95, help="the server's JPEG quality")
    return p


def find_process(address: str, info, x_mm: float, near_z_mm: float) -> float:
    """z of the force peak nearest to near_z_mm on a line of presses along the back."""
    from palpsim.batch import run_plan
    from palpsim.demo import force_peaks, make_plan

    line = argparse.Namespace(x_mm=x_mm, z_from_mm=near_z_mm - 40.0, z_to_mm=near_z_mm + 40.0,
                              step_mm=2.0, depth_mm=22.0, speed_mm_per_s=20.0, rate_hz=500.0)
    plan = make_plan(info, line)
    result = run_plan(plan, address, sessions=1, progress=False)
    z, force, peaks, prominence, _ = force_peaks(result.table, plan)
    print(f"[docs] line at x = {x_mm:.1f} mm, z {z.min():.0f}..{z.max():.0f} mm: peaks "
          + (", ".join(f"z {p.position_mm:.1f} ({p.height:.2f} N, +{p.prominence:.2f})"
                       for p in peaks) or "none"))
    if not peaks:
        raise SystemExit(f"docs_frames.py: no force peak (prominence {prominence:.2f} N) on the "
                         f"line near z = {near_z_mm:g} mm; give --z-mm")
    return min(peaks, key=lambda p: abs(p.position_mm - near_z_mm)).position_mm


def main(argv: list[str] | None = None) -> int:
    from PIL import Image

    from palpsim.client import Client
    from palpsim.record import record_press
    from palpsim.server import LocalServer, find_server

    args = build_parser().parse_args(argv)
    w, h = (int(t) for t in args.size.lower().split("x"))
    binary = Path(args.server) if args.server else find_server()
    if binary is None:
        print("docs_frames.py: no palpsim-server (give --server or set PALPSIM_BUILD_DIR)",
              file=sys.stderr)
        return 1
    with LocalServer(binary, scene=args.scene) as srv:   # its output: quoted if it fails
        with Client(srv.address, timeout_s=30.0) as c:
            info = c.info()
            b0, b1 = info.patient.body_min_mm, info.patient.body_max_mm
            x = args.x_mm if args.x_mm is not None else 0.5 * (b0.x + b1.x)
            z = args.z_mm if args.z_mm is not None else find_process(srv.address, info, x,
                                                                     args.find_near)
            view = {"width": w, "height": h, "preset": args.preset, "show_tip": True,
                    "azimuth_deg": args.azimuth, "elevation_deg": args.elevation,
                    "zoom": args.zoom, "slice_fov_mm": args.slice_fov_mm,
                    "jpeg_quality": args.quality}
            t0 = time.monotonic()
            rec = record_press(c, (x, b1.y + 10.0, z), (0.0, -1.0, 0.0), [args.depth_mm],
                               view=view, look_at_depth_mm=args.look_at_depth_mm,
                               step_timeout_s=300.0)
    (f,) = rec.frames
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(f.rgb).save(args.out, format="PNG", optimize=True)
    fr = f.frame
    print(f"[docs] {info.scene_name}: pressed ({x:.1f}, {rec.skin_mm[1]:.1f} -> "
          f"{f.tip_mm[1]:.1f}, {z:.1f}) mm, depth {f.reply.depth_mm:.1f} mm, force "
          f"{np.linalg.norm(f.reply.force_n):.2f} N, deformation step {fr.deform_step} "
          f"({'deformed' if fr.deformed else 'undeformed'}); frame {fr.width}x{fr.height} "
          f"rendered in {fr.times.total_ms / 1000:.1f} s, {time.monotonic() - t0:.1f} s in all; "
          f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT / "clients" / "python"))
    sys.exit(main())
