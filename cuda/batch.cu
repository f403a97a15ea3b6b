// Batched steps: one launch per stage steps every session of a batch (the sessions the
// deformation worker found ready in one pass, with the same settings).
//
// Why batched launches and not streams per session. One session's step at VOI 64 is
// latency-bound: cooperative launches, a grid barrier per ChainMail sweep and per
// relaxation iteration, small kernels; the GPU is mostly idle during it (722 steps/s
// for one session in palpsim-bench server on the H100). With one stream per session
// and 1/K of the device each (--deform-concurrency K, e785eaa) K steps overlap, but each
// still pays its own barriers and launches: 16 sessions got 119 steps/s each one at a
// time and 223 with K = 4, 64 sessions 28 and 54, and 16 watched sessions 26.7 frames/s
// with K = 4. A batch pays one launch and one barrier per sweep or iteration for all of
// its sessions and fills the device with their elements: 16 sessions 238 and 64
// sessions 63 steps/s each (c85ba1b, J copied to the host in every step), 268 and 69
// with J's host copy made only when read (below); 16 watched sessions kept 29.9 frames/s.
//
// Where a batch's time goes then (H100, 16 sessions, per step, at c85ba1b): reset 0.004 ms,
// ChainMail 0.046, relaxation 0.073, inversion 0.039: the GPU is busy, no longer waiting.
// Measured again for issue 10 (palpsim-bench server now records the stage times; H100,
// f32eabd): at 16 sessions reset 0.0034, ChainMail 0.044, relaxation 0.072, inversion
// 0.060, counters 0.0004, GPU 0.180 of a 0.182 ms step; at 64 sessions 0.003, 0.038,
// 0.068, 0.061, GPU 0.169 of 0.169. The host adds ~1%: the batch's wall is its GPU time.
// The worker's naps (28% of its time at 16 and 64 sessions) are the quarter of each 1 Hz
// press when every bench client, all in phase, is above the body: no contact, no step.
// The relaxation then read each element three times an iteration, from device memory
// (16 sessions' fields are 116 MB); it now walks columns with the sessions in L2-sized
// groups (relax.cu): 0.049 ms at 16 sessions, 0.056 at 64 (ad19d85), and the inversion
// is the largest stage. Copying J to the host in every step cost 16 MB per batch of 16
// over PCIe (a seventh of the batch); the server reads the host copy only for brick
// viewers (frames take the device copy), so a batched step leaves it on the device and
// deformed_brick() copies it when asked.
//
// Each session's results equal its own step's to the bit: every element runs the same
// device function as the single kernels (chainmail_element, relax_column (one kernel for
// both), invert_element), reads only its own session's buffers, and a session's ChainMail
// stops sweeping after its own quiet sweep; sums are per element or integer counts.
#include "cuda/batch.h"

#include <algorithm>

#include "cuda/check.h"

namespace palpsim::cuda {

namespace {

// reset_kernel of cuda_backend.cu for every session: blockIdx.y is the session
__global__ void reset_batch_kernel(const BatchItem* __restrict__ items) {
  const BatchItem& item = items[blockIdx.y];
  reset_elements(item.reset_count, item.b, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

// every session's counters into its pinned host copy (mapped: cudaMallocHost memory is
// device-accessible under unified addressing), one thread each
__global__ void gather_batch_kernel(const BatchItem* __restrict__ items, int n) {
  const int q = int(blockIdx.x * blockDim.x + threadIdx.x);
  if (q < n) *items[q].host_counters = *items[q].b.counters;
}

}  // namespace

void launch_reset_batch(const BatchItem* items, int n, unsigned max_reset, cudaStream_t stream) {
  if (n < 1) return;
  const unsigned threads = 256;
  // as reset_kernel: at most a few blocks per session, at least one (it zeroes the counters)
  const unsigned blocks = std::max(1u, std::min((max_reset + threads - 1) / threads, 64u));
  reset_batch_kernel<<<dim3(blocks, unsigned(n)), threads, 0, stream>>>(items);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
}

void launch_gather_batch(const BatchItem* items, int n, cudaStream_t stream) {
  if (n < 1) return;
  gather_batch_kernel<<<1, kMaxBatch, 0, stream>>>(items, n);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
}

CudaBatch::CudaBatch() {
  PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking));
  for (cudaEvent_t& e : ev) PALPSIM_CUDA_CHECK(cudaEventCreate(&e));
  PALPSIM_CUDA_CHECK(cudaMallocHost(&host_items, kMaxBatch * sizeof(BatchItem)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&dev_items, kMaxBatch * sizeof(BatchItem)));
}

CudaBatch::~CudaBatch() {
  // errors are ignored here: a destructor must not throw; a batch in flight is waited for
  if (stream) cudaStreamSynchronize(stream);
  cudaFree(dev_items);
  cudaFreeHost(host_items);
  for (cudaEvent_t& e : ev)
    if (e) cudaEventDestroy(e);
  if (stream) cudaStreamDestroy(stream);
}

void CudaBatch::wait() {
  if (done) return;
  PALPSIM_CUDA_CHECK(cudaEventSynchronize(ev[5]));
  wall_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  for (int s = 0; s < 5; ++s) PALPSIM_CUDA_CHECK(cudaEventElapsedTime(&stage_ms[s], ev[s], ev[s + 1]));
  done = true;
}

}  // namespace palpsim::cuda
