"""bench/accuracy_report.py (the report of `palpsim-bench accuracy`) on a tiny constructed JSON."""

import json
import os
import sys

import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "..", "bench"))
import accuracy_report as rep  # noqa: E402


def _row(backend, knob, setting, ms, a_u, a_j, b, c):
    return {"backend": backend, "knob": knob, "setting": setting, "reps": 3, "moved": 10,
            "step": {"median_ms": ms, "p10_ms": ms, "p90_ms": ms}, "stage": {"median_ms": ms, "p10_ms": ms, "p90_ms": ms},
            "errors": {"a_u_pct": a_u, "a_u_rms_vox": a_u / 100, "a_J_pct": a_j, "a_J_rms_hu": a_j, "b_shape_pct": b,
                       "b_isotropy_pct": 3.0, "b_ratio6": 0.97, "c_u_pct": c, "c_corr": 0.9}}


def _doc(rows, device="cpu only"):
    return {"area": "accuracy", "date": "2026-11-23T00:00:00Z", "device": device, "host_cpu": "test cpu",
            "host_threads": 2, "commit": "abc1234", "quick": True, "storage": "fp32",
            "phantom": {"voxel_mm": 1.333, "size": [1, 1, 1]},
            "press": {"landmark": "spinous_tip_L3", "press_mm": 10, "bone_depth_mm": 23.0},
            "base": {"preset": "p1", "voi_edge": 64, "relax_method": "diffusion", "relax_iterations": 20,
                     "invert_iterations": 8},
            "reference_a": {"relax_steady_state_multigrid_steps": 20, "invert_iterations": 64, "voi_edge": 160},
            "reference_b": {"block_voxels": 64, "press_vox": 6, "nu": 0.45, "r_min_vox": 3, "r_max_vox": 12},
            "reference_c": {"nu": 0.45, "E_kpa": 10, "voi": [64, 52, 64], "computed": True, "solve": None},
            "rows": rows,
            "force": [{"sampling": "trilinear", "where": "all in soft tissue", "n": 10, "contact_disagree": 0, "rms_n": 0.01,
                       "max_n": 0.05, "rel_rms_pct": 2.0, "ref_rms_n": 0.5, "ns_per_pose": 300},
                      {"sampling": "nearest", "where": "all in soft tissue", "n": 10, "contact_disagree": 1, "rms_n": 0.03,
                       "max_n": 0.2, "rel_rms_pct": 6.0, "ref_rms_n": 0.5, "ns_per_pose": 50}]}


# three relaxation rows and one VOI row: errors (%) and times (ms) chosen so that each
# threshold picks a different row and one row is dominated
CPU_ROWS = [
    _row("cpu", "relaxation diffusion", "0", 10.0, 20.0, 15.0, 40.0, 50.0),
    _row("cpu", "relaxation diffusion", "20", 30.0, 8.0, 4.0, 30.0, 45.0),
    _row("cpu", "relaxation diffusion", "160", 100.0, 0.5, 0.8, 25.0, 40.0),
    _row("cpu", "VOI edge", "96", 120.0, 9.0, 9.0, 35.0, 44.0),  # slower and worse than relaxation 20: dominated
]


def test_pareto_front_skips_dominated_points_and_missing_values():
    pts = [(10, 20), (30, 8), (100, 0.8), (120, 9), (None, 1), (5, float("nan"))]
    assert rep.pareto(pts) == [0, 1, 2]


def test_fastest_within_each_threshold_of_reference_a():
    rows = rep.merged_rows(_doc(CPU_ROWS))
    err = rep.REFERENCES[0][2]
    pick = {th: rep.fastest_within(rows, lambda r: err(r["errors"]), th, "cpu_ms") for th in (1, 5, 10, 25)}
    # (a) is the larger of the u and J errors: 20 / 8 / 0.8 / 9
    assert pick[1]["setting"] == "160"
    assert pick[5]["setting"] == "160"
    assert pick[10]["setting"] == "20"
    assert pick[25]["setting"] == "0"
    assert rep.fastest_within(rows, lambda r: err(r["errors"]), 0.1, "cpu_ms") is None


def test_times_within_the_tie_factor_pick_the_first_listed_row():
    rows = [{"t": 10.2, "e": 0.0, "name": "16"}, {"t": 10.0, "e": 0.0, "name": "32"}, {"t": 9.0, "e": 50.0, "name": "0"}]
    # 10.2 ms is within 3 % of 10.0 ms: the first listed (16 iterations) is named; 0 is too wrong
    assert rep.fastest_within(rows, lambda r: r["e"], 1.0, "t")["name"] == "16"
    rows[0]["t"] = 10.5  # 5 % slower: no longer a tie
    assert rep.fastest_within(rows, lambda r: r["e"], 1.0, "t")["name"] == "32"


def test_gpu_times_merge_by_knob_and_setting():
    gpu = _doc([_row("cpu", "relaxation diffusion", "0", 5.0, 20, 15, 40, 50),
                _row("cuda", "relaxation diffusion", "0", 0.2, 20, 15, 40, 50)], device="NVIDIA H100")
    rows = rep.merged_rows(_doc(CPU_ROWS), gpu)
    assert rows[0]["gpu_ms"] == 0.2  # the cuda row, not the GPU machine's cpu row
    assert all(r["gpu_ms"] is None for r in rows[1:])
    assert len(rows) == len(CPU_ROWS)


def test_report_lists_every_row_and_the_fastest_settings(tmp_path):
    cpu = tmp_path / "cpu.json"
    cpu.write_text(json.dumps(_doc(CPU_ROWS)))
    sys.argv = ["accuracy_report.py", "--cpu", str(cpu), "--out-dir", str(tmp_path)]
    rep.main()
    md = (tmp_path / "accuracy.md").read_text()
    for r in CPU_ROWS:
        assert f"| {r['knob']} | {r['setting']} | {r['step']['median_ms']:.3f} | not measured |" in md
    # (a) per knob: relaxation's fastest within 1 % is 160, within 10 % is 20; the VOI row's 9 % is within 10
    assert "| (a) own converged solution: relaxation diffusion | 1 % | relaxation diffusion 160 (100.000, 0.8)" in md
    assert "| 10 % | relaxation diffusion 20 (30.000, 8)" in md
    assert "| (a) own converged solution: VOI edge | 1 % | none |" in md
    assert "| 10 % | VOI edge 96 (120.000, 9)" in md
    # (b): every shape error is above 10 %
    assert "| (b) Boussinesq half-space (shape) | 1 % | none |" in md
    # the force rows and the fastest force sampling within 10 %: nearest (6 %) is faster than trilinear
    assert "Fastest force sampling within 10 % of (d) (all tips in soft tissue): nearest (6 %)." in md
    assert "Fastest force sampling within 5 % of (d) (all tips in soft tissue): trilinear (2 %)." in md
    assert (tmp_path / "accuracy-cpu.png").stat().st_size > 0


def test_a_file_that_is_not_an_accuracy_json_is_refused(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text(json.dumps({"area": "deform-accuracy", "rows": []}))
    with pytest.raises(SystemExit):
        rep.load(str(bad))
