#!/usr/bin/env python3
"""Study throughput: the same study run locally, on a Ray cluster of 1 node and of 2 nodes
on this machine (palpsim.raycluster), in tasks per second, and the scaling efficiency
tasks/s(2 nodes) / (2 x tasks/s(1 node)), from the medians of `--rounds` alternating runs.

    .venv/bin/python bench/study_bench.py --json bench/results/study-DATE-MACHINE.json   # about 3 minutes here

The study: the example's two phantom variants and the shared CT (left out where
../shared/data is absent), each pressed at `--points` points along its back, at a 2 x 3
grid of stiffness and friction. Every node gets `--cpus-per-node` CPUs (one worker
each). The prep caches are warmed first, so the figures are the palpation's, not the
preparation's; every run must give the local run's digest.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "clients" / "python"))

from palpsim.raycluster import LocalRayCluster  # noqa: E402
from palpsim.study import load_study, run_study  # noqa: E402

EXAMPLES = ROOT / "clients" / "python" / "examples" / "study"
CT = ROOT.parent / "shared" / "data" / "ct" / "abdomen-lumbar-3mm.nii.gz"


def write_study(folder: Path, points: int) -> Path:
    """The bench study in `folder`: the example plans with `points` points each."""
    for name in ("phantom_line.toml", "ct_line.toml"):
        text = (EXAMPLES / name).read_text().replace("count_v = 2", f"count_v = {points}")
        text = text.replace("size_v_mm = 10.0", f"size_v_mm = {5.0 * (points - 1):.1f}")
        (folder / name).write_text(text)
    patients = [("phantom-2mm", "phantom_2mm.textproto", "phantom line"),
                ("phantom-3mm-soft", "phantom_3mm_soft.textproto", "phantom line")]
    if CT.exists():
        patients.append(("abdomen-ct-3mm", "ct_3mm.textproto", "ct line"))
    text = 'name = "study bench"\nplans = ["phantom_line.toml", "ct_line.toml"]\n'
    for name, scene, plan in patients:
        text += (f'[[patients]]\nname = "{name}"\nscene = "{EXAMPLES / scene}"\n'
                 f'plans = ["{plan}"]\n')
    text += "[grid]\nstiffness_n_per_mm = [0.2, 0.3]\nfriction = [0.1, 0.2, 0.3]\n"
    path = folder / "study.toml"
    path.write_text(text)
    return path


def main() -> int:
    """Runs the three configurations and prints and saves the figures."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=16, help="press points per plan (default 16)")
    ap.add_argument("--cpus-per-node", type=int, default=1, help="CPUs (workers) per node")
    ap.add_argument("--rounds", type=int, default=3, help="runs of each cluster (default 3)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="study-bench-"))
    try:
        return _bench(args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _bench(args: argparse.Namespace, tmp: Path) -> int:
    """The bench proper, its study, caches and outputs in `tmp`."""
    study = load_study(write_study(tmp, args.points))
    caches = [tmp / f"cache{i}" for i in range(2)]
    rows = []

    def record(name: str, run, nodes: int) -> None:
        r = run.summary["run"]
        rows.append({"config": name, "nodes": nodes, "workers": r["workers"],
                     "tasks": r["ran"], "wall_s": r["wall_s"], "tasks_per_s": r["tasks_per_s"],
                     "startup_s": r.get("startup_s", 0.0),
                     "tasks_per_s_after_startup": r["ran"] / (r["wall_s"] - r.get("startup_s", 0.0)),
                     "poses_per_s": len(run.table) / r["wall_s"],
                     "task_s_mean": sum(r["task_s"].values()) / len(r["task_s"]),
                     "prep_and_server_start_s": sum(e["start_s"] for e in r["prep"]),
                     "digest": run.digest})
        print(f"{name:>14}: {r['ran']} tasks in {r['wall_s']:.2f} s, {r['tasks_per_s']:.2f} tasks/s, "
              f"{len(run.table) / r['wall_s']:.0f} poses/s (Ray start-up {r.get('startup_s', 0.0):.1f} s, "
              f"{rows[-1]['tasks_per_s_after_startup']:.2f} tasks/s after it), a task "
              f"{rows[-1]['task_s_mean']:.2f} s on its worker, server starts "
              f"{rows[-1]['prep_and_server_start_s']:.1f} s in all, "
              f"digest {run.digest[:16]}", flush=True)

    # warm both nodes' prep caches, then the local baseline (one server, tasks in order)
    for c in caches:
        os.environ["PALPSIM_CACHE"] = str(c)
        run_study(study, tmp / f"warm-{c.name}", progress=False)
    os.environ["PALPSIM_CACHE"] = str(caches[0])
    record("local", run_study(study, tmp / "local", progress=False), 1)

    # the same study on 1 and on 2 nodes, alternating, `--rounds` times (the VM is shared)
    for _ in range(args.rounds):
        for nodes in (1, 2):
            env = [{"PALPSIM_CACHE": str(c)} for c in caches[:nodes]]
            with LocalRayCluster(nodes=nodes, cpus_per_node=args.cpus_per_node,
                                 node_env=env) as cl:
                record(f"ray {nodes} node{'s' if nodes > 1 else ''}",
                       run_study(study, tmp / f"ray{nodes}-{len(rows)}", ray_address=cl.address,
                                 progress=False), nodes)

    def median(nodes: int, key: str) -> float:
        return statistics.median(r[key] for r in rows if r["config"] != "local"
                                 and r["nodes"] == nodes)

    one, two = median(1, "tasks_per_s"), median(2, "tasks_per_s")
    efficiency = two / (2 * one)
    work = median(2, "tasks_per_s_after_startup") / (2 * median(1, "tasks_per_s_after_startup"))
    same = len({r["digest"] for r in rows}) == 1
    print(f"medians: 1 node {one:.2f} tasks/s, 2 nodes {two:.2f} tasks/s; scaling {two / one:.2f}x, "
          f"efficiency {efficiency:.0%} ({work:.0%} after the start-up); "
          f"digests {'all equal' if same else 'DIFFER'}")
    if args.json:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True).stdout.strip()
        out = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
               "commit": commit, "machine": f"{platform.node()} {os.cpu_count()} cores",
               "load_avg_at_end": os.getloadavg(), "study": {"tasks": len(study.tasks),
                                                             "points_per_plan": args.points},
               "cpus_per_node": args.cpus_per_node, "rounds": args.rounds, "runs": rows,
               "median_tasks_per_s": {"1 node": one, "2 nodes": two},
               "speedup_2_nodes": two / one, "scaling_efficiency": efficiency,
               "scaling_efficiency_after_startup": work,
               "digests_equal": same}
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0 if same else 1


if __name__ == "__main__":
    t0 = time.perf_counter()
    rc = main()
    print(f"bench took {time.perf_counter() - t0:.0f} s")
    sys.exit(rc)
