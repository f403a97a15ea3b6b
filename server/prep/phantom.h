// The built-in procedural phantom: a torso in HU with closed-form bone and skin
// geometry, so tests can check masks and distances against truth. No ITK here.
//
// Layout (LPS, mm; +x patient's left, +y posterior, +z superior). The patient lies
// PRONE: the back faces +y (up, free to palpate) and the CT table lies under the
// anterior side (low y). The torso is an elliptic cylinder along z (semi-axes 155 x
// 110 mm, centred on x = y = 0, back skin at y = +110) that the volume cuts at
// z = -110 and +110 like a CT's field of view. Spine: vertebral bodies centred at
// y = +6 for T12 (z = +96), L1 (+62), L2 (+28), L3 (-6), L4 (-40), L5 (-74) and the
// top of S1 (-108); spinous process tips 24-38 mm under the back skin; ribs 10-12 on
// both sides; iliac crests with their tops at z = -34 (L4, Tuffier's line) at
// x = +-128; bowel loops with gas pockets; a carbon CT table at y = -114..-140
// (4 mm below the skin). The grid: origin (-170, -145, -110) mm for every voxel size,
// direction identity, voxel centres at origin + (i, j, k) * voxel_mm, extent
// 340 x 270 x 220 mm (see phantom_grid).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/volume.h"

namespace palpsim {

/// Tissue values of the phantom (HU) before partial-volume averaging and texture.
namespace phantom_hu {
constexpr float kAir = -1000;        // outside air and bowel gas
constexpr float kSkin = 30;          // 2 mm dermis
constexpr float kFat = -100;         // subcutaneous fat
constexpr float kMuscle = 50;        // muscle (body wall, back, psoas)
constexpr float kViscera = 30;       // abdominal cavity content between bowel loops
constexpr float kBowelWall = 40;     // 3 mm bowel wall
constexpr float kBowelFluid = 15;    // fluid in bowel loops (below the gas level)
constexpr float kCanal = 15;         // spinal canal (CSF, cord)
constexpr float kDisc = 80;          // intervertebral discs
constexpr float kCortical = 1000;    // cortical bone shell
constexpr float kCancellousVertebra = 180;  // vertebral body interior: below the default bone threshold 200
constexpr float kCancellous = 300;   // interior of other bones (arches, ribs, ilium, sacrum)
constexpr float kTableShell = 300;   // carbon-fibre skin of the CT table
constexpr float kTableCore = -850;   // low-density foam core of the CT table
constexpr float kTextureAmplitude = 10;  // +- texture noise on tissue (none in pure air or gas)
}  // namespace phantom_hu

/// A named anatomical point on a bone surface (mm, LPS), e.g. "spinous_tip_L3".
struct PhantomLandmark {
  std::string name;
  Vec3 p_mm;
};

struct PhantomShapes;

/// Closed-form description of the phantom's anatomy, in physical mm (LPS).
/// Implemented in phantom.cpp; the generator rasterizes exactly these shapes.
class PhantomGeometry {
 public:
  /// Builds the (fixed, deterministic) list of shapes; cheap, shares them between copies.
  PhantomGeometry();
  /// Signed distance (mm) to the skin surface: negative inside the body. Exact (the
  /// torso is an elliptic cylinder along z; the volume's z ends are not skin).
  double skin_signed_distance_mm(const Vec3& p_mm) const;
  /// Signed distance (mm) to the nearest bone surface: negative inside bone. Exact
  /// outside bone (bones are unions of capsules, rounded boxes and rounded elliptic
  /// slabs with exact distances); inside bone the magnitude is a lower bound of the
  /// true depth (the deepest of the overlapping shapes).
  double bone_signed_distance_mm(const Vec3& p_mm) const;
  /// True where the CT table is (outside the patient), foam core included.
  bool in_table(const Vec3& p_mm) const;
  /// True inside a gas pocket of the bowel (inside the patient).
  bool in_bowel_gas(const Vec3& p_mm) const;
  /// Bone landmarks for tests and scenarios: spinous_tip_<level> (posterior-most
  /// point of each spinous process, levels T12 L1..L5 S1), iliac_crest_top_{left,right}
  /// (highest point of each crest), rib<n>_{left,right} (a point on the outer surface,
  /// facing the skin, of ribs 10-12 inside the volume), all on a bone surface; and
  /// vertebral_body_<level> (centre of each vertebral body, deep inside bone).
  const std::vector<PhantomLandmark>& landmarks() const;
  /// The landmark called `name`; throws palpsim::Error naming it when there is none.
  Vec3 landmark(const std::string& name) const;

 private:
  std::shared_ptr<const PhantomShapes> shapes_;
  friend struct PhantomRasterizer;
};

/// The phantom CT (HU, float) at `voxel_mm`, and its geometry. Deterministic:
/// the same voxel size gives the same voxels on every machine.
struct PhantomCt {
  Volume<float> hu;
  PhantomGeometry geometry;
};

/// The phantom's grid at `voxel_mm`: origin (-170, -145, -110) mm, identity
/// direction, floor(extent / voxel_mm) + 1 voxels per axis for the extent
/// 340 x 270 x 220 mm. Throws palpsim::Error outside 0.25 to 4 mm.
Grid phantom_grid(double voxel_mm);

/// Generates the phantom at the given isotropic voxel size (mm, 0.25 to 4); partial
/// volume at every boundary (an SDF ramp over one voxel), a fixed hash texture.
PhantomCt make_phantom(double voxel_mm);

}  // namespace palpsim
