"""bench/accuracy_fem.py (reference (c) of `palpsim-bench accuracy`) on analytic cases."""

import os
import sys

import numpy as np
import pytest

pytest.importorskip("skfem")  # scripts/requirements.txt installs it; a bare venv skips instead of failing to import
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "..", "bench"))
import accuracy_fem as fem  # noqa: E402
from skfem import condense  # noqa: E402

import pyamg  # noqa: E402,F401


def test_uniaxial_compression_of_a_block_matches_the_closed_form():
    # a 5 x 6 x 7 voxel block: bottom face z = 0 held along z, top face pressed by -d
    # along z, sides free, one corner pinned in x and y against rigid motion and the
    # neighbouring corner in x: the exact field u_z = -d z / H, u_x = nu d x / H,
    # u_y = nu d y / H is trilinear, which Q1 hexahedra reproduce exactly
    nx, ny, nz, nu, d = 5, 6, 7, 0.3, 0.6
    idx = np.arange(nx * ny * nz).reshape((nx, ny, nz), order="F")
    t = np.stack([idx[di:nx - 1 + di, dj:ny - 1 + dj, dk:nz - 1 + dk].ravel() for di, dj, dk in fem.HEX_CORNERS])
    K = fem.assemble_voxels(t, nx * ny * nz, nu, 10.0)
    H = nz - 1
    x = np.zeros(3 * nx * ny * nz)
    D = list(3 * idx[:, :, 0].ravel() + 2) + list(3 * idx[:, :, -1].ravel() + 2)
    x[3 * idx[:, :, -1].ravel() + 2] = -d
    D += [3 * idx[0, 0, 0], 3 * idx[0, 0, 0] + 1, 3 * idx[0, 1, 0]]  # pin: x, y at the origin, x at (0, 1, 0)
    u = fem_solve(K, x, np.array(D))
    i, j, k = np.unravel_index(np.arange(nx * ny * nz), (nx, ny, nz), order="F")
    # solved directly (spsolve): the only error is rounding, 1e-9 voxel is far above it
    np.testing.assert_allclose(u[2::3], -d * k / H, atol=1e-9)
    np.testing.assert_allclose(u[0::3], nu * d * i / H, atol=1e-9)
    np.testing.assert_allclose(u[1::3], nu * d * j / H, atol=1e-9)


def fem_solve(K, x, D):
    """K u = 0 with u = x on dofs D, solved directly."""
    import scipy.sparse.linalg as spla
    A, b, _, I = condense(K, x=x, D=D)
    out = x.copy()
    out[I] = spla.spsolve(A.tocsc(), b)
    return out


def test_press_holds_bone_and_faces_and_moves_the_grabbed_node():
    # 9^3 voxels, air on the top two layers, a bone voxel under the grabbed one
    lab = np.ones((9, 9, 9), np.uint8)
    lab[:, :, 7:] = 0
    lab[4, 4, 2] = 2
    u, stats = fem.solve_press(lab, (4, 4, 6), (0.0, 0.0, -1.0), 0.45)
    assert np.allclose(u[4, 4, 6], [0, 0, -1])
    assert np.allclose(u[4, 4, 2], 0) and np.allclose(u[0, 4, 4], 0)  # bone, a face
    assert np.isnan(u[4, 4, 8]).all()  # air: no element
    # the CG tolerance (1e-8 relative) bounds the residual the solver reports
    assert stats["relative_residual"] < 1e-7
    # the press pushes the soft node below the grabbed one down, less than the grabbed node
    assert -1 < u[4, 4, 5, 2] < 0
