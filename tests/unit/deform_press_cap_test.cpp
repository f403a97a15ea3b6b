// Where bone stops the fingertip (server/deform/press_cap.h): the elastic model's press
// held at (1 - f) T under the skin point, T the tissue along the press to the bone, on
// the built-in phantom as prep makes it (2 mm voxels, A from its distance transform);
// the engine steps the held press, whose cells fold far less than the press taken on
// into bone.
#include <catch2/catch.hpp>

#include <cmath>
#include <cstdio>

#include "deform/engine.h"
#include "deform/press_cap.h"
#include "prep/phantom.h"
#include "support/deform_fixtures.h"
#include "support/phantom_press.h"
#include "support/prepared_phantom.h"

using namespace palpsim;
using namespace palpsim::deform;

namespace {

constexpr double kVoxelMm = 2.0;

// the phantom prepared once for the file's cases
const PatientPtr& phantom() {
  static const PatientPtr p = test::prepared_phantom(kVoxelMm);
  return p;
}

// L3's press of the accuracy studies (X 1 mm under the skin, straight above the spinous
// tip, along -y), at `depth_mm`
test::Press l3_press(double depth_mm) {
  test::Press p = test::spinous_press(PhantomGeometry{});
  p.contact.tip_mm = p.contact.skin_point_mm - Vec3{0, depth_mm, 0};
  return p;
}

DeformConfig elastic_config(double fraction) {
  DeformConfig c = test::preset_config(1);
  c.settings.relax_method = RelaxMethod::kElastic;
  c.settings.grab_radius_mm = 5;
  c.settings.voi_edge = 32;
  c.settings.backend = DeformBackendChoice::kCpu;
  c.settings.elastic.min_tissue_fraction = fraction;
  c.relax = c.invert = true;
  return c;
}

double depth_of(const DeformContact& c) { return norm(c.tip_mm - c.skin_point_mm); }

}  // namespace

TEST_CASE("the tissue along a press ends at the bone under it", "[press-cap]") {
  const test::Press p = l3_press(10);
  const PressTissue t = tissue_along_press(*phantom(), p.contact, 60);
  std::printf("L3: tissue along the press %.2f mm, the spinous tip %.2f mm under X\n", t.thickness_mm, p.bone_depth_mm);
  REQUIRE(t.bone);
  // the bone mask holds the voxels whose centre lies in bone, so its face is within a
  // voxel of the closed-form tip, and A's trilinear half-voxel level within half another
  CHECK(t.thickness_mm == Approx(p.bone_depth_mm).margin(1.5 * kVoxelMm));
  // bone beyond the distance searched is not found
  CHECK_FALSE(tissue_along_press(*phantom(), p.contact, 0.5 * p.bone_depth_mm).bone);
  // no direction, no tissue
  CHECK_FALSE(tissue_along_press(*phantom(), {p.contact.skin_point_mm, p.contact.skin_point_mm}, 60).bone);
}

TEST_CASE("an elastic press is held at (1 - f) T, along its own line, and only there", "[press-cap]") {
  const Patient& pt = *phantom();
  const double T = tissue_along_press(pt, l3_press(1).contact, 60).thickness_mm;
  for (const double f : {0.5, 0.3, 0.8}) {
    INFO("min_tissue_fraction " << f << ", T " << T << " mm");
    // shallower than (1 - f) T: as given, bit for bit (the accuracy studies' 10 mm press
    // over L3 is one at the default 0.5, so their figures stand)
    const DeformContact shallow = l3_press(0.9 * (1 - f) * T).contact;
    const DeformContact same = cap_press_at_bone(pt, shallow, f);
    CHECK(same.tip_mm == shallow.tip_mm);
    CHECK(same.skin_point_mm == shallow.skin_point_mm);
    // deeper, into the bone: held at (1 - f) T on the same line from the same X (1e-9 mm:
    // rounding of the scaling)
    const DeformContact deep = l3_press(T + 5).contact;
    const DeformContact held = cap_press_at_bone(pt, deep, f);
    CHECK(held.skin_point_mm == deep.skin_point_mm);
    CHECK(depth_of(held) == Approx((1 - f) * T).margin(1e-9));
    CHECK(norm(held.tip_mm - (deep.skin_point_mm + (deep.tip_mm - deep.skin_point_mm) * ((1 - f) * T / (T + 5)))) < 1e-9);
    // held again: where it was
    CHECK(norm(cap_press_at_bone(pt, held, f).tip_mm - held.tip_mm) < 1e-9);
  }
  const DeformContact accuracy = test::spinous_press(PhantomGeometry{}).contact;
  CHECK(cap_press_at_bone(pt, accuracy, 0.5).tip_mm == accuracy.tip_mm);
  // fraction 0: the model as it was, the press into bone as given
  const DeformContact deep = l3_press(T + 5).contact;
  CHECK(cap_press_at_bone(pt, deep, 0).tip_mm == deep.tip_mm);
  // the configuration decides: the elastic model's fraction, every other relaxation none
  CHECK(depth_of(capped_press(pt, elastic_config(0.5), deep)) == Approx(0.5 * T).margin(1e-9));
  DeformConfig multigrid = elastic_config(0.5);
  multigrid.settings.relax_method = RelaxMethod::kMultigrid;
  CHECK(capped_press(pt, multigrid, deep).tip_mm == deep.tip_mm);
}

TEST_CASE("the engine steps the held press: the same field, and far fewer folded cells than into bone",
          "[press-cap][elastic]") {
  const PatientPtr& pt = phantom();
  const double T = tissue_along_press(*pt, l3_press(1).contact, 60).thickness_mm;
  const DeformContact deep = l3_press(T + 3).contact;  // 3 mm into the spinous process
  DeformEngine held(pt, elastic_config(0.5));
  const DeformStats a = held.step(deep);
  DeformEngine at_cap(pt, elastic_config(0));
  const DeformStats b = at_cap.step(held.pressed(deep));
  DeformEngine into_bone(pt, elastic_config(0));
  const DeformStats c = into_bone.step(deep);
  std::printf("L3 pressed %.1f mm (T %.1f): held at %.1f mm %lld folded cells, force %.3f N; into bone %lld folded "
              "cells, force %.3f N\n",
              T + 3, T, depth_of(held.pressed(deep)), a.elastic.inverted_cells, norm(a.elastic.force_n),
              c.elastic.inverted_cells, norm(c.elastic.force_n));
  REQUIRE(a.elastic.contact);
  // the engine's step is the held contact's step: the same solve, bit for bit
  const std::vector<Vec3f>& ua = held.backend().displacement();
  const std::vector<Vec3f>& ub = at_cap.backend().displacement();
  REQUIRE(ua.size() == ub.size());
  bool same = true;
  for (std::size_t e = 0; e < ua.size(); ++e) same = same && ua[e] == ub[e];
  CHECK(same);
  CHECK(a.elastic.inverted_cells == b.elastic.inverted_cells);
  // pressed on into bone the skin is taken through the tissue to the sphere: many more
  // folds (48 against 348 on this 2 mm phantom when written; at most a quarter is checked)
  CHECK(a.elastic.inverted_cells * 4 <= c.elastic.inverted_cells);
  CHECK(c.elastic.inverted_cells > 0);
}
