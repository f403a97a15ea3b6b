"""The demo's analysis: NRRD reading, peaks of a profile, process tips from a bone mask,
and matching peaks to expected positions."""

from __future__ import annotations

import numpy as np
import pytest

from palpsim.nrrd import NrrdError, read_nrrd
from palpsim.spine import bone_profile, match_peaks, profile_peaks


def _write_nrrd(path, data_kji, origin, spacing, type_="uint8"):
    """Writes a NRRD the way palpsim-prep does (server/prep/outputs.cpp)."""
    nk, nj, ni = data_kji.shape
    header = (f"NRRD0004\n# written by palpsim-prep\ntype: {type_}\ndimension: 3\n"
              f"space: left-posterior-superior\nsizes: {ni} {nj} {nk}\n"
              f"space directions: ({spacing},0,0) (0,{spacing},0) (0,0,{spacing})\n"
              "kinds: domain domain domain\nendian: little\nencoding: raw\n"
              'space units: "mm" "mm" "mm"\n'
              f"space origin: ({origin[0]},{origin[1]},{origin[2]})\n\n")
    dtype = {"uint8": "u1", "float": "<f4"}[type_]
    path.write_bytes(header.encode() + np.ascontiguousarray(data_kji, dtype=dtype).tobytes())


def _spine(tmp_path):
    """A box body (y up to 40 mm) and bone whose top rises to y = 30 mm at z = -40, 0, 40
    (spinous process tips, 6 mm wide along z) and sits at y = 20 mm elsewhere; 1 mm voxels."""
    origin = (-20.0, -10.0, -60.0)
    xs, ys, zs = (np.arange(41) - 20.0, np.arange(61) - 10.0, np.arange(121) - 60.0)
    Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
    body = (Y <= 40).astype(np.uint8)
    tips = np.zeros_like(Z, dtype=bool)
    for zt in (-40.0, 0.0, 40.0):
        tips |= (np.abs(Z - zt) <= 3) & (np.abs(X) <= 2) & (Y <= 30)
    bone = ((Y <= 20) | tips).astype(np.uint8)
    _write_nrrd(tmp_path / "bone.nrrd", bone, origin, 1.0)
    _write_nrrd(tmp_path / "body.nrrd", body, origin, 1.0)
    return read_nrrd(tmp_path / "bone.nrrd"), read_nrrd(tmp_path / "body.nrrd")


def test_nrrd_reads_geometry_and_voxels(tmp_path):
    bone, body = _spine(tmp_path)
    assert bone.data.shape == (121, 61, 41)
    np.testing.assert_allclose(bone.to_physical([0, 0, 0]), [-20, -10, -60])
    np.testing.assert_allclose(bone.to_index([0.0, 30.0, 0.0]), [20, 40, 60])
    assert bone.data[60, 40, 20] == 1 and bone.data[60, 41, 20] == 0  # the middle tip's top


def test_nrrd_errors_name_file_and_field(tmp_path):
    p = tmp_path / "x.nrrd"
    p.write_bytes(b"NRRD0004\ntype: float\ndimension: 2\nsizes: 2 2\n\n" + b"\0" * 16)
    with pytest.raises(NrrdError, match=r"x\.nrrd: dimension"):
        read_nrrd(p)
    _write_nrrd(p, np.zeros((2, 2, 2)), (0, 0, 0), 1.0, "float")
    p.write_bytes(p.read_bytes()[:-4])
    with pytest.raises(NrrdError, match=r"x\.nrrd: truncated"):
        read_nrrd(p)


def test_bone_profile_finds_the_process_tips(tmp_path):
    bone, body = _spine(tmp_path)
    bp = bone_profile(bone, body, x_mm=0.0, band_mm=3.0, z_from_mm=-55, z_to_mm=55)
    assert [p.position_mm for p in bp.processes] == pytest.approx([-40, 0, 40], abs=3.0)
    assert np.nanmax(bp.bone_top_y_mm) == 30 and np.nanmin(bp.bone_top_y_mm) == 20
    assert np.all(bp.skin_top_y_mm == 40)
    # away from the midline band there are no tips
    far = bone_profile(bone, body, x_mm=15.0, band_mm=3.0, z_from_mm=-55, z_to_mm=55)
    assert far.processes == []


def test_profile_peaks_respect_prominence_and_separation():
    z = np.arange(-60, 61, 2.0)
    f = 1.0 + np.exp(-0.5 * ((z + 40) / 4) ** 2) + 0.5 * np.exp(-0.5 * ((z - 30) / 4) ** 2)
    f += 0.01 * np.cos(z)  # ripples far below the prominence threshold
    peaks = profile_peaks(z, f, min_separation_mm=15, min_prominence=0.2)
    assert [p.position_mm for p in peaks] == [-40, 30]
    assert peaks[0].prominence == pytest.approx(1.0, abs=0.05)
    # a higher threshold drops the smaller peak
    assert [p.position_mm for p in profile_peaks(z, f, 15, 0.7)] == [-40]
    # a monotonic profile's end counts as a peak only if it stands out from the padding
    assert profile_peaks(z, np.zeros_like(z), 15, 0.1) == []


def test_match_pairs_nearest_within_tolerance():
    m = match_peaks([-39.0, 2.0, 70.0], [-40.0, 0.0, 40.0], tolerance_mm=6.0)
    assert [(x.expected_mm, x.found_mm) for x in m] == [(-40.0, -39.0), (0.0, 2.0), (40.0, None)]
    assert m[0].error_mm == pytest.approx(1.0) and m[2].error_mm is None
    # one found peak never serves two expected positions
    m = match_peaks([0.0], [-2.0, 1.0], tolerance_mm=6.0)
    assert [x.found_mm for x in m] == [None, 0.0]


def test_a_flat_top_is_one_peak_at_its_middle():
    z = np.arange(0, 61, 2.0)
    f = np.minimum(3.0 * np.exp(-0.5 * ((z - 30) / 8) ** 2), 2.5)
    f[13] += 1e-12  # rounding noise on the clamped plateau
    peaks = profile_peaks(z, f, min_separation_mm=15, min_prominence=0.1)
    plateau = z[f >= 2.5 - 1e-9]
    assert len(peaks) == 1
    assert peaks[0].position_mm == pytest.approx(0.5 * (plateau[0] + plateau[-1]))
