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

// the first element goes to x in both buffers; it moved in sweep 0 (one thread). `alone`:
// ChainMail is left out (ChainMailStats::skipped), so the run is over, converged
__device__ __forceinline__ void chainmail_start(const StepGeometry& geo, const Vec3f& u0, const DeviceBuffers& b,
                                                bool alone = false) {
  const deform::Voi& voi = geo.voi;
  const Vec3i g = geo.grabbed;
  const int g_idx = g.z * voi.size.x * voi.size.y + g.y * voi.size.x + g.x;
  Counters* c = b.counters;
  for (int p = 0; p < 2; ++p) {
    b.u[p][0][g_idx] = u0.x;
    b.u[p][1][g_idx] = u0.y;
    b.u[p][2][g_idx] = u0.z;
  }
  b.stamp[0][g_idx] = 0;
  c->sweep_moved[0] = c->sweep_moved[1] = c->sweep_moved[2] = 0;
  c->moved_total = 0;
  c->sweeps = 0;
  c->converged = alone ? 1 : 0;
}

// the wave moves one voxel per sweep: only the box g +- s can hold candidates; its
// corner and extent (VOI-local)
__device__ __forceinline__ void sweep_box(const StepGeometry& geo, int s, int lo[3], int ext[3]) {
  const Vec3i g = geo.grabbed;
#pragma unroll
  for (int a = 0; a < 3; ++a) {
    lo[a] = max(g[a] - s, 0);
    ext[a] = min(g[a] + s, geo.voi.size[a] - 1) - lo[a] + 1;
  }
}

// row r (j, k) of the sweep's box and the run [i0, i1] of it within s neighbour steps
// (L1) of the grabbed element, where sweep s can find an element to move (the wave moves
// one neighbour a sweep); false when the row holds none. A warp takes a row, its lanes
// the run: the box's corners cost a row's test, not an element's index arithmetic each
__device__ __forceinline__ bool sweep_row(const StepGeometry& geo, int s, const int lo[3], const int ext[3],
                                          unsigned r, int& j, int& k, int& i0, int& i1) {
  const unsigned ey = unsigned(ext[1]);
  const unsigned kk = r / ey;
  j = lo[1] + int(r - kk * ey);
  k = lo[2] + int(kk);
  const Vec3i g = geo.grabbed;
  const int rest = s - abs(j - g.y) - abs(k - g.z);
  if (rest < 0) return false;
  i0 = max(lo[0], g.x - rest);
  i1 = min(lo[0] + ext[0] - 1, g.x + rest);
  return i0 <= i1;
}

// sweep s of one element, VOI-local voxel (i, j, k) of one session: chainmail.cpp's
// rule; adds 1 to moved_here when it moved, and to fresh_here when for the first time
__device__ __forceinline__ void chainmail_element(const StepGeometry& geo, const DeviceBuffers& b,
                                                  const deform::ChainMailLimits& lim, int s, int i, int j, int k,
                                                  int& moved_here, int& fresh_here) {
  const deform::Voi& voi = geo.voi;
  const Vec3i g = geo.grabbed;
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;  // VOIs hold < 2^31 voxels (checked at bind)
  const int g_idx = g.z * sxy + g.y * sx + g.x;
  const int step[6] = {-1, 1, -sx, sx, -sxy, sxy};  // linear offsets in the fixed neighbour order
  const int pa = (s - 1) & 1, pb = s & 1;
  const float* ax = b.u[pa][0];
  const float* ay = b.u[pa][1];
  const float* az = b.u[pa][2];
  const int* sa = b.stamp[pa];
  int* sb = b.stamp[pb];
  const int e = k * sxy + j * sx + i;
  if (e == g_idx) return;
  // which neighbours moved in the previous sweep (stamps only: most elements stop here)
  const int n_ok[6] = {i > 0, i + 1 < voi.size.x, j > 0, j + 1 < voi.size.y, k > 0, k + 1 < voi.size.z};
  unsigned mask = 0;
#pragma unroll
  for (int q = 0; q < 6; ++q)
    if (n_ok[q] && (sa[e + step[q]] & ~kFirstMove) == s - 1) mask |= 1u << q;
  const bool self_prev = (sa[e] & ~kFirstMove) == s - 1;
  if (!mask && !self_prev) return;
  if (b.bone[geo.patient_index(i, j, k)]) return;
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
      deform::chainmail_clamp(v, Vec3f{ax[ni], ay[ni], az[ni]}, deform::neighbour_axis(q), deform::neighbour_below(q),
                              lim);
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

__global__ void __launch_bounds__(kPersistentThreads) chainmail_kernel(StepGeometry geo, Vec3f u0,
                                                                       deform::ChainMailLimits lim, int max_sweeps,
                                                                       DeviceBuffers b) {
  __shared__ int2 scratch[32];
  cg::grid_group grid = cg::this_grid();
  Counters* c = b.counters;
  if (grid.thread_rank() == 0) chainmail_start(geo, u0, b);
  grid.sync();

  const unsigned nwarps = gridDim.x * blockDim.x / 32, warp = (blockIdx.x * blockDim.x + threadIdx.x) / 32;
  const int lane = int(threadIdx.x & 31);
  for (int s = 1; s <= max_sweeps; ++s) {
    int lo[3], ext[3];
    sweep_box(geo, s, lo, ext);
    const unsigned rows = unsigned(ext[1]) * unsigned(ext[2]);
    int moved_here = 0, fresh_here = 0;
    // a warp a row of the box, its lanes along the row's run within reach
    for (unsigned r = warp; r < rows; r += nwarps) {
      int j, k, i0, i1;
      if (!sweep_row(geo, s, lo, ext, r, j, k, i0, i1)) continue;
      for (int i = i0 + lane; i <= i1; i += 32) chainmail_element(geo, b, lim, s, i, j, k, moved_here, fresh_here);
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

// ChainMail of several sessions in one cooperative grid (batch.cu says why): every
// sweep's boxes of the sessions still sweeping are laid end to end, row by row, and the
// grid's warps stride over all those rows, so the work spreads over the device whatever
// each box holds; each
// element runs chainmail_element as in the kernel above, and a session leaves the sweeps
// after its own quiet sweep, so its sweeps, counts and fields are those of its step
// alone. The grid leaves when every session has converged or at the sweep cap.
__global__ void __launch_bounds__(kPersistentThreads) chainmail_batch_kernel(const BatchItem* __restrict__ items, int n,
                                                                             deform::ChainMailLimits lim, int max_sweeps) {
  __shared__ unsigned box_end[kMaxBatch];     // sweeping sessions' boxes' rows end to end: where each ends
  __shared__ int which[kMaxBatch];            // the session of each of them
  __shared__ int active_n;                    // sessions still sweeping
  __shared__ unsigned char active[kMaxBatch]; // 1: the session still sweeps
  __shared__ int moved_s[kMaxBatch], fresh_s[kMaxBatch];  // this block's counts per session, this sweep
  cg::grid_group grid = cg::this_grid();
  for (int q = int(grid.thread_rank()); q < n; q += int(grid.size()))
    if (items[q].chainmail) chainmail_start(items[q].geo, items[q].u0, items[q].b, items[q].chainmail == 2);
  for (int q = threadIdx.x; q < n; q += blockDim.x) active[q] = items[q].chainmail == 1;
  grid.sync();

  const unsigned nwarps = gridDim.x * blockDim.x / 32, warp = (blockIdx.x * blockDim.x + threadIdx.x) / 32;
  const int lane = threadIdx.x & 31;
  for (int s = 1; s <= max_sweeps; ++s) {
    // the sweeping sessions' boxes end to end, in rows: a scan over the sessions in the first warp
    if (threadIdx.x < 32) {
      unsigned carry = 0;
      int m = 0;
      for (int base = 0; base < n; base += 32) {
        const int q = base + lane;
        const bool on = q < n && active[q];
        int lo[3], ext[3];
        unsigned box = 0u;
        if (on) {
          sweep_box(items[q].geo, s, lo, ext);
          box = unsigned(ext[1]) * unsigned(ext[2]);  // the box's rows
        }
        for (int o = 1; o < 32; o <<= 1) {
          const unsigned up = __shfl_up_sync(0xffffffffu, box, o);
          if (lane >= o) box += up;
        }
        const unsigned ballot = __ballot_sync(0xffffffffu, on);
        const int pos = m + __popc(ballot & ((1u << lane) - 1u));
        if (on) {
          box_end[pos] = carry + box;
          which[pos] = q;
        }
        carry += __shfl_sync(0xffffffffu, box, 31);
        m += __popc(ballot);
      }
      if (lane == 0) active_n = m;
    }
    for (int q = threadIdx.x; q < n; q += blockDim.x) moved_s[q] = fresh_s[q] = 0;
    __syncthreads();
    const int m_on = active_n;
    if (m_on == 0) return;  // no session sweeps at all (every grabbed element in bone)
    const unsigned total = box_end[m_on - 1];
    // a warp a row of the sessions' boxes laid end to end, its lanes along the row's run
    // within reach (sweep_row)
    for (unsigned t = warp; t < total; t += nwarps) {
      // the session whose box holds row t
      int a = 0, z = m_on - 1;
      while (a < z) {
        const int mid = (a + z) >> 1;
        if (t < box_end[mid]) z = mid; else a = mid + 1;
      }
      const int q = which[a];
      const StepGeometry& geo = items[q].geo;
      int lo[3], ext[3], j, k, i0, i1;
      sweep_box(geo, s, lo, ext);
      if (!sweep_row(geo, s, lo, ext, t - (a ? box_end[a - 1] : 0u), j, k, i0, i1)) continue;
      int moved_here = 0, fresh_here = 0;
      for (int i = i0 + lane; i <= i1; i += 32)
        chainmail_element(geo, items[q].b, lim, s, i, j, k, moved_here, fresh_here);
      if (moved_here) atomicAdd(&moved_s[q], moved_here);
      if (fresh_here) atomicAdd(&fresh_s[q], fresh_here);
    }
    __syncthreads();
    // one atomic per block and session for the sweep's counts
    for (int q = threadIdx.x; q < n; q += blockDim.x) {
      Counters* c = items[q].b.counters;
      if (moved_s[q]) atomicAdd(&c->sweep_moved[s % 3], moved_s[q]);
      if (fresh_s[q]) atomicAdd(&c->moved_total, (unsigned long long)fresh_s[q]);
      // slot (s+1) % 3 was last read before the previous barrier
      if (blockIdx.x == 0 && active[q]) c->sweep_moved[(s + 1) % 3] = 0;
    }
    grid.sync();
    // every block reads the same counts: a session whose sweep was quiet has converged
    for (int q = threadIdx.x; q < n; q += blockDim.x)
      if (active[q]) {
        Counters* c = items[q].b.counters;
        if (*(volatile int*)&c->sweep_moved[s % 3] == 0) {
          active[q] = 0;
          if (blockIdx.x == 0) {
            c->sweeps = s;
            c->converged = 1;
          }
        }
      }
    __syncthreads();
    // all leave together once none sweeps (the count is the same in every block)
    int left = 0;
    for (int q = 0; q < n; ++q) left += active[q];
    if (left == 0) return;
    __syncthreads();  // active[] is read above before the next sweep's scan
  }
  // the sweep cap: the sessions still sweeping did not converge
  for (int q = int(grid.thread_rank()); q < n; q += int(grid.size()))
    if (active[q]) items[q].b.counters->sweeps = max_sweeps;
}

// ChainMail's start alone (a step that skips ChainMail)
__global__ void chainmail_start_kernel(StepGeometry geo, Vec3f u0, DeviceBuffers b) { chainmail_start(geo, u0, b, true); }

}  // namespace

void launch_chainmail_start(const StepGeometry& g, const Vec3f& u0, const DeviceBuffers& b, cudaStream_t stream) {
  chainmail_start_kernel<<<1, 1, 0, stream>>>(g, u0, b);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
}

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

void launch_chainmail_batch(const BatchItem* items, int n, const deform::ChainMailLimits& limits, int max_sweeps,
                            const LaunchShape& shape, cudaStream_t stream) {
  if (n < 1 || n > kMaxBatch) throw Error("launch_chainmail_batch: " + std::to_string(n) + " sessions (1 to " +
                                          std::to_string(kMaxBatch) + ")");
  // the grid of the single kernel: one 1024-thread block per multiprocessor, the whole device
  const BatchItem* it = items;
  deform::ChainMailLimits lim = limits;
  void* args[] = {&it, &n, &lim, &max_sweeps};
  PALPSIM_CUDA_CHECK(cudaLaunchCooperativeKernel((const void*)chainmail_batch_kernel, dim3(shape.chainmail_blocks),
                                                 dim3(shape.threads), args, 0, stream));
}

LaunchShape persistent_launch_shape() {
  LaunchShape s;
  int dev = 0, sms = 0, coop = 0, per_sm_cm = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&coop, cudaDevAttrCooperativeLaunch, dev));
  if (!coop) throw Error("CUDA device " + std::to_string(dev) + " cannot launch cooperative kernels");
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm_cm, chainmail_kernel, s.threads, 0));
  int per_sm_batch = 0;  // the batched ChainMail runs on the same grid
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm_batch, chainmail_batch_kernel, s.threads, 0));
  per_sm_cm = std::min(per_sm_cm, per_sm_batch);
  // few, large blocks: a grid barrier costs about one atomic per block, and one
  // 1024-thread block per SM covers a 64^3 VOI in two passes
  s.chainmail_blocks = sms * std::min(per_sm_cm, kPersistentBlocksPerSm);
  s.relax_blocks = sms * std::min(relax_blocks_per_sm(s.threads), kPersistentBlocksPerSm);
  if (s.chainmail_blocks < 1 || s.relax_blocks < 1) throw Error("CUDA: the persistent deformation kernels do not fit on the device");
  return s;
}

}  // namespace palpsim::cuda
