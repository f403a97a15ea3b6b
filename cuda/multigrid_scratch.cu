// The multigrid solver's device scratch (MultigridScratch, cuda_backend.h): its buffers,
// shared by the sessions of one device and lent to each solve in turn.
#include <memory>

#include "cuda/check.h"
#include "cuda/cuda_backend.h"

namespace palpsim::cuda {

MultigridScratch::MultigridScratch(long long n, long long nc) : capacity(n), coarse_capacity(nc) {
  PALPSIM_CUDA_CHECK(cudaGetDevice(&device));
  for (float** v : {&r[0], &r[1], &z, &p[0], &p[1], &q, &res})
    PALPSIM_CUDA_CHECK(cudaMalloc(v, std::size_t(n) * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&held, std::size_t(n)));
  for (float** v : {&cx, &cf, &cres}) PALPSIM_CUDA_CHECK(cudaMalloc(v, std::size_t(nc) * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&cheld, std::size_t(nc)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&dots, 6 * deform::kMultigridMaxCycles * sizeof(double)));
  PALPSIM_CUDA_CHECK(cudaEventCreateWithFlags(&done, cudaEventDisableTiming));
}

MultigridScratch::~MultigridScratch() {
  cudaEventDestroy(done);
  for (void* v : {(void*)r[0], (void*)r[1], (void*)z, (void*)p[0], (void*)p[1], (void*)q, (void*)res, (void*)held,
                  (void*)cx, (void*)cf, (void*)cres, (void*)cheld, (void*)dots})
    cudaFree(v);
}

std::shared_ptr<MultigridScratch> MultigridScratch::shared(long long n, long long nc) {
  return shared_scratch<MultigridScratch>(n, nc);
}

void MultigridScratch::lend_to(MultigridBuffers& m) const {
  m.r[0] = r[0];
  m.r[1] = r[1];
  m.z = z;
  m.p[0] = p[0];
  m.p[1] = p[1];
  m.q = q;
  m.res = res;
  m.held = held;
  m.cx = cx;
  m.cf = cf;
  m.cres = cres;
  m.cheld = cheld;
  m.dots = dots;
}

std::size_t MultigridScratch::bytes() const {
  return std::size_t(capacity) * (7 * sizeof(float) + 1) + std::size_t(coarse_capacity) * (3 * sizeof(float) + 1) +
         6 * deform::kMultigridMaxCycles * sizeof(double);
}

}  // namespace palpsim::cuda
