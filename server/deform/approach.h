// Where a tip outside the body is expected to touch the skin: the server solves the
// multigrid relaxation's unit response there while the tip approaches
// (DeformBackend::prime), so that a session's first contact starts warm.
#pragma once

#include "core/patient.h"
#include "core/vec3.h"

namespace palpsim::deform {

/// The centroid of the body mask C (continuous voxel index); the grid's centre when the
/// mask is empty or missing. One pass over the patient: the server computes it once per scene.
Vec3 body_centroid_vox(const Patient& p);

/// The body voxel where a tip at `tip_mm` (outside the body) is expected to touch the
/// skin, into `out`: the body voxel nearest the tip (in mm) among those within
/// `radius_vox` voxels of the tip voxel along every axis (the tip clamped into the grid),
/// or where there is none, the first body voxel on the segment from there to
/// `centroid_vox` (body_centroid_vox()). False when neither finds one (an empty or
/// missing body mask) or the tip is not finite. `near`, when given, says whether the first search found
/// it (the tip within `radius_vox` of the body). Reads at most (2 radius + 1)^3 voxels of C
/// and stops a ring search as soon as no farther ring can hold a nearer voxel.
bool expected_skin_voxel(const Patient& p, const Vec3& tip_mm, int radius_vox, const Vec3& centroid_vox, Vec3i& out,
                         bool* near = nullptr);

}  // namespace palpsim::deform
