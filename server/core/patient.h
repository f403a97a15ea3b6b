// The patient: a CT made palpable, on one isotropic grid. Immutable once built and
// shared by every session (MuJoCo's mjModel role).
#pragma once

#include <cstdint>
#include <limits>
#include <memory>
#include <string>

#include "core/grid.h"
#include "core/volume.h"

namespace palpsim {

/// Everything the simulation reads from the CT, on one isotropic grid (mm, LPS).
struct Patient {
  Grid grid;                       // the patient grid; every volume below shares it
  Volume<float> intensity;         // resampled CT: HU, or the image's own units if not HU
  Volume<std::uint8_t> body;       // C: 1 inside the patient, 0 outside air, table and border air
  Volume<std::uint8_t> bone;       // 1 where rigid bone is
  Volume<float> dist_bone_mm;      // A: Euclidean distance to the nearest bone voxel (mm)
  Volume<float> dist_skin_mm;      // B: depth under the skin, distance to the nearest outside voxel (mm), 0 outside;
                                   // beyond the grid's faces counts as outside with prep.cut_faces "skin"
  Volume<float> force;             // F = alpha*C/(beta+A) + gamma*B (mm), eq. 1
  Volume<Vec3f> grad_force;        // grad F in physical axes (mm/mm), central differences
  bool has_bone = false;           // false when the bone mask is empty (A is then +inf)
  double bone_threshold_hu = std::numeric_limits<double>::quiet_NaN();  // the low bone threshold prep used
                                   // (automatic or the scene's); NaN for patients not made by prep
  std::string source;              // what it was made from (path or "phantom")
};

using PatientPtr = std::shared_ptr<const Patient>;

}  // namespace palpsim
