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


# ---- the elastic model's references ----------------------------------------------------------

def _explicit_element(h, nu, full=False):
    """The selective-reduced-integration cell matrix by hand: shape-function gradients at the
    2x2x2 Gauss points for the mu part and at the centre (or the Gauss points) for the lambda
    part, corners in MODEL_CORNERS order; E = 1 kPa = 1e-3 N/mm^2."""
    e = 1e-3
    lam, mu = e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))
    vol = h[0] * h[1] * h[2]

    def grads(t):
        g = np.zeros((8, 3))
        for c, off in enumerate(fem.MODEL_CORNERS):
            lin = [t[a] if off[a] else 1 - t[a] for a in range(3)]
            dl = [1.0 if off[a] else -1.0 for a in range(3)]
            g[c] = [dl[0] * lin[1] * lin[2] / h[0], lin[0] * dl[1] * lin[2] / h[1], lin[0] * lin[1] * dl[2] / h[2]]
        return g

    gp = [0.5 - 0.5 / np.sqrt(3), 0.5 + 0.5 / np.sqrt(3)]
    gauss = [(gp[q & 1], gp[(q >> 1) & 1], gp[(q >> 2) & 1]) for q in range(8)]
    k = np.zeros((24, 24))
    for t in gauss:
        g = grads(t)
        for a in range(8):
            for b in range(8):
                k[3 * a:3 * a + 3, 3 * b:3 * b + 3] += vol / 8 * mu * (np.eye(3) * (g[a] @ g[b]) + np.outer(g[b], g[a]))
    for t, w in ([(tt, vol / 8) for tt in gauss] if full else [((0.5, 0.5, 0.5), vol)]):
        g = grads(t)
        for a in range(8):
            for b in range(8):
                k[3 * a:3 * a + 3, 3 * b:3 * b + 3] += w * lam * np.outer(g[a], g[b])
    return k


@pytest.mark.parametrize("full", [False, True])
def test_scikit_fem_element_is_the_models_selective_reduced_integration(full):
    # scikit-fem's element (intorder per form) against the rule integrated by hand, on a box of
    # three different edges at nu 0.49: the same to rounding (1e-12 of the largest entry)
    h, nu = (0.7, 1.3, 2.5), 0.49
    k = fem.sri_element(h, nu, full=full)
    ref = _explicit_element(h, nu, full=full)
    assert np.abs(k - ref).max() <= 1e-12 * np.abs(ref).max()


def test_reduced_element_has_the_rigid_modes_only_and_does_not_lock():
    # six zero eigenvalues (rigid motions), 18 positive (no hourglass: the mu part is fully
    # integrated); a uniform volume change of the cell costs lambda at one point, a bending mode
    # (u_x = x y) costs no volume term at the centre, where the full element charges lambda for
    # it: at nu 0.49 (lambda = 49 mu) the fully integrated cell is far stiffer in bending
    k = fem.sri_element((1.0, 1.0, 1.0), 0.49)
    ev = np.linalg.eigvalsh(k)
    assert np.all(np.abs(ev[:6]) <= 1e-12 * ev[-1]) and ev[6] > 1e-4 * ev[-1]
    bend = np.zeros(24)
    for c, (i, j, _) in enumerate(fem.MODEL_CORNERS):
        bend[3 * c] = (i - 0.5) * (j - 0.5)
    full = fem.sri_element((1.0, 1.0, 1.0), 0.49, full=True)
    assert bend @ full @ bend > 10 * (bend @ k @ bend)


def _tensor_grid():
    # a graded tensor grid of 5 x 4 x 6 nodes with two moduli
    xs, ys, zs = np.array([0, 0.5, 1.5, 2, 4.0]), np.array([0, 1, 1.25, 3.0]), np.array([0, 1, 2, 2.5, 3, 5.0])
    cell_e = np.full((4, 3, 5), 10.0)
    cell_e[2:, :, 3:] = 35.0
    return xs, ys, zs, cell_e


def test_grid_assembly_holds_a_uniform_strain():
    # a linear field is in the trilinear space, so K u is zero at every node inside the grid (the
    # patch test of the scatter: node numbering, corner order, spacing per axis, per-cell moduli)
    xs, ys, zs, cell_e = _tensor_grid()
    K = fem.assemble_grid(xs, ys, zs, cell_e, 0.45)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    pos = np.stack([X.ravel(order="F"), Y.ravel(order="F"), Z.ravel(order="F")], axis=1)
    G = np.array([[0.01, 0.004, -0.003], [0.002, -0.008, 0.005], [-0.001, 0.006, 0.012]])
    f = (K @ (pos @ G.T).ravel()).reshape(-1, 3)
    # nodes inside the grid whose eight cells share one modulus (at the interface the stress jumps)
    padded = np.pad(cell_e, 1, constant_values=np.nan)
    around = np.stack([padded[a:a + 5, b:b + 4, c:c + 6] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    one_material = (np.nanmin(around, axis=0) == np.nanmax(around, axis=0)) & ~np.isnan(around).any(axis=0)
    inside = one_material.ravel(order="F")
    assert inside.sum() == 18  # 24 inside, 6 where the 35 kPa block meets the rest
    assert np.abs(f[inside]).max() <= 1e-12 * np.abs(f).max()
    assert np.abs(f[~inside]).max() > 1e-6  # the boundary and the interface carry forces


def _column(nu):
    # a column of 3 x 3 cells of 1 mm and 6 high on a held base (u_z = 0, one corner pinned), its
    # top layer the skin pushed d along -z by a flat platen (every skin node's push is d)
    xs, zs = np.arange(4.0), np.arange(7.0)
    K = fem.assemble_grid(xs, xs, zs, np.full((3, 3, 6), 10.0), nu)
    X, Y, Z = np.meshgrid(xs, xs, zs, indexing="ij")
    pos = np.stack([X.ravel(order="F"), Y.ravel(order="F"), Z.ravel(order="F")], axis=1)
    fixed = np.zeros((len(pos), 3), bool)
    fixed[pos[:, 2] == 0, 2] = True
    fixed[(pos[:, 2] == 0) & (pos[:, 0] == 0) & (pos[:, 1] == 0), :2] = True
    fixed[(pos[:, 2] == 0) & (pos[:, 0] == 3) & (pos[:, 1] == 0), 1] = True
    skin = pos[:, 2] == 6
    d = 0.3
    push = np.where(skin, d, -1.0)
    return K, pos, fixed, skin, push, d


def test_a_platen_on_a_column_gives_e_a_d_over_l_on_both_contact_paths():
    # nu 0: uniaxial, F = E A d / L exactly (A 9 mm^2, L 6 mm, E 10 kPa); the contact as a
    # constrained z component and in the rotated frame (n, t1, t2) give the same field (1e-8 mm:
    # two CG solves to 1e-9)
    K, pos, fixed, skin, push, d = _column(0.0)
    u_axis, c_axis, s_axis = fem.solve_contact(K, pos, fixed, skin, push, np.array([0, 0, -1.0]), 1e-4)
    u_rot, c_rot, s_rot = fem.solve_contact(K, pos, fixed, skin, push, np.array([0, 0, -1.0]), 1e-4, rotate=True)
    expect = 10e-3 * 9 * d / 6
    assert s_axis["settled"] and c_axis.sum() == 16 and (c_axis == c_rot).all()
    assert s_axis["press_n"] == pytest.approx(expect, rel=1e-8)
    assert s_rot["press_n"] == pytest.approx(expect, rel=1e-8)
    assert np.abs(u_axis - u_rot).max() < 1e-8
    # the force on the sphere points back out of the column (+z)
    assert s_axis["force_n"][2] == pytest.approx(expect, rel=1e-8)


def test_contact_rounds_release_nodes_the_sphere_would_pull():
    # a sphere pressed into the middle of a slab's skin: from rest every skin node under the sphere
    # is in contact; those at the rim end up pulled (the tissue around the dent sinks less than the
    # sphere's edge) and leave. At the end every contact node pushes on the sphere and no free
    # node lies inside it (to the margin)
    n = 11
    xs = np.arange(float(n))
    K = fem.assemble_grid(xs, xs, xs, np.full((n - 1,) * 3, 10.0), 0.45)
    X, Y, Z = np.meshgrid(xs, xs, xs, indexing="ij")
    pos = np.stack([X.ravel(order="F"), Y.ravel(order="F"), Z.ravel(order="F")], axis=1)
    fixed = np.zeros((len(pos), 3), bool)
    face = (pos == 0).any(axis=1) | (pos[:, :2] == n - 1).any(axis=1)
    fixed[face] = True
    skin = (pos[:, 2] == n - 1) & ~face
    nrm = np.array([0, 0, -1.0])
    R, d = 4.0, 1.2
    push = np.where(skin, fem.sphere_push(pos, np.array([5, 5, n - 1 - d + R]), nrm, R), -1.0)
    u, contact, s = fem.solve_contact(K, pos, fixed, skin, push, nrm, 1e-4)
    assert s["settled"] and s["rounds"] >= 2
    assert contact.sum() < (skin & (push > 0)).sum()  # some rim nodes left
    fn = (K @ u.ravel()).reshape(-1, 3) @ nrm
    assert (fn[contact] >= 0).all()
    np.testing.assert_allclose(u[contact] @ nrm, push[contact], atol=1e-12)
    free = skin & ~contact & (push > 0)
    assert (push[free] - u[free] @ nrm <= 1e-4).all()


def test_hertz_surface_profile_is_continuous_and_meets_the_force():
    R, d = 8.0, 1.6
    a = np.sqrt(R * d)
    # continuous at the contact radius: both branches give a^2 / 2R there
    inside = fem.hertz_surface(np.array([a * (1 - 1e-9)]), R, d)[0]
    outside = fem.hertz_surface(np.array([a * (1 + 1e-9)]), R, d)[0]
    assert inside == pytest.approx(a * a / (2 * R), rel=1e-6) and outside == pytest.approx(inside, rel=1e-6)
    assert fem.hertz_surface(np.array([0.0]), R, d)[0] == d
    # far out the dent decays like a point load's, 4 a^3 / (3 pi R r)
    r = 200 * a
    assert fem.hertz_surface(np.array([r]), R, d)[0] == pytest.approx(4 * a ** 3 / (3 * np.pi * R * r), rel=1e-3)
    # 4/3 E* sqrt(R) d^1.5: E = 10 kPa, nu 0.5 gives E* = 13.33 kPa
    assert fem.hertz_force(10, 0.5, 4, 1) == pytest.approx(4 / 3 * 10e-3 / 0.75 * 2)
    # the profile error of Hertz's own profile is 0, of twice it 100 %
    rr = np.linspace(0, 4 * a, 41)
    assert fem.profile_error_pct(rr, fem.hertz_surface(rr, R, d), R, d) == pytest.approx(0, abs=1e-12)
    assert fem.profile_error_pct(rr, 2 * fem.hertz_surface(rr, R, d), R, d) == pytest.approx(100)


def _export(tmp_path, body, bone, hu, depth, tip, normal, radius, nu=0.45):
    """Writes a VOI as the bench exports it (BASE.json and its arrays) and returns BASE."""
    import json
    nx, ny, nz = hu.shape
    base = str(tmp_path / "case")
    with open(base + ".json", "w") as f:
        json.dump({"size": [nx, ny, nz], "spacing_mm": [1.0, 1.0, 1.0], "nu": nu,
                   "material": {"table_hu": [-900, -200, -50, 20], "table_e_kpa": [1.0, 3.25, 3.25, 12.0],
                                "skin_e_kpa": 35.0, "skin_mm": 2.0, "air_e_kpa": 1e-4},
                   "tip_mm": list(tip), "normal": list(normal), "radius_mm": radius,
                   "element": list(fem.sri_element((1.0, 1.0, 1.0), nu).astype(np.float32).ravel().astype(float))}, f)
    hu.ravel(order="F").astype(np.float32).tofile(base + ".hu.f32")
    depth.ravel(order="F").astype(np.float32).tofile(base + ".depth.f32")
    bone.ravel(order="F").astype(np.uint8).tofile(base + ".bone.u8")
    body.ravel(order="F").astype(np.uint8).tofile(base + ".body.u8")
    return base


def test_an_exported_voi_gets_the_models_moduli_held_nodes_and_contact(tmp_path):
    # 12^3 nodes: tissue (40 HU) below the skin layer j = 8, air above, a bone node under the
    # press; a sphere of 3 mm pressed 1 mm at (6, 8, 6) along -y. The body array has one node
    # more on every side (air beyond the VOI)
    n, top = 12, 8
    body = np.zeros((n + 2,) * 3, bool)
    body[1:-1, 1:top + 2, 1:-1] = True
    hu = np.where(body[1:-1, 1:-1, 1:-1], 40.0, -1000.0)
    depth = np.where(body[1:-1, 1:-1, 1:-1], (top + 1 - np.arange(n))[None, :, None] * 1.0, 0.0)
    bone = np.zeros((n,) * 3, bool)
    bone[6, 3, 6] = True
    base = _export(tmp_path, body, bone, hu, depth, (6.0, top - 1.0, 6.0), (0.0, -1.0, 0.0), 3.0)
    u, contact, s = fem.contact_case(base)
    # the same cell matrix as the model's (its float copy): to float rounding
    assert s["element_max_rel_diff"] < 1e-6
    assert s["settled"] and s["contact_nodes"] > 0
    assert np.abs(u[6, 3, 6]).max() == 0 and np.abs(u[0]).max() == 0 and np.abs(u[:, -1]).max() == 0  # bone, faces
    # the contact lies on the skin layer under the tip and follows the sphere: 1 mm at the axis
    assert contact[:, top, :].sum() == contact.sum() and contact[6, top, 6]
    assert u[6, top, 6, 1] == pytest.approx(-1.0, abs=1e-9)
    # the force pushes the finger back out (+y); the cells with an air corner are the gel, so the
    # tissue ends at the skin nodes and the air above moves with far less force than the tissue
    assert s["force_n"][1] > 0 and s["cells_tissue"] == (n - 1) ** 2 * top
