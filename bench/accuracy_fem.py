#!/usr/bin/env python3
"""The FEM references of `palpsim-bench accuracy`: reference (c) and the elastic model's.

Reference (c), linear-elastic FEM of one ChainMail press on a voxel VOI: the VOI comes from the bench as BASE.json (size, grabbed voxel, its prescribed
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

The elastic model's references (the same FEM as deform.relax_method "elastic", so that the
model can be verified and its discretisation measured; server/deform/elastic_math.h says
what it solves): `solve_contact` solves static linear elasticity on a tensor grid of
trilinear hexahedra with per-cell moduli, selective reduced integration (`sri_element`:
the mu part with 2x2x2 Gauss points, the lambda part at the cell centre, as
elastic_element() builds it; intorder per form), fixed components and a rigid sphere
pressed along a unit n: skin nodes under the sphere lie on it along n and slide across n
without friction, round by round (nodes the sphere pulls leave, nodes pushed into it
join) until no node changes. `contact_case` builds that problem from a VOI the bench
exports (the model's rules for cell moduli, held nodes, skin nodes and the sphere's push
re-implemented here), and `hertz_case` a quarter of a large block on a graded mesh for
Hertz's sphere (symmetry planes, far faces held).

usage: accuracy_fem.py BASE                 reference (c): reads BASE.json and BASE.labels.u8
       accuracy_fem.py contact BASE         the model's problem on a VOI: reads BASE.json, BASE.*.f32/u8,
                                            writes BASE.u_fem.f32 (mm, 3 per node, i fastest) and BASE.fem.json
       accuracy_fem.py hertz OUT.json --radius R --depth D --nu NU [--full] [--h0 H] [--extent L]
"""
import json
import sys
import time

import argparse
import math

import numpy as np
import pyamg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from skfem import Basis, BilinearForm, ElementHex1, ElementQuad1, ElementVector, MeshHex, MeshQuad, asm, condense
from skfem.helpers import ddot, div, sym_grad
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



# ---- the elastic model's references -------------------------------------------------

# corner c of a cell in the elastic model's order (elastic_corner(): bit 0 +i, bit 1 +j, bit 2 +k)
MODEL_CORNERS = [(c & 1, (c >> 1) & 1, (c >> 2) & 1) for c in range(8)]

# a free skin node joins the contact when the sphere lies deeper than it by more than this
# (voxel edges along the grid's first axis): the model's kElasticPenetrationVox
PENETRATION_VOX = 1e-4

# relative residual every FEM solve reaches (the model's float fields round at about 1e-7)
FEM_TOL = 1e-9

# MeshHex's corner order of a cell (init_tensor's on one box), as offsets (di, dj, dk)
_MESHHEX_CORNERS = [(0, 0, 0), (0, 1, 0), (1, 0, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1), (1, 0, 1), (1, 1, 1)]


def sri_elements(boxes, nu, full=False):
    """The 24 x 24 stiffness (N/mm) of box cells with edges boxes[m] (mm) for E = 1 kPa
    (1e-3 N/mm^2), shape (m, 24, 24), rows and columns 3 corner + component in MODEL_CORNERS
    order. Selective reduced integration as elastic_element() builds it: the mu part
    2 mu eps(u) : eps(v) with 2x2x2 Gauss points (scikit-fem intorder 3), the lambda part
    lambda div u div v at the cell centre (a one-point rule: scikit-fem raises intorder 0 or 1 on
    hexahedra to two points per axis, so the rule is given). full=True integrates both parts
    with 2x2x2 points: the fully integrated trilinear element, which locks as nu nears 1/2.
    scikit-fem assembles all boxes at once as cells of one mesh that share no node."""
    boxes = np.asarray(boxes, float).reshape(-1, 3)
    m = len(boxes)
    corners = np.array(MODEL_CORNERS, float)
    p = (boxes[:, None, :] * corners[None, :, :]).reshape(-1, 3).T
    t = np.arange(m)[None, :] * 8 + np.array([MODEL_CORNERS.index(c) for c in _MESHHEX_CORNERS])[:, None]
    mesh = MeshHex(p, t)
    e = 1e-3
    lam, mu = e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))
    elem = ElementVector(ElementHex1())
    gauss = Basis(mesh, elem, intorder=3)
    centre = gauss if full else Basis(mesh, elem, quadrature=(np.full((3, 1), 0.5), np.ones(1)))
    K = (asm(BilinearForm(lambda u, v, w: 2 * mu * ddot(sym_grad(u), sym_grad(v))), gauss) +
         asm(BilinearForm(lambda u, v, w: lam * div(u) * div(v)), centre)).tocoo()
    # every dof's box and place (3 corner + component) in it; node 8 b + corner is corner of box b
    owner = np.empty(3 * 8 * m, np.int64)
    place = np.empty(3 * 8 * m, np.int64)
    for comp in range(3):
        dof = gauss.nodal_dofs[comp]
        owner[dof] = np.arange(8 * m) // 8
        place[dof] = 3 * (np.arange(8 * m) % 8) + comp
    out = np.zeros((m, 24, 24))
    np.add.at(out, (owner[K.row], place[K.row], place[K.col]), K.data)
    return out


def sri_element(h, nu, full=False):
    """sri_elements() of one box with edges h (mm)."""
    return sri_elements([h], nu, full)[0]


def _unique_spacing(h):
    """The distinct spacings of one axis (to 1e-9 mm: arange's rounding) and each cell's index into them."""
    return np.unique(np.round(h, 9), return_inverse=True)


def assemble_grid(xs, ys, zs, cell_e, nu, full=False, chunk=16384):
    """The stiffness (CSR, N/mm) of the cells of a tensor grid with node coordinates xs, ys, zs (mm):
    node n = i + nx (j + ny k), dof 3 n + component; cell (ci, cj, ck) between nodes (ci..ci+1, ...)
    has Young's modulus cell_e[ci, cj, ck] (kPa; 0: no cell). One sri_element per distinct box,
    scattered cell by cell in chunks (a VOI of 64^3 nodes has 250000 cells, 144 M entries)."""
    nx, ny, nz = len(xs), len(ys), len(zs)
    ux, ix = _unique_spacing(np.diff(xs))
    uy, iy = _unique_spacing(np.diff(ys))
    uz, iz = _unique_spacing(np.diff(zs))
    ci, cj, ck = np.nonzero(cell_e > 0)
    e = cell_e[ci, cj, ck].astype(float)
    keys = (ix[ci] * len(uy) + iy[cj]) * len(uz) + iz[ck]
    ukeys, kinv = np.unique(keys, return_inverse=True)
    ke = sri_elements([(ux[q // (len(uy) * len(uz))], uy[(q // len(uz)) % len(uy)], uz[q % len(uz)]) for q in ukeys],
                      nu, full)
    off = np.array([ox + nx * (oy + ny * oz) for ox, oy, oz in MODEL_CORNERS], np.int64)
    base = ci + nx * (cj + ny * ck).astype(np.int64)
    n3 = 3 * nx * ny * nz
    K = sp.csr_matrix((n3, n3))
    for s0 in range(0, len(base), chunk):
        b = base[s0:s0 + chunk]
        m = len(b)
        dofs = (3 * (b[:, None] + off[None, :])[:, :, None] + np.arange(3)).reshape(m, 24).astype(np.int32)
        data = ke[kinv[s0:s0 + chunk]] * e[s0:s0 + chunk, None, None]
        rows = np.repeat(dofs, 24, axis=1).ravel()
        cols = np.tile(dofs, (1, 24)).ravel()
        K = K + sp.coo_matrix((data.ravel(), (rows, cols)), shape=(n3, n3)).tocsr()
    return K


def rigid_modes(pos):
    """The six rigid-body modes (3 N x 6) at node positions pos (N x 3, mm), about their centre."""
    x = pos - pos.mean(axis=0)
    one, zero = np.ones(len(x)), np.zeros(len(x))
    modes = [(one, zero, zero), (zero, one, zero), (zero, zero, one),
             (-x[:, 1], x[:, 0], zero), (zero, -x[:, 2], x[:, 1]), (x[:, 2], zero, -x[:, 0])]
    return np.stack([np.stack(m, axis=1).ravel() for m in modes], axis=1)


def sphere_push(pos, centre, n, radius):
    """How far along n (mm) the sphere of `radius` at `centre` pushes points at rest at pos (N x 3)
    to lie on its far side; -1 beside the sphere (elastic_sphere_push)."""
    d = pos - centre
    along = d @ n
    across = d - np.outer(along, n)
    h2 = radius * radius - np.einsum("ij,ij->i", across, across)
    return np.where(h2 > 0, np.sqrt(np.maximum(h2, 0)) - along, -1.0)


def _frame(n):
    """An orthonormal basis (3 x 3, columns n, t1, t2) with n first."""
    t = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = t - n * (t @ n)
    t1 /= np.linalg.norm(t1)
    return np.stack([n, t1, np.cross(n, t1)], axis=1)


def solve_contact(K, pos, fixed, skin, push, n, margin_mm, tol=FEM_TOL, max_rounds=50, rotate=None, direct=False):
    """Static equilibrium K u = 0 with the sphere's frictionless contact, by the model's rules.

    K: stiffness (dim N square, N/mm; dof dim node + component, dim 3, or 2 for an axisymmetric
    problem's (r, z)); pos: node rest positions (N x dim, mm; for the AMG's rigid modes); fixed:
    components held at 0 (N x dim bool); skin: nodes the sphere may touch; push:
    each node's push along the unit n (mm; <= 0: not under the sphere). A contact node's u . n
    is its push, its other components free. From rest every skin node under the sphere is in
    contact (the model's fresh start); after each solve a contact node whose force (K u) . n is
    negative (the sphere would pull it) leaves, and a free skin node under the sphere that it
    would penetrate by more than margin_mm joins, until a round changes nothing. n along a grid
    axis constrains that component; any other n rotates the contact nodes' components into
    (n, t1, t2) first (rotate=True forces that path; 3 components only). Solved by CG
    preconditioned by pyamg's smoothed aggregation with the rigid modes, or directly (SuperLU)
    with `direct`. Returns u (N x dim, mm), the final contact nodes and statistics:
    rounds, the CG steps of each, contact nodes, the force on the sphere (N, -n times the
    contact's sum of (K u) . n) and the relative residual of the last solve."""
    t0 = time.perf_counter()
    N, dim = fixed.shape
    n = np.asarray(n, float)
    axis = int(np.argmax(np.abs(n)))
    if rotate is None:
        rotate = abs(abs(n[axis]) - 1) > 1e-12
    if rotate and dim != 3:
        raise ValueError("accuracy_fem: a press off the axes needs 3 components")
    eligible = skin & ~(fixed.any(axis=1) if rotate else fixed.all(axis=1)) & (push > 0)
    contact = eligible.copy()
    u = np.zeros((N, dim))
    B = None if direct else rigid_modes(pos)
    frame = _frame(n) if rotate else None
    rounds, its = 0, []
    rel = 0.0
    while True:
        rounds += 1
        if rotate:
            # contact nodes' components in the frame (n, t1, t2): u = T w
            blocks = np.tile(np.eye(3), (N, 1, 1))
            blocks[contact] = frame
            T = sp.block_diag(list(blocks), format="csr")
            A_full = (T.T @ K @ T).tocsr()
            Bw = T.T @ B
            w = np.einsum("nji,nj->ni", blocks, u)
            D = fixed.copy()
            D[contact, 0] = True
            w[fixed] = 0
            w[contact, 0] = push[contact]
        else:
            A_full, Bw, w = K, B, u.copy()
            D = fixed.copy()
            D[contact, axis] = True
            w[fixed] = 0
            w[contact, axis] = push[contact] * n[axis]
        x = w.ravel()
        A, b, _, I = condense(A_full, x=x, D=np.flatnonzero(D.ravel()))
        residuals = []
        if I.size and direct:
            x[I] = spla.spsolve(A.tocsc(), b)
        elif I.size:
            ml = pyamg.smoothed_aggregation_solver(A.tocsr(), B=Bw[I], max_coarse=500)
            x[I] = ml.solve(b, x0=x[I], tol=tol, accel="cg", maxiter=1000, residuals=residuals)
        if I.size:
            rel = float(np.linalg.norm(b - A @ x[I]) / max(np.linalg.norm(b), 1e-300))
        its.append(max(len(residuals) - 1, 0))
        w = x.reshape(N, dim)
        u = np.einsum("nij,nj->ni", blocks, w) if rotate else w.copy()
        fn = (K @ u.ravel()).reshape(N, dim) @ n
        un = u @ n
        leave = contact & (fn < 0)
        join = eligible & ~contact & (push - un > margin_mm)
        if rounds >= max_rounds or not (leave.any() or join.any()):
            break
        contact = (contact & ~leave) | join
    press = float(fn[contact].sum())
    stats = {"rounds": rounds, "iterations": its, "settled": not (leave.any() or join.any()),
             "contact_nodes": int(contact.sum()), "force_n": list(-n * press), "press_n": press,
             "relative_residual": rel, "dofs": dim * N, "total_s": time.perf_counter() - t0}
    return u, contact, stats


def node_modulus(hu, body, depth_mm, table_hu, table_e, skin_e, skin_mm, air_e):
    """Young's modulus (kPa) of each node as elastic_node_modulus() gives it: air's gel outside the
    body, the skin's within skin_mm under it, else the table's (linear, constant beyond its ends)."""
    e = np.interp(np.nan_to_num(hu, nan=-np.inf), table_hu, table_e)
    e = np.where(depth_mm < skin_mm, skin_e, e)
    return np.where(body, e, air_e)


def contact_case(base):
    """The model's problem on one exported VOI (BASE.json and arrays; see the module's usage):
    the model's rules re-implemented for the node and cell moduli (cells whose 8 corners are in
    the body: the corners' mean; else air's gel), held nodes (bone and the VOI's faces), skin
    nodes (body, not bone, a face neighbour outside the body) and the sphere's push, then
    solve_contact. Returns u (nx, ny, nz, 3; mm) and statistics."""
    with open(base + ".json") as f:
        h = json.load(f)
    nx, ny, nz = h["size"]
    hs = np.asarray(h["spacing_mm"], float)
    count = nx * ny * nz

    def read(suffix, dtype, shape):
        a = np.fromfile(base + suffix, dtype)
        if a.size != int(np.prod(shape)):
            raise ValueError(f"accuracy_fem: {base}{suffix} has {a.size} values, expected {int(np.prod(shape))}")
        return a.reshape(shape, order="F")

    hu = read(".hu.f32", np.float32, (nx, ny, nz)).astype(float)
    depth = read(".depth.f32", np.float32, (nx, ny, nz)).astype(float)
    bone = read(".bone.u8", np.uint8, (nx, ny, nz)) > 0
    body_m = read(".body.u8", np.uint8, (nx + 2, ny + 2, nz + 2)) > 0  # one node more on every side
    body = body_m[1:-1, 1:-1, 1:-1]
    m = h["material"]
    e_node = node_modulus(hu, body, depth, m["table_hu"], m["table_e_kpa"], m["skin_e_kpa"], m["skin_mm"], m["air_e_kpa"])
    # cells: the corners' mean where all eight are in the body, else the gel
    in_body = np.ones((nx - 1, ny - 1, nz - 1), bool)
    e_sum = np.zeros((nx - 1, ny - 1, nz - 1))
    for ox, oy, oz in MODEL_CORNERS:
        in_body &= body[ox:nx - 1 + ox, oy:ny - 1 + oy, oz:nz - 1 + oz]
        e_sum += e_node[ox:nx - 1 + ox, oy:ny - 1 + oy, oz:nz - 1 + oz]
    cell_e = np.where(in_body, e_sum / 8, m["air_e_kpa"])
    # held: bone and the faces; skin: body, not bone, a face neighbour outside the body
    held = bone.copy()
    held[[0, -1], :, :] = True
    held[:, [0, -1], :] = True
    held[:, :, [0, -1]] = True
    outside_nb = np.zeros_like(body)
    for a in range(3):
        for s in (-1, 1):
            sl = [slice(1, -1)] * 3
            sl[a] = slice(1 + s, body_m.shape[a] - 1 + s)
            outside_nb |= ~body_m[tuple(sl)]
    skin = body & ~bone & outside_nb & ~held
    xs, ys, zs = (np.arange(k) * hs[a] for a, k in enumerate((nx, ny, nz)))
    I, J, Kk = np.meshgrid(xs, ys, zs, indexing="ij")
    pos = np.stack([I.ravel(order="F"), J.ravel(order="F"), Kk.ravel(order="F")], axis=1)
    n = np.asarray(h["normal"], float)
    n /= np.linalg.norm(n)
    centre = np.asarray(h["tip_mm"], float) - n * h["radius_mm"]
    flat = lambda a: a.ravel(order="F")  # noqa: E731
    push = np.where(flat(skin), sphere_push(pos, centre, n, h["radius_mm"]), -1.0)
    t0 = time.perf_counter()
    K = assemble_grid(xs, ys, zs, cell_e, h["nu"])
    t_asm = time.perf_counter() - t0
    fixed = np.repeat(flat(held)[:, None], 3, axis=1)
    u, contact, stats = solve_contact(K, pos, fixed, flat(skin), push, n, PENETRATION_VOX * hs[0],
                                      tol=h.get("tol", FEM_TOL))
    stats.update({"nodes": count, "cells_tissue": int(in_body.sum()), "skin_nodes": int(skin.sum()),
                  "assemble_s": t_asm})
    if "element" in h:
        # the model's own cell matrix (float) against this one: the same element
        k_model = np.asarray(h["element"], float).reshape(24, 24)
        k_fem = sri_element(tuple(hs), h["nu"])
        stats["element_max_rel_diff"] = float(np.abs(k_model - k_fem).max() / np.abs(k_fem).max())
    return u.reshape((nx, ny, nz, 3), order="F"), contact.reshape((nx, ny, nz), order="F"), stats


def graded_axis(h0, core_mm, extent_mm, per_level=4):
    """Node coordinates from 0 (mm): cells of h0 up to core_mm, then per_level cells of each
    doubled spacing until extent_mm is reached."""
    xs = list(np.arange(int(math.ceil(core_mm / h0)) + 1) * h0)
    step = h0
    while xs[-1] < extent_mm:
        step *= 2
        for _ in range(per_level):
            xs.append(xs[-1] + step)
    return np.array(xs)


def hertz_force(e_kpa, nu, radius, depth):
    """Hertz's force (N) of a rigid sphere of radius (mm) pressed depth (mm) into a half-space."""
    return 4.0 / 3.0 * (e_kpa * 1e-3) / (1 - nu * nu) * math.sqrt(radius) * depth ** 1.5


def hertz_surface(r, radius, depth):
    """Hertz's surface displacement into the half-space (mm) at distance r (mm) from the axis:
    depth - r^2 / 2R inside the contact radius a = sqrt(R depth), and
    ((2 a^2 - r^2) asin(a / r) + a sqrt(r^2 - a^2)) / (pi R) outside (Johnson, Contact Mechanics, 3.42)."""
    r = np.asarray(r, float)
    a = math.sqrt(radius * depth)
    out = np.empty_like(r)
    inside = r <= a
    out[inside] = depth - r[inside] ** 2 / (2 * radius)
    ro = r[~inside]
    out[~inside] = ((2 * a * a - ro ** 2) * np.arcsin(a / ro) + a * np.sqrt(ro ** 2 - a * a)) / (math.pi * radius)
    return out


# the profile compares the surface within this many contact radii of the axis
PROFILE_RADII = 3.0


def profile_error_pct(r, w, radius, depth, radii=PROFILE_RADII):
    """Relative RMS error (%) of a surface profile w(r) (displacement into the block, mm, at radii r
    along a ray from the axis) against Hertz's, over the disc r <= radii a: the squares weighted
    by r (trapezoids), as a sum over the disc's nodes weighs them."""
    r, w = np.asarray(r, float), np.asarray(w, float)
    keep = r <= radii * math.sqrt(radius * depth) + 1e-9
    r, w = r[keep], w[keep]
    wh = hertz_surface(r, radius, depth)
    return float(100 * math.sqrt(np.trapezoid((w - wh) ** 2 * r, r) / np.trapezoid(wh ** 2 * r, r)))


def assemble_axisymmetric(rs, zs, e_kpa, nu, full=False):
    """The stiffness (CSR, N/mm; dof 2 node + component, components (r, z); nodes as MeshQuad's
    init_tensor numbers them) of a homogeneous solid of revolution meshed by the quadrilaterals of
    the tensor grid rs x zs (mm): the strains e_rr, e_zz, e_rz and the hoop strain u_r / r, each
    cell's energy weighted by 2 pi r, so that K u at a node is the whole ring's force. Selective
    reduced integration as the voxel model's cells: the mu part with 2x2 Gauss points, the lambda
    part (the volume change, hoop strain included) at the cell centre; full=True integrates both
    with 2x2 points. Returns K and the node positions (N x 2)."""
    mesh = MeshQuad.init_tensor(np.asarray(rs, float), np.asarray(zs, float))
    elem = ElementVector(ElementQuad1())
    gauss = Basis(mesh, elem, intorder=3)
    centre = gauss if full else Basis(mesh, elem, quadrature=(np.full((2, 1), 0.5), np.ones(1)))
    e = e_kpa * 1e-3
    lam, mu = e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))

    def strains(u, r):
        g = u.grad
        return g[0][0], g[1][1], 0.5 * (g[0][1] + g[1][0]), u.value[0] / r

    @BilinearForm
    def mu_part(u, v, w):
        r = w.x[0]
        a, b = strains(u, r), strains(v, r)
        return 2 * np.pi * r * 2 * mu * (a[0] * b[0] + a[1] * b[1] + 2 * a[2] * b[2] + a[3] * b[3])

    @BilinearForm
    def lambda_part(u, v, w):
        r = w.x[0]
        a, b = strains(u, r), strains(v, r)
        return 2 * np.pi * r * lam * (a[0] + a[1] + a[3]) * (b[0] + b[1] + b[3])

    K = (asm(mu_part, gauss) + asm(lambda_part, centre)).tocsr()
    if not (gauss.nodal_dofs == np.arange(2 * mesh.p.shape[1]).reshape(-1, 2).T).all():
        raise ValueError("accuracy_fem: scikit-fem numbers the vector dofs otherwise than 2 node + component")
    return K, mesh.p.T.copy()


def hertz_case(radius, depth, nu, e_kpa=10.0, h0=0.05, extent=1000.0, full=False):
    """A sphere pressed into a homogeneous block, axisymmetric: the solid of revolution r <= extent,
    -extent <= z <= 0 (mm), its top z = 0 the skin, cells of h0 (mm) to 2.5 contact radii
    a = sqrt(R depth) from the axis and from the top, doubling outwards (4 cells each), the far
    faces held, u_r = 0 on the axis; the sphere's frictionless contact by the model's rules
    (solve_contact), solved directly. Returns statistics with the force (N), Hertz's and their
    ratio, and the surface profile (rest r, displacement into the block) and its error against
    Hertz's (profile_error_pct)."""
    a = math.sqrt(radius * depth)
    rs = graded_axis(h0, 2.5 * a, extent)
    zs = -graded_axis(h0, 2.5 * a, extent)[::-1]
    t0 = time.perf_counter()
    K, pos = assemble_axisymmetric(rs, zs, e_kpa, nu, full)
    t_asm = time.perf_counter() - t0
    fixed = np.zeros((len(pos), 2), bool)
    fixed[pos[:, 0] == 0, 0] = True
    fixed[(pos[:, 0] == rs[-1]) | (pos[:, 1] == zs[0])] = True
    skin = pos[:, 1] == 0
    n = np.array([0.0, -1.0])
    pos3 = np.stack([pos[:, 0], np.zeros(len(pos)), pos[:, 1]], axis=1)
    push = np.where(skin, sphere_push(pos3, np.array([0.0, 0.0, radius - depth]), np.array([0.0, 0.0, -1.0]), radius),
                    -1.0)
    u, contact, stats = solve_contact(K, pos, fixed, skin, push, n, PENETRATION_VOX * h0, direct=True)
    force = stats["press_n"]
    ref = hertz_force(e_kpa, nu, radius, depth)
    order = np.argsort(pos[skin, 0])
    r, w = pos[skin, 0][order], -u[skin, 1][order]
    stats.update({"radius_mm": radius, "depth_mm": depth, "nu": nu, "e_kpa": e_kpa, "full_integration": full,
                  "axisymmetric": True, "h0_mm": h0, "extent_mm": float(rs[-1]), "nodes": int(len(pos)),
                  "assemble_s": t_asm, "force_n": force, "hertz_n": ref, "ratio": force / ref,
                  "profile_pct": profile_error_pct(r, w, radius, depth),
                  "profile": {"r_mm": [float(x) for x in r[r <= 8 * a]], "w_mm": [float(x) for x in w[r <= 8 * a]]}})
    return stats


def main_press(base):
    """Reference (c): BASE.json and BASE.labels.u8 in, BASE.u_fem.f32 and BASE.fem.json out."""
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


def main_contact(base):
    """The model's problem on an exported VOI: BASE.u_fem.f32 (mm, 3 per node, i fastest),
    BASE.contact.u8 (1 on the final contact nodes) and BASE.fem.json out."""
    try:
        u, contact, stats = contact_case(base)
    except (OSError, ValueError, KeyError) as e:
        sys.exit(f"accuracy_fem contact: {base}: {e}")
    u.reshape((-1, 3), order="F").astype(np.float32).tofile(base + ".u_fem.f32")
    contact.ravel(order="F").astype(np.uint8).tofile(base + ".contact.u8")
    with open(base + ".fem.json", "w") as f:
        json.dump(stats, f)
    print(f"accuracy_fem contact: {stats['nodes']} nodes, {stats['rounds']} rounds ({stats['iterations']} CG steps), "
          f"{stats['contact_nodes']} contact nodes, force {np.linalg.norm(stats['force_n']):.5g} N, "
          f"{stats['total_s']:.0f} s")


def main_hertz(argv):
    """Hertz's block on a graded mesh: the statistics, force and profile as JSON."""
    ap = argparse.ArgumentParser(prog="accuracy_fem.py hertz")
    ap.add_argument("out")
    ap.add_argument("--radius", type=float, required=True, help="sphere radius (mm)")
    ap.add_argument("--depth", type=float, required=True, help="press depth (mm)")
    ap.add_argument("--nu", type=float, required=True)
    ap.add_argument("--e-kpa", type=float, default=10.0)
    ap.add_argument("--h0", type=float, default=0.05, help="cell edge at the contact (mm)")
    ap.add_argument("--extent", type=float, default=1000.0, help="the block's radius and depth (mm)")
    ap.add_argument("--full", action="store_true", help="fully integrated cells (locking) instead of SRI")
    a = ap.parse_args(argv)
    stats = hertz_case(a.radius, a.depth, a.nu, a.e_kpa, a.h0, a.extent, a.full)
    with open(a.out, "w") as f:
        json.dump(stats, f)
    print(f"accuracy_fem hertz: R {a.radius} d {a.depth} nu {a.nu}{' full' if a.full else ''}: F {stats['force_n']:.5g} N, "
          f"Hertz {stats['hertz_n']:.5g} N, ratio {stats['ratio']:.4f}, {stats['nodes']} nodes, {stats['rounds']} rounds, "
          f"{stats['total_s']:.0f} s")


def main():
    if len(sys.argv) >= 2 and sys.argv[1] == "hertz":
        main_hertz(sys.argv[2:])
    elif len(sys.argv) == 3 and sys.argv[1] == "contact":
        main_contact(sys.argv[2])
    elif len(sys.argv) == 2 and not sys.argv[1].startswith("-"):
        main_press(sys.argv[1])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
