// The patient's intensity and bone mask on the GPU, one copy per patient and device,
// shared by every session bound to that patient (issue 10): a class of trainees
// palpating one patient holds it once, and a session's own GPU memory is only its VOI
// state. The copy lives while any session holds it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>

#include "core/patient.h"

namespace palpsim::cuda {

/// A read-only device copy of a patient's intensity (float) and bone mask (uint8),
/// whole volume, on the device that was current when it was made.
class DevicePatient {
 public:
  /// The copy of `patient` on the current device: the one already made while any
  /// holder keeps it, else a new upload (blocking; call it off the haptic path).
  /// Thread-safe. Throws palpsim::Error naming the CUDA call that failed.
  static std::shared_ptr<const DevicePatient> acquire(const PatientPtr& patient);

  ~DevicePatient();
  DevicePatient(const DevicePatient&) = delete;
  DevicePatient& operator=(const DevicePatient&) = delete;

  /// The intensity volume on the device (patient grid, i fastest).
  const float* intensity() const { return intensity_; }
  /// The bone mask on the device (patient grid, i fastest; nonzero = bone).
  const std::uint8_t* bone() const { return bone_; }
  /// Device bytes the copy holds.
  std::size_t bytes() const { return bytes_; }
  /// Copies of patients that exist now on all devices (for tests and stats).
  static int live_copies();

 private:
  DevicePatient(PatientPtr patient, int device);

  PatientPtr patient_;  // held so that the patient's address, the cache key, is not reused while this lives
  int device_ = 0;
  float* intensity_ = nullptr;
  std::uint8_t* bone_ = nullptr;
  std::size_t bytes_ = 0;
};

/// A read-only device copy of a patient's body mask C (uint8) and depth under the skin B
/// (float, mm), whole volume, on the device that was current when it was made: what the
/// elastic model reads besides the intensity and bone mask, so made only for sessions
/// whose scene asks for it, one per patient and device like DevicePatient.
class DeviceBody {
 public:
  /// The copy of `patient`'s C and B on the current device (the one alive, or a new upload);
  /// thread-safe. Throws palpsim::Error naming the CUDA call that failed, or saying that the
  /// patient has no body mask or B on its grid.
  static std::shared_ptr<const DeviceBody> acquire(const PatientPtr& patient);

  ~DeviceBody();
  DeviceBody(const DeviceBody&) = delete;
  DeviceBody& operator=(const DeviceBody&) = delete;

  /// The body mask on the device (patient grid, i fastest; nonzero = body).
  const std::uint8_t* body() const { return body_; }
  /// B on the device (patient grid, i fastest; mm).
  const float* dist_skin_mm() const { return dist_skin_; }
  /// Device bytes the copy holds.
  std::size_t bytes() const { return bytes_; }

 private:
  DeviceBody(PatientPtr patient, int device);

  PatientPtr patient_;  // held so that the patient's address, the cache key, is not reused while this lives
  int device_ = 0;
  std::uint8_t* body_ = nullptr;
  float* dist_skin_ = nullptr;
  std::size_t bytes_ = 0;
};

}  // namespace palpsim::cuda
