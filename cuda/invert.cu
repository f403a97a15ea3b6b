// Inversion on the GPU: J on the VOI by the same Newton steps and cell search as
// server/deform/invert.cpp; one thread per voxel, one launch.
#include <algorithm>

#include "cuda/check.h"
#include "cuda/kernels.h"

namespace palpsim::cuda {

namespace {

__global__ void __launch_bounds__(256) invert_kernel(StepGeometry geo, int src, int iterations, DeviceBuffers b) {
  const deform::Voi& voi = geo.voi;
  const int e = int(blockIdx.x * blockDim.x + threadIdx.x);  // VOIs hold < 2^31 voxels (checked at bind)
  float r = 0.0f, change = 0.0f;
  bool broken = false;
  if (e < int(voi.count())) {
    const float* ux = b.u[src][0];
    const float* uy = b.u[src][1];
    const float* uz = b.u[src][2];
    const Vec3i size = geo.volume_size;
    // displacement of a VOI-local voxel, zero outside the VOI (undeformed tissue)
    auto load_u = [&](int i, int j, int k) {
      if (!voi.contains(i, j, k)) return Vec3f{0, 0, 0};
      const int n = (k * voi.size.y + j) * voi.size.x + i;
      return Vec3f{ux[n], uy[n], uz[n]};
    };
    // intensity at a VOI-local voxel, clamped at the volume border
    auto load_i = [&](int i, int j, int k) {
      const int gi = min(max(voi.lo.x + i, 0), size.x - 1);
      const int gj = min(max(voi.lo.y + j, 0), size.y - 1);
      const int gk = min(max(voi.lo.z + k, 0), size.z - 1);
      return b.intensity[((long long)gk * size.y + gj) * size.x + gi];
    };
    const int sxy = voi.size.x * voi.size.y;
    const int k = e / sxy, rem = e - k * sxy, j = rem / voi.size.x, i = rem - j * voi.size.x;
    const Vec3f p = deform::invert_voxel(load_u, voi.size, Vec3f(float(i), float(j), float(k)), iterations, r);
    const float jv = deform::trilinear<float>(load_i, p);
    b.j[e] = jv;
    // how far J moved from I here, and whether it is a number at all
    broken = !isfinite(jv);
    if (!broken) change = fabsf(jv - load_i(i, j, k));
  }
  // unresolved voxels of the warp, counted before r is reduced
  const unsigned bad = __popc(__ballot_sync(0xffffffffu, r > deform::kInvertResolvedVox));
  const unsigned nonfinite = __popc(__ballot_sync(0xffffffffu, broken));
  // the largest residual: warp maximum, then one atomic per warp (float bits order as unsigned for r >= 0)
  // and the largest change of the image, likewise
  for (int o = 16; o > 0; o >>= 1) {
    r = fmaxf(r, __shfl_down_sync(0xffffffffu, r, o));
    change = fmaxf(change, __shfl_down_sync(0xffffffffu, change, o));
  }
  if ((threadIdx.x & 31) == 0) {
    atomicMax(&b.counters->residual_bits, __float_as_uint(r));
    atomicMax(&b.counters->change_bits, __float_as_uint(change));
    if (bad) atomicAdd(&b.counters->unresolved, (unsigned long long)bad);
    if (nonfinite) atomicAdd(&b.counters->nonfinite, (unsigned long long)nonfinite);
  }
}

}  // namespace

void launch_invert(const StepGeometry& g, int src, int iterations, const DeviceBuffers& b, cudaStream_t stream) {
  const long long n = g.voi.count();
  const int threads = 256;
  invert_kernel<<<unsigned((n + threads - 1) / threads), threads, 0, stream>>>(g, src, iterations, b);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
}

}  // namespace palpsim::cuda
