"""Studies (palpsim.study): the study file's checks, local runs, resuming, and Ray runs on a
local cluster of two nodes (two `ray start`s on 127.0.0.2 and 127.0.0.3, each with its own
prep cache, as two machines would have), a worker or a whole node killed mid-study.

The study: two phantom variants (2 mm; 3 mm with a softer force image) and, where
../shared/data exists, the shared abdominal CT at 3 mm, each pressed twice along its back
at 2 x 2 haptics settings (8 or 12 tasks of about 600-1,500 poses). About a minute in all.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pandas as pd
import pytest

from palpsim.batch import main as batch_main
from palpsim.server import find_server
from palpsim.study import (StudyError, is_study_file, load_study, parse_study, read_task,
                           run_study, study_digest)

ROOT = Path(__file__).resolve().parents[3]
EXAMPLES = ROOT / "clients" / "python" / "examples" / "study"
CT = ROOT.parent / "shared" / "data" / "ct" / "abdomen-lumbar-3mm.nii.gz"


def _write_study(tmp_path: Path, with_ct: bool, extra: str = "") -> Path:
    """The example study's patients and plans (absolute paths), the CT only when asked."""
    text = f"""name = "test study"
plans = ["{EXAMPLES}/phantom_line.toml", "{EXAMPLES}/ct_line.toml"]
[[patients]]
name = "phantom-2mm"
scene = "{EXAMPLES}/phantom_2mm.textproto"
plans = ["phantom line"]
[[patients]]
name = "phantom-3mm-soft"
scene = "{EXAMPLES}/phantom_3mm_soft.textproto"
plans = ["phantom line"]
"""
    if with_ct:
        text += f"""[[patients]]
name = "abdomen-ct-3mm"
scene = "{EXAMPLES}/ct_3mm.textproto"
plans = ["ct line"]
"""
    text += extra or "[grid]\nstiffness_n_per_mm = [0.2, 0.3]\nfriction = [0.1, 0.3]\n"
    path = tmp_path / "study.toml"
    path.write_text(text)
    return path


# -- the study file ------------------------------------------------------------------------

def test_example_study_expands_in_canonical_order():
    study = load_study(EXAMPLES / "tiny_study.toml")
    keys = [t.key for t in study.tasks]
    # 3 patients x their one plan x 4 settings; the last grid name (stiffness) varies fastest
    assert len(keys) == 12
    assert keys[:2] == ["phantom-2mm--phantom_line--s000", "phantom-2mm--phantom_line--s001"]
    assert study.tasks[1].parameters == (("friction", 0.1), ("stiffness_n_per_mm", 0.3))
    assert study.tasks[2].parameters == (("friction", 0.3), ("stiffness_n_per_mm", 0.2))
    assert {t.plan.name for t in study.tasks if t.patient.name == "abdomen-ct-3mm"} == {"ct line"}
    # the grid's values override the plan's own [parameters] in the plan a task runs
    assert study.tasks[1].run_plan().parameters["stiffness_n_per_mm"] == 0.3
    assert is_study_file(EXAMPLES / "tiny_study.toml")
    assert not is_study_file(EXAMPLES / "phantom_line.toml")


@pytest.mark.parametrize("extra, message", [
    ("[grid]\nstiffness = [0.2]\n", "grid.stiffness: not a haptics parameter"),
    ("[grid]\nfriction = [1.5]\n", "grid.friction: 1.5 is outside [0, 0.99]"),
    ("[grid]\nfriction = []\n", "grid.friction: must be a non-empty list"),
    ("[grid]\nfriction = [0.1, 0.1]\n", "grid.friction: holds a value twice"),
    ("colour = 3\n", "colour: unknown field"),
])
def test_bad_study_names_file_and_field(tmp_path, extra, message):
    path = _write_study(tmp_path, with_ct=False, extra=extra)
    with pytest.raises(StudyError) as e:
        load_study(path)
    assert str(e.value).startswith(f"{path}: ") and message in str(e.value), str(e.value)


def test_bad_patients_and_plans_are_named(tmp_path):
    base = {"plans": [str(EXAMPLES / "phantom_line.toml")],
            "patients": [{"scene": str(EXAMPLES / "phantom_2mm.textproto")}]}
    src = str(tmp_path / "s.toml")
    cases = [
        ({"patients": [{"scene": "missing.textproto"}]}, "patients[0].scene: cannot read the scene"),
        ({"patients": [{"scene": str(EXAMPLES / "phantom_line.toml")}]},
         "patients[0].scene: " + str(EXAMPLES / "phantom_line.toml") + " is not a valid scene"),
        ({"patients": [base["patients"][0], base["patients"][0]]},
         "patients[1].name: a second patient named 'phantom_2mm'"),
        ({"patients": [{**base["patients"][0], "plans": ["nope"]}]},
         "patients[0].plans: 'nope' is not the name of a plan"),
        ({"plans": [str(EXAMPLES / "phantom_line.toml")] * 2}, "plans[1]: a second plan named"),
        ({"plans": ["absent.toml"]}, "plans[0]: "),
        ({"patients": []}, "patients: must be a non-empty list"),
    ]
    for change, message in cases:
        with pytest.raises(StudyError) as e:
            parse_study({**base, **change}, source=src)
        assert str(e.value).startswith(f"{src}: ") and message in str(e.value), (change, str(e.value))


def test_unreachable_ray_cluster_is_a_clear_error(tmp_path, capsys):
    import socket
    with socket.socket() as s:  # a loopback port where nothing listens
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = _write_study(tmp_path, with_ct=False)
    rc = batch_main([str(path), "--ray", f"127.0.0.1:{port}", "--out", str(tmp_path / "out"),
                     "--no-progress"])
    assert rc == 1 and f"--ray 127.0.0.1:{port}: no Ray cluster answers there" in capsys.readouterr().err
    assert not (tmp_path / "out" / "study.parquet").exists()


def test_bad_study_on_the_command_line_exits_2(tmp_path, capsys):
    path = _write_study(tmp_path, with_ct=False, extra="[grid]\nfriction = [2.0]\n")
    assert batch_main([str(path), "--no-progress"]) == 2
    assert "grid.friction" in capsys.readouterr().err


def test_workers_are_one_per_gpu_else_per_cpu_slot():
    from palpsim.study import _ray_slots
    cpu_nodes = [{"NodeID": "a", "Resources": {"CPU": 4.0}}, {"NodeID": "b", "Resources": {"CPU": 2.0}}]
    slots = _ray_slots(cpu_nodes, cpus_per_worker=2)
    # 4 // 2 + 2 // 2 workers, alternating between the nodes so that a cap still spreads them
    assert [n for n, _ in slots] == ["a", "b", "a"]
    assert all(opts == {"num_cpus": 2} for _, opts in slots)
    gpu_nodes = [{"NodeID": "head", "Resources": {"CPU": 8.0}},
                 {"NodeID": "g1", "Resources": {"CPU": 16.0, "GPU": 4.0}},
                 {"NodeID": "g2", "Resources": {"CPU": 16.0, "GPU": 2.0}}]
    slots = _ray_slots(gpu_nodes, cpus_per_worker=1)
    # with GPUs in the cluster: one worker per GPU and none on the CPU-only head
    assert sorted(n for n, _ in slots) == ["g1"] * 4 + ["g2"] * 2
    assert all(opts == {"num_gpus": 1, "num_cpus": 0} for _, opts in slots)


# -- local runs ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def binary():
    b = find_server()
    if b is None:
        reason = "SKIPPED: no palpsim-server built (PALPSIM_BUILD_DIR or build/)"
        print(reason)
        pytest.skip(reason)
    return b


@pytest.fixture(scope="module")
def study_file(tmp_path_factory):
    if not CT.exists():
        print(f"the CT patient is left out: {CT} is absent")
    return _write_study(tmp_path_factory.mktemp("study"), with_ct=CT.exists())


@pytest.fixture(scope="module")
def local(binary, study_file, tmp_path_factory):
    """The study run locally once: the digest every other run must reproduce."""
    # the local servers' prep cache, for this module's tests only
    mp = pytest.MonkeyPatch()
    mp.setenv("PALPSIM_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield run_study(load_study(study_file), tmp_path_factory.mktemp("local"), binary=binary,
                    progress=False)
    mp.undo()


def test_local_run_is_reproducible(local, binary, study_file, tmp_path):
    study = load_study(study_file)
    again = run_study(study, tmp_path / "again", binary=binary, progress=False)
    assert again.digest == local.digest
    # identical result columns, not merely close: no wall clock enters a pose or a force
    timing = ["session", "rtt_us", "service_us"]
    pd.testing.assert_frame_equal(again.table.drop(columns=timing),
                                  local.table.drop(columns=timing), check_exact=True)
    # the written table and summary agree with the run
    written = pd.read_parquet(tmp_path / "again" / "study.parquet")
    assert study_digest(study, written) == again.digest
    summary = json.loads((tmp_path / "again" / "study.json").read_text())
    assert summary["digest"] == again.digest and summary["tasks"] == len(study.tasks)
    # every task pressed skin, and the stiffer setting of a point feels stiffer
    df = again.table
    assert df.groupby("task")["contact"].any().all()
    peak = df.groupby(["patient", "param_friction", "param_stiffness_n_per_mm"])["force_n"].max()
    for (patient, friction, k), f in peak.items():
        if k == 0.2:
            assert peak[(patient, friction, 0.3)] > f


def test_ct_patient_is_in_the_study(local):
    if not CT.exists():
        reason = f"SKIPPED: {CT} is absent"
        print(reason)
        pytest.skip(reason)
    ct = local.table[local.table["patient"] == "abdomen-ct-3mm"]
    assert len(ct) and ct["contact"].any() and set(ct["plan"]) == {"ct line"}


def test_resume_keeps_finished_tasks(local, binary, study_file, tmp_path):
    study = load_study(study_file)
    out = tmp_path / "out"

    def interrupt(task, meta):
        if task.index == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(study, out, binary=binary, progress=False, on_task=interrupt)
    # three tasks finished and written whole; no study table for an unfinished study
    files = sorted((out / "tasks").glob("*.parquet"))
    assert len(files) == 3 and not (out / "study.parquet").exists()
    assert not list((out / "tasks").glob(".*.tmp"))
    before = {f.name: (f.stat().st_ino, f.stat().st_mtime_ns) for f in files}
    # a damaged finished task is run again, not trusted
    files[0].write_bytes(files[0].read_bytes()[:100])
    ran = []
    run = run_study(study, out, binary=binary, progress=False,
                    on_task=lambda task, meta: ran.append(task.index))
    assert run.digest == local.digest
    assert run.summary["run"]["kept"] == 2 and sorted(ran) == [0] + list(range(3, len(study.tasks)))
    for f in files[1:]:
        assert (f.stat().st_ino, f.stat().st_mtime_ns) == before[f.name]
    df, why = read_task(study, study.tasks[0], out)
    assert why == "finished"


# -- Ray ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    try:
        import ray  # noqa: F401
        from palpsim.raycluster import LocalRayCluster, RayClusterError
    except ImportError as e:
        reason = f"SKIPPED: ray is not installed ({e})"
        print(reason)
        pytest.skip(reason)
    caches = [tmp_path_factory.mktemp(f"node{i}-cache") for i in range(2)]
    c = LocalRayCluster(nodes=2, cpus_per_node=1,
                        node_env=[{"PALPSIM_CACHE": str(p)} for p in caches])
    try:
        c.start()
    except RayClusterError as e:
        c.stop()
        reason = f"SKIPPED: a local Ray cluster does not start here: {e}"
        print(reason)
        pytest.skip(reason)
    yield c
    c.stop()


def _prepared_once_per_node(summary: dict) -> None:
    """Each patient was prepared (not read from the cache) at most once on each node."""
    prep = summary["run"]["prep"]
    events = [(e["node"], e["patient"]) for e in prep if e["prep"] == "prepared"]
    assert len(events) == len(set(events)), prep


def test_ray_run_gives_the_local_digest(local, cluster, binary, study_file, tmp_path, capsys):
    # the command line, as a person runs it
    out = tmp_path / "ray"
    rc = batch_main([str(study_file), "--ray", cluster.address, "--server", str(binary),
                     "--out", str(out), "--no-progress"])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    summary = json.loads((out / "study.json").read_text())
    r = summary["run"]
    assert summary["digest"] == local.digest and local.digest[:16] in printed
    assert study_digest(load_study(study_file), pd.read_parquet(out / "study.parquet")) == local.digest
    assert r["mode"] == "ray" and r["nodes"] == 2 and r["workers"] == 2 and r["retried"] == 0
    _prepared_once_per_node(summary)
    # both workers did work
    assert len({e["node"] for e in r["prep"]}) == 2


def test_ray_gives_each_gpu_one_worker(local, binary, study_file, tmp_path):
    """One node declaring two GPUs (this machine has none; Ray schedules by the count):
    two workers, each with its own CUDA_VISIBLE_DEVICES for its palpsim-server (which
    falls back to the CPU here), and the study's digest stays the local one."""
    try:
        import ray  # noqa: F401
        from palpsim.raycluster import LocalRayCluster, RayClusterError
    except ImportError as e:
        pytest.skip(f"SKIPPED: ray is not installed ({e})")
    # on 127.0.0.10: apart from the module's two-node cluster on .2 and .3
    c = LocalRayCluster(nodes=1, cpus_per_node=1, gpus_per_node=2, first_ip=10,
                        node_env=[{"PALPSIM_CACHE": str(tmp_path / "cache")}])
    try:
        c.start()
    except RayClusterError as e:
        c.stop()
        pytest.skip(f"SKIPPED: a local Ray cluster does not start here: {e}")
    try:
        run = run_study(load_study(study_file), tmp_path / "ray-gpu", binary=binary, ray_address=c.address,
                        progress=False)
    finally:
        c.stop()
    r = run.summary["run"]
    assert run.digest == local.digest
    assert r["workers"] == 2 and r["nodes"] == 1, r
    assert sorted(r["gpus"]) == ["0", "1"], r


def test_ray_worker_killed_mid_study(local, cluster, binary, study_file, tmp_path):
    killed = []

    def kill_first(task, meta):
        # the worker that finished the first task holds a second one: kill its process
        if not killed:
            killed.append(meta["pid"])
            os.kill(meta["pid"], signal.SIGKILL)

    study = load_study(study_file)
    run = run_study(study, tmp_path / "ray", binary=binary, ray_address=cluster.address,
                    progress=False, on_task=kill_first)
    r = run.summary["run"]
    assert run.digest == local.digest
    assert r["retried"] >= 1 and r["ran"] == len(study.tasks), r
    _prepared_once_per_node(run.summary)


def test_ray_node_killed_mid_study(local, cluster, binary, study_file, tmp_path):
    """Runs last: it ends the cluster's second node."""
    study = load_study(study_file)
    second = []

    def kill_node(task, meta):
        if not second:
            second.append(meta["node"])
            cluster.kill_node(1)

    run = run_study(study, tmp_path / "ray", binary=binary, ray_address=cluster.address,
                    progress=False, on_task=kill_node)
    r = run.summary["run"]
    assert run.digest == local.digest
    # the killed node's tasks in flight were lost and run again on the head's worker
    assert r["retried"] >= 1 and r["ran"] == len(study.tasks), r
