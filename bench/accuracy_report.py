#!/usr/bin/env python3
"""The report of `palpsim-bench accuracy`: bench/results/accuracy.md and its plots.

Reads the CPU machine's JSON of the ChainMail knobs' study (`--cpu`, written by `palpsim-bench
accuracy`) and, when given, a GPU machine's (`--gpu`, written there by `palpsim-bench accuracy
--json-only`), the elastic study's (`--elastic`, `palpsim-bench accuracy --elastic`) and a GPU
machine's run of it (`--elastic-gpu`, with `--json-only`). `palpsim-bench accuracy --from-json`
runs this script on recorded JSON, so that the report is regenerated from bench/results.

The elastic study's section: the shipped configuration's press and a block against references a
correct elasticity solver can meet ((i) the FEM of the same problem, (ii) the same problem at
h/2, (iii) Hertz's force, (iv) Hertz's surface profile), every row (model, mode, setting) with
its step time on the CPU and the GPU, the fastest row within 1, 5 and 10 % of each reference and
the Pareto front across models, and the VOI's held faces against larger VOIs.

The ChainMail knobs' section: every deformation row gets its step time on this CPU and on the
GPU (the "cuda" row of the same knob and setting; "not measured" without one) and its errors
against references (a)-(c), computed on the CPU run (the backends agree to 1e-6 voxel, see
tests/gpu/deform_gpu_test.cpp); the force rows get reference (d). Error metric: the relative RMS
error in percent, RMS |v - v_ref| / RMS |v_ref| over the compared voxels (or tips); "within 5 %"
means that error is at most 5. For (a) a row's error is the larger of its displacement and its J
error (J's relative to the image change RMS |J_ref - I|). A row is on the Pareto front of a
reference when no other row is both faster and at most as wrong (ties in both: the first listed).

usage: accuracy_report.py --cpu accuracy-cpu.json [--gpu accuracy-h100.json] [--elastic E.json]
                          [--elastic-gpu EG.json] [--out-dir bench/results]
"""
import argparse
import glob
import json
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from accuracy_halfspace import halfspace_markdown  # noqa: E402 (beside this script)

# error thresholds (%) of the "fastest within" table
THRESHOLDS = (1.0, 5.0, 10.0)

# the deformation references: key, title, the row's error (%) for it
REFERENCES = [
    ("a", "(a) own converged solution",
     lambda e: max(e["a_u_pct"], e["a_J_pct"]) if _finite(e.get("a_u_pct")) and _finite(e.get("a_J_pct")) else None),
    ("b", "(b) Boussinesq half-space (shape)", lambda e: e.get("b_shape_pct")),
    ("c", "(c) linear-elastic FEM", lambda e: e.get("c_u_pct")),
]


def _finite(v):
    return isinstance(v, (int, float)) and math.isfinite(v)


def load_json(path, area, producer):
    """The JSON of one bench run of `area`; exits naming the file when it cannot be read or is not
    one (`producer` names the command that writes it)."""
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError) as e:
        sys.exit(f"{os.path.basename(sys.argv[0])}: cannot read {path}: {e}")
    if d.get("area") != area or "rows" not in d:
        sys.exit(f"{os.path.basename(sys.argv[0])}: {path} is not the JSON of `{producer}`")
    return d


def load(path):
    """The JSON of one `palpsim-bench accuracy` run."""
    return load_json(path, "accuracy", "palpsim-bench accuracy")


def merged_rows(cpu, gpu=None):
    """The CPU run's cpu-backend rows, each with `cpu_ms` and `gpu_ms` (None: not measured)."""
    gpu_ms = {}
    if gpu:
        for r in gpu["rows"]:
            if r["backend"] == "cuda":
                gpu_ms[(r["knob"], r["setting"])] = r["step"]["median_ms"]
    rows = []
    for r in cpu["rows"]:
        if r["backend"] != "cpu":
            continue
        rows.append(dict(r, cpu_ms=r["step"]["median_ms"], gpu_ms=gpu_ms.get((r["knob"], r["setting"]))))
    return rows


def pareto(points):
    """Indices of the Pareto front of (time, error) pairs (None entries skipped): no other
    point is faster and at most as wrong, or as fast and less wrong. Sorted by time."""
    idx = [i for i, (t, e) in enumerate(points) if _finite(t) and _finite(e)]
    idx.sort(key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in idx:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


# times within this factor of the fastest count as equal (the p10-p90 spread of a shared
# machine's timings is a few percent); among equals the first listed, the cheapest setting
TIME_TIE = 1.03


def fastest_within(rows, error_of, threshold, time_key):
    """The fastest row whose error (%) is at most `threshold`, or None; rows within TIME_TIE of
    the fastest count as equally fast, and the first of them in `rows` is taken."""
    ok = [r for r in rows if _finite(error_of(r)) and error_of(r) <= threshold and _finite(r.get(time_key))]
    if not ok:
        return None
    t_min = min(r[time_key] for r in ok)
    return next(r for r in ok if r[time_key] <= TIME_TIE * t_min)


def selection_groups(key, rows, error_of):
    """The row sets that one "fastest within" selection runs over: for reference (a) each knob
    that has one (its own converged value), labelled ": knob"; for the others all rows."""
    if key != "a":
        return [("", rows)]
    knobs = dict.fromkeys(r["knob"] for r in rows if _finite(error_of(r)))
    return [(f": {k}", [r for r in rows if r["knob"] == k]) for k in knobs]


def _fmt(v, digits=3):
    if not _finite(v):
        return "-"
    if v == 0:
        return "0"
    if abs(v) >= 100:
        return f"{v:.0f}"
    return f"{v:.{digits}g}"


def _ms(v):
    return "not measured" if v is None else f"{v:.3f}"


def _name(r):
    return f"{r['knob']} {r['setting']}"


def fastest_lines(title, rows, error_of, gpu, name, front_txt):
    """One reference's lines of a "fastest within" table: per threshold the fastest of `rows` on the
    CPU and on the GPU (named by name(row), with its time and error), the Pareto front on the first."""
    L = []
    for n, th in enumerate(THRESHOLDS):
        cells = []
        for tk in ("cpu_ms", "gpu_ms"):
            best = fastest_within(rows, error_of, th, tk)
            if tk == "gpu_ms" and not gpu:
                cells.append("not measured")
            else:
                cells.append(f"{name(best)} ({best[tk]:.3f}, {_fmt(error_of(best))})" if best else "none")
        L.append(f"| {title if n == 0 else ''} | {th:g} % | {cells[0]} | {cells[1]} | {front_txt if n == 0 else ''} |")
    return L


def image_lines(images):
    """Markdown lines showing each (title, path) image by its file name (the report lies beside them)."""
    L = []
    for title, path in images:
        L.append(f"![{title}]({os.path.basename(path)})")
        L.append("")
    return L


def chainmail_markdown(cpu, gpu, rows, plots):
    """The report's section on the ChainMail knobs against references (a)-(d), as lines."""
    gpu_name = gpu["device"] if gpu else "none given"
    b, rb, rc = cpu["base"], cpu["reference_b"], cpu["reference_c"]
    a = cpu["reference_a"]
    p = cpu["press"]
    L = []
    L.append("## The ChainMail knobs against their own references (a)-(d)")
    L.append("")
    L.append(f"- CPU run: {cpu['host_cpu']} ({cpu['host_threads']} threads), commit {cpu['commit']}, {cpu['date']}"
             f"{' (quick)' if cpu.get('quick') else ''}")
    L.append(f"- GPU run: {gpu_name}" + (f", commit {gpu['commit']}, {gpu['date']}" if gpu else
                                          " (run `palpsim-bench accuracy --json-only H100.json` there, then "
                                          "`palpsim-bench accuracy --gpu-json H100.json` here)"))
    L.append(f"- Press: {p['press_mm']:g} mm anterior, X 1 mm under the back skin, {p['bone_depth_mm']:.1f} mm above "
             f"{p['landmark']}; phantom at {cpu['phantom']['voxel_mm']:.3f} mm voxels.")
    L.append(f"- Base: preset {b['preset']}, VOI {b['voi_edge']}, relaxation {b['relax_method']} "
             f"{b['relax_iterations']}, inversion {b['invert_iterations']}; each row changes one knob.")
    L.append(f"- Storage precision: {cpu.get('storage', 'fp32')} only: no backend stores fields in fp16, so there is "
             "no fp16 row. Relaxation methods: the paper's explicit diffusion (iterations) and the multigrid "
             "steady-state solver (deform.relax_method \"multigrid\", steps), timed solving afresh from zero every "
             "step (a new VOI or grabbed element: the tip entered another voxel, with deform.relax_warm_cycles 0), "
             "as \"multigrid warm\" (steps: deform.relax_warm_cycles) with the tip reaching the press a voxel a "
             "step, each step starting from the last step's unit response, and as \"multigrid reused\" with the "
             "same press repeated, which reuses the unit response (u = d G, the same bits; "
             "server/deform/README.md), and as \"multigrid primed\": the press as a new session's first step, "
             "after the prime the server's worker runs while the tip hovers 5 mm above the skin (a new engine "
             "each repetition; steps: deform.relax_warm_cycles; the prime's own solve, as much GPU as the 4-step "
             "row, runs before the contact and is not in the step time); another is one entry in kRelaxMethods (bench/deform_accuracy_bench.cpp).")
    L.append("")
    L.append("### References and error metrics")
    L.append("")
    L.append("Error = relative RMS error in percent, RMS |v - v_ref| / RMS |v_ref| over the compared voxels; "
             "\"within 5 %\" means at most 5. Fastest: the least median step time, where times within "
             f"{(TIME_TIE - 1) * 100:.0f} % of it count as equal (timing noise) and the first listed, the cheapest "
             "setting, is named.")
    L.append("")
    L.append(f"- **(a) the model's own converged solution**, per knob as `palpsim-bench deform --accuracy` does: "
             f"the base with that knob at its converged value (relaxation: the steady state both methods head for, "
             f"{a['relax_steady_state_multigrid_steps']} multigrid steps; inversion "
             f"{a['invert_iterations']}, VOI {a['voi_edge']}), same press. Displacement u compared on the "
             "reference's VOI (u = 0 outside a row's VOI), J there too (J = I outside a row's VOI), J's error "
             "relative to the image change RMS |J_ref - I|. The row's (a) error is the larger of the two. None for "
             "the ChainMail preset: another preset is another model, not an approximation of this one.")
    L.append(f"- **(b) physics on a homogeneous block**: {rb['block_voxels']}^3 voxels of soft tissue (1 mm), its "
             f"+y face pressed at the centre by {rb['press_vox']:g} voxels, with each row's settings. Boussinesq's point load on an elastic "
             f"half-space, nu = {rb['nu']:g} (E does not matter: the shape of the normalised field depends on nu "
             f"only), load at the grabbed voxel's centre; compared on voxels {rb['r_min_vox']:g} to "
             f"{rb['r_max_vox']:g} voxels from it after the least-squares scale (shape error; the model's "
             "tangential part counts as error). Isotropy: |u| on the face at distance r = 4, 6, 8 voxels along the "
             "diagonal against along the axis; the largest |ratio - 1| in % (Boussinesq: 0), the ratio at r = 6 "
             "in brackets.")
    solve = rc.get("solve") or {}
    solve_txt = (f"; {solve.get('nodes')} nodes, {solve.get('elements')} hexahedra, {solve.get('iterations')} CG "
                 f"iterations, relative residual {solve.get('relative_residual', float('nan')):.0e}, "
                 f"{solve.get('total_s', float('nan')):.0f} s") if solve else ""
    L.append(f"- **(c) linear-elastic FEM** (scikit-fem trilinear hexahedra, pyamg-preconditioned CG; "
             f"bench/accuracy_fem.py) of the same press on the base VOI ({' x '.join(map(str, rc['voi']))} "
             f"voxels){solve_txt}. One node per voxel centre, so the fields compare voxel by voxel; elements "
             "where none of the 8 voxels is air (below -500 HU), so the skin is traction-free. Homogeneous "
             f"isotropic tissue, E = {rc['E_kpa']:g} kPa (scales only the reaction force of a displacement-driven "
             f"press), nu = {rc['nu']:g}. Boundary conditions: bone voxels held (rigid, as in the model), the "
             "grabbed voxel prescribed at the tip's displacement, the VOI's faces held (the model's own u = 0 "
             "outside the VOI). Compared on soft voxels off the faces, 3 voxels or more from the grabbed one; "
             "corr = Pearson correlation of the components. A single prescribed voxel is a point constraint: "
             "in both models its far field's amplitude depends on the discretisation, so the relative error "
             "mixes amplitude and shape, and corr measures the shape alone.")
    L.append("- **(d) force**: the force model as it runs (trilinear samples of the float F and grad F) and "
             "with nearest-voxel sampling, against eq. 1-2 in double on the phantom's closed-form skin and bone "
             "(A = distance to bone, B = depth + h/2 as prep defines it), grad F by central differences of h/8; "
             "spring force f = -k F grad F / |grad F| of a fresh proxy without friction or clamps (the 3.3 N clamp "
             "would hide errors). Patient: the default scene's 1 mm phantom through prep. Tips: a lattice of 7.3 mm "
             "over back and sides (not on voxel centres), 1 mm outside to 40 mm under the skin; classes by the "
             "closed form (near skin: under 3 mm deep; near bone: outside it, within 3 mm).")
    L.append("")
    L.append("### Every row")
    L.append("")
    L.append(f"| knob | setting | CPU step ms | H100 step ms | (a) u % | (a) J % | (b) shape % | (b) isotropy % "
             "(ratio r=6) | (c) u % | (c) corr |")
    L.append("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        e = r["errors"]
        L.append(f"| {r['knob']} | {r['setting']} | {_ms(r['cpu_ms'])} | {_ms(r['gpu_ms'])} | {_fmt(e['a_u_pct'])} | "
                 f"{_fmt(e['a_J_pct'])} | {_fmt(e['b_shape_pct'])} | {_fmt(e['b_isotropy_pct'])} "
                 f"({_fmt(e['b_ratio6'])}) | {_fmt(e['c_u_pct'])} | {_fmt(e['c_corr'])} |")
    L.append("")
    L.append("### Fastest setting within 1 %, 5 % and 10 % of each reference")
    L.append("")
    L.append("| reference | within | fastest on CPU (ms, error %) | fastest on H100 (ms, error %) | Pareto front (CPU) |")
    L.append("|---|---|---|---|---|")
    for key, title, err in REFERENCES:
        def error_of(r, err=err):
            return err(r["errors"])
        # (a) differs per knob (each knob's own converged value): one selection per knob
        for label, sel in selection_groups(key, rows, error_of):
            front = pareto([(r["cpu_ms"], error_of(r)) for r in sel])
            front_txt = ", ".join(_name(sel[i]) for i in front) or "-"
            L += fastest_lines(title + label, sel, error_of, gpu, _name, front_txt)
    L.append("")
    L.append("### Force model against reference (d)")
    L.append("")
    L.append("Time per pose on each machine's CPU (the force model runs on the host): the sampling of F and grad F "
             "and the spring, without the skin-point search that both samplings need. Errors: the model as it "
             "runs (trilinear) and its nearest-voxel variant. Contact disagrees: tips where "
             "the model and the closed form differ on inside/outside (left out of the errors).")
    L.append("")
    gpu_force = {(f["sampling"], f["where"]): f["ns_per_pose"] for f in (gpu or {}).get("force", [])}
    L.append("| sampling | tips | n | RMS error N | max error N | error % | RMS |f_ref| N | contact disagrees | "
             "CPU ns/pose | H100 host ns/pose |")
    L.append("|---|---|---|---|---|---|---|---|---|---|")
    for f in cpu.get("force", []):
        g = gpu_force.get((f["sampling"], f["where"]))
        L.append(f"| {f['sampling']} | {f['where']} | {f['n']} | {_fmt(f['rms_n'])} | {_fmt(f['max_n'])} | "
                 f"{_fmt(f['rel_rms_pct'])} | {_fmt(f['ref_rms_n'])} | {f['contact_disagree']} | "
                 f"{f['ns_per_pose']:.0f} | {'not measured' if g is None else f'{g:.0f}'} |")
    all_tips = [f for f in cpu.get("force", []) if f["where"] == "all in soft tissue"]
    for th in THRESHOLDS:
        best = fastest_within(all_tips, lambda f: f["rel_rms_pct"], th, "ns_per_pose")
        L.append("")
        L.append(f"Fastest force sampling within {th:g} % of (d) (all tips in soft tissue): "
                 f"{best['sampling'] + ' (' + _fmt(best['rel_rms_pct']) + ' %)' if best else 'none'}.")
    L.append("")
    L.append("### Plots")
    L.append("")
    L += image_lines(plots)
    return L


# ---- the elastic study (palpsim-bench accuracy --elastic) --------------------------------------

def load_elastic(path):
    """The JSON of one `palpsim-bench accuracy --elastic` run."""
    return load_json(path, "accuracy-elastic", "palpsim-bench accuracy --elastic")


def _abs(v):
    return abs(v) if _finite(v) else None


# the elastic study's references: key, title, the row's error (%) for it
ELASTIC_REFERENCES = [
    ("fem", "(i) FEM of the same problem: displacement", lambda e: e.get("fem_u_pct")),
    ("fine", "(ii) the same problem at h/2: displacement", lambda e: e.get("fine_u_pct")),
    ("hertz", "(iii) Hertz's force on the block (size of the error)", lambda e: _abs(e.get("hertz_force_pct"))),
    ("profile", "(iv) Hertz's surface profile on the block", lambda e: e.get("profile_pct")),
]

# the situations a session meets and the row modes that serve each (the explicit relaxation's
# "every step" keeps nothing from step to step, so it serves all three)
SITUATIONS = [("a new press", ("from rest", "from zero", "every step")),
              ("the tip moving a voxel a step", ("tip moving", "every step")),
              ("the press held", ("press repeated", "every step"))]

# bands a reference's own FEM is held to: the smallest of these at or above its error (%)
BANDS = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0)


def band_for(err):
    """The smallest band (%) at or above `err`, or None."""
    return next((b for b in BANDS if _finite(err) and err <= b), None)


def _time(ms):
    """A step time (ms) in a few digits, without an exponent."""
    return f"{ms:.0f}" if ms >= 100 else f"{ms:.3g}"


def _row_name(r):
    return f"{r['model']}, {r['mode']}, {r['setting']}"


def merged_elastic_rows(el, gpu=None):
    """The elastic study's cpu rows, each with `cpu_ms` and `gpu_ms` (the GPU run's cuda row of the
    same model, mode and setting; None: not measured)."""
    gpu_ms = {}
    for r in (gpu or {}).get("rows", []):
        if r["backend"] == "cuda":
            gpu_ms[(r["model"], r["mode"], r["setting"])] = r["step"]["median_ms"]
    return [dict(r, cpu_ms=r["step"]["median_ms"], gpu_ms=gpu_ms.get((r["model"], r["mode"], r["setting"])))
            for r in el["rows"] if r["backend"] == "cpu"]


def _met(v, goal):
    return "-" if not _finite(v) else ("yes" if abs(v) <= goal else "no")


def _vec_norm(v):
    return math.sqrt(sum(x * x for x in v)) if v else float("nan")


def elastic_markdown(el, gpu, rows, plots, sheets):
    """The report's section on the elastic model and the shipped configuration, as lines."""
    refs = el.get("references") or {}
    p, b = el["press"], el["block"]
    d = el["elastic_defaults"]
    L = ["## The shipped configuration against elasticity", ""]
    L.append(f"- CPU run: {el['host_cpu']} ({el['host_threads']} threads, shared with other work: times vary by "
             f"up to 2x between runs), commit {el['commit']}, {el['date']}{' (quick)' if el.get('quick') else ''}.")
    if gpu:
        L.append(f"- GPU run: {gpu['device']}, commit {gpu['commit']}, {gpu['date']}.")
    else:
        L.append("- GPU run: none yet: the GPU column stays empty until the elastic model runs on \"cuda\" (every row "
                 "goes through make_deform_backend, so the same command fills it). Still to take, on the GPU: every "
                 "row's step time (the issue's goals at VOI 64: an elastic step while the tip moves at most 1 ms, "
                 "from rest at most 2 ms). There: `palpsim-bench accuracy --elastic --json-only "
                 "accuracy-elastic-GPU.json --backend cuda --commit C`; here: `palpsim-bench accuracy --from-json "
                 "... --elastic-gpu-json accuracy-elastic-GPU.json` (the command below with it).")
    L.append(f"- Scene: `{el['scene']}` as shipped: the phantom through prep at {el['voxel_mm']:g} mm, VOI "
             f"{el['voi_edge']}, the fingertip of {el['finger_radius_mm']:g} mm (deform.grab_radius_mm), inversion "
             f"with its cell search; the elastic model at its defaults (nu {el['poisson']:g}, tolerance "
             f"{d['tolerance']:g}, at most {d['max_iterations']} CG steps a round, {d['contact_rounds']} contact "
             "rounds) unless a row says otherwise.")
    L.append(f"- Press: X where the haptic path puts it, on the skin (the trilinear body mask at 1/2) straight above "
             f"{p['landmark']}, x {p['press_mm']:g} mm anterior (into the back, towards the bone). Every model gets "
             "this contact: ChainMail grabs the element nearest X (the multigrid diffusion moves the tissue within "
             "the fingertip's radius with it); the elastic model presses a sphere of the fingertip's radius whose "
             "deepest point is x.")
    L.append(f"- Block: {' x '.join(map(str, b['size']))} voxels of 1 mm of homogeneous tissue ({b['hu']:g} HU: "
             f"E {b['e_kpa']:g} kPa from the scene's table, no skin layer), the skin the node layer j = {b['skin_j']}, "
             f"pressed at its centre by the fingertip, d = {b['depth_mm']:g} mm (R/5) from that layer; the VOI as the "
             f"scene sets it (centred on the tip, so the tissue reaches about {el['voi_edge'] // 2} voxels under "
             f"the skin); Hertz's force {b['hertz_n']:.4g} N.")
    L.append("")
    L.append("### References")
    L.append("")
    L.append("Errors in percent: displacement as relative RMS, RMS |u - u_ref| / RMS |u_ref| over the body nodes that "
             "are not bone and not on the VOI's faces (u = 0 where a row's VOI does not reach); forces as "
             "(F - F_ref) / F_ref of |F|; only the elastic model has a force of its own (the ChainMail family's "
             "force is the haptic path's eq. 2, not a solve).")
    L.append("")
    L.append("- **(i) verification**: the FEM of the elastic model's own problem (bench/accuracy_fem.py `contact`: "
             "scikit-fem on the same voxels, the same element by selective reduced integration, the mu part at 2x2x2 "
             "Gauss points and the lambda part at the centre, intorder per form; the same cell moduli, held nodes, "
             "skin nodes and frictionless sphere contact, its own active-set rounds by the model's rules until no "
             "node changes; pyamg-preconditioned CG to a relative residual of 1e-9), against the elastic model "
             "converged (tolerance 1e-6, rounds until settled). Goal: within 1 % displacement RMS.")
    L.append("- **(ii) discretisation**: the same problem on the grid refined 2x (fine node 2i on coarse node i, "
             "the same VOI faces held; intensity and depth under the skin as the trilinear interpolant of the "
             "voxels; a fine node is body, or bone, where the interpolated mask is above 1/2, the rule the tip's "
             "inside test uses, so the tissue still ends at the coarse skin nodes; bench/elastic_refs.h "
             "refine_half), solved by the CPU elastic model converged: (i) shows that it is that FEM, and the FEM "
             "itself is too large for pyamg on this machine at h/2 (2 M nodes). Goal: the model at voxel "
             "resolution within 5 % of it on displacement and on force.")
    L.append("- **(iii) Hertz**: a sphere of radius R pressed d into a large homogeneous block, F = 4/3 E/(1-nu^2) "
             "sqrt(R) d^(3/2), against the elastic model on a whole block of 1 mm voxels (its faces held) and the "
             "FEM of the same element's axisymmetric form (accuracy_fem.py `hertz`: the solid of revolution with its "
             "hoop strain, the mu part at 2x2 Gauss points and the lambda part at the cell centre, the contact by "
             "the model's rules; cells of 0.1 mm at the contact doubling outwards to 1000 mm, where the faces are "
             "held: converged, 0.05 mm moves the force by 1e-4), and the same FEM with cells of the voxels' 1 mm, "
             "reduced and fully integrated: what locking does. (A 3D FEM of a block that large needs cells "
             "stretched 100:1 far out, on which pyamg's CG took 130 steps and minutes a solve here.) Goal: the "
             "elastic model within 5 % for d <= R/5.")
    L.append(f"- **(iv) profile**: Hertz's surface displacement into the block, d - r^2/2R inside the contact radius "
             f"a = sqrt(R d) and its decay outside (Johnson, Contact Mechanics, 3.42), compared as relative RMS over "
             f"the skin within {b['profile_within_radii']:g} a of the axis; the band is the smallest of "
             f"{', '.join(f'{x:g}' for x in BANDS)} % that the FEM of (iii), converged, meets.")
    L.append("- **(v)** every row (the paper's explicit relaxation, the shipped multigrid diffusion, the elastic "
             "model) against the same references, with its step time: the whole step (ChainMail where it runs, "
             "relaxation or the elastic solve, inversion), median of the timed repetitions.")
    L.append("")
    if not refs:
        L.append("No references in this run (a GPU machine's times only).")
        L.append("")
    fem_ok = bool(refs) and refs["press"].get("verification") is not None
    if refs:
        L.append("### (i) Verification: the elastic model is the FEM")
        L.append("")
        L.append("| case | VOI nodes | compared | FEM rounds (CG steps) | contact nodes FEM / model | u % | force % | "
                 "max abs(du) mm | FEM s | goal 1 % |")
        L.append("|---|---|---|---|---|---|---|---|---|---|")
        for name, title in (("press", "phantom press"), ("block", "block")):
            c = refs[name]
            v = c.get("verification")
            st = (c.get("fem") or {}).get("stats") or {}
            size = " x ".join(map(str, c["voi"]["size"]))
            if v:
                L.append(f"| {title} | {size} | {c['compared_nodes']} | {st.get('rounds')} ({st.get('iterations')}) | "
                         f"{st.get('contact_nodes')} / {c['elastic']['contact_nodes']} | {_fmt(v['u_pct'])} | "
                         f"{_fmt(v['force_pct'])} | {_fmt(v['max_diff_mm'])} | {_fmt(st.get('total_s'))} | "
                         f"{_met(v['u_pct'], 1.0)} |")
            else:
                L.append(f"| {title} | {size} | {c['compared_nodes']} | not computed | - | - | - | - | - | - |")
        el_diff = [((refs[n].get("fem") or {}).get("stats") or {}).get("element_max_rel_diff") for n in ("press", "block")]
        if fem_ok and _finite(el_diff[0]):
            L.append("")
            L.append(f"The model's cell matrix (elastic_element, float) and scikit-fem's differ by at most "
                     f"{_fmt(max(x for x in el_diff if _finite(x)))} of the largest entry.")
        L.append("")
        L.append("### (ii) Discretisation: voxel resolution against h/2")
        L.append("")
        L.append("| case | VOI nodes | refined grid | u % | force % | contact nodes h / h/2 | goal 5 % (u, force) |")
        L.append("|---|---|---|---|---|---|---|")
        for name, title in (("press", "phantom press"), ("block", "block")):
            c = refs[name]
            dz = c["discretisation"]
            L.append(f"| {title} | {' x '.join(map(str, c['voi']['size']))} | {' x '.join(map(str, c['fine']['size']))} | "
                     f"{_fmt(dz['u_pct'])} | {_fmt(dz['force_pct'])} | {c['elastic']['contact_nodes']} / "
                     f"{c['fine']['contact_nodes']} | {_met(dz['u_pct'], 5.0)}, {_met(dz['force_pct'], 5.0)} |")
        bh = refs.get("block_hertz_pct") or {}
        L.append("")
        L.append(f"On the shipped VOI the block's force is {_fmt(bh.get('elastic'))} % from Hertz's at voxel resolution and "
                 f"{_fmt(bh.get('fine'))} % at h/2: what is left at h/2 is the VOI's held faces (below).")
        L.append("")
        L.append("### (iii) Hertz: a sphere on a large block")
        L.append("")
        L.append("| block | nu | d mm (d/R) | Hertz N | elastic N | elastic / Hertz | CG steps (rounds) | s | "
                 "FEM / Hertz | FEM 1 mm / Hertz | FEM 1 mm fully integrated / Hertz | goal 5 % |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for h in refs.get("hertz", []):
            ratios = [f"{h[k]['ratio']:.3f}" if h.get(k) else "-" for k in ("fem", "fem_voxel", "fem_full")]
            L.append(f"| {h['block_n']}^3 | {h['nu']:g} | {h['depth_mm']:g} (1/{h['radius_mm'] / h['depth_mm']:.0f}) | "
                     f"{_fmt(h['hertz_n'], 4)} | {_fmt(h['elastic_n'], 4)} | {h['ratio']:.3f} | {h['iterations']} "
                     f"({h['rounds']}) | {_fmt(h['seconds'])} | {' | '.join(ratios)} | "
                     f"{_met(100 * (h['ratio'] - 1), 5.0)} |")
        L.append("")
        pr = refs.get("profile")
        if pr:
            L.append("### (iv) Hertz's surface profile")
            L.append("")
            L.append(f"Relative RMS error of the displacement into the block over the skin within {pr['within_radii']:g} "
                     "contact radii a of the axis; the band is the smallest the converged FEM meets.")
            L.append("")
            L.append("| block | nu | d mm | a mm | FEM % (band) | FEM 1 mm % | elastic % | elastic within the band |")
            L.append("|---|---|---|---|---|---|---|---|")
            for h in refs.get("hertz", []):
                fem_err = (h.get("fem") or {}).get("profile_pct")
                band = band_for(fem_err)
                L.append(f"| {h['block_n']}^3 | {h['nu']:g} | {h['depth_mm']:g} | {math.sqrt(h['radius_mm'] * h['depth_mm']):.2f} | "
                         f"{_fmt(fem_err)} ({'-' if band is None else f'{band:g}'}) | "
                         f"{_fmt((h.get('fem_voxel') or {}).get('profile_pct'))} | {_fmt(h.get('profile_pct'))} | "
                         f"{'-' if band is None else _met(h.get('profile_pct'), band)} |")
            gb = refs.get("block_fem_hertz")
            if gb:
                gband = band_for(gb.get("profile_pct"))
                fband = band_for(abs(100 * (gb["ratio"] - 1)))
                L.append("")
                L.append(f"The shipped block's press (R {gb['radius_mm']:g} mm, d {gb['depth_mm']:g} mm) by the same "
                         f"FEM, converged: its force {100 * (gb['ratio'] - 1):+.2f} % from Hertz's, its profile "
                         f"{_fmt(gb.get('profile_pct'))} %: the bands the rows' Hertz columns are held to are "
                         f"{fband:g} % (force) and {gband:g} % (profile).")
            L.append("")
        vo = refs.get("voi") or []
        if vo:
            big = vo[-1]["edge"]
            L.append("### The VOI: what holding its faces costs")
            L.append("")
            L.append(f"The elastic press converged on larger VOIs, against VOI {big} (displacement on VOI "
                     f"{vo[0]['edge']}'s compared nodes); the step time from rest at the default settings, one run.")
            L.append("")
            L.append(f"| VOI | force N | force vs VOI {big} % | u vs VOI {big} % | CG steps converged | "
                     "step from rest ms (CG steps) |")
            L.append("|---|---|---|---|---|---|")
            for v in vo:
                L.append(f"| {v['edge']} | {_fmt(v['force_n'], 4)} | {_fmt(v['force_pct'])} | {_fmt(v['u_pct'])} | "
                         f"{v['converged_iterations']} | {v['step_ms']:.0f} ({v['step_iterations']}) |")
            L.append("")
    L.append("### (v) Every row: models, modes and settings")
    L.append("")
    L.append("Modes: \"every step\" repeats the press, each step from ChainMail's start (the explicit relaxation keeps "
             "nothing); \"from zero\" solves the multigrid diffusion from zero each step (a new VOI, "
             "deform.relax_warm_cycles 0); \"tip moving\" reaches the press a voxel a step from 5 voxels short, as "
             "the server runs it: the VOI held while the tip stays within voi_edge / 8 voxels, each step starting "
             "from the last (the multigrid's unit response; the elastic field and contact set); \"press repeated\" "
             "repeats the press (the multigrid reuses its unit response; the elastic model starts from its own "
             "solution); \"from rest\" is "
             "a session's first press (a new engine each repetition: the elastic set-up is in the step). Elastic "
             "settings: the relative residual each contact round stops at (tol) and the CG steps a round may take "
             "(cap). On the block the same setting in the same mode presses the block (\"tip moving\": from half "
             "the depth).")
    L.append("")
    L.append("| model | mode | setting | CPU step ms | GPU step ms | CG steps | FEM u % | FEM force % | h/2 u % | "
             "h/2 force % | Hertz force % | profile % |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        e = r["errors"]
        L.append(f"| {r['model']} | {r['mode']} | {r['setting']} | {_ms(r['cpu_ms'])} | {_ms(r['gpu_ms'])} | "
                 f"{'-' if r.get('cg_steps') is None else r['cg_steps']} | {_fmt(e.get('fem_u_pct'))} | "
                 f"{_fmt(e.get('fem_force_pct'))} | {_fmt(e.get('fine_u_pct'))} | {_fmt(e.get('fine_force_pct'))} | "
                 f"{_fmt(e.get('hertz_force_pct'))} | {_fmt(e.get('profile_pct'))} |")
    L.append("")
    L.append("### Fastest within 1 %, 5 % and 10 %, and the Pareto fronts across models")
    L.append("")
    L.append("Per situation a session meets, over the rows that serve it (the explicit relaxation keeps nothing from "
             "step to step, so its rows serve every situation): the fastest row within each error (its median step "
             "ms and error %) and the Pareto front (no other row both faster and at most as wrong).")
    L.append("")
    for tk, machine in (("cpu_ms", "CPU"), ("gpu_ms", "GPU")):
        if tk == "gpu_ms" and not any(r["gpu_ms"] is not None for r in rows):
            L.append("GPU: not measured (see the run's GPU line above).")
            L.append("")
            continue
        L.append(f"| reference | situation | {machine}: fastest within 1 % | within 5 % | within 10 % | "
                 f"Pareto front ({machine}) |")
        L.append("|---|---|---|---|---|---|")
        for key, title, err in ELASTIC_REFERENCES:
            def error_of(r, err=err):
                return err(r["errors"])
            for n, (situation, modes) in enumerate(SITUATIONS):
                sel = [r for r in rows if r["mode"] in modes and r[tk] is not None]
                cells = []
                for th in THRESHOLDS:
                    best = fastest_within(sel, error_of, th, tk)
                    cells.append(f"{_row_name(best)} ({_time(best[tk])}, {_fmt(error_of(best))})" if best else "none")
                front = pareto([(r[tk], error_of(r)) for r in sel])
                front_txt = "; ".join(f"{_row_name(sel[i])} ({_time(sel[i][tk])}, {_fmt(error_of(sel[i]))})"
                                      for i in front) or "-"
                L.append(f"| {title if n == 0 else ''} | {situation} | {' | '.join(cells)} | {front_txt} |")
        L.append("")
    L.append("### Plots")
    L.append("")
    L += image_lines(plots)
    if sheets:
        L.append("### Contact sheet")
        L.append("")
        L += image_lines(("contact sheet", path) for path in sheets)
    return L


MODEL_STYLE = {"explicit (paper)": ("tab:blue", "o"), "multigrid (shipped)": ("tab:red", "P"), "elastic": ("tab:green", "s")}


def plot_elastic(rows, time_key, machine, out_png):
    """Each elastic-study reference's error against step time, one panel each, with the Pareto front across
    models in each situation (SITUATIONS) marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, grid = plt.subplots(2, 2, figsize=(14, 11))
    for ax, (key, title, err) in zip(grid.ravel(), ELASTIC_REFERENCES):
        pts = [(r[time_key], err(r["errors"])) for r in rows]
        for (model, mode) in dict.fromkeys((r["model"], r["mode"]) for r in rows):
            colour, marker = MODEL_STYLE.get(model, ("tab:gray", "o"))
            sel = [(r, q) for r, q in zip(rows, pts) if r["model"] == model and r["mode"] == mode and
                   _finite(q[0]) and _finite(q[1])]
            if not sel:
                continue
            ax.scatter([q[0] for _, q in sel], [max(q[1], 1e-3) for _, q in sel], c=colour, marker=marker, s=30,
                       alpha=1.0 if mode in ("from rest", "every step", "from zero") else 0.5, label=f"{model}, {mode}")
            for r, q in sel:
                ax.annotate(r["setting"], (q[0], max(q[1], 1e-3)), textcoords="offset points", xytext=(4, 3), fontsize=6,
                            color=colour)
        for (situation, modes), style in zip(SITUATIONS, ("-", "--", ":")):
            sel = [q for r, q in zip(rows, pts) if r["mode"] in modes]
            front = pareto(sel)
            if front:
                ax.step([sel[i][0] for i in front], [max(sel[i][1], 1e-3) for i in front], where="post", c="k", lw=1,
                        ls=style, alpha=0.7, label=f"Pareto front: {situation}")
        for th in THRESHOLDS:
            ax.axhline(th, c="grey", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"step time on {machine}, median (ms)")
        ax.set_ylabel("error (%)")
        ax.set_title(f"{title}\n(dotted: 1, 5, 10 %)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)


def plot_profile(el, out_png):
    """Hertz's surface profile, the FEM's (axisymmetric, converged) and the elastic model's on its block."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pr = el["references"]["profile"]
    R, d = pr["radius_mm"], pr["depth_mm"]
    fem = next((h.get("fem") for h in el["references"]["hertz"] if h["block_n"] == pr["block_n"] and h["nu"] == pr["nu"]
                and h["depth_mm"] == d and h.get("fem")), None)
    rmax = max(pr["elastic"]["r_mm"])
    rs = [rmax * i / 400 for i in range(401)]
    a = math.sqrt(R * d)

    def hertz(r):
        if r <= a:
            return d - r * r / (2 * R)
        return ((2 * a * a - r * r) * math.asin(a / r) + a * math.sqrt(r * r - a * a)) / (math.pi * R)

    fig, ax = plt.subplots(figsize=(8, 5))
    ax.plot(rs, [hertz(r) for r in rs], "k-", label="Hertz")
    if fem:
        sel = [(r, w) for r, w in zip(fem["profile"]["r_mm"], fem["profile"]["w_mm"]) if r <= rmax]
        ax.plot([q[0] for q in sel], [q[1] for q in sel], "o--", ms=3, c="tab:orange",
                label=f"FEM, axisymmetric, converged ({fem['profile_pct']:.2g} %)")
    ax.plot(pr["elastic"]["r_mm"], pr["elastic"]["w_mm"], "s", ms=4, c="tab:green",
            label=f"elastic model, {pr['block_n']}^3 voxels of 1 mm ({pr['elastic_pct']:.2g} %)")
    ax.axvline(a, c="grey", ls=":", lw=0.8)
    ax.axvline(pr["within_radii"] * a, c="grey", ls="--", lw=0.8)
    ax.set_xlabel("distance from the axis on the skin (mm)")
    ax.set_ylabel("displacement into the block (mm)")
    ax.set_title(f"Hertz's profile: R {R:g} mm, d {d:g} mm, nu {pr['nu']:g} (dotted: a; dashed: the compared disc)",
                 fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)


# ---- the two force models for the same press (palpsim-bench accuracy --forces) -----------------

def load_forces(path):
    """The JSON of one `palpsim-bench accuracy --forces` run."""
    return load_json(path, "accuracy-forces", "palpsim-bench accuracy --forces")


def forces_markdown(fm):
    """The section comparing eq. 2's force with the elastic model's, as the server reports each."""
    h = fm["haptics"]
    L = ["## The force each model reports", ""]
    L.append(f"Measured {fm['date']} on {fm['host_cpu']} ({fm['host_threads']} threads), {fm['device']}, commit "
             f"{fm['commit']}. The same press of `{fm['scene']}` (a fingertip of {fm['finger_radius_mm']:g} mm, "
             f"Poisson {fm['poisson']:g}) with `haptics.force_model` \"proxy\" (eq. 2, the default: "
             f"k = {h['stiffness_n_per_mm']:g} N/mm times the proxy's distance) and \"elastic\" (the reaction of the "
             f"elastic solve on the fingertip), each as the pose reply carries it once the tip is held "
             f"(bench/press_forces.h runs the server's own code; both clamped at {h['max_force_n']:g} N, the elastic "
             f"model's updates at {h['elastic_max_jump_n']:g} N a pose). The tip comes in at 1 kHz from outside the "
             "skin along the normal and is held at the depth given. On the homogeneous block (no bone, no skin layer, "
             f"{fm['block']['size'][0]}x{fm['block']['size'][1]}x{fm['block']['size'][2]} voxels of 1 mm at "
             f"{fm['block']['hu']:g} HU) Hertz's force for a sphere of the fingertip's radius is the reference; "
             f"above the phantom's {fm['landmark']} there is none.")
    L.append("")
    L.append("| where | depth mm | eq. 2 N | elastic N | elastic unclamped N | Hertz N | eq. 2 / Hertz | "
             "elastic / Hertz | elastic k N/mm | contact nodes | CG steps | step ms |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in fm["rows"]:
        fp, fe, f0 = _vec_norm(r["proxy_n"]), _vec_norm(r["elastic_n"]), _vec_norm(r["elastic_f0_n"])
        fh = r.get("hertz_n") if _finite(r.get("hertz_n")) else float("nan")
        L.append(f"| {r['where']} | {r['depth_mm']:g} | {_fmt(fp)} | {_fmt(fe)} | {_fmt(f0)} | {_fmt(fh)} | "
                 f"{_fmt(fp / fh)} | {_fmt(fe / fh)} | {_fmt(r['stiffness_n_per_mm'])} | {r['contact_nodes']} | "
                 f"{r['cg_steps']} | {_time(r['step_ms'])} |")
    L.append("")
    return L


def markdown(cpu, gpu, rows, plots, elastic=None, elastic_gpu=None, elastic_rows=(), elastic_plots=(), sheets=(),
             command=None, forces=None, halfspace=None):
    """The report's markdown text: the elastic study's section (when given), the force models' (when
    given) and the ChainMail knobs'."""
    L = ["# What accuracy costs in time", ""]
    L.append("Generated by `palpsim-bench accuracy` (bench/accuracy_bench.cpp, bench/elastic_accuracy_bench.cpp, "
             "bench/accuracy_report.py); do not edit by hand." + (f" Regenerate it from the recorded runs "
                                                                  f"(bench/results) with `{command}`." if command else ""))
    L.append("")
    if elastic:
        L += elastic_markdown(elastic, elastic_gpu, list(elastic_rows), list(elastic_plots), list(sheets))
    if halfspace:
        L += halfspace_markdown(halfspace, elastic, _fmt, _met, band_for)
    if forces:
        L += forces_markdown(forces)
    L += chainmail_markdown(cpu, gpu, rows, plots)
    return "\n".join(L) + "\n"


KNOB_STYLE = {"relaxation diffusion": ("tab:blue", "o"), "relaxation multigrid": ("tab:red", "P"),
              "relaxation multigrid warm": ("tab:pink", "X"),
              "relaxation multigrid reused": ("tab:brown", "*"),
              "relaxation multigrid primed": ("tab:olive", "d"),
              "inversion iterations": ("tab:orange", "s"), "VOI edge": ("tab:green", "^"),
              "ChainMail preset": ("tab:purple", "D")}


def plot(rows, time_key, machine, out_png, force=None):
    """Error against step time, one panel per reference (a)-(c) (and (d) when `force`), Pareto front marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401 (the time axis's locator and formatters)
    fig, grid = plt.subplots(2, 2, figsize=(14, 11))
    axes = list(grid.ravel())
    for ax, (key, title, err) in zip(axes, REFERENCES):
        pts = [(r[time_key], err(r["errors"])) for r in rows]
        for knob in dict.fromkeys(r["knob"] for r in rows):
            colour, marker = KNOB_STYLE.get(knob, ("tab:blue", "o"))
            sel = [(r, p) for r, p in zip(rows, pts) if r["knob"] == knob and _finite(p[0]) and _finite(p[1])]
            ax.scatter([p[0] for _, p in sel], [max(p[1], 1e-3) for _, p in sel], c=colour, marker=marker, s=28,
                       label=knob)
            for r, p in sel:
                ax.annotate(r["setting"], (p[0], max(p[1], 1e-3)), textcoords="offset points", xytext=(4, 3),
                            fontsize=7, color=colour)
        # the Pareto front: per knob for (a) (each knob has its own reference), else over all rows
        for label, sel in selection_groups(key, rows, lambda r, err=err: err(r["errors"])):
            sp = [(r[time_key], err(r["errors"])) for r in sel]
            front = pareto(sp)
            if not front:
                continue
            colour = KNOB_STYLE.get(sel[0]["knob"], ("tab:blue", "o"))[0] if label else "k"
            ax.step([sp[i][0] for i in front], [max(sp[i][1], 1e-3) for i in front], where="post", c=colour, lw=1,
                    alpha=0.7, label="Pareto front" + label)
            ax.scatter([sp[i][0] for i in front], [max(sp[i][1], 1e-3) for i in front], s=110, facecolors="none",
                       edgecolors=colour, lw=1)
        for th in THRESHOLDS:
            ax.axhline(th, c="grey", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        # ticks at 1, 2, 5 per decade as plain numbers (the default labels every minor tick, overlapping)
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel(f"step time on {machine}, median (ms)")
        ax.set_ylabel("relative RMS error (%)")
        ax.set_title(f"{title}\n(dotted: 1, 5, 10 %; errors below 1e-3 % drawn at 1e-3)", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    if not force:
        axes[-1].set_visible(False)
    else:
        ax = axes[-1]
        for f in force:
            if f["where"] == "all in soft tissue":
                continue
            ax.scatter(f["ns_per_pose"], max(f["rel_rms_pct"], 1e-3), marker="o" if f["sampling"] == "trilinear" else "x",
                       s=40, label=f"{f['sampling']}: {f['where']}")
        ax.set_yscale("log")
        ax.set_xlabel(f"force sampling time per pose on {machine} (ns)")
        ax.set_ylabel("relative RMS force error (%)")
        ax.set_title("(d) force model vs eq. 1-2 in double, by tip class", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)


def _command(a):
    """The `palpsim-bench accuracy --from-json` command that regenerates this report, with the files
    given by their path relative to the repository (or as given)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def rel(path):
        full = os.path.abspath(path)
        return os.path.relpath(full, root) if full.startswith(root + os.sep) else path

    cmd = f"build/palpsim-bench accuracy --from-json {rel(a.cpu)}"
    for flag, value in (("--gpu-json", a.gpu), ("--elastic-json", a.elastic), ("--elastic-gpu-json", a.elastic_gpu),
                        ("--forces-json", a.forces), ("--halfspace-json", a.halfspace)):
        if value:
            cmd += f" {flag} {rel(value)}"
    return cmd


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cpu", required=True, help="JSON of `palpsim-bench accuracy` on this machine")
    ap.add_argument("--gpu", help="JSON of `palpsim-bench accuracy --json-only` on the GPU machine")
    ap.add_argument("--elastic", help="JSON of `palpsim-bench accuracy --elastic` on this machine")
    ap.add_argument("--elastic-gpu", help="JSON of `palpsim-bench accuracy --elastic --json-only` on the GPU machine")
    ap.add_argument("--forces", help="JSON of `palpsim-bench accuracy --forces` (the two force models)")
    ap.add_argument("--halfspace", help="JSON of `palpsim-bench accuracy --halfspace` (Hertz's blocks on the half-space)")
    ap.add_argument("--out-dir", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"))
    a = ap.parse_args()
    cpu = load(a.cpu)
    gpu = load(a.gpu) if a.gpu else None
    os.makedirs(a.out_dir, exist_ok=True)
    el = load_elastic(a.elastic) if a.elastic else None
    el_gpu = load_elastic(a.elastic_gpu) if a.elastic_gpu else None
    rows = merged_rows(cpu, gpu)
    plots = [("error against CPU step time", os.path.join(a.out_dir, "accuracy-cpu.png"))]
    plot(rows, "cpu_ms", "CPU", plots[0][1], cpu.get("force"))
    if gpu and any(r["gpu_ms"] is not None for r in rows):
        plots.append(("error against H100 step time", os.path.join(a.out_dir, "accuracy-h100.png")))
        plot([r for r in rows if r["gpu_ms"] is not None], "gpu_ms", "H100", plots[1][1], gpu.get("force"))
    el_rows, el_plots, sheets = [], [], []
    if el:
        el_rows = merged_elastic_rows(el, el_gpu)
        el_plots.append(("the elastic study's errors against CPU step time", os.path.join(a.out_dir, "accuracy-elastic-cpu.png")))
        plot_elastic(el_rows, "cpu_ms", "CPU", el_plots[-1][1])
        if any(r["gpu_ms"] is not None for r in el_rows):
            el_plots.append(("the elastic study's errors against GPU step time",
                             os.path.join(a.out_dir, "accuracy-elastic-gpu.png")))
            plot_elastic([r for r in el_rows if r["gpu_ms"] is not None], "gpu_ms", el_gpu["device"], el_plots[-1][1])
        if (el.get("references") or {}).get("profile"):
            el_plots.append(("Hertz's surface profile", os.path.join(a.out_dir, "accuracy-elastic-profile.png")))
            plot_profile(el, el_plots[-1][1])
        # the contact sheet of the three models, where one lies beside the elastic JSON
        sheets = sorted(glob.glob(os.path.join(os.path.dirname(os.path.abspath(a.elastic)), "elastic-contact-sheet*.png")))
    md = os.path.join(a.out_dir, "accuracy.md")
    with open(md, "w") as f:
        f.write(markdown(cpu, gpu, rows, plots, el, el_gpu, el_rows, el_plots, sheets, _command(a),
                         load_forces(a.forces) if a.forces else None,
                         load_json(a.halfspace, "accuracy-halfspace", "palpsim-bench accuracy --halfspace")
                         if a.halfspace else None))
    print(f"wrote {md} and {', '.join(p for _, p in plots + el_plots)}")


if __name__ == "__main__":
    main()
