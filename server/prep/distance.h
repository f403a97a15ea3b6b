// Exact Euclidean distance transforms on anisotropic grids (Felzenszwalb and
// Huttenlocher's separable lower-envelope algorithm), multithreaded, no ITK.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>

#include "core/volume.h"

namespace palpsim {

/// Distance (mm) from every voxel centre to the nearest voxel centre where
/// `mask` is non-zero, with the grid's spacing per axis (exact Euclidean, not a
/// chamfer). Feature voxels get 0; with no feature voxel at all every voxel gets
/// +infinity. Runs on worker_threads(threads) threads, with identical results.
Volume<float> distance_to_mask_mm(const Volume<std::uint8_t>& mask, int threads = 0);

/// Same as distance_to_mask_mm but to the voxels where `mask` is zero (the
/// distance inside a mask to its outside; 0 outside the mask).
Volume<float> distance_to_background_mm(const Volume<std::uint8_t>& mask, int threads = 0);

/// Squared distances (mm^2) to the voxels where `feature(mask value)` holds;
/// the building block of both functions above.
Volume<float> squared_distance_mm2(const Volume<std::uint8_t>& mask, bool to_nonzero, int threads = 0);

/// The number of threads a request for `requested` runs on: the hardware's cores
/// for 0 or less, never more than them (more would only take turns on a core).
int worker_threads(int requested);

/// Runs fn(begin, end) over [0, n) split into contiguous chunks on
/// worker_threads(threads) threads; used by the prep stages for their voxel loops.
void parallel_for(std::size_t n, int threads, const std::function<void(std::size_t, std::size_t)>& fn);

}  // namespace palpsim
