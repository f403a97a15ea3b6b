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

__global__ void __launch_bounds__(kPersistentThreads) relax_kernel(StepGeometry geo, int src, int iterations, float step,
                                                    float threshold, float width, DeviceBuffers b) {
  cg::grid_group grid = cg::this_grid();
  const deform::Voi& voi = geo.voi;
  const int sx = voi.size.x, sxy = voi.size.x * voi.size.y;  // VOIs hold < 2^31 voxels (checked at bind)
  const int g_idx = geo.grabbed.z * sxy + geo.grabbed.y * sx + geo.grabbed.x;
  const unsigned n = unsigned(voi.count());
  const unsigned nthreads = gridDim.x * blockDim.x;
  const int step_of[6] = {-1, 1, -sx, sx, -sxy, sxy};  // linear offsets in the fixed neighbour order
  for (int it = 0; it < iterations; ++it) {
    const int pa = (src + it) & 1, pb = pa ^ 1;
    const float* ax = b.u[pa][0];
    const float* ay = b.u[pa][1];
    const float* az = b.u[pa][2];
    for (unsigned t = blockIdx.x * blockDim.x + threadIdx.x; t < n; t += nthreads) {
      // 32-bit index arithmetic: 64-bit division costs tens of instructions on the GPU
      const int e = int(t);
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
    grid.sync();
  }
}

}  // namespace

int relax_blocks_per_sm(int threads) {
  int per_sm = 0;
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, relax_kernel, threads, 0));
  return per_sm;
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

}  // namespace palpsim::cuda
