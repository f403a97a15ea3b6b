// From a scene to a patient: load the CT (or generate the phantom), resample,
// masks, distance maps, F and its gradient; with a content-hashed cache.
#pragma once

#include <string>

#include "core/patient.h"
#include "core/scene.h"

namespace palpsim {

/// What preparing a patient did and cost (written as prep.json by palpsim-prep).
struct PrepReport {
  std::string json;          // the whole report as JSON (input geometry, grid, HU range, volumes, stage times)
  bool from_cache = false;   // the patient was read from the cache
  std::string cache_path;    // the cache entry used or written ("" when caching is off)
  double total_s = 0;        // wall time of the whole preparation
};

/// Prepares the scene's patient. Throws palpsim::Error naming the file and the
/// problem for bad input; never leaves a half-written cache entry behind.
PatientPtr prepare_patient(const Scene& scene, PrepReport* report = nullptr);

}  // namespace palpsim
