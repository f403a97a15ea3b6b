// The press of the accuracy studies (palpsim-bench deform --accuracy and palpsim-bench
// accuracy) and the comparisons both make: the phantom with the spinous press, RMS of
// image differences and a field against its reference on the reference's VOI.
#pragma once

#include <cmath>
#include <utility>
#include <vector>

#include "bench/deform_runs.h"
#include "prep/phantom.h"
#include "tests/support/deform_fixtures.h"
#include "tests/support/phantom_press.h"

namespace palpsim::bench {

// the phantom at voxel_mm (deformation reads intensity and bone only; the body mask is
// for the multigrid prime's guess of the skin point) and the press on it
inline std::pair<PatientPtr, test::Press> phantom_press(double voxel_mm) {
  PhantomCt ct = make_phantom(voxel_mm);
  const test::Press press = test::spinous_press(ct.geometry);
  return {test::with_body_mask(test::patient_from_intensity(std::move(ct.hu), "phantom")), press};
}

// RMS of a - b (HU) over the voxels `use` accepts (all when it is empty)
inline double rms_diff(const std::vector<float>& a, const std::vector<float>& b, const std::vector<bool>& use = {}) {
  double sum = 0;
  long long n = 0;
  for (std::size_t e = 0; e < a.size(); ++e) {
    if (!use.empty() && !use[e]) continue;
    sum += double(a[e] - b[e]) * double(a[e] - b[e]);
    ++n;
  }
  return n ? std::sqrt(sum / double(n)) : 0;
}

// RMS and max |u - u_ref| over the reference's VOI, u = 0 outside its own (smaller) VOI
inline Diff diff_on_reference(const Voi& ref_voi, const std::vector<Vec3f>& u_ref, const Voi& voi, const std::vector<Vec3f>& u) {
  return field_diff(field_on(ref_voi, voi, u, true), u_ref);
}

}  // namespace palpsim::bench
