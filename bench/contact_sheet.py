#!/usr/bin/env python3
"""Compose the contact sheet of one press over L3 of the phantom from `palpsim-bench contact_sheet`.

Three models side by side (columns): the paper's explicit relaxation, the shipped multigrid
diffusion and the elastic model. Rows: the deformed image J on the sagittal and the axial
slice through the press, then |u| (mm, drawn at each voxel's rest position) on both. J panels carry the undeformed skin (cyan,
dashed) and bone (yellow) contours, so that the dent and whether bone moved can be read
off; |u| panels share one colour scale, with contours at 1, 2 and 5 mm. The tip is a red
cross; the fingertip is drawn where the model has one (multigrid: the grabbed ball moved to
the tip; elastic: the sphere whose deepest point is the tip). Column titles: the model,
its step time on the run's CPU (while pressing a millimetre a step, and from rest) and the
reaction force where the model has one.

    build/palpsim-bench contact_sheet --commit $(git rev-parse --short HEAD) --out out/contact-sheet
    .venv/bin/python bench/contact_sheet.py out/contact-sheet

writes bench/results/elastic-contact-sheet-<date>-cpu-<commit>.png and the run's JSON beside
it (same name, .json); -o names another PNG.
"""
import argparse
import json
import os
import shutil
import sys

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
J_WINDOW_HU = (-250.0, 350.0)  # fat dark, muscle and skin grey, bone white
U_LEVELS_MM = (1.0, 2.0, 5.0)


def load(folder):
    """The run's JSON and a loader of its slices; exits naming the file when it is not one."""
    path = os.path.join(folder, "contact_sheet.json")
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError) as e:
        sys.exit(f"contact_sheet.py: cannot read {path}: {e}")
    if d.get("area") != "contact_sheet" or "models" not in d or "planes" not in d:
        sys.exit(f"contact_sheet.py: {path} is not the JSON of `palpsim-bench contact_sheet`")

    def slice_of(plane, what):
        f = os.path.join(folder, f"{plane}-{what}.npy")
        try:
            return np.load(f)
        except OSError as e:
            sys.exit(f"contact_sheet.py: cannot read {f}: {e}")

    return path, d, slice_of


def in_plane(p, plane):
    """(column, row) coordinates (mm) of the point p (mm, LPS) in a plane of the JSON."""
    return p[plane["column_axis"]], p[1]


def fingertip(ax, model, press, plane):
    """The fingertip of `model` in `plane`: the tip, and its ball or sphere where it has one."""
    tip = press["tip_mm"]
    if model["relax_method"] == "elastic":
        n = model["elastic"]["normal"]
        r = model["elastic"]["radius_mm"]
        # the sphere where the model presses: held short of bone (press_cap.h), the device
        # tip (the cross) on beyond it
        held = model["elastic"].get("pressed_tip_mm", tip)
        centre = [held[a] - n[a] * r for a in range(3)]
        off = centre[plane["cut_axis"]] - plane["cut_mm"]
        if abs(off) < r:
            ax.add_patch(Circle(in_plane(centre, plane), np.sqrt(r * r - off * off), fill=False, color="red", lw=0.8))
    elif model["grab_radius_mm"] > 0:
        # the soft elements within grab_radius_mm of the grabbed element move with it to the tip
        ax.add_patch(Circle(in_plane(tip, plane), model["grab_radius_mm"], fill=False, color="red", lw=0.8, ls="--"))
    ax.plot(*in_plane(tip, plane), marker="+", color="red", ms=7, mew=1.2)


def title(model, press):
    """A column's title: the model, its step times, its force (and where bone held its press)."""
    w, r = model["step_while_pressing"], model["step_from_rest"]
    lines = [model["label"], f"step {w['median_ms']:.0f} ms pressing 1 mm a step, {r['median_ms']:.0f} ms from rest"]
    if "elastic" in model:
        e = model["elastic"]
        lines.append(f"reaction on the finger {e['force_norm_n']:.2f} N, {e['inverted_cells']} folded cells")
        depth = e.get("pressed_depth_mm")
        if depth is not None and depth < press["depth_mm"] - 1e-6:
            lines.append(f"held {depth:.1f} mm deep: {e['min_tissue_fraction']:.0%} of the tissue over the bone left")
    else:
        lines.append("no force of its own (the proxy's eq. 2)")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("folder", help="the --out folder of palpsim-bench contact_sheet")
    p.add_argument("-o", "--out", help="PNG to write (default bench/results/elastic-contact-sheet-<date>-cpu-<commit>.png)")
    a = p.parse_args(argv)
    json_path, d, slice_of = load(a.folder)
    out = a.out or os.path.join(HERE, "results", f"elastic-contact-sheet-{d['date'][:10]}-cpu-{d['commit']}.png")

    models, planes, press = d["models"], d["planes"], d["press"]
    u_max = max(float(slice_of(pl["name"], "u-" + m["key"]).max()) for pl in planes for m in models)
    n = len(planes)
    fig, axes = plt.subplots(2 * n, len(models), figsize=(4.6 * len(models) + 1.4, 4.1 * 2 * n), squeeze=False,
                             constrained_layout=True)
    col_name = {0: "x (mm, patient's left \u2192)", 2: "z (mm, superior \u2192)"}
    box = {"facecolor": "black", "alpha": 0.6, "pad": 2, "edgecolor": "none"}
    j_img = u_img = None
    for q, pl in enumerate(planes):
        ext = pl["extent_mm"]
        body, bone = slice_of(pl["name"], "body"), slice_of(pl["name"], "bone")
        # contour coordinates: voxel centres
        xs = np.linspace(ext[0], ext[1], pl["cols"] + 1)
        xs = 0.5 * (xs[:-1] + xs[1:])
        ys = np.linspace(ext[3], ext[2], pl["rows"] + 1)
        ys = 0.5 * (ys[:-1] + ys[1:])
        cut = "x" if pl["cut_axis"] == 0 else "z"
        for c, m in enumerate(models):
            # rows: J of every plane, then |u| of every plane
            aj, au = axes[q][c], axes[n + q][c]
            j_img = aj.imshow(slice_of(pl["name"], "J-" + m["key"]), cmap="gray", vmin=J_WINDOW_HU[0],
                              vmax=J_WINDOW_HU[1], extent=ext, origin="upper", interpolation="nearest")
            aj.contour(xs, ys, body, levels=[0.5], colors="cyan", linewidths=0.7, linestyles="--")
            aj.contour(xs, ys, bone, levels=[0.5], colors="yellow", linewidths=0.7)
            u = slice_of(pl["name"], "u-" + m["key"])
            u_img = au.imshow(u, cmap="inferno", vmin=0, vmax=u_max, extent=ext, origin="upper",
                              interpolation="nearest")
            if u.max() > U_LEVELS_MM[0]:
                au.contour(xs, ys, u, levels=[v for v in U_LEVELS_MM if v < u.max()], colors="white",
                           linewidths=0.6)
            au.contour(xs, ys, body, levels=[0.5], colors="cyan", linewidths=0.5, linestyles="--")
            for ax in (aj, au):
                fingertip(ax, m, press, pl)
                ax.set_xlim(ext[0], ext[1])
                ax.set_ylim(ext[2], ext[3])
                ax.set_xlabel(col_name[pl["column_axis"]], fontsize=8)
                ax.tick_params(labelsize=7)
            if c == 0:
                aj.set_ylabel(f"{pl['name']} ({cut} = {pl['cut_mm']:.0f} mm): J\ny (mm, posterior \u2191)", fontsize=9)
                au.set_ylabel(f"{pl['name']} ({cut} = {pl['cut_mm']:.0f} mm): |u| at rest positions\n"
                              "y (mm, posterior \u2191)", fontsize=9)
            if q == 0:
                aj.set_title(title(m, press), fontsize=9)
            aj.text(0.02, 0.02, f"max |u| {m['max_u_mm']:.1f} mm, bone voxels moved {m['bone_moved_voxels']}, "
                    f"J unresolved {m['invert_unresolved']}", transform=aj.transAxes, color="white", fontsize=7,
                    bbox=box)
    fig.colorbar(j_img, ax=[axes[q][-1] for q in range(n)], shrink=0.8, label="J (HU)")
    fig.colorbar(u_img, ax=[axes[n + q][-1] for q in range(n)], shrink=0.8,
                 label="|u| (mm), one scale for the three; contours 1, 2, 5 mm")
    X = press["X_mm"]
    fig.suptitle(f"A {press['depth_mm']:.0f} mm press over L3's spinous process of the phantom ({d['scene']}), along "
                 f"-y at x {X[0]:.0f}, z {X[2]:.0f} mm; skin at y {press['skin_mm'][1]:.1f} mm; the proxy's eq. 2 force "
                 f"{press['eq2_force_norm_n']:.2f} N\n{d['backend']} backend on {d['machine']} (shared, load "
                 f"{d['load_average'][0]:.1f}-{d['load_average'][1]:.1f}), median of {d['repeats']}; commit "
                 f"{d['commit']}, {d['date']}. Cyan dashed: the skin at rest; yellow: bone at rest; red: the tip "
                 "and fingertip", fontsize=10)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=110)
    shutil.copyfile(json_path, os.path.splitext(out)[0] + ".json")
    print(f"wrote {out} and {os.path.splitext(out)[0] + '.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
