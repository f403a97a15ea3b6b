// Device memory that one module allocates and another only passes along: the cuda
// deformation backend copies J into it, the render thread's CUDA-GL overlay writer reads
// it. Opaque outside cuda/ (no CUDA type crosses this header).
#pragma once

#include <cstddef>

namespace palpsim {

/// A block of GPU memory; freed by its destructor (on any thread of the process).
class DeviceBytes {
 public:
  virtual ~DeviceBytes() = default;
  /// The device pointer.
  virtual void* data() = 0;
  virtual const void* data() const = 0;
  /// Its size (bytes).
  virtual std::size_t size() const = 0;
};

}  // namespace palpsim
