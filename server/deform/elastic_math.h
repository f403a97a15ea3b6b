// The elastic model (deform.relax_method = "elastic"): the per-node and per-cell math of
// static linear elasticity on the VOI's voxels, written once and compiled by both
// backends (g++ for server/deform/relax_elastic.cpp, nvcc for cuda/relax_elastic.cu).
//
// What it solves: K u = 0 on the free degrees of freedom, with
// - nodes at the voxel centres (one per ChainMail element, so u, J, bricks and frames work
//   as for the other models), u in mm along the grid axes;
// - trilinear hexahedra (cells) between eight neighbouring nodes, each with one Young's
//   modulus E (kPa): the mean of its corners' moduli (elastic_node_modulus: a scene table of
//   HU, a skin layer, and air as a gel kElasticAirRatio times as stiff as the softest
//   tissue), and the scene's Poisson ratio nu;
// - selective reduced integration: the mu part with 2x2x2 Gauss points, the lambda part
//   (the volume change) at the cell centre, so that nu up to 0.49 does not lock (a cell
//   whose volume change is held to 0 at eight points is held nearly rigid);
// - held nodes (u = 0): bone (rigid and fixed, as ChainMail's bone), the VOI's faces, and
//   air beyond kElasticAirRim nodes from the body (the solve skips them);
// - contact nodes: body nodes under the fingertip, a rigid sphere of radius R whose deepest
//   point is the tip x, pressing along n (from the skin point X to x). A contact node's
//   displacement along n is prescribed (it lies on the sphere: elastic_sphere_push); across
//   n it is free: the finger slides without friction, as Hertz's contact does. Nodes pulled
//   (tension) leave the contact set and nodes pushed into the sphere join it, round by round.
//
// How: conjugate gradients on the free subspace (the projection elastic_project() takes
// the held components out), each step preconditioned by one symmetric geometric multigrid
// V-cycle: damped Jacobi smoothing, residuals restricted by the transpose of trilinear
// prolongation, coarse cells of edge 2^l h whose modulus is the mean of the fine cells they
// cover (the coarse finite element space is nested in the fine one, so this is the
// Galerkin operator of a homogeneous region), a coarse node held or in contact where the
// fine node it lies on is.
//
// Units: E in kPa, lengths and u in mm, forces in N: the cell matrix elastic_element()
// is for E = 1 kPa (N/mm per mm of displacement), so K u is in N.
#pragma once

#include <cmath>
#include <cstdint>
#include <utility>

#include "core/hd.h"
#include "core/vec3.h"
#include "deform/deform_math.h"

namespace palpsim::deform {

/// Largest number of points of a scene's HU-to-modulus table.
constexpr int kElasticMaxTable = 16;
/// Most multigrid levels of an elastic plan (a VOI of 2^16 voxels along an axis needs 15).
constexpr int kElasticMaxLevels = 16;
/// Air (outside the body mask) is a gel this many times as stiff as the table's softest
/// entry: its pull on the skin is 1e-4 of the tissue's (traction-free to that), it carries
/// the displacement on into the air (so that J shows a clean dent, where air held at rest
/// would stretch the skin's intensity over the whole dent) and anchors tissue fragments that
/// touch nothing held (otherwise free to move as rigid bodies: a singular system).
constexpr float kElasticAirRatio = 1e-4f;
/// The V-cycle's smoother: Chebyshev polynomials in D^-1 K (D the diagonal), aimed at the
/// upper part [lmax / kElasticChebyshevRatio, kElasticChebyshevMargin lmax] of its spectrum.
/// Damped Jacobi does not do: the centre-point volume term puts lmax(D^-1 K) well above the
/// 2 of a Laplacian (a cell's divergence couples its 24 unknowns), so a weight that keeps
/// Jacobi stable leaves the rest of the upper spectrum nearly undamped. lmax comes from
/// kElasticLanczosSteps Lanczos steps per level when a VOI is set up (elastic_lanczos_lmax).
/// The degrees are the scene's (ElasticDegrees).
constexpr float kElasticChebyshevRatio = 20.0f;
constexpr float kElasticCoarsestRatio = 400.0f;  // the coarsest level's interval reaches further down
constexpr float kElasticChebyshevMargin = 1.1f;  // the estimate is a lower bound of lmax
/// Lanczos steps (each one application of D^-1 K) for a level's lmax: Lanczos's largest Ritz
/// value nears lmax far faster than the power iteration's ratio, whose 12 steps (used
/// before) left some levels of the phantom's VOI nearly a margin under lmax and whose 6
/// let the smoother diverge; 8 Lanczos steps came closer than those 12 on every level.
constexpr int kElasticLanczosSteps = 8;

/// Lanczos without normalising (Stieltjes' form, in the inner product <a, b>_D = a . D b in
/// which D^-1 K is symmetric): u_{j+1} = A u_j - alpha_j u_j - beta_j u_{j-1}, with alpha_j =
/// <A u_j, u_j> / <u_j, u_j> and beta_j = <u_j, u_j> / <u_{j-1}, u_{j-1}> (beta_0 = 0). Step j
/// of a backend sums s[j] = <u_j, u_j>_D and n[j] = <A u_j, u_j>_D; this returns the largest
/// eigenvalue of the tridiagonal matrix they make (diagonal alpha, off-diagonal sqrt(beta)),
/// the largest Ritz value: a lower bound of lmax that the steps bring up to it fast. It stops
/// at the first step whose s is not above 0 (the space is exhausted), and gives 1 where the
/// first is (a level all held).
constexpr double kElasticLanczosPrecision = 1e-10;  // the relative width at which the bisection stops
PALPSIM_HD double elastic_lanczos_lmax(const double* s, const double* n, int steps) {
  double a[kElasticLanczosSteps], b2[kElasticLanczosSteps];
  int m = 0;
  for (int j = 0; j < steps && j < kElasticLanczosSteps; ++j) {
    if (!(s[j] > 0)) break;
    a[j] = n[j] / s[j];
    b2[j] = j > 0 ? s[j] / s[j - 1] : 0.0;  // the square of T's entry (j - 1, j)
    ++m;
  }
  if (m == 0) return 1.0;
  // bisection on Sturm's count of the eigenvalues above x, inside Gershgorin's bound
  double hi = 0;
  for (int j = 0; j < m; ++j) {
    const double left = j > 0 ? sqrt(b2[j]) : 0.0, right = j + 1 < m ? sqrt(b2[j + 1]) : 0.0;
    const double r = fabs(a[j]) + left + right;
    hi = r > hi ? r : hi;
  }
  // until the interval is far within float's precision of its ends (about 34 halvings of
  // Gershgorin's; the backends keep lmax as a float), no further: each halving costs m
  // divisions in sequence, on the GPU a single thread's per level within a VOI's set-up
  double lo = -hi;
  for (int it = 0; it < 100 && hi - lo > kElasticLanczosPrecision * (fabs(lo) > fabs(hi) ? fabs(lo) : fabs(hi));
       ++it) {
    const double x = 0.5 * (lo + hi);
    int above = 0;
    double q = 1.0;
    for (int j = 0; j < m; ++j) {
      q = a[j] - x - (j > 0 ? b2[j] / q : 0.0);
      if (q == 0.0) q = 1e-300;
      if (q > 0) ++above;
    }
    if (above > 0) lo = x;
    else hi = x;
  }
  return lo > 0 ? lo : 1.0;
}

/// The Lanczos start on a level (relax_elastic.cpp, estimate_lmax): component c of
/// node e is elastic_power_start(3 e + c), the (3 e + c + 1)-th state of a linear
/// congruential generator from kElasticPowerSeed mapped to [-0.5, 0.5). Computed by jumping
/// ahead (O'Neill, PCG's advance), so that a GPU thread makes its own nodes' values and the
/// two backends start from the same vector.
constexpr std::uint32_t kElasticPowerSeed = 12345u;
PALPSIM_HD float elastic_power_start(unsigned long long m) {
  std::uint32_t mult = 1u, plus = 0u, cur_mult = 1664525u, cur_plus = 1013904223u;
  for (unsigned long long steps = m + 1; steps > 0; steps >>= 1) {
    if (steps & 1) {
      mult *= cur_mult;
      plus = plus * cur_mult + cur_plus;
    }
    cur_plus = (cur_mult + 1u) * cur_plus;
    cur_mult *= cur_mult;
  }
  const std::uint32_t state = mult * kElasticPowerSeed + plus;
  return float(state >> 8) / float(1u << 24) - 0.5f;
}

/// The Chebyshev smoother's recurrence for the interval [lo, hi]: step 0 is d = b[0] D^-1 r,
/// step s > 0 is d = a[s] d + b[s] D^-1 r (r the residual after the last step), x += d each
/// step (Saad, Iterative Methods for Sparse Linear Systems, alg. 12.1).
PALPSIM_HD void elastic_chebyshev(float lo, float hi, int degree, float* a, float* b) {
  const float theta = 0.5f * (hi + lo), delta = 0.5f * (hi - lo);
  const float sigma = theta / delta;
  float rho = 1.0f / sigma;
  a[0] = 0.0f;
  b[0] = 1.0f / theta;
  for (int s = 1; s < degree; ++s) {
    const float rho_next = 1.0f / (2.0f * sigma - rho);
    a[s] = rho_next * rho;
    b[s] = 2.0f * rho_next / delta;
    rho = rho_next;
  }
}

/// The largest Chebyshev degree any level uses (the coefficient arrays' size).
constexpr int kElasticMaxDegree = 32;

/// The V-cycle's Chebyshev degrees (deform.elastic.smooth_degree, coarse_smooth_degree and
/// coarsest_degree): the finest level's before and after the coarse correction, the coarse
/// levels' above the coarsest, and the coarsest's (its smoothing is all it does there).
/// Each lies in [2, kElasticMaxDegree]: the GPU fuses a smoothing's first step into the
/// pass before it and needs a second. A higher degree takes fewer CG steps of more passes
/// each; the coarsest level's passes cost the GPU a grid barrier each for a few free nodes.
struct ElasticDegrees {
  int fine = 8, coarse = 2, coarsest = 2;
  /// level `l`'s degree in a V-cycle of `levels` levels (a single level is the coarsest)
  PALPSIM_HD int at(int l, int levels) const { return l + 1 == levels ? coarsest : (l == 0 ? fine : coarse); }
};

/// A free skin node joins the contact set when the sphere's surface lies deeper than it by
/// more than this (voxel edges): a margin above float rounding of positions of tens of mm.
constexpr float kElasticPenetrationVox = 1e-4f;

/// Air nodes more than this many nodes away (along some axis) from every body node are held
/// at rest: the gel there (kElasticAirRatio times as stiff as tissue) moves nothing the body
/// feels, and the solve skips them. The air nodes nearer the body follow the skin, so a cell
/// of air folds only where the skin bulges out by more than this many voxels.
constexpr int kElasticAirRim = 2;

/// Node flags (one byte a node, every level).
constexpr std::uint8_t kElasticHeld = 1;     // u = 0 (bone, a VOI face, beyond a coarse level's fine grid)
constexpr std::uint8_t kElasticContact = 2;  // u . n prescribed (under the fingertip); across n free
constexpr std::uint8_t kElasticBody = 4;     // level 0: inside the body mask and not bone
constexpr std::uint8_t kElasticSkin = 8;     // level 0: a body node with a face neighbour outside the body (the finger touches these)
constexpr std::uint8_t kElasticAir = 16;     // level 0: held as air beyond kElasticAirRim (coarse levels do not inherit the hold)

/// A scene's table from intensity (HU) to Young's modulus (kPa): points sorted by HU,
/// linear between them, constant beyond the ends.
struct ElasticTable {
  int n = 0;
  float hu[kElasticMaxTable] = {};
  float e_kpa[kElasticMaxTable] = {};
};

/// The material of the elastic model: the table, the skin layer and the gel of air.
struct ElasticMaterial {
  ElasticTable table;
  float skin_e_kpa = 35;      // body voxels within skin_mm of the skin (depth B below it)
  float skin_mm = 2;
  float air_e_kpa = 3e-4f;    // kElasticAirRatio times the table's least modulus
};

/// Young's modulus (kPa) of the table at intensity `hu`.
PALPSIM_HD float elastic_table_e(const ElasticTable& t, float hu) {
  if (t.n <= 0) return 0.0f;
  if (!(hu > t.hu[0])) return t.e_kpa[0];  // NaN reads as the first entry
  for (int i = 1; i < t.n; ++i) {
    if (hu <= t.hu[i]) {
      const float w = (hu - t.hu[i - 1]) / (t.hu[i] - t.hu[i - 1]);
      return t.e_kpa[i - 1] + w * (t.e_kpa[i] - t.e_kpa[i - 1]);
    }
  }
  return t.e_kpa[t.n - 1];
}

/// Young's modulus (kPa) of one voxel: air's gel outside the body, the skin's within
/// skin_mm under the skin (B, depth_mm), else the table's at its intensity. Bone voxels
/// take the table's value too (they are held; their modulus only weighs their cells).
PALPSIM_HD float elastic_node_modulus(const ElasticMaterial& m, float hu, bool body, float depth_mm) {
  if (!body) return m.air_e_kpa;
  if (depth_mm < m.skin_mm) return m.skin_e_kpa;
  return elastic_table_e(m.table, hu);
}

/// Corner c of a cell (bit 0: +i, bit 1: +j, bit 2: +k; deform_math.h's cell_blend order).
PALPSIM_HD Vec3i elastic_corner(int c) { return Vec3i{c & 1, (c >> 1) & 1, (c >> 2) & 1}; }

/// The cell matrix's mirror symmetry: a box cell of one isotropic material is the same
/// seen from each corner, with the axes through that corner, so entry (3 a + i, 3 b + j)
/// (corner a's component i, corner b's component j) is corner 0's entry (i, 3 (a ^ b) + j)
/// times this sign: + on the diagonal blocks' diagonals (i == j), else - where corner a lies
/// on the far side along exactly one of axes i and j. elastic_element() builds every entry
/// so, and a backend may keep corner 0's 72 entries alone (ElasticCellBase).
PALPSIM_HD constexpr bool elastic_mirror_negates(int a, int i, int j) {
  return i != j && (((a >> i) ^ (a >> j)) & 1) != 0;
}

/// The cell matrix kept as corner 0's row block (72 entries, base[9 d + 3 i + j] = entry
/// (i, 3 d + j)), read as the full matrix through elastic_mirror_negates(): the same
/// entries to the bit (elastic_element() makes them so); a GPU reads 288 bytes of constants
/// instead of 2304, which its constant cache holds.
struct ElasticCellBase {
  const float* base;
  PALPSIM_HD float operator()(int r, int c) const {
    const int a = r / 3, i = r % 3, b = c / 3, j = c % 3;
    const float v = base[9 * (a ^ b) + 3 * i + j];
    return elastic_mirror_negates(a, i, j) ? -v : v;
  }
};

/// A level-0 node's static flags: held where it is bone, on a VOI face (`face`) or air
/// farther than kElasticAirRim nodes from the body (air as well only off the faces), body where the body mask holds it and
/// it is no bone, skin where such a node has a face neighbour outside the body;
/// `in_body(gi, gj, gk)` reads the mask at patient voxel (gi, gj, gk), false outside the grid.
template <typename InBody>
PALPSIM_HD std::uint8_t elastic_static_flags(bool body, bool bone, bool face, const InBody& in_body, int gi, int gj,
                                             int gk) {
  std::uint8_t f = 0;
  if (bone || face) f |= kElasticHeld;
  if (!body) {
    bool near = false;
    for (int dk = -kElasticAirRim; dk <= kElasticAirRim && !near; ++dk)
      for (int dj = -kElasticAirRim; dj <= kElasticAirRim && !near; ++dj)
        for (int di = -kElasticAirRim; di <= kElasticAirRim && !near; ++di) near = in_body(gi + di, gj + dj, gk + dk);
    // a face node is held as a face, which the coarse nodes on it inherit (every level's
    // faces held: the GPU's coarse gathers leave tiles of the high faces out)
    if (!near && !face) f |= kElasticHeld | kElasticAir;
  }
  if (body && !bone) {
    f |= kElasticBody;
    bool skin = false;
    for (int q = 0; q < 6 && !skin; ++q) {
      const Vec3i o = neighbour_offset(q);
      skin = !in_body(gi + o.x, gj + o.y, gk + o.z);
    }
    if (skin) f |= kElasticSkin;
  }
  return f;
}

/// A level-0 cell's modulus (kPa): the mean of its corners' node moduli `node_e(c)` where
/// all eight corners are in the body (`corner_body(c)`; bone counts), else `air_e_kpa`
/// (air's gel), so that the tissue ends at the skin nodes; c in elastic_corner() order.
template <typename NodeE, typename CornerBody>
PALPSIM_HD float elastic_cell_modulus(const NodeE& node_e, const CornerBody& corner_body, float air_e_kpa) {
  float sum = 0;
  bool body = true;
  for (int c = 0; c < 8; ++c) {
    body = body && corner_body(c);
    sum += node_e(c);
  }
  return body ? sum / 8 : air_e_kpa;
}

/// Adds the 3 x 3 block K[a][b] of one cell's matrix times corner b's displacement `u` (mm)
/// to `y` (N per kPa of the cell's modulus), one running sum a row, a product at a time (a
/// compiler that fuses multiply-adds makes each term one instruction). `k(r, c)` reads the
/// 24 x 24 cell matrix, row and column 3 corner + component. Every product of K with a
/// field goes through it, so that all of them sum in one order.
template <typename KMat>
PALPSIM_HD void elastic_cell_block_add(const KMat& k, int a, int b, const Vec3f& u, Vec3f& y) {
  y.x += k(3 * a, 3 * b) * u.x;
  y.x += k(3 * a, 3 * b + 1) * u.y;
  y.x += k(3 * a, 3 * b + 2) * u.z;
  y.y += k(3 * a + 1, 3 * b) * u.x;
  y.y += k(3 * a + 1, 3 * b + 1) * u.y;
  y.y += k(3 * a + 1, 3 * b + 2) * u.z;
  y.z += k(3 * a + 2, 3 * b) * u.x;
  y.z += k(3 * a + 2, 3 * b + 1) * u.y;
  y.z += k(3 * a + 2, 3 * b + 2) * u.z;
}

/// The row block of corner `a` of one cell's matrix times the cell's corner displacements
/// `uc` (8 corners, mm): sum_b K[a][b] uc[b] (N per kPa of the cell's modulus), b in order.
template <typename KMat>
PALPSIM_HD Vec3f elastic_cell_row(const KMat& k, int a, const Vec3f uc[8]) {
  Vec3f y{0, 0, 0};
  for (int b = 0; b < 8; ++b) elastic_cell_block_add(k, a, b, uc[b], y);
  return y;
}

/// The diagonal of corner `a`'s row block (N/mm per kPa): what one cell adds to its node's
/// Jacobi diagonal.
template <typename KMat>
PALPSIM_HD Vec3f elastic_cell_diag(const KMat& k, int a) {
  return Vec3f{k(3 * a, 3 * a), k(3 * a + 1, 3 * a + 1), k(3 * a + 2, 3 * a + 2)};
}

/// Adds to `y` corner a's part of (K u) at node (i, j, k) of a level of `size` nodes: the
/// row block of the cell in which the node is corner `a` (if that cell lies between nodes
/// 0 .. size - 1) times the cell's corners, times the cell's modulus `cell_e(lowest
/// corner)` (kPa) and `scale`, the level's cell edge over level 0's (2^level: the matrix
/// grows with the edge); `load_u(i, j, k)` gives a node's displacement (mm). One term of
/// elastic_apply_node(), for a backend that sums the eight cells on eight threads.
template <typename KMat, typename CellE, typename LoadU>
PALPSIM_HD void elastic_add_cell(const KMat& k, const CellE& cell_e, const LoadU& load_u, const Vec3i& size,
                                 float scale, int i, int j, int kk, int a, Vec3f& y) {
  const Vec3i o = elastic_corner(a);
  const int ci = i - o.x, cj = j - o.y, ck = kk - o.z;
  if (ci < 0 || cj < 0 || ck < 0 || ci + 1 >= size.x || cj + 1 >= size.y || ck + 1 >= size.z) return;
  const float e = cell_e(ci, cj, ck);
  if (e == 0.0f) return;
  Vec3f uc[8];
  for (int b = 0; b < 8; ++b) {
    const Vec3i ob = elastic_corner(b);
    uc[b] = load_u(ci + ob.x, cj + ob.y, ck + ob.z);
  }
  y += elastic_cell_row(k, a, uc) * (e * scale);
}

/// (K u) at node (i, j, k) of a level of `size` nodes (N): over the (up to) eight cells
/// around it, elastic_add_cell() in corner order.
template <typename KMat, typename CellE, typename LoadU>
PALPSIM_HD Vec3f elastic_apply_node(const KMat& k, const CellE& cell_e, const LoadU& load_u, const Vec3i& size,
                                    float scale, int i, int j, int kk) {
  Vec3f y{0, 0, 0};
  for (int a = 0; a < 8; ++a) elastic_add_cell(k, cell_e, load_u, size, scale, i, j, kk, a, y);
  return y;
}

/// Adds to `d` what the cell in which node (i, j, k) is corner `a` gives the node's Jacobi
/// diagonal (N/mm), as elastic_add_cell() applies it.
template <typename KMat, typename CellE>
PALPSIM_HD void elastic_add_cell_diag(const KMat& k, const CellE& cell_e, const Vec3i& size, float scale, int i,
                                      int j, int kk, int a, Vec3f& d) {
  const Vec3i o = elastic_corner(a);
  const int ci = i - o.x, cj = j - o.y, ck = kk - o.z;
  if (ci < 0 || cj < 0 || ck < 0 || ci + 1 >= size.x || cj + 1 >= size.y || ck + 1 >= size.z) return;
  d += elastic_cell_diag(k, a) * (cell_e(ci, cj, ck) * scale);
}

/// The Jacobi diagonal (N/mm) of node (i, j, k), as elastic_apply_node() sums it.
template <typename KMat, typename CellE>
PALPSIM_HD Vec3f elastic_diag_node(const KMat& k, const CellE& cell_e, const Vec3i& size, float scale, int i, int j,
                                   int kk) {
  Vec3f d{0, 0, 0};
  for (int a = 0; a < 8; ++a) elastic_add_cell_diag(k, cell_e, size, scale, i, j, kk, a, d);
  return d;
}

/// A node's displacement (mm) and the modulus (kPa) of the cell whose lowest corner it is, as
/// elastic_apply_interior_once() reads them.
struct ElasticNodeCell {
  Vec3f u;
  float e;
};

namespace detail {
// elastic_apply_interior_once()'s pieces as templates, so that every index into the partial
// sums and the matrix is a constant on both compilers (nvcc left the loops rolled inside
// the step kernel, and the matrix then went to local memory)

// neighbour D's (dx + 1 + 3 (dy + 1) + 9 (dz + 1)) products in cell A, where it is corner b
template <int D, int A, typename KMat>
PALPSIM_HD void elastic_once_cell(const KMat& k, const Vec3f& u, Vec3f (&acc)[8]) {
  constexpr int bx = D % 3 - 1 + (A & 1), by = (D / 3) % 3 - 1 + ((A >> 1) & 1), bz = D / 9 - 1 + ((A >> 2) & 1);
  if constexpr (bx >= 0 && bx <= 1 && by >= 0 && by <= 1 && bz >= 0 && bz <= 1)
    elastic_cell_block_add(k, A, bx + 2 * by + 4 * bz, u, acc[A]);
}

// neighbour D read once: its products in the cells it is a corner of, and the modulus of
// the cell whose lowest corner it is
template <int D, typename KMat, typename NodeAt, int... A>
PALPSIM_HD void elastic_once_neighbour(const KMat& k, const NodeAt& node, int sy, int sz, float scale, Vec3f (&acc)[8],
                                       float (&es)[8], std::integer_sequence<int, A...>) {
  constexpr int dx = D % 3 - 1, dy = (D / 3) % 3 - 1, dz = D / 9 - 1;
  const ElasticNodeCell q = node(dx + dy * sy + dz * sz);
  if constexpr (dx <= 0 && dy <= 0 && dz <= 0) es[-dx - 2 * dy - 4 * dz] = q.e * scale;
  (elastic_once_cell<D, A>(k, q.u, acc), ...);
}

// cell A's partial sum scaled into kx and its diagonal into dg (a cell of modulus 0 adds
// nothing: elastic_add_cell skips it; its diagonal adds +0)
template <int A, typename KMat>
PALPSIM_HD void elastic_once_scale(const KMat& k, const Vec3f (&acc)[8], const float (&es)[8], Vec3f& kx, Vec3f& dg) {
  if (es[A] == 0.0f) return;
  kx += acc[A] * es[A];
  dg += elastic_cell_diag(k, A) * es[A];
}

template <typename KMat, typename NodeAt, int... D, int... A>
PALPSIM_HD void elastic_once_all(const KMat& k, const NodeAt& node, int sy, int sz, float scale, Vec3f& kx, Vec3f& dg,
                                 std::integer_sequence<int, D...>, std::integer_sequence<int, A...> cells) {
  Vec3f acc[8] = {};  // cell a's row block (the cell in which the node is corner a) times its corners
  float es[8] = {};   // cell a's modulus times scale
  (elastic_once_neighbour<D>(k, node, sy, sz, scale, acc, es, cells), ...);
  kx = Vec3f{0, 0, 0};
  dg = Vec3f{0, 0, 0};
  (elastic_once_scale<A>(k, acc, es, kx, dg), ...);
}
}  // namespace detail

/// (K u) at an interior node (all eight cells around it lie in the level) into `kx` (N) and
/// its Jacobi diagonal into `dg` (N/mm), each of the node's 27 neighbours read once:
/// `node(o)` gives the node at flat offset o (strides 1, `sy`, `sz` along i, j and k) and
/// the modulus (kPa) of the cell whose lowest corner it is. Each cell's row block times its
/// corners is summed over the corners in elastic_cell_row()'s order (the neighbours, k then
/// j then i, run through each cell's corners in corner order), then scaled and added cell by
/// cell, so kx and dg are elastic_apply_node()'s and elastic_diag_node()'s to the bit. It
/// holds eight partial sums instead of a cell's eight corners: a backend whose loads are
/// the cost (a shared-memory tile, a float4 a node, every load one register and a constant
/// apart) reads 27 nodes, not 64 corners.
template <typename KMat, typename NodeAt>
PALPSIM_HD void elastic_apply_interior_once(const KMat& k, const NodeAt& node, int sy, int sz, float scale, Vec3f& kx,
                                            Vec3f& dg) {
  detail::elastic_once_all(k, node, sy, sz, scale, kx, dg, std::make_integer_sequence<int, 27>{},
                           std::make_integer_sequence<int, 8>{});
}

/// v with the components a node's constraint holds taken out: 0 at a held node, v minus its
/// part along the press direction n (unit) at a contact node, v elsewhere.
PALPSIM_HD Vec3f elastic_project(std::uint8_t flags, const Vec3f& n, const Vec3f& v) {
  if (flags & kElasticHeld) return Vec3f{0, 0, 0};
  if (flags & kElasticContact) return v - n * dot(v, n);
  return v;
}

/// How far along n (mm) the sphere of radius `r_mm` centred at `c` pushes a point at rest
/// at `p` (mm) to lie on its far side (the side n points to): the point leaves the sphere at
/// p + t n. Negative where p lies beside the sphere (no line along n through p meets it) or
/// where the sphere's far side lies behind p along n (p is not under the sphere).
PALPSIM_HD float elastic_sphere_push(const Vec3f& p, const Vec3f& c, const Vec3f& n, float r_mm) {
  const Vec3f d = p - c;
  const float along = dot(d, n);
  const Vec3f across = d - n * along;
  const float h2 = r_mm * r_mm - dot(across, across);
  if (h2 <= 0.0f) return -1.0f;
  return sqrtf(h2) - along;
}

/// A fresh press (no last field to start from, elastic_warm) starts with the skin nodes the
/// sphere pushes by at least this fraction of the tip's depth in its contact set. Hertz's
/// contact radius sqrt(R d) is where the sphere's surface lies d / 2 above its deepest point,
/// so the nodes inside it are pushed d / 2 or more; the whole overlap (radius sqrt(2 R d),
/// twice the area) pulls its outer ring, and the contact rounds took those nodes off a round
/// at a time. Nodes the start leaves out that the sphere still passes join in the rounds.
constexpr float kElasticFreshContactFraction = 0.5f;

/// Whether a skin node is in the contact set at a step's start: `t` is how far the sphere
/// pushes it along n (mm, elastic_sphere_push: <= 0 not under the sphere), `u_n` its start
/// field along n (mm), `was` whether it was in the last step's set, `warm` whether the step
/// starts from the last field (elastic_warm), `depth_mm` the tip's depth, `pulled` whether
/// the prediction has the finger pull it (elastic_predicted_pull). Warm: the nodes of the
/// last set still under the sphere that the prediction does not pull, and the others that
/// the start field leaves inside it, or within `touch_mm` of its surface (0 for the last
/// field as it was; a field moved with the tip, elastic_shifted, holds its contact nodes on
/// the new sphere to rounding); fresh: the nodes within Hertz's contact area
/// (kElasticFreshContactFraction).
PALPSIM_HD bool elastic_start_contact(float t, float u_n, bool was, bool warm, float depth_mm, float touch_mm,
                                      bool pulled = false) {
  if (!(t > 0.0f)) return false;
  if (warm) return was ? !pulled : t - u_n > -touch_mm;
  return t >= kElasticFreshContactFraction * depth_mm;
}

/// Whether the finger would pull a node of the last step's contact set in a step predicted
/// from the last unit press (ElasticPredict::kUnit, the tip moved `move_mm` along n and not
/// across it) as the tip backs off (move_mm < 0): the predicted field is the last press plus
/// move_mm times the unit press, so its reaction at the node (N along n) is `react_press`
/// plus move_mm times `react_unit`, theirs at the node; exact while the set stays, which is
/// what the first round solves. A node the tip leaves as it backs off would otherwise stay
/// in the set for a whole round (its solve, the pass that finds it pulled, and a second solve
/// without it). A tip going deeper keeps every node: a unit press stopped at its tolerance
/// (0.01 in the scenes, often with no CG step) can leave an edge node's reaction below 0,
/// which would take off a node the press still pushes.
PALPSIM_HD bool elastic_predicted_pull(float react_press, float react_unit, float move_mm) {
  return move_mm < 0.0f && react_press + move_mm * react_unit < 0.0f;
}

/// Whether a step starts from the last step's field (a warm start): there is one
/// (`have_field`, of the same model), the last step pressed (`last_pressing`; a field at
/// rest holds nothing to start from) and this step's VOI shares a node with the last one's
/// (a press elsewhere carries nothing over). Otherwise it starts as a fresh press.
PALPSIM_HD bool elastic_warm(bool have_field, bool last_pressing, const Voi& last, const Voi& voi) {
  if (!have_field || !last_pressing) return false;
  return voi.lo.x < last.lo.x + last.size.x && last.lo.x < voi.lo.x + voi.size.x &&
         voi.lo.y < last.lo.y + last.size.y && last.lo.y < voi.lo.y + voi.size.y &&
         voi.lo.z < last.lo.z + last.size.z && last.lo.z < voi.lo.z + voi.size.z;
}

/// How a step's solve starts from the last step's field when the tip pressed along the same n
/// then and now (the warm start's prediction): the contact nodes are placed on the sphere
/// anyway, so the prediction is what the free nodes start from. kUnit adds the last unit
/// press (the field of every contact node moved 1 mm along n, the set held: the exact
/// change for a sphere moved along n while the set stays) times the tip's move along n;
/// kScale scales the field by the depth's ratio (the field of a press grows about in
/// proportion to its depth). Either leaves CG the contact set's change at the contact's
/// edge, where the last field alone leaves it the whole press's change (palpsim-bench
/// deform --elastic measures both, and how far each ends from the converged field).
enum class ElasticPredict : int { kNone = 0, kUnit = 1, kScale = 2 };

/// The prediction of one step (elastic_prediction) and its factor: mm of tip motion along n
/// for kUnit, the depth's ratio for kScale; and the tip's move across n (voxels along the
/// grid axes, zero below kElasticShiftMinVox): the last field (and unit press) is moved with
/// the tip before either applies (elastic_shifted), as a frictionless finger sliding over
/// homogeneous tissue carries its field along unchanged.
struct ElasticPrediction {
  ElasticPredict kind = ElasticPredict::kNone;
  float factor = 0.0f;
  Vec3f shift_vox{0, 0, 0};
};

/// How near the sphere's surface (mm) a node outside the last set may start and join it at a
/// warm start (elastic_start_contact's touch_mm) for grid spacing `h_mm` along i: a field
/// moved with the tip (`shifted`, elastic_shifted) or predicted from the unit press (kUnit:
/// the last set's nodes each moved the tip's move along n) puts nodes on the sphere to
/// rounding, and a node the last step's rounds left there (free, on the sphere) would
/// otherwise miss the start by rounding and join a round later; the last field as it was, 0.
PALPSIM_HD float elastic_start_touch(bool shifted, ElasticPredict kind, float h_mm) {
  return shifted || kind == ElasticPredict::kUnit ? kElasticPenetrationVox * h_mm : 0.0f;
}

/// A tip's move across n shorter than this (voxels) moves no field: a press straight along n
/// keeps its last field bit for bit (rounding of positions of tens of mm is far below it).
constexpr float kElasticShiftMinVox = 1e-3f;

/// Whether a prediction's shift (ElasticPrediction::shift_vox) moves the field.
PALPSIM_HD bool elastic_shifts(const Vec3f& shift_vox) {
  return shift_vox.x != 0.0f || shift_vox.y != 0.0f || shift_vox.z != 0.0f;
}

/// Whether a step's start weighs the last set's reactions (elastic_predicted_pull): a step
/// predicted from the unit press (kUnit) whose field was not moved across n (`shift_vox`,
/// elastic_shifts: a moved field's set starts from its penetration alone).
PALPSIM_HD bool elastic_start_weighs_reactions(ElasticPredict kind, const Vec3f& shift_vox) {
  return kind == ElasticPredict::kUnit && !elastic_shifts(shift_vox);
}

/// The press a step predicts from (the last one) as the backends keep it.
struct ElasticLastPress {
  bool pressing = false;       // the last step's tip lay below the skin
  Vec3 tip_mm{0, 0, 0};        // its tip (mm along the grid axes from voxel 0)
  double depth_mm = 0;         // its depth along normal
  Vec3f normal{0, 0, 0};
};

/// The prediction of a step that presses `depth_mm` along `n` with its tip at `tip_mm` (mm
/// from voxel 0), after `last`: none unless the field is the last step's (`warm`) and both
/// pressed along n within 2.6 degrees (cos 0.999); kUnit when the last unit press is there
/// along that n as well (`unit_along_n`), else kScale, its ratio held to [0, 2] so that a
/// field of a first graze (a few hundredths of a mm) is not blown up into a guess worse
/// than none. The tip's move across n in voxels of `h_mm` is the field's shift.
inline ElasticPrediction elastic_prediction(const ElasticLastPress& last, bool warm, bool unit_along_n,
                                            const Vec3& tip_mm, double depth_mm, const Vec3f& n, const Vec3& h_mm) {
  ElasticPrediction p;
  if (!warm || !last.pressing || !(depth_mm > 1e-6) || !(last.depth_mm > 1e-6) || dot(n, last.normal) <= 0.999f)
    return p;
  const Vec3 move = tip_mm - last.tip_mm;
  const Vec3 across = move - Vec3(n) * dot(move, Vec3(n));
  const Vec3f shift{float(across.x / h_mm.x), float(across.y / h_mm.y), float(across.z / h_mm.z)};
  if (dot(shift, shift) >= kElasticShiftMinVox * kElasticShiftMinVox) p.shift_vox = shift;
  if (unit_along_n) {
    p.kind = ElasticPredict::kUnit;
    p.factor = float(dot(move, Vec3(n)));
  } else {
    p.kind = ElasticPredict::kScale;
    const double ratio = depth_mm / last.depth_mm;
    p.factor = float(ratio < 2.0 ? ratio : 2.0);
  }
  return p;
}

/// A superposed step: n within this cosine of the unit press's (an angle of 4.5e-4 rad, which
/// moves a contact node's prescribed part along n by under 5e-4 of its move across n).
constexpr float kElasticSuperposeCos = 1.0f - 1e-7f;

/// Whether a warm step may superpose, as far as the host can tell (the device adds that the
/// step's start left the contact set as it was): the press moved along n alone (kUnit, no
/// shift), with n within kElasticSuperposeCos of the unit press's (`unit_cos`), since a
/// step that solved, converged and settled (`last_solved`, kept through superposed steps).
/// Linear elasticity then holds the answer already: the last press plus `factor` unit
/// presses meets every constraint (each contact node's push grows by the tip's move along
/// n, the unit press moves each by 1 mm along n) and K u = 0 holds as well as each solve
/// left it, so no solve runs and the force grows by factor times the stiffness. Its
/// residual is the last solve's plus factor times the unit press's (solved to
/// `unit_tolerance`), so the superposed moves since that solve (`superposed_mm`, this one's
/// included) stay within tolerance / unit_tolerance of the depth: the residual then stays
/// within about twice the tolerance, and the next step past that solves.
PALPSIM_HD bool elastic_superposes(const ElasticPrediction& pred, float unit_cos, bool last_solved,
                                   double superposed_mm, double depth_mm, float tolerance, float unit_tolerance) {
  if (pred.kind != ElasticPredict::kUnit || elastic_shifts(pred.shift_vox) || !(unit_cos >= kElasticSuperposeCos) ||
      !last_solved || !(depth_mm > 0))
    return false;
  const double moved = superposed_mm + fabs(double(pred.factor));
  return moved * double(unit_tolerance) <= double(tolerance) * depth_mm;
}

/// The value at node (i, j, k) of a field `load(i, j, k)` (0 beyond its VOI: the loader's)
/// moved by `shift_vox`: trilinear at the node less the shift. The contact set does not move
/// with it: a shifted start's set is the nodes the moved field leaves inside the sphere or on
/// it (elastic_start_contact with no last set and a touch of kElasticPenetrationVox; the
/// last set moved to the nearest nodes cost the bench's slide half again as many CG steps
/// at the set's edge).
template <typename Load>
PALPSIM_HD Vec3f elastic_shifted(const Load& load, int i, int j, int k, const Vec3f& shift_vox) {
  return trilinear<Vec3f>(load, Vec3f{float(i) - shift_vox.x, float(j) - shift_vox.y, float(k) - shift_vox.z});
}

/// A node's start value under a prediction: its last value `u`, and its last unit press
/// `unit` (read only for kUnit), each already shifted when the prediction shifts.
PALPSIM_HD Vec3f elastic_predicted(ElasticPredict kind, float factor, const Vec3f& u, const Vec3f& unit) {
  if (kind == ElasticPredict::kUnit) return u + unit * factor;
  if (kind == ElasticPredict::kScale) return u * factor;
  return u;
}

// The force and stiffness by reciprocity (deform.elastic.stiffness_tolerance above 0). Let
// w be the unit press (every contact node 1 mm along n, the same set) and u the press. At
// the exact solutions K u and K w vanish on the free components, so Betti's theorem gives
// the finger's push F = sum over contact nodes of (K u) . n = w . K u = u . K w = sum of
// push_i (K w)_i . n, and the stiffness k = sum of (K w)_i . n = w . K w. Written with the
// residual r of an inexact w (K w = -r on the free components), F = sum push_i (K w)_i . n
// - u . r and k = sum (K w)_i . n - w . r are the bilinear and quadratic forms themselves:
// with u and w each off their solution by an error in the free components, F is off by the
// product of the two errors (the first-order terms pair a free-only error with a residual
// that vanishes there), and k by w's error squared in the energy norm (k >= the exact one).
// So the unit press may stop ten times earlier than the press for the same accuracy of
// both, and the force no longer depends on how far u's solve went.

/// Nodes of the next coarser level along one axis of `fine` nodes: its node I lies on fine
/// node 2 I; an even count gets one more node, 2 I = fine, just beyond the fine grid (held:
/// it stands for the fine level's held face one fine spacing before it).
PALPSIM_HD int elastic_coarse_nodes(int fine) { return fine % 2 == 0 ? fine / 2 + 1 : (fine + 1) / 2; }

/// The levels of one VOI's multigrid and where the coarse levels lie in one buffer.
struct ElasticPlan {
  int levels = 0;
  Vec3i size[kElasticMaxLevels];
  long long offset[kElasticMaxLevels];  // first node of level l in the coarse buffers (level 0: 0, its own buffers)
  long long coarse_count = 0;           // nodes of all levels >= 1
};

/// A coarse level has at least this many nodes along every axis: a level of 3 (one node
/// inside its held faces) costs each V-cycle passes for nothing (the accuracy study's VOI 64 of
/// 1 mm voxels took the same CG steps without it). At 5 the phantom's VOI (64 x 49 x 64
/// nodes) loses its 5 x 4 x 5 level as well: a step from rest then takes 2 + 1 CG steps
/// instead of 3 + 1, but ends 5.5 % from converged in u instead of 2.2 %
/// (bench/results/elastic-coarsest-5-2026-12-06-h200-374ee99.txt).
constexpr int kElasticCoarsestNodes = 4;

/// The plan for a VOI of `voi_size` nodes: coarsen while every axis of the next level keeps
/// at least kElasticCoarsestNodes nodes, at most kElasticMaxLevels levels.
PALPSIM_HD ElasticPlan elastic_plan(const Vec3i& voi_size) {
  ElasticPlan p;
  p.size[0] = voi_size;
  p.offset[0] = 0;
  p.levels = 1;
  long long at = 0;
  while (p.levels < kElasticMaxLevels) {
    const Vec3i& s = p.size[p.levels - 1];
    const Vec3i c{elastic_coarse_nodes(s.x), elastic_coarse_nodes(s.y), elastic_coarse_nodes(s.z)};
    if (c.x < kElasticCoarsestNodes || c.y < kElasticCoarsestNodes || c.z < kElasticCoarsestNodes) break;
    p.size[p.levels] = c;
    p.offset[p.levels] = at;
    at += (long long)c.x * c.y * c.z;
    ++p.levels;
  }
  p.coarse_count = at;
  return p;
}

/// Trilinear prolongation: the value at fine node (i, j, k) of the coarse field
/// `load_c(I, J, K)` (coarse node I on fine node 2 I; coarse nodes beyond the coarse grid
/// read as 0 through the loader).
template <typename LoadC>
PALPSIM_HD Vec3f elastic_prolong(const LoadC& load_c, int i, int j, int k) {
  const int ci0 = i >> 1, cj0 = j >> 1, ck0 = k >> 1;
  const int ni = (i & 1) ? 2 : 1, nj = (j & 1) ? 2 : 1, nk = (k & 1) ? 2 : 1;
  const float wi = (i & 1) ? 0.5f : 1.0f, wj = (j & 1) ? 0.5f : 1.0f, wk = (k & 1) ? 0.5f : 1.0f;
  Vec3f v{0, 0, 0};
  for (int c = 0; c < nk; ++c)
    for (int b = 0; b < nj; ++b)
      for (int a = 0; a < ni; ++a) v += load_c(ci0 + a, cj0 + b, ck0 + c) * (wi * wj * wk);
  return v;
}

/// Restriction, the transpose of elastic_prolong(): coarse node (I, J, K) gathers the fine
/// nodes 2 I + {-1, 0, 1} along each axis with weights 1/2, 1, 1/2; `load_f` reads a fine
/// node and returns 0 beyond the fine grid.
template <typename LoadF>
PALPSIM_HD Vec3f elastic_restrict(const LoadF& load_f, int ci, int cj, int ck) {
  Vec3f v{0, 0, 0};
  for (int c = -1; c <= 1; ++c)
    for (int b = -1; b <= 1; ++b)
      for (int a = -1; a <= 1; ++a) {
        const float w = (a == 0 ? 1.0f : 0.5f) * (b == 0 ? 1.0f : 0.5f) * (c == 0 ? 1.0f : 0.5f);
        v += load_f(2 * ci + a, 2 * cj + b, 2 * ck + c) * w;
      }
  return v;
}

/// A coarse cell's modulus (kPa): the mean of the fine cells it covers (fine cells with
/// lowest corner 2 C + {0, 1}^3 that lie inside the fine grid's cells); 0 where none does.
template <typename FineE>
PALPSIM_HD float elastic_coarse_cell_e(const FineE& fine_e, const Vec3i& fine_size, int ci, int cj, int ck) {
  float sum = 0.0f;
  int n = 0;
  for (int c = 0; c < 8; ++c) {
    const Vec3i o = elastic_corner(c);
    const int fi = 2 * ci + o.x, fj = 2 * cj + o.y, fk = 2 * ck + o.z;
    if (fi + 1 >= fine_size.x || fj + 1 >= fine_size.y || fk + 1 >= fine_size.z) continue;
    sum += fine_e(fi, fj, fk);
    ++n;
  }
  return n > 0 ? sum / float(n) : 0.0f;
}

/// The unit press's start where no last unit press along n is kept: the press's field times
/// this (1 / the tip's depth in mm, 0 at no depth), the unit press's shape to first order.
PALPSIM_HD float elastic_unit_start_scale(double depth_mm) { return depth_mm > 0 ? float(1.0 / depth_mm) : 0.0f; }

/// A coarse node's flags from the fine node it lies on (2 I): held beyond the fine grid or
/// where the fine node is held (but as far air); in contact where it is.
PALPSIM_HD std::uint8_t elastic_coarse_flags(std::uint8_t fine_flags, bool beyond) {
  if (beyond) return kElasticHeld;
  // far air is held on level 0 only: a coarse node held there would pin the coarse
  // correction of the skin within its cell (level 2's cells span four voxels)
  if (fine_flags & kElasticAir) return 0;
  return std::uint8_t(fine_flags & (kElasticHeld | kElasticContact));
}

}  // namespace palpsim::deform
