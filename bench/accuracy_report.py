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
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from accuracy_common import (THRESHOLDS, TIME_TIE, _finite, _fmt, _ms, fastest_within,  # noqa: E402,F401
                             image_lines, load_json, pareto)
from accuracy_elastic import (_met, _time, _vec_norm, band_for, elastic_markdown,  # noqa: E402,F401
                              load_elastic, merged_elastic_rows, plot_elastic, plot_profile)
from accuracy_halfspace import halfspace_markdown  # noqa: E402 (beside this script)

# the deformation references: key, title, the row's error (%) for it
REFERENCES = [
    ("a", "(a) own converged solution",
     lambda e: max(e["a_u_pct"], e["a_J_pct"]) if _finite(e.get("a_u_pct")) and _finite(e.get("a_J_pct")) else None),
    ("b", "(b) Boussinesq half-space (shape)", lambda e: e.get("b_shape_pct")),
    ("c", "(c) linear-elastic FEM", lambda e: e.get("c_u_pct")),
]


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


def selection_groups(key, rows, error_of):
    """The row sets that one "fastest within" selection runs over: for reference (a) each knob
    that has one (its own converged value), labelled ": knob"; for the others all rows."""
    if key != "a":
        return [("", rows)]
    knobs = dict.fromkeys(r["knob"] for r in rows if _finite(error_of(r)))
    return [(f": {k}", [r for r in rows if r["knob"] == k]) for k in knobs]


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


def _chainmail_setup(cpu, gpu):
    """The section's title and what was run: the machines, the press and the base settings."""
    gpu_name = gpu["device"] if gpu else "none given"
    p, b = cpu["press"], cpu["base"]
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
    return L


def _chainmail_references(cpu):
    """References (a)-(d) and the error metrics, in words."""
    a, rb, rc = cpu["reference_a"], cpu["reference_b"], cpu["reference_c"]
    L = []
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
    return L


def _chainmail_rows(rows):
    """Every row with its step times and errors."""
    L = []
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
    return L


def _chainmail_fastest(rows, gpu):
    """The fastest setting within 1, 5 and 10 % of each reference, with the Pareto front."""
    L = []
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
    return L


def _force_lines(cpu, gpu):
    """The force model against reference (d), per sampling and where the tips are."""
    L = []
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
    return L


def chainmail_markdown(cpu, gpu, rows, plots):
    """The report's section on the ChainMail knobs against references (a)-(d), as lines."""
    L = _chainmail_setup(cpu, gpu)
    L += _chainmail_references(cpu)
    L += _chainmail_rows(rows)
    L += _chainmail_fastest(rows, gpu)
    L += _force_lines(cpu, gpu)
    L.append("### Plots")
    L.append("")
    L += image_lines(plots)
    return L


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
        # the newest contact sheet of the three models beside the elastic JSON (named by
        # date, then commit; older ones stay in bench/results as history)
        sheets = sorted(glob.glob(os.path.join(os.path.dirname(os.path.abspath(a.elastic)),
                                               "elastic-contact-sheet*.png")))[-1:]
    md = os.path.join(a.out_dir, "accuracy.md")
    with open(md, "w") as f:
        f.write(markdown(cpu, gpu, rows, plots, el, el_gpu, el_rows, el_plots, sheets, _command(a),
                         load_forces(a.forces) if a.forces else None,
                         load_json(a.halfspace, "accuracy-halfspace", "palpsim-bench accuracy --halfspace")
                         if a.halfspace else None))
    print(f"wrote {md} and {', '.join(p for _, p in plots + el_plots)}")


if __name__ == "__main__":
    main()
