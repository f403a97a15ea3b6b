"""palpsim-demo: the main job's palpation. Presses a line of points along the midline of
the back (the phantom lies prone: +y, posterior in LPS, faces up) from the sacrum
towards the thorax, each to the same depth under the skin, and shows the force profile
along the back, in which the spinous processes stand out as peaks.

    palpsim-demo                                   # starts build/palpsim-server itself
    palpsim-demo --connect tcp://127.0.0.1:7420    # a server that is already running

Writes into --out: the batch outputs (steps.parquet, summary.json, force_vs_depth.png,
peak_force_map.png) and spine_profile.png, spine.json; prints a summary of the peaks
found and, when the prepared patient (palpsim-prep's bone.nrrd and body.nrrd) is at
hand, where its bone mask puts the spinous processes (the top of each one's posterior edge).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .batch import run_plan, write_outputs
from .client import Client, PalpsimError
from .plan import Plan, PlanError, parse_plan
from .results import point_table, write_json

# the line's default z-range (mm, LPS) on the built-in phantom (server/prep/phantom.cpp):
# its spinous process tips L5..L1 lie near z = -70, -38, -5, 28, 61 mm, each process a
# plate about 14 mm long in z sloping down from its tip; S1's ends above z = -101 mm and
# T12's plate reaches down to z = 78 mm, so this range holds L1-L5 and the gaps around them
PHANTOM_LUMBAR_Z_MM = (-90.0, 72.0)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="palpsim-demo",
        description="Palpate along the lumbar spine of the patient a palpsim-server serves and "
                    "show the force profile along the back (the spinous processes as peaks).")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--connect", metavar="ADDR", help="control address of a running server")
    src.add_argument("--server", metavar="PATH",
                     help="palpsim-server to start (default: $PALPSIM_BUILD_DIR or build/)")
    p.add_argument("--scene", help="scene file for the started server (default: its default, "
                                   "the lumbar phantom)")
    p.add_argument("--patient", metavar="DIR",
                   help="palpsim-prep output of the same patient (bone.nrrd, body.nrrd) for the "
                        "expected process positions (default: out/demo/patient when present)")
    p.add_argument("--out", default="out/demo/palpation", help="output folder (default %(default)s)")
    line = p.add_argument_group("the line of presses (mm, LPS)")
    line.add_argument("--x-mm", type=float, help="x of the line (default: the body's mid x)")
    line.add_argument("--z-from-mm", type=float,
                      help="inferior end of the line (default: %g on the phantom, else 10 mm "
                           "inside the body's z extent)" % PHANTOM_LUMBAR_Z_MM[0])
    line.add_argument("--z-to-mm", type=float,
                      help="superior end of the line (default: %g on the phantom, else 10 mm "
                           "inside the body's z extent)" % PHANTOM_LUMBAR_Z_MM[1])
    line.add_argument("--step-mm", type=float, default=2.0, help="spacing of the presses")
    line.add_argument("--depth-mm", type=float, default=22.0,
                      help="press depth under the skin (default %(default)g: the phantom's "
                           "spinous process tips lie 24 to 31 mm under the skin)")
    line.add_argument("--speed-mm-per-s", type=float, default=20.0)
    line.add_argument("--rate-hz", type=float, default=500.0, help="poses per second")
    p.add_argument("--sessions", type=int, default=2, help="parallel sessions")
    p.add_argument("--tolerance-mm", type=float, default=6.0,
                   help="a peak within this of an expected process counts as found")
    p.add_argument("--no-progress", action="store_true")
    return p


def make_plan(info: Any, args: argparse.Namespace) -> Plan:
    """The demo's plan: a line along z over the back, pressed along -y from above the body."""
    body_min, body_max = info.patient.body_min_mm, info.patient.body_max_mm
    x = args.x_mm if args.x_mm is not None else 0.5 * (body_min.x + body_max.x)
    # the phantom's lumbar spine, or (another patient) the whole back that was scanned
    # PatientInfo.source is "phantom" by the schema's comment; v1 servers say "the phantom"
    if info.patient.source.strip().lower() in ("phantom", "the phantom"):
        default_z = PHANTOM_LUMBAR_Z_MM
    else:
        default_z = (body_min.z + 10.0, body_max.z - 10.0)
    z0, z1 = sorted((args.z_from_mm if args.z_from_mm is not None else default_z[0],
                     args.z_to_mm if args.z_to_mm is not None else default_z[1]))
    if z1 - z0 < args.step_mm:
        raise PlanError(f"--z-from-mm/--z-to-mm: the line from {z0:g} to {z1:g} mm is shorter "
                        f"than one step ({args.step_mm:g} mm)")
    count = int(np.floor((z1 - z0) / args.step_mm + 1e-9)) + 1
    # start 10 mm above the highest point of the body; search for the skin down to mid-body
    approach_mm = 10.0
    half_thickness = 0.5 * (body_max.y - body_min.y)
    data = {
        "name": "lumbar spine line",
        "sample_rate_hz": args.rate_hz,
        "repetitions": 1,
        "grid": {"center_mm": [x, body_max.y, 0.5 * (z0 + z1)], "axis_u": [1, 0, 0],
                 "axis_v": [0, 0, 1], "size_u_mm": 0.0, "size_v_mm": (count - 1) * args.step_mm,
                 "count_u": 1, "count_v": count},
        "press": {"direction": [0, -1, 0], "reference": "skin", "depth_mm": args.depth_mm,
                  "speed_mm_per_s": args.speed_mm_per_s, "approach_mm": approach_mm,
                  "max_travel_mm": max(half_thickness, 20.0), "hold_s": 0.0},
    }
    return parse_plan(data, source="palpsim-demo")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prog = "palpsim-demo"
    out = Path(args.out)
    try:
        from .server import find_server, serving
        binary = None
        if not args.connect:
            binary = Path(args.server) if args.server else find_server()
            if binary is None:
                print(f"{prog}: error: no palpsim-server found (build it, or give --server PATH "
                      "or --connect ADDR)", file=sys.stderr)
                return 1
            print(f"[demo] starting {binary}" + (f" --scene {args.scene}" if args.scene else ""))
        with serving(args.connect, binary, scene=args.scene, log_path=out / "server.log") as address:
            if binary is not None:
                print(f"[demo] server ready on {address} (log: {out / 'server.log'})")
            with Client(address) as c:
                info = c.info()
            plan = make_plan(info, args)
            g = plan.grid
            print(f"[demo] scene {info.scene_name!r}: pressing {g.count_v} points along the back, "
                  f"x = {g.center_mm[0]:.1f} mm, z from {g.center_mm[2] - g.size_v_mm / 2:.1f} to "
                  f"{g.center_mm[2] + g.size_v_mm / 2:.1f} mm, {plan.press.depth_mm:g} mm under the "
                  f"skin, {args.sessions} sessions")
            result = run_plan(plan, address, sessions=args.sessions, progress=not args.no_progress)
            summary = write_outputs(plan, result, out, "steps.parquet")
    except (PlanError, PalpsimError, OSError, RuntimeError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1

    report = analyse(result.table, plan, args)
    write_json(report, out / "spine.json")
    from .plots import spine_profile_plot
    spine_profile_plot(result.table, report, out / "spine_profile.png",
                       title=f"{info.scene_name}: pressing {plan.press.depth_mm:g} mm along the back")
    print(format_report(report, summary))
    print(f"[demo] wrote {out / 'spine_profile.png'}, {out / 'spine.json'} and the batch outputs "
          f"in {out}")
    return 0


def analyse(df, plan: Plan, args: argparse.Namespace) -> dict[str, Any]:
    """Peaks of the peak-force profile along z, and the processes the bone mask expects."""
    from .spine import bone_profile, match_peaks, profile_peaks

    pts = point_table(df).sort_values("v_mm")
    z = plan.grid.center_mm[2] + pts["v_mm"].to_numpy()
    force = pts["peak_force_n"].to_numpy()
    span = float(np.nanmax(force) - np.nanmin(force)) if len(force) else 0.0
    # a process must stand out from its surroundings by 0.1 N (and 5 % of the profile's
    # range): the force field is smooth (trilinear F), so ripples stay far below that,
    # while the deepest process (L5 on the phantom) still stands out by about 0.2 N;
    # neighbouring processes are 30 mm or more apart, so peaks closer than 15 mm are one
    prominence = max(0.05 * span, 0.1)
    # a clamped or nearly flat top (within 5 % of the peak's prominence) is one peak at
    # its middle
    peaks = profile_peaks(z, force, min_separation_mm=15.0, min_prominence=prominence,
                          flat_fraction=0.05)
    report: dict[str, Any] = {
        "line": {"x_mm": plan.grid.center_mm[0], "z_mm": z.tolist(),
                 "peak_force_n": force.tolist(),
                 "skin_y_mm": pts["skin_y_mm"].to_numpy().tolist()},
        "depth_mm": plan.press.depth_mm,
        "peaks": [{"z_mm": p.position_mm, "force_n": p.height, "prominence_n": p.prominence}
                  for p in peaks],
        "min_prominence_n": prominence,
        "expected": None,
    }
    patient = Path(args.patient) if args.patient else Path("out/demo/patient")
    if (patient / "bone.nrrd").is_file():
        from .nrrd import read_nrrd
        bone = read_nrrd(patient / "bone.nrrd")
        body = read_nrrd(patient / "body.nrrd") if (patient / "body.nrrd").is_file() else None
        bp = bone_profile(bone, body, x_mm=plan.grid.center_mm[0], band_mm=3.0,
                          z_from_mm=float(z.min()), z_to_mm=float(z.max()))
        matches = match_peaks([p.position_mm for p in peaks],
                              [p.position_mm for p in bp.processes], args.tolerance_mm)
        report["expected"] = {
            "source": str(patient),
            "tolerance_mm": args.tolerance_mm,
            "processes": [{"z_mm": m.expected_mm, "found_z_mm": m.found_mm,
                           "error_mm": m.error_mm} for m in matches],
            "found": sum(m.found_mm is not None for m in matches),
            "extra_peaks": len(peaks) - sum(m.found_mm is not None for m in matches),
            "bone_top": {"z_mm": bp.z_mm.tolist(), "y_mm": bp.bone_top_y_mm.tolist()},
            "skin_top": {"z_mm": bp.z_mm.tolist(), "y_mm": bp.skin_top_y_mm.tolist()},
        }
    return report


def format_report(report: dict[str, Any], summary: dict[str, Any]) -> str:
    """The printed summary of the demo."""
    from .results import format_summary

    lines = ["", format_summary(summary), ""]
    peaks = report["peaks"]
    lines.append(f"spinous processes found as force peaks: {len(peaks)} "
                 f"(prominence at least {report['min_prominence_n']:.2f} N)")
    for i, p in enumerate(sorted(peaks, key=lambda p: -p["z_mm"])):
        lines.append(f"  peak {i + 1}: z = {p['z_mm']:7.1f} mm  peak force {p['force_n']:.2f} N  "
                     f"(stands out by {p['prominence_n']:.2f} N)")
    exp = report["expected"]
    if exp is None:
        lines.append("expected positions: no prepared patient (bone.nrrd) to compare with; "
                     "run palpsim-prep or give --patient DIR")
    else:
        lines.append(f"expected from the bone mask ({exp['source']}): {len(exp['processes'])} "
                     f"processes; found {exp['found']} within {exp['tolerance_mm']:g} mm, "
                     f"{exp['extra_peaks']} extra peaks")
        for e in sorted(exp["processes"], key=lambda e: -e["z_mm"]):
            got = (f"peak at {e['found_z_mm']:7.1f} mm, off by {e['error_mm']:+.1f} mm"
                   if e["found_z_mm"] is not None else "no peak within tolerance")
            lines.append(f"  process at z = {e['z_mm']:7.1f} mm: {got}")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
