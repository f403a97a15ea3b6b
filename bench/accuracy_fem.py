#!/usr/bin/env python3
"""Reference (c) of `palpsim-bench accuracy`: linear-elastic FEM of one press on a voxel VOI.

The VOI comes from the bench as BASE.json (size, grabbed voxel, its prescribed
displacement, material) and BASE.labels.u8 (one byte per voxel, i fastest:
0 air, 1 soft tissue, 2 bone). Nodes are the voxel centres (one node per ChainMail
element, so the fields compare voxel by voxel); trilinear hexahedra (scikit-fem's
ElementHex1) join 8 neighbouring centres and exist where none of the 8 is air, so the
skin is a traction-free surface. Boundary conditions: bone nodes held (u = 0, bone
rigid and fixed, as in the model), the grabbed node prescribed (the tip's
displacement), the VOI's outer faces held (u = 0, the model's own rule outside the
VOI). Homogeneous isotropic material: E only scales the reaction force, never the
displacement of a displacement-driven problem; nu shapes it. Solved by conjugate
gradients preconditioned by pyamg's smoothed aggregation with the rigid-body modes.

Writes BASE.u_fem.f32: 3 floats per voxel (voxel edge lengths, components x y z,
i fastest), NaN at nodes in no element (air). Displacements are in voxel units
throughout (the grid is isotropic, so linear elasticity is unchanged by the unit).

usage: accuracy_fem.py BASE     (reads BASE.json and BASE.labels.u8)
"""
import json
import sys
import time

import numpy as np
import pyamg
import scipy.sparse as sp
from skfem import Basis, ElementHex1, ElementVector, MeshHex, asm, condense
from skfem.models.elasticity import lame_parameters, linear_elasticity

# the 8 corners of a voxel-centre hexahedron in scikit-fem's MeshHex order (di, dj, dk)
HEX_CORNERS = [(0, 0, 0), (0, 1, 0), (1, 0, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 0, 1), (1, 1, 1)]


def voxel_stiffness(nu, e_kpa):
    """The 24 x 24 stiffness of one unit hexahedron (edge 1 voxel) from scikit-fem, rows and
    columns in the order (corner of HEX_CORNERS, component): 3 corner + component."""
    mesh = MeshHex.init_tensor(np.array([0.0, 1.0]), np.array([0.0, 1.0]), np.array([0.0, 1.0]))
    basis = Basis(mesh, ElementVector(ElementHex1()))
    k = asm(linear_elasticity(*lame_parameters(e_kpa, nu)), basis).toarray()
    order = []
    for corner in HEX_CORNERS:
        node = int(np.flatnonzero((mesh.p.T == np.array(corner, float)).all(axis=1))[0])
        order += [int(basis.nodal_dofs[c, node]) for c in range(3)]
    return k[np.ix_(order, order)]


def assemble_voxels(t, nodes, nu, e_kpa):
    """Global stiffness (CSR, dof 3 node + component) of hexahedra `t` (8, elements; corners in
    HEX_CORNERS order) on a unit voxel grid. Every element is the same unit cube, so scikit-fem
    computes one element matrix and this scatters it (assembling each element in Python would
    take minutes: scikit-fem loops over the 576 basis pairs for every element batch)."""
    ke = voxel_stiffness(nu, e_kpa)
    dofs = (3 * t[:, None, :] + np.arange(3)[None, :, None]).reshape(24, -1).astype(np.int32)  # (24, elements)
    rows = np.repeat(dofs, 24, axis=0).ravel()
    cols = np.tile(dofs, (24, 1)).ravel()
    data = np.repeat(ke.ravel(), t.shape[1])
    return sp.coo_matrix((data, (rows, cols)), shape=(3 * nodes, 3 * nodes)).tocsr()


def solve_press(labels, grabbed, grabbed_u, nu, e_kpa=10.0, tol=1e-8):
    """Displacement (voxel) at every voxel centre of `labels` (nx, ny, nz; 0 air, 1 soft, 2 bone).

    `grabbed` is the (i, j, k) of the node held at `grabbed_u` (voxel); bone and the
    outer faces are held at 0. Returns (u of shape (nx, ny, nz, 3) with NaN off the
    mesh, a dict of solve statistics)."""
    t0 = time.perf_counter()
    labels = np.asarray(labels)
    nx, ny, nz = labels.shape
    idx = np.arange(nx * ny * nz).reshape((nx, ny, nz), order="F")  # node n = i + nx (j + ny k)
    # hexahedra between voxel centres with no air corner
    solid = labels > 0
    keep = np.ones((nx - 1, ny - 1, nz - 1), bool)
    for di, dj, dk in HEX_CORNERS:
        keep &= solid[di:nx - 1 + di, dj:ny - 1 + dj, dk:nz - 1 + dk]
    t = np.stack([idx[di:nx - 1 + di, dj:ny - 1 + dj, dk:nz - 1 + dk][keep] for di, dj, dk in HEX_CORNERS])
    if t.shape[1] == 0:
        raise ValueError("accuracy_fem: no hexahedron without air in the VOI")
    # the mesh on the used nodes only (unused nodes would make the stiffness singular)
    used = np.unique(t)
    renum = -np.ones(nx * ny * nz, np.int64)
    renum[used] = np.arange(used.size)
    ii, jj, kk = np.unravel_index(used, (nx, ny, nz), order="F")
    K = assemble_voxels(renum[t], used.size, nu, e_kpa)
    t_asm = time.perf_counter() - t0
    # Dirichlet nodes: bone, the VOI's faces, the grabbed node
    gi, gj, gk = grabbed
    g = idx[gi, gj, gk]
    if renum[g] < 0:
        raise ValueError("accuracy_fem: the grabbed voxel is in no hexahedron (air around it)")
    face = (ii == 0) | (ii == nx - 1) | (jj == 0) | (jj == ny - 1) | (kk == 0) | (kk == nz - 1)
    held = (labels[ii, jj, kk] == 2) | face
    held[renum[g]] = True
    ndof = 3 * used.size
    x = np.zeros(ndof)
    nodal = np.arange(ndof).reshape((3, -1), order="F")  # the dof of component c at node n: 3 n + c
    x[nodal[:, renum[g]]] = grabbed_u
    D = nodal[:, held].ravel()
    A, b, _, I = condense(K, x=x, D=D)
    # smoothed aggregation with the rigid-body modes of the free nodes
    free_nodes = np.flatnonzero(~held)
    px, py, pz = ii[free_nodes].astype(float), jj[free_nodes].astype(float), kk[free_nodes].astype(float)
    one, zero = np.ones_like(px), np.zeros_like(px)
    modes = [(one, zero, zero), (zero, one, zero), (zero, zero, one),
             (-py, px, zero), (zero, -pz, py), (pz, zero, -px)]
    B = np.zeros((ndof, 6))
    for m, (bx, by, bz) in enumerate(modes):
        B[nodal[0, free_nodes], m], B[nodal[1, free_nodes], m], B[nodal[2, free_nodes], m] = bx, by, bz
    ml = pyamg.smoothed_aggregation_solver(A.tocsr(), B=B[I], max_coarse=500)
    residuals = []
    xi = ml.solve(b, tol=tol, accel="cg", maxiter=300, residuals=residuals)
    x[I] = xi
    rel = float(np.linalg.norm(b - A @ xi) / max(np.linalg.norm(b), 1e-300))
    u = np.full((nx * ny * nz, 3), np.nan)
    u[used] = x[nodal].T
    stats = {"nodes": int(used.size), "elements": int(t.shape[1]), "dofs_free": int(I.size),
             "iterations": len(residuals) - 1, "relative_residual": rel,
             "assemble_s": t_asm, "total_s": time.perf_counter() - t0}
    return u.reshape((nx, ny, nz, 3), order="F"), stats


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    base = sys.argv[1]
    with open(base + ".json") as f:
        h = json.load(f)
    nx, ny, nz = h["size"]
    labels = np.fromfile(base + ".labels.u8", np.uint8)
    if labels.size != nx * ny * nz:
        sys.exit(f"accuracy_fem: {base}.labels.u8 has {labels.size} bytes, expected {nx * ny * nz}")
    u, stats = solve_press(labels.reshape((nx, ny, nz), order="F"), h["grabbed"], h["grabbed_u"], h["nu"],
                           h.get("E_kpa", 10.0))
    u.reshape((-1, 3), order="F").astype(np.float32).tofile(base + ".u_fem.f32")
    with open(base + ".fem.json", "w") as f:
        json.dump(stats, f)
    print(f"accuracy_fem: {stats['nodes']} nodes, {stats['elements']} hexahedra, {stats['iterations']} CG "
          f"iterations, relative residual {stats['relative_residual']:.1e}, {stats['total_s']:.1f} s")


if __name__ == "__main__":
    main()
