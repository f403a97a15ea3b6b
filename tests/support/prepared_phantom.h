// The built-in phantom through the real preparation pipeline, for the tests that check
// what prep makes of it and those that draw it.
#pragma once

#include "prep/prepare.h"

namespace palpsim::test {

/// The built-in phantom prepared at `voxel_mm` without the cache (each call prepares it anew).
inline PatientPtr prepared_phantom(double voxel_mm) {
  Scene s;
  s.name = "test phantom";
  s.use_phantom = true;
  s.phantom_voxel_mm = voxel_mm;
  s.prep.use_cache = false;
  return prepare_patient(s);
}

}  // namespace palpsim::test
