// Multigrid relaxation on the CPU: conjugate gradients preconditioned by V-cycles, to
// the explicit relaxation's steady state (the plan, the linearity argument and the
// per-node passes are in relax_multigrid.h). Passes run in the order the CUDA kernel
// runs them, each over every node, so both backends compute alike.
#include "deform/relax_multigrid.h"

#include <algorithm>

#include "deform/cpu_backend.h"
#include "deform/node_loops.h"

namespace palpsim::deform {

namespace {

// the V-cycle on levels lv (level 0's x holds the first red-black sweep from 0, the
// coarser ones are made on the way down): z = M r on level 0
void vcycle(const MultigridLevel* lv, const MultigridPlan& plan) {
  const int last = plan.levels - 1;
  for (int l = 0; l < last; ++l) {
    // black half-sweep (level 0's came with CG's update), then the coarse level from the residual
    if (l > 0) each_node(lv[l].n, [&](int i, int j, int k) { multigrid_sweep_node(lv[l], 1, i, j, k); });
    each_node(lv[l].n, [&](int i, int j, int k) { multigrid_residual_node(lv[l], i, j, k); });
    const Vec3i o = plan.origin[l];
    each_node(lv[l + 1].n, [&](int I, int J, int K) {
      const float f = multigrid_restrict_sum(multigrid_restrict_plane(lv[l], o, I, J, K, -1),
                                             multigrid_restrict_plane(lv[l], o, I, J, K, 0),
                                             multigrid_restrict_plane(lv[l], o, I, J, K, 1));
      multigrid_coarse_node(lv[l + 1], I, J, K, f, multigrid_coarse_byte(lv[l], o, I, J, K));
    });
  }
  // the coarsest level: its black half-sweep (level 0's, when it is the coarsest, came
  // with CG's update), then red, black, ...
  if (last > 0) each_node(lv[last].n, [&](int i, int j, int k) { multigrid_sweep_node(lv[last], 1, i, j, k); });
  for (int h = 0; h < kMultigridCoarsestHalfSweeps; ++h)
    each_node(lv[last].n, [&](int i, int j, int k) { multigrid_sweep_node(lv[last], h % 2, i, j, k); });
  // back up: the correction of red nodes, the black half-sweep, then red
  for (int l = last - 1; l >= 0; --l) {
    const Vec3i o = plan.origin[l];
    each_node(lv[l].n, [&](int i, int j, int k) { multigrid_correct_red(lv[l], lv[l + 1], o, i, j, k); });
    each_node(lv[l].n, [&](int i, int j, int k) { multigrid_sweep_node(lv[l], 1, i, j, k); });
    each_node(lv[l].n, [&](int i, int j, int k) { multigrid_sweep_node(lv[l], 0, i, j, k); });
  }
}

// conjugate gradients for the field X on level 0 (`held` set), held nodes at
// data(e), free ones started at `start` (0 unless it holds the last G); `cycles` steps
// (fewer when the residual vanishes)
template <typename Data>
void solve(const MultigridPlan& plan, MultigridLevel* lv, float* X, float* p, float* q, int cycles,
           const MultigridStart& start, Data data) {
  const MultigridLevel& L0 = lv[0];
  const Vec3i n = L0.n;
  const std::uint8_t* held = L0.held;
  float* r = L0.f;
  float* z = L0.x;
  const int count = L0.count();
  each_node(n, [&](int i, int j, int k) {
    const int e = L0.index(i, j, k);
    X[e] = held[e] ? data(e) : start.at(i, j, k);
  });
  // r = -(6 X - sum6) on free nodes: the residual of the steady state; z = its first
  // red half-sweep from 0, then the black one
  each_node(n, [&](int i, int j, int k) {
    const int e = L0.index(i, j, k);
    const float re = held[e] ? 0.0f : L0.sum6(X, i, j, k) - 6.0f * X[e];
    r[e] = re;
    z[e] = !held[e] && multigrid_colour(i, j, k) == 0 ? multigrid_smooth(0.0f, re) : 0.0f;
  });
  each_node(n, [&](int i, int j, int k) { multigrid_sweep_node(L0, 1, i, j, k); });
  double rho = 0;
  for (int c = 0; c < cycles; ++c) {
    vcycle(lv, plan);
    double rho_new = 0;
    for (int e = 0; e < count; ++e) rho_new += double(r[e]) * z[e];
    if (!(rho_new > 0)) break;  // r = 0: converged (or z lost positivity to rounding)
    const float beta = c == 0 ? 0.0f : float(rho_new / rho);
    rho = rho_new;
    // p = z + beta p; q = A p on free nodes (p is 0 at held ones)
    for (int e = 0; e < count; ++e) p[e] = c == 0 ? z[e] : z[e] + p[e] * beta;
    double pq = 0;
    each_node(n, [&](int i, int j, int k) {
      const int e = L0.index(i, j, k);
      q[e] = held[e] ? 0.0f : 6.0f * p[e] - L0.sum6(p, i, j, k);
      pq += double(p[e]) * q[e];
    });
    if (!(pq > 0)) break;
    const float alpha = float(rho / pq);
    for (int e = 0; e < count; ++e) X[e] += p[e] * alpha;
    if (c + 1 == cycles) break;
    // r -= alpha q; z for the next V-cycle as at the start
    each_node(n, [&](int i, int j, int k) {
      const int e = L0.index(i, j, k);
      r[e] = multigrid_cg_residual(r[e], q[e], alpha);
      z[e] = !held[e] && multigrid_colour(i, j, k) == 0 ? multigrid_smooth(0.0f, r[e]) : 0.0f;
    });
    each_node(n, [&](int i, int j, int k) { multigrid_sweep_node(L0, 1, i, j, k); });
  }
}

}  // namespace

namespace {

// sizes the state's multigrid buffers for `voi` and `plan` (they only grow) and sets the
// levels over them: 0 solves for z with right-hand side r, the others live in the
// coarse buffers
void multigrid_buffers(const Voi& voi, const MultigridPlan& plan, CpuState& s, MultigridLevel* lv) {
  const std::size_t n = std::size_t(voi.count());
  const std::size_t nc = std::size_t(plan.coarse_count);
  for (auto* v : {&s.mg_g, &s.mg_g_last, &s.mg_r, &s.mg_z, &s.mg_p, &s.mg_q, &s.mg_res})
    if (v->size() < n) v->resize(n);
  if (s.mg_held.size() < n) s.mg_held.resize(n);
  if (s.mg_cx.size() < nc) {
    s.mg_cx.resize(nc);
    s.mg_cf.resize(nc);
    s.mg_cres.resize(nc);
    s.mg_held_coarse.resize(nc);
  }
  lv[0] = MultigridLevel{voi.size, s.mg_z.data(), s.mg_r.data(), s.mg_held.data(), s.mg_res.data()};
  for (int l = 1; l < plan.levels; ++l) {
    const long long o = plan.offset[l];
    lv[l] = MultigridLevel{plan.size[l], s.mg_cx.data() + o, s.mg_cf.data() + o, s.mg_held_coarse.data() + o,
                           s.mg_cres.data() + o};
  }
}

// the hold of VOI element (i, j, k) (patient voxel gi), as both solvers take it
std::uint8_t hold_of(const Patient& p, std::size_t gi, bool grabbed, int i, int j, int k, const Vec3i& g,
                     float finger_r2, float threshold, float width) {
  return multigrid_hold(grabbed, multigrid_on_finger(i, j, k, g, finger_r2), p.intensity.data[gi],
                        p.bone.data[gi] != 0, threshold, width);
}

// solves the unit response G of `key` into mg_g with level 0's held mask in place: from the
// last G where `warm_cycles` > 0 and there is one (multigrid_start; the last one moves to
// mg_g_last, a swap: start.g stays its data), else from zero in `cycles` steps; keeps the key
MultigridRun solve_unit_response(const MultigridPlan& plan, MultigridLevel* lv, const MultigridCache& key, int cycles,
                                 int warm_cycles, CpuState& s) {
  MultigridStart start;
  if (warm_cycles > 0) start = multigrid_start(s.mg_cache, s.mg_g.data(), key.lo, key.grabbed);
  const bool warm = start.g != nullptr;
  if (warm) std::swap(s.mg_g, s.mg_g_last);
  const int steps = warm ? multigrid_warm_steps(start, warm_cycles) : cycles;
  solve(plan, lv, s.mg_g.data(), s.mg_p.data(), s.mg_q.data(), steps, start,
        [&](int e) { return s.mg_held[e] == kMultigridHeldGrabbed ? 1.0f : 0.0f; });
  s.mg_cache = key;
  return {1, warm, warm ? steps : 0};
}

}  // namespace

MultigridRun relax_multigrid_cpu(const Patient& p, const ChainMailStats& st, int cycles, int warm_cycles,
                                 float threshold, float width, float finger_r2, bool reuse, CpuState& s) {
  if (cycles <= 0) return {};  // no steps: the field stays as ChainMail left it
  const Voi& voi = st.voi;
  const Grid& grid = p.grid;
  const Vec3i g = st.grabbed_vox - voi.lo;
  const MultigridPlan plan = multigrid_plan(voi.size, g);
  const std::size_t n = std::size_t(voi.count());
  MultigridLevel lv[kMultigridMaxLevels];
  multigrid_buffers(voi, plan, s, lv);
  // level 0 holds the grabbed element and the soft elements on the fingertip at the
  // grabbed element's displacement d (set here: ChainMail moved them otherwise), and every
  // element of material weight 0 (bone) at its own; clean: every one of those at rest
  const long long g_idx = voi.index(g.x, g.y, g.z);
  const Vec3f d = s.u[g_idx];
  bool clean = true;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const std::size_t gi = grid.index(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k);
        const long long e = voi.index(i, j, k);
        const std::uint8_t hold = hold_of(p, gi, e == g_idx, i, j, k, g, finger_r2, threshold, width);
        s.mg_held[e] = hold;
        if (hold == kMultigridHeldGrabbed)
          s.u[e] = d;
        else if (hold == kMultigridHeldAtRest && !(s.u[e] == Vec3f{0, 0, 0}))
          clean = false;
      }
  // the unit response G of this VOI and grabbed element, from the last step where it is that one
  const MultigridCache key = MultigridCache::of(voi, g, cycles);
  const bool reused = clean && reuse && s.mg_cache == key;
  if (clean) {
    // a new G starts from the last one when the scene asks for it; then u = d G on free elements
    const MultigridRun run = reused ? MultigridRun{} : solve_unit_response(plan, lv, key, cycles, reuse ? warm_cycles : 0, s);
    const float* X = s.mg_g.data();
    for (std::size_t e = 0; e < n; ++e)
      if (!s.mg_held[e]) s.u[e] = Vec3f{d.x * X[e], d.y * X[e], d.z * X[e]};
    return run;
  }
  // each component from its own held data, from zero; X no longer holds G
  s.mg_cache = MultigridCache{};
  float* X = s.mg_g.data();
  for (int c = 0; c < 3; ++c) {
    solve(plan, lv, X, s.mg_p.data(), s.mg_q.data(), cycles, MultigridStart{}, [&](int e) { return s.u[e][c]; });
    for (std::size_t e = 0; e < n; ++e)
      if (!s.mg_held[e]) s.u[e][c] = X[e];
  }
  return {3, false};
}

MultigridRun prime_multigrid_cpu(const Patient& p, const Voi& voi, const Vec3i& grabbed_vox, int cycles,
                                 int warm_cycles, float threshold, float width, float finger_r2, CpuState& s) {
  if (cycles <= 0) return {};
  const Vec3i g = grabbed_vox - voi.lo;
  const MultigridCache key = MultigridCache::of(voi, g, cycles);
  if (s.mg_cache == key) return {};  // held already
  const MultigridPlan plan = multigrid_plan(voi.size, g);
  MultigridLevel lv[kMultigridMaxLevels];
  multigrid_buffers(voi, plan, s, lv);
  // the held mask as a step makes it; the displacement field is not touched
  const long long g_idx = voi.index(g.x, g.y, g.z);
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const long long e = voi.index(i, j, k);
        s.mg_held[e] = hold_of(p, p.grid.index(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k), e == g_idx, i, j, k, g,
                               finger_r2, threshold, width);
      }
  return solve_unit_response(plan, lv, key, cycles, warm_cycles, s);
}

}  // namespace palpsim::deform
