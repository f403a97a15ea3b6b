// Cutting a ForcePatch (force_patch.h) out of the patient around a point: the box on the
// patient grid and the copy of C, F and grad F into it, row by row. Server side only
// (the client receives patches); the pose thread calls it for a session that asked for
// patches, so it copies into buffers it is given and allocates nothing itself.
#pragma once

#include <cstdint>

#include "core/patient.h"
#include "haptics/force_patch.h"

namespace palpsim {

/// The box of `edge` voxels per axis (fewer where the patient grid is smaller) whose centre
/// is the voxel nearest to `center_mm`, moved inside the patient grid. Returns its first
/// voxel; `size` gets its size.
Vec3i patch_box(const Grid& patient_grid, const Vec3& center_mm, int edge, Vec3i& size);

/// Copies C, F and grad F of the box (lo, size) into `body`, `force_mm` and `grad_force`
/// (size.x*size.y*size.z values each, i fastest). The box must lie inside the grid.
void gather_patch(const Patient& patient, const Vec3i& lo, const Vec3i& size, std::uint8_t* body, float* force_mm,
                  Vec3f* grad_force);

/// Grid of a box of the patient grid: the same spacing and direction, origin at its first voxel.
Grid patch_grid(const Grid& patient_grid, const Vec3i& lo, const Vec3i& size);

/// A whole ForcePatch of `edge` voxels around `center_mm` (allocates: tests and tools).
ForcePatch cut_patch(const Patient& patient, const Vec3& center_mm, int edge, const HapticsSettings& params,
                     std::uint64_t version);

}  // namespace palpsim
