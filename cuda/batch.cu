// Batched steps: one launch per stage steps every session of a batch (the sessions the
// deformation worker found ready in one pass, with the same settings).
//
// Why batched launches and not streams per session. One session's step at VOI 64 is
// latency-bound: cooperative launches, a grid barrier per ChainMail sweep and per
// relaxation iteration, small kernels; the GPU is mostly idle during it. Streams per
// session with a share of the device each (--deform-concurrency K) overlap K steps, but
// each still pays its own barriers and launches. A batch pays one launch and one barrier
// per sweep or iteration for all of its sessions and fills the device with their
// elements, so that its wall is its GPU time (docs/benchmarks.md and bench/results/ have
// the steps a second of each way and the stage times). The relaxation walks columns with
// the sessions in L2-sized groups (relax.cu), so that a batch's fields are not read from
// device memory three times an iteration. J stays on the device after a batched step:
// frames take the device copy, and deformed_brick() copies it to the host only when a
// brick viewer asks.
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
  for (cudaStream_t& l : lane_stream) PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&l, cudaStreamNonBlocking));
  PALPSIM_CUDA_CHECK(cudaEventCreateWithFlags(&fork, cudaEventDisableTiming));
  for (cudaEvent_t& e : joined) PALPSIM_CUDA_CHECK(cudaEventCreateWithFlags(&e, cudaEventDisableTiming));
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
  for (cudaEvent_t& e : joined)
    if (e) cudaEventDestroy(e);
  if (fork) cudaEventDestroy(fork);
  for (cudaStream_t& l : lane_stream)
    if (l) cudaStreamDestroy(l);
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
