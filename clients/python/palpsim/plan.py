"""Palpation plans: parsing and validation of a plan file, and its expansion into presses.

A plan (TOML or JSON, same keys) describes a grid of press points over a skin region,
how each point is pressed, how often, and at which sample rate. Units: millimetres,
seconds, newtons; coordinates in the CT's physical space (LPS).

    name = "lumbar grid"
    sample_rate_hz = 500          # poses per second of trajectory time
    repetitions = 2               # presses per point

    [grid]                        # press points: center + offsets along two axes
    center_mm = [0.0, 110.0, 0.0] # a point of the region (on or near the skin)
    axis_u = [1.0, 0.0, 0.0]      # first grid direction (normalized here)
    axis_v = [0.0, 0.0, 1.0]      # second grid direction (normalized here)
    size_u_mm = 40.0              # extent along axis_u (points from -size/2 to +size/2)
    size_v_mm = 80.0
    count_u = 5                   # points along axis_u (1: a line along axis_v)
    count_v = 9

    [press]
    direction = [0.0, -1.0, 0.0]  # press direction, into the body (normalized here)
    reference = "skin"            # "skin": depth counted from the first contact;
                                  # "plane": depth counted from the grid point itself
    depth_mm = 8.0                # how far to press beyond the reference
    speed_mm_per_s = 20.0         # tip speed while approaching, pressing and retracting
    approach_mm = 15.0            # start this far before the grid point, against direction
    max_travel_mm = 40.0          # "skin": give up if no contact this far past the grid point
    hold_s = 0.05                 # hold at full depth

    [parameters]                  # optional: session parameters set before pressing
    friction = 0.2

Every press starts from a fresh session state (the runner resets the session) and its
poses are a function of the plan and of the server's deterministic replies only: no
wall-clock enters a trajectory, so the same plan gives the same numbers again.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

# phases of a press, in the order they happen; stored as small integers in the table
PHASES = ("approach", "press", "hold", "retract")
APPROACH, PRESS, HOLD, RETRACT = range(4)


class PlanError(ValueError):
    """A plan is malformed; the message names the file and the field and says what is wrong."""


@dataclass(frozen=True)
class Grid:
    """Press points: `center_mm` plus offsets along two unit axes (mm)."""

    center_mm: tuple[float, float, float]
    axis_u: tuple[float, float, float]
    axis_v: tuple[float, float, float]
    size_u_mm: float
    size_v_mm: float
    count_u: int
    count_v: int


@dataclass(frozen=True)
class Press:
    """How each point is pressed (mm, mm/s, s)."""

    direction: tuple[float, float, float]
    reference: str
    depth_mm: float
    speed_mm_per_s: float
    approach_mm: float
    max_travel_mm: float
    hold_s: float


@dataclass(frozen=True)
class Plan:
    """A validated palpation plan."""

    name: str
    sample_rate_hz: float
    repetitions: int
    grid: Grid
    press: Press
    parameters: dict[str, float] = field(default_factory=dict)
    source: str = "<plan>"

    @property
    def step_mm(self) -> float:
        """Tip travel per pose (mm): speed divided by sample rate."""
        return self.press.speed_mm_per_s / self.sample_rate_hz

    def to_dict(self) -> dict[str, Any]:
        """The plan as plain data (the same keys as the file), for summaries."""
        g, p = self.grid, self.press
        return {
            "name": self.name,
            "sample_rate_hz": self.sample_rate_hz,
            "repetitions": self.repetitions,
            "grid": {k: list(v) if isinstance(v, tuple) else v for k, v in g.__dict__.items()},
            "press": {k: list(v) if isinstance(v, tuple) else v for k, v in p.__dict__.items()},
            "parameters": dict(self.parameters),
        }


@dataclass(frozen=True)
class PressPoint:
    """One grid point: its index, grid coordinates and position (mm)."""

    point_id: int
    iu: int
    iv: int
    u_mm: float
    v_mm: float
    target_mm: np.ndarray  # the grid point itself (on the reference plane)
    start_mm: np.ndarray   # where the press starts: target - approach * direction


@dataclass(frozen=True)
class PressTask:
    """One press of one point: the unit of work a session runs after a reset."""

    index: int  # position in the plan's order (point-major, then repetition)
    point: PressPoint
    rep: int


# limits that catch absurd plans before they run for hours (see _check_size)
MAX_RATE_HZ = 10_000.0
MAX_POSES = 50_000_000
MAX_LENGTH_MM = 2_000.0

_TOP_KEYS = {"name", "sample_rate_hz", "repetitions", "grid", "press", "parameters"}
_GRID_KEYS = {"center_mm", "axis_u", "axis_v", "size_u_mm", "size_v_mm", "count_u", "count_v"}
_PRESS_KEYS = {"direction", "reference", "depth_mm", "speed_mm_per_s", "approach_mm",
               "max_travel_mm", "hold_s"}
_PRESS_DEFAULTS = {"reference": "skin", "approach_mm": 15.0, "max_travel_mm": 40.0, "hold_s": 0.0}


class _Fields:
    """Reads typed fields of one table of the plan, naming `source: table.key` in errors."""

    def __init__(self, source: str, table: str, data: Any, known: set[str]):
        self.source, self.table = source, table
        if not isinstance(data, Mapping):
            raise self.error(None, f"must be a table, got {type(data).__name__}")
        unknown = sorted(set(data) - known)
        if unknown:
            raise self.error(unknown[0], f"unknown field (known: {', '.join(sorted(known))})")
        self.data = data

    def error(self, key: str | None, what: str) -> PlanError:
        name = ".".join(x for x in (self.table, key) if x) or "plan"
        return PlanError(f"{self.source}: {name}: {what}")

    def get(self, key: str, default: Any = None, required: bool = True) -> Any:
        if key in self.data:
            return self.data[key]
        if required and default is None:
            raise self.error(key, "missing (required)")
        return default

    def number(self, key: str, lo: float, hi: float, default: float | None = None,
               lo_open: bool = False) -> float:
        v = self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(key, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.error(key, f"must be finite, got {v!r}")
        if v < lo or v > hi or (lo_open and v == lo):
            left = "(" if lo_open else "["
            raise self.error(key, f"must be in {left}{lo:g}, {hi:g}], got {v:g}")
        return v

    def integer(self, key: str, lo: int, hi: int, default: int | None = None) -> int:
        v = self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            if isinstance(v, float) and v.is_integer():
                v = int(v)
            else:
                raise self.error(key, f"must be an integer, got {v!r}")
        if v < lo or v > hi:
            raise self.error(key, f"must be in [{lo}, {hi}], got {v}")
        return v

    def vector(self, key: str, unit: bool) -> tuple[float, float, float]:
        v = self.get(key)
        if (not isinstance(v, (list, tuple)) or len(v) != 3
                or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in v)):
            raise self.error(key, f"must be a list of 3 numbers, got {v!r}")
        a = np.array(v, dtype=float)
        if not np.all(np.isfinite(a)):
            raise self.error(key, f"must be finite, got {v!r}")
        if unit:
            n = float(np.linalg.norm(a))
            # a direction needs a length well above rounding noise to be normalized
            if n < 1e-9:
                raise self.error(key, "must not be the zero vector")
            a = a / n
        elif np.max(np.abs(a)) > 10 * MAX_LENGTH_MM:
            raise self.error(key, f"is {np.max(np.abs(a)):g} mm from the origin: absurd for a patient")
        return (float(a[0]), float(a[1]), float(a[2]))


def parse_plan(data: Mapping[str, Any], source: str = "<plan>") -> Plan:
    """Validates plan data (a dict as read from TOML or JSON) and returns a Plan.

    Raises PlanError naming `source` and the field for anything missing, unknown,
    of the wrong type or out of range."""
    top = _Fields(source, "", data, _TOP_KEYS)
    name = top.get("name", default=Path(source).stem if source != "<plan>" else "plan")
    if not isinstance(name, str):
        raise top.error("name", f"must be a string, got {name!r}")
    rate = top.number("sample_rate_hz", 0.0, MAX_RATE_HZ, lo_open=True)
    reps = top.integer("repetitions", 1, 1000, default=1)

    g = _Fields(source, "grid", top.get("grid"), _GRID_KEYS)
    grid = Grid(
        center_mm=g.vector("center_mm", unit=False),
        axis_u=g.vector("axis_u", unit=True),
        axis_v=g.vector("axis_v", unit=True),
        size_u_mm=g.number("size_u_mm", 0.0, MAX_LENGTH_MM, default=0.0),
        size_v_mm=g.number("size_v_mm", 0.0, MAX_LENGTH_MM, default=0.0),
        count_u=g.integer("count_u", 1, 10_000, default=1),
        count_v=g.integer("count_v", 1, 10_000, default=1),
    )
    if grid.count_u > 1 and grid.count_v > 1:
        # a 2-D grid needs two independent axes
        if abs(float(np.dot(grid.axis_u, grid.axis_v))) > 1 - 1e-6:
            raise g.error("axis_v", "is parallel to axis_u: the grid would collapse to a line")

    p = _Fields(source, "press", top.get("press"), _PRESS_KEYS)
    reference = p.get("reference", _PRESS_DEFAULTS["reference"])
    if reference not in ("skin", "plane"):
        raise p.error("reference", f'must be "skin" or "plane", got {reference!r}')
    press = Press(
        direction=p.vector("direction", unit=True),
        reference=reference,
        depth_mm=p.number("depth_mm", 0.0, 200.0, lo_open=True),
        speed_mm_per_s=p.number("speed_mm_per_s", 0.0, 1000.0, lo_open=True),
        approach_mm=p.number("approach_mm", 0.0, MAX_LENGTH_MM, default=_PRESS_DEFAULTS["approach_mm"]),
        max_travel_mm=p.number("max_travel_mm", 0.0, MAX_LENGTH_MM,
                               default=_PRESS_DEFAULTS["max_travel_mm"]),
        hold_s=p.number("hold_s", 0.0, 60.0, default=_PRESS_DEFAULTS["hold_s"]),
    )

    params = top.get("parameters", default={}, required=False)
    if not isinstance(params, Mapping):
        raise top.error("parameters", f"must be a table of name = number, got {params!r}")
    parameters: dict[str, float] = {}
    pf = _Fields(source, "parameters", params, set(params))
    for key in sorted(params):
        if not isinstance(key, str) or not key:
            raise pf.error(str(key), "parameter names must be non-empty strings")
        parameters[key] = pf.number(key, -1e12, 1e12)

    plan = Plan(name=name, sample_rate_hz=rate, repetitions=reps, grid=grid, press=press,
                parameters=parameters, source=source)
    _check_size(plan, top)
    return plan


def _check_size(plan: Plan, top: _Fields) -> None:
    """Refuses plans whose pose count is absurd (hours of work by mistake)."""
    p = plan.press
    travel = p.approach_mm + (p.max_travel_mm + p.depth_mm if p.reference == "skin" else p.depth_mm)
    steps = 2 * travel / plan.step_mm + p.hold_s * plan.sample_rate_hz + 4
    poses = steps * plan.grid.count_u * plan.grid.count_v * plan.repetitions
    if poses > MAX_POSES:
        raise top.error("sample_rate_hz",
                        f"the plan would send about {poses:.3g} poses (limit {MAX_POSES:.0e}): "
                        "lower the sample rate, the grid counts or the repetitions")


def load_plan(path: str | Path) -> Plan:
    """Reads and validates a plan file (.toml or .json)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise PlanError(f"{path}: unknown plan format {suffix!r} (use .toml or .json)")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise PlanError(f"{path}: cannot read the plan: {e.strerror or e}") from None
    try:
        data = tomllib.loads(raw.decode("utf-8")) if suffix == ".toml" else json.loads(raw)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise PlanError(f"{path}: not valid {suffix[1:].upper()}: {e}") from None
    return parse_plan(data, source=str(path))


def grid_points(plan: Plan) -> list[PressPoint]:
    """The plan's press points, row by row: point_id = iv * count_u + iu."""
    g, p = plan.grid, plan.press
    center, au, av = (np.array(x, dtype=float) for x in (g.center_mm, g.axis_u, g.axis_v))
    d = np.array(p.direction, dtype=float)

    def offsets(size: float, count: int) -> np.ndarray:
        if count == 1:
            return np.zeros(1)
        return -size / 2 + size * np.arange(count) / (count - 1)

    us, vs = offsets(g.size_u_mm, g.count_u), offsets(g.size_v_mm, g.count_v)
    points = []
    for iv, v in enumerate(vs):
        for iu, u in enumerate(us):
            target = center + u * au + v * av
            points.append(PressPoint(point_id=iv * g.count_u + iu, iu=iu, iv=iv,
                                     u_mm=float(u), v_mm=float(v), target_mm=target,
                                     start_mm=target - p.approach_mm * d))
    return points


def expand(plan: Plan) -> list[PressTask]:
    """Every press of the plan in a fixed order (point by point, repetitions inside)."""
    tasks = []
    for point in grid_points(plan):
        for rep in range(plan.repetitions):
            tasks.append(PressTask(index=len(tasks), point=point, rep=rep))
    return tasks


class PressPath:
    """The pose sequence of one press, step by step, as a small state machine.

    Travel s (mm, along the press direction from the start) grows by `step_mm` per
    pose while approaching and pressing, stays at its maximum while holding, and
    falls back to 0 while retracting. With reference "skin" the press target is the
    travel at the first pose the server reported in contact plus depth_mm; with
    "plane" it is approach_mm + depth_mm, known in advance. The next pose depends
    only on the plan and on the contact flags already received, never on time."""

    def __init__(self, plan: Plan, point: PressPoint):
        p = plan.press
        self.start = point.start_mm
        self.direction = np.array(p.direction, dtype=float)
        self.step_mm = plan.step_mm
        self.rate_hz = plan.sample_rate_hz
        self.skin = p.reference == "skin"
        self.depth_mm = p.depth_mm
        self.hold_steps = int(round(p.hold_s * plan.sample_rate_hz))
        # with "skin", approaching stops at first contact or after this much travel
        self.approach_limit_mm = p.approach_mm + (p.max_travel_mm if self.skin else 0.0)
        self.target_mm = None if self.skin else p.approach_mm + p.depth_mm
        self.contact_travel_mm: float | None = None
        self.phase = APPROACH
        self.k = 0  # pose index within the press
        self.s = 0.0
        self.peak_s = 0.0
        self.phase_k = 0  # poses since HOLD or RETRACT began
        self.done = False

    def pose(self) -> tuple[int, float, int, float, np.ndarray]:
        """The current pose: (step, t_s, phase, travel_mm, tip position in mm)."""
        return self.k, self.k / self.rate_hz, self.phase, self.s, self.start + self.s * self.direction

    def advance(self, contact: bool) -> None:
        """Moves to the next pose given the contact flag of the current pose's reply."""
        self.k += 1
        # approaching: stop at the first contact ("skin") or at the grid plane ("plane")
        if self.phase == APPROACH:
            if self.skin and contact:
                self.contact_travel_mm = self.s
                self.target_mm = self.s + self.depth_mm
                self.phase = PRESS
            elif self.s >= self.approach_limit_mm:
                if self.skin:
                    # no skin within max_travel_mm: go back without pressing
                    self._begin(RETRACT)
                else:
                    self.phase = PRESS
        # moving inwards: travel is step index times step, so it never drifts
        if self.phase in (APPROACH, PRESS):
            limit = self.approach_limit_mm if self.phase == APPROACH else self.target_mm
            if self.s < limit:
                self.s = min(self.k * self.step_mm, limit)
                return
            self._begin(HOLD if self.hold_steps > 0 else RETRACT)
        # holding at full depth for hold_steps poses
        if self.phase == HOLD:
            self.phase_k += 1
            if self.phase_k <= self.hold_steps:
                return
            self._begin(RETRACT)
        # retracting to the start, then done
        if self.s <= 0.0:
            self.done = True
            return
        self.phase_k += 1
        self.s = max(self.peak_s - self.phase_k * self.step_mm, 0.0)

    def _begin(self, phase: int) -> None:
        """Enters HOLD or RETRACT from the current (deepest) travel."""
        self.peak_s = self.s
        self.phase = phase
        self.phase_k = 0
