// The resources of one batched deformation step of several sessions (batch.cu): its
// stream, stage events and the sessions' BatchItems on the host (pinned) and device.
#pragma once

#include <cuda_runtime.h>

#include <chrono>

#include "cuda/kernels.h"

namespace palpsim::cuda {

/// A batch's launches and what they read: CudaDeformBackend::begin_batch_impl fills the
/// items and enqueues the stages, each member's end_step() waits for it once. Reused by
/// the backend that led it once every member has ended its step.
class CudaBatch {
 public:
  /// Creates the stream and events and allocates room for kMaxBatch items; throws
  /// palpsim::Error naming the CUDA call that failed.
  CudaBatch();
  ~CudaBatch();
  CudaBatch(const CudaBatch&) = delete;
  CudaBatch& operator=(const CudaBatch&) = delete;

  /// Waits for the batch's last stage (once) and reads the stage times.
  void wait();

  /// Elastic solves side by side (relax_elastic_lanes()): each lane's stream waits for
  /// `fork` (the reset, recorded on `stream`), `stream` for each lane's `joined`.
  static constexpr int kMaxLanes = 8;
  cudaStream_t lane_stream[kMaxLanes] = {};
  cudaEvent_t fork = nullptr, joined[kMaxLanes] = {};

  cudaStream_t stream = nullptr;
  cudaEvent_t ev[6] = {};                // before reset, after reset, ChainMail, relax, invert, counters copied
  BatchItem* host_items = nullptr;       // pinned, kMaxBatch
  BatchItem* dev_items = nullptr;        // device, kMaxBatch
  int n = 0;                             // sessions in the batch now
  bool done = true;                      // wait() has run since the last launch
  float stage_ms[5] = {};                // reset, ChainMail, relax, invert, counters: the whole batch's (ms)
  std::chrono::steady_clock::time_point start;  // when the batch was begun
  double wall_ms = 0;                    // from begin to the end of the first wait() (ms)
};

}  // namespace palpsim::cuda
