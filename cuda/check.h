// Checking every CUDA call: a failed call throws palpsim::Error naming the call,
// the error and the source line. CUDA types stay inside cuda/.
#pragma once

#include <cuda_runtime.h>

#include <string>

#include "core/error.h"

namespace palpsim::cuda {

/// Throws palpsim::Error when `e` is not cudaSuccess.
inline void check(cudaError_t e, const char* call, const char* file, int line) {
  if (e != cudaSuccess)
    throw Error(std::string("CUDA error ") + cudaGetErrorName(e) + " (" + cudaGetErrorString(e) + ") in " + call +
                " at " + file + ":" + std::to_string(line));
}

}  // namespace palpsim::cuda

/// Checks a CUDA runtime call (or cudaGetLastError() after a launch).
#define PALPSIM_CUDA_CHECK(call) ::palpsim::cuda::check((call), #call, __FILE__, __LINE__)
