"""The elastic study's section of the accuracy report (palpsim-bench accuracy --elastic): the
shipped configuration's press and a block against references (i)-(iv), every row with its step
times, the fastest rows and Pareto fronts, and its plots (bench/accuracy_report.py writes it)."""
import math

from accuracy_common import THRESHOLDS, _finite, _fmt, _ms, fastest_within, image_lines, load_json, pareto


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


def _elastic_setup(el, gpu):
    """The section's title and what was run: the machines, the scene, the press and the block."""
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
             "rounds" + (f"; the unit press solved to {d['stiffness_tolerance']:g}, as an elastic scene solves it, "
                         "predicting warm steps and superposing those that move along n alone"
                         if d.get("unit_press") else "") + ") unless a row says otherwise.")
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
    return L


def _elastic_references_text(el):
    """The references (i)-(v) and the error metrics, in words."""
    b = el["block"]
    L = []
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
    return L


def _verification_lines(refs, fem_ok):
    """(i): the elastic model against the FEM of its own problem."""
    L = []
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
    return L


def _discretisation_lines(refs):
    """(ii): voxel resolution against h/2, and what is left of the block's force at h/2."""
    L = []
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
    return L


def _hertz_lines(refs):
    """(iii): a sphere on a large block against Hertz's force."""
    L = []
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
    return L


def _profile_lines(refs):
    """(iv): Hertz's surface profile; none without it in the run."""
    L = []
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
    return L


def _voi_lines(refs):
    """What holding the VOI's faces costs, against larger VOIs; none without them in the run."""
    L = []
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
    return L


def _elastic_rows_lines(rows):
    """(v): every row with its step times and errors."""
    L = []
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
    return L


def _elastic_fastest_lines(rows):
    """The fastest row within 1, 5 and 10 % and the Pareto front, per machine, reference and situation."""
    L = []
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
    return L


def elastic_markdown(el, gpu, rows, plots, sheets):
    """The report's section on the elastic model and the shipped configuration, as lines."""
    refs = el.get("references") or {}
    L = _elastic_setup(el, gpu)
    L += _elastic_references_text(el)
    if not refs:
        L.append("No references in this run (a GPU machine's times only).")
        L.append("")
    fem_ok = bool(refs) and refs["press"].get("verification") is not None
    if refs:
        L += _verification_lines(refs, fem_ok)
        L += _discretisation_lines(refs)
        L += _hertz_lines(refs)
        L += _profile_lines(refs)
        L += _voi_lines(refs)
    L += _elastic_rows_lines(rows)
    L += _elastic_fastest_lines(rows)
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
    import matplotlib.ticker  # noqa: F401 (the time axis's locator and formatters)
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
        # ticks at 1, 2, 5 per decade as plain numbers (the default labels every minor tick, overlapping)
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
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


