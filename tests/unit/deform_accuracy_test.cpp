// The invariant behind the relaxation row of `palpsim-bench deform --accuracy`: more
// relaxation iterations never move the displacement field away from the relaxed
// limit. Each update is u' = M u with M's rows non-negative and summing to at most 1
// (relax_step * m <= 1/6; held elements are identity rows), and the limit u* = M u*,
// so the error e' = M e never grows in the max norm.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

#include "deform/cpu_backend.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

// the largest |a - b| over the field's components (voxel)
double max_norm(const std::vector<Vec3f>& a, const std::vector<Vec3f>& b) {
  double m = 0;
  for (std::size_t e = 0; e < a.size(); ++e)
    for (int c = 0; c < 3; ++c) m = std::max(m, std::fabs(double(a[e][c]) - double(b[e][c])));
  return m;
}

// the field after ChainMail and `iterations` relaxation iterations
std::vector<Vec3f> relaxed(const PatientPtr& p, DeformConfig cfg, const DeformContact& c, int iterations) {
  cfg.settings.relax_iterations = iterations;
  CpuDeformBackend b;
  b.bind(p, cfg);
  b.chainmail(c);
  b.relax();
  return b.displacement();
}

}  // namespace

TEST_CASE("more relaxation iterations never increase the max-norm distance to the relaxed limit") {
  // a torso with bone (held still) and soft tissue, pressed 3 voxels in and 1 along
  const int n = 24;
  auto patient = make_torso_patient(n);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = n;
  cfg.invert = false;
  const Vec3i grab{8, 9, 12};
  REQUIRE(patient->bone.at(grab.x, grab.y, grab.z) == 0);
  REQUIRE(patient->intensity.at(grab.x, grab.y, grab.z) > kAirHu);
  const DeformContact contact = voxel_contact(grab, {0, 3, 1});

  // the limit: 6000 iterations; the slowest mode of a 24-voxel box decays by about
  // exp(-6000 * 0.15 * 3 * (pi / 25)^2) ~ 1e-18, so 4000 and 6000 agree to float rounding
  const auto limit = relaxed(patient, cfg, contact, 6000);
  REQUIRE(max_norm(limit, relaxed(patient, cfg, contact, 4000)) < 1e-6);

  // one iteration per relax() call: the distance must never grow. 1e-5 voxel covers
  // float rounding of the six-neighbour sums (values up to 3 voxel, ~3e-7 per update,
  // accumulated over the iterations) and the limit's own 1e-6
  cfg.settings.relax_iterations = 1;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  b.chainmail(contact);
  double prev = max_norm(b.displacement(), limit);
  const double first = prev;
  INFO("distance before relaxation " << first << " voxel");
  REQUIRE(first > 0.3);  // ChainMail's field is far from the relaxed one: the check means something
  for (int it = 1; it <= 300; ++it) {
    b.relax();
    const double d = max_norm(b.displacement(), limit);
    INFO("iteration " << it << ": " << d << " voxel, previous " << prev);
    REQUIRE(d <= prev + 1e-5);
    prev = d;
  }
  // and it does converge: after 300 iterations the distance has at least halved
  CHECK(prev < 0.5 * first);
}
