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

// sums v over the block; the result is valid in thread 0
__device__ int block_sum(int v, int* scratch) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(0xffffffffu, v, o);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  __syncthreads();
  if (lane == 0) scratch[warp] = v;
  __syncthreads();
  int s = 0;
  if (threadIdx.x == 0)
    for (int w = 0; w < int(blockDim.x >> 5); ++w) s += scratch[w];
  return s;
}

__global__ void __launch_bounds__(256) chainmail_kernel(StepGeometry geo, Vec3f u0, deform::ChainMailLimits lim,
                                                        int max_sweeps, DeviceBuffers b) {
  __shared__ int scratch[32];
  cg::grid_group grid = cg::this_grid();
  const deform::Voi& voi = geo.voi;
  const Vec3i g = geo.grabbed;
  const long long g_idx = voi.index(g.x, g.y, g.z);
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

  const long long nthreads = (long long)gridDim.x * blockDim.x;
  for (int s = 1; s <= max_sweeps; ++s) {
    const int pa = (s - 1) & 1, pb = s & 1;
    const float* ax = b.u[pa][0];
    const float* ay = b.u[pa][1];
    const float* az = b.u[pa][2];
    const int* sa = b.stamp[pa];
    int* sb = b.stamp[pb];
    // the wave moves one voxel per sweep: only the box g +- s can hold candidates
    int lo[3], ext[3];
    for (int a = 0; a < 3; ++a) {
      lo[a] = max(g[a] - s, 0);
      ext[a] = min(g[a] + s, voi.size[a] - 1) - lo[a] + 1;
    }
    const long long box = (long long)ext[0] * ext[1] * ext[2];
    int moved_here = 0, fresh_here = 0;
    for (long long t = (long long)blockIdx.x * blockDim.x + threadIdx.x; t < box; t += nthreads) {
      const int i = lo[0] + int(t % ext[0]);
      const int j = lo[1] + int((t / ext[0]) % ext[1]);
      const int k = lo[2] + int(t / ((long long)ext[0] * ext[1]));
      const long long e = voi.index(i, j, k);
      if (e == g_idx) continue;
      const long long gi = ((long long)(voi.lo.z + k) * geo.volume_size.y + (voi.lo.y + j)) * geo.volume_size.x +
                           (voi.lo.x + i);
      if (b.bone[gi]) continue;
      // clamp into the box of every neighbour that moved in the previous sweep, in the fixed order
      const Vec3f old{ax[e], ay[e], az[e]};
      Vec3f v = old;
      bool any = false;
      for (int q = 0; q < 6; ++q) {
        const Vec3i n = Vec3i{i, j, k} + deform::neighbour_offset(q);
        if (!voi.contains(n.x, n.y, n.z)) continue;
        const long long ni = voi.index(n.x, n.y, n.z);
        if (sa[ni] != s - 1) continue;
        any = true;
        deform::chainmail_clamp(v, Vec3f{ax[ni], ay[ni], az[ni]}, deform::neighbour_axis(q),
                                deform::neighbour_below(q), lim);
      }
      // buffer pb holds sweep s-2: rewrite it where this sweep or the last one changed anything
      if (any || sa[e] == s - 1) {
        b.u[pb][0][e] = v.x;
        b.u[pb][1][e] = v.y;
        b.u[pb][2][e] = v.z;
      }
      if (any && v != old) {
        ++moved_here;
        if (sa[e] < 0 && sb[e] < 0) ++fresh_here;
        sb[e] = s;
      }
    }
    // one atomic per block for the sweep's counts
    const int m = block_sum(moved_here, scratch);
    const int f = block_sum(fresh_here, scratch);
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
  s.chainmail_blocks = sms * per_sm_cm;
  s.relax_blocks = relax_blocks_per_sm(s.threads) * sms;
  return s;
}

}  // namespace palpsim::cuda
