// Multigrid relaxation on the GPU: the same scalar conjugate gradients with a symmetric
// V-cycle preconditioner as server/deform/relax_multigrid.cpp, the same passes in the
// same order (relax_multigrid.h), in one persistent cooperative kernel. Levels with more
// than kBlockNodes nodes run on the whole grid with grid.sync() between passes; the
// coarser ones run in block 0 alone, in its shared memory, with __syncthreads(). A
// grid-wide pass costs a grid barrier whatever its level's size, and a step has 20 of
// them (three grid levels) besides block 0's part. A step whose VOI and grabbed element equal the last
// solved one's reuses the unit response G: one pass, u = d G; another VOI or grabbed
// element starts G from the last one (deform::MultigridStart), so that fewer steps
// (deform.relax_warm_cycles) reach the same distance to the steady state.
#include <cooperative_groups.h>

#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

using deform::MultigridLevel;
using deform::MultigridPlan;

// levels of at most this many nodes (8^3) run in block 0 alone, in its shared memory:
// 4096 (16^3, 61 KB of shared memory) measured about the same, 64 slower; one block's
// pass over 16^3 costs about as much as a grid-wide pass, so moving levels into the
// block gains little
constexpr int kBlockNodes = 512;

// the first level that block 0 handles alone (plan.levels: none)
__host__ __device__ int block_split(const MultigridPlan& plan) {
  for (int l = 0; l < plan.levels; ++l)
    if (deform::node_count(plan.size[l]) <= kBlockNodes) return l;
  return plan.levels;
}

// the threads that share a pass: the whole grid, or block 0 alone
struct Team {
  int first, stride;
};

// calls fn(i, j, k) for the nodes of `colour` of a level of `n` nodes, split over team t:
// task q is row q / half of the level, its (q % half)-th node of that colour
template <typename Fn>
__device__ void each_of_colour(const Vec3i n, int colour, Team t, Fn fn) {
  const int half = (n.x + 1) / 2, rows = n.y * n.z;
  for (int q = t.first; q < rows * half; q += t.stride) {
    const int row = q / half;
    const int k = row / n.y, j = row - k * n.y;
    const int i = 2 * (q - row * half) + ((colour + j + k) & 1);
    if (i < n.x) fn(i, j, k);
  }
}

// one half-sweep of `colour` over level L (levels by value: in registers, where stores
// through their fields cannot alias them)
__device__ void sweep(const MultigridLevel L, int colour, Team t) {
  each_of_colour(L.n, colour, t, [&](int i, int j, int k) { deform::multigrid_sweep_node(L, colour, i, j, k); });
}

// the coarse level from the fine one's residual, one thread per coarse node (block 0)
__device__ void restrict_block(const MultigridLevel fine, const MultigridLevel coarse, const Vec3i o, Team t) {
  for (int e = t.first; e < coarse.count(); e += t.stride) {
    int I, J, K;
    coarse.coords(e, I, J, K);
    const float f = deform::multigrid_restrict_sum(deform::multigrid_restrict_plane(fine, o, I, J, K, -1),
                                                   deform::multigrid_restrict_plane(fine, o, I, J, K, 0),
                                                   deform::multigrid_restrict_plane(fine, o, I, J, K, 1));
    deform::multigrid_coarse_node(coarse, I, J, K, f, deform::multigrid_coarse_byte(fine, o, I, J, K));
  }
}

// the same on the whole grid, four lanes per coarse node: lanes 0-2 sum one plane each
// (dk = -1, 0, 1), lane 3 adds 0 and makes the node's byte, and two shuffles add
// (p0 + p1) + (p2 + 0), the order of multigrid_restrict_sum; whole warps run each round so
// the shuffles see every lane
__device__ void restrict_grid(const MultigridLevel fine, const MultigridLevel coarse, const Vec3i o) {
  const int lane = threadIdx.x & 31;
  const int stride = gridDim.x * blockDim.x;
  const int tasks = 4 * coarse.count();
  for (int t0 = blockIdx.x * blockDim.x + (threadIdx.x & ~31); t0 < tasks; t0 += stride) {
    const int t = t0 + lane, e = t >> 2, part = t & 3;
    const bool mine = t < tasks && part < 3;
    int I = 0, J = 0, K = 0;
    if (t < tasks) coarse.coords(e, I, J, K);
    float v = mine ? deform::multigrid_restrict_plane(fine, o, I, J, K, part - 1) : 0.0f;
    // lane 3 makes the coarse node's byte meanwhile
    const int byte = t < tasks && part == 3 ? deform::multigrid_coarse_byte(fine, o, I, J, K) : 0;
    v += __shfl_down_sync(0xffffffffu, v, 1, 4);
    v += __shfl_down_sync(0xffffffffu, v, 2, 4);
    const int lane3_byte = __shfl_down_sync(0xffffffffu, byte, 3, 4);
    if (t < tasks && part == 0) deform::multigrid_coarse_node(coarse, I, J, K, v, std::uint8_t(lane3_byte));
  }
}

// the coarse correction of level l's red free nodes from level l+1
__device__ void correct_red(const MultigridLevel fine, const MultigridLevel coarse, const Vec3i o, Team t) {
  each_of_colour(fine.n, 0, t, [&](int i, int j, int k) { deform::multigrid_correct_red(fine, coarse, o, i, j, k); });
}

// the residual of level L after its black half-sweep (red free nodes; 0 elsewhere)
__device__ void residual(const MultigridLevel L, Team t) {
  for (int e = t.first; e < L.count(); e += t.stride) {
    int i, j, k;
    L.coords(e, i, j, k);
    deform::multigrid_residual_node(L, i, j, k);
  }
}

// the V-cycle's levels from..to-1 going down (level from's black half-sweep done when
// from is 0), each pass by team t with `sync` after it
template <typename Sync>
__device__ void down(const MultigridLevel* lv, const Vec3i* origin, int from, int to, Team t, bool grid_wide,
                     Sync sync) {
  for (int l = from; l < to; ++l) {
    if (l > 0) {
      sweep(lv[l], 1, t);
      sync();
    }
    residual(lv[l], t);
    sync();
    if (grid_wide)
      restrict_grid(lv[l], lv[l + 1], origin[l]);
    else
      restrict_block(lv[l], lv[l + 1], origin[l], t);
    sync();
  }
}

// ... and back up from level to-1 to from: red correction, black, red (the last red
// half-sweep of level `skip_red`'s is left to the caller)
template <typename Sync>
__device__ void up(const MultigridLevel* lv, const Vec3i* origin, int from, int to, Team t, int skip_red,
                   Sync sync) {
  for (int l = to - 1; l >= from; --l) {
    correct_red(lv[l], lv[l + 1], origin[l], t);
    sync();
    sweep(lv[l], 1, t);
    sync();
    if (l == skip_red) continue;
    sweep(lv[l], 0, t);
    sync();
  }
}

// the coarsest level's half-sweeps after its first red one (its black one unless level
// 0's came with CG's update)
template <typename Sync>
__device__ void coarsest(const MultigridLevel& L, bool black_first, Team t, Sync sync) {
  if (black_first) {
    sweep(L, 1, t);
    sync();
  }
  for (int h = 0; h < deform::kMultigridCoarsestHalfSweeps; ++h) {
    sweep(L, h % 2, t);
    sync();
  }
}

// adds this thread's `v` to *out: a block sum, then one atomic per block
__device__ void block_sum_add(double v, double* out) {
  __shared__ double warp_sums[32];
  for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  if (lane == 0) warp_sums[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = lane < int(blockDim.x >> 5) ? warp_sums[lane] : 0.0;
    for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
    if (lane == 0) atomicAdd(out, v);
  }
  __syncthreads();
}

struct MgArgs {
  StepGeometry geo;
  MultigridPlan plan;
  int src;
  int cycles;
  float threshold, width;
  float finger_r2;  // the fingertip's radius squared (voxel^2; deform::finger_r2)
  int hit;     // the host's cache key matches: G may be reused if the device says it holds it
  int warm_cycles;
  // the last field shifted onto the new grabbed element (its g: m.g_last, swapped there by
  // the host; null: none), the start if the device says that field is a G
  deform::MultigridStart start;
  int parity;  // which of the two dirty flags this launch uses (the other is zeroed for the next)
  int prime;   // G alone for this VOI and grabbed element: u and the counters untouched
  DeviceBuffers b;
  MultigridBuffers m;
};

constexpr int kL = deform::kMultigridMaxLevels;

// the levels' descriptors in global memory (thread 0 of each block): level 0 solves for z
// with right-hand side r (lvs[b]: r[b]), the coarse ones from the plan; and the origins
__device__ __forceinline__ void grid_levels(const MultigridPlan& plan, const MultigridBuffers& m,
                                            const deform::Voi& voi, MultigridLevel (*lvs)[kL], Vec3i* origin) {
  for (int b = 0; b < 2; ++b) {
    lvs[b][0] = MultigridLevel{voi.size, m.z, m.r[b], m.held, m.res};
    for (int l = 1; l < plan.levels; ++l) {
      const long long o = plan.offset[l];
      lvs[b][l] = MultigridLevel{plan.size[l], m.cx + o, m.cf + o, m.cheld + o, m.cres + o};
    }
  }
  for (int l = 0; l + 1 < plan.levels; ++l) origin[l] = plan.origin[l];
}

// the descriptors of levels split..last (the end of the coarse buffers) in block 0's
// shared memory mg_smem (thread 0 of each block)
__device__ __forceinline__ void block_levels(const MultigridPlan& plan, int split, int last, float* mg_smem,
                                             MultigridLevel* sl) {
  const long long base = plan.offset[split];
  const int nb = int(plan.coarse_count - base);
  float* sx = mg_smem;
  float* sf = sx + nb;
  float* sr = sf + nb;
  std::uint8_t* sh = reinterpret_cast<std::uint8_t*>(sr + nb);
  for (int l = split; l <= last; ++l) {
    const int o = int(plan.offset[l] - base);
    sl[l] = MultigridLevel{plan.size[l], sx + o, sf + o, sh + o, sr + o};
  }
}

// the held mask (the grabbed element and the fingertip's soft elements, set to d here;
// material weight 0), and with a reusable G (hit) already u = d G (overwritten later if
// an element held at rest moved: the solves read u at held elements only); returns
// whether one did. Every thread read d before and writes the same d at the grabbed element.
__device__ __forceinline__ bool hold_pass(const MgArgs& a, const MultigridLevel& L0, int n, int g_idx, const Vec3f d,
                                          bool hit, float* const (&u)[3], const float* X, Team all) {
  const MultigridBuffers& m = a.m;
  bool moved_held = false;
  for (int e = all.first; e < n; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    const long long gi = a.geo.patient_index(i, j, k);
    const std::uint8_t hold =
        deform::multigrid_hold(e == g_idx, deform::multigrid_on_finger(i, j, k, a.geo.grabbed, a.finger_r2),
                               a.b.intensity[gi], a.b.bone[gi] != 0, a.threshold, a.width);
    const bool held = hold != deform::kMultigridFree;
    m.held[e] = hold;
    if (a.prime) continue;  // a prime's field is G alone
    if (hold == deform::kMultigridHeldGrabbed) {
      u[0][e] = d.x;
      u[1][e] = d.y;
      u[2][e] = d.z;
    } else if (held && (u[0][e] != 0.0f || u[1][e] != 0.0f || u[2][e] != 0.0f)) {
      moved_held = true;
    }
    if (hit && !held) {
      const float ge = X[e];
      u[0][e] = d.x * ge;
      u[1][e] = d.y * ge;
      u[2][e] = d.z * ge;
    }
  }
  return moved_held;
}

// a solve's start: X the held data, the start on free nodes (0, or the last G shifted);
// r = sum6(X) - 6 X on free nodes; z its first red half-sweep from 0 (X of the neighbours
// from the mask, the data and the start)
template <typename Data>
__device__ __forceinline__ void solve_start(const MultigridBuffers& m, const MultigridLevel& L0, int n, Data data,
                                            const deform::MultigridStart& start, float* X, Team all) {
  for (int e = all.first; e < n; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    const bool held = m.held[e];
    const float xe = held ? data(e) : start.at(i, j, k);
    float s = 0;
    for (int q = 0; q < 6; ++q) {
      const Vec3i nb = Vec3i{i, j, k} + deform::neighbour_offset(q);
      if (!L0.inside(nb.x, nb.y, nb.z)) continue;
      const int ne = L0.index(nb.x, nb.y, nb.z);
      s += m.held[ne] ? data(ne) : start.at(nb.x, nb.y, nb.z);
    }
    const float re = held ? 0.0f : s - 6.0f * xe;
    X[e] = xe;
    m.r[0][e] = re;
    m.z[e] = !held && deform::multigrid_colour(i, j, k) == 0 ? deform::multigrid_smooth(0.0f, re) : 0.0f;
  }
}

// z = M r: the grid down to level split, block 0 below it (in shared memory, sl, when
// split > 0), the grid back up; level 0's last red half-sweep is left to red_and_rho
__device__ __forceinline__ void v_cycle(const MultigridLevel* lv, const MultigridLevel* sl, const Vec3i* origin,
                                        int split, int last, int grid_to, Team all, Team block0,
                                        cg::grid_group& grid) {
  auto gsync = [&] { grid.sync(); };
  auto bsync = [] { __syncthreads(); };
  down(lv, origin, 0, grid_to, all, true, gsync);
  if (split <= last) {
    if (blockIdx.x == 0) {
      const MultigridLevel* bl = split > 0 ? sl : lv;
      if (split > 0) {
        // level split's f, held mask and first red half-sweep into shared memory
        const MultigridLevel g = lv[split], sg = bl[split];
        for (int e = block0.first; e < g.count(); e += block0.stride) {
          sg.x[e] = g.x[e];
          sg.f[e] = g.f[e];
          sg.held[e] = g.held[e];
        }
        __syncthreads();
      }
      down(bl, origin, split, last, block0, false, bsync);
      coarsest(bl[last], last > 0, block0, bsync);
      up(bl, origin, split, last, block0, -1, bsync);
      if (split > 0) {
        const MultigridLevel g = lv[split], sg = bl[split];
        for (int e = block0.first; e < g.count(); e += block0.stride) g.x[e] = sg.x[e];
      }
    }
    grid.sync();
  } else {
    // the coarsest level too large for one block (a thin VOI: level 0 itself)
    coarsest(lv[last], last > 0, all, gsync);
  }
  up(lv, origin, 0, grid_to, all, 0, gsync);
}

// level 0's red half-sweep, when the grid runs it, with this thread's part of rho = r . z
// (rho alone when block 0 ran that half-sweep)
__device__ __forceinline__ double red_and_rho(const MultigridBuffers& m, const MultigridLevel& L0, int n,
                                              const MultigridLevel l0, bool red_on_grid, const float* r, Team all) {
  double part = 0;
  for (int e = all.first; e < n; e += all.stride) {
    if (red_on_grid) {
      int i, j, k;
      L0.coords(e, i, j, k);
      deform::multigrid_sweep_node(l0, 0, i, j, k);
    }
    part += double(r[e]) * m.z[e];
  }
  return part;
}

// p' = z + beta p into p_next, q = A p' on free nodes (p' of the neighbours from z and p);
// returns this thread's part of p' . q
__device__ __forceinline__ double direction_pass(const MultigridBuffers& m, const MultigridLevel& L0, int n, int c,
                                                 float beta, const float* p, float* p_next, Team all) {
  double part = 0;
  for (int e = all.first; e < n; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    const float pe = c == 0 ? m.z[e] : m.z[e] + p[e] * beta;
    float s = 0;
    for (int q = 0; q < 6; ++q) {
      const Vec3i nb = Vec3i{i, j, k} + deform::neighbour_offset(q);
      if (!L0.inside(nb.x, nb.y, nb.z)) continue;
      const int ne = L0.index(nb.x, nb.y, nb.z);
      s += c == 0 ? m.z[ne] : m.z[ne] + p[ne] * beta;
    }
    const float qe = m.held[e] ? 0.0f : 6.0f * pe - s;
    p_next[e] = pe;
    m.q[e] = qe;
    part += double(pe) * qe;
  }
  return part;
}

// X += alpha p; r' = r - alpha q into r_next; z for the next V-cycle: r' / 6 at red free
// nodes, the black half-sweep from those at black free nodes
__device__ __forceinline__ void update_pass(const MultigridBuffers& m, const MultigridLevel& L0, int n, float alpha,
                                            const float* pn, const float* r, float* r_next, float* X, Team all) {
  for (int e = all.first; e < n; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    X[e] += pn[e] * alpha;
    const float re = deform::multigrid_cg_residual(r[e], m.q[e], alpha);
    r_next[e] = re;
    float ze = 0;
    if (!m.held[e]) {
      if (deform::multigrid_colour(i, j, k) == 0) {
        ze = deform::multigrid_smooth(0.0f, re);
      } else {
        float s = 0;
        for (int q = 0; q < 6; ++q) {
          const Vec3i nb = Vec3i{i, j, k} + deform::neighbour_offset(q);
          if (!L0.inside(nb.x, nb.y, nb.z)) continue;
          const int ne = L0.index(nb.x, nb.y, nb.z);
          s += m.held[ne] ? 0.0f : deform::multigrid_smooth(0.0f, deform::multigrid_cg_residual(r[ne], m.q[ne], alpha));
        }
        ze = deform::multigrid_smooth(s, re);
      }
    }
    m.z[e] = ze;
  }
}

// one solve's CG cycles after its start: a V-cycle, rho, the direction and q, then X and
// r (dots: this solve's 2 per cycle); the last cycle's X += alpha p is left to the output
// pass (stepped), with its alpha and the buffer (pc) of p
__device__ __forceinline__ void cg_cycles(const MultigridBuffers& m, MultigridLevel (*lvs)[kL], const MultigridLevel* sl,
                                          const Vec3i* origin, int split, int last, int grid_to,
                                          const MultigridLevel& L0, int n, int cycles, double* dots, float* X,
                                          Team all, Team block0, cg::grid_group& grid, bool& stepped, float& alpha,
                                          int& pc) {
  int cur = 0;
  double rho = 0;
  for (int c = 0; c < cycles; ++c) {
    const MultigridLevel* lv = lvs[cur];
    v_cycle(lv, sl, origin, split, last, grid_to, all, block0, grid);
    const float* r = m.r[cur];
    block_sum_add(red_and_rho(m, L0, n, lv[0], grid_to > 0, r, all), &dots[2 * c]);
    grid.sync();
    const double rho_new = dots[2 * c];
    if (!(rho_new > 0)) break;  // r = 0: converged
    const float beta = c == 0 ? 0.0f : float(rho_new / rho);
    rho = rho_new;
    block_sum_add(direction_pass(m, L0, n, c, beta, m.p[pc], m.p[pc ^ 1], all), &dots[2 * c + 1]);
    pc ^= 1;
    grid.sync();
    const double pq = dots[2 * c + 1];
    if (!(pq > 0)) break;
    alpha = float(rho / pq);
    if (c + 1 == cycles) {
      stepped = true;
      break;
    }
    update_pass(m, L0, n, alpha, m.p[pc], r, m.r[cur ^ 1], X, all);
    cur ^= 1;
    grid.sync();
  }
}

// the last X += alpha p (stepped), and u from X on free elements: d X (X = G, clean) or
// component comp
__device__ __forceinline__ void output_pass(const MultigridBuffers& m, int n, bool stepped, float alpha,
                                            const float* pn, float* X, bool prime, bool clean, const Vec3f d,
                                            float* const (&u)[3], int comp, Team all) {
  for (int e = all.first; e < n; e += all.stride) {
    if (stepped) X[e] += pn[e] * alpha;
    if (m.held[e] || prime) continue;
    const float xe = X[e];
    if (clean) {
      u[0][e] = d.x * xe;
      u[1][e] = d.y * xe;
      u[2][e] = d.z * xe;
    } else {
      u[comp][e] = xe;
    }
  }
}

__global__ void __launch_bounds__(kPersistentThreads) relax_multigrid_kernel(MgArgs a) {
  cg::grid_group grid = cg::this_grid();
  const Team all{int(blockIdx.x * blockDim.x + threadIdx.x), int(gridDim.x * blockDim.x)};
  const Team block0{int(threadIdx.x), int(blockDim.x)};
  const bool first_thread = blockIdx.x == 0 && threadIdx.x == 0;
  const MultigridPlan& plan = a.plan;
  const MultigridBuffers& m = a.m;
  const deform::Voi& voi = a.geo.voi;
  float* u[3] = {a.b.u[a.src][0], a.b.u[a.src][1], a.b.u[a.src][2]};
  // the levels in shared memory, one copy per block (per-thread arrays indexed by level
  // would live in local memory), as raw bytes (__shared__ allows no default member
  // initialisers)
  __shared__ alignas(16) unsigned char level_bytes[3 * kL * sizeof(MultigridLevel) + kL * sizeof(Vec3i)];
  auto* lvs = reinterpret_cast<MultigridLevel(*)[kL]>(level_bytes);
  MultigridLevel* sl = reinterpret_cast<MultigridLevel*>(level_bytes + 2 * kL * sizeof(MultigridLevel));
  Vec3i* origin = reinterpret_cast<Vec3i*>(level_bytes + 3 * kL * sizeof(MultigridLevel));
  if (threadIdx.x == 0) grid_levels(plan, m, voi, lvs, origin);
  const MultigridLevel L0{voi.size, m.z, m.r[0], m.held, m.res};  // level 0 (its f aside)
  const int n = L0.count();
  float* X = m.g;  // the field: X = G
  const int split = block_split(plan);
  const int last = plan.levels - 1;
  const int grid_to = split < last ? split : last;
  extern __shared__ float mg_smem[];
  if (threadIdx.x == 0 && split > 0 && split <= last) block_levels(plan, split, last, mg_smem, sl);
  __syncthreads();
  const int g_idx = L0.index(a.geo.grabbed.x, a.geo.grabbed.y, a.geo.grabbed.z);
  const Vec3f d = a.prime ? Vec3f{0, 0, 0} : Vec3f{u[0][g_idx], u[1][g_idx], u[2][g_idx]};
  int* dirty = m.flags + a.parity;
  const bool kept = *(volatile int*)(m.flags + 2) != 0;  // read before the first thread may clear it
  const bool hit = a.hit && kept;

  // the held mask, u = d G with a reusable G, and whether an element held at rest moved
  if (first_thread) m.flags[a.parity ^ 1] = 0;
  for (int e = all.first; e < 6 * max(a.cycles, a.warm_cycles); e += all.stride) m.dots[e] = 0.0;
  if (hold_pass(a, L0, n, g_idx, d, hit, u, X, all)) *(volatile int*)dirty = 1;
  grid.sync();
  const bool clean = *(volatile int*)dirty == 0;
  // one scalar solve per component with its own held data, or one for G when clean
  const int solves = hit && clean ? 0 : (clean ? 1 : 3);
  // a new G from the last one (the host swapped it into g_last) when that one is a G
  const bool warm = solves == 1 && a.start.g && kept;
  const int cycles = warm ? a.warm_cycles : a.cycles;
  const deform::MultigridStart start = warm ? a.start : deform::MultigridStart{};
  if (first_thread && !a.prime) {
    a.b.counters->relax_solves = solves;
    a.b.counters->relax_warm = warm;
    if (!clean) m.flags[2] = 0;  // X will not hold G
  }
  if (solves == 0) return;
  for (int comp = 0; comp < solves; ++comp) {
    const float* ucomp = u[comp];
    auto data = [&](int e) { return clean ? (m.held[e] == deform::kMultigridHeldGrabbed ? 1.0f : 0.0f) : ucomp[e]; };
    solve_start(m, L0, n, data, start, X, all);
    grid.sync();
    sweep(lvs[0][0], 1, all);
    grid.sync();
    int pc = 0;
    float alpha = 0;
    bool stepped = false;  // the last step's X += alpha p is left to the output pass
    cg_cycles(m, lvs, sl, origin, split, last, grid_to, L0, n, cycles, m.dots + 2 * cycles * comp, X, all, block0,
              grid, stepped, alpha, pc);
    output_pass(m, n, stepped, alpha, m.p[pc], X, a.prime, clean, d, u, comp, all);
    if (comp + 1 < solves) grid.sync();
  }
  if (clean && first_thread) m.flags[2] = 1;  // X holds G
}

}  // namespace

int relax_multigrid_blocks() {
  int dev = 0, sms = 0, per_sm = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev));
  PALPSIM_CUDA_CHECK(
      cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, relax_multigrid_kernel, kPersistentThreads, 0));
  // one block per SM, as the other persistent kernels: a grid barrier costs about one atomic per block
  const int blocks = sms * std::min(per_sm, kPersistentBlocksPerSm);
  if (blocks < 1) throw Error("CUDA: the multigrid relaxation kernel does not fit on the device");
  return blocks;
}

bool multigrid_reuses(const StepGeometry& g, int cycles, bool reuse, const MultigridBuffers& m) {
  return reuse && m.cache == deform::MultigridCache::of(g.voi, g.grabbed, cycles);
}

namespace {

// the reuse pass of relax_multigrid_kernel for a batch's reusing sessions (blockIdx.y): the
// held mask's test and u = d G on free elements, in the same arithmetic
__global__ void reuse_batch_kernel(const BatchItem* __restrict__ items, float threshold, float width) {
  const BatchItem& it = items[blockIdx.y];
  if (!it.mg_g) return;
  const StepGeometry& geo = it.geo;
  const deform::Voi& voi = geo.voi;
  const int n = int(voi.count());  // VOIs hold < 2^31 voxels (checked at bind)
  float* u[3] = {it.b.u[it.relax_src][0], it.b.u[it.relax_src][1], it.b.u[it.relax_src][2]};
  const int g_idx = (geo.grabbed.z * voi.size.y + geo.grabbed.y) * voi.size.x + geo.grabbed.x;
  const Vec3f d{u[0][g_idx], u[1][g_idx], u[2][g_idx]};  // the grabbed element is held: never written here
  for (int e = int(blockIdx.x * blockDim.x + threadIdx.x); e < n; e += int(gridDim.x * blockDim.x)) {
    const int i = e % voi.size.x, j = (e / voi.size.x) % voi.size.y, k = e / (voi.size.x * voi.size.y);
    const long long gi = geo.patient_index(i, j, k);
    const std::uint8_t hold =
        deform::multigrid_hold(e == g_idx, deform::multigrid_on_finger(i, j, k, geo.grabbed, it.finger_r2),
                               it.b.intensity[gi], it.b.bone[gi] != 0, threshold, width);
    if (hold == deform::kMultigridFree) {
      const float ge = it.mg_g[e];
      u[0][e] = d.x * ge;
      u[1][e] = d.y * ge;
      u[2][e] = d.z * ge;
    } else if (hold == deform::kMultigridHeldGrabbed) {
      u[0][e] = d.x;
      u[1][e] = d.y;
      u[2][e] = d.z;
    }
  }
  if (blockIdx.x == 0 && threadIdx.x == 0) {
    it.b.counters->relax_solves = 0;
    it.b.counters->relax_warm = 0;
  }
}

}  // namespace

void launch_multigrid_reuse_batch(const BatchItem* items, int n, unsigned max_count, float threshold, float width,
                                  cudaStream_t stream) {
  if (n < 1) return;
  const unsigned threads = 256;
  const unsigned blocks = std::max(1u, std::min((max_count + threads - 1) / threads, 256u));
  reuse_batch_kernel<<<dim3(blocks, unsigned(n)), threads, 0, stream>>>(items, threshold, width);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
}

bool launch_relax_multigrid(const StepGeometry& g, int src, int cycles, int warm_cycles, float threshold, float width,
                            float finger_r2, bool reuse, const DeviceBuffers& b, MultigridBuffers& m, int max_blocks,
                            cudaStream_t stream, bool prime) {
  if (cycles <= 0) return false;
  const long long n = g.voi.count();
  MgArgs a;
  a.geo = g;
  a.plan = deform::multigrid_plan(g.voi.size, g.grabbed);
  if (a.plan.coarse_count > m.coarse_capacity || n > m.capacity)
    throw Error("deform backend \"cuda\": the multigrid buffers are smaller than this VOI needs");
  a.src = src;
  a.cycles = std::min(cycles, deform::kMultigridMaxCycles);
  a.threshold = threshold;
  a.width = width;
  a.finger_r2 = finger_r2;
  // the unit response in m.g was solved for this VOI and grabbed element (if the device
  // found the step clean then: flags[2])
  a.hit = !prime && multigrid_reuses(g, cycles, reuse, m);
  a.prime = prime;
  // another VOI or grabbed element than the last launch's (multigrid_start; whether that
  // field is a G the device knows): that field becomes the start, the new one goes
  // to the other buffer (a swap: a.start.g stays the old field's)
  a.start = reuse && !a.hit && warm_cycles > 0 ? deform::multigrid_start(m.cache, m.g, g.voi.lo, g.grabbed)
                                               : deform::MultigridStart{};
  a.warm_cycles = deform::multigrid_warm_steps(a.start, warm_cycles);  // at most kMultigridMaxCycles
  m.warm_steps = a.warm_cycles;
  if (a.start.g) std::swap(m.g, m.g_last);
  m.cache = deform::MultigridCache::of(g.voi, g.grabbed, cycles);
  a.parity = int(m.launches++ & 1);
  // block 0's shared memory: levels split..last (x, f, residual, held mask); each level
  // has at most (2/3)^3 of the nodes of the one above, so below 512 / (1 - 0.3) nodes,
  // 10 KB, within the 48 KB a launch may take without opting in
  const int split = block_split(a.plan);
  std::size_t smem = 0;
  if (split > 0 && split < a.plan.levels)
    smem = std::size_t(a.plan.coarse_count - a.plan.offset[split]) * (3 * sizeof(float) + 1);
  a.b = b;
  a.m = m;
  const int blocks = int(std::min<long long>(max_blocks, (n + kPersistentThreads - 1) / kPersistentThreads));
  void* args[] = {&a};
  PALPSIM_CUDA_CHECK(cudaLaunchCooperativeKernel((const void*)relax_multigrid_kernel, dim3(std::max(blocks, 1)),
                                                 dim3(kPersistentThreads), args, smem, stream));
  return a.start.g != nullptr;
}

}  // namespace palpsim::cuda
