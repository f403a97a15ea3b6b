// Multigrid relaxation on the CPU: V-cycles to the explicit relaxation's steady state
// (the plan and per-node math are in relax_multigrid.h).
#include "deform/relax_multigrid.h"

#include <algorithm>

#include "deform/cpu_backend.h"

namespace palpsim::deform {

namespace {

// one level: its nodes, field x, right-hand side f (null on level 0, where f = 0),
// residual r and held mask
struct Level {
  Vec3i n;
  Vec3f* x = nullptr;
  Vec3f* f = nullptr;
  Vec3f* r = nullptr;
  std::uint8_t* held = nullptr;

  long long index(int i, int j, int k) const { return ((long long)k * n.y + j) * n.x + i; }
  bool inside(int i, int j, int k) const { return i >= 0 && j >= 0 && k >= 0 && i < n.x && j < n.y && k < n.z; }
  Vec3f rhs(long long e) const { return f ? f[e] : Vec3f{0, 0, 0}; }
  // the six neighbours' x in the fixed order, zero outside the level
  Vec3f sum6(int i, int j, int k) const {
    Vec3f s{0, 0, 0};
    for (int q = 0; q < 6; ++q) {
      const Vec3i m = Vec3i{i, j, k} + neighbour_offset(q);
      if (inside(m.x, m.y, m.z)) s += x[index(m.x, m.y, m.z)];
    }
    return s;
  }
};

// red-black Gauss-Seidel: nodes of one colour have no neighbour of that colour, so
// updating them in place in any order is the GPU's parallel update
void smooth(const Level& L, int sweeps, bool backward) {
  for (int s = 0; s < sweeps; ++s)
    for (int c = 0; c < 2; ++c) {
      const int colour = backward ? 1 - c : c;
      for (int k = 0; k < L.n.z; ++k)
        for (int j = 0; j < L.n.y; ++j)
          for (int i = 0; i < L.n.x; ++i) {
            const long long e = L.index(i, j, k);
            if (multigrid_colour(i, j, k) != colour || L.held[e]) continue;
            L.x[e] = multigrid_smooth(L.sum6(i, j, k), L.rhs(e));
          }
    }
}

// the residual of every node, 0 at held ones
void residual(const Level& L) {
  for (int k = 0; k < L.n.z; ++k)
    for (int j = 0; j < L.n.y; ++j)
      for (int i = 0; i < L.n.x; ++i) {
        const long long e = L.index(i, j, k);
        L.r[e] = L.held[e] ? Vec3f{0, 0, 0} : multigrid_residual(L.x[e], L.sum6(i, j, k), L.rhs(e));
      }
}

// the coarse level's right-hand side and held mask from the fine residual; x = 0 there
void restrict_to(const Level& fine, const Level& coarse, const Vec3i& o) {
  auto load_r = [&](int i, int j, int k) { return fine.inside(i, j, k) ? fine.r[fine.index(i, j, k)] : Vec3f{0, 0, 0}; };
  Vec3f* f = coarse.f;
  for (int k = 0; k < coarse.n.z; ++k)
    for (int j = 0; j < coarse.n.y; ++j)
      for (int i = 0; i < coarse.n.x; ++i) {
        const long long e = coarse.index(i, j, k);
        f[e] = multigrid_restrict(load_r, o, i, j, k);
        coarse.held[e] = fine.held[fine.index(2 * i + o.x, 2 * j + o.y, 2 * k + o.z)];
        coarse.x[e] = Vec3f{0, 0, 0};
      }
}

// the coarse correction added to every free fine node
void correct(const Level& fine, const Level& coarse, const Vec3i& o) {
  auto load_x = [&](int i, int j, int k) {
    return coarse.inside(i, j, k) ? coarse.x[coarse.index(i, j, k)] : Vec3f{0, 0, 0};
  };
  for (int k = 0; k < fine.n.z; ++k)
    for (int j = 0; j < fine.n.y; ++j)
      for (int i = 0; i < fine.n.x; ++i) {
        const long long e = fine.index(i, j, k);
        if (!fine.held[e]) fine.x[e] += multigrid_prolong(load_x, o, i, j, k);
      }
}

// q = A p = 6 p - sum6 on free nodes (the operator; `r` of the level receives it)
void apply(const Level& L) {
  for (int k = 0; k < L.n.z; ++k)
    for (int j = 0; j < L.n.y; ++j)
      for (int i = 0; i < L.n.x; ++i) {
        const long long e = L.index(i, j, k);
        L.r[e] = L.held[e] ? Vec3f{0, 0, 0} : -multigrid_residual(L.x[e], L.sum6(i, j, k), Vec3f{0, 0, 0});
      }
}

// one symmetric V-cycle on levels lv (level 0's x must start at 0): red-black sweeps
// down, black-red sweeps up, so the preconditioner is symmetric as CG needs
void vcycle(Level* lv, const MultigridPlan& plan) {
  const int last = plan.levels - 1;
  for (int l = 0; l < last; ++l) {
    smooth(lv[l], kMultigridPreSweeps, false);
    residual(lv[l]);
    restrict_to(lv[l], lv[l + 1], plan.origin[l]);
  }
  // the coarsest level (the whole VOI when it is too thin to coarsen)
  for (int s = 0; s < kMultigridCoarsestSweeps; ++s) smooth(lv[last], 1, false);
  for (int s = 0; s < kMultigridCoarsestSweeps; ++s) smooth(lv[last], 1, true);
  for (int l = last - 1; l >= 0; --l) {
    correct(lv[l], lv[l + 1], plan.origin[l]);
    smooth(lv[l], kMultigridPostSweeps, true);
  }
}

}  // namespace

void relax_multigrid_cpu(const Patient& p, const ChainMailStats& st, int cycles, float threshold, float width,
                         CpuState& s) {
  if (cycles <= 0) return;  // no steps: the field stays as ChainMail left it
  const Voi& voi = st.voi;
  const Grid& grid = p.grid;
  const Vec3i g = st.grabbed_vox - voi.lo;
  const MultigridPlan plan = multigrid_plan(voi.size, g);
  const std::size_t n = std::size_t(voi.count());
  const std::size_t nc = std::size_t(plan.coarse_count);
  for (auto* v : {&s.mg_r0, &s.mg_z, &s.mg_p, &s.mg_q})
    if (v->size() < n) v->resize(n);
  if (s.mg_held.size() < n) s.mg_held.resize(n);
  if (s.mg_x.size() < nc) {
    s.mg_x.resize(nc);
    s.mg_f.resize(nc);
    s.mg_r.resize(nc);
    s.mg_held_coarse.resize(nc);
  }
  // level 0 holds the grabbed element and every element of material weight 0 (bone)
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const std::size_t gi = grid.index(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k);
        s.mg_held[voi.index(i, j, k)] =
            Vec3i{i, j, k} == g ||
            material_weight(p.intensity.data[gi], p.bone.data[gi] != 0, threshold, width) == 0.0f;
      }
  // the preconditioner's levels: 0 solves for z with right-hand side r (residual in q),
  // the others live in the coarse buffers
  Level lv[kMultigridMaxLevels];
  lv[0] = Level{voi.size, s.mg_z.data(), s.mg_r0.data(), s.mg_q.data(), s.mg_held.data()};
  for (int l = 1; l < plan.levels; ++l) {
    const long long o = plan.offset[l];
    lv[l] = Level{plan.size[l], s.mg_x.data() + o, s.mg_f.data() + o, s.mg_r.data() + o, s.mg_held_coarse.data() + o};
  }
  Vec3f *r = s.mg_r0.data(), *z = s.mg_z.data(), *pd = s.mg_p.data(), *q = s.mg_q.data();
  auto dot = [&](const Vec3f* a, const Vec3f* b) {
    double d = 0;
    for (std::size_t e = 0; e < n; ++e) d += double(a[e].x) * b[e].x + double(a[e].y) * b[e].y + double(a[e].z) * b[e].z;
    return d;
  };
  // start from u = 0 on free elements: the steady state depends on the held elements only,
  // and ChainMail's field lies farther from it than zero does (6.6 against 1 times the
  // steady state's RMS on the phantom press)
  for (std::size_t e = 0; e < n; ++e)
    if (!s.mg_held[e]) s.u[e] = Vec3f{0, 0, 0};
  // r = -(6 u - sum6) on free elements: the residual of the steady state
  residual(Level{voi.size, s.u.data(), nullptr, r, s.mg_held.data()});
  double rho = 0;
  for (int c = 0; c < cycles; ++c) {
    // z = one symmetric V-cycle applied to r
    std::fill_n(z, n, Vec3f{0, 0, 0});
    vcycle(lv, plan);
    const double rho_new = dot(r, z);
    if (!(rho_new > 0)) break;  // r = 0: converged (or z lost positivity to rounding)
    // p = z + beta p
    const double beta = c == 0 ? 0.0 : rho_new / rho;
    for (std::size_t e = 0; e < n; ++e) pd[e] = z[e] + pd[e] * float(beta);
    rho = rho_new;
    // q = A p (free elements; p is 0 at held ones)
    const Level pl{voi.size, pd, nullptr, q, s.mg_held.data()};
    apply(pl);
    const double pq = dot(pd, q);
    if (!(pq > 0)) break;
    const float alpha = float(rho / pq);
    for (std::size_t e = 0; e < n; ++e) {
      s.u[e] += pd[e] * alpha;
      r[e] -= q[e] * alpha;
    }
  }
}

}  // namespace palpsim::deform
