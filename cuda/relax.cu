// Relaxation on the GPU: the same explicit diffusion as server/deform/relax.cpp.
// All iterations run in one persistent cooperative kernel with a grid-wide barrier
// between them: 20 iterations as 20 host launches cost 20 x 3.3 us (DEVICE.md) at
// VOI 64, where the work of one iteration is a few microseconds; the barrier costs
// about as much as a CUDA graph node (~1 us) and needs no graph per VOI size.
#include <cooperative_groups.h>

#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

// one relaxation update of VOI-local element e of one session, from buffer pa into the other
__device__ __forceinline__ void relax_element(const StepGeometry& geo, const DeviceBuffers& b, int pa, int e, float step,
                                              float threshold, float width) {
  const deform::Voi& voi = geo.voi;
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;  // VOIs hold < 2^31 voxels (checked at bind)
  const int g_idx = geo.grabbed.z * sxy + geo.grabbed.y * sx + geo.grabbed.x;
  const int step_of[6] = {-1, 1, -sx, sx, -sxy, sxy};  // linear offsets in the fixed neighbour order
  const int pb = pa ^ 1;
  const float* ax = b.u[pa][0];
  const float* ay = b.u[pa][1];
  const float* az = b.u[pa][2];
  // 32-bit index arithmetic: 64-bit division costs tens of instructions on the GPU
  const int k = e / sxy, r = e - k * sxy, j = r / sx, i = r - j * sx;
  const long long gi = ((long long)(voi.lo.z + k) * geo.volume_size.y + (voi.lo.y + j)) * geo.volume_size.x +
                       (voi.lo.x + i);
  const Vec3f u{ax[e], ay[e], az[e]};
  const float w = step * deform::material_weight(b.intensity[gi], b.bone[gi] != 0, threshold, width);
  Vec3f out = u;
  if (e != g_idx && w != 0.0f) {
    // the six neighbours in the fixed order, zero outside the VOI
    Vec3f sum6{0, 0, 0};
    const int n_ok[6] = {i > 0, i + 1 < voi.size.x, j > 0, j + 1 < voi.size.y, k > 0, k + 1 < voi.size.z};
    for (int q = 0; q < 6; ++q) {
      if (!n_ok[q]) continue;
      const int ni = e + step_of[q];
      sum6 += Vec3f{ax[ni], ay[ni], az[ni]};
    }
    out = deform::relax_update(u, sum6, w);
  }
  b.u[pb][0][e] = out.x;
  b.u[pb][1][e] = out.y;
  b.u[pb][2][e] = out.z;
}

__global__ void __launch_bounds__(kPersistentThreads) relax_kernel(StepGeometry geo, int src, int iterations, float step,
                                                    float threshold, float width, DeviceBuffers b) {
  cg::grid_group grid = cg::this_grid();
  const unsigned n = unsigned(geo.voi.count());
  const unsigned nthreads = gridDim.x * blockDim.x;
  for (int it = 0; it < iterations; ++it) {
    const int pa = (src + it) & 1;
    for (unsigned t = blockIdx.x * blockDim.x + threadIdx.x; t < n; t += nthreads)
      relax_element(geo, b, pa, int(t), step, threshold, width);
    grid.sync();
  }
}

// the relaxation of several sessions in one cooperative grid (batch.cu says why): each
// iteration strides over the sessions' VOIs laid end to end, `stride` elements apart
// (the largest VOI), each element updated by relax_element as above
__global__ void __launch_bounds__(kPersistentThreads) relax_batch_kernel(const BatchItem* __restrict__ items, int n,
                                                                         unsigned stride, int iterations, float step,
                                                                         float threshold, float width) {
  cg::grid_group grid = cg::this_grid();
  const unsigned total = unsigned(n) * stride;
  const unsigned nthreads = gridDim.x * blockDim.x;
  for (int it = 0; it < iterations; ++it) {
    for (unsigned t = blockIdx.x * blockDim.x + threadIdx.x; t < total; t += nthreads) {
      const unsigned q = t / stride, e = t - q * stride;
      const BatchItem& item = items[q];
      if (e < unsigned(item.geo.voi.count()))
        relax_element(item.geo, item.b, (item.relax_src + it) & 1, int(e), step, threshold, width);
    }
    grid.sync();
  }
}

}  // namespace

int relax_blocks_per_sm(int threads) {
  int per_sm = 0, per_sm_batch = 0;  // the batched relaxation runs on the same grid
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, relax_kernel, threads, 0));
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm_batch, relax_batch_kernel, threads, 0));
  return std::min(per_sm, per_sm_batch);
}

void launch_relax(const StepGeometry& g, int src, int iterations, float step, float threshold, float width,
                  const DeviceBuffers& b, const LaunchShape& shape, cudaStream_t stream) {
  if (iterations <= 0) return;
  const long long n = g.voi.count();
  const int blocks = int(std::min<long long>(shape.relax_blocks, (n + shape.threads - 1) / shape.threads));
  StepGeometry geo = g;
  DeviceBuffers buf = b;
  void* args[] = {&geo, &src, &iterations, &step, &threshold, &width, &buf};
  PALPSIM_CUDA_CHECK(
      cudaLaunchCooperativeKernel((const void*)relax_kernel, dim3(blocks), dim3(shape.threads), args, 0, stream));
}

void launch_relax_batch(const BatchItem* items, int n, unsigned max_count, int iterations, float step, float threshold,
                        float width, const LaunchShape& shape, cudaStream_t stream) {
  if (iterations <= 0 || n < 1) return;
  // the sessions' VOIs end to end must be indexable with 32 bits
  if ((unsigned long long)n * max_count >= (1ULL << 32))
    throw Error("launch_relax_batch: " + std::to_string(n) + " VOIs of " + std::to_string(max_count) +
                " elements exceed 32-bit indices");
  const unsigned long long total = (unsigned long long)n * max_count;
  const int blocks = int(std::min<unsigned long long>(shape.relax_blocks, (total + shape.threads - 1) / shape.threads));
  const BatchItem* it = items;
  unsigned stride = max_count;
  void* args[] = {&it, &n, &stride, &iterations, &step, &threshold, &width};
  PALPSIM_CUDA_CHECK(
      cudaLaunchCooperativeKernel((const void*)relax_batch_kernel, dim3(blocks), dim3(shape.threads), args, 0, stream));
}

}  // namespace palpsim::cuda
