"""The tidy table of a batch run (one row per pose) and its summary.

Columns (units in the names; positions in the CT's physical space, LPS):

    point_id, iu, iv, u_mm, v_mm   the grid point (plan.grid_points)
    rep, step, phase, t_s          repetition, pose index in the press, phase name,
                                   trajectory time (step / sample rate)
    travel_mm                      tip travel along the press direction from the start
    tip_{x,y,z}_mm                 the pose sent
    depth_mm, contact              depth under the skin and contact flag (server)
    force_{x,y,z}_n, force_n       force on the device and its magnitude
    press_force_n                  force component against the press direction (-f . d)
    proxy_{x,y,z}_mm               proxy p
    skin_{x,y,z}_mm                skin point X
    seq                            the pose's sequence number (a function of the plan)
    session, rtt_us, service_us    which worker session ran it, client round trip,
                                   server service time: timing, not results

Everything but TIMING_COLUMNS is a function of the plan and the scene alone;
`result_digest` hashes exactly those columns so that two runs can be compared.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from .plan import PHASES

# columns that describe how the run went, not what it measured (they vary run to run)
TIMING_COLUMNS = ("session", "rtt_us", "service_us")

COLUMNS = (
    "point_id", "iu", "iv", "u_mm", "v_mm", "rep", "step", "phase", "t_s", "travel_mm",
    "tip_x_mm", "tip_y_mm", "tip_z_mm", "depth_mm", "contact",
    "force_x_n", "force_y_n", "force_z_n", "force_n", "press_force_n",
    "proxy_x_mm", "proxy_y_mm", "proxy_z_mm", "skin_x_mm", "skin_y_mm", "skin_z_mm",
    "seq", "session", "rtt_us", "service_us",
)

# integer columns and their dtypes (everything else not named here is float64)
_INT_COLUMNS = {"point_id": "int32", "iu": "int32", "iv": "int32", "rep": "int32",
                "step": "int32", "seq": "uint64", "session": "int32"}


class TableError(ValueError):
    """A table cannot be written or read (unknown extension, missing columns)."""


def finish_table(df: pd.DataFrame) -> pd.DataFrame:
    """Puts a table in canonical form: canonical column order and dtypes, rows sorted by
    point, repetition and step, so that parallel runs give identical tables."""
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise TableError(f"table lacks columns: {', '.join(missing)}")
    df = df.loc[:, list(COLUMNS)].copy()
    for c, dt in _INT_COLUMNS.items():
        df[c] = df[c].astype(dt)
    for c in COLUMNS:
        if c not in _INT_COLUMNS and c not in ("contact", "phase"):
            df[c] = df[c].astype("float64")
    df["contact"] = df["contact"].astype(bool)
    if df["phase"].dtype.kind in "iu":
        df["phase"] = pd.Categorical.from_codes(df["phase"].to_numpy(), categories=list(PHASES))
    else:
        df["phase"] = pd.Categorical(df["phase"].astype(str), categories=list(PHASES))
    df = df.sort_values(["point_id", "rep", "step"], kind="stable").reset_index(drop=True)
    return df


def result_digest(df: pd.DataFrame) -> str:
    """SHA-256 over every result column (not TIMING_COLUMNS), in canonical order: two runs
    of the same plan on the same scene give the same digest."""
    return digest_columns(df, [c for c in COLUMNS if c not in TIMING_COLUMNS])


def digest_columns(df: pd.DataFrame, columns: list[str]) -> str:
    """SHA-256 over the named columns in that order: each column's name, then its values
    (categories as their codes, strings as UTF-8 each ended by a NUL, numbers as bytes)."""
    h = hashlib.sha256()
    for c in columns:
        col = df[c]
        if isinstance(col.dtype, pd.CategoricalDtype):
            data = np.asarray(col.cat.codes, dtype=np.int16).tobytes()
        elif col.dtype.kind in "OSUT":
            data = b"".join(str(v).encode() + b"\0" for v in col.to_numpy())
        else:
            data = np.ascontiguousarray(col.to_numpy()).tobytes()
        h.update(c.encode())
        h.update(data)
    return h.hexdigest()


def _atomic_path(path: Path) -> tuple[int, str]:
    """A temporary file beside `path`, renamed over it when complete (nothing half-written)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)


def write_table(df: pd.DataFrame, path: str | Path) -> Path:
    """Writes the table as CSV or Parquet, chosen by the extension (.csv, .parquet)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".csv", ".parquet"):
        raise TableError(f"{path}: unknown table format {ext!r} (use .csv or .parquet)")
    if ext == ".csv":
        # repr-exact floats, so a CSV reads back to the same numbers
        return write_atomically(path, lambda tmp: df.to_csv(tmp, index=False, float_format="%.17g"))
    return write_atomically(path, lambda tmp: df.to_parquet(tmp, index=False))


def write_atomically(path: str | Path, write: Callable[[str], Any]) -> Path:
    """Calls write(tmp) for a temporary file beside `path`, then renames it over `path`: the
    file is there whole or not at all (the temporary file is removed when write fails)."""
    path = Path(path)
    fd, tmp = _atomic_path(path)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_table(path: str | Path) -> pd.DataFrame:
    """Reads a table written by write_table back into canonical form."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".csv":
        df = pd.read_csv(path)
    elif ext == ".parquet":
        df = pd.read_parquet(path)
    else:
        raise TableError(f"{path}: unknown table format {ext!r} (use .csv or .parquet)")
    return finish_table(df)


def write_json(data: Any, path: str | Path) -> Path:
    """Writes JSON atomically (indent 2, no NaN: NaN becomes null)."""
    path = Path(path)
    fd, tmp = _atomic_path(path)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(_clean(data), f, indent=2, allow_nan=False)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _clean(x: Any) -> Any:
    """JSON-ready copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def press_table(df: pd.DataFrame) -> pd.DataFrame:
    """One row per press: peak force, where the skin was met, depth reached."""
    g = df.groupby(["point_id", "rep"], sort=True, observed=True)
    out = g.agg(iu=("iu", "first"), iv=("iv", "first"), u_mm=("u_mm", "first"),
                v_mm=("v_mm", "first"), peak_force_n=("force_n", "max"),
                peak_press_force_n=("press_force_n", "max"), max_depth_mm=("depth_mm", "max"),
                max_travel_mm=("travel_mm", "max"), poses=("step", "size"),
                any_contact=("contact", "any"))
    # the first pose in contact: where the press met the skin
    first = df[df["contact"]].groupby(["point_id", "rep"], sort=True, observed=True).first()
    for c, src in (("contact_travel_mm", "travel_mm"), ("skin_x_mm", "tip_x_mm"),
                   ("skin_y_mm", "tip_y_mm"), ("skin_z_mm", "tip_z_mm")):
        out[c] = first[src].reindex(out.index)
    return out.reset_index()


def point_table(df: pd.DataFrame) -> pd.DataFrame:
    """One row per grid point: peak force over its repetitions (mean, spread)."""
    presses = press_table(df)
    g = presses.groupby("point_id", sort=True)
    out = g.agg(iu=("iu", "first"), iv=("iv", "first"), u_mm=("u_mm", "first"),
                v_mm=("v_mm", "first"), peak_force_n=("peak_force_n", "mean"),
                peak_force_min_n=("peak_force_n", "min"), peak_force_max_n=("peak_force_n", "max"),
                max_depth_mm=("max_depth_mm", "mean"), contact_presses=("any_contact", "sum"),
                presses=("rep", "size"), skin_x_mm=("skin_x_mm", "mean"),
                skin_y_mm=("skin_y_mm", "mean"), skin_z_mm=("skin_z_mm", "mean"))
    return out.reset_index()


def _pct(a: np.ndarray, q: float) -> float:
    a = a[np.isfinite(a)]
    return float(np.percentile(a, q)) if a.size else float("nan")


def summarize(df: pd.DataFrame, plan_dict: dict[str, Any] | None = None,
              run: dict[str, Any] | None = None) -> dict[str, Any]:
    """The summary of a run: sizes, forces, contact, repeatability, timing, digest."""
    points = point_table(df)
    presses = press_table(df)
    no_contact = sorted(int(p) for p in presses.loc[~presses["any_contact"], "point_id"].unique())
    spread = (points["peak_force_max_n"] - points["peak_force_min_n"]).to_numpy()
    best = points.loc[points["peak_force_n"].idxmax()] if len(points) else None
    rtt = df["rtt_us"].to_numpy(dtype=float)
    svc = df["service_us"].to_numpy(dtype=float)
    summary: dict[str, Any] = {
        "plan": plan_dict,
        "points": int(len(points)),
        "presses": int(len(presses)),
        "poses": int(len(df)),
        "presses_without_contact": int((~presses["any_contact"]).sum()),
        "points_without_contact": no_contact,
        "force": {
            "max_force_n": float(df["force_n"].max()) if len(df) else float("nan"),
            "peak_force_n_mean": float(points["peak_force_n"].mean()),
            "peak_force_n_min": float(points["peak_force_n"].min()),
            "peak_force_n_max": float(points["peak_force_n"].max()),
            "max_force_out_of_contact_n": float(df.loc[~df["contact"], "force_n"].max())
            if (~df["contact"]).any() else 0.0,
            "strongest_point": None if best is None else {
                "point_id": int(best["point_id"]), "u_mm": float(best["u_mm"]),
                "v_mm": float(best["v_mm"]), "peak_force_n": float(best["peak_force_n"])},
        },
        "depth": {
            "max_depth_mm": float(df["depth_mm"].max()) if len(df) else float("nan"),
            "mean_max_depth_mm": float(presses["max_depth_mm"].mean()),
        },
        # repetitions of one point restart from a reset proxy: their peaks should agree
        "repeatability": {"max_peak_spread_n": float(spread.max()) if spread.size else 0.0},
        "timing": {
            "rtt_us_p50": _pct(rtt, 50), "rtt_us_p99": _pct(rtt, 99),
            "rtt_us_p999": _pct(rtt, 99.9), "rtt_us_max": float(np.nanmax(rtt)) if rtt.size else float("nan"),
            "service_us_p50": _pct(svc, 50), "service_us_p99": _pct(svc, 99),
        },
        "digest": result_digest(df),
        "per_point": points.to_dict(orient="records"),
    }
    if run:
        summary["run"] = run
    return summary


def format_summary(s: dict[str, Any]) -> str:
    """The summary as a few printed lines."""
    f, t = s["force"], s["timing"]
    name = (s.get("plan") or {}).get("name", "plan")
    run = s.get("run", {})
    lines = [
        f"plan {name!r}: {s['points']} points, {s['presses']} presses, {s['poses']} poses"
        + (f", {run['sessions']} sessions, {run['wall_s']:.1f} s ({run['poses_per_s']:.0f} poses/s)"
           if run else ""),
        f"peak force per point: mean {f['peak_force_n_mean']:.3f} N, "
        f"min {f['peak_force_n_min']:.3f} N, max {f['peak_force_n_max']:.3f} N; "
        f"largest force {f['max_force_n']:.3f} N",
        f"presses without contact: {s['presses_without_contact']}"
        + (f" (points {s['points_without_contact'][:10]})" if s["points_without_contact"] else ""),
        f"deepest {s['depth']['max_depth_mm']:.2f} mm under the skin; "
        f"force out of contact at most {f['max_force_out_of_contact_n']:.3g} N; "
        f"peak spread over repetitions {s['repeatability']['max_peak_spread_n']:.3g} N",
        f"round trip p50 {t['rtt_us_p50']:.0f} us, p99 {t['rtt_us_p99']:.0f} us; "
        f"server service p50 {t['service_us_p50']:.1f} us",
        f"result digest {s['digest'][:16]}",
    ]
    if f["strongest_point"]:
        sp = f["strongest_point"]
        lines.insert(2, f"strongest point {sp['point_id']} at u {sp['u_mm']:.1f} mm, "
                        f"v {sp['v_mm']:.1f} mm: {sp['peak_force_n']:.3f} N")
    return "\n".join(lines)
