// Multigrid relaxation (deform.relax_method = "multigrid"): the level plan and the
// per-node math of geometric multigrid V-cycles, written once and compiled by both
// backends (g++ for server/deform/relax_multigrid.cpp, nvcc for cuda/relax_multigrid.cu).
//
// What it solves: the steady state of the explicit relaxation (relax.cpp). The explicit
// update u' = u + s m (sum6 - 6 u) stops changing exactly where sum6 - 6 u = 0, so its
// fixed point is the discrete Laplace equation on every free element, with the held
// elements (the grabbed element, every element with m == 0: bone) and u = 0 outside the
// VOI as Dirichlet data. The material function m sets only how fast the explicit scheme
// gets there (and, through m == 0, which elements are held), not where it gets.
//
// How: conjugate gradients on that Laplace equation (free elements only), each step
// preconditioned by one symmetric geometric multigrid V-cycle. Level 0 is the VOI;
// level l+1 has half the nodes of level l along each axis, its node I on level l's node
// 2 I + origin (origin 0 or 1 per axis, chosen so that the grabbed element is a node of
// every level), and every level holds the 7-point operator 6 x - sum6 with zero outside
// it. A coarse node is held (its correction stays 0) when the fine node it lies on is.
// Smoother: red-black Gauss-Seidel (colour = parity of i + j + k), in place, red then
// black going down and black then red coming up, so the V-cycle is symmetric; residuals
// restricted by full weighting, corrections prolonged trilinearly and never applied to
// held nodes. Plain V-cycles with these coarse grids stall near the held elements and
// the VOI's faces (0.6-0.95 per cycle where the faces fall between coarse nodes);
// conjugate gradients remove those few slow modes, and each step costs one V-cycle,
// one operator application and two dot products.
#pragma once

#include "core/hd.h"
#include "core/vec3.h"
#include "deform/deform_math.h"

namespace palpsim::deform {

/// The most levels a plan holds: 2^16 voxels along every axis would need 15.
constexpr int kMultigridMaxLevels = 16;
/// The most steps (deform.relax_cycles) a scene may ask for.
constexpr int kMultigridMaxCycles = 100;
/// Red-black Gauss-Seidel sweeps before and after each coarse-grid correction (one each:
/// two reached 1% of the phantom press's steady state in one step fewer, at twice the
/// barriers per step).
constexpr int kMultigridPreSweeps = 1;
constexpr int kMultigridPostSweeps = 1;
/// Symmetric sweep pairs on the coarsest level (some axis below 3 nodes there, so the
/// Dirichlet faces are at most 2 nodes apart along it and each sweep reduces the error by
/// 0.7 or better; CG absorbs the rest: 2 pairs reach the steady state as fast per step as
/// 16 on the phantom press, and cost 0.1 ms less over 5 steps on the H100).
constexpr int kMultigridCoarsestSweeps = 2;

/// Sizes of the levels of one VOI and where the coarse levels lie in one buffer.
struct MultigridPlan {
  int levels = 0;                           // level 0 is the VOI itself
  Vec3i size[kMultigridMaxLevels];          // nodes per axis of each level
  Vec3i origin[kMultigridMaxLevels];        // level l+1's node I lies on level l's node 2 I + origin[l] (0 or 1)
  long long offset[kMultigridMaxLevels];    // first node of level l >= 1 in the coarse buffers (level 0: 0)
  long long coarse_count = 0;               // nodes of all levels >= 1
};

/// Nodes of a box of `s` nodes.
PALPSIM_HD long long node_count(const Vec3i& s) { return (long long)s.x * s.y * s.z; }

/// The plan for a VOI of `voi_size` nodes with the grabbed element at VOI-local `grabbed`:
/// halve every axis while each has at least 3 nodes (so the coarser level keeps at least
/// one), at most kMultigridMaxLevels levels, each level's origin on the grabbed element.
PALPSIM_HD MultigridPlan multigrid_plan(const Vec3i& voi_size, const Vec3i& grabbed) {
  MultigridPlan p;
  p.size[0] = voi_size;
  p.offset[0] = 0;
  p.levels = 1;
  long long at = 0;
  Vec3i g = grabbed;
  while (p.levels < kMultigridMaxLevels) {
    const Vec3i& s = p.size[p.levels - 1];
    if (s.x < 3 || s.y < 3 || s.z < 3) break;
    Vec3i o;
    for (int a = 0; a < 3; ++a) {
      o[a] = (g[a] % 2 + 2) % 2;
      g[a] = (g[a] - o[a]) / 2;
    }
    p.origin[p.levels - 1] = o;
    p.size[p.levels] = Vec3i{(s.x - o.x + 1) / 2, (s.y - o.y + 1) / 2, (s.z - o.z + 1) / 2};
    p.offset[p.levels] = at;
    at += node_count(p.size[p.levels]);
    ++p.levels;
  }
  p.coarse_count = at;
  return p;
}

/// The red-black colour of node (i, j, k): sweeps update colour 0, then colour 1.
PALPSIM_HD int multigrid_colour(int i, int j, int k) { return (i + j + k) & 1; }

/// The Gauss-Seidel value of a free node: the x that makes 6 x - sum6 = f.
PALPSIM_HD Vec3f multigrid_smooth(const Vec3f& sum6, const Vec3f& f) {
  return Vec3f{(f.x + sum6.x) / 6.0f, (f.y + sum6.y) / 6.0f, (f.z + sum6.z) / 6.0f};
}

/// The residual f - (6 x - sum6) of a free node (0 at held nodes, decided by the caller).
PALPSIM_HD Vec3f multigrid_residual(const Vec3f& x, const Vec3f& sum6, const Vec3f& f) {
  return Vec3f{f.x + sum6.x - 6.0f * x.x, f.y + sum6.y - 6.0f * x.y, f.z + sum6.z - 6.0f * x.z};
}

/// The right-hand side of coarse node (I, J, K): full weighting of the fine residual
/// `load_r(i, j, k)` (zero outside the fine level and at held fine nodes) over the 27
/// fine nodes around 2I+1, times 4 (the coarse operator's spacing is 2 fine spacings).
/// Sums in a fixed order (k, then j, then i) so both backends add alike; `o` is the
/// level's origin (MultigridPlan::origin).
template <typename LoadR>
PALPSIM_HD Vec3f multigrid_restrict(const LoadR& load_r, const Vec3i& o, int I, int J, int K) {
  Vec3f sum{0, 0, 0};
  for (int dk = -1; dk <= 1; ++dk)
    for (int dj = -1; dj <= 1; ++dj)
      for (int di = -1; di <= 1; ++di) {
        const int i = 2 * I + o.x + di, j = 2 * J + o.y + dj, k = 2 * K + o.z + dk;
        // tensor weights 1/2 at the centre, 1/4 beside it, per axis; times 4
        const float w = 4.0f * (di ? 0.25f : 0.5f) * (dj ? 0.25f : 0.5f) * (dk ? 0.25f : 0.5f);
        sum += load_r(i, j, k) * w;
      }
  return sum;
}

/// The coarse correction at fine node (i, j, k): trilinear interpolation of the coarse
/// level's values `load_x` (zero outside it) at coarse coordinate ((i-1)/2, (j-1)/2, (k-1)/2).
template <typename LoadX>
PALPSIM_HD Vec3f multigrid_prolong(const LoadX& load_x, const Vec3i& o, int i, int j, int k) {
  return trilinear<Vec3f>(load_x, Vec3f{0.5f * float(i - o.x), 0.5f * float(j - o.y), 0.5f * float(k - o.z)});
}

}  // namespace palpsim::deform
