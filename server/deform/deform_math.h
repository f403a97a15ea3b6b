// The per-voxel math of deformation, written once and compiled by both backends
// (g++ for server/deform, nvcc for cuda/): the ChainMail restriction of one
// neighbour, the material function, one relaxation update, trilinear sampling and
// the inversion of a point (Newton steps). Loops, memory layout and reductions live
// in each backend. Displacements are in voxel edge lengths along the grid axes.
#pragma once

#include <cmath>

#include "core/hd.h"
#include "core/vec3.h"

namespace palpsim::deform {

/// A box of voxels of the patient grid: the volume of interest (VOI) of one step.
/// `lo` is the first voxel (patient index), `size` the extent; local index i fastest.
struct Voi {
  Vec3i lo{0, 0, 0};
  Vec3i size{0, 0, 0};

  /// Number of voxels in the box.
  PALPSIM_HD long long count() const { return (long long)size.x * size.y * size.z; }
  /// True when the local index (i, j, k) lies inside the box.
  PALPSIM_HD bool contains(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < size.x && j < size.y && k < size.z;
  }
  /// Local linear index of local voxel (i, j, k).
  PALPSIM_HD long long index(int i, int j, int k) const {
    return ((long long)k * size.y + j) * size.x + i;
  }
  /// Equality of boxes.
  PALPSIM_HD bool operator==(const Voi& o) const { return lo == o.lo && size == o.size; }
};

/// ChainMail restrictions expressed on displacements (voxel). For neighbours one
/// voxel apart along axis a, with e above n (e = n + 1 along a), the positions obey
/// minDist <= x_e,a - x_n,a <= maxDist and |x_e,b - x_n,b| <= maxSheer for b != a;
/// since x = index + u, that is axial_lo <= u_e,a - u_n,a <= axial_hi.
struct ChainMailLimits {
  float axial_lo = -0.5f;  // minDist - 1
  float axial_hi = 0.5f;   // maxDist - 1
  float sheer = 0.5f;      // maxSheer
};

/// Limits from the scene's minDist, maxDist and maxSheer (voxel edge lengths).
inline ChainMailLimits chainmail_limits(double min_dist, double max_dist, double max_sheer) {
  return {float(min_dist - 1.0), float(max_dist - 1.0), float(max_sheer)};
}

/// Clamps v into [lo, hi] (lo <= hi); plain comparisons so both compilers agree bit for bit.
PALPSIM_HD float clamp_to(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

/// The larger of two ints (std::max is not a device function).
PALPSIM_HD int max_int(int a, int b) { return a > b ? a : b; }

/// The six neighbour offsets in the fixed order every backend uses: -i, +i, -j, +j, -k, +k.
/// Neighbour q lies along axis q / 2, below the element for even q.
PALPSIM_HD int neighbour_axis(int q) { return q >> 1; }
PALPSIM_HD bool neighbour_below(int q) { return (q & 1) == 0; }
PALPSIM_HD Vec3i neighbour_offset(int q) {
  const int s = (q & 1) ? 1 : -1;
  return q < 2 ? Vec3i{s, 0, 0} : (q < 4 ? Vec3i{0, s, 0} : Vec3i{0, 0, s});
}

/// Moves the displacement `u` of an element the least that the neighbour with
/// displacement `un` (along `axis`, below the element when `below`) asks: per component,
/// a neighbour moved towards -inf pulls the element to at most its box's upper end, one
/// moved towards +inf to at least its lower end, one at rest asks nothing. Per component
/// the restrictions are difference constraints, and with one grabbed element (d) each
/// component moves one way only, so the sweeps reach their solution nearest rest,
/// min(0, d + shortest path) for d < 0 (max(0, d - shortest path) for d > 0), where
/// every restriction holds; clamping into both ends let two neighbours' disjoint boxes
/// leave an element violating one of them (server/deform/README.md, "Sweeps").
PALPSIM_HD void chainmail_clamp(Vec3f& u, const Vec3f& un, int axis, bool below, const ChainMailLimits& l) {
#if defined(__CUDACC__)
#pragma unroll
#endif
  for (int b = 0; b < 3; ++b) {
    float lo, hi;
    if (b != axis) {
      // sheer: the same coordinate within maxSheer of the neighbour's
      lo = un[b] - l.sheer;
      hi = un[b] + l.sheer;
    } else if (below) {
      // the neighbour is below: minDist <= x_e - x_n <= maxDist
      lo = un[b] + l.axial_lo;
      hi = un[b] + l.axial_hi;
    } else {
      // the neighbour is above: minDist <= x_n - x_e <= maxDist
      lo = un[b] - l.axial_hi;
      hi = un[b] - l.axial_lo;
    }
    if (un[b] < 0.0f)
      u[b] = u[b] < hi ? u[b] : hi;
    else if (un[b] > 0.0f)
      u[b] = u[b] > lo ? u[b] : lo;
  }
}

/// The material function of relaxation: 1 for soft tissue, falling smoothly to 0
/// across the bone threshold (a continuous Heaviside step of width `width`, in the
/// intensity's units), and exactly 0 on the bone mask so bone never diffuses.
PALPSIM_HD float material_weight(float intensity, bool bone, float threshold, float width) {
  if (bone) return 0.0f;
  return 0.5f * (1.0f - tanhf((intensity - threshold) / width));
}

/// The explicit scheme's stable limit of the relaxation step: u' = u + s m (sum of
/// the six neighbours - 6 u) keeps non-negative weights for s m <= 1/6, m <= 1.
constexpr double kRelaxStableStep = 1.0 / 6.0;

/// The sum of the six neighbours of element e of a box (strides 1, sx, sxy) in the fixed
/// order -i, +i, -j, +j, -k, +k, from `zero`: for an element off the box's faces, the
/// same sums as adding each neighbour inside the box in that order (relaxation's and
/// multigrid's), without the tests.
template <typename T>
PALPSIM_HD T sum6_inner(const T* v, long long e, long long sx, long long sxy, T zero) {
  T s = zero;
  s += v[e - 1];
  s += v[e + 1];
  s += v[e - sx];
  s += v[e + sx];
  s += v[e - sxy];
  s += v[e + sxy];
  return s;
}

/// One explicit diffusion update of a voxel: `sum6` is the sum of the six neighbours'
/// displacements (zero outside the VOI), `step_weight` = relax_step * material_weight.
PALPSIM_HD Vec3f relax_update(const Vec3f& u, const Vec3f& sum6, float step_weight) {
  return Vec3f{u.x + step_weight * (sum6.x - 6.0f * u.x), u.y + step_weight * (sum6.y - 6.0f * u.y),
               u.z + step_weight * (sum6.z - 6.0f * u.z)};
}

/// Trilinear interpolation of `load(i, j, k)` (returns T: float or Vec3f) at the
/// continuous index p; the loader decides what lies outside its data.
template <typename T, typename Load>
PALPSIM_HD T trilinear(const Load& load, const Vec3f& p) {
  const float fx0 = floorf(p.x), fy0 = floorf(p.y), fz0 = floorf(p.z);
  const int i = int(fx0), j = int(fy0), k = int(fz0);
  const float fx = p.x - fx0, fy = p.y - fy0, fz = p.z - fz0;
  const float gx = 1.0f - fx, gy = 1.0f - fy, gz = 1.0f - fz;
  // blend along i, then j, then k
  const T c00 = load(i, j, k) * gx + load(i + 1, j, k) * fx;
  const T c10 = load(i, j + 1, k) * gx + load(i + 1, j + 1, k) * fx;
  const T c01 = load(i, j, k + 1) * gx + load(i + 1, j, k + 1) * fx;
  const T c11 = load(i, j + 1, k + 1) * gx + load(i + 1, j + 1, k + 1) * fx;
  const T c0 = c00 * gy + c10 * fy;
  const T c1 = c01 * gy + c11 * fy;
  return c0 * gz + c1 * fz;
}

/// How far (neighbour steps, L1) from the grabbed element explicit relaxation step `it`
/// (0-based) of `iterations` must update, for a field nonzero only within `reach` steps
/// of it (ChainMail moves its wave one neighbour a sweep, so its field reaches as far as
/// its sweeps; each relaxation step one neighbour further): reach + it + 1, and in step 0
/// reach + iterations, so that step 0 sees every element a later step updates (the CUDA
/// kernel computes the weights there). Beyond it the update leaves u = 0 as it is.
/// reach < 0 (a field of unknown extent): every element.
PALPSIM_HD int relax_reach(int reach, int it, int iterations) {
  if (reach < 0) return 1 << 30;
  const int r = reach < (1 << 24) ? reach : (1 << 24);
  return r + (it == 0 ? (iterations > 1 ? iterations : 1) : it + 1);
}

/// `load` at the source p of an inversion: trilinear, except at a voxel centre (where
/// invert_point() leaves a voxel at rest) the voxel itself, the blend's value there
/// (its other seven weights are 0), read alone.
template <typename T, typename Load>
PALPSIM_HD T sample_at_source(const Load& load, const Vec3f& p) {
  const float fx0 = floorf(p.x), fy0 = floorf(p.y), fz0 = floorf(p.z);
  if (p.x == fx0 && p.y == fy0 && p.z == fz0) return load(int(fx0), int(fy0), int(fz0));
  return trilinear<T>(load, p);
}

/// A voxel whose inversion residual exceeds this (voxel) counts as unresolved: the
/// inversion did not find where its tissue came from (a fold: the deformation is not
/// invertible there).
constexpr float kInvertResolvedVox = 0.1f;

/// Trilinear blend of the eight corner values `c` of one cell (index bit 0: +i, bit 1:
/// +j, bit 2: +k) at local coordinates (fx, fy, fz) in [0, 1], with its partial
/// derivatives along i, j, k (the columns of the Jacobian of the blend inside the cell).
PALPSIM_HD Vec3f cell_blend(const Vec3f c[8], float fx, float fy, float fz, Vec3f grad[3]) {
  const float gx = 1.0f - fx, gy = 1.0f - fy, gz = 1.0f - fz;
  // along i first (as trilinear()), so that the value is the same bits as trilinear()'s
  const Vec3f c00 = c[0] * gx + c[1] * fx, c10 = c[2] * gx + c[3] * fx;
  const Vec3f c01 = c[4] * gx + c[5] * fx, c11 = c[6] * gx + c[7] * fx;
  const Vec3f c0 = c00 * gy + c10 * fy, c1 = c01 * gy + c11 * fy;
  // d/di: differences along i blended in j and k; likewise for j and k
  const Vec3f d00 = c[1] - c[0], d10 = c[3] - c[2], d01 = c[5] - c[4], d11 = c[7] - c[6];
  grad[0] = (d00 * gy + d10 * fy) * gz + (d01 * gy + d11 * fy) * fz;
  grad[1] = (c10 - c00) * gz + (c11 - c01) * fz;
  grad[2] = c1 - c0;
  return c0 * gz + c1 * fz;
}

/// The eight corner displacements of the cell whose lowest corner is voxel (i, j, k), in
/// cell_blend()'s order.
template <typename LoadU>
PALPSIM_HD void load_cell(const LoadU& load_u, int i, int j, int k, Vec3f c[8]) {
  for (int q = 0; q < 8; ++q) c[q] = load_u(i + (q & 1), j + ((q >> 1) & 1), k + (q >> 2));
}

/// Trilinear interpolation of the displacement `load_u` at p with its partial
/// derivatives along i, j, k (the columns of the Jacobian of u inside p's cell).
template <typename LoadU>
PALPSIM_HD Vec3f trilinear_with_gradient(const LoadU& load_u, const Vec3f& p, Vec3f grad[3]) {
  const float fx0 = floorf(p.x), fy0 = floorf(p.y), fz0 = floorf(p.z);
  Vec3f c[8];
  load_cell(load_u, int(fx0), int(fy0), int(fz0), c);
  return cell_blend(c, p.x - fx0, p.y - fy0, p.z - fz0, grad);
}

/// The smallest determinant of I + grad u (the trilinear displacement field's Jacobian;
/// positive where the deformation keeps orientation, no fold) in the cell whose lowest
/// corner is local voxel (i, j, k), at its eight corners and its centre. At a corner the
/// gradient is taken 1e-3 voxel inside the cell, so it is the cell's own.
template <typename LoadU>
PALPSIM_HD float cell_min_det(const LoadU& load_u, int i, int j, int k) {
  float worst = 3.4e38f;
  for (int c = 0; c <= 8; ++c) {
    // corner c (bit 0: +i, bit 1: +j, bit 2: +k), then the centre
    const float fi = c == 8 ? 0.5f : ((c & 1) ? 0.999f : 0.001f);
    const float fj = c == 8 ? 0.5f : ((c & 2) ? 0.999f : 0.001f);
    const float fk = c == 8 ? 0.5f : ((c & 4) ? 0.999f : 0.001f);
    Vec3f g[3];
    trilinear_with_gradient(load_u, Vec3f(float(i) + fi, float(j) + fj, float(k) + fk), g);
    // the columns of I + grad u: g[a] is du/d(axis a); det = a . (b x e)
    const Vec3f a = g[0] + Vec3f(1, 0, 0), b = g[1] + Vec3f(0, 1, 0), e = g[2] + Vec3f(0, 0, 1);
    const float det = a.x * (b.y * e.z - b.z * e.y) - b.x * (a.y * e.z - a.z * e.y) + e.x * (a.y * b.z - a.z * b.y);
    worst = det < worst ? det : worst;
  }
  return worst;
}

/// Whether cell (i, j, k) may fold under u (voxels, `load_u(i, j, k)`): false when
/// along every edge each component of u changes by less than kCellNoFoldEdgeVox. Each
/// entry of grad u anywhere in the cell is a mean of four such edge changes, so I + grad u
/// is then strictly diagonally dominant by rows with a margin (1 - 0.3 = 2 x 0.3 + 0.1),
/// its determinant at least 0.1^3 everywhere in the cell: cell_min_det() > 0 without
/// evaluating it. A cell that does not move at all may not fold either.
constexpr float kCellNoFoldEdgeVox = 0.3f;
template <typename LoadU>
PALPSIM_HD bool cell_may_fold(const LoadU& load_u, int i, int j, int k) {
  Vec3f c[8];
  for (int n = 0; n < 8; ++n) c[n] = load_u(i + (n & 1), j + ((n >> 1) & 1), k + ((n >> 2) & 1));
  // the twelve edges: corner pairs differing in one bit
  for (int n = 0; n < 8; ++n)
    for (int b = 1; b < 8; b <<= 1) {
      if (n & b) continue;
      const Vec3f d = c[n | b] - c[n];
      if (fabsf(d.x) >= kCellNoFoldEdgeVox || fabsf(d.y) >= kCellNoFoldEdgeVox || fabsf(d.z) >= kCellNoFoldEdgeVox)
        return true;
    }
  return false;
}

/// Whether cell (i, j, k) is folded under u (voxels, `load_u(i, j, k)`): det(I + grad u) <= 0
/// somewhere in it, evaluated only where cell_may_fold() lets it be (the elastic step's
/// count of folded cells, the same rule on both backends).
template <typename LoadU>
PALPSIM_HD bool cell_folded(const LoadU& load_u, int i, int j, int k) {
  return cell_may_fold(load_u, i, j, k) && !(cell_min_det(load_u, i, j, k) > 0.0f);
}

/// Untangling (issue 8, section 4): a cell counts as folded, and its eight elements start
/// the untangling, when its cell_min_det() is at most this: a margin above 0, so that a
/// cell that untangling leaves alone keeps its inside one to one with room for float
/// rounding and for the nine sample points missing a det dip between them.
constexpr float kUntangleFoldDet = 0.05f;

/// Untangling's smallest spacing (voxel) of two face neighbours along their axis: an
/// element farther from the grabbed one keeps at least this distance beyond the nearer
/// one, so no element passes its neighbour on the way to the grabbed element. Above 2/3:
/// where the three edges of a corner are compressed along one push direction (a rank-one
/// change, I + d c^T), det = 1 - the sum of the three compressions, which stays positive
/// only while each is below 1/3 (measured: 0.5 and 0.6 left folds in 39 and 29 of the 40
/// random pushes of tests/unit/deform_untangle_test.cpp, 0.7 in none).
constexpr float kUntangleMinSpacing = 0.7f;

/// How far beyond the smallest spacing (voxel) untangle_pull() puts an element it moves,
/// so that float rounding and the pulls of its other neighbours do not bring it back
/// under the limit by a hair, sweep after sweep (a round would then never go quiet).
constexpr float kUntangleMargin = 0.05f;

/// Untangling's cap on sweeps per round (each moves the front one element further from
/// the grabbed one, so a press of d voxels needs about d / (1 - kUntangleMinSpacing -
/// kUntangleMargin) + 1: the Table 1 press, 7.5 voxel, took 30).
constexpr int kUntangleMaxSweeps = 128;

/// Untangling's cap on rounds (each finds the folded cells again and sweeps from their
/// corners); a round after the first sees only folds that the previous one made.
constexpr int kUntangleMaxRounds = 4;

/// True when the eight corners of the cell whose lowest corner is local voxel (i, j, k)
/// are soft tissue (`soft(i, j, k)`); cells touching bone are not untangled (bone
/// enforces nothing, so soft tissue may pass it).
template <typename Soft>
PALPSIM_HD bool untangle_cell_soft(const Soft& soft, int i, int j, int k) {
  for (int c = 0; c < 8; ++c)
    if (!soft(i + (c & 1), j + ((c >> 1) & 1), k + (c >> 2))) return false;
  return true;
}

/// True when local voxel (i, j, k) is a corner of a folded cell: `folded(a, b, c)` tells
/// whether the cell with lowest corner (a, b, c) is folded (cells lie in the VOI, their
/// lowest corner at most size - 2).
template <typename Folded>
PALPSIM_HD bool untangle_is_seed(const Folded& folded, const Voi& voi, int i, int j, int k) {
  for (int c = 0; c < 8; ++c) {
    const int a = i - (c & 1), b = j - ((c >> 1) & 1), d = k - (c >> 2);
    if (a >= 0 && b >= 0 && d >= 0 && a + 1 < voi.size.x && b + 1 < voi.size.y && d + 1 < voi.size.z && folded(a, b, d))
      return true;
  }
  return false;
}

/// Pulls the displacement `u` of an element towards that of its neighbour `un` along
/// `axis` (the neighbour lies between the element and the grabbed one, below the element
/// when `below`) when the two are closer than kUntangleMinSpacing along the axis
/// (x_e - x_n for a neighbour below, x_n - x_e for one above), to kUntangleMinSpacing +
/// kUntangleMargin; the whole difference u - un is scaled, so the pair's shear shrinks
/// with it. Nothing changes when the spacing is kept already.
PALPSIM_HD void untangle_pull(Vec3f& u, const Vec3f& un, int axis, bool below) {
  // the pair's spacing beyond 1 voxel, signed towards the element: spacing - 1
  const float diff = below ? u[axis] - un[axis] : un[axis] - u[axis];
  if (!(diff < kUntangleMinSpacing - 1.0f)) return;
  const float s = (kUntangleMinSpacing + kUntangleMargin - 1.0f) / diff;  // in (0, 1): diff < spacing - 1 < 0
  u = Vec3f{un.x + s * (u.x - un.x), un.y + s * (u.y - un.y), un.z + s * (u.z - un.z)};
}

/// The backtracking halvings of one inversion step before it gives up on the step.
constexpr int kInvertHalvings = 6;

/// The residual (voxel) at which the inversion's Newton steps stop: near float rounding
/// of VOI coordinates (a float's spacing is 4e-6 at 32-64 voxels), so a further step
/// finds nothing lower and costs 2 (kInvertHalvings + 1) evaluations of u to learn it,
/// most of the inversion's work where a deep press moves most of the VOI; J moves by
/// 1e-4 voxel times I's gradient at most (0.1 HU at a 1000 HU/voxel bone edge).
constexpr float kInvertConvergedVox = 1e-5f;

/// Damped Newton descent on a residual r(p) (voxel) with Jacobian A = I + g (columns
/// I + g[a]): `eval(q, g)` returns r(q) and writes g at q; `project(q)` maps a trial point
/// into the domain. Each iteration tries Newton's step (where A is invertible and keeps
/// orientation), then steepest descent of |r|^2 (-A^T r, scaled to r's length: where A
/// is singular or reversed, or at a cell face where Newton's step overshoots the kink),
/// each full, then halved up to kInvertHalvings times, and takes the first trial whose
/// residual is lower; so the residual never grows from one iteration to the next. Stops
/// after `iterations`, once |r| <= `done` (0: only at r = 0), or when no trial lowers it
/// (a local minimum of |r| as far as these steps can tell); returns |r| at the final p.
template <typename Eval, typename Project>
PALPSIM_HD float newton_descend(const Eval& eval, const Project& project, Vec3f& p, int iterations, float done = 0.0f) {
  Vec3f g[3];
  Vec3f r = eval(p, g);
  float rn = sqrtf(r.x * r.x + r.y * r.y + r.z * r.z);
  for (int it = 0; it < iterations && rn > done; ++it) {
    // the step d solving (I + grad u) d = -r by Cramer's rule
    const Vec3f a{1.0f + g[0].x, g[0].y, g[0].z}, b{g[1].x, 1.0f + g[1].y, g[1].z}, c{g[2].x, g[2].y, 1.0f + g[2].z};
    // columns a, b, c of A = I + grad u: det = a . (b x c)
    const Vec3f bc{b.y * c.z - b.z * c.y, b.z * c.x - b.x * c.z, b.x * c.y - b.y * c.x};
    const Vec3f ca{c.y * a.z - c.z * a.y, c.z * a.x - c.x * a.z, c.x * a.y - c.y * a.x};
    const Vec3f ab{a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
    const float det = a.x * bc.x + a.y * bc.y + a.z * bc.z;
    bool moved = false;
    for (int dir = det > 1e-3f ? 0 : 1; dir < 2 && !moved; ++dir) {
      Vec3f d;
      if (dir == 0) {
        // A^-1 has rows bc, ca, ab over det
        d = Vec3f{-(bc.x * r.x + bc.y * r.y + bc.z * r.z) / det, -(ca.x * r.x + ca.y * r.y + ca.z * r.z) / det,
                  -(ab.x * r.x + ab.y * r.y + ab.z * r.z) / det};
      } else {
        d = -Vec3f{a.x * r.x + a.y * r.y + a.z * r.z, b.x * r.x + b.y * r.y + b.z * r.z,
                   c.x * r.x + c.y * r.y + c.z * r.z};
        const float dn = sqrtf(d.x * d.x + d.y * d.y + d.z * d.z);
        if (!(dn > 0.0f)) break;
        d = d * (rn / dn);
      }
      for (int h = 0; h <= kInvertHalvings && !moved; ++h) {
        const Vec3f q = project(p + d);
        Vec3f gq[3];
        const Vec3f rq = eval(q, gq);
        const float qn = sqrtf(rq.x * rq.x + rq.y * rq.y + rq.z * rq.z);
        if (qn < rn) {
          p = q;
          r = rq;
          rn = qn;
          g[0] = gq[0];
          g[1] = gq[1];
          g[2] = gq[2];
          moved = true;
        }
        d = d * 0.5f;
      }
    }
    if (!moved) break;  // no step lowers the residual: p is as good as it gets
  }
  return rn;
}

/// Inverts the displacement at the deformed point y (continuous VOI-local index): finds
/// the undeformed point p with p + u(p) = y, starting at p = y; `load_u` gives the
/// displacement of a VOI-local voxel (zero outside the VOI). `iterations` steps of
/// newton_descend() on p + u(p) - y with the Jacobian I + grad u of the trilinear field.
/// The paper's fixed-point iteration p <- y - u(p) converges only where |grad u| < 1 and
/// swings between two points next to a grabbed element stretched by more than that (the
/// Table 1 press: 450 voxels, 7.5 voxel); Newton converges wherever the deformation is
/// locally invertible and its start lies in the source's basin. Returns p and writes
/// |p + u(p) - y| (voxel), the inversion residual, to `residual`.
template <typename LoadU>
PALPSIM_HD Vec3f invert_point(const LoadU& load_u, const Vec3f& y, int iterations, float& residual) {
  // a voxel centre at rest (u = 0 there) is its own source: Newton's first evaluation
  // finds r = 0 there (the blend's other seven weights are 0); its one voxel is read
  // instead of the cell's eight and the gradient (most of a VOI away from the dent)
  const float fx0 = floorf(y.x), fy0 = floorf(y.y), fz0 = floorf(y.z);
  if (y.x == fx0 && y.y == fy0 && y.z == fz0) {
    const Vec3f u0 = load_u(int(fx0), int(fy0), int(fz0));
    if (u0.x == 0.0f && u0.y == 0.0f && u0.z == 0.0f) {
      residual = 0.0f;
      return y;
    }
  }
  Vec3f p = y;
  residual = newton_descend([&](const Vec3f& q, Vec3f g[3]) { return q + trilinear_with_gradient(load_u, q, g) - y; },
                            [](const Vec3f& q) { return q; }, p, iterations, kInvertConvergedVox);
  return p;
}

/// The residual (voxel) above which Newton's voxel goes to the cell search of
/// invert_voxel(): a fifth of the goal of issue 8 (max residual 0.05 voxel), so that a
/// voxel left to Newton is well within it; also where the search stops (a source within
/// it ends the search).
constexpr float kInvertSearchVox = 0.01f;

/// Newton iterations of the solve inside one cell of the search (local coordinates, the
/// trilinear blend is smooth there: quadratic convergence from the centre in 4-6), and
/// of each start of its second pass, in cells stretched over thousands of voxels, whose
/// source may lie a thousandth of the cell from a corner.
constexpr int kInvertCellIterations = 12;
constexpr int kInvertFineIterations = 32;

/// Sub-cells per axis of invert_in_cell()'s second pass: 64 starts, each within 1/8 cell
/// (along each axis) of any point of its sub-cell.
constexpr int kInvertSubcells = 4;

/// True when y (local coordinates of the cell with corners `c`) lies in the bounding box,
/// grown by kInvertSearchVox, of the deformed corners of the sub-cell [lo, lo + h]^3 (local
/// coordinates): the blend of a sub-cell is a trilinear patch, so its image lies in the
/// convex hull of its corners' images too.
PALPSIM_HD bool subcell_holds(const Vec3f c[8], const Vec3f& lo, float h, const Vec3f& yl) {
  Vec3f bl{3.4e38f, 3.4e38f, 3.4e38f}, bh{-3.4e38f, -3.4e38f, -3.4e38f};
  for (int q = 0; q < 8; ++q) {
    const Vec3f f{lo.x + ((q & 1) ? h : 0.0f), lo.y + ((q & 2) ? h : 0.0f), lo.z + ((q & 4) ? h : 0.0f)};
    Vec3f g[3];
    const Vec3f x = f + cell_blend(c, f.x, f.y, f.z, g);
    for (int a = 0; a < 3; ++a) {
      bl[a] = x[a] < bl[a] ? x[a] : bl[a];
      bh[a] = x[a] > bh[a] ? x[a] : bh[a];
    }
  }
  for (int a = 0; a < 3; ++a)
    if (!(yl[a] >= bl[a] - kInvertSearchVox && yl[a] <= bh[a] + kInvertSearchVox)) return false;
  return true;
}

/// Solves p + u(p) = y inside the cell whose lowest corner is `o` (corner displacements
/// `c`, cell_blend()'s order) by newton_descend() on local coordinates kept in [0, 1]:
/// from the cell's centre (`fine` false), or (`fine` true: for a twisted or very
/// stretched cell, whose blend has several local minima of |r|) from the centre of each
/// of its kInvertSubcells^3 sub-cells whose image may hold y, in turn, until one gets
/// within kInvertSearchVox; returns the best p and writes its residual (voxel).
PALPSIM_HD Vec3f invert_in_cell(const Vec3f c[8], const Vec3i& o, const Vec3f& y, bool fine, float& residual) {
  const Vec3f yl{y.x - float(o.x), y.y - float(o.y), y.z - float(o.z)};  // y in local coordinates
  const float h = 1.0f / float(kInvertSubcells);
  Vec3f best{0.5f, 0.5f, 0.5f};
  residual = 3.4e38f;
  const int starts = fine ? kInvertSubcells * kInvertSubcells * kInvertSubcells : 1;
  for (int s = 0; s < starts && !(residual <= kInvertSearchVox); ++s) {
    // start s: the centre, or the centre of sub-cell s (i fastest)
    Vec3f f{0.5f, 0.5f, 0.5f};
    if (fine) {
      const Vec3f lo{h * float(s % kInvertSubcells), h * float((s / kInvertSubcells) % kInvertSubcells),
                     h * float(s / (kInvertSubcells * kInvertSubcells))};
      if (!subcell_holds(c, lo, h, yl)) continue;
      f = Vec3f{lo.x + 0.5f * h, lo.y + 0.5f * h, lo.z + 0.5f * h};
    }
    const float r = newton_descend([&](const Vec3f& q, Vec3f g[3]) { return q + cell_blend(c, q.x, q.y, q.z, g) - yl; },
                                   [](const Vec3f& q) {
                                     return Vec3f{clamp_to(q.x, 0.0f, 1.0f), clamp_to(q.y, 0.0f, 1.0f),
                                                  clamp_to(q.z, 0.0f, 1.0f)};
                                   },
                                   f, fine ? kInvertFineIterations : kInvertCellIterations);
    if (r < residual) {
      residual = r;
      best = f;
    }
  }
  return Vec3f{float(o.x) + best.x, float(o.y) + best.y, float(o.z) + best.z};
}

/// The cells of the search's ring r: those at Chebyshev distance r from its centre cell
/// (1 for r = 0, else (2r+1)^3 - (2r-1)^3).
PALPSIM_HD int search_ring_size(int r) {
  const int s = 2 * r + 1;
  return r == 0 ? 1 : 2 * s * s + (s - 2) * 8 * r;
}

/// Cell `idx` (0 <= idx < search_ring_size(r)) of ring r, as an offset from the centre
/// cell, in the order every backend uses: the face at -k and the face at +k (i fastest),
/// then each layer between them: its row at -j, its row at +j (i fastest), and the two
/// ends (-i, +i) of each row between.
PALPSIM_HD Vec3i search_ring_cell(int r, int idx) {
  const int s = 2 * r + 1;
  if (idx < 2 * s * s) {
    const int f = idx / (s * s), q = idx - f * s * s;
    return Vec3i{q % s - r, q / s - r, f ? r : -r};
  }
  const int m = idx - 2 * s * s, layer = m / (8 * r), q = m - layer * 8 * r;
  const int dk = layer + 1 - r;
  if (q < 2 * s) return Vec3i{q % s - r, q < s ? -r : r, dk};
  const int q2 = q - 2 * s;
  return Vec3i{(q2 & 1) ? r : -r, q2 / 2 + 1 - r, dk};
}

/// Where the search of y starts: the cell holding `guess` (clamped to the cells that
/// touch the VOI, lowest corners in [-1, size - 1]); returns it and writes the last ring
/// that still holds such a cell.
PALPSIM_HD Vec3i search_centre(const Vec3i& size, const Vec3f& guess, int& rmax) {
  Vec3i m;
  rmax = 0;
  for (int a = 0; a < 3; ++a) {
    m[a] = int(clamp_to(floorf(guess[a]), -1.0f, float(size[a] - 1)));
    rmax = max_int(rmax, max_int(m[a] + 1, size[a] - 1 - m[a]));
  }
  return m;
}

/// The bounding box (voxel) of the deformed corners of the cell with lowest corner `o`
/// (corner displacements `c`, cell_blend()'s order): the trilinear image of the cell lies
/// inside it.
PALPSIM_HD void cell_box(const Vec3f c[8], const Vec3i& o, Vec3f& lo, Vec3f& hi) {
  for (int a = 0; a < 3; ++a) {
    float l = 3.4e38f, h = -3.4e38f;
    for (int q = 0; q < 8; ++q) {
      const float x = float(o[a] + ((q >> a) & 1)) + c[q][a];
      l = x < l ? x : l;
      h = x > h ? x : h;
    }
    lo[a] = l;
    hi[a] = h;
  }
}

/// True when y lies in the box [lo, hi] grown by kInvertSearchVox.
PALPSIM_HD bool box_holds(const Vec3f& lo, const Vec3f& hi, const Vec3f& y) {
  for (int a = 0; a < 3; ++a)
    if (!(y[a] >= lo[a] - kInvertSearchVox && y[a] <= hi[a] + kInvertSearchVox)) return false;
  return true;
}

/// One cell of the search: false where the cell with lowest corner `o` lies beyond the
/// cells that touch the VOI, or y lies outside the bounding box of its deformed corners
/// (grown by kInvertSearchVox; the trilinear image of a cell lies in its corners' convex
/// hull); else solves it (invert_in_cell(), from its sub-cells on pass 1) and writes p
/// and its residual (voxel).
template <typename LoadU>
PALPSIM_HD bool search_cell(const LoadU& load_u, const Vec3i& size, const Vec3i& o, const Vec3f& y, int pass,
                            Vec3f& p, float& residual) {
  if (o.x < -1 || o.y < -1 || o.z < -1 || o.x > size.x - 1 || o.y > size.y - 1 || o.z > size.z - 1) return false;
  Vec3f c[8];
  load_cell(load_u, o.x, o.y, o.z, c);
  Vec3f lo, hi;
  cell_box(c, o, lo, hi);
  if (!box_holds(lo, hi, y)) return false;
  p = invert_in_cell(c, o, y, pass == 1, residual);
  return true;
}

/// The index of the cell at offset d (Chebyshev distance r from the centre) in ring r's
/// order: the inverse of search_ring_cell(), for a search that finds its cells some other
/// way (cuda/invert.cu scatters each cell to the voxels its box holds) and must still pick
/// as the ring order does.
PALPSIM_HD int search_ring_index(int r, const Vec3i& d) {
  if (r == 0) return 0;
  const int s = 2 * r + 1;
  if (d.z == -r || d.z == r) return (d.z == r ? s * s : 0) + (d.y + r) * s + (d.x + r);
  const int base = 2 * s * s + (d.z + r - 1) * 8 * r;
  if (d.y == -r) return base + d.x + r;
  if (d.y == r) return base + s + d.x + r;
  return base + 2 * s + 2 * (d.y + r - 1) + (d.x == r ? 1 : 0);
}

/// Ring r of the search around centre cell m on `pass` (0: cells' centres, 1: their
/// sub-cells'): each cell by search_cell(), in ring order; a lower residual replaces
/// `best` (the first in ring order wins among equals), and [r_lo, r_hi] widens to r
/// where a cell's box holds y.
template <typename LoadU>
PALPSIM_HD void search_ring(const LoadU& load_u, const Vec3i& size, const Vec3i& m, const Vec3f& y, int pass, int r,
                            Vec3f& best, float& residual, int& r_lo, int& r_hi) {
  for (int idx = 0, n = search_ring_size(r); idx < n; ++idx) {
    Vec3f p;
    float rc;
    if (!search_cell(load_u, size, m + search_ring_cell(r, idx), y, pass, p, rc)) continue;
    r_lo = r < r_lo ? r : r_lo;
    r_hi = r > r_hi ? r : r_hi;
    if (rc < residual) {
      residual = rc;
      best = p;
    }
  }
}

/// The search of invert_voxel(): the source of y among the cells whose lowest corner lies
/// in [-1, size - 1] (cells beyond the VOI's faces included: u = 0 outside), ring by ring
/// (search_ring_cell()) around the cell holding `guess`; each cell by search_cell(), from
/// its centre (pass 0), and where no cell gets within kInvertSearchVox so, the rings
/// again from the centres of the cells' sub-cells (pass 1). The first ring holding a source within
/// kInvertSearchVox ends the search; the lowest residual wins, the first in ring order
/// among equals (cuda/invert.cu splits each ring over a warp and reduces to the same).
/// A source always exists: p + u(p) is continuous and the identity beyond the VOI, so
/// every y in the VOI has one (its degree is 1). Returns p and writes its residual (voxel).
template <typename LoadU>
PALPSIM_HD Vec3f invert_search(const LoadU& load_u, const Vec3i& size, const Vec3f& y, const Vec3f& guess,
                               float& residual) {
  int rmax;
  const Vec3i m = search_centre(size, guess, rmax);
  Vec3f best = guess;
  residual = 3.4e38f;
  // the rings of pass 0 with a cell whose box holds y: pass 1 visits only those, as
  // search_cell() refuses the same cells on either pass (the result is unchanged)
  int r_lo = rmax + 1, r_hi = -1;
  for (int pass = 0; pass < 2 && !(residual <= kInvertSearchVox); ++pass)
    for (int r = pass ? r_lo : 0; r <= (pass ? r_hi : rmax) && !(residual <= kInvertSearchVox); ++r)
      search_ring(load_u, size, m, y, pass, r, best, residual, r_lo, r_hi);
  return best;
}

/// The inversion of one VOI voxel y (both backends): `iterations` Newton steps from y
/// (invert_point()), and where they end above kInvertSearchVox (stalled in a local minimum
/// of |r| next to a fold, bone or a VOI face, or not there yet), invert_search() around
/// y - u(y), whichever leaves the lower residual. The search starts from the same guess
/// whatever `iterations` is, so a voxel it takes gets the same source at any count.
/// With 0 iterations nothing is inverted (p = y, as the paper's iteration with none);
/// without `search` (deform.invert_search off) Newton's answer stands. Writes the
/// residual (voxel). The definition both backends follow; they run it in two halves
/// (Newton for every voxel, then the search for the voxels Newton left, found mostly by
/// invert_scatter.h's scatter_search() and cuda/invert.cu's kernels).
template <typename LoadU>
PALPSIM_HD Vec3f invert_voxel(const LoadU& load_u, const Vec3i& size, const Vec3f& y, int iterations, bool search,
                              float& residual) {
  Vec3f p = invert_point(load_u, y, iterations, residual);
  if (search && iterations > 0 && residual > kInvertSearchVox) {
    float rs;
    const Vec3f q = invert_search(load_u, size, y, y - trilinear<Vec3f>(load_u, y), rs);
    if (rs < residual) {
      residual = rs;
      p = q;
    }
  }
  return p;
}

}  // namespace palpsim::deform
