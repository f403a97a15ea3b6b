// Contrast-filled chambers and vessels: large smooth bright regions inside soft
// tissue that a bone threshold takes for bone. Found, reported and (prep.contrast =
// "tissue") left out of the bone mask. Plain C++ on the project's own types.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/volume.h"
#include "prep/pipeline.h"

namespace palpsim {

/// One bright region: its volume, place and why it is not bone.
struct ContrastRegion {
  double volume_ml = 0;       // voxels of the region (ml)
  Vec3 centroid_mm;           // LPS (mm)
  double mean_hu = 0;         // mean value of its core (HU, or image units)
  double sd_hu = 0;           // spread of its core's values (HU)
  double shell_fraction = 0;  // of its outer layer, the fraction brighter than its core by kShellContrastHu
  double bone_ml = 0;         // of it, what the bone mask held (ml)
};

/// The value (HU) from which a region counts as bright: the bone mask's cancellous
/// level (a cavity that bright enclosed by bone is filled as bone), but no more than
/// 100 HU below its low threshold.
double contrast_level(const BoneThresholds& t);

/// Bright voxels (at or above contrast_level) that hold a core, kContrastCoreMm
/// in from the nearest darker voxel (thick, so not cortex or a rib), grown back from it
/// within the bright voxels; a region of at least kMinContrastMl is contrast when its
/// core is homogeneous (spread at most
/// kMaxContrastSdHu), its outer layer has no cortex (at most kMaxShellFraction of it
/// brighter than the core by kShellContrastHu) and its centroid lies outside the spine
/// column (farther than kColumnRadiusMm from its axis, or beyond its ends). Blood with
/// contrast varies by the scanner's noise (10-40 HU); cancellous bone by 60-200 HU in
/// the shared scans, and its cortex shows in the outer layer.
constexpr double kContrastCoreMm = 4;
constexpr double kMinContrastMl = 5;
constexpr double kMaxContrastSdHu = 50;
constexpr double kShellContrastHu = 150;
constexpr double kMaxShellFraction = 0.1;
constexpr double kColumnRadiusMm = 25;

/// The contrast regions of `image` inside `body` (as ContrastRegion describes), largest
/// first; `regions`, when given, gets 1 on their voxels. `t` are the bone mask's
/// thresholds, `bone` the mask (for ContrastRegion::bone_ml), `column` the spine.
std::vector<ContrastRegion> find_contrast_regions(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                                  const Volume<std::uint8_t>& bone, const BoneThresholds& t,
                                                  const SpineColumn& column, Volume<std::uint8_t>* regions = nullptr,
                                                  int threads = 0);

/// prep.json's list of regions: [{"volume_ml", "centroid_mm", "mean_hu", "sd_hu",
/// "shell_fraction", "bone_ml"}, ...].
std::string contrast_regions_json(const std::vector<ContrastRegion>& regions);

}  // namespace palpsim
