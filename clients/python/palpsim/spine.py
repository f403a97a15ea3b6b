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
                  min_prominence: float, flat_tolerance: float = 1e-6,
                  flat_fraction: float = 0.0) -> list[Peak]:
    """Local maxima of a profile sampled at increasing, evenly spaced positions that stand
    out by at least `min_prominence` and lie at least `min_separation_mm` apart.

    A flat top (values within max(flat_tolerance, flat_fraction * prominence) of the
    peak's height, as where the force clamp holds, or where a mask's height is quantized
    to voxels) counts as one peak at the middle of the flat run."""
    position_mm = np.asarray(position_mm, dtype=float)
    value = np.asarray(value, dtype=float)
    if position_mm.size < 3:
        return []
    step = float(np.median(np.diff(position_mm)))
    distance = max(1, int(round(min_separation_mm / step)))
    # pad with the profile's minimum so that a peak at an end can count too
    pad = np.nanmin(value)
    clean = np.nan_to_num(value, nan=pad)
    padded = np.concatenate(([pad], clean, [pad]))
    idx, props = find_peaks(padded, distance=distance, prominence=min_prominence)
    peaks = []
    for i, prom in zip(idx - 1, props["prominences"]):
        # widen to the flat top around the peak: rounding noise on a clamped plateau
        # would otherwise put the peak at an arbitrary sample of it
        h = clean[i]
        tol = max(flat_tolerance, flat_fraction * prom)
        lo = hi = i
        while lo > 0 and clean[lo - 1] >= h - tol:
            lo -= 1
        while hi < clean.size - 1 and clean[hi + 1] >= h - tol:
            hi += 1
        peaks.append(Peak(position_mm=float(0.5 * (position_mm[lo] + position_mm[hi])),
                          height=float(h), prominence=float(prom)))
    return peaks


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
    """Finds the spinous processes under a line along z at x = x_mm: for each z slice of
    the mask the largest y of bone within |x - x_mm| <= band_mm, and the local maxima of
    that height along z, each at the middle of its highest voxels: where the bone comes
    closest to the back. Needs an axis-aligned grid (the prep grid is)."""
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
    # heights are quantized to voxels: equal heights (to half a voxel) around a peak are
    # its flat top, and the peak sits at the middle of it
    voxel_mm = float(abs(d[1, 1]))
    processes = profile_peaks(z, np.where(np.isnan(bone_y), np.nanmin(bone_y), bone_y),
                              min_separation_mm, min_prominence_mm,
                              flat_tolerance=0.5 * voxel_mm) if np.isfinite(bone_y).any() else []
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
