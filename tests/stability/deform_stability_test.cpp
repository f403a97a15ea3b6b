// Deformation over long runs: the paper's Table 2 at d = 30 and hundreds of steps
// with random contacts on a torso-like volume, every invariant checked each step.
#include <catch2/catch.hpp>

#include <random>

#include "deform/cpu_backend.h"
#include "deform/engine.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

TEST_CASE("chainmail reproduces Table 2 at d = 30 (p1: 280958, p2: 58898)") {
  const int d = 30, n = 4 * d + 5, c = n / 2;
  auto patient = make_soft_patient(n);
  for (int preset = 1; preset <= 2; ++preset) {
    DeformConfig cfg = preset_config(preset);
    cfg.settings.whole_volume = true;
    CpuDeformBackend b;
    b.bind(patient, cfg);
    const ChainMailStats st = b.chainmail(voxel_contact({c, c, c}, {0, 0, -d}));
    CHECK(st.moved == (preset == 1 ? 280958 : 58898));
    CHECK(st.sweeps == 2 * d);
    CHECK(st.converged);
  }
}

TEST_CASE("hundreds of random steps keep every invariant") {
  auto patient = make_torso_patient(64);
  std::mt19937 rng(1234);
  std::uniform_real_distribution<double> pos(2.0, 61.0), disp(-9.0, 9.0);
  for (int preset = 1; preset <= 2; ++preset) {
    DeformConfig cfg = preset_config(preset);
    cfg.settings.voi_edge = 32;
    cfg.settings.relax_iterations = 10;
    DeformEngine eng(patient, cfg);
    for (int s = 0; s < 150; ++s) {
      const Vec3 X{pos(rng), pos(rng), pos(rng)};
      const Vec3 x = X + Vec3{disp(rng), disp(rng), disp(rng)};
      const DeformStats st = eng.step({X, x});
      INFO("step " << s << " X " << X.x << "," << X.y << "," << X.z);
      REQUIRE(st.chainmail.converged);
      const Voi& voi = st.chainmail.voi;
      const auto u = eng.backend().displacement();
      REQUIRE(moved_bone_count(*patient, voi, u) == 0);
      for (const Vec3f& v : u) REQUIRE(is_finite(v));
      REQUIRE(std::isfinite(st.invert_residual_vox));
      // untangling off (the scenes' default): the field folds, and the inversion's cell
      // search still finds a source for every voxel within its 0.01 voxel; 0.05 is issue
      // 8's goal
      REQUIRE(st.invert_unresolved == 0);
      REQUIRE(st.invert_residual_vox < 0.05);
      if (s % 25 == 0) {
        // restrictions hold right after ChainMail (before relaxation changes the field),
        // up to float rounding of u_n + limit: a few ulps of 64 voxel (7.6e-6 each)
        eng.backend().chainmail({X, x});
        REQUIRE(max_restriction_violation(*patient, voi, eng.backend().displacement(), cfg.settings) <= 4 * 64 * 1.2e-7);
        eng.step({X, x});
        REQUIRE(changed_outside_voi(*patient, voi, eng.deformed_volume()) == 0);
      }
    }
    eng.reset();
    REQUIRE(eng.deformed_volume().data == patient->intensity.data);
  }
}
