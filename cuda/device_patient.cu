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

// the body copies that exist, likewise
SharedCache<const DeviceBody>& body_copies() {
  static SharedCache<const DeviceBody> c;
  return c;
}

// copies each host buffer (src[i], bytes[i]) into a new device allocation *dst[i]: all
// allocated first (a failure frees what was made), then copied on a stream of their own
// that is waited for: cudaMemcpy() from pageable memory may return before its DMA has
// landed, and the sessions' non-blocking streams do not wait for the legacy default
// stream it runs on
template <std::size_t N>
void upload(const void* const (&src)[N], const std::size_t (&bytes)[N], void** const (&dst)[N]) {
  cudaStream_t copy = nullptr;
  try {
    for (std::size_t i = 0; i < N; ++i) PALPSIM_CUDA_CHECK(cudaMalloc(dst[i], bytes[i]));
    PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&copy, cudaStreamNonBlocking));
    for (std::size_t i = 0; i < N; ++i)
      PALPSIM_CUDA_CHECK(cudaMemcpyAsync(*dst[i], src[i], bytes[i], cudaMemcpyHostToDevice, copy));
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(copy));
    PALPSIM_CUDA_CHECK(cudaStreamDestroy(std::exchange(copy, nullptr)));
  } catch (...) {
    if (copy) cudaStreamDestroy(copy);
    for (std::size_t i = 0; i < N; ++i) {
      cudaFree(*dst[i]);
      *dst[i] = nullptr;
    }
    throw;
  }
}

}  // namespace

DevicePatient::DevicePatient(PatientPtr patient, int device) : patient_(std::move(patient)), device_(device) {
  const Patient& p = *patient_;
  const std::size_t nvol = p.grid.count();
  upload({(const void*)p.intensity.data.data(), (const void*)p.bone.data.data()}, {nvol * sizeof(float), nvol},
         {(void**)&intensity_, (void**)&bone_});
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

DeviceBody::DeviceBody(PatientPtr patient, int device) : patient_(std::move(patient)), device_(device) {
  const Patient& p = *patient_;
  const std::size_t nvol = p.grid.count();
  if (!p.body.grid.same_geometry(p.grid) || p.body.data.size() != nvol || !p.dist_skin_mm.grid.same_geometry(p.grid) ||
      p.dist_skin_mm.data.size() != nvol)
    throw Error("deform backend \"cuda\": the elastic model needs the patient's body mask and depth under the skin "
                "(Patient::body, Patient::dist_skin_mm) on its grid");
  upload({(const void*)p.body.data.data(), (const void*)p.dist_skin_mm.data.data()}, {nvol, nvol * sizeof(float)},
         {(void**)&body_, (void**)&dist_skin_});
  bytes_ = nvol * (sizeof(std::uint8_t) + sizeof(float));
}

DeviceBody::~DeviceBody() {
  // errors are ignored here: a destructor must not throw
  cudaFree(body_);
  cudaFree(dist_skin_);
}

std::shared_ptr<const DeviceBody> DeviceBody::acquire(const PatientPtr& patient) {
  int device = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&device));
  return body_copies().get(
      [&](const DeviceBody& d) { return d.device_ == device && d.patient_.get() == patient.get(); },
      [&] { return std::shared_ptr<const DeviceBody>(new DeviceBody(patient, device)); });
}

}  // namespace palpsim::cuda
