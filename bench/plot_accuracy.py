#!/usr/bin/env python3
"""Plot what deformation accuracy costs in time, from `palpsim-bench deform --accuracy --json FILE`.

One panel per knob (relaxation iterations, inversion iterations, VOI edge): the
accuracy figure against the median step time, one line per backend, each point
labelled with its setting; horizontal bars span the 10th to 90th percentile of the
step time. Time is log-scaled where it spans more than a factor of 10 (always when
cpu and cuda share a panel). The reference rows are not drawn (their error is 0 by
definition); the panel titles name them.

usage: plot_accuracy.py bench/results/accuracy-DATE-DEVICE.json [-o OUT.png]
       (default OUT: the JSON path with .png, i.e. bench/results/accuracy-DATE-DEVICE.png)
"""
import argparse
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from accuracy_report import load_json  # noqa: E402

# values at or below this are drawn on the floor of a log axis (energy fractions reach exactly 0)
FLOOR = 1e-9

COLOURS = {"cpu": "tab:blue", "cuda": "tab:green"}

# per knob: title, the figures drawn (metric, label, line style) and the y label
PANELS = [
    ("relax_iterations", "relaxation iterations",
     [("u_rms_diff_vox", "RMS |u - u_ref|", "-"), ("u_max_diff_vox", "max |u - u_ref|", "--"),
      ("laplacian_rms_vox", "RMS Laplacian of u (roughness)", ":")],
     "displacement error vs reference / roughness (voxel)"),
    ("invert_iterations", "inversion iterations",
     [("residual_mean_vox", "mean residual (voxel)", "-"), ("J_rms_diff_hu", "RMS |J - J_ref| (HU)", "--"),
      ("J_rms_diff_resolved_hu", "RMS |J - J_ref|, voxels resolved in ref (HU)", ":")],
     "mean residual (voxel) / RMS J error (HU)"),
    ("voi_edge", "VOI edge",
     [("clipped_energy_relax20", "clipped energy, relax 20", "-"), (None, "clipped energy, relax REF", "--")],
     "fraction of reference energy outside the VOI"),
]


def load(path):
    """The JSON of one accuracy run; exits with a message naming the file when it is not one."""
    return load_json(path, "deform-accuracy", "palpsim-bench deform --accuracy")


def panel(ax, d, knob, title, figures, ylabel):
    """Draws one knob: accuracy figures against step time per backend."""
    ref = d["reference"]
    ref_setting = {"relax_iterations": ref["relax_iterations"], "invert_iterations": ref["invert_iterations"],
                   "voi_edge": ref["voi_edge"]}[knob]
    rows = [r for r in d["rows"] if r["knob"] == knob and not r["reference"]]
    times = []
    floored = False
    for backend in sorted({r["backend"] for r in rows}):
        rs = sorted((r for r in rows if r["backend"] == backend), key=lambda r: r["setting"])
        t = [r["step"]["median_ms"] for r in rs]
        lo = [r["step"]["median_ms"] - r["step"]["p10_ms"] for r in rs]
        hi = [r["step"]["p90_ms"] - r["step"]["median_ms"] for r in rs]
        times += t
        for n, (metric, label, style) in enumerate(figures):
            if metric is None:  # the long-relaxation reference's clipped energy
                metric = f"clipped_energy_relax{ref['relax_iterations']}"
                label = label.replace("REF", str(ref["relax_iterations"]))
            y = [r["metrics"][metric] for r in rs]
            yd = [max(v, FLOOR) for v in y]
            floored = floored or any(v <= FLOOR for v in y)
            ax.errorbar(t, yd, xerr=[lo, hi], fmt="osv"[n], ls=style, ms=4, capsize=2,
                        color=COLOURS.get(backend, "tab:red"), alpha=1.0 if n == 0 else 0.6,
                        label=f"{backend}: {label}")
            # label each point with its setting
            for tx, yy, r in zip(t, yd, rs):
                ax.annotate(str(r["setting"]), (tx, yy), textcoords="offset points", xytext=(4, 4 if n == 0 else -10 * n),
                            fontsize=7, color=COLOURS.get(backend, "tab:red"))
    ax.set_yscale("log")
    if times and max(times) / max(min(times), 1e-9) > 10:
        ax.set_xscale("log")
    ax.set_xlabel("time per step, median (ms)")
    ax.set_ylabel(ylabel)
    note = f" (values <= {FLOOR:g} drawn at {FLOOR:g})" if floored else ""
    ax.set_title(f"{title}; reference {ref_setting}{note}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("json")
    ap.add_argument("-o", "--out", help="PNG to write (default: the JSON path with .png)")
    a = ap.parse_args()
    d = load(a.json)
    out = a.out or os.path.splitext(a.json)[0] + ".png"
    fig, axes = plt.subplots(1, 3, figsize=(18, 5.5))
    for ax, (knob, title, figures, ylabel) in zip(axes, PANELS):
        panel(ax, d, knob, title, figures, ylabel)
    b, p = d["base"], d["press"]
    fig.suptitle(
        f"deform accuracy vs time: {d['device']}, host {d['host_cpu']} ({d['host_threads']} threads), "
        f"commit {d['commit']}, {d['date']}\n"
        f"phantom {d['phantom']['voxel_mm']:.3f} mm, {p['press_mm']:g} mm press {p['bone_depth_mm']:g} mm above "
        f"{p['landmark']}; one knob varied, others at base: preset {b['preset']}, VOI {b['voi_edge']}, "
        f"relax {b['relax_iterations']}, invert {b['invert_iterations']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
