"""palpsim-batch: runs a palpation plan over N parallel sessions of a palpsim-server and
writes a tidy table of every pose, a summary (JSON and printed) and PNG plots.

    palpsim-batch plan.toml --connect tcp://127.0.0.1:7420 --sessions 4 --out out/batch

The presses run through runner.run_plan (its docstring says why a run is deterministic);
a study file is handed to study.main.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from . import keys
from .client import PalpsimError
from .plan import Plan, PlanError, load_plan
from .results import TableError, format_summary, summarize, write_json, write_table
from .runner import RunResult, run_plan


def write_outputs(plan: Plan, result: RunResult, out_dir: Path, table_name: str = "steps.parquet",
                  plots: bool = True) -> dict:
    """Writes the table, summary.json and the plots into out_dir; returns the summary."""
    from .plots import force_depth_plot, peak_force_plot

    out_dir.mkdir(parents=True, exist_ok=True)
    table_path = Path(table_name) if Path(table_name).is_absolute() or "/" in table_name \
        else out_dir / table_name
    df = result.table
    run = {"sessions": result.sessions, "wall_s": result.wall_s,
           "poses_per_s": len(df) / result.wall_s if result.wall_s > 0 else float("nan"),
           "server": result.server, "table": str(table_path)}
    summary = summarize(df, plan.to_dict(), run)
    write_table(df, table_path)
    if plots:
        g = plan.grid
        axes = (f"u along {_fmt(g.axis_u)}", f"v along {_fmt(g.axis_v)}")
        run["plots"] = [
            str(force_depth_plot(df, out_dir / "force_vs_depth.png",
                                 title=f"{plan.name}: force against depth")),
            str(peak_force_plot(df, out_dir / "peak_force_map.png",
                                title=f"{plan.name}: peak force", axis_names=axes)),
        ]
    write_json(summary, out_dir / "summary.json")
    return summary


def _fmt(v: Sequence[float]) -> str:
    return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="palpsim-batch",
        description="Run a palpation plan against palpsim-server; write a tidy table of every "
                    "pose, a summary and plots. Given a study file (a .toml with [[patients]]) "
                    "it runs the study instead, locally or with --ray (palpsim-batch STUDY --help).")
    p.add_argument("plan", nargs="?", help="plan file (.toml or .json; --plan-help for the fields)")
    p.add_argument("--plan-help", action="store_true", help="print the plan's fields and exit")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--connect", metavar="ADDR",
                     help="control address of a running server (the 'ready on ADDR' it printed)")
    src.add_argument("--start-server", metavar="PATH",
                     help="start this palpsim-server on a free loopback port, stop it at the end")
    p.add_argument("--scene", help="scene file for --start-server (default: the server's default)")
    p.add_argument("--sessions", type=int, default=2, help="parallel sessions (default 2)")
    p.add_argument("--out", default=None, help="output folder (default out/batch/<plan name>)")
    p.add_argument("--table", default="steps.parquet",
                   help="table file name or path; .csv or .parquet (default steps.parquet)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for a reply")
    keys.add_arguments(p, token=False)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    # a study file (plans x patients x grid) has its own options (palpsim.study)
    argv = list(sys.argv[1:] if argv is None else argv)
    from .study import is_study_file
    if any(is_study_file(a) for a in argv if not a.startswith("-")):
        from .study import main as study_main
        return study_main(argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    prog = "palpsim-batch"
    if args.plan_help:
        from . import plan as plan_module
        print(plan_module.__doc__)
        return 0
    if not args.plan or not (args.connect or args.start_server):
        parser.error("give a plan file and one of --connect ADDR or --start-server PATH")
    try:
        plan = load_plan(args.plan)
        if args.sessions < 1:
            raise PlanError(f"--sessions: must be at least 1, got {args.sessions}")
        ext = Path(args.table).suffix.lower()
        if ext not in (".csv", ".parquet"):
            raise PlanError(f"--table: {args.table}: use a .csv or .parquet name")
        curve = keys.from_arguments(args)
    except (PlanError, keys.KeyFileError, RuntimeError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    out_dir = Path(args.out) if args.out else Path("out/batch") / _slug(plan.name)
    try:
        from .server import serving
        with serving(args.connect, args.start_server, scene=args.scene,
                     log_path=out_dir / "server.log") as address:
            if args.start_server:
                print(f"{prog}: started {args.start_server} on {address}", file=sys.stderr)
            result = run_plan(plan, address, sessions=args.sessions, timeout_s=args.timeout,
                              progress=not args.no_progress, curve=curve)
            summary = write_outputs(plan, result, out_dir, args.table, plots=not args.no_plots)
    except (PalpsimError, TableError, OSError, RuntimeError) as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    print(format_summary(summary))
    print(f"wrote {summary['run']['table']}, {out_dir / 'summary.json'}"
          + ("".join(f", {p}" for p in summary["run"].get("plots", []))))
    return 0


def _slug(name: str) -> str:
    s = "".join(c if c.isalnum() or c in "-_" else "_" for c in name.strip().lower())
    return s.strip("_") or "plan"


if __name__ == "__main__":
    sys.exit(main())
