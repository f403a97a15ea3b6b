// From a scene to a patient: load the CT (or generate the phantom), resample,
// masks, distance maps, F and its gradient; with a content-hashed cache.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "core/path_policy.h"
#include "core/patient.h"
#include "core/scene.h"
#include "prep/contrast.h"
#include "prep/field_of_view.h"
#include "prep/pipeline.h"

namespace palpsim {

/// What preparing a patient did and cost (written as prep.json by palpsim-prep).
struct PrepReport {
  std::string json;          // the whole report as JSON (input geometry, grid, HU range, volumes, stage times)
  bool from_cache = false;   // the patient was read from the cache
  std::string cache_path;    // the cache entry used or written ("" when caching is off)
  double total_s = 0;        // wall time of the whole preparation
  std::string cache_key;     // the content key (SHA-256 hex; "" when caching is off)
  std::vector<std::pair<std::string, double>> stage_s;  // wall time of each stage (s), in order
  double body_ml = 0;        // volume of the body mask C
  double bone_ml = 0;        // volume of the bone mask
  BoneThresholds bone_thresholds;  // the bone mask's thresholds and why
  BoneSummary bone_summary;  // bone volume per region, whether a spine was found, warnings
  std::vector<ContrastRegion> contrast_regions;  // contrast-filled chambers and vessels, largest first
  double contrast_removed_ml = 0;  // bone left out of the mask in them (prep.contrast = "tissue")
  FieldOfView field_of_view;  // the faces where the image's border cuts the body
  BodyCheck body_check;      // the body mask's pieces and cross-section, warnings where it looks like no body
  std::string units = "HU";  // the image's values: "HU", or "image units" for an image not in HU
  /// Lines for a reader at a glance (the preview's caption): thresholds, bone per region, warnings.
  std::vector<std::string> summary_lines() const;
};

/// Prepares the scene's patient. Throws palpsim::Error naming the file and the
/// problem for bad input; never leaves a half-written cache entry behind. Every CT file
/// is opened through `files` (read_ct_info says how; nullptr: the CT's own folder).
PatientPtr prepare_patient(const Scene& scene, PrepReport* report = nullptr, const PathPolicy* files = nullptr);

/// Builds a patient from an image already in memory (HU, or image units with
/// both prep thresholds set): resampling, masks, distance maps, F and grad F.
/// No cache, no file I/O; `source` names it. Appends stage times to
/// report->stage_s and sets body_ml, bone_ml, bone_thresholds, bone_summary, contrast_regions,
/// contrast_removed_ml, field_of_view and
/// body_check (naming values in report->units). Throws palpsim::Error for an
/// all-air image or one without a body.
PatientPtr build_patient(const Volume<float>& image, const Scene& scene, const std::string& source,
                         PrepReport* report = nullptr);

/// Refuses (palpsim::Error naming `what` and the scene fields prep.air_threshold
/// and prep.bone_threshold) an image that cannot be in Hounsfield units: unsigned
/// 8-bit data, or a value range no CT has (no air below -500 HU, or values outside
/// -32768..32767), unless the scene set both thresholds in the image's own units.
void check_hounsfield(const std::string& what, const std::string& pixel_type, double min_value, double max_value,
                      const PrepSettings& prep);

}  // namespace palpsim
