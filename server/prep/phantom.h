// The built-in procedural phantom: a torso in HU with closed-form bone and skin
// geometry, so tests can check masks and distances against truth. No ITK here.
#pragma once

#include "core/volume.h"

namespace palpsim {

/// Closed-form description of the phantom's anatomy, in physical mm (LPS).
/// Implemented in phantom.cpp; the generator rasterizes exactly these shapes.
class PhantomGeometry {
 public:
  /// Signed distance (mm) to the skin surface: negative inside the body.
  double skin_signed_distance_mm(const Vec3& p_mm) const;
  /// Signed distance (mm) to the nearest bone surface: negative inside bone.
  double bone_signed_distance_mm(const Vec3& p_mm) const;
  /// True where the CT table is (outside the patient).
  bool in_table(const Vec3& p_mm) const;
  /// True inside a gas pocket of the bowel (inside the patient).
  bool in_bowel_gas(const Vec3& p_mm) const;
};

/// The phantom CT (HU, float) at `voxel_mm`, and its geometry. Deterministic:
/// the same voxel size gives the same voxels on every machine.
struct PhantomCt {
  Volume<float> hu;
  PhantomGeometry geometry;
};

/// Generates the phantom at the given isotropic voxel size (mm, 0.25 to 4).
PhantomCt make_phantom(double voxel_mm);

}  // namespace palpsim
