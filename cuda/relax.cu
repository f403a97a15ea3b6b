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
// - A block updates a unit of 32 rows of one VOI plane, 64 threads along i and 16 rows
//   along j: an element's (i, j, k) come from its thread and unit, not from three integer
//   divisions of its linear index (tens of instructions each on the GPU) as before.
// - Sessions are relaxed a group at a time, all 20 iterations of a group before the next
//   group, the group as large as keeps its fields (both displacement buffers and the
//   weights, 28 bytes an element) within a share of the L2 cache: a batch of 16 VOIs of
//   64^3 holds 116 MB, which every iteration streamed from device memory.
#include <cooperative_groups.h>

#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

// a block's threads: 64 along i (two warps a row, coalesced) by 16 rows along j
constexpr int kRelaxTx = 64;
constexpr int kRelaxTy = kPersistentThreads / kRelaxTx;
static_assert(kRelaxTx * kRelaxTy == kPersistentThreads, "a relaxation block is 64 x 16 threads");
// rows along j a work unit holds: two per thread, so that a 64^3 VOI makes 128 units, about
// one per multiprocessor for a session alone
constexpr int kRelaxUnitRows = 2 * kRelaxTy;

// the share of the L2 cache a group of sessions' fields may fill; 0: all sessions at once.
// A build may set it (-DPALPSIM_RELAX_L2_SHARE=...) to compare; bench/results has the
// figures of each
#ifndef PALPSIM_RELAX_L2_SHARE
#define PALPSIM_RELAX_L2_SHARE 0.6
#endif

// one relaxation update of VOI-local element e = (i, j, k) of a VOI of `size`, from
// buffer pa into the other, with weight w (0: the element keeps its displacement)
__device__ __forceinline__ void relax_element(const Vec3i& size, const DeviceBuffers& b, int pa, int e, int i, int j,
                                              int k, float w) {
  const int sx = size.x, sxy = size.x * size.y;  // VOIs hold < 2^31 voxels (checked at bind)
  const float* ax = b.u[pa][0];
  const float* ay = b.u[pa][1];
  const float* az = b.u[pa][2];
  const Vec3f u{ax[e], ay[e], az[e]};
  Vec3f out = u;
  if (w != 0.0f) {
    // the six neighbours in the fixed order, zero outside the VOI
    Vec3f sum6{0, 0, 0};
    if (i > 0) sum6 += Vec3f{ax[e - 1], ay[e - 1], az[e - 1]};
    if (i + 1 < sx) sum6 += Vec3f{ax[e + 1], ay[e + 1], az[e + 1]};
    if (j > 0) sum6 += Vec3f{ax[e - sx], ay[e - sx], az[e - sx]};
    if (j + 1 < size.y) sum6 += Vec3f{ax[e + sx], ay[e + sx], az[e + sx]};
    if (k > 0) sum6 += Vec3f{ax[e - sxy], ay[e - sxy], az[e - sxy]};
    if (k + 1 < size.z) sum6 += Vec3f{ax[e + sxy], ay[e + sxy], az[e + sxy]};
    out = deform::relax_update(u, sum6, w);
  }
  const int pb = pa ^ 1;
  b.u[pb][0][e] = out.x;
  b.u[pb][1][e] = out.y;
  b.u[pb][2][e] = out.z;
}

// iteration `it` of one session on the rows j0 .. j0 + kRelaxUnitRows - 1 of VOI plane k
__device__ __forceinline__ void relax_unit(const BatchItem& item, int it, int k, int j0, float step, float threshold,
                                           float width) {
  const StepGeometry& geo = item.geo;
  const Vec3i size = geo.voi.size;
  if (k >= size.z) return;  // a smaller (clipped) VOI than the batch's largest
  const DeviceBuffers& b = item.b;
  const int pa = (item.relax_src + it) & 1;
  const int tx = int(threadIdx.x) % kRelaxTx, ty = int(threadIdx.x) / kRelaxTx;
  const int g_idx = (geo.grabbed.z * size.y + geo.grabbed.y) * size.x + geo.grabbed.x;
  const int j_end = min(j0 + kRelaxUnitRows, size.y);
  for (int j = j0 + ty; j < j_end; j += kRelaxTy) {
    const int row = (k * size.y + j) * size.x;
    // the row's start in the patient volume
    const long long grow = ((long long)(geo.voi.lo.z + k) * geo.volume_size.y + (geo.voi.lo.y + j)) *
                               geo.volume_size.x + geo.voi.lo.x;
    for (int i = tx; i < size.x; i += kRelaxTx) {
      const int e = row + i;
      float w;
      if (it == 0) {
        // the grabbed element keeps its displacement: weight 0
        w = e == g_idx ? 0.0f
                       : step * deform::material_weight(b.intensity[grow + i], b.bone[grow + i] != 0, threshold, width);
        b.relax_w[e] = w;
      } else {
        w = b.relax_w[e];
      }
      relax_element(size, b, pa, e, i, j, k, w);
    }
  }
}

// `iterations` relaxation steps of n sessions, `group` at a time (each group all its
// iterations before the next), each iteration a grid-stride loop over the group's units
// (a session's units as if its VOI were the largest: `planes` planes of `row_units` units)
// and a grid barrier. kBatch: the sessions are items[0 .. n-1]; otherwise the one in `one`
template <bool kBatch>
__global__ void __launch_bounds__(kPersistentThreads)
    relax_kernel(const BatchItem* __restrict__ items, BatchItem one, int n, int group, int planes, int row_units,
                 int iterations, float step, float threshold, float width) {
  cg::grid_group grid = cg::this_grid();
  const unsigned per_session = unsigned(planes) * unsigned(row_units);
  for (int g0 = 0; g0 < n; g0 += group) {
    const int gn = min(group, n - g0);
    const unsigned units = unsigned(gn) * per_session;
    for (int it = 0; it < iterations; ++it) {
      for (unsigned t = blockIdx.x; t < units; t += gridDim.x) {
        const unsigned q = t / per_session, r = t - q * per_session;
        const unsigned k = r / unsigned(row_units), jb = r - k * unsigned(row_units);
        if (kBatch)
          relax_unit(items[g0 + int(q)], it, int(k), int(jb) * kRelaxUnitRows, step, threshold, width);
        else
          relax_unit(one, it, int(k), int(jb) * kRelaxUnitRows, step, threshold, width);
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
  int planes = most.z, row_units = (most.y + kRelaxUnitRows - 1) / kRelaxUnitRows;
  const unsigned long long count = (unsigned long long)most.x * most.y * most.z;
  int group = items ? relax_group(n, count) : 1;
  // the units of a group must be indexable with 32 bits
  if ((unsigned long long)group * planes * row_units >= (1ULL << 32))
    throw Error("launch_relax: " + std::to_string(group) + " VOIs of " + std::to_string(count) +
                " elements exceed 32-bit unit indices");
  const unsigned long long units = (unsigned long long)group * planes * row_units;
  const int blocks = int(std::min<unsigned long long>(max_blocks, units));
  const BatchItem* it = items;
  BatchItem single = one;
  void* args[] = {&it, &single, &n, &group, &planes, &row_units, &iterations, &step, &threshold, &width};
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

void launch_relax(const StepGeometry& g, int src, int iterations, float step, float threshold, float width,
                  const DeviceBuffers& b, const LaunchShape& shape, cudaStream_t stream) {
  if (iterations <= 0) return;
  if (shape.threads != kPersistentThreads)
    throw Error("launch_relax: the relaxation kernel runs " + std::to_string(kPersistentThreads) +
                " threads a block, not " + std::to_string(shape.threads));
  BatchItem one;
  one.geo = g;
  one.relax_src = src;
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
