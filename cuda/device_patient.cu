// One device copy per patient and device, found through a cache of weak references.
#include "cuda/device_patient.h"

#include <cuda_runtime.h>

#include <utility>

#include "core/shared_cache.h"
#include "cuda/check.h"

namespace palpsim::cuda {

namespace {

// the copies that exist, by device and patient (a copy holds its patient, so the address
// names it while the copy lives)
SharedCache<const DevicePatient>& copies() {
  static SharedCache<const DevicePatient> c;
  return c;
}

}  // namespace

DevicePatient::DevicePatient(PatientPtr patient, int device) : patient_(std::move(patient)), device_(device) {
  const Patient& p = *patient_;
  const std::size_t nvol = p.grid.count();
  // allocate both first: a failure frees what was made (the destructor does not run).
  // The copies go on a stream of their own that is waited for: cudaMemcpy() from pageable
  // memory may return before its DMA has landed, and the sessions' non-blocking streams
  // do not wait for the legacy default stream it runs on
  cudaStream_t copy = nullptr;
  try {
    PALPSIM_CUDA_CHECK(cudaMalloc(&intensity_, nvol * sizeof(float)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&bone_, nvol));
    PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&copy, cudaStreamNonBlocking));
    PALPSIM_CUDA_CHECK(
        cudaMemcpyAsync(intensity_, p.intensity.data.data(), nvol * sizeof(float), cudaMemcpyHostToDevice, copy));
    PALPSIM_CUDA_CHECK(cudaMemcpyAsync(bone_, p.bone.data.data(), nvol, cudaMemcpyHostToDevice, copy));
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(copy));
    PALPSIM_CUDA_CHECK(cudaStreamDestroy(std::exchange(copy, nullptr)));
  } catch (...) {
    if (copy) cudaStreamDestroy(copy);
    cudaFree(intensity_);
    cudaFree(bone_);
    throw;
  }
  bytes_ = nvol * (sizeof(float) + sizeof(std::uint8_t));
}

DevicePatient::~DevicePatient() {
  // errors are ignored here: a destructor must not throw
  cudaFree(intensity_);
  cudaFree(bone_);
}

std::shared_ptr<const DevicePatient> DevicePatient::acquire(const PatientPtr& patient) {
  int device = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&device));
  // the upload runs under the cache's lock: a second session binding the same patient
  // waits for this copy instead of making its own
  return copies().get(
      [&](const DevicePatient& d) { return d.device_ == device && d.patient_.get() == patient.get(); },
      [&] { return std::shared_ptr<const DevicePatient>(new DevicePatient(patient, device)); });
}

int DevicePatient::live_copies() { return copies().live(); }

}  // namespace palpsim::cuda
