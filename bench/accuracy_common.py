"""What the accuracy report's sections share (bench/accuracy_report.py, bench/accuracy_elastic.py):
reading a bench run's JSON, the Pareto front, the fastest row within an error, number cells
and image lines."""
import json
import math
import os
import sys

# error thresholds (%) of the "fastest within" tables
THRESHOLDS = (1.0, 5.0, 10.0)


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


def image_lines(images):
    """Markdown lines showing each (title, path) image by its file name (the report lies beside them)."""
    L = []
    for title, path in images:
        L.append(f"![{title}]({os.path.basename(path)})")
        L.append("")
    return L
