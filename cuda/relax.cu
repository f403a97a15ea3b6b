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

__global__ void __launch_bounds__(256) relax_kernel(StepGeometry geo, int src, int iterations, float step,
                                                    float threshold, float width, DeviceBuffers b) {
  cg::grid_group grid = cg::this_grid();
  const deform::Voi& voi = geo.voi;
  const long long g_idx = voi.index(geo.grabbed.x, geo.grabbed.y, geo.grabbed.z);
  const long long n = voi.count();
  const long long nthreads = (long long)gridDim.x * blockDim.x;
  for (int it = 0; it < iterations; ++it) {
    const int pa = (src + it) & 1, pb = pa ^ 1;
    const float* ax = b.u[pa][0];
    const float* ay = b.u[pa][1];
    const float* az = b.u[pa][2];
    for (long long e = (long long)blockIdx.x * blockDim.x + threadIdx.x; e < n; e += nthreads) {
      const int i = int(e % voi.size.x);
      const int j = int((e / voi.size.x) % voi.size.y);
      const int k = int(e / ((long long)voi.size.x * voi.size.y));
      const long long gi = ((long long)(voi.lo.z + k) * geo.volume_size.y + (voi.lo.y + j)) * geo.volume_size.x +
                           (voi.lo.x + i);
      const Vec3f u{ax[e], ay[e], az[e]};
      const float w = step * deform::material_weight(b.intensity[gi], b.bone[gi] != 0, threshold, width);
      Vec3f out = u;
      if (e != g_idx && w != 0.0f) {
        // the six neighbours in the fixed order, zero outside the VOI
        Vec3f sum6{0, 0, 0};
        for (int q = 0; q < 6; ++q) {
          const Vec3i nb = Vec3i{i, j, k} + deform::neighbour_offset(q);
          if (!voi.contains(nb.x, nb.y, nb.z)) continue;
          const long long ni = voi.index(nb.x, nb.y, nb.z);
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
