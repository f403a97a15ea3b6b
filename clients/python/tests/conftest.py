"""Shared helpers: a small valid plan and a synthetic run of it (no server needed)."""

from __future__ import annotations

import copy

import numpy as np
import pandas as pd
import pytest

from palpsim.plan import PressPath, expand, parse_plan
from palpsim.results import finish_table

# a 3 x 2 grid pressed along -y into a flat skin at y = SKIN_Y_MM
SKIN_Y_MM = 100.0
PLAN = {
    "name": "synthetic",
    "sample_rate_hz": 200.0,
    "repetitions": 2,
    "grid": {"center_mm": [0.0, SKIN_Y_MM, 0.0], "axis_u": [1, 0, 0], "axis_v": [0, 0, 1],
             "size_u_mm": 20.0, "size_v_mm": 10.0, "count_u": 3, "count_v": 2},
    "press": {"direction": [0, -1, 0], "reference": "skin", "depth_mm": 5.0,
              "speed_mm_per_s": 20.0, "approach_mm": 4.0, "max_travel_mm": 10.0, "hold_s": 0.02},
}


@pytest.fixture
def plan_data():
    """A fresh copy of the plan's data, for tests that edit a field."""
    return copy.deepcopy(PLAN)


def synthetic_table(plan) -> pd.DataFrame:
    """Runs every press of `plan` against a closed-form body: flat skin at y = SKIN_Y_MM,
    force k * depth along +y with k = 0.2 + 0.1 * iu N/mm (so the map has structure).
    Timing columns get fixed values; everything else follows the runner's conventions."""
    cols: dict[str, list] = {k: [] for k in (
        "point_id", "iu", "iv", "u_mm", "v_mm", "rep", "step", "phase", "t_s", "travel_mm",
        "tip_x_mm", "tip_y_mm", "tip_z_mm", "depth_mm", "contact", "force_x_n", "force_y_n",
        "force_z_n", "force_n", "press_force_n", "proxy_x_mm", "proxy_y_mm", "proxy_z_mm",
        "skin_x_mm", "skin_y_mm", "skin_z_mm", "seq", "session", "rtt_us", "service_us")}
    for task in expand(plan):
        path = PressPath(plan, task.point)
        k_n_per_mm = 0.2 + 0.1 * task.point.iu
        while not path.done:
            k, t_s, phase, s, tip = path.pose()
            depth = max(SKIN_Y_MM - tip[1], 0.0)
            contact = depth > 0
            fy = k_n_per_mm * depth
            row = dict(point_id=task.point.point_id, iu=task.point.iu, iv=task.point.iv,
                       u_mm=task.point.u_mm, v_mm=task.point.v_mm, rep=task.rep, step=k,
                       phase=phase, t_s=t_s, travel_mm=s, tip_x_mm=tip[0], tip_y_mm=tip[1],
                       tip_z_mm=tip[2], depth_mm=depth, contact=contact, force_x_n=0.0,
                       force_y_n=fy, force_z_n=0.0, force_n=abs(fy), press_force_n=fy,
                       proxy_x_mm=tip[0], proxy_y_mm=tip[1] + depth, proxy_z_mm=tip[2],
                       skin_x_mm=tip[0], skin_y_mm=min(tip[1], SKIN_Y_MM), skin_z_mm=tip[2],
                       seq=(task.index << 24) + k + 1, session=task.index % 2,
                       rtt_us=100.0 + k, service_us=5.0)
            for c, v in row.items():
                cols[c].append(v)
            path.advance(contact)
    return finish_table(pd.DataFrame(cols))


@pytest.fixture
def plan():
    return parse_plan(copy.deepcopy(PLAN), source="synthetic.toml")


@pytest.fixture
def table(plan):
    return synthetic_table(plan)
