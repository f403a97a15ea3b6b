// Multigrid relaxation (deform.relax_method = "multigrid"): the level plan and the
// per-node passes of the solver, written once and compiled by both backends (g++ for
// server/deform/relax_multigrid.cpp, nvcc for cuda/relax_multigrid.cu).
//
// What it solves: the steady state of the explicit relaxation (relax.cpp). The explicit
// update u' = u + s m (sum6 - 6 u) stops changing exactly where sum6 - 6 u = 0, so its
// fixed point is the discrete Laplace equation on every free element, with the held
// elements (the grabbed element, every element with m == 0: bone) and u = 0 outside the
// VOI as Dirichlet data. The material function m sets only how fast the explicit scheme
// gets there (and, through m == 0, which elements are held), not where it gets.
//
// Linearity: the equation is the same scalar Laplace equation for each component, and
// its data are the held elements' displacements. ChainMail never moves bone, so where
// every held element but the grabbed one is at rest (u = 0; "clean"), the steady state is
// u = d G with d the grabbed element's displacement and G the unit response: 1 at the
// grabbed element, 0 at the other held elements and outside the VOI, harmonic elsewhere.
// G depends on the VOI, the grabbed element and the patient, not on d or on ChainMail,
// so one scalar solve serves the three components, and while the VOI and the grabbed
// element stay (a press within the tip's voxel) the next step reuses G (u = d G, the
// same bits as solving again). A held element that ChainMail did move (m == 0 outside
// the bone mask: intensities far above the bone threshold) makes the step solve each
// component with its own data instead.
//
// How: conjugate gradients (CG) on that scalar Laplace equation (free elements only),
// each step preconditioned by one symmetric geometric multigrid V-cycle. Level 0 is the
// VOI; level l+1 has half the nodes of level l along each axis, its node I on level l's
// node 2 I + origin (origin 0 or 1 per axis, chosen so that the grabbed element is a node
// of every level), and every level holds the 7-point operator 6 x - sum6 with zero outside
// it. A coarse node is held (its correction stays 0) when the fine node it lies on is.
// Coarse links that cross a Dirichlet point midway are cut: where the fine node between two
// coarse nodes is held, lies beyond the fine level's faces (a VOI face between coarse
// nodes), or a fine half-link on the way is cut, the coarse operator takes the ghost value
// -x across that link (zero half a coarse spacing away, linearly): the diagonal grows by
// one per cut link and the neighbour drops out. Without the cuts a coarse level saw no bone
// or face between its nodes and its correction overshot there: on the accuracy press
// (phantom, VOI 64; palpsim-bench deform --accuracy --study relax_cycles, cpu) steps from
// zero to 1% of the steady state went 5 -> 4 (4 steps 2.09% -> 0.46%, 3 steps 6.9% ->
// 3.8%), one step from the last G 0.046% -> 0.015%. A link is cut from both of its ends,
// so the operator, and the V-cycle as a preconditioner, stay symmetric.
// Smoother: red-black Gauss-Seidel (colour = parity of i + j + k), in place, red then
// black going down and black then red coming up, so the V-cycle is symmetric; residuals
// restricted by full weighting, corrections prolonged trilinearly and never applied to
// held nodes. Plain V-cycles with these coarse grids stall near the held elements and
// the VOI's faces (0.6-0.95 per cycle where the faces fall between coarse nodes);
// conjugate gradients remove those few slow modes.
//
// The passes are shaped for few grid-wide barriers on the GPU (each costs microseconds
// there), and the CPU runs the same passes in the same order, so both compute alike:
// - going down, each level starts from x = 0, so its first red half-sweep is x = f / 6,
//   written by the pass that makes f (the restriction, or CG's update on level 0);
// - after the black half-sweep the residual is 0 at black nodes (Gauss-Seidel zeroes it
//   where it just updated), so only red nodes compute one; the restriction sums each
//   plane of its 27 weights apart (a GPU warp sums the three planes in three lanes);
// - going up, only red nodes take the coarse correction: the black half-sweep that
//   follows overwrites the black ones;
// - CG's update pass makes the next V-cycle's first red-black sweep on level 0 (z = r / 6
//   at red nodes, the black sweep from those computed on the fly).
#pragma once

#include <cstdint>

#include "core/hd.h"
#include "core/vec3.h"
#include "deform/deform_math.h"

namespace palpsim::deform {

/// The most levels a plan holds: 2^16 voxels along every axis would need 15.
constexpr int kMultigridMaxLevels = 16;
/// The most steps (deform.relax_cycles) a scene may ask for.
constexpr int kMultigridMaxCycles = 100;
/// Red-black sweeps after the first (red, black) one on the coarsest level (some axis
/// below 3 nodes there, so the Dirichlet faces are at most 2 nodes apart along it and each
/// sweep reduces the error by 0.7 or better; CG absorbs the rest): red, black, red, black,
/// red, i.e. two symmetric sweep pairs (a black half-sweep repeated at the turn changes
/// nothing and is left out).
constexpr int kMultigridCoarsestHalfSweeps = 5;

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

/// What the unit response G in a backend's buffer was solved for: the VOI (patient
/// voxel indices), the VOI-local grabbed element and the steps; `ok` false: none.
struct MultigridCache {
  Vec3i lo{0, 0, 0}, size{0, 0, 0}, grabbed{0, 0, 0};
  int cycles = 0;
  bool ok = false;

  /// The key of a solve on `voi` for the VOI-local grabbed element with `cycles` steps
  /// (at most kMultigridMaxCycles, as the solvers run); both backends test and keep it.
  PALPSIM_HD static MultigridCache of(const Voi& voi, const Vec3i& grabbed, int cycles) {
    return {voi.lo, voi.size, grabbed, cycles < kMultigridMaxCycles ? cycles : kMultigridMaxCycles, true};
  }

  PALPSIM_HD bool operator==(const MultigridCache& o) const {
    return ok && o.ok && lo == o.lo && size == o.size && grabbed == o.grabbed && cycles == o.cycles;
  }
};

/// Where a new unit response starts when the last one is at hand (deform.relax_warm_cycles):
/// the last G, solved on a VOI of `size` nodes, shifted so that its grabbed element lies
/// on the new one: node (i, j, k) of the new VOI takes the last G's node (i, j, k) + shift
/// (shift: the last VOI-local grabbed element minus the new one), 0 where that lies
/// outside the last VOI. A press a voxel on moves the VOI with the tip while the grabbed
/// element stays (the last G on the same patient voxels, its far faces a voxel off), and
/// a tip sliding a voxel along the skin moves both (the same response beside bone a voxel
/// off): either way close to the new G, so fewer steps reach the same distance. A jump
/// across the patient starts from a G of another place: the response to a press has one
/// shape wherever it is (the bone around it changes the detail), so that G is still a far
/// better start than zero (kMultigridNearMove has the figures; 2 steps from zero: 1-14%).
struct MultigridStart {
  const float* g = nullptr;  // the last G (VOI-local index, i fastest); null: start from zero
  Vec3i size{0, 0, 0};
  Vec3i shift{0, 0, 0};
  bool far = false;          // the grabbed element moved more than kMultigridNearMove voxels: one more step

  /// The start at free node (i, j, k) of the new VOI.
  PALPSIM_HD float at(int i, int j, int k) const {
    if (!g) return 0.0f;
    const int a = i + shift.x, b = j + shift.y, c = k + shift.z;
    if (a < 0 || b < 0 || c < 0 || a >= size.x || b >= size.y || c >= size.z) return 0.0f;
    return g[(c * size.y + b) * size.x + a];
  }
};

/// The most voxels (along each axis) the grabbed element may have moved since the last G
/// for a warm start to take deform.relax_warm_cycles steps; one that moved farther takes
/// one more. Measured on make_torso_patient(64) at VOI 40 (tests/unit/
/// deform_relax_multigrid_test.cpp), one warm step: the grabbed element staying (a press a
/// voxel or 4 voxels a step: the VOI moves) or moving a voxel (sliding along the skin)
/// 0.03-0.36% from the steady state; moving 2 voxels 0.4-1.4%, jumps of 10-30 voxels up
/// to 5%, which a second step brings to 0.03-0.27% and 0.28-0.72%.
constexpr int kMultigridNearMove = 1;

/// The start of a G for VOI `lo` (patient voxels) with VOI-local grabbed element `grabbed`
/// from the last G `last` (its buffer `g`): shifted onto the new grabbed element, or none
/// (start from zero) when there is no last G.
PALPSIM_HD MultigridStart multigrid_start(const MultigridCache& last, const float* g, const Vec3i& lo,
                                          const Vec3i& grabbed) {
  MultigridStart s;
  if (!last.ok) return s;
  s.g = g;
  s.size = last.size;
  s.shift = last.grabbed - grabbed;
  for (int a = 0; a < 3; ++a) {
    const int moved = (lo[a] + grabbed[a]) - (last.lo[a] + last.grabbed[a]);
    if (moved > kMultigridNearMove || moved < -kMultigridNearMove) s.far = true;
  }
  return s;
}

/// The steps of a solve from start `s` for a scene's `warm_cycles`: one more where the
/// grabbed element moved far (MultigridStart::far), at most kMultigridMaxCycles.
PALPSIM_HD int multigrid_warm_steps(const MultigridStart& s, int warm_cycles) {
  const int n = s.far ? warm_cycles + 1 : warm_cycles;
  return n < kMultigridMaxCycles ? n : kMultigridMaxCycles;
}

/// Whether VOI element (i, j, k) lies on the fingertip: within the grab radius of the
/// grabbed element g (r2: that radius squared, in voxels^2; 0: the grabbed element alone).
PALPSIM_HD bool multigrid_on_finger(int i, int j, int k, const Vec3i& g, float r2) {
  const float dx = float(i - g.x), dy = float(j - g.y), dz = float(k - g.z);
  return dx * dx + dy * dy + dz * dz <= r2;
}

/// How relaxation holds an element (the held mask's values): kMultigridFree, or a
/// Dirichlet node of the steady state, either at its own data (kMultigridHeldAtRest: every
/// element of material weight 0, bone or far above the threshold) or moving with the
/// grabbed element (kMultigridHeldGrabbed: the grabbed element, and the soft elements on
/// the fingertip, deform.grab_radius_mm). Both backends' solvers and the batched reuse
/// test it the same way.
constexpr std::uint8_t kMultigridFree = 0, kMultigridHeldAtRest = 1, kMultigridHeldGrabbed = 2;
PALPSIM_HD std::uint8_t multigrid_hold(bool grabbed, bool on_finger, float intensity, bool bone, float threshold,
                                       float width) {
  if (grabbed) return kMultigridHeldGrabbed;
  if (material_weight(intensity, bone, threshold, width) == 0.0f) return kMultigridHeldAtRest;
  return on_finger ? kMultigridHeldGrabbed : kMultigridFree;
}

/// A level's per-node byte (MultigridLevel::held): bits 0-1 how the node is held (level 0:
/// kMultigridFree, kMultigridHeldAtRest or kMultigridHeldGrabbed; coarse levels: 0 or 1),
/// bits 2-7 its cut links (coarse levels only; bit 2 + q: link q of neighbour_offset's order).
constexpr std::uint8_t kMultigridHoldMask = 3;
constexpr int kMultigridCutShift = 2;

/// Whether a level's node byte `h` holds its node (a Dirichlet node: its x stays).
PALPSIM_HD bool multigrid_held(std::uint8_t h) { return (h & kMultigridHoldMask) != 0; }

/// The cut links of a node byte `h` (bit q: link q), 0 on level 0.
PALPSIM_HD int multigrid_cuts(std::uint8_t h) { return h >> kMultigridCutShift; }

/// The operator's diagonal at a node with cut links `cuts`: 6 and one per cut (the ghost -x).
PALPSIM_HD float multigrid_diagonal(int cuts) {
#ifdef __CUDA_ARCH__
  return float(6 + __popc(cuts));
#else
  return float(6 + __builtin_popcount(unsigned(cuts)));
#endif
}

/// The red-black colour of node (i, j, k): 0 red, 1 black.
PALPSIM_HD int multigrid_colour(int i, int j, int k) { return (i + j + k) & 1; }

/// One level of the scalar problem: its nodes, field x, right-hand side f, held mask and
/// the residual after the way down's black half-sweep (local index i fastest; VOIs hold
/// < 2^31 voxels, checked at bind).
struct MultigridLevel {
  Vec3i n;
  float* x;
  float* f;
  std::uint8_t* held;  // the node bytes: how each node is held and its cut links (multigrid_held, multigrid_cuts)
  float* res;

  PALPSIM_HD int count() const { return n.x * n.y * n.z; }
  PALPSIM_HD bool inside(int i, int j, int k) const { return i >= 0 && j >= 0 && k >= 0 && i < n.x && j < n.y && k < n.z; }
  PALPSIM_HD int index(int i, int j, int k) const { return (k * n.y + j) * n.x + i; }
  PALPSIM_HD void coords(int e, int& i, int& j, int& k) const {
    k = e / (n.x * n.y);
    const int rem = e - k * n.x * n.y;
    j = rem / n.x;
    i = rem - j * n.x;
  }
  /// The six neighbours of (i, j, k) in `v` in the fixed order, zero outside the level
  /// (on the CPU a node off the level's faces adds them without the tests: the same sums
  /// in the same order; on the GPU that branch was measured to make the solve slower).
  PALPSIM_HD float sum6(const float* v, int i, int j, int k) const {
#ifndef __CUDA_ARCH__
    if (i > 0 && j > 0 && k > 0 && i + 1 < n.x && j + 1 < n.y && k + 1 < n.z)
      return sum6_inner(v, index(i, j, k), n.x, (long long)n.x * n.y, 0.0f);
#endif
    float s = 0;
    for (int q = 0; q < 6; ++q) {
      const Vec3i m = Vec3i{i, j, k} + neighbour_offset(q);
      if (inside(m.x, m.y, m.z)) s += v[index(m.x, m.y, m.z)];
    }
    return s;
  }
  /// The neighbours of (i, j, k) in `v` over its uncut links (`cuts`: multigrid_cuts), in
  /// the fixed order and zero outside the level: sum6 where no link is cut. A cut
  /// neighbour is loaded and weighted 0 rather than skipped, so that on the GPU the loads
  /// need not wait for the node byte that holds the cuts (skipping them costs a second
  /// memory round trip a coarse pass); v * 1 = v and s + (+-0) = s
  /// (s starts at +0 and a sum that cancels is +0), so the sums are those of skipping.
  PALPSIM_HD float sum_links(const float* v, int i, int j, int k, int cuts) const {
#ifndef __CUDA_ARCH__
    if (cuts == 0) return sum6(v, i, j, k);
#endif
    float s = 0;
    for (int q = 0; q < 6; ++q) {
      const Vec3i m = Vec3i{i, j, k} + neighbour_offset(q);
      if (inside(m.x, m.y, m.z)) s += v[index(m.x, m.y, m.z)] * ((cuts >> q) & 1 ? 0.0f : 1.0f);
    }
    return s;
  }
};

/// The Gauss-Seidel value of a free node with diagonal `diag` (multigrid_diagonal; 6 on
/// level 0): the x that makes diag x - sum = f.
PALPSIM_HD float multigrid_smooth(float sum, float f, float diag = 6.0f) { return (f + sum) / diag; }

/// One red-black half-sweep at node (i, j, k): a free node of `colour` takes its
/// Gauss-Seidel value; others stay.
PALPSIM_HD void multigrid_sweep_node(const MultigridLevel& L, int colour, int i, int j, int k) {
  const int e = L.index(i, j, k);
  const std::uint8_t h = L.held[e];
  if (multigrid_colour(i, j, k) != colour || multigrid_held(h)) return;
  const int cuts = multigrid_cuts(h);
  L.x[e] = multigrid_smooth(L.sum_links(L.x, i, j, k, cuts), L.f[e], multigrid_diagonal(cuts));
}

/// The residual f - (diag x - sum) at node (i, j, k) of level L after its black half-sweep,
/// into L.res: 0 at black nodes (the sweep zeroed it) and held nodes.
PALPSIM_HD void multigrid_residual_node(const MultigridLevel& L, int i, int j, int k) {
  const int e = L.index(i, j, k);
  const std::uint8_t h = L.held[e];
  const int cuts = multigrid_cuts(h);
  L.res[e] = multigrid_colour(i, j, k) != 0 || multigrid_held(h)
                 ? 0.0f
                 : L.f[e] + L.sum_links(L.x, i, j, k, cuts) - multigrid_diagonal(cuts) * L.x[e];
}

/// One plane (dk) of the full weighting at coarse node (I, J, K): the fine residuals
/// (multigrid_residual_node; zero outside the fine level) of the 9 nodes around 2I+o at
/// fine offset dk along k, each times its tensor weight (1/2 at the centre, 1/4 beside it,
/// per axis) times 4 (the coarse operator's spacing is 2 fine spacings), summed j then i.
/// multigrid_restrict_sum() adds the three planes.
PALPSIM_HD float multigrid_restrict_plane(const MultigridLevel& fine, const Vec3i& o, int I, int J, int K, int dk) {
  float sum = 0;
  const int k = 2 * K + o.z + dk;
  for (int dj = -1; dj <= 1; ++dj)
    for (int di = -1; di <= 1; ++di) {
      const int i = 2 * I + o.x + di, j = 2 * J + o.y + dj;
      const float w = 4.0f * (di ? 0.25f : 0.5f) * (dj ? 0.25f : 0.5f) * (dk ? 0.25f : 0.5f);
      sum += (fine.inside(i, j, k) ? fine.res[fine.index(i, j, k)] : 0.0f) * w;
    }
  return sum;
}

/// The restriction's planes added in a fixed order: (dk -1 + dk 0) + dk 1.
PALPSIM_HD float multigrid_restrict_sum(float below, float centre, float above) { return (below + centre) + above; }

/// The node byte of coarse node (I, J, K): held where the fine node it lies on is, else
/// its cut links (bit q: link q), those whose fine midpoint is held or lies beyond the fine
/// level's faces, or whose fine half-links are cut. The seven fine bytes are loaded first,
/// independently of each other (0xff beyond the faces: held).
PALPSIM_HD std::uint8_t multigrid_coarse_byte(const MultigridLevel& fine, const Vec3i& o, int I, int J, int K) {
  const Vec3i c{2 * I + o.x, 2 * J + o.y, 2 * K + o.z};
  std::uint8_t h[6];
  for (int q = 0; q < 6; ++q) {
    const Vec3i m = c + neighbour_offset(q);
    h[q] = fine.inside(m.x, m.y, m.z) ? fine.held[fine.index(m.x, m.y, m.z)] : std::uint8_t(0xff);
  }
  const std::uint8_t hc = fine.held[fine.index(c.x, c.y, c.z)];
  if (multigrid_held(hc)) return 1;
  const int fine_cuts = multigrid_cuts(hc);
  int cuts = 0;
  for (int q = 0; q < 6; ++q)
    if (((fine_cuts >> q) & 1) != 0 || multigrid_held(h[q]) || ((multigrid_cuts(h[q]) >> q) & 1) != 0) cuts |= 1 << q;
  return std::uint8_t(cuts << kMultigridCutShift);
}

/// Makes coarse node (I, J, K) from the fine level after its black half-sweep: its
/// right-hand side `f` (the restricted residual, multigrid_restrict_sum of the planes),
/// its node byte `byte` (multigrid_coarse_byte), and x = f / diag at red free nodes (the
/// first red half-sweep from x = 0), 0 elsewhere.
PALPSIM_HD void multigrid_coarse_node(const MultigridLevel& coarse, int I, int J, int K, float f, std::uint8_t byte) {
  const int e = coarse.index(I, J, K);
  const bool held = multigrid_held(byte);
  coarse.f[e] = f;
  coarse.held[e] = byte;
  coarse.x[e] = !held && multigrid_colour(I, J, K) == 0 ? multigrid_smooth(0.0f, f, multigrid_diagonal(multigrid_cuts(byte)))
                                                         : 0.0f;
}

/// The coarse correction at fine node (i, j, k): trilinear interpolation of the coarse
/// level's x (zero outside it) at coarse coordinate ((i-o)/2, (j-o)/2, (k-o)/2).
PALPSIM_HD float multigrid_prolong(const MultigridLevel& coarse, const Vec3i& o, int i, int j, int k) {
  auto load = [&](int a, int b, int c) { return coarse.inside(a, b, c) ? coarse.x[coarse.index(a, b, c)] : 0.0f; };
  return trilinear<float>(load, Vec3f{0.5f * float(i - o.x), 0.5f * float(j - o.y), 0.5f * float(k - o.z)});
}

/// The coarse correction of red free node (i, j, k): x += prolonged correction (black
/// nodes are overwritten by the black half-sweep that follows, so they need none).
PALPSIM_HD void multigrid_correct_red(const MultigridLevel& fine, const MultigridLevel& coarse, const Vec3i& o, int i,
                                      int j, int k) {
  const int e = fine.index(i, j, k);
  if (multigrid_colour(i, j, k) != 0 || multigrid_held(fine.held[e])) return;
  fine.x[e] = fine.x[e] + multigrid_prolong(coarse, o, i, j, k);
}

/// CG's new residual at a node, r - alpha q (alpha: the step length).
PALPSIM_HD float multigrid_cg_residual(float r, float q, float alpha) { return r - alpha * q; }

}  // namespace palpsim::deform
