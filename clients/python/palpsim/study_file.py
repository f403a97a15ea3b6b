"""The study file: plans x patients x a grid of haptics parameters, read and checked into
a Study of tasks (palpsim.study runs them).

A study file (TOML; paths relative to the study file):

    name = "lumbar study"
    plans = ["phantom_line.toml", "ct_line.toml"]   # existing plan files

    [[patients]]                    # one scene each: a phantom variant or a CT
    name = "phantom-2mm"            # default: the scene file's stem
    scene = "phantom_2mm.textproto"
    plans = ["phantom line"]        # optional: only these plans (by plan name); default all

    [[patients]]
    scene = "ct_3mm.textproto"      # its ct_path: "data:...", absolute, or relative to the scene
    plans = ["ct line"]

    [grid]                          # optional: every combination of these values
    stiffness_n_per_mm = [0.2, 0.3] # names and ranges of scene.proto's Haptics (SetParameter)
    friction = [0.1, 0.2]

The study expands into tasks (patient, plan, setting), patient by patient, then plan by
plan, then setting by setting (the grid's names sorted, the last name varying fastest).
A task runs its plan with the setting's parameters over the plan's own [parameters] on a
server serving the patient's scene; its rows are the batch table (results.COLUMNS) with
key columns in front: task, patient, plan, setting and one param_<name> per grid name.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from .plan import Plan, PlanError, load_plan

# the grid's parameter columns are named PARAM_PREFIX + name
PARAM_PREFIX = "param_"

_TOP_KEYS = {"name", "plans", "patients", "grid"}
_PATIENT_KEYS = {"name", "scene", "plans"}


class StudyError(ValueError):
    """A study is malformed or cannot run; the message names the file and field."""


@dataclass(frozen=True)
class Patient:
    """One patient of a study: a scene file (absolute path) and its content hash."""

    name: str
    scene: str
    scene_sha256: str
    plans: tuple[str, ...]


@dataclass(frozen=True)
class Task:
    """One unit of work: a plan run with one parameter setting on one patient."""

    index: int
    key: str
    patient: Patient
    plan: Plan
    setting: int
    parameters: tuple[tuple[str, float], ...]  # the grid's values, by name

    def run_plan(self) -> Plan:
        """The plan with this setting's parameters over its own."""
        return dataclasses.replace(self.plan, parameters={**self.plan.parameters,
                                                          **dict(self.parameters)})

    def spec_hash(self) -> str:
        """SHA-256 of what decides this task's results: scene text, plan, parameters, key."""
        spec = {"key": self.key, "index": self.index, "patient": self.patient.name,
                "scene_sha256": self.patient.scene_sha256, "plan": self.plan.to_dict(),
                "setting": self.setting, "parameters": list(self.parameters)}
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class Study:
    """A validated study: its patients, plans, grid and tasks."""

    name: str
    source: str
    patients: tuple[Patient, ...]
    plans: tuple[Plan, ...]
    grid: tuple[tuple[str, tuple[float, ...]], ...]
    tasks: tuple[Task, ...]

    @property
    def param_columns(self) -> list[str]:
        """The grid's parameter columns, in name order."""
        return [PARAM_PREFIX + n for n, _ in self.grid]

    @property
    def key_columns(self) -> list[str]:
        """The columns that say which task a row belongs to."""
        return ["task", "patient", "plan", "setting"] + self.param_columns


def _haptics_ranges() -> dict[str, tuple[float, float, str]]:
    """SetParameter's names and ranges, from the scene schema the server checks them with."""
    from .proto import _load
    scene_pb2 = _load("scene_pb2")
    options_pb2 = _load("options_pb2")
    out = {}
    for f in scene_pb2.Haptics.DESCRIPTOR.fields:
        o = f.GetOptions()
        out[f.name] = (o.Extensions[options_pb2.min], o.Extensions[options_pb2.max],
                       o.Extensions[options_pb2.unit])
    return out


def _slug(name: str) -> str:
    s = "".join(c if c.isalnum() or c in "-_." else "_" for c in name.strip().lower())
    return s.strip("_.") or "x"


def _check_scene(path: Path, where: str) -> str:
    """Parses a scene file as the server's schema (text format); returns its SHA-256."""
    from google.protobuf import text_format
    from .proto import _load
    scene_pb2 = _load("scene_pb2")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise StudyError(f"{where}: cannot read the scene {path}: {e.strerror or e}") from None
    try:
        text_format.Parse(raw.decode("utf-8"), scene_pb2.Scene())
    except (text_format.ParseError, UnicodeDecodeError) as e:
        raise StudyError(f"{where}: {path} is not a valid scene: {e}") from None
    return hashlib.sha256(raw).hexdigest()


def parse_study(data: Mapping[str, Any], source: str) -> Study:
    """Validates study data (a dict as read from TOML) and expands it into tasks.

    Relative paths are relative to the folder of `source`. Raises StudyError naming
    `source` and the field for anything missing, unknown, of the wrong type or out of range."""
    base = Path(source).resolve().parent

    def err(field: str, what: str) -> StudyError:
        return StudyError(f"{source}: {field}: {what}")

    if not isinstance(data, Mapping):
        raise StudyError(f"{source}: must be a table")
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise err(unknown[0], f"unknown field (known: {', '.join(sorted(_TOP_KEYS))})")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str) or not name.strip():
        raise err("name", f"must be a non-empty string, got {name!r}")

    # plans: existing plan files, each validated by plan.load_plan
    plan_files = data.get("plans")
    if not isinstance(plan_files, list) or not plan_files \
            or not all(isinstance(p, str) for p in plan_files):
        raise err("plans", "must be a non-empty list of plan file paths")
    plans: list[Plan] = []
    for i, f in enumerate(plan_files):
        try:
            plan = load_plan(base / f)
        except PlanError as e:
            raise err(f"plans[{i}]", str(e)) from None
        if any(p.name == plan.name for p in plans):
            raise err(f"plans[{i}]", f"a second plan named {plan.name!r} (plan names must differ)")
        plans.append(plan)
    plan_names = [p.name for p in plans]

    # patients: scene files, names unique, optional plan subsets
    raw_patients = data.get("patients")
    if not isinstance(raw_patients, list) or not raw_patients:
        raise err("patients", "must be a non-empty list of [[patients]] tables")
    patients: list[Patient] = []
    for i, rp in enumerate(raw_patients):
        where = f"patients[{i}]"
        if not isinstance(rp, Mapping):
            raise err(where, f"must be a table with a scene, got {rp!r}")
        bad = sorted(set(rp) - _PATIENT_KEYS)
        if bad:
            raise err(f"{where}.{bad[0]}", f"unknown field (known: {', '.join(sorted(_PATIENT_KEYS))})")
        scene = rp.get("scene")
        if not isinstance(scene, str) or not scene:
            raise err(f"{where}.scene", "missing: the patient's scene file (.textproto)")
        path = (base / scene).resolve()
        sha = _check_scene(path, f"{source}: {where}.scene")
        pname = rp.get("name", path.stem)
        if not isinstance(pname, str) or not pname.strip():
            raise err(f"{where}.name", f"must be a non-empty string, got {pname!r}")
        if any(p.name == pname for p in patients):
            raise err(f"{where}.name", f"a second patient named {pname!r} (names must differ)")
        chosen = rp.get("plans", plan_names)
        if not isinstance(chosen, list) or not chosen:
            raise err(f"{where}.plans", "must be a non-empty list of plan names")
        for p in chosen:
            if p not in plan_names:
                raise err(f"{where}.plans", f"{p!r} is not the name of a plan of this study "
                                            f"(plans: {', '.join(map(repr, plan_names))})")
        patients.append(Patient(name=pname, scene=str(path), scene_sha256=sha,
                                plans=tuple(p for p in plan_names if p in chosen)))

    # the grid: every combination of the named haptics parameters' values
    raw_grid = data.get("grid", {})
    if not isinstance(raw_grid, Mapping):
        raise err("grid", "must be a table of parameter = [values]")
    ranges = _haptics_ranges()
    grid: list[tuple[str, tuple[float, ...]]] = []
    for pname in sorted(raw_grid):
        values = raw_grid[pname]
        field = f"grid.{pname}"
        if pname not in ranges:
            raise err(field, f"not a haptics parameter (SetParameter takes: {', '.join(ranges)})")
        if not isinstance(values, list) or not values:
            raise err(field, "must be a non-empty list of numbers")
        lo, hi, unit = ranges[pname]
        for v in values:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise err(field, f"must hold finite numbers, got {v!r}")
            if not lo <= v <= hi:
                raise err(field, f"{v:g} is outside [{lo:g}, {hi:g}] {unit}".rstrip())
        if len(set(map(float, values))) != len(values):
            raise err(field, f"holds a value twice: {values}")
        grid.append((pname, tuple(float(v) for v in values)))

    # the tasks, in canonical order
    settings = list(itertools.product(*[vals for _, vals in grid])) or [()]
    names = [n for n, _ in grid]
    tasks: list[Task] = []
    for patient in patients:
        for plan in plans:
            if plan.name not in patient.plans:
                continue
            for s, values in enumerate(settings):
                key = f"{_slug(patient.name)}--{_slug(plan.name)}--s{s:03d}"
                tasks.append(Task(index=len(tasks), key=key, patient=patient, plan=plan,
                                  setting=s, parameters=tuple(zip(names, values))))
    keys = [t.key for t in tasks]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise err("patients", f"two tasks share the file name {dup!r}: patient or plan names "
                              "differ only in characters a file name cannot hold")
    return Study(name=name, source=source, patients=tuple(patients), plans=tuple(plans),
                 grid=tuple(grid), tasks=tuple(tasks))


def load_study(path: str | Path) -> Study:
    """Reads and validates a study file (.toml)."""
    path = Path(path)
    if path.suffix.lower() != ".toml":
        raise StudyError(f"{path}: a study file is TOML (.toml)")
    try:
        data = tomllib.loads(path.read_bytes().decode("utf-8"))
    except OSError as e:
        raise StudyError(f"{path}: cannot read the study: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise StudyError(f"{path}: not valid TOML: {e}") from None
    return parse_study(data, source=str(path))


def is_study_file(path: str | Path) -> bool:
    """True for a TOML file with a `patients` list (a study rather than a plan)."""
    path = Path(path)
    if path.suffix.lower() != ".toml":
        return False
    try:
        return "patients" in tomllib.loads(path.read_text("utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False
