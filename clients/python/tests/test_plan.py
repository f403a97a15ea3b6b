"""Plan files: parsing, clear errors that name the field, and deterministic expansion."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import PLAN
from palpsim.plan import (APPROACH, HOLD, PRESS, RETRACT, PlanError, PressPath, expand,
                          grid_points, load_plan, parse_plan)


def _toml(d: dict) -> str:
    """A tiny TOML writer for the plan's shape (scalars, lists, one level of tables)."""
    def val(v):
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)
    lines = [f"{k} = {val(v)}" for k, v in d.items() if not isinstance(v, dict)]
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"[{k}]")
            lines += [f"{kk} = {val(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def test_toml_and_json_give_the_same_plan(tmp_path):
    (tmp_path / "p.toml").write_text(_toml(PLAN))
    (tmp_path / "p.json").write_text(json.dumps(PLAN))
    a, b = load_plan(tmp_path / "p.toml"), load_plan(tmp_path / "p.json")
    assert a.to_dict() == b.to_dict()
    assert a.grid.count_u == 3 and a.press.reference == "skin"
    assert a.step_mm == pytest.approx(0.1)


def test_defaults_fill_optional_fields(plan_data):
    for k in ("reference", "approach_mm", "max_travel_mm", "hold_s"):
        del plan_data["press"][k]
    del plan_data["repetitions"]
    p = parse_plan(plan_data)
    assert p.repetitions == 1 and p.press.reference == "skin" and p.press.hold_s == 0.0


@pytest.mark.parametrize("edit, field, words", [
    (lambda d: d["press"].pop("depth_mm"), "press.depth_mm", "missing"),
    (lambda d: d["press"].update(speed_mm_per_s=-1), "press.speed_mm_per_s", "must be in"),
    (lambda d: d["press"].update(speed_mm_per_s=0), "press.speed_mm_per_s", "must be in"),
    (lambda d: d["press"].update(depth_mm="deep"), "press.depth_mm", "must be a number"),
    (lambda d: d["press"].update(direction=[0, 0, 0]), "press.direction", "zero vector"),
    (lambda d: d["press"].update(direction=[0, 1]), "press.direction", "3 numbers"),
    (lambda d: d["press"].update(reference="bone"), "press.reference", '"skin" or "plane"'),
    (lambda d: d["grid"].update(cout_u=3), "grid.cout_u", "unknown field"),
    (lambda d: d["grid"].update(count_u=2.5), "grid.count_u", "integer"),
    (lambda d: d["grid"].update(count_v=0), "grid.count_v", "must be in"),
    (lambda d: d["grid"].update(axis_v=[2, 0, 0]), "grid.axis_v", "parallel"),
    (lambda d: d["grid"].update(center_mm=[0, 1e9, 0]), "grid.center_mm", "absurd"),
    (lambda d: d.pop("grid"), "grid", "missing"),
    (lambda d: d.update(sample_rate_hz=float("nan")), "sample_rate_hz", "finite"),
    (lambda d: d.update(sample_rate_hz=1e6), "sample_rate_hz", "must be in"),
    (lambda d: d.update(repetitions=True), "repetitions", "integer"),
    (lambda d: d.update(colour="red"), "colour", "unknown field"),
    (lambda d: d.update(parameters={"friction": "lots"}), "parameters.friction", "number"),
    (lambda d: d.update(sample_rate_hz=10000, repetitions=1000), "sample_rate_hz", "poses"),
])
def test_bad_plans_name_the_field(plan_data, edit, field, words):
    edit(plan_data)
    with pytest.raises(PlanError) as e:
        parse_plan(plan_data, source="bad.toml")
    msg = str(e.value)
    assert msg.startswith(f"bad.toml: {field}:"), msg
    assert words in msg, msg


def test_unreadable_files_name_the_file(tmp_path):
    with pytest.raises(PlanError, match=r"nope\.toml: cannot read"):
        load_plan(tmp_path / "nope.toml")
    (tmp_path / "p.yaml").write_text("a: 1")
    with pytest.raises(PlanError, match=r"p\.yaml: unknown plan format"):
        load_plan(tmp_path / "p.yaml")
    (tmp_path / "p.toml").write_text("name = [unclosed\n")
    with pytest.raises(PlanError, match=r"p\.toml: not valid TOML"):
        load_plan(tmp_path / "p.toml")
    (tmp_path / "p.json").write_text("{]")
    with pytest.raises(PlanError, match=r"p\.json: not valid JSON"):
        load_plan(tmp_path / "p.json")


def test_grid_points_are_ordered_centered_and_spaced(plan):
    pts = grid_points(plan)
    assert [p.point_id for p in pts] == list(range(6))
    assert [(p.iu, p.iv) for p in pts] == [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1)]
    targets = np.array([p.target_mm for p in pts])
    # the grid is symmetric about its center and spans size_u_mm x size_v_mm
    np.testing.assert_allclose(targets.mean(axis=0), PLAN["grid"]["center_mm"], atol=1e-12)
    assert np.ptp(targets[:, 0]) == pytest.approx(20.0)
    assert np.ptp(targets[:, 2]) == pytest.approx(10.0)
    # every start lies approach_mm before its target, against the press direction
    for p in pts:
        np.testing.assert_allclose(p.start_mm - p.target_mm, [0.0, 4.0, 0.0], atol=1e-12)


def test_expansion_is_deterministic(plan_data):
    a = expand(parse_plan(plan_data))
    b = expand(parse_plan(plan_data))
    assert [(t.index, t.point.point_id, t.rep) for t in a] == \
           [(t.index, t.point.point_id, t.rep) for t in b]
    assert [(t.point.point_id, t.rep) for t in a][:4] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    for x, y in zip(a, b):
        assert np.array_equal(x.point.start_mm, y.point.start_mm)


def _walk(plan, contact_at_travel_mm=None):
    """Runs one PressPath with contact from a given travel on; returns its poses."""
    path = PressPath(plan, grid_points(plan)[0])
    poses = []
    while not path.done:
        k, t, phase, s, tip = path.pose()
        poses.append((k, t, phase, s, tip.copy()))
        assert len(poses) < 100_000
        path.advance(contact_at_travel_mm is not None and s >= contact_at_travel_mm)
    return path, poses


def test_plane_press_reaches_depth_holds_and_returns(plan_data):
    plan_data["press"]["reference"] = "plane"
    plan = parse_plan(plan_data)
    path, poses = _walk(plan)  # contact flags do not matter for "plane"
    s = np.array([p[3] for p in poses])
    phases = [p[2] for p in poses]
    # travel: from 0 up to approach + depth exactly, never a step larger than step_mm
    assert s[0] == 0.0 and s[-1] == 0.0
    assert s.max() == pytest.approx(4.0 + 5.0, abs=1e-12)
    assert np.all(np.abs(np.diff(s)) <= plan.step_mm + 1e-12)
    # phases in order, hold lasts hold_s * rate poses at the deepest travel
    order = [x for i, x in enumerate(phases) if i == 0 or phases[i - 1] != x]
    assert order == [APPROACH, PRESS, HOLD, RETRACT]
    held = s[np.array(phases) == HOLD]
    assert len(held) == 4 and np.all(held == s.max())
    # time is the pose index over the sample rate: no wall clock
    assert [p[1] for p in poses] == [k / 200.0 for k in range(len(poses))]
    # tips lie on the press line
    tips = np.array([p[4] for p in poses])
    np.testing.assert_allclose(tips[:, 0], tips[0, 0])
    np.testing.assert_allclose(tips[:, 1], 104.0 - s, atol=1e-12)


def test_skin_press_counts_depth_from_first_contact(plan):
    path, poses = _walk(plan, contact_at_travel_mm=3.0)
    s = np.array([p[3] for p in poses])
    assert path.contact_travel_mm == pytest.approx(3.0, abs=plan.step_mm)
    assert s.max() == pytest.approx(path.contact_travel_mm + 5.0, abs=1e-12)
    assert s[-1] == 0.0


def test_skin_press_without_contact_gives_up_after_max_travel(plan):
    path, poses = _walk(plan, contact_at_travel_mm=None)
    s = np.array([p[3] for p in poses])
    assert path.contact_travel_mm is None
    assert s.max() == pytest.approx(4.0 + 10.0, abs=1e-12)
    assert HOLD not in [p[2] for p in poses] and PRESS not in [p[2] for p in poses]
    assert s[-1] == 0.0


def test_documented_and_example_plans_are_valid():
    import re
    import tomllib
    from pathlib import Path

    import palpsim.plan as plan_module
    # the example in the module's documentation (the indented TOML block)
    block = re.search(r"\n(    name = .*?)\n\nEvery", plan_module.__doc__, re.S).group(1)
    doc = parse_plan(tomllib.loads("\n".join(l[4:] for l in block.splitlines())), "doc")
    assert doc.grid.count_u == 5 and doc.parameters == {"friction": 0.2}
    # the shipped example plans
    examples = sorted((Path(__file__).parents[1] / "examples").glob("*.toml"))
    assert examples
    for p in examples:
        load_plan(p)
