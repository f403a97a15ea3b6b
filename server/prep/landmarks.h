// Palpable landmarks found in a prepared patient: the tips of the spinous processes
// and the tops of the iliac crests, each with the skin point above it and the start
// point and travel of a scripted press (palpsim-haptic --device press:X,Y,Z,TRAVEL) that
// reaches it.
#pragma once

#include <string>
#include <vector>

#include "core/patient.h"

namespace palpsim {

/// One landmark: a bone point, the skin above it and where a press towards it starts.
struct SkinLandmark {
  std::string name;   // "spinous process 1" (counted from superior), "iliac crest left" / "right"
  Vec3 bone_mm;       // the bone point (mm, LPS)
  Vec3 skin_mm;       // where the line from bone_mm along +y (posterior) leaves the body (mm, LPS)
  double depth_mm = 0;  // bone_mm under skin_mm (mm)
  Vec3 press_start_mm;  // kPressStandoffMm beyond skin_mm along +y (mm, LPS)
  double press_travel_mm = 0;  // from press_start_mm along -y to bone_mm and kPressBeyondBoneMm on (mm)
  double normal_angle_deg = 0;  // the angle between the skin's outward normal at skin_mm and +y
};

/// How far (mm) outside the skin a printed press starts: the scripted press
/// (clients/haptic, --device press:X,Y,Z,TRAVEL) moves from its start point TRAVEL mm
/// along -y at 20 mm/s, so a start 10 mm out puts its first contact 0.5 s in.
constexpr double kPressStandoffMm = 10;
/// How far (mm) a printed press goes on past the bone point: the tip then reaches the
/// bone, whose surface the bone mask may place up to a voxel either side of the point.
constexpr double kPressBeyondBoneMm = 5;

/// Finds the landmarks (empty when none stands out). Spinous processes: per axial slice
/// the posterior-most bone within kSpinousHalfWidthMm of the body's left-right centre;
/// a tip is where that reaches a maximum along the body's long axis, standing out
/// kSpinousProminenceMm above the slices within kSpinousSpacingMm / 2 (the middle of the
/// run of slices that reach as far back), at least kSpinousSpacingMm from the next tip,
/// with its whole window in the image. Either lies at most kMaxLandmarkDepthMm under the skin. Iliac crests: on each side, the bone beyond
/// kCrestLateralMm from the centre that the lowest slice holds (the pelvis), followed
/// slice by slice superiorly; its top is the last slice before a gap (where the ribs
/// would start). The skin point lies along +y (posterior), the side the scripted press comes from.
std::vector<SkinLandmark> find_landmarks(const Patient& p);
constexpr double kSpinousHalfWidthMm = 15;
constexpr double kSpinousProminenceMm = 3;
constexpr double kSpinousSpacingMm = 20;
constexpr double kCrestLateralMm = 60;
/// The deepest a palpable landmark lies under the skin (mm): a spinous process tip about
/// 8 cm in obese adults, an iliac crest seen from the back a little more; deeper
/// "landmarks" are the sacrum through the buttocks, or bone seen through the belly.
constexpr double kMaxLandmarkDepthMm = 100;

/// The press argument that starts at `l.press_start_mm` and goes `l.press_travel_mm`:
/// "press:X,Y,Z,TRAVEL" (mm, one decimal).
std::string press_argument(const SkinLandmark& l);

}  // namespace palpsim
