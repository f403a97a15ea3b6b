// ChainMail on the GPU: the same Jacobi sweeps as server/deform/chainmail.cpp, all
// of them in one persistent cooperative kernel.
//
// Why a persistent kernel: a step needs up to 2d sweeps (60 at d = 30) and each
// sweep is little work (the box the wave can have reached, mostly idle elements),
// so synchronisation decides the time. DEVICE.md's floors: a host launch costs
// 3.3-3.5 us and a launch + sync round trip 8.5 us, so one launch per sweep with a
// host convergence check would cost ~0.5 ms at d = 30 before any work; a CUDA graph
// of sweeps (about 1 us a node) cannot stop at the first quiet sweep without a host
// round trip every few sweeps. One cooperative launch keeps everything on the GPU:
// a grid-wide barrier per sweep (~1-2 us), and every thread reads the sweep's moved
// count after the barrier and leaves together when it is zero.
#include <cooperative_groups.h>

#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

// sums a and b over the block; the results are valid in thread 0
__device__ int2 block_sum2(int a, int b, int2* scratch) {
  for (int o = 16; o > 0; o >>= 1) {
    a += __shfl_down_sync(0xffffffffu, a, o);
    b += __shfl_down_sync(0xffffffffu, b, o);
  }
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  __syncthreads();  // the previous sweep's readers are done with scratch
  if (lane == 0) scratch[warp] = make_int2(a, b);
  __syncthreads();
  int2 s = make_int2(0, 0);
  if (threadIdx.x == 0)
    for (int w = 0; w < int(blockDim.x >> 5); ++w) {
      s.x += scratch[w].x;
      s.y += scratch[w].y;
    }
  return s;
}

// a stamp with this bit set records an element's first move (stamps stay below it)
constexpr int kFirstMove = 1 << 30;

__global__ void __launch_bounds__(kPersistentThreads) chainmail_kernel(StepGeometry geo, Vec3f u0,
                                                                       deform::ChainMailLimits lim, int max_sweeps,
                                                                       DeviceBuffers b) {
  __shared__ int2 scratch[32];
  cg::grid_group grid = cg::this_grid();
  const deform::Voi& voi = geo.voi;
  const Vec3i g = geo.grabbed;
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;  // VOIs hold < 2^31 voxels (checked at bind)
  const int g_idx = g.z * sxy + g.y * sx + g.x;
  Counters* c = b.counters;
  // the first element goes to x in both buffers; it moved in sweep 0
  if (grid.thread_rank() == 0) {
    for (int p = 0; p < 2; ++p) {
      b.u[p][0][g_idx] = u0.x;
      b.u[p][1][g_idx] = u0.y;
      b.u[p][2][g_idx] = u0.z;
    }
    b.stamp[0][g_idx] = 0;
    c->sweep_moved[0] = c->sweep_moved[1] = c->sweep_moved[2] = 0;
    c->moved_total = 0;
    c->sweeps = 0;
    c->converged = 0;
  }
  grid.sync();

  const unsigned nthreads = gridDim.x * blockDim.x;
  const int step[6] = {-1, 1, -sx, sx, -sxy, sxy};  // linear offsets in the fixed neighbour order
  for (int s = 1; s <= max_sweeps; ++s) {
    const int pa = (s - 1) & 1, pb = s & 1;
    const float* ax = b.u[pa][0];
    const float* ay = b.u[pa][1];
    const float* az = b.u[pa][2];
    const int* sa = b.stamp[pa];
    int* sb = b.stamp[pb];
    // the wave moves one voxel per sweep: only the box g +- s can hold candidates
    int lo[3], ext[3];
#pragma unroll
    for (int a = 0; a < 3; ++a) {
      lo[a] = max(g[a] - s, 0);
      ext[a] = min(g[a] + s, voi.size[a] - 1) - lo[a] + 1;
    }
    const unsigned ex = unsigned(ext[0]), exy = unsigned(ext[0] * ext[1]), box = exy * unsigned(ext[2]);
    int moved_here = 0, fresh_here = 0;
    for (unsigned t = blockIdx.x * blockDim.x + threadIdx.x; t < box; t += nthreads) {
      // 32-bit index arithmetic: 64-bit division costs tens of instructions on the GPU
      const unsigned kk = t / exy, r = t - kk * exy, jj = r / ex;
      const int i = lo[0] + int(r - jj * ex), j = lo[1] + int(jj), k = lo[2] + int(kk);
      const int e = k * sxy + j * sx + i;
      if (e == g_idx) continue;
      // which neighbours moved in the previous sweep (stamps only: most elements stop here)
      const int n_ok[6] = {i > 0, i + 1 < voi.size.x, j > 0, j + 1 < voi.size.y, k > 0, k + 1 < voi.size.z};
      unsigned mask = 0;
#pragma unroll
      for (int q = 0; q < 6; ++q)
        if (n_ok[q] && (sa[e + step[q]] & ~kFirstMove) == s - 1) mask |= 1u << q;
      const bool self_prev = (sa[e] & ~kFirstMove) == s - 1;
      if (!mask && !self_prev) continue;
      const long long gi = ((long long)(voi.lo.z + k) * geo.volume_size.y + (voi.lo.y + j)) * geo.volume_size.x +
                           (voi.lo.x + i);
      if (b.bone[gi]) continue;
      // clamp into the box of every neighbour that moved in an earlier sweep, in the fixed
      // order (chainmail.cpp). sb is being written in this sweep: a neighbour reads as
      // having moved before when its stamp of this parity is an earlier sweep, or this
      // one without kFirstMove (it had moved before), whichever value the race shows
      const Vec3f old{ax[e], ay[e], az[e]};
      Vec3f v = old;
      unsigned held = 0;
#pragma unroll
      for (int q = 0; q < 6; ++q)
        if (n_ok[q] && (sa[e + step[q]] >= 0 || (sb[e + step[q]] >= 0 && sb[e + step[q]] != (s | kFirstMove))))
          held |= 1u << q;
#pragma unroll
      for (int q = 0; q < 6; ++q)
        if (held & (1u << q)) {
          const int ni = e + step[q];
          deform::chainmail_clamp(v, Vec3f{ax[ni], ay[ni], az[ni]}, deform::neighbour_axis(q),
                                  deform::neighbour_below(q), lim);
        }
      // buffer pb holds sweep s-2: rewrite it where this sweep or the last one changed anything
      b.u[pb][0][e] = v.x;
      b.u[pb][1][e] = v.y;
      b.u[pb][2][e] = v.z;
      if (mask && v != old) {
        ++moved_here;
        const bool first = sa[e] < 0 && sb[e] < 0;
        fresh_here += first;
        sb[e] = first ? (s | kFirstMove) : s;
      }
    }
    // one atomic per block for the sweep's counts
    const int2 sums = block_sum2(moved_here, fresh_here, scratch);
    const int m = sums.x, f = sums.y;
    if (threadIdx.x == 0 && m) atomicAdd(&c->sweep_moved[s % 3], m);
    if (threadIdx.x == 0 && f) atomicAdd(&c->moved_total, (unsigned long long)f);
    // slot (s+1) % 3 was last read before the previous barrier
    if (grid.thread_rank() == 0) c->sweep_moved[(s + 1) % 3] = 0;
    grid.sync();
    // everyone reads the same count and leaves together after a quiet sweep
    if (*(volatile int*)&c->sweep_moved[s % 3] == 0) {
      if (grid.thread_rank() == 0) {
        c->sweeps = s;
        c->converged = 1;
      }
      return;
    }
  }
  if (grid.thread_rank() == 0) c->sweeps = max_sweeps;
}

}  // namespace

void launch_chainmail(const StepGeometry& g, const Vec3f& u0, const deform::ChainMailLimits& limits,
                      int max_sweeps, const DeviceBuffers& b, const LaunchShape& shape, cudaStream_t stream) {
  // no more blocks than the largest box needs
  const long long max_box = g.voi.count();
  const int blocks = int(std::min<long long>(shape.chainmail_blocks, (max_box + shape.threads - 1) / shape.threads));
  StepGeometry geo = g;
  Vec3f u = u0;
  deform::ChainMailLimits lim = limits;
  DeviceBuffers buf = b;
  void* args[] = {&geo, &u, &lim, &max_sweeps, &buf};
  PALPSIM_CUDA_CHECK(cudaLaunchCooperativeKernel((const void*)chainmail_kernel, dim3(blocks), dim3(shape.threads),
                                                 args, 0, stream));
}

LaunchShape persistent_launch_shape() {
  LaunchShape s;
  int dev = 0, sms = 0, coop = 0, per_sm_cm = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&coop, cudaDevAttrCooperativeLaunch, dev));
  if (!coop) throw Error("CUDA device " + std::to_string(dev) + " cannot launch cooperative kernels");
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm_cm, chainmail_kernel, s.threads, 0));
  // few, large blocks: a grid barrier costs about one atomic per block, and one
  // 1024-thread block per SM covers a 64^3 VOI in two passes
  s.chainmail_blocks = sms * std::min(per_sm_cm, kPersistentBlocksPerSm);
  s.relax_blocks = sms * std::min(relax_blocks_per_sm(s.threads), kPersistentBlocksPerSm);
  if (s.chainmail_blocks < 1 || s.relax_blocks < 1) throw Error("CUDA: the persistent deformation kernels do not fit on the device");
  return s;
}

}  // namespace palpsim::cuda
