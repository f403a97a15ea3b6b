// Relaxation on the GPU: the same explicit diffusion as server/deform/relax.cpp.
// All iterations run in one persistent cooperative kernel with a grid-wide barrier
// between them: 20 iterations as 20 host launches cost 20 x 3.3 us (DEVICE.md) at
// VOI 64, where the work of one iteration is a few microseconds; the barrier costs
// about as much as a CUDA graph node (~1 us) and needs no graph per VOI size.
//
// One kernel serves a session alone and a batch of sessions (batch.cu), so a batched
// session's field equals its own step's to the bit. Its shape (issue 10: a batch of 16
// sessions spent 0.073 ms a step here, the largest stage):
// - The weight (relax_step times the material function, 0 at the grabbed element) is
//   computed from I and the bone mask once per step, in the first iteration, and kept
//   in a VOI buffer (DeviceBuffers::relax_w) for the other 19: before, every iteration
//   read I and the mask at 64-bit patient indices and evaluated tanhf and a division.
// - A thread walks up one column (i, j) of the VOI over a run of planes, keeping the
//   planes below and above in registers: each displacement is read from memory about once
//   an iteration instead of three times (itself and as the neighbour above and below,
//   which another block had read); a block is 64 x 16 columns, so the neighbours in the
//   plane come through its L1 cache, and (i, j, k) come from the thread and its unit, not
//   from three integer divisions of a linear index (tens of instructions each).
// - Sessions are relaxed a group at a time, all 20 iterations of a group before the next
//   group, the group as large as keeps its fields (both displacement buffers and the
//   weights, 28 bytes an element) within a share of the L2 cache: a batch of 16 VOIs of
//   64^3 holds 116 MB, which every iteration would otherwise stream from device memory.
// The rows of a plane per unit instead of columns, and all sessions at once instead of L2
// groups, were both measured slower (bench/results/server-2026-11-23-h100-*.json).
#include <cooperative_groups.h>

#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

// a block's threads: 64 along i (two warps a row, coalesced) by 16 rows along j; a block
// updates a tile of 64 x 16 columns over a run of planes
constexpr int kRelaxTx = 64;
constexpr int kRelaxTy = kPersistentThreads / kRelaxTx;
static_assert(kRelaxTx * kRelaxTy == kPersistentThreads, "a relaxation block is 64 x 16 threads");

// the share of the L2 cache a group of sessions' fields may fill; 0: all sessions at once.
// A build may set it (-DPALPSIM_RELAX_L2_SHARE=...) to compare; bench/results has the
// figures of each
#ifndef PALPSIM_RELAX_L2_SHARE
#define PALPSIM_RELAX_L2_SHARE 0.6
#endif

__device__ __forceinline__ Vec3f load3(const float* x, const float* y, const float* z, int e) {
  return Vec3f{x[e], y[e], z[e]};
}

// iteration `it` of one session on column (i, j) of its VOI, planes k0 .. k1 - 1, from
// buffer pa into the other. The thread walks up the column keeping the planes below and
// above in registers, so each displacement is read from memory once (plus a plane at
// either end of the run) instead of three times; the four neighbours in the plane come
// from the block's neighbouring threads through the L1 cache. The weight (0 at the grabbed
// element, which keeps its displacement) is computed from I and the bone mask in the first
// iteration and kept in b.relax_w; each element sums its neighbours in the fixed order
// -i, +i, -j, +j, -k, +k and updates by deform::relax_update, as server/deform/relax.cpp
__device__ __forceinline__ void relax_column(const BatchItem& item, int it, int i, int j, int k0, int k1, float step,
                                             float threshold, float width) {
  const StepGeometry& geo = item.geo;
  const Vec3i size = geo.voi.size;
  const DeviceBuffers& b = item.b;
  const int pa = (item.relax_src + it) & 1, pb = pa ^ 1;
  const float* ax = b.u[pa][0];
  const float* ay = b.u[pa][1];
  const float* az = b.u[pa][2];
  const int sx = size.x, sxy = size.x * size.y;  // VOIs hold < 2^31 voxels (checked at bind)
  const int g_idx = (geo.grabbed.z * size.y + geo.grabbed.y) * size.x + geo.grabbed.x;
  const long long vxy = (long long)geo.volume_size.x * geo.volume_size.y;
  // the column's element at plane k0, in the VOI and in the patient volume
  int e = (k0 * size.y + j) * sx + i;
  long long gi = (geo.voi.lo.z + k0) * vxy + (long long)(geo.voi.lo.y + j) * geo.volume_size.x + geo.voi.lo.x + i;
  Vec3f below{0, 0, 0};
  if (k0 > 0) below = load3(ax, ay, az, e - sxy);
  Vec3f cur = load3(ax, ay, az, e);
  for (int k = k0; k < k1; ++k, e += sxy, gi += vxy) {
    Vec3f above{0, 0, 0};
    if (k + 1 < size.z) above = load3(ax, ay, az, e + sxy);
    float w;
    if (it == 0) {
      w = e == g_idx ? 0.0f : step * deform::material_weight(b.intensity[gi], b.bone[gi] != 0, threshold, width);
      b.relax_w[e] = w;
    } else {
      w = b.relax_w[e];
    }
    Vec3f out = cur;
    if (w != 0.0f) {
      // the six neighbours in the fixed order, zero outside the VOI
      Vec3f sum6{0, 0, 0};
      if (i > 0) sum6 += load3(ax, ay, az, e - 1);
      if (i + 1 < sx) sum6 += load3(ax, ay, az, e + 1);
      if (j > 0) sum6 += load3(ax, ay, az, e - sx);
      if (j + 1 < size.y) sum6 += load3(ax, ay, az, e + sx);
      if (k > 0) sum6 += below;
      if (k + 1 < size.z) sum6 += above;
      out = deform::relax_update(cur, sum6, w);
    }
    b.u[pb][0][e] = out.x;
    b.u[pb][1][e] = out.y;
    b.u[pb][2][e] = out.z;
    below = cur;
    cur = above;
  }
}

// the shape of a launch's work: a session's units are tiles_x x tiles_y tiles of 64 x 16
// columns times chunks runs of `planes` planes, as if its VOI were the largest
struct RelaxUnits {
  int tiles_x = 1, tiles_y = 1, chunks = 1, planes = 1;
};

// `iterations` relaxation steps of n sessions, `group` at a time (each group all its
// iterations before the next), each iteration a grid-stride loop over the group's units
// and a grid barrier. kBatch: the sessions are items[0 .. n-1]; otherwise the one in `one`
template <bool kBatch>
__global__ void __launch_bounds__(kPersistentThreads)
    relax_kernel(const BatchItem* __restrict__ items, BatchItem one, int n, int group, RelaxUnits shape,
                 int iterations, float step, float threshold, float width) {
  cg::grid_group grid = cg::this_grid();
  const unsigned tiles = unsigned(shape.tiles_x) * unsigned(shape.tiles_y);
  const unsigned per_session = tiles * unsigned(shape.chunks);
  const int tx = int(threadIdx.x) % kRelaxTx, ty = int(threadIdx.x) / kRelaxTx;
  // how far each session's field reaches (ChainMail's sweeps, in its counters, plus the
  // steps since; -1: unknown), read once per block into shared memory rather than through
  // item -> counters -> sweeps in every unit
  __shared__ int reach_base[kMaxBatch];
  for (int q = int(threadIdx.x); q < n; q += int(blockDim.x)) {
    const BatchItem& item = kBatch ? items[q] : one;
    reach_base[q] = item.relax_extra < 0 ? -1 : item.b.counters->sweeps + item.relax_extra;
  }
  __syncthreads();
  for (int g0 = 0; g0 < n; g0 += group) {
    const int gn = min(group, n - g0);
    const unsigned units = unsigned(gn) * per_session;
    for (int it = 0; it < iterations; ++it) {
      for (unsigned t = blockIdx.x; t < units; t += gridDim.x) {
        const unsigned q = t / per_session, r = t - q * per_session;
        const unsigned c = r / tiles, tile = r - c * tiles;
        const unsigned ty0 = tile / unsigned(shape.tiles_x), tx0 = tile - ty0 * unsigned(shape.tiles_x);
        const BatchItem& item = kBatch ? items[g0 + int(q)] : one;
        const Vec3i size = item.geo.voi.size;
        const int i = int(tx0) * kRelaxTx + tx, j = int(ty0) * kRelaxTy + ty;
        int k0 = int(c) * shape.planes, k1 = min(k0 + shape.planes, size.z);
        // only the planes within reach (L1, deform::relax_reach) of the grabbed element from
        // the tile's nearest column: the rest is 0 in both buffers and stays so; the same
        // planes for the whole block, so a warp's loads stay in one plane (ranges per column
        // were measured slower)
        const Vec3i g = item.geo.grabbed;
        const int ti0 = int(tx0) * kRelaxTx, tj0 = int(ty0) * kRelaxTy;
        const int near = max(max(ti0 - g.x, g.x - (ti0 + kRelaxTx - 1)), 0) +
                         max(max(tj0 - g.y, g.y - (tj0 + kRelaxTy - 1)), 0);
        const int rest = deform::relax_reach(reach_base[g0 + int(q)], it, iterations) - near;
        if (rest < 0) continue;  // the whole tile (the same for every thread of the block)
        k0 = max(k0, g.z - rest);
        k1 = min(k1, g.z + rest + 1);
        // beyond a smaller (clipped) VOI than the batch's largest: nothing
        if (i < size.x && j < size.y && k0 < k1) relax_column(item, it, i, j, k0, k1, step, threshold, width);
      }
      // the last iteration of the last group needs none: the kernel's end is one
      if (it + 1 < iterations || g0 + group < n) grid.sync();
    }
  }
}

// sessions relaxed together (relax_kernel's group): as many of the largest VOI's fields
// as fill PALPSIM_RELAX_L2_SHARE of the L2 cache, at least 1, spread evenly over groups
int relax_group(int n, unsigned long long max_count) {
  const double share = PALPSIM_RELAX_L2_SHARE;
  if (share <= 0) return n;
  int dev = 0, l2 = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&l2, cudaDevAttrL2CacheSize, dev));
  // both displacement buffers and the weights: 7 floats an element
  const double per_session = double(max_count) * 7 * sizeof(float);
  const int fit = std::max(1, int(share * l2 / std::max(1.0, per_session)));
  const int groups = (n + fit - 1) / fit;
  return (n + groups - 1) / groups;
}

void launch(const BatchItem* items, const BatchItem& one, int n, const Vec3i& most, int iterations, float step,
            float threshold, float width, int max_blocks, cudaStream_t stream) {
  const unsigned long long count = (unsigned long long)most.x * most.y * most.z;
  int group = items ? relax_group(n, count) : 1;
  RelaxUnits shape;
  shape.tiles_x = (most.x + kRelaxTx - 1) / kRelaxTx;
  shape.tiles_y = (most.y + kRelaxTy - 1) / kRelaxTy;
  // the longest runs of planes that still give every block a unit (each run's ends read
  // a plane more), at least three quarters of the blocks busy: a 64^3 VOI alone in runs of
  // 2 planes (128 units), 16 of them together in runs of 32
  const unsigned long long tiles = (unsigned long long)group * shape.tiles_x * shape.tiles_y;
  shape.planes = std::max(1, most.z);
  while (shape.planes > 1 && 4 * tiles * ((most.z + shape.planes - 1) / shape.planes) < 3ULL * max_blocks)
    shape.planes = (shape.planes + 1) / 2;
  shape.chunks = (most.z + shape.planes - 1) / shape.planes;
  const unsigned long long units = tiles * shape.chunks;
  // the units of a group must be indexable with 32 bits
  if (units >= (1ULL << 32))
    throw Error("launch_relax: " + std::to_string(group) + " VOIs of " + std::to_string(count) +
                " elements exceed 32-bit unit indices");
  const int blocks = int(std::min<unsigned long long>(max_blocks, units));
  const BatchItem* it = items;
  BatchItem single = one;
  void* args[] = {&it, &single, &n, &group, &shape, &iterations, &step, &threshold, &width};
  const void* kernel = items ? (const void*)relax_kernel<true> : (const void*)relax_kernel<false>;
  PALPSIM_CUDA_CHECK(cudaLaunchCooperativeKernel(kernel, dim3(blocks), dim3(kPersistentThreads), args, 0, stream));
}

}  // namespace

int relax_blocks_per_sm(int threads) {
  int per_sm = 0, per_sm_batch = 0;  // the batched relaxation runs on the same grid
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, relax_kernel<false>, threads, 0));
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm_batch, relax_kernel<true>, threads, 0));
  return std::min(per_sm, per_sm_batch);
}

void launch_relax(const StepGeometry& g, int src, int extra, int iterations, float step, float threshold, float width,
                  const DeviceBuffers& b, const LaunchShape& shape, cudaStream_t stream) {
  if (iterations <= 0) return;
  if (shape.threads != kPersistentThreads)
    throw Error("launch_relax: the relaxation kernel runs " + std::to_string(kPersistentThreads) +
                " threads a block, not " + std::to_string(shape.threads));
  BatchItem one;
  one.geo = g;
  one.relax_src = src;
  one.relax_extra = extra;
  one.b = b;
  launch(nullptr, one, 1, g.voi.size, iterations, step, threshold, width, shape.relax_blocks, stream);
}

void launch_relax_batch(const BatchItem* items, int n, const Vec3i& most, int iterations, float step,
                        float threshold, float width, const LaunchShape& shape, cudaStream_t stream) {
  if (iterations <= 0 || n < 1) return;
  if (shape.threads != kPersistentThreads)
    throw Error("launch_relax_batch: the relaxation kernel runs " + std::to_string(kPersistentThreads) +
                " threads a block, not " + std::to_string(shape.threads));
  launch(items, BatchItem{}, n, most, iterations, step, threshold, width, shape.relax_blocks, stream);
}

}  // namespace palpsim::cuda
