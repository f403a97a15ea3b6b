// The preparation stages on synthetic volumes with known geometry: resampling,
// body mask (table, gas, cut airways, arms, border), bone mask, eq. 1 and grad F.
#include <catch2/catch.hpp>

#include <cmath>

#include "core/error.h"
#include "prep/distance.h"
#include "prep/pipeline.h"
#include "prep/prepare.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

Grid make_grid(Vec3i size, Vec3 spacing) {
  Grid g;
  g.size = size;
  g.spacing_mm = spacing;
  return g;
}

}  // namespace

TEST_CASE("resampling keeps origin and direction and interpolates linearly") {
  Grid in = make_grid({11, 7, 5}, {1.0, 2.0, 3.0});
  in.origin_mm = {10, -20, 5};
  in.direction = {0, 1, 0, -1, 0, 0, 0, 0, 1};  // rotated 90 degrees about S
  Volume<float> v(in);
  // a linear ramp along physical x: linear interpolation reproduces it exactly
  for (int k = 0; k < 5; ++k)
    for (int j = 0; j < 7; ++j)
      for (int i = 0; i < 11; ++i) v.at(i, j, k) = float(in.to_physical(Vec3{double(i), double(j), double(k)}).x);
  CHECK(patient_spacing_mm(in, 0) == 1.0);
  const Grid out = isotropic_grid(in, 0.5);
  CHECK(out.origin_mm == in.origin_mm);
  CHECK(out.direction == in.direction);
  CHECK(out.size == Vec3i{21, 25, 25});  // centres 0..10 mm, 0..12 mm, 0..12 mm at 0.5 mm
  const auto r = resample_linear(v, out, -1024);
  for (int k = 0; k < out.size.z; k += 3)
    for (int j = 0; j < out.size.y; j += 2)
      for (int i = 0; i < out.size.x; ++i)
        // float storage of mm values near 30: 1e-4 mm
        CHECK(r.at(i, j, k) == Approx(out.to_physical(Vec3{double(i), double(j), double(k)}).x).margin(1e-4));
}

TEST_CASE("the automatic spacing is the smallest input spacing clamped to 0.5-2 mm") {
  CHECK(patient_spacing_mm(make_grid({2, 2, 2}, {0.3, 0.4, 1}), 0) == 0.5);
  CHECK(patient_spacing_mm(make_grid({2, 2, 2}, {0.977, 0.977, 2}), 0) == Approx(0.977));
  CHECK(patient_spacing_mm(make_grid({2, 2, 2}, {3, 3, 3}), 0) == 2.0);
  CHECK(patient_spacing_mm(make_grid({2, 2, 2}, {3, 3, 3}), 1.5) == 1.5);
}

TEST_CASE("body mask: table cut off, gas and cut airways inside, arm kept, body at the border") {
  const Grid g = make_grid({150, 100, 40}, {1, 1, 1});
  Volume<float> v(g, -1000);
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 100; ++j)
      for (int i = 0; i < 150; ++i) {
        const double x = i - 50, y = j - 50;
        float hu = -1000;
        if ((x / 40) * (x / 40) + (y / 30) * (y / 30) <= 1) hu = 40;        // torso
        if (std::hypot(x + 15, y) <= 6) hu = -1000;                          // gas pocket (a tube along z)
        if (std::hypot(x - 10, y + 10) <= 4) hu = -1000;                     // airway cut by both end slices
        if (std::hypot(i - 120.0, y) <= 20) hu = 40;                        // arm, 10 mm apart from the torso
        if (j >= 81 && j <= 83) hu = 300;                                   // table shell, 3 mm, touching the torso at x = 0
        if (i <= 2 && j >= 40 && j <= 60) hu = 40;                          // tissue touching the volume border
        v.at(i, j, k) = hu;
      }
  // join the tissue at the border to the torso so it is part of the body
  for (int k = 0; k < 40; ++k)
    for (int i = 0; i <= 12; ++i)
      for (int j = 44; j <= 56; ++j) v.at(i, j, k) = 40;
  const auto C = body_mask(v, -400);
  const int k = 20;
  CHECK(C.at(50, 50, k) == 1);   // torso centre
  CHECK(C.at(35, 50, k) == 1);   // gas pocket
  CHECK(C.at(60, 40, k) == 1);   // airway, also in the first and last slice
  CHECK(C.at(60, 40, 0) == 1);
  CHECK(C.at(60, 40, 39) == 1);
  CHECK(C.at(120, 50, k) == 1);  // arm
  CHECK(C.at(0, 50, k) == 1);    // body touching the volume's border
  CHECK(C.at(5, 79, k) == 0);    // table far from the body
  // the table beside the torso: 10 mm from the torso's 5 mm-eroded core, beyond the
  // opening radius plus the 1.5-voxel margin (6.5 mm); only its contact line may stay
  CHECK(C.at(30, 82, k) == 0);
  CHECK(C.at(70, 82, k) == 0);
  CHECK(C.at(95, 50, k) == 0);   // the air between arm and torso
  CHECK(C.at(110, 5, k) == 0);   // outside air
  CHECK(C.at(50, 95, k) == 0);   // air below the table
  CHECK(C.at(50, 80, k) == 1);   // the torso's own bottom edge
}

TEST_CASE("bone mask fills a cortical tube's marrow, not a canal of soft tissue; small pieces go") {
  const Grid g = make_grid({80, 80, 30}, {1, 1, 1});
  Volume<float> v(g, 40);
  Volume<std::uint8_t> body(g, 1);
  for (int k = 0; k < 30; ++k)
    for (int j = 0; j < 80; ++j)
      for (int i = 0; i < 80; ++i) {
        const double rb = std::hypot(i - 25.0, j - 40.0), rc = std::hypot(i - 55.0, j - 40.0);
        if (rb <= 10) v.at(i, j, k) = rb >= 8 ? 900.0f : 150.0f;  // bone with 150 HU cancellous interior
        if (rc <= 10) v.at(i, j, k) = rc >= 8 ? 900.0f : 15.0f;   // ring around a canal of CSF
      }
  v.at(70, 10, 15) = 900;  // a 1-voxel calcification
  // a plain 200 HU threshold (an explicit scene value): the marrow comes in by the fill
  // alone (automatic thresholds would take it in by hysteresis; prep_bone_test.cpp)
  PrepSettings prep;
  prep.bone_threshold_set = true;
  const auto bone = bone_mask(v, body, prep, 6.0);
  CHECK(bone.at(25, 40, 15) == 1);  // the marrow is bone
  CHECK(bone.at(25, 40, 0) == 1);   // also where the tube leaves the volume
  CHECK(bone.at(33, 40, 15) == 1);  // the cortex
  CHECK(bone.at(55, 40, 15) == 0);  // the canal is not
  CHECK(bone.at(64, 40, 15) == 1);
  CHECK(bone.at(70, 10, 15) == 0);  // below bone_min_volume_ml
  CHECK(bone.at(5, 5, 15) == 0);
  prep.bone_fill_holes = false;
  const auto shell = bone_mask(v, body, prep, 6.0);
  CHECK(shell.at(25, 40, 15) == 0);
}

TEST_CASE("F follows eq. 1 at every voxel, is 0 outside the body, and grad F points away from the skin") {
  Scene scene;
  scene.prep.spacing_mm = 1.0;
  const auto v = synthetic_torso({100, 70, 24}, {1.2, 1.2, 2.5});
  PrepReport r;
  const PatientPtr p = build_patient(v, scene, "synthetic", &r);
  REQUIRE(p->has_bone);
  const auto& f = scene.force_image;
  std::size_t inside = 0;
  for (std::size_t i = 0; i < p->grid.count(); ++i) {
    const double C = p->body.data[i], A = p->dist_bone_mm.data[i], B = p->dist_skin_mm.data[i];
    const double expect = f.alpha * C / (f.beta + A) + f.gamma * B;
    // float storage: 1e-5 relative
    REQUIRE(p->force.data[i] == Approx(expect).epsilon(1e-5).margin(1e-6));
    if (!C) {
      REQUIRE(p->force.data[i] == 0);
      REQUIRE(B == 0);
    }
    inside += C != 0;
  }
  CHECK(inside > 0);
  CHECK(r.body_ml == Approx(double(inside) * 1e-3));
  // every Patient member lives on the one grid
  for (const Grid* gg : {&p->intensity.grid, &p->body.grid, &p->bone.grid, &p->dist_bone_mm.grid,
                         &p->dist_skin_mm.grid, &p->force.grid, &p->grad_force.grid})
    CHECK(gg->same_geometry(p->grid));
  // B grows with depth: on the left flank, under the skin, F's gradient points inward (+x)
  const Vec3 flank = p->grid.to_index(Vec3{-55, 0, 30});
  const Vec3f gr = p->grad_force.at(int(std::lround(flank.x)), int(std::lround(flank.y)), int(std::lround(flank.z)));
  CHECK(gr.x > 0);
  // bone: A = 0 and F = alpha/beta
  const Vec3 marrow = p->grid.to_index(Vec3{0, 15, 30});
  const int mi = int(std::lround(marrow.x)), mj = int(std::lround(marrow.y)), mk = int(std::lround(marrow.z));
  CHECK(p->bone.at(mi, mj, mk) == 1);
  CHECK(p->force.at(mi, mj, mk) == Approx(f.alpha / f.beta + f.gamma * p->dist_skin_mm.at(mi, mj, mk)));
}

TEST_CASE("without bone A is infinite and F = gamma * B") {
  Scene scene;
  auto v = synthetic_torso({60, 50, 10}, {2, 2, 2});
  for (auto& x : v.data) x = std::min(x, 40.0f);  // no bone
  const PatientPtr p = build_patient(v, scene, "no bone");
  CHECK_FALSE(p->has_bone);
  for (std::size_t i = 0; i < p->grid.count(); ++i) {
    REQUIRE(std::isinf(p->dist_bone_mm.data[i]));
    REQUIRE(p->force.data[i] == Approx(scene.force_image.gamma * p->dist_skin_mm.data[i]));
  }
}

TEST_CASE("gradient of a linear field is exact in physical axes, with a rotated grid") {
  Grid g = make_grid({8, 9, 10}, {0.5, 0.5, 0.5});
  g.direction = {0, -1, 0, 1, 0, 0, 0, 0, 1};
  Volume<float> f(g);
  const Vec3 w{0.3, -0.7, 0.2};
  for (int k = 0; k < 10; ++k)
    for (int j = 0; j < 9; ++j)
      for (int i = 0; i < 8; ++i) f.at(i, j, k) = float(dot(w, g.to_physical(Vec3{double(i), double(j), double(k)})));
  const auto gr = gradient_physical(f);
  for (const auto& v : gr.data) {
    // float rounding of values up to ~5: 1e-4
    REQUIRE(v.x == Approx(w.x).margin(1e-4));
    REQUIRE(v.y == Approx(w.y).margin(1e-4));
    REQUIRE(v.z == Approx(w.z).margin(1e-4));
  }
}

TEST_CASE("prep.body_opening_mm and prep.body_min_part_ml decide what thin or small parts stay") {
  const Grid g = make_grid({80, 60, 12}, {1, 1, 1});
  Volume<float> v(g, -1000);
  for (int k = 0; k < 12; ++k)
    for (int j = 0; j < 60; ++j)
      for (int i = 0; i < 80; ++i) {
        if (std::hypot(i - 30.0, j - 30.0) <= 20) v.at(i, j, k) = 40;  // torso
        if (i >= 60 && i <= 62 && j >= 10 && j <= 50) v.at(i, j, k) = 300;  // a 3 mm plate apart from it
      }
  // the default opening (5 mm) removes the plate; without opening it is a body part,
  // kept when body_min_part_ml allows its 1.5 ml (3 x 41 x 12 mm)
  CHECK(body_mask(v, -400).at(61, 30, 6) == 0);
  CHECK(body_mask(v, -400, 0.0, 0.1).at(61, 30, 6) == 1);
  CHECK(body_mask(v, -400, 0.0, 20).at(61, 30, 6) == 0);
  CHECK(body_mask(v, -400, 0.0, 20).at(30, 30, 6) == 1);
}
