// Untangling on the GPU: the same rounds and Jacobi sweeps as server/deform/untangle.cpp,
// in one persistent cooperative kernel (a grid-wide barrier between phases, as relax.cu).
// The sweeps visit only the box of the elements that can be active: the corners of the
// folded cells and the elements it has moved, grown by one (an element is active when it
// is such a corner or its neighbour towards the grabbed element has moved). Compiled
// without fused multiply-adds (cuda/CMakeLists.txt), so that each determinant and pull is
// the CPU's to the bit on the same input.
#include <cooperative_groups.h>

#include <algorithm>
#include <climits>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

// flag bits, as untangle.cpp: a corner of a folded cell in this round, moved in an earlier
// sweep; and one of this sweep: changes, its new value waiting in untangle_new
constexpr std::uint8_t kSeed = 1, kMoved = 2, kChanges = 4;

// a box of VOI-local elements (inclusive), read by every thread after a barrier
struct Box {
  int lo[3], hi[3];
};

__device__ Box read_box(const int* box, const deform::Voi& voi, int grow) {
  Box b;
  for (int a = 0; a < 3; ++a) {
    b.lo[a] = max(box[a] - grow, 0);
    b.hi[a] = min(box[3 + a] + grow, voi.size[a] - 1);
  }
  return b;
}

__device__ void grow_box(int* box, int i, int j, int k) {
  atomicMin(&box[0], i);
  atomicMin(&box[1], j);
  atomicMin(&box[2], k);
  atomicMax(&box[3], i);
  atomicMax(&box[4], j);
  atomicMax(&box[5], k);
}

// no flags yet, the box of possibly active elements empty, the counters zero; the
// other buffer (w) keeps the relaxed field, to return to if untangling ends with more folds
__device__ __forceinline__ void untangle_start(const DeviceBuffers& b, Counters* c, float* const (&u)[3],
                                               float* const (&w)[3], unsigned n, unsigned t0, unsigned nthreads) {
  for (unsigned e = t0; e < n; e += nthreads) {
    b.untangle_flags[e] = 0;
    for (int a = 0; a < 3; ++a) w[a][e] = u[a][e];
  }
  if (t0 == 0) {
    for (int a = 0; a < 3; ++a) {
      c->untangle_box[a] = INT_MAX;
      c->untangle_box[3 + a] = -1;
    }
    for (int& f : c->untangle_folded) f = 0;
    c->untangle_sweeps = c->untangle_rounds = c->untangle_reverted = 0;
    c->untangle_moved = 0;
  }
}

// the folded cells of this round: flag, count, and grow the box by their corners
template <typename LoadU, typename Soft>
__device__ __forceinline__ void flag_folded(const DeviceBuffers& b, Counters* c, const deform::Voi& voi, int round,
                                            LoadU load_u, Soft soft, unsigned n, unsigned t0, unsigned nthreads) {
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;
  for (unsigned e = t0; e < n; e += nthreads) {
    const int k = int(e) / sxy, r = int(e) - k * sxy, j = r / sx, i = r - j * sx;
    bool folded = false;
    if (i + 1 < voi.size.x && j + 1 < voi.size.y && k + 1 < voi.size.z && deform::untangle_cell_soft(soft, i, j, k))
      folded = deform::cell_min_det(load_u, i, j, k) <= deform::kUntangleFoldDet;
    b.cell_folded[e] = folded;
    if (folded) {
      atomicAdd(&c->untangle_folded[round], 1);
      grow_box(c->untangle_box, i, j, k);
      grow_box(c->untangle_box, i + 1, j + 1, k + 1);
    }
  }
}

// worse than relaxation alone: its field (w) back, over the box that holds what moved
__device__ __forceinline__ void revert_to_relaxed(Counters* c, const deform::Voi& voi, float* const (&u)[3],
                                                  float* const (&w)[3], unsigned t0, unsigned nthreads) {
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;
  const Box box = read_box(c->untangle_box, voi, 0);
  const int bx = box.hi[0] - box.lo[0] + 1, bxy = bx * (box.hi[1] - box.lo[1] + 1);
  const unsigned nb = unsigned(bxy * (box.hi[2] - box.lo[2] + 1));
  for (unsigned t = t0; t < nb; t += nthreads) {
    const int kk = int(t) / bxy, r = int(t) - kk * bxy, jj = r / bx;
    const int e = (box.lo[2] + kk) * sxy + (box.lo[1] + jj) * sx + box.lo[0] + r - jj * bx;
    for (int a = 0; a < 3; ++a) u[a][e] = w[a][e];
  }
  if (t0 == 0) c->untangle_reverted = 1;
}

// this round's seeds, over the box (it holds every earlier seed, to be cleared); the
// sweep counters start at zero (last read before the barrier that ended the last round)
__device__ __forceinline__ void seed_round(const DeviceBuffers& b, Counters* c, const deform::Voi& voi, unsigned t0,
                                           unsigned nthreads) {
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;
  if (t0 == 0) c->untangle_changed[0] = c->untangle_changed[1] = c->untangle_changed[2] = 0;
  const Box box = read_box(c->untangle_box, voi, 0);
  const int bx = box.hi[0] - box.lo[0] + 1, bxy = bx * (box.hi[1] - box.lo[1] + 1);
  const unsigned nb = unsigned(bxy * (box.hi[2] - box.lo[2] + 1));
  for (unsigned t = t0; t < nb; t += nthreads) {
    const int kk = int(t) / bxy, r = int(t) - kk * bxy, jj = r / bx;
    const int i = box.lo[0] + r - jj * bx, j = box.lo[1] + jj, k = box.lo[2] + kk;
    const bool seed = deform::untangle_is_seed(
        [&](int a, int bb, int d) { return b.cell_folded[d * sxy + bb * sx + a] != 0; }, voi, i, j, k);
    std::uint8_t& f = b.untangle_flags[k * sxy + j * sx + i];
    f = std::uint8_t((f & kMoved) | (seed ? kSeed : 0));
  }
}

// a Jacobi sweep's compute over `box`: the active elements' pulls into untangle_new,
// flagged kChanges where they change
template <typename Soft>
__device__ __forceinline__ void jacobi_compute(const DeviceBuffers& b, const deform::Voi& voi, const Vec3i g,
                                               float* const (&u)[3], Soft soft, const Box& box, unsigned t0,
                                               unsigned nthreads) {
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;
  const int cx = box.hi[0] - box.lo[0] + 1, cxy = cx * (box.hi[1] - box.lo[1] + 1);
  const unsigned nb = unsigned(cxy * (box.hi[2] - box.lo[2] + 1));
  for (unsigned t = t0; t < nb; t += nthreads) {
    const int kk = int(t) / cxy, r = int(t) - kk * cxy, jj = r / cx;
    const Vec3i e{box.lo[0] + r - jj * cx, box.lo[1] + jj, box.lo[2] + kk};
    if (e == g || !soft(e.x, e.y, e.z)) continue;
    const int ei = e.z * sxy + e.y * sx + e.x;
    bool active = (b.untangle_flags[ei] & kSeed) != 0;
    const Vec3f old{u[0][ei], u[1][ei], u[2][ei]};
    Vec3f v = old;
    for (int a = 0; a < 3; ++a) {
      if (e[a] == g[a]) continue;
      Vec3i nbr = e;
      nbr[a] += e[a] > g[a] ? -1 : 1;  // the neighbour towards the grabbed element
      if (!soft(nbr.x, nbr.y, nbr.z)) continue;
      const int ni = nbr.z * sxy + nbr.y * sx + nbr.x;
      active = active || (b.untangle_flags[ni] & kMoved) != 0;
      deform::untangle_pull(v, Vec3f{u[0][ni], u[1][ni], u[2][ni]}, a, e[a] > g[a]);
    }
    if (active && v != old) {
      b.untangle_new[0][ei] = v.x;
      b.untangle_new[1][ei] = v.y;
      b.untangle_new[2][ei] = v.z;
      b.untangle_flags[ei] |= kChanges;
    }
  }
}

// a Jacobi sweep's apply over the same box (read before anyone grows it): the changes
// into u, counted and grown into the box; returns this thread's count
__device__ __forceinline__ int jacobi_apply(const DeviceBuffers& b, Counters* c, const deform::Voi& voi,
                                            float* const (&u)[3], const Box& box, unsigned t0, unsigned nthreads) {
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;
  const int cx = box.hi[0] - box.lo[0] + 1, cxy = cx * (box.hi[1] - box.lo[1] + 1);
  const unsigned nb = unsigned(cxy * (box.hi[2] - box.lo[2] + 1));
  int changed = 0;
  for (unsigned t = t0; t < nb; t += nthreads) {
    const int kk = int(t) / cxy, r = int(t) - kk * cxy, jj = r / cx;
    const int i = box.lo[0] + r - jj * cx, j = box.lo[1] + jj, k = box.lo[2] + kk;
    const int ei = k * sxy + j * sx + i;
    std::uint8_t f = b.untangle_flags[ei];
    if (!(f & kChanges)) continue;
    u[0][ei] = b.untangle_new[0][ei];
    u[1][ei] = b.untangle_new[1][ei];
    u[2][ei] = b.untangle_new[2][ei];
    if (!(f & kMoved)) atomicAdd(&c->untangle_moved, 1ull);
    b.untangle_flags[ei] = std::uint8_t((f | kMoved) & ~kChanges);
    grow_box(c->untangle_box, i, j, k);
    ++changed;
  }
  return changed;
}

__global__ void __launch_bounds__(kPersistentThreads) untangle_kernel(StepGeometry geo, int cur, DeviceBuffers b) {
  cg::grid_group grid = cg::this_grid();
  const deform::Voi& voi = geo.voi;
  const Vec3i g = geo.grabbed;
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;
  const unsigned n = unsigned(voi.count());
  const unsigned t0 = blockIdx.x * blockDim.x + threadIdx.x, nthreads = gridDim.x * blockDim.x;
  Counters* c = b.counters;
  float* u[3] = {b.u[cur][0], b.u[cur][1], b.u[cur][2]};
  float* w[3] = {b.u[cur ^ 1][0], b.u[cur ^ 1][1], b.u[cur ^ 1][2]};
  auto load_u = [&](int i, int j, int k) {
    if (!voi.contains(i, j, k)) return Vec3f{0, 0, 0};
    const int e = k * sxy + j * sx + i;
    return Vec3f{u[0][e], u[1][e], u[2][e]};
  };
  auto soft = [&](int i, int j, int k) {
    return b.bone[geo.patient_index(i, j, k)] == 0;
  };
  untangle_start(b, c, u, w, n, t0, nthreads);
  grid.sync();
  for (int round = 0;; ++round) {
    flag_folded(b, c, voi, round, load_u, soft, n, t0, nthreads);
    grid.sync();
    const int folded = c->untangle_folded[round];
    if (folded > c->untangle_folded[0] && round == deform::kUntangleMaxRounds)
      revert_to_relaxed(c, voi, u, w, t0, nthreads);
    if (folded == 0 || round == deform::kUntangleMaxRounds) {
      if (t0 == 0) c->untangle_rounds = round;
      return;
    }
    seed_round(b, c, voi, t0, nthreads);
    // Jacobi sweeps until a quiet one: compute into the other buffer, barrier, apply
    for (int sweep = 0; sweep < deform::kUntangleMaxSweeps; ++sweep) {
      grid.sync();
      const int slot = sweep % 3;
      if (t0 == 0) c->untangle_changed[(sweep + 1) % 3] = 0;  // last read two sweeps ago
      const Box box = read_box(c->untangle_box, voi, 1);
      jacobi_compute(b, voi, g, u, soft, box, t0, nthreads);
      grid.sync();
      const int changed = jacobi_apply(b, c, voi, u, box, t0, nthreads);
      if (changed) atomicAdd(&c->untangle_changed[slot], changed);
      if (t0 == 0) atomicAdd(&c->untangle_sweeps, 1);
      grid.sync();
      if (c->untangle_changed[slot] == 0) break;
    }
    grid.sync();
  }
}

}  // namespace

void launch_untangle(const StepGeometry& g, int cur, const DeviceBuffers& b, const LaunchShape& shape,
                     cudaStream_t stream) {
  // blocks that fit at once (a cooperative launch needs them all resident), once per process
  static const int per_sm = [] {
    int v = 0;
    PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&v, untangle_kernel, kPersistentThreads, 0));
    return v;
  }();
  if (per_sm < 1) throw Error("CUDA: the untangling kernel does not fit on the device");
  const long long n = g.voi.count();
  const int blocks =
      int(std::min<long long>({(long long)shape.relax_blocks, (n + shape.threads - 1) / shape.threads}));
  StepGeometry geo = g;
  DeviceBuffers buf = b;
  void* args[] = {&geo, &cur, &buf};
  PALPSIM_CUDA_CHECK(
      cudaLaunchCooperativeKernel((const void*)untangle_kernel, dim3(blocks), dim3(shape.threads), args, 0, stream));
}

}  // namespace palpsim::cuda
