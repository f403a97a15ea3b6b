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

Then, where the scene asks for frames, it records a press over one spinous process (L3
on the phantom; elsewhere the most prominent force peak) as the server renders it
(palpsim.record): in --record-steps steps down to --record-depth-mm and back up, one
frame per step, written as press.mp4, press_contact_sheet.png and press.json.
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
from .view import positive_int, positive_number

# the line's default z-range (mm, LPS) on the built-in phantom (server/prep/phantom.cpp):
# its spinous process tips L5..L1 lie near z = -70, -38, -5, 28, 61 mm, each process a
# plate about 14 mm long in z sloping down from its tip; S1's ends above z = -101 mm and
# T12's plate reaches down to z = 78 mm, so this range holds L1-L5 and the gaps around them
PHANTOM_LUMBAR_Z_MM = (-90.0, 72.0)
# the recorded press on the phantom: over the tip of L3's spinous process, the middle of
# the lumbar spine (24 mm under the skin), away from the iliac crests (L4) and ribs (T12)
PHANTOM_L3_Z_MM = -5.0
# the line starts (and the recorded press starts) this far above the body's highest point
APPROACH_MM = 10.0


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
    rec = p.add_argument_group("the recorded press (scenes with frames; palpsim.record)")
    rec.add_argument("--no-record", action="store_true", help="do not record the press")
    rec.add_argument("--record-steps", type=positive_int, default=5,
                     help="depth steps down (and as many back up), one frame each (default "
                          "%(default)s; a step waits about two frames: 1280x720 frames take "
                          "0.6-1.1 s on a 2-core CPU)")
    rec.add_argument("--record-depth-mm", type=positive_number("mm of depth"), default=15.0,
                     help="deepest step under the skin (default %(default)g)")
    rec.add_argument("--record-z-mm", type=float,
                     help="z of the press (default: L3, %g mm, on the phantom; else the most "
                          "prominent force peak)" % PHANTOM_L3_Z_MM)
    return p


def make_plan(info: Any, args: argparse.Namespace) -> Plan:
    """The demo's plan: a line along z over the back, pressed along -y from above the body."""
    body_min, body_max = info.patient.body_min_mm, info.patient.body_max_mm
    x = args.x_mm if args.x_mm is not None else 0.5 * (body_min.x + body_max.x)
    # the phantom's lumbar spine, or (another patient) the whole back that was scanned
    if is_phantom(info):
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
    approach_mm = APPROACH_MM
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
            report = analyse(result.table, plan, args)
            write_json(report, out / "spine.json")
            from .plots import spine_profile_plot
            spine_profile_plot(result.table, report, out / "spine_profile.png",
                               title=f"{info.scene_name}: pressing {plan.press.depth_mm:g} mm "
                                     "along the back")
            print(format_report(report, summary))
            print(f"[demo] wrote {out / 'spine_profile.png'}, {out / 'spine.json'} and the batch "
                  f"outputs in {out}")
            # the recorded press, on the same server
            if not args.no_record:
                record_demo_press(address, info, plan, report, args, out)
    except (PlanError, PalpsimError, OSError, RuntimeError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    return 0


def is_phantom(info: Any) -> bool:
    """Whether the server serves the built-in phantom (PatientInfo.source is "phantom" by
    the schema's comment; v1 servers say "the phantom")."""
    return info.patient.source.strip().lower() in ("phantom", "the phantom")


def press_site(info: Any, plan: Plan, report: dict[str, Any],
               args: argparse.Namespace) -> tuple[float, float, str]:
    """(x, z, name) of the recorded press: on the line the demo palpated, over L3 on the
    phantom, else over the most prominent force peak (the middle of the line if none)."""
    x = plan.grid.center_mm[0]
    if args.record_z_mm is not None:
        return x, args.record_z_mm, f"z = {args.record_z_mm:g} mm"
    if is_phantom(info):
        return x, PHANTOM_L3_Z_MM, "the L3 spinous process"
    if report["peaks"]:
        best = max(report["peaks"], key=lambda p: p["prominence_n"])
        return x, best["z_mm"], "the most prominent force peak"
    return x, plan.grid.center_mm[2], "the middle of the line"


def record_demo_press(address: str, info: Any, plan: Plan, report: dict[str, Any],
                      args: argparse.Namespace, out: Path) -> None:
    """Records a stepped press over a spinous process as frames and writes press.mp4,
    press_contact_sheet.png and press.json into `out` (palpsim.record)."""
    from .record import press_depths, record_press, summary, write_recording

    if "frames" not in info.stages:
        print("[demo] the scene asks for no frames (effects.frames): no recorded press")
        return
    x, z, what = press_site(info, plan, report, args)
    top = (x, info.patient.body_max_mm.y + APPROACH_MM, z)
    depths = press_depths(args.record_depth_mm, args.record_steps)
    print(f"[demo] recording a press over {what} (x = {x:.1f}, z = {z:.1f} mm) in "
          f"{args.record_steps} steps to {args.record_depth_mm:g} mm and back, one rendered "
          "frame a step")

    def progress(f: Any, steps: int) -> None:
        where = f"depth {f.depth_mm:4.1f} mm" if f.depth_mm >= 0 else f"{-f.depth_mm:g} mm above"
        print(f"[demo]   step {f.index + 1}/{steps}: {where}, force {f.force_n:.2f} N, frame "
              f"after {f.wait_s:.1f} s (rendered in {f.render_ms / 1000:.1f} s)", flush=True)

    with Client(address) as c:
        rec = record_press(c, top, (0.0, -1.0, 0.0), depths, progress=progress)
    title = (f"{info.scene_name}: press over {what}, {args.record_depth_mm:g} mm in "
             f"{args.record_steps} steps and back")
    paths = write_recording(rec, out, title=title, seconds_per_step=0.8)
    print("[demo] " + summary(rec, paths))


def force_peaks(df, plan: Plan) -> tuple[np.ndarray, np.ndarray, list[Any], float, Any]:
    """The line's profile and its peaks: (z, peak force per point, peaks (spine.Peak),
    the prominence a peak needs, the points' table sorted along the line)."""
    from .spine import profile_peaks

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
    return z, force, peaks, prominence, pts


def analyse(df, plan: Plan, args: argparse.Namespace) -> dict[str, Any]:
    """Peaks of the peak-force profile along z, and the processes the bone mask expects."""
    from .spine import bone_profile, match_peaks

    z, force, peaks, prominence, pts = force_peaks(df, plan)
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
