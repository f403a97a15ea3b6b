"""The tidy table, its digest, the summary and the plots, from a synthetic run."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from conftest import PLAN, synthetic_table
from palpsim.plan import parse_plan
from palpsim.plots import force_depth_plot, peak_force_plot
from palpsim.results import (COLUMNS, TableError, finish_table, format_summary, point_table,
                             read_table, result_digest, summarize, write_json, write_table)


def test_canonical_table_does_not_depend_on_row_order_or_timing(table):
    shuffled = table.sample(frac=1.0, random_state=3)[list(reversed(COLUMNS))]
    again = finish_table(shuffled)
    pd.testing.assert_frame_equal(again, table)
    # timing columns (session, rtt, service time) are not results
    timing = table.copy()
    timing["session"] = 7
    timing["rtt_us"] *= 3
    assert result_digest(timing) == result_digest(table)
    # any result change changes the digest
    changed = table.copy()
    changed.loc[10, "force_y_n"] += 1e-12
    assert result_digest(changed) != result_digest(table)


def test_missing_columns_are_named(table):
    with pytest.raises(TableError, match="force_n"):
        finish_table(table.drop(columns=["force_n"]))


@pytest.mark.parametrize("name", ["steps.csv", "steps.parquet"])
def test_table_round_trips_exactly(table, tmp_path, name):
    path = write_table(table, tmp_path / "sub" / name)
    back = read_table(path)
    pd.testing.assert_frame_equal(back, table)
    assert result_digest(back) == result_digest(table)
    # nothing but the table is left behind (the temporary file was renamed)
    assert [p.name for p in (tmp_path / "sub").iterdir()] == [name]


def test_unknown_table_format_is_refused(table, tmp_path):
    with pytest.raises(TableError, match=r"steps\.xlsx: unknown table format"):
        write_table(table, tmp_path / "steps.xlsx")
    assert not any(tmp_path.iterdir())


def test_summary_matches_the_synthetic_physics(table, plan):
    s = summarize(table, plan.to_dict(), {"sessions": 2, "wall_s": 1.0, "poses_per_s": 1.0})
    assert s["points"] == 6 and s["presses"] == 12 and s["poses"] == len(table)
    assert s["presses_without_contact"] == 0
    # no force out of contact; every press reaches depth_mm beyond its first contact
    assert s["force"]["max_force_out_of_contact_n"] == 0.0
    pts = point_table(table)
    # first contact happens within one step past the skin, so depth is 5 mm + < 1 step
    step = plan.step_mm
    assert np.all(pts["max_depth_mm"] >= 5.0) and np.all(pts["max_depth_mm"] <= 5.0 + step + 1e-9)
    # the synthetic stiffness grows with iu, and so does the peak force
    k = 0.2 + 0.1 * pts["iu"]
    np.testing.assert_allclose(pts["peak_force_n"], k * pts["max_depth_mm"], rtol=1e-12)
    assert s["force"]["strongest_point"]["point_id"] in (2, 5)
    # repetitions restart from the same state: identical peaks
    assert s["repeatability"]["max_peak_spread_n"] == 0.0
    # the skin point of each press is where it met y = 100
    np.testing.assert_allclose(pts["skin_y_mm"], 100.0 - step, atol=1e-9)
    text = format_summary(s)
    assert "6 points, 12 presses" in text and s["digest"][:16] in text


def test_summary_json_is_strict_json(table, plan, tmp_path):
    s = summarize(table, plan.to_dict())
    s["nan_field"] = float("nan")
    path = write_json(s, tmp_path / "summary.json")
    back = json.loads(path.read_text())
    assert back["nan_field"] is None
    assert back["per_point"][0]["point_id"] == 0
    assert back["plan"]["grid"]["count_u"] == 3


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_plots_are_written(table, tmp_path):
    a = force_depth_plot(table, tmp_path / "fd.png")
    b = peak_force_plot(table, tmp_path / "map.png")
    for p in (a, b):
        w, h = _png_size(p)
        assert w > 300 and h > 300


def test_profile_plot_for_a_line_of_points(tmp_path):
    data = json.loads(json.dumps(PLAN))
    data["grid"].update(count_u=1, count_v=7, size_v_mm=30.0)
    data["repetitions"] = 1
    line = synthetic_table(parse_plan(data))
    w, h = _png_size(peak_force_plot(line, tmp_path / "line.png"))
    assert w > h  # the profile's landscape figure
