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


# ---- the elastic study's section -----------------------------------------------------------------

def _erow(model, mode, setting, ms, fem_u, fine_u, hertz, profile, backend="cpu"):
    return {"backend": backend, "model": model, "mode": mode, "setting": setting, "reps": 3,
            "step": {"median_ms": ms, "p10_ms": ms, "p90_ms": ms}, "relax": {"median_ms": ms, "p10_ms": ms, "p90_ms": ms},
            "cg_steps": 5 if model == "elastic" else None, "force_n": 0.4 if model == "elastic" else None,
            "errors": {"fem_u_pct": fem_u, "fem_force_pct": 0.5 if model == "elastic" else None, "fine_u_pct": fine_u,
                       "fine_force_pct": -2.0 if model == "elastic" else None, "hertz_force_pct": hertz,
                       "profile_pct": profile}}


def _elastic_doc(rows, refs=True):
    case = {"voi": {"lo": [0, 0, 0], "size": [64, 59, 64]}, "compared_nodes": 1000,
            "elastic": {"iterations": 20, "rounds": 2, "settled": True, "contact_nodes": 76, "force_n": [0, 0.47, 0],
                        "seconds": 4.6},
            "fem": {"stats": {"rounds": 3, "iterations": [20, 5, 3], "contact_nodes": 76, "total_s": 300,
                              "element_max_rel_diff": 3e-8}},
            "verification": {"u_pct": 0.2, "force_pct": 0.1, "max_diff_mm": 0.01},
            "fine": {"size": [127, 117, 127], "iterations": 40, "rounds": 3, "contact_nodes": 300,
                     "force_n": [0, 0.48, 0], "seconds": 60},
            "discretisation": {"u_pct": 3.0, "force_pct": -2.0}}
    hertz = {"block_n": 96, "nu": 0.45, "radius_mm": 8, "depth_mm": 1.6, "e_kpa": 12, "hertz_n": 0.1, "elastic_n": 0.104,
             "ratio": 1.04, "iterations": 22, "rounds": 3, "contact_nodes": 37, "seconds": 8, "profile_pct": 4.0,
             "fem": {"ratio": 0.993, "profile_pct": 1.3, "profile": {"r_mm": [0, 1, 2, 4, 8], "w_mm": [1.6, 1.5, 1.35, 0.8, 0.3]}},
             "fem_voxel": {"ratio": 0.99}, "fem_full": {"ratio": 1.03}}
    references = {"press": case, "block": case, "block_hertz_pct": {"elastic": -8.0, "fine": -9.0},
                  "block_fem_hertz": {"radius_mm": 5, "depth_mm": 1, "ratio": 0.99, "profile_pct": 1.5},
                  "hertz": [hertz],
                  "profile": {"block_n": 96, "nu": 0.45, "radius_mm": 8, "depth_mm": 1.6, "a_mm": 3.58,
                              "within_radii": 3, "elastic_pct": 4.0,
                              "elastic": {"r_mm": [0, 1, 2, 3, 4], "w_mm": [1.6, 1.5, 1.3, 1.0, 0.8]}},
                  "voi": [{"edge": 64, "force_n": 0.47, "force_pct": 12.0, "u_pct": 20.0, "converged_iterations": 20,
                           "converged_s": 4, "step_ms": 2600, "step_iterations": 6},
                          {"edge": 128, "force_n": 0.42, "force_pct": 0.0, "u_pct": 0.0, "converged_iterations": 25,
                           "converged_s": 40, "step_ms": 20000, "step_iterations": 7}]} if refs else None
    return {"area": "accuracy-elastic", "date": "2026-12-05T00:00:00Z", "device": "cpu only", "host_cpu": "test cpu",
            "host_threads": 2, "commit": "abc1234", "quick": False, "scene": "config/scenes/lumbar_phantom.textproto",
            "voxel_mm": 1, "voi_edge": 64, "finger_radius_mm": 5, "poisson": 0.45,
            "elastic_defaults": {"tolerance": 1e-3, "max_iterations": 60, "contact_rounds": 4},
            "press": {"landmark": "spinous_tip_L3", "X_mm": [0, 109.5, -4.5], "x_mm": [0, 99.5, -4.5], "press_mm": 10},
            "block": {"size": [96, 72, 96], "skin_j": 68, "hu": 40, "e_kpa": 12, "radius_mm": 5, "depth_mm": 1,
                      "hertz_n": 0.05, "profile_within_radii": 3},
            "references": references, "rows": rows}


ELASTIC_ROWS = [
    _erow("explicit (paper)", "every step", "20 iterations", 15.0, 400.0, 380.0, None, 300.0),
    _erow("multigrid (shipped)", "from zero", "4 steps", 50.0, 80.0, 75.0, None, 60.0),
    _erow("elastic", "from rest", "tol 0.1, cap 60", 900.0, 8.0, 9.0, -12.0, 6.0),
    _erow("elastic", "from rest", "tol 0.001, cap 60", 2600.0, 0.3, 3.0, -8.0, 4.0),
    _erow("elastic", "tip moving", "tol 0.001, cap 60", 700.0, 0.8, 3.2, -8.0, 4.0),
]


def test_elastic_rows_merge_gpu_times_by_model_mode_and_setting():
    gpu = _elastic_doc([_erow("elastic", "from rest", "tol 0.001, cap 60", 1.5, 0, 0, 0, 0, backend="cuda"),
                        _erow("elastic", "from rest", "tol 0.001, cap 60", 2000, 0, 0, 0, 0)], refs=False)
    rows = rep.merged_elastic_rows(_elastic_doc(ELASTIC_ROWS), gpu)
    assert [r["gpu_ms"] for r in rows] == [None, None, None, 1.5, None]
    assert [r["cpu_ms"] for r in rows] == [15.0, 50.0, 900.0, 2600.0, 700.0]


def test_bands_are_the_smallest_the_fem_meets():
    assert rep.band_for(1.3) == 2.0 and rep.band_for(0.4) == 1.0 and rep.band_for(5.0) == 5.0
    assert rep.band_for(None) is None and rep.band_for(float("nan")) is None


def test_the_elastic_section_names_goals_fronts_and_the_missing_gpu_figures(tmp_path):
    cpu, el = tmp_path / "cpu.json", tmp_path / "el.json"
    cpu.write_text(json.dumps(_doc(CPU_ROWS)))
    el.write_text(json.dumps(_elastic_doc(ELASTIC_ROWS)))
    (tmp_path / "elastic-contact-sheet-L3.png").write_bytes(b"png")
    sys.argv = ["accuracy_report.py", "--cpu", str(cpu), "--elastic", str(el), "--out-dir", str(tmp_path)]
    rep.main()
    md = (tmp_path / "accuracy.md").read_text()
    # both sections, the elastic study first
    assert md.index("## The shipped configuration against elasticity") < md.index("## The ChainMail knobs")
    # (i): 0.2 % meets the 1 % goal; (ii): 3 % and -2 % meet 5 %; (iii): 1.04 meets 5 %
    assert "| phantom press | 64 x 59 x 64 | 1000 | 3 ([20, 5, 3]) | 76 / 76 | 0.2 | 0.1 | 0.01 | 300 | yes |" in md
    assert "| phantom press | 64 x 59 x 64 | 127 x 117 x 127 | 3 | -2 | 76 / 300 | yes, yes |" in md
    assert "| 96^3 | 0.45 | 1.6 (1/5) | 0.1 | 0.104 | 1.040 | 22 (3) | 8 | 0.993 | 0.990 | 1.030 | yes |" in md
    # (iv): the FEM's 1.3 % gives the 2 % band, which the model's 4 % misses
    assert "| 96^3 | 0.45 | 1.6 | 3.58 | 1.3 (2) | - | 4 | no |" in md
    # every row, no GPU time yet, and the line that says how to take it
    assert "| elastic | tip moving | tol 0.001, cap 60 | 700.000 | not measured | 5 | 0.8 |" in md
    assert "--elastic --json-only accuracy-elastic-GPU.json --backend cuda" in md
    # fastest within 1 % of the FEM for a new press: the converged elastic row (the paper's and the
    # multigrid's are faster but wrong); its front runs from the paper's 20 iterations to it
    assert ("| (i) FEM of the same problem: displacement | a new press | elastic, from rest, tol 0.001, cap 60 "
            "(2600, 0.3) |") in md
    assert ("explicit (paper), every step, 20 iterations (15, 400); multigrid (shipped), from zero, 4 steps (50, 80); "
            "elastic, from rest, tol 0.1, cap 60 (900, 8); elastic, from rest, tol 0.001, cap 60 (2600, 0.3) |") in md
    # while the tip moves: within 1 % the tip-moving row (700 ms, 0.8 %)
    assert "| the tip moving a voxel a step | elastic, tip moving, tol 0.001, cap 60 (700, 0.8) |" in md
    # Hertz's force error counts by its size: -8 % is within 10, not 5
    assert ("| (iii) Hertz's force on the block (size of the error) | a new press | none | none | "
            "elastic, from rest, tol 0.001, cap 60 (2600, 8) |") in md
    assert "GPU: not measured" in md
    # the VOI's held faces, the plots and the contact sheet beside the JSON
    assert "| 64 | 0.47 | 12 | 20 | 20 | 2600 (6) |" in md
    assert "![contact sheet](elastic-contact-sheet-L3.png)" in md
    assert (tmp_path / "accuracy-elastic-cpu.png").stat().st_size > 0
    assert (tmp_path / "accuracy-elastic-profile.png").stat().st_size > 0
    # the command that regenerates the report names the files given
    assert f"--elastic-json {el}" in md


def test_a_file_that_is_not_the_elastic_json_is_refused(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text(json.dumps(_doc(CPU_ROWS)))
    with pytest.raises(SystemExit):
        rep.load_elastic(str(bad))


def _forces_doc():
    def row(where, d, proxy, elastic, f0, hertz):
        return {"where": where, "depth_mm": d, "contact": True, "haptic_depth_mm": d + 0.5, "proxy_n": [0, proxy, 0],
                "elastic_n": [0, elastic, 0], "elastic_f0_n": [0, f0, 0], "stiffness_n_per_mm": 0.07,
                "contact_nodes": 21, "cg_steps": 9, "converged": True, "step_ms": 1203.1, "hertz_n": hertz}
    return {"area": "accuracy-forces", "date": "2026-12-05T03:52:58Z", "device": "cpu only, backend cpu",
            "host_cpu": "AMD EPYC", "host_threads": 2, "commit": "abc1234", "quick": False,
            "scene": "config/scenes/lumbar_phantom.textproto", "finger_radius_mm": 5, "poisson": 0.45,
            "block": {"size": [96, 72, 96], "hu": 40},
            "haptics": {"stiffness_n_per_mm": 0.25, "max_force_n": 3.3, "elastic_max_jump_n": 0.05},
            "landmark": "spinous_tip_L3",
            # the block beside Hertz; the phantom without a reference, its elastic force clamped
            "rows": [row("block", 1, 0.008, 0.0472, 0.0472, 0.04486),
                     row("phantom above L3", 10, 1.12, 3.3, 4.1, float("nan"))]}


def test_the_force_section_compares_both_models_with_hertz(tmp_path):
    cpu, fm = tmp_path / "cpu.json", tmp_path / "forces.json"
    cpu.write_text(json.dumps(_doc(CPU_ROWS)))
    fm.write_text(json.dumps(_forces_doc()))
    sys.argv = ["accuracy_report.py", "--cpu", str(cpu), "--forces", str(fm), "--out-dir", str(tmp_path)]
    rep.main()
    md = (tmp_path / "accuracy.md").read_text()
    assert md.index("## The force each model reports") < md.index("## The ChainMail knobs")
    # ratios to Hertz: 0.008 / 0.04486 = 0.178, 0.0472 / 0.04486 = 1.05 (3 digits)
    assert "| block | 1 | 0.008 | 0.0472 | 0.0472 | 0.0449 | 0.178 | 1.05 | 0.07 | 21 | 9 | 1203 |" in md
    # no reference on the phantom: dashes, and the clamped force beside the unclamped one
    assert "| phantom above L3 | 10 | 1.12 | 3.3 | 4.1 | - | - | - | 0.07 | 21 | 9 | 1203 |" in md
    assert f"--forces-json {fm}" in md


def test_a_file_that_is_not_the_forces_json_is_refused(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text(json.dumps(_elastic_doc(ELASTIC_ROWS)))
    with pytest.raises(SystemExit):
        rep.load_forces(str(bad))


def _bench():
    d = os.environ.get("PALPSIM_BUILD_DIR")
    root = os.path.join(os.path.dirname(__file__), "..", "..", "..")
    p = os.path.join(d, "palpsim-bench") if d else os.path.join(root, "build", "palpsim-bench")
    if not (os.path.isfile(p) and os.access(p, os.X_OK)):
        pytest.skip(f"SKIPPED: no palpsim-bench in $PALPSIM_BUILD_DIR={d}")
    return p


def test_the_committed_report_is_regenerated_by_palpsim_bench_from_the_committed_json(tmp_path):
    # bench/results/accuracy.md names the command that made it; that command (palpsim-bench
    # accuracy --from-json, with the recorded JSON in bench/results) writes the same text again
    import re
    import subprocess
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
    committed = open(os.path.join(root, "bench", "results", "accuracy.md")).read()
    m = re.search(r"with `build/palpsim-bench (accuracy --from-json [^`]+)`", committed)
    assert m, "accuracy.md does not say how to regenerate it"
    args = m.group(1).split()
    subprocess.run([_bench()] + args + ["--out-dir", str(tmp_path)], cwd=root, check=True, capture_output=True)
    assert (tmp_path / "accuracy.md").read_text() == committed


def test_the_half_space_table_judges_force_and_profile_against_their_bands():
    # one row that meets both (3 % soft, profile 3 % where the converged FEM's 2.3 % gives the
    # 5 % band) and one that misses the force (8 % soft) and the converged FEM's 1 % band but
    # meets the 1 mm FEM's 10 % band (its 7.9 %)
    hs = {"date": "2026-12-05T00:00:00Z", "host_cpu": "test cpu", "host_threads": 2, "commit": "abc1234",
          "radius_mm": 8, "hu": 40, "force_settled": 1e-4,
          "rows": [{"block_n": 64, "nu": 0.45, "depth_mm": 1.6, "hertz_n": 0.1148, "held_ratio": 1.085,
                    "halfspace_ratio": 0.97, "held_profile_pct": 17.0, "halfspace_profile_pct": 3.0,
                    "face_updates": 5, "settled": True, "iterations": 71, "seconds": 20.0},
                   {"block_n": 64, "nu": 0.45, "depth_mm": 0.4, "hertz_n": 0.01436, "held_ratio": 0.97,
                    "halfspace_ratio": 0.92, "held_profile_pct": 14.0, "halfspace_profile_pct": 8.3,
                    "face_updates": 4, "settled": False, "iterations": 59, "seconds": 20.0}]}
    el = {"references": {"hertz": [
        {"nu": 0.45, "depth_mm": 1.6, "fem": {"ratio": 0.984, "profile_pct": 2.34},
         "fem_voxel": {"ratio": 0.985, "profile_pct": 3.45}},
        {"nu": 0.45, "depth_mm": 0.4, "fem": {"ratio": 0.997, "profile_pct": 0.81},
         "fem_voxel": {"ratio": 0.96, "profile_pct": 7.9}}]}}
    rows = [l for l in rep.halfspace_markdown(hs, el, rep._fmt, rep._met, rep.band_for) if l.startswith("| 64^3")]
    assert len(rows) == 2
    cells = [[c.strip() for c in r.strip("|").split("|")] for r in rows]
    # columns: ..., goal 5 % (7), ..., converged band (11), within it (12), within the 1 mm FEM's (13), updates (14)
    assert cells[0][7] == "yes" and cells[0][11] == "2.34 (5)" and cells[0][12] == "yes" and cells[0][13] == "yes"
    assert cells[1][7] == "no" and cells[1][11] == "0.81 (1)" and cells[1][12] == "no" and cells[1][13] == "yes"
    assert cells[1][14] == "4 (not settled)"
