// Backend choice by name and the validating wrapper's refusals.
#include <catch2/catch.hpp>

#include "core/error.h"
#include "deform/cpu_backend.h"
#include "deform/engine.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {
std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST_CASE("backends are chosen by name; an unavailable cuda says why") {
  CHECK(make_deform_backend("cpu")->name() == "cpu");
  CHECK(error_of([] { make_deform_backend("gpu"); }).find("\"auto\", \"cpu\" or \"cuda\"") != std::string::npos);
  std::string why, note;
  const bool have_cuda = cuda_deform_available(&why);
  CHECK_FALSE(why.empty());
  auto a = make_deform_backend("auto", &note);
  CHECK(a->name() == (have_cuda ? "cuda" : "cpu"));
  CHECK(note.find(a->name()) != std::string::npos);
  if (!have_cuda) {
    const std::string e = error_of([] { make_deform_backend("cuda"); });
    CHECK(e.find("unavailable") != std::string::npos);
    CHECK(e.find(why) != std::string::npos);
  }
}

TEST_CASE("bad settings and contacts are refused with the field named") {
  auto patient = make_soft_patient(16);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 8;
  CpuDeformBackend b;
  CHECK(error_of([&] { b.chainmail(voxel_contact({8, 8, 8}, {1, 0, 0})); }).find("before bind") != std::string::npos);
  DeformConfig bad = cfg;
  bad.settings.min_dist = 1.5;
  CHECK(error_of([&] { b.bind(patient, bad); }).find("deform.min_dist") != std::string::npos);
  bad = cfg;
  bad.settings.material_width = 0;
  CHECK(error_of([&] { b.bind(patient, bad); }).find("deform.material_width") != std::string::npos);
  b.bind(patient, cfg);
  CHECK(error_of([&] { b.relax(); }).find("before chainmail") != std::string::npos);
  CHECK(error_of([&] { b.chainmail({Vec3(40, 8, 8), Vec3(8, 8, 8)}); }).find("skin_point_mm (X)") != std::string::npos);
  CHECK(error_of([&] { b.chainmail({Vec3(8, 8, 8), Vec3(8, NAN, 8)}); }).find("tip_mm (x) is not finite") !=
        std::string::npos);
  // after a refused contact the backend still works
  CHECK(b.chainmail(voxel_contact({8, 8, 8}, {1, 0, 0})).converged);
  CHECK(error_of([&] { b.set_displacement(std::vector<Vec3f>(3)); }).find("got 3 values") != std::string::npos);
}

TEST_CASE("DeformConfig::from_scene takes Deform{}, prep's bone threshold and the effects") {
  Scene s;
  s.deform.voi_edge = 96;
  s.prep.bone_threshold = 250;
  s.effects.relaxation = false;
  s.effects.inversion = true;
  const DeformConfig c = DeformConfig::from_scene(s);
  CHECK(c.settings.voi_edge == 96);
  CHECK(c.bone_threshold == 250);
  CHECK_FALSE(c.relax);
  CHECK(c.invert);
  // the threshold prep chose for the patient, unless the scene set one explicitly
  Patient p;
  CHECK(DeformConfig::from_scene(s, &p).bone_threshold == 250);  // prep chose none (NaN)
  p.bone_threshold_hu = 137;
  CHECK(DeformConfig::from_scene(s, &p).bone_threshold == 137);
  s.prep.bone_threshold_set = true;
  CHECK(DeformConfig::from_scene(s, &p).bone_threshold == 250);
}
