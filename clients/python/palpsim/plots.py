"""PNG figures of a batch run, drawn from its tidy table with matplotlib's Agg backend:
force against depth, and the peak force over the skin region (a map for a 2-D grid,
a profile for a line of points)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from .results import point_table  # noqa: E402


def _save(fig: "plt.Figure", path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def force_depth_plot(df: pd.DataFrame, path: str | Path, title: str = "") -> Path:
    """|f| against depth under the skin, one line per press, coloured by its peak force;
    pressing in solid, retracting faint (the gap between them is the friction's hysteresis)."""
    fig, ax = plt.subplots(figsize=(7, 5))
    peaks = df.groupby(["point_id", "rep"], observed=True)["force_n"].max()
    norm = matplotlib.colors.Normalize(vmin=float(peaks.min()), vmax=max(float(peaks.max()), 1e-9))
    cmap = matplotlib.colormaps["viridis"]
    for (pid, rep), g in df.groupby(["point_id", "rep"], observed=True, sort=True):
        color = cmap(norm(peaks.loc[(pid, rep)]))
        inward = g[g["phase"].isin(["approach", "press", "hold"])]
        out = g[g["phase"] == "retract"]
        ax.plot(inward["depth_mm"], inward["force_n"], color=color, lw=1.0, alpha=0.8)
        ax.plot(out["depth_mm"], out["force_n"], color=color, lw=0.6, alpha=0.25)
    sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=ax, label="peak force of the press (N)")
    ax.set_xlabel("depth under the skin (mm)")
    ax.set_ylabel("|force| (N)")
    ax.set_title(title or "force against depth")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def peak_force_plot(df: pd.DataFrame, path: str | Path, title: str = "",
                    axis_names: Sequence[str] = ("u", "v")) -> Path:
    """Mean peak force per grid point: a map over (u, v) for a 2-D grid, a profile for a
    line. Points whose presses never met the skin are marked with an x."""
    pts = point_table(df)
    nu, nv = int(pts["iu"].max()) + 1, int(pts["iv"].max()) + 1
    no_contact = pts["contact_presses"] == 0
    if nu > 1 and nv > 1:
        # a figure shaped like the region, so the map's equal aspect wastes little space
        span_u = max(float(np.ptp(pts["u_mm"])), 1e-9)
        span_v = max(float(np.ptp(pts["v_mm"])), 1e-9)
        ratio = span_u / span_v
        size = (max(4.5, 5.5 * ratio + 2.5), 6.0) if ratio <= 1 else (8.0, max(3.5, 6.0 / ratio + 1.5))
    else:
        size = (8.0, 4.5)
    fig, ax = plt.subplots(figsize=size)
    if nu > 1 and nv > 1:
        grid = np.full((nv, nu), np.nan)
        grid[pts["iv"].to_numpy(), pts["iu"].to_numpy()] = pts["peak_force_n"].to_numpy()
        us = np.sort(pts["u_mm"].unique())
        vs = np.sort(pts["v_mm"].unique())
        mesh = ax.pcolormesh(us, vs, grid, shading="nearest", cmap="magma")
        fig.colorbar(mesh, ax=ax, label="peak force (N, mean over repetitions)", shrink=0.8)
        ax.plot(pts["u_mm"], pts["v_mm"], ".", color="white", ms=2, alpha=0.6)
        ax.plot(pts.loc[no_contact, "u_mm"], pts.loc[no_contact, "v_mm"], "x", color="cyan",
                label="no contact")
        ax.set_xlabel(f"{axis_names[0]} (mm)")
        ax.set_ylabel(f"{axis_names[1]} (mm)")
        ax.set_aspect("equal")
        if no_contact.any():
            ax.legend(loc="upper right")
    else:
        along = "u_mm" if nu > 1 else "v_mm"
        name = axis_names[0] if nu > 1 else axis_names[1]
        pts = pts.sort_values(along)
        ax.plot(pts[along], pts["peak_force_n"], "-o", ms=3, color="tab:red", label="mean peak")
        if (pts["presses"] > 1).any():
            ax.fill_between(pts[along], pts["peak_force_min_n"], pts["peak_force_max_n"],
                            color="tab:red", alpha=0.2, label="min to max over repetitions")
        if no_contact.any():
            ax.plot(pts.loc[no_contact, along], pts.loc[no_contact, "peak_force_n"], "x",
                    color="k", label="no contact")
        ax.set_xlabel(f"{name} (mm)")
        ax.set_ylabel("peak force (N)")
        ax.grid(alpha=0.3)
        ax.legend(loc="best")
    ax.set_title(title or "peak force over the skin region")
    fig.tight_layout()
    return _save(fig, path)


def spine_profile_plot(df: pd.DataFrame, report: dict, path: str | Path, title: str = "") -> Path:
    """The demo's figure, along the line of presses (z, superior to the right): on top the
    peak force of each press with the peaks found and the process tips the bone mask
    expects; below, a sagittal section: the force felt at each tip position in contact
    (one column per press), the skin where each press met it, and the top of the bone
    from the mask."""
    line = report["line"]
    z = np.asarray(line["z_mm"], dtype=float)
    fig, (top, sec) = plt.subplots(2, 1, figsize=(10, 7.5), sharex=True, layout="constrained",
                                   gridspec_kw={"height_ratios": [1, 1.2]})
    exp = report.get("expected")
    # top: the force profile and its peaks
    top.plot(z, line["peak_force_n"], "-", color="tab:red", lw=1.5, label="peak force of the press")
    pk = report["peaks"]
    top.plot([p["z_mm"] for p in pk], [p["force_n"] for p in pk], "v", color="k", ms=8,
             label=f"peaks found ({len(pk)})")
    for p in pk:
        top.annotate(f"{p['z_mm']:.0f}", (p["z_mm"], p["force_n"]), textcoords="offset points",
                     xytext=(0, 7), ha="center", fontsize=8)
    if exp:
        for i, e in enumerate(exp["processes"]):
            for ax in (top, sec):
                ax.axvline(e["z_mm"], color="tab:blue", ls="--", lw=0.8, alpha=0.7,
                           label="process (bone mask)" if (i == 0 and ax is top) else None)
    top.set_ylabel("peak force (N)")
    top.grid(alpha=0.3)
    top.legend(loc="best", fontsize=8)
    top.set_title(title or "force profile along the back")
    # below: the section with the forces felt under the skin
    inside = df[df["contact"] & df["phase"].isin(["approach", "press", "hold"])]
    if len(inside):
        # an image: one column per press, the largest |force| in 0.5 mm bins of tip y
        bin_mm = 0.5
        yb = np.round(inside["tip_y_mm"].to_numpy() / bin_mm).astype(int)
        zs = np.unique(inside["tip_z_mm"].to_numpy())
        zi = np.searchsorted(zs, inside["tip_z_mm"].to_numpy())
        img = np.full((yb.max() - yb.min() + 1, len(zs)), np.nan)
        np.fmax.at(img, (yb - yb.min(), zi), inside["force_n"].to_numpy())
        img_y = (np.arange(img.shape[0]) + yb.min()) * bin_mm
        mesh = sec.pcolormesh(zs, img_y, np.ma.masked_invalid(img), shading="nearest", cmap="magma")
        # one colour bar beside both panels keeps their z axes aligned
        fig.colorbar(mesh, ax=[top, sec], label="|force| in the section below (N)", pad=0.01,
                     fraction=0.03)
    sec.plot(z, line["skin_y_mm"], "-", color="tab:green", lw=1.2, label="skin met by the press")
    if exp:
        sec.plot(exp["bone_top"]["z_mm"], exp["bone_top"]["y_mm"], "-", color="tab:blue", lw=1.2,
                 label="top of bone (mask)")
    if len(inside):
        # zoom on the pressed layer and the bone just under it
        sec.set_ylim(inside["tip_y_mm"].min() - 15.0, np.nanmax(line["skin_y_mm"]) + 5.0)
    sec.set_xlabel("z (mm, LPS: inferior to superior)")
    sec.set_ylabel("y (mm, posterior up)")
    sec.grid(alpha=0.3)
    sec.legend(loc="lower right", fontsize=8)
    return _save(fig, path)
