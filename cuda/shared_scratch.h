// Solver scratch that sessions share (MultigridScratch, ElasticScratch): one per device and
// capacities while any session holds it, and turns on it, one launch at a time, in order on
// the device, without a host wait.
#pragma once

#include <cuda_runtime.h>

#include <memory>
#include <mutex>

#include "core/shared_cache.h"
#include "cuda/check.h"

namespace palpsim::cuda {

/// Held around a launch that uses a scratch shared by sessions (MultigridScratch,
/// ElasticScratch: a `done` event and a mutex `mu`): the launch waits on the device for the
/// last one that used the scratch, on whatever stream that ran (no host wait), and the next
/// waits for this one.
template <typename Scratch>
class ScratchTurn {
 public:
  ScratchTurn(Scratch& s, cudaStream_t stream) : s_(s), stream_(stream), lock_(s.mu) {
    PALPSIM_CUDA_CHECK(cudaStreamWaitEvent(stream, s.done, 0));  // a no-op before the first record
  }
  ~ScratchTurn() { cudaEventRecord(s_.done, stream_); }  // errors ignored: a destructor must not throw
  ScratchTurn(const ScratchTurn&) = delete;
  ScratchTurn& operator=(const ScratchTurn&) = delete;

 private:
  Scratch& s_;
  cudaStream_t stream_;
  std::lock_guard<std::mutex> lock_;
};

/// The scratch of type Scratch (constructed from `capacity`, `coarse_capacity`, with those
/// members and `device`) shared on the current device for these capacities: the one alive,
/// or a new one.
template <typename Scratch>
std::shared_ptr<Scratch> shared_scratch(long long capacity, long long coarse_capacity) {
  static SharedCache<Scratch> scratches;
  int dev = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  return scratches.get(
      [&](const Scratch& s) { return s.device == dev && s.capacity == capacity && s.coarse_capacity == coarse_capacity; },
      [&] { return std::make_shared<Scratch>(capacity, coarse_capacity); });
}

}  // namespace palpsim::cuda
