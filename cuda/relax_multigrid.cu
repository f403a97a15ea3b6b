// Multigrid relaxation on the GPU: the same conjugate gradients with a symmetric
// V-cycle preconditioner as server/deform/relax_multigrid.cpp, in one persistent
// cooperative kernel. Levels with more than kBlockNodes nodes run on the whole grid
// with grid.sync() between passes; the coarser ones run in block 0 alone with
// __syncthreads(). Each grid-wide pass with its barrier costs ~4.8 us at VOI 64 on the
// H100 whatever the level's size (a step has 24), so the step's cost is its barriers.
#include <cooperative_groups.h>

#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

using deform::MultigridPlan;

// levels of at most this many nodes (8^3) run in block 0 alone: measured at VOI 64 on
// the H100, a step took 118 us with 512, 129 us with 4096 (16^3 in one block), 144 us
// with none and 330 us with 32768
constexpr long long kBlockNodes = 512;


// one level: nodes, field x, right-hand side f (null: 0), residual r, held mask
struct Level {
  Vec3i n;
  Vec3f* x;
  Vec3f* f;
  Vec3f* r;
  std::uint8_t* held;

  __device__ int count() const { return n.x * n.y * n.z; }
  __device__ bool inside(int i, int j, int k) const { return i >= 0 && j >= 0 && k >= 0 && i < n.x && j < n.y && k < n.z; }
  __device__ int index(int i, int j, int k) const { return (k * n.y + j) * n.x + i; }
  __device__ void coords(int e, int& i, int& j, int& k) const {
    k = e / (n.x * n.y);
    const int rem = e - k * n.x * n.y;
    j = rem / n.x;
    i = rem - j * n.x;
  }
  __device__ Vec3f rhs(int e) const { return f ? f[e] : Vec3f{0, 0, 0}; }
  // the six neighbours of `v` in the fixed order, zero outside the level
  __device__ Vec3f sum6(const Vec3f* v, int i, int j, int k) const {
    Vec3f s{0, 0, 0};
    for (int q = 0; q < 6; ++q) {
      const Vec3i m = Vec3i{i, j, k} + deform::neighbour_offset(q);
      if (inside(m.x, m.y, m.z)) s += v[index(m.x, m.y, m.z)];
    }
    return s;
  }
};

// the threads that share a pass: the whole grid, or block 0 alone
struct Team {
  unsigned first, stride;
};

__device__ void smooth_colour(const Level& L, int colour, Team t) {
  for (int e = int(t.first); e < L.count(); e += int(t.stride)) {
    int i, j, k;
    L.coords(e, i, j, k);
    if (deform::multigrid_colour(i, j, k) != colour || L.held[e]) continue;
    L.x[e] = deform::multigrid_smooth(L.sum6(L.x, i, j, k), L.rhs(e));
  }
}

__device__ void residual(const Level& L, Team t) {
  for (int e = int(t.first); e < L.count(); e += int(t.stride)) {
    int i, j, k;
    L.coords(e, i, j, k);
    L.r[e] = L.held[e] ? Vec3f{0, 0, 0} : deform::multigrid_residual(L.x[e], L.sum6(L.x, i, j, k), L.rhs(e));
  }
}

__device__ void restrict_to(const Level& fine, const Level& coarse, const Vec3i& o, Team t) {
  auto load_r = [&](int i, int j, int k) { return fine.inside(i, j, k) ? fine.r[fine.index(i, j, k)] : Vec3f{0, 0, 0}; };
  for (int e = int(t.first); e < coarse.count(); e += int(t.stride)) {
    int i, j, k;
    coarse.coords(e, i, j, k);
    coarse.f[e] = deform::multigrid_restrict(load_r, o, i, j, k);
    coarse.held[e] = fine.held[fine.index(2 * i + o.x, 2 * j + o.y, 2 * k + o.z)];
    coarse.x[e] = Vec3f{0, 0, 0};
  }
}

__device__ void correct(const Level& fine, const Level& coarse, const Vec3i& o, Team t) {
  auto load_x = [&](int i, int j, int k) { return coarse.inside(i, j, k) ? coarse.x[coarse.index(i, j, k)] : Vec3f{0, 0, 0}; };
  for (int e = int(t.first); e < fine.count(); e += int(t.stride)) {
    int i, j, k;
    fine.coords(e, i, j, k);
    if (!fine.held[e]) fine.x[e] += deform::multigrid_prolong(load_x, o, i, j, k);
  }
}

// the V-cycle from level `from` down to the coarsest and back (level from's x starts at
// 0), all passes by team `t`, `sync` between them
// (level 0's first red half-sweep is left out when the caller did it: from z = 0 it is
// z = r / 6 on red free nodes, which CG's update pass writes)
template <typename Sync>
__device__ void vcycle(const Level* lv, const MultigridPlan& plan, int from, int to, Team t, Sync sync) {
  for (int l = from; l < to; ++l) {
    for (int s = 0; s < deform::kMultigridPreSweeps; ++s)
      for (int c = 0; c < 2; ++c) {
        if (l == 0 && s == 0 && c == 0) continue;
        smooth_colour(lv[l], c, t);
        sync();
      }
    residual(lv[l], t);
    sync();
    restrict_to(lv[l], lv[l + 1], plan.origin[l], t);
    sync();
  }
}

template <typename Sync>
__device__ void vcycle_up(const Level* lv, const MultigridPlan& plan, int from, int to, Team t, Sync sync) {
  for (int l = to - 1; l >= from; --l) {
    correct(lv[l], lv[l + 1], plan.origin[l], t);
    sync();
    for (int s = 0; s < deform::kMultigridPostSweeps; ++s)
      for (int c = 1; c >= 0; --c) {
        smooth_colour(lv[l], c, t);
        sync();
      }
  }
}

// the coarsest level's symmetric sweeps
template <typename Sync>
__device__ void coarsest(const Level& L, int sweeps, Team t, Sync sync) {
  // forward then backward, so the V-cycle stays symmetric
  for (int dir = 0; dir < 2; ++dir)
    for (int s = 0; s < sweeps; ++s)
      for (int c = 0; c < 2; ++c) {
        smooth_colour(L, dir == 0 ? c : 1 - c, t);
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

__device__ double dot3(const Vec3f& a, const Vec3f& b) { return double(a.x) * b.x + double(a.y) * b.y + double(a.z) * b.z; }

struct MgArgs {
  StepGeometry geo;
  MultigridPlan plan;
  int src;
  int cycles;
  float threshold, width;
  DeviceBuffers b;
  MultigridBuffers m;
};

__global__ void __launch_bounds__(kPersistentThreads) relax_multigrid_kernel(MgArgs a) {
  cg::grid_group grid = cg::this_grid();
  auto gsync = [&] { grid.sync(); };
  auto bsync = [] { __syncthreads(); };
  const Team all{blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x};
  const Team block0{threadIdx.x, blockDim.x};
  const MultigridPlan& plan = a.plan;
  const MultigridBuffers& m = a.m;
  const deform::Voi& voi = a.geo.voi;
  const int n = int(voi.count());
  float* u[3] = {a.b.u[a.src][0], a.b.u[a.src][1], a.b.u[a.src][2]};
  // the levels: 0 solves for z with right-hand side r (residual in q); the field is X
  Level lv[deform::kMultigridMaxLevels];
  lv[0] = Level{voi.size, m.z, m.r, m.q, m.held};
  for (int l = 1; l < plan.levels; ++l) {
    const long long o = plan.offset[l];
    lv[l] = Level{plan.size[l], m.cx + o, m.cf + o, m.cr + o, m.cheld + o};
  }
  const Level field{voi.size, m.x, nullptr, m.r, m.held};
  // the first level that block 0 handles alone
  int split = plan.levels;
  for (int l = 0; l < plan.levels; ++l)
    if (deform::node_count(plan.size[l]) <= kBlockNodes) {
      split = l;
      break;
    }
  const int last = plan.levels - 1;
  const int grid_to = split < last ? split : last;

  // X from u, the held mask (grabbed element, material weight 0), dot sums zeroed
  const int g_idx = field.index(a.geo.grabbed.x, a.geo.grabbed.y, a.geo.grabbed.z);
  for (int e = int(all.first); e < n; e += int(all.stride)) {
    int i, j, k;
    field.coords(e, i, j, k);
    const long long gi = ((long long)(voi.lo.z + k) * a.geo.volume_size.y + (voi.lo.y + j)) * a.geo.volume_size.x +
                         (voi.lo.x + i);
    const bool held =
        e == g_idx || deform::material_weight(a.b.intensity[gi], a.b.bone[gi] != 0, a.threshold, a.width) == 0.0f;
    // the start: u on held elements, 0 on free ones (as the CPU reference)
    m.x[e] = held ? Vec3f{u[0][e], u[1][e], u[2][e]} : Vec3f{0, 0, 0};
    m.held[e] = held;
    m.p[e] = Vec3f{0, 0, 0};
  }
  if (all.first < unsigned(2 * a.cycles)) m.dots[all.first] = 0.0;
  grid.sync();
  // r = -(6 X - sum6) on free elements; z = r / 6 on red free elements (the V-cycle's
  // first half-sweep from z = 0), 0 elsewhere
  for (int e = int(all.first); e < n; e += int(all.stride)) {
    int i, j, k;
    field.coords(e, i, j, k);
    const Vec3f r = m.held[e] ? Vec3f{0, 0, 0} : deform::multigrid_residual(m.x[e], field.sum6(m.x, i, j, k), Vec3f{0, 0, 0});
    m.r[e] = r;
    m.z[e] = deform::multigrid_colour(i, j, k) == 0 ? deform::multigrid_smooth(Vec3f{0, 0, 0}, r) : Vec3f{0, 0, 0};
  }
  grid.sync();

  Vec3f* p = m.p;
  Vec3f* p_next = m.p2;
  double rho = 0;
  for (int c = 0; c < a.cycles; ++c) {
    // z = one symmetric V-cycle applied to r: the grid down to level `split`, block 0
    // below it, the grid back up
    vcycle(lv, plan, 0, grid_to, all, gsync);
    if (split <= last) {
      if (blockIdx.x == 0) {
        vcycle(lv, plan, split, last, block0, bsync);
        coarsest(lv[last], deform::kMultigridCoarsestSweeps, block0, bsync);
        vcycle_up(lv, plan, split, last, block0, bsync);
      }
      grid.sync();
    } else {
      coarsest(lv[last], deform::kMultigridCoarsestSweeps, all, gsync);  // a thin VOI whose coarsest level is too large for one block
    }
    vcycle_up(lv, plan, 0, grid_to, all, gsync);
    // rho = r . z
    double part = 0;
    for (int e = int(all.first); e < n; e += int(all.stride)) part += dot3(m.r[e], m.z[e]);
    block_sum_add(part, &m.dots[2 * c]);
    grid.sync();
    const double rho_new = m.dots[2 * c];
    if (!(rho_new > 0)) break;  // r = 0: converged
    const float beta = c == 0 ? 0.0f : float(rho_new / rho);
    rho = rho_new;
    // p' = z + beta p into the other buffer, q = A p' on free elements (p' of the
    // neighbours from z and p), and p' . q
    part = 0;
    for (int e = int(all.first); e < n; e += int(all.stride)) {
      int i, j, k;
      field.coords(e, i, j, k);
      const Vec3f pe = m.z[e] + p[e] * beta;
      Vec3f sum6{0, 0, 0};
      for (int nq = 0; nq < 6; ++nq) {
        const Vec3i nb = Vec3i{i, j, k} + deform::neighbour_offset(nq);
        if (!field.inside(nb.x, nb.y, nb.z)) continue;
        const int ne = field.index(nb.x, nb.y, nb.z);
        sum6 += m.z[ne] + p[ne] * beta;
      }
      const Vec3f q = m.held[e] ? Vec3f{0, 0, 0} : -deform::multigrid_residual(pe, sum6, Vec3f{0, 0, 0});
      p_next[e] = pe;
      m.q[e] = q;
      part += dot3(pe, q);
    }
    block_sum_add(part, &m.dots[2 * c + 1]);
    Vec3f* t = p;
    p = p_next;
    p_next = t;
    grid.sync();
    const double pq = m.dots[2 * c + 1];
    if (!(pq > 0)) break;
    const float alpha = float(rho / pq);
    // X += alpha p, r -= alpha q, and z for the next V-cycle as at the start
    for (int e = int(all.first); e < n; e += int(all.stride)) {
      int i, j, k;
      field.coords(e, i, j, k);
      m.x[e] += p[e] * alpha;
      const Vec3f r = m.r[e] - m.q[e] * alpha;
      m.r[e] = r;
      m.z[e] = deform::multigrid_colour(i, j, k) == 0 && !m.held[e] ? deform::multigrid_smooth(Vec3f{0, 0, 0}, r)
                                                                   : Vec3f{0, 0, 0};
    }
    grid.sync();
  }
  // u = X
  for (int e = int(all.first); e < n; e += int(all.stride)) {
    u[0][e] = m.x[e].x;
    u[1][e] = m.x[e].y;
    u[2][e] = m.x[e].z;
  }
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

void launch_relax_multigrid(const StepGeometry& g, int src, int cycles, float threshold, float width,
                            const DeviceBuffers& b, const MultigridBuffers& m, int max_blocks, cudaStream_t stream) {
  if (cycles <= 0) return;
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
  a.b = b;
  a.m = m;
  const int blocks = int(std::min<long long>(max_blocks, (n + kPersistentThreads - 1) / kPersistentThreads));
  void* args[] = {&a};
  PALPSIM_CUDA_CHECK(cudaLaunchCooperativeKernel((const void*)relax_multigrid_kernel, dim3(std::max(blocks, 1)),
                                                 dim3(kPersistentThreads), args, 0, stream));
}

}  // namespace palpsim::cuda
