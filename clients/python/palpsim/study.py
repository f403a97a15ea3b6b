"""Studies: plans x patients x a grid of haptics parameters (the study file:
palpsim.study_file), run locally or on a Ray cluster.

The study's table is the tasks' tables in task order, and its digest hashes the key
columns and every result column (results.digest_columns), so a local run and a Ray run
of the same study give the same digest.

Outputs in OUT, each written whole or not at all (a temporary file renamed into place):
`tasks/<key>.parquet` for each finished task (its spec hash and digest in the file's
metadata), then `study.parquet` and `study.json` (digest, tasks, throughput, workers,
retries, where each patient was prepared). Started again, a study keeps every finished
task whose spec and digest still match and runs only the others.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import fcntl
import hashlib
import itertools
import json
import os
import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import pandas as pd

from .client import PalpsimError
from .results import (COLUMNS, TIMING_COLUMNS, TableError, digest_columns, finish_table,
                      write_atomically)
from .runner import run_plan
# the study file's model and reader, part of this module's API
from .study_file import (PARAM_PREFIX, Patient, Study, StudyError, Task, _slug,  # noqa: F401
                         is_study_file, load_study, parse_study)

# how many tasks a Ray worker holds at once: one running, one queued behind it
WORKER_DEPTH = 2
# a worker whose calls failed this many times in a row is given up
WORKER_MAX_FAILURES = 3
# how long to wait for a restarted worker when no task is running anywhere (s)
WORKER_WAIT_S = 300.0

# -- one task's table ----------------------------------------------------------------------

def task_table(task: Task, table: pd.DataFrame) -> pd.DataFrame:
    """A batch table (canonical) with the task's key columns in front."""
    n = len(table)
    keys = {"task": pd.Series([task.index] * n, dtype="int32"),
            "patient": pd.Series([task.patient.name] * n, dtype=object),
            "plan": pd.Series([task.plan.name] * n, dtype=object),
            "setting": pd.Series([task.setting] * n, dtype="int32")}
    for name, value in task.parameters:
        keys[PARAM_PREFIX + name] = pd.Series([value] * n, dtype="float64")
    return pd.concat([pd.DataFrame(keys), table.reset_index(drop=True)], axis=1)


def study_digest(study: Study, df: pd.DataFrame) -> str:
    """SHA-256 over the key columns and every result column of a study (or task) table."""
    return digest_columns(df, study.key_columns + [c for c in COLUMNS if c not in TIMING_COLUMNS])


def finish_study_table(study: Study, df: pd.DataFrame) -> pd.DataFrame:
    """Canonical form of a study table: key columns, then the batch table's, rows in
    task order and each task's rows in the batch table's canonical order."""
    parts = []
    for _, part in df.groupby("task", sort=True):
        keys = part[study.key_columns].reset_index(drop=True)
        parts.append(pd.concat([keys, finish_table(part.reset_index(drop=True))], axis=1))
    out = pd.concat(parts, ignore_index=True)
    out["task"] = out["task"].astype("int32")
    out["setting"] = out["setting"].astype("int32")
    for c in ("patient", "plan"):
        out[c] = out[c].astype(object)
    return out


def _task_path(out_dir: Path, task: Task) -> Path:
    return out_dir / "tasks" / f"{task.key}.parquet"


def write_task(study: Study, task: Task, df: pd.DataFrame, out_dir: Path,
               meta: dict[str, Any]) -> str:
    """Writes one finished task's table whole or not at all, with its spec hash and digest
    in the Parquet metadata; returns the digest."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    digest = study_digest(study, df)
    table = pa.Table.from_pandas(df, preserve_index=False)
    info = {"key": task.key, "spec": task.spec_hash(), "digest": digest, **meta}
    md = dict(table.schema.metadata or {})
    md[b"palpsim.task"] = json.dumps(info).encode()
    table = table.replace_schema_metadata(md)
    write_atomically(_task_path(out_dir, task), lambda tmp: pq.write_table(table, tmp))
    return digest


def read_task(study: Study, task: Task, out_dir: Path) -> tuple[pd.DataFrame | None, str]:
    """A finished task's table when its file exists, belongs to this task's spec and its
    rows hash to the digest stored with it; else (None, why not)."""
    import pyarrow.parquet as pq

    path = _task_path(out_dir, task)
    if not path.exists():
        return None, "not run yet"
    try:
        table = pq.read_table(path)
        info = json.loads((table.schema.metadata or {}).get(b"palpsim.task", b"{}"))
        df = table.to_pandas()
    except Exception as e:  # noqa: BLE001 - any unreadable file is simply run again
        return None, f"{path} is unreadable ({e}): running it again"
    if info.get("spec") != task.spec_hash():
        return None, f"{path} was made for another version of this task: running it again"
    for c in ("patient", "plan"):
        if c in df:
            df[c] = df[c].astype(object)
    try:
        digest = study_digest(study, df)
    except (KeyError, TableError) as e:
        return None, f"{path} lacks a column ({e}): running it again"
    if digest != info.get("digest"):
        return None, f"{path} does not match its digest: running it again"
    return df, "finished"


# -- running tasks ---------------------------------------------------------------------------

@dataclass
class StudyRun:
    """How a study run went: the table, its digest and the run's figures."""

    table: pd.DataFrame
    digest: str
    summary: dict[str, Any]


class _Progress:
    """A progress bar over the whole study (tqdm), or nothing."""

    def __init__(self, study: Study, done: int, enabled: bool):
        from tqdm import tqdm
        self.bar = tqdm(total=len(study.tasks), initial=done, unit="task", disable=not enabled,
                        dynamic_ncols=True, desc=study.name[:30])

    def update(self, task: Task) -> None:
        self.bar.set_postfix_str(task.key[-40:], refresh=False)
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


def _prep_source(tail: str) -> str:
    """'cache' when the server took its patient from the prep cache, else 'prepared'."""
    return "cache" if "from cache" in tail else "prepared"


class PatientServer:
    """One palpsim-server at a time on this machine, restarted for another patient. Each
    patient is prepared once per machine: starts of the same scene with the same cache
    folder take turns (a file lock), so the second start finds the first's cache entry."""

    def __init__(self, binary: str | Path, log_dir: Path | None = None,
                 die_with_parent: bool = False):
        self.binary = Path(binary)
        self.log_dir = log_dir
        self.die_with_parent = die_with_parent
        self.server = None
        self.patient: str | None = None

    def address_for(self, patient: Patient) -> tuple[str, dict[str, Any] | None]:
        """The address of a server for `patient`, and the prep event when one was started
        for it ({patient, prep: "prepared"|"cache", start_s, host})."""
        from .server import LocalServer
        if self.patient == patient.name and self.server is not None:
            return self.server.address, None
        self.close()
        cache = os.environ.get("PALPSIM_CACHE") or str(Path.home() / ".cache" / "palpsim")
        lock_dir = Path(tempfile.gettempdir()) / "palpsim-study-locks"
        lock_dir.mkdir(parents=True, exist_ok=True)
        lock = lock_dir / (hashlib.sha256((patient.scene_sha256 + cache).encode()).hexdigest()[:32]
                           + ".lock")
        log = self.log_dir / f"server-{_slug(patient.name)}.log" if self.log_dir else None
        t0 = time.perf_counter()
        # one start of this scene at a time on this machine: the first prepares, the rest
        # read the prep cache
        with open(lock, "a") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            server = LocalServer(self.binary, scene=patient.scene, log_path=log,
                                 die_with_parent=self.die_with_parent)
            server.start()
        self.server, self.patient = server, patient.name
        return server.address, {"patient": patient.name, "prep": _prep_source(server.tail()),
                                "start_s": time.perf_counter() - t0, "host": socket.gethostname()}

    def close(self) -> None:
        """Stops the server, if one runs."""
        if self.server is not None:
            self.server.stop()
        self.server, self.patient = None, None


def run_task(servers: PatientServer, task: Task, sessions: int = 1,
             timeout_s: float = 10.0) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Runs one task on a server for its patient; returns its table (key columns first)
    and how it ran (prep event, wall time)."""
    address, prep = servers.address_for(task.patient)
    t0 = time.perf_counter()
    result = run_plan(task.run_plan(), address, sessions=sessions, timeout_s=timeout_s,
                      progress=False)
    return task_table(task, result.table), {"prep": prep, "wall_s": time.perf_counter() - t0,
                                             "host": socket.gethostname(), "pid": os.getpid()}


def _finished(study: Study, out_dir: Path) -> tuple[dict[int, pd.DataFrame], list[str]]:
    """The tasks already finished in out_dir (kept), and a line for each redone file."""
    done, notes = {}, []
    for task in study.tasks:
        df, why = read_task(study, task, out_dir)
        if df is not None:
            done[task.index] = df
        elif why != "not run yet":
            notes.append(why)
    return done, notes


def run_study(study: Study, out_dir: str | Path, binary: str | Path | None = None,
              ray_address: str | None = None, sessions: int = 1, timeout_s: float = 10.0,
              workers: int | None = None, cpus_per_worker: float = 1.0, progress: bool = True,
              on_task: Callable[[Task, dict[str, Any]], None] | None = None) -> StudyRun:
    """Runs the study's unfinished tasks, locally (one server at a time, tasks in order)
    or on the Ray cluster at `ray_address` ("auto" or HOST:PORT), and writes each task's
    table, then the study's table and summary, into out_dir. `on_task(task, meta)` is
    called after each task's table is written (meta: host, pid, prep, wall_s)."""
    from .server import find_server
    out_dir = Path(out_dir)
    binary = Path(binary) if binary else find_server()
    if binary is None and not ray_address:
        raise StudyError("no palpsim-server found (build it, set PALPSIM_BUILD_DIR or give --server)")
    if sessions < 1:
        raise StudyError(f"--sessions: must be at least 1, got {sessions}")
    done, notes = _finished(study, out_dir)
    for line in notes:
        print(f"palpsim-batch: {line}", file=sys.stderr)
    todo = [t for t in study.tasks if t.index not in done]
    bar = _Progress(study, len(done), progress)
    # task_s: each task's palpation time on its worker (s), server start not included
    stats: dict[str, Any] = {"kept": len(done), "ran": 0, "retried": 0, "prep": [], "task_s": {}}

    def finish(task: Task, df: pd.DataFrame, meta: dict[str, Any]) -> None:
        write_task(study, task, df, out_dir, {"host": meta.get("host"), "pid": meta.get("pid")})
        done[task.index] = df
        stats["ran"] += 1
        stats["task_s"][task.key] = meta.get("wall_s")
        if meta.get("prep"):
            stats["prep"].append(meta["prep"])
        bar.update(task)
        if on_task:
            on_task(task, meta)

    t0 = time.perf_counter()
    try:
        if not todo:
            stats.update(mode="none: every task was finished", workers=0, nodes=0)
        elif ray_address:
            # without a server here, each worker looks for its node's own
            stats.update(_run_ray(todo, ray_address, str(binary or ""), sessions, timeout_s,
                                  workers, cpus_per_worker, finish))
        else:
            servers = PatientServer(binary, log_dir=out_dir / "logs")
            try:
                for task in todo:
                    df, meta = run_task(servers, task, sessions, timeout_s)
                    finish(task, df, meta)
            finally:
                servers.close()
            stats.update(mode="local", workers=1, nodes=1)
    finally:
        bar.close()
    wall = time.perf_counter() - t0

    # the study's table and summary, each written whole
    from .results import write_json, write_table
    table = finish_study_table(study, pd.concat([done[t.index] for t in study.tasks],
                                                ignore_index=True))
    digest = study_digest(study, table)
    summary = {
        "study": study.name, "source": study.source, "digest": digest,
        "tasks": len(study.tasks), "rows": len(table),
        "patients": [dataclasses.asdict(p) for p in study.patients],
        "plans": [p.name for p in study.plans],
        "grid": {n: list(v) for n, v in study.grid},
        "run": {**stats, "wall_s": wall,
                "tasks_per_s": stats["ran"] / wall if wall > 0 and stats["ran"] else None,
                "sessions_per_task": sessions},
        "task_digests": {t.key: study_digest(study, done[t.index]) for t in study.tasks},
        "table": str(out_dir / "study.parquet"),
    }
    write_table(table, out_dir / "study.parquet")
    write_json(summary, out_dir / "study.json")
    return StudyRun(table=table, digest=digest, summary=summary)


# -- Ray ---------------------------------------------------------------------------------------

class _RayWorker:
    """A Ray actor: one palpsim-server of its own on its node, tasks run one at a time."""

    def __init__(self, binary: str, sessions: int, timeout_s: float):
        from .server import find_server
        path: Path | None = Path(binary) if binary else None
        if path is None or not (path.is_file() and os.access(path, os.X_OK)):
            path = find_server()  # this node's own build or PATH
        self.servers = PatientServer(path, die_with_parent=True) if path else None
        self.sessions, self.timeout_s = sessions, timeout_s

    def where(self) -> dict[str, Any]:
        """The node, host and process this worker runs in, and the GPUs Ray gave it (its
        CUDA_VISIBLE_DEVICES, which its palpsim-server inherits; None without a GPU)."""
        import ray
        return {"node": ray.get_runtime_context().get_node_id(), "host": socket.gethostname(),
                "pid": os.getpid(), "gpus": os.environ.get("CUDA_VISIBLE_DEVICES") or None}

    def run(self, task: Task) -> tuple[pd.DataFrame, dict[str, Any]]:
        """Runs one task; the table comes back to the driver, which writes it."""
        if self.servers is None:
            raise StudyError(f"{socket.gethostname()}: no palpsim-server on this node (not at "
                             "--server's path, nor in $PALPSIM_BUILD_DIR, build/ or PATH)")
        df, meta = run_task(self.servers, task, self.sessions, self.timeout_s)
        meta["node"] = self.where()["node"]
        if meta["prep"]:
            meta["prep"]["node"] = meta["node"]
        return df, meta


def _ray_slots(nodes: list[dict[str, Any]], cpus_per_worker: float) -> list[tuple[str, dict]]:
    """(node id, actor options) for each worker: one per GPU where the cluster has GPUs,
    else one per `cpus_per_worker` CPUs of each node."""
    gpus = any(n["Resources"].get("GPU", 0) >= 1 for n in nodes)
    slots = []
    for n in nodes:
        if gpus:
            count, opts = int(n["Resources"].get("GPU", 0)), {"num_gpus": 1, "num_cpus": 0}
        else:
            count = int(n["Resources"].get("CPU", 0) // cpus_per_worker)
            opts = {"num_cpus": cpus_per_worker}
        slots += [(n["NodeID"], opts)] * count
    # round robin over nodes, so that a cap on the workers still spreads them
    by_node = collections.OrderedDict()
    for node, opts in slots:
        by_node.setdefault(node, []).append((node, opts))
    return [s for group in itertools.zip_longest(*by_node.values()) for s in group if s]


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Refuses a HOST:PORT where nothing answers (ray.init would retry it for minutes)."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise StudyError(f"--ray {address}: give auto or the head's HOST:PORT")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise StudyError(f"--ray {address}: no Ray cluster answers there ({e.strerror or e})") from None


def _run_ray(todo: list[Task], address: str, binary: str, sessions: int, timeout_s: float,
             workers: int | None, cpus_per_worker: float,
             finish: Callable[[Task, pd.DataFrame, dict[str, Any]], None]) -> dict[str, Any]:
    """Runs the tasks on Ray workers with a scheduler loop: each worker holds up to
    WORKER_DEPTH tasks, preferring its current patient; a task whose worker died goes
    back to the queue for any worker; results come back to the driver, which writes them."""
    if address != "auto":
        _check_reachable(address)
    try:
        import ray
        from ray.exceptions import ObjectLostError, RayActorError, RayTaskError, WorkerCrashedError
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy
    except ImportError:
        raise StudyError("--ray needs the ray package (pip install 'ray==2.60.0')") from None
    lost = (RayActorError, ObjectLostError, WorkerCrashedError)
    t0 = time.perf_counter()
    started = not ray.is_initialized()
    if started:
        # workers import this very palpsim (a node without it on this path uses its own)
        pkg = str(Path(__file__).resolve().parents[1])
        try:
            ray.init(address=address, log_to_driver=False,
                     runtime_env={"env_vars": {"PYTHONPATH": pkg}})
        except (ConnectionError, RuntimeError, ValueError) as e:
            raise StudyError(f"--ray {address}: cannot connect to the Ray cluster: {e}") from None
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        slots = _ray_slots(nodes, cpus_per_worker)
        if workers:
            slots = slots[:workers]
        if not slots:
            raise StudyError(f"--ray {address}: the cluster has no free GPU and no "
                             f"{cpus_per_worker:g} CPUs on any node for a worker")
        cls = ray.remote(_RayWorker)
        actors = [cls.options(max_restarts=2, max_task_retries=0, scheduling_strategy=
                              NodeAffinitySchedulingStrategy(node, soft=True), **opts)
                  .remote(binary, sessions, timeout_s) for node, opts in slots]
        where = ray.get([a.where.remote() for a in actors], timeout=300)
        info = {"mode": "ray", "address": address, "workers": len(actors),
                "nodes": len({w["node"] for w in where}), "gpus": [w["gpus"] for w in where], "lost": [],
                "startup_s": time.perf_counter() - t0}

        pending = collections.deque(todo)
        inflight: dict[Any, tuple[int, Task]] = {}
        probes: dict[Any, int] = {}  # where() calls to workers that lost a task
        load = [0] * len(actors)
        patient: list[str | None] = [None] * len(actors)
        failures = [0] * len(actors)
        alive = set(range(len(actors)))
        avoid: dict[int, int] = {}

        def lose(a: int) -> None:
            """A call to worker a failed: probe it before it gets work again (Ray restarts
            it, on its node or elsewhere), or give it up after WORKER_MAX_FAILURES."""
            failures[a] += 1
            patient[a] = None
            if failures[a] >= WORKER_MAX_FAILURES:
                alive.discard(a)
            elif a not in probes.values():
                probes[actors[a].where.remote()] = a

        while pending or inflight:
            # hand out work: each live, answering worker up to WORKER_DEPTH tasks, its
            # current patient first
            for a in sorted(alive - set(probes.values())):
                while load[a] < WORKER_DEPTH:
                    # a task lost with a worker goes elsewhere while another worker lives
                    fits = [t for t in pending if avoid.get(t.index) != a or len(alive) == 1]
                    if not fits:
                        break
                    task = next((t for t in fits if t.patient.name == patient[a]), fits[0])
                    pending.remove(task)
                    inflight[actors[a].run.remote(task)] = (a, task)
                    load[a] += 1
                    patient[a] = task.patient.name
            if not inflight and not probes:
                raise StudyError(f"every Ray worker died; {len(pending)} tasks left unfinished "
                                 "(finished ones are kept: start the study again)")
            # with only probes out, a worker that is never placed again must not hang the run
            ready, _ = ray.wait(list(inflight) + list(probes), num_returns=1,
                                timeout=None if inflight else WORKER_WAIT_S)
            if not ready:
                raise StudyError(f"no Ray worker came back within {WORKER_WAIT_S:g} s; "
                                 f"{len(pending)} tasks left unfinished (finished ones are kept)")
            for ref in ready:
                if ref in probes:
                    a = probes.pop(ref)
                    try:
                        ray.get(ref)
                        failures[a] = 0
                    except lost:
                        lose(a)
                    continue
                a, task = inflight.pop(ref)
                load[a] -= 1
                try:
                    df, meta = ray.get(ref)
                except lost as e:
                    # the worker (or its node) died: the task goes back for another worker
                    info["retried"] = info.get("retried", 0) + 1
                    info["lost"].append({"task": task.key, "error": type(e).__name__})
                    pending.appendleft(task)
                    avoid[task.index] = a
                    lose(a)
                    continue
                except RayTaskError as e:
                    raise StudyError(f"task {task.key} failed: {e.cause if e.cause else e}") from None
                failures[a] = 0
                finish(task, df, meta)
        return info
    finally:
        if started:
            ray.shutdown()


# -- command line ------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    """palpsim-batch's options for a study file."""
    p = argparse.ArgumentParser(
        prog="palpsim-batch",
        description="Run a study (plans x patients x a parameter grid), locally or on Ray; "
                    "write one table of every pose of every task and a summary.")
    p.add_argument("study", help="study file (.toml with [[patients]]; see clients/python/README.md)")
    p.add_argument("--ray", metavar="auto|ADDRESS",
                   help="run on this Ray cluster (one worker per GPU, else per CPU slot)")
    p.add_argument("--server", metavar="PATH",
                   help="palpsim-server binary (default: build/ or $PALPSIM_BUILD_DIR or PATH)")
    p.add_argument("--out", help="output folder (default out/study/<study name>)")
    p.add_argument("--sessions", type=int, default=1, help="parallel sessions per task (default 1)")
    p.add_argument("--workers", type=int, default=None, help="at most this many Ray workers")
    p.add_argument("--cpus-per-worker", type=float, default=1.0,
                   help="CPUs per Ray worker on a cluster without GPUs (default 1)")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for a reply")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """palpsim-batch STUDY [--ray auto|ADDRESS]: exit 0 done, 1 a failed run, 2 bad input."""
    args = build_parser().parse_args(argv)
    prog = "palpsim-batch"
    try:
        study = load_study(args.study)
        if args.cpus_per_worker <= 0:
            raise StudyError(f"--cpus-per-worker: must be positive, got {args.cpus_per_worker:g}")
        if args.workers is not None and args.workers < 1:
            raise StudyError(f"--workers: must be at least 1, got {args.workers}")
    except StudyError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path("out/study") / _slug(study.name)
    try:
        run = run_study(study, out, binary=args.server, ray_address=args.ray,
                        sessions=args.sessions, timeout_s=args.timeout, workers=args.workers,
                        cpus_per_worker=args.cpus_per_worker, progress=not args.no_progress)
    except StudyError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 1
    except (PalpsimError, OSError, RuntimeError, ValueError) as e:  # ServerStartError, TableError
        print(f"{prog}: error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    r = run.summary["run"]
    tps = f"{r['tasks_per_s']:.3f} tasks/s" if r["tasks_per_s"] else "nothing left to run"
    print(f"study {study.name!r}: {len(study.tasks)} tasks ({r['kept']} kept, {r['ran']} run, "
          f"{r['retried']} retried) on {r['workers']} worker(s), {r['nodes']} node(s), "
          f"{r['wall_s']:.1f} s, {tps}")
    print(f"result digest {run.digest[:16]}; wrote {out / 'study.parquet'}, {out / 'study.json'}")
    return 0
