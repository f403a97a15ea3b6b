"""Reading a force profile along the back: peaks (the spinous processes), where the
patient's own bone mask says the processes are, and how the two match.

Positions along the line are in mm along its axis (LPS z, superior positive, for the
demo's line along the spine)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import find_peaks

from .nrrd import NrrdVolume


@dataclass(frozen=True)
class Peak:
    """A local maximum of a profile."""

    position_mm: float
    height: float
    prominence: float


def profile_peaks(position_mm: np.ndarray, value: np.ndarray, min_separation_mm: float,
                  min_prominence: float) -> list[Peak]:
    """Local maxima of a profile sampled at increasing, evenly spaced positions that stand
    out by at least `min_prominence` and lie at least `min_separation_mm` apart."""
    position_mm = np.asarray(position_mm, dtype=float)
    value = np.asarray(value, dtype=float)
    if position_mm.size < 3:
        return []
    step = float(np.median(np.diff(position_mm)))
    distance = max(1, int(round(min_separation_mm / step)))
    # pad with the profile's minimum so that a peak at an end can count too
    pad = np.nanmin(value)
    padded = np.concatenate(([pad], np.nan_to_num(value, nan=pad), [pad]))
    idx, props = find_peaks(padded, distance=distance, prominence=min_prominence)
    return [Peak(position_mm=float(position_mm[i - 1]), height=float(value[i - 1]),
                 prominence=float(p)) for i, p in zip(idx, props["prominences"])]


@dataclass(frozen=True)
class BoneProfile:
    """The most posterior bone (and skin) along a line of constant x in the patient."""

    z_mm: np.ndarray            # positions along the line
    bone_top_y_mm: np.ndarray   # largest y of bone at each z within the band (nan: none)
    skin_top_y_mm: np.ndarray   # largest y of the body at each z within the band (nan: none)
    processes: list[Peak]       # local maxima of bone_top_y: the spinous process tips


def bone_profile(bone: NrrdVolume, body: NrrdVolume | None, x_mm: float, band_mm: float,
                 z_from_mm: float, z_to_mm: float, min_separation_mm: float = 15.0,
                 min_prominence_mm: float = 3.0) -> BoneProfile:
    """Finds the spinous process tips under a line along z at x = x_mm: for each z slice
    of the mask the largest y of bone within |x - x_mm| <= band_mm, and the local maxima
    of that height along z. Needs an axis-aligned grid (the prep grid is)."""
    d = bone.directions
    if not np.allclose(d, np.diag(np.diag(d))):
        raise ValueError("bone_profile: the mask's grid is not axis-aligned")
    i = np.arange(bone.data.shape[2])
    j = np.arange(bone.data.shape[1])
    k = np.arange(bone.data.shape[0])
    xs = bone.origin_mm[0] + d[0, 0] * i
    ys = bone.origin_mm[1] + d[1, 1] * j
    zs = bone.origin_mm[2] + d[2, 2] * k
    cols = np.abs(xs - x_mm) <= band_mm
    rows = (zs >= min(z_from_mm, z_to_mm)) & (zs <= max(z_from_mm, z_to_mm))
    order = np.argsort(zs[rows])

    def top_y(vol: NrrdVolume) -> np.ndarray:
        m = vol.data[rows][:, :, cols] > 0          # (z, y, x-band)
        any_y = m.any(axis=2)                        # (z, y)
        y_or_nan = np.where(any_y, ys[None, :], -np.inf).max(axis=1)
        return np.where(np.isfinite(y_or_nan), y_or_nan, np.nan)[order]

    z = zs[rows][order]
    bone_y = top_y(bone)
    skin_y = top_y(body) if body is not None else np.full_like(z, np.nan)
    processes = profile_peaks(z, np.where(np.isnan(bone_y), np.nanmin(bone_y), bone_y),
                              min_separation_mm, min_prominence_mm) if np.isfinite(bone_y).any() else []
    return BoneProfile(z_mm=z, bone_top_y_mm=bone_y, skin_top_y_mm=skin_y, processes=processes)


@dataclass(frozen=True)
class Match:
    """An expected position and the found peak nearest to it (None: none within tolerance)."""

    expected_mm: float
    found_mm: float | None

    @property
    def error_mm(self) -> float | None:
        return None if self.found_mm is None else self.found_mm - self.expected_mm


def match_peaks(found_mm: list[float], expected_mm: list[float], tolerance_mm: float) -> list[Match]:
    """Pairs each expected position with a distinct found peak within tolerance, closest
    pairs first (greedy; fine for peaks much farther apart than the tolerance)."""
    pairs = sorted((abs(f - e), ei, fi) for ei, e in enumerate(expected_mm)
                   for fi, f in enumerate(found_mm) if abs(f - e) <= tolerance_mm)
    used_e: dict[int, int] = {}
    used_f: set[int] = set()
    for _, ei, fi in pairs:
        if ei not in used_e and fi not in used_f:
            used_e[ei] = fi
            used_f.add(fi)
    return [Match(expected_mm=e, found_mm=found_mm[used_e[ei]] if ei in used_e else None)
            for ei, e in enumerate(expected_mm)]
