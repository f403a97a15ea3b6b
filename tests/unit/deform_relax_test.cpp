// Relaxation and inversion on the CPU reference, and the Fig. 4 cases end to end.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

#include "core/error.h"
#include "deform/cpu_backend.h"
#include "deform/engine.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;
using palpsim::deform::invert_point;
using palpsim::deform::kInvertResolvedVox;
using palpsim::deform::kInvertSearchVox;
using palpsim::deform::trilinear;

TEST_CASE("relaxation keeps bone and the grabbed element still and obeys the maximum principle") {
  auto patient = make_cube_patient(40, 16, 3);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 40;
  cfg.settings.relax_iterations = 30;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  const ChainMailStats st = b.chainmail(voxel_contact({20, 20, 20}, {4, -3, 2}));
  const auto before = b.displacement();
  b.relax();
  const auto after = b.displacement();
  CHECK(moved_bone_count(*patient, st.voi, after) == 0);
  const Vec3i g = st.grabbed_vox - st.voi.lo;
  CHECK(after[st.voi.index(g.x, g.y, g.z)] == before[st.voi.index(g.x, g.y, g.z)]);
  // with a stable step each update is a convex combination: no component leaves the
  // range it had (1e-5 voxel: float rounding of sums of six values up to 4 voxels)
  for (int a = 0; a < 3; ++a) {
    float lo = 0, hi = 0, lo2 = 0, hi2 = 0;
    for (std::size_t e = 0; e < before.size(); ++e) {
      lo = std::min(lo, before[e][a]);
      hi = std::max(hi, before[e][a]);
      lo2 = std::min(lo2, after[e][a]);
      hi2 = std::max(hi2, after[e][a]);
    }
    CHECK(lo2 >= lo - 1e-5f);
    CHECK(hi2 <= hi + 1e-5f);
  }
  CHECK(roughness(st.voi, after) < roughness(st.voi, before));
}

TEST_CASE("relaxation updating only the elements ChainMail's field can reach equals relaxing every element") {
  // the same ChainMail field relaxed as it came from ChainMail (the steps skip the
  // elements beyond its sweeps plus the steps so far, deform::relax_reach) and set by
  // hand (its extent unknown: every element updated); the skipped elements are 0 and
  // stay 0, so the fields must agree to the bit, after one relaxation and after a second
  auto torso = make_torso_patient(64);
  int skipping = 0;  // presses whose first relaxation leaves some element beyond its reach
  for (const ReachPress& r : reach_presses()) {
    INFO(r.name);
    CpuDeformBackend reach, every;
    reach.bind(torso, r.cfg);
    every.bind(torso, r.cfg);
    const ChainMailStats st = reach.chainmail(r.contact);
    REQUIRE(st.moved > 0);
    REQUIRE(st.converged);
    every.chainmail(r.contact);
    every.set_displacement(reach.displacement());
    for (int round = 0; round < 2; ++round) {
      reach.relax();
      every.relax();
      CHECK(reach.displacement() == every.displacement());
    }
    // the reach skips work: some element of the VOI lies beyond the first step's reach
    const Vec3i g = st.grabbed_vox - st.voi.lo;
    const int far = std::max({g.x, st.voi.size.x - 1 - g.x}) + std::max({g.y, st.voi.size.y - 1 - g.y}) +
                    std::max({g.z, st.voi.size.z - 1 - g.z});
    std::printf("relaxation reach, %s: %d sweeps, the VOI's farthest element %d steps away\n", r.name, st.sweeps, far);
    skipping += st.sweeps + r.cfg.settings.relax_iterations < far;
  }
  CHECK(skipping >= 3);
}

TEST_CASE("a relax_step above the stable limit is refused with the limit in the message") {
  auto patient = make_soft_patient(16);
  DeformConfig cfg = preset_config(1);
  cfg.settings.relax_step = 0.2;
  CpuDeformBackend b;
  try {
    b.bind(patient, cfg);
    FAIL("bind accepted relax_step 0.2");
  } catch (const Error& e) {
    CHECK(std::string(e.what()).find("relax_step") != std::string::npos);
    CHECK(std::string(e.what()).find("0.166667") != std::string::npos);
  }
  cfg.settings.relax_step = 1.0 / 6.0;  // the limit itself is stable
  CHECK_NOTHROW(b.bind(patient, cfg));
}

TEST_CASE("inversion recovers a translation of a linear ramp exactly inside the VOI") {
  // I is linear, so trilinear sampling is exact and J(y) = I(y - t)
  auto patient = make_patient({32, 32, 32}, [](int i, int j, int k) { return 3.0f * i - 2.0f * j + 0.5f * k; });
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  cfg.settings.invert_iterations = 4;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  const ChainMailStats st = b.chainmail(voxel_contact({16, 16, 16}, {0, 0, 0}));
  const Vec3f t{0.75f, -0.5f, 0.25f};
  b.set_displacement(std::vector<Vec3f>(std::size_t(st.voi.count()), t));
  b.invert();
  b.upload();
  const float* J = b.deformed_brick();
  // away from the VOI's faces (where u falls to 0 outside) the fixed point is y - t
  for (int k = 2; k < 30; ++k)
    for (int j = 2; j < 30; ++j)
      for (int i = 2; i < 30; ++i) {
        const float expect = 3.0f * (i - t.x) - 2.0f * (j - t.y) + 0.5f * (k - t.z);
        REQUIRE(std::fabs(J[st.voi.index(i, j, k)] - expect) < 1e-4f);  // float rounding of values up to ~100
      }
}

TEST_CASE("the inversion residual falls to rounding for a smooth displacement field") {
  // u_j = A sin(pi i/31) sin(pi j/31) sin(pi k/31), zero on the VOI's faces, with
  // A pi/31 = 0.405 < 1: the deformation is invertible everywhere
  auto patient = make_soft_patient(32);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  const ChainMailStats st = b.chainmail(voxel_contact({16, 16, 16}, {0, 0, 0}));
  std::vector<Vec3f> u(std::size_t(st.voi.count()));
  for (int k = 0; k < 32; ++k)
    for (int j = 0; j < 32; ++j)
      for (int i = 0; i < 32; ++i) {
        const float w = 3.14159265f / 31.0f;
        u[st.voi.index(i, j, k)] = Vec3f(0, 4.0f * std::sin(w * i) * std::sin(w * j) * std::sin(w * k), 0);
      }
  // Newton alone (invert_point): the largest residual over the VOI falls with every
  // doubling of the iterations until it reaches float rounding of positions up to 32 (ulp
  // 4e-6 voxel; 1e-5 allows a few ulps), then stays there
  const Voi& voi = st.voi;
  auto load_u = [&](int i, int j, int k) { return voi.contains(i, j, k) ? u[voi.index(i, j, k)] : Vec3f{0, 0, 0}; };
  double last = 1e9;
  for (int iters : {0, 2, 4, 8, 16}) {
    float worst = 0;
    long long above = 0;
    for (int k = 0; k < 32; ++k)
      for (int j = 0; j < 32; ++j)
        for (int i = 0; i < 32; ++i) {
          float r = 0;
          invert_point(load_u, Vec3f(float(i), float(j), float(k)), iters, r);
          worst = std::max(worst, r);
          above += r > kInvertResolvedVox;
        }
    INFO("Newton, iterations " << iters << ": residual " << worst << ", above 0.1 voxel " << above);
    if (iters >= 4) CHECK(above == 0);  // Newton: 0.1 voxel is reached in 2-3 steps
    if (iters == 0) CHECK(above > 0);   // without iterations the residual is |u(y)| up to 4 voxel
    CHECK((worst < last || worst <= 1e-5));
    last = worst;
  }
  CHECK(last < 1e-5);
  // the backend's inversion adds the cell search where Newton stays above
  // kInvertSearchVox: every voxel resolved from one iteration on (0 inverts nothing)
  for (int iters : {1, 2, 4, 8, 16}) {
    cfg.settings.invert_iterations = iters;
    b.bind(patient, cfg);
    b.chainmail(voxel_contact({16, 16, 16}, {0, 0, 0}));
    b.set_displacement(u);
    const InvertStats inv = b.invert();
    INFO("inversion, iterations " << iters << ": residual " << inv.max_residual_vox << ", unresolved " << inv.unresolved);
    CHECK(inv.unresolved == 0);
    CHECK(inv.max_residual_vox <= kInvertSearchVox);
    if (iters >= 8) CHECK(inv.max_residual_vox < 1e-5);  // Newton's own, as above
  }
}

TEST_CASE("the inversion's search visits each cell of a ring once") {
  // ring r holds exactly the offsets at Chebyshev distance r, each once, in
  // search_ring_size(r) indices (the order both backends share)
  for (int r = 0; r <= 6; ++r) {
    const int s = 2 * r + 1, n = palpsim::deform::search_ring_size(r);
    CHECK(n == s * s * s - (r > 0 ? (s - 2) * (s - 2) * (s - 2) : 0));
    std::vector<int> seen(std::size_t(s * s * s), 0);
    for (int idx = 0; idx < n; ++idx) {
      const Vec3i d = palpsim::deform::search_ring_cell(r, idx);
      INFO("ring " << r << " index " << idx << ": " << d.x << "," << d.y << "," << d.z);
      REQUIRE(std::max({std::abs(d.x), std::abs(d.y), std::abs(d.z)}) == r);
      ++seen[std::size_t(((d.z + r) * s + d.y + r) * s + d.x + r)];
    }
    long long twice = 0, once = 0;
    for (int v : seen) {
      twice += v > 1;
      once += v == 1;
    }
    CHECK(twice == 0);
    CHECK(once == n);
  }
}

TEST_CASE("the inversion converges where the fixed-point iteration of the paper cannot (a stretch over 2x)") {
  // a deformation along j only, p_j -> f(p_j) = 31 (0.1 t + 0.9 t^3), t = p_j / 31:
  // monotone (f' from 0.1 to 2.8), so invertible, and f(0) = 0, f(31) = 31; u = f(p) - p
  // has du/dj from -0.9 to 1.8: the fixed point p <- y - u(p) cannot converge where
  // |du/dj| > 1, Newton's steps converge everywhere
  auto f = [](float j) {
    const float t = j / 31.0f;
    return 31.0f * (0.1f * t + 0.9f * t * t * t);
  };
  auto load_u = [&](int i, int j, int k) {
    (void)i;
    (void)k;
    return (j < 0 || j > 31) ? Vec3f(0, 0, 0) : Vec3f(0, f(float(j)) - float(j), 0);
  };
  int fixed_point_failures = 0;
  for (float yj = 0.25f; yj < 31.0f; yj += 0.37f) {
    const Vec3f y(5.5f, yj, 7.25f);
    // the residual never grows with more iterations, and 8 reach 1e-3 voxel (the
    // piecewise-linear field between voxels: Newton lands on the exact cell in a few steps)
    float last = 1e9f;
    for (int it = 0; it <= 8; ++it) {
      float r = 0;
      invert_point(load_u, y, it, r);
      INFO("y_j " << yj << ", " << it << " iterations: residual " << r);
      CHECK(r <= last);
      last = r;
    }
    CHECK(last < 1e-3f);
    // the paper's iteration, for comparison (8 steps as its default)
    Vec3f p = y;
    for (int it = 0; it < 8; ++it) p = y - trilinear<Vec3f>(load_u, p);
    const Vec3f r = p + trilinear<Vec3f>(load_u, p) - y;
    fixed_point_failures += std::fabs(r.y) > kInvertResolvedVox;
  }
  INFO("points the fixed-point iteration leaves unresolved: " << fixed_point_failures);
  CHECK(fixed_point_failures > 0);
}

TEST_CASE("the paper's Fig. 4: soft cube and soft cube in bone, p1 and p2, 0/20/40 relaxation") {
  for (int shell : {0, 4})
    for (int preset = 1; preset <= 2; ++preset) {
      double rough_prev = 1e30;
      for (int iters : {0, 20, 40}) {
        INFO("bone shell " << shell << ", p" << preset << ", " << iters << " relaxation iterations");
        auto patient = make_cube_patient(48, 20, shell);
        DeformConfig cfg = preset_config(preset);
        cfg.settings.voi_edge = 40;
        cfg.settings.relax_iterations = iters;
        DeformEngine eng(patient, cfg);
        CHECK(eng.backend_name() == "cpu");
        // press into the cube's top face
        const DeformStats st = eng.step(voxel_contact({24, 24, 14}, {0, 0, 5}));
        CHECK(st.chainmail.converged);
        CHECK(st.chainmail.moved > 0);
        CHECK(st.relax_iterations == iters);
        const auto u = eng.backend().displacement();
        CHECK(moved_bone_count(*patient, st.chainmail.voi, u) == 0);
        const Volume<float> J = eng.deformed_volume();
        CHECK(changed_outside_voi(*patient, st.chainmail.voi, J) == 0);
        // bone stays put in the image too: u = 0 at a bone voxel makes p = y the fixed point
        long long bone_changed = 0;
        for (std::size_t e = 0; e < J.data.size(); ++e)
          if (patient->bone.data[e] && J.data[e] != patient->intensity.data[e]) ++bone_changed;
        CHECK(bone_changed == 0);
        const double rough = roughness(st.chainmail.voi, u);
        CHECK(rough < rough_prev);  // more relaxation, smoother field
        rough_prev = rough;
      }
    }
}

TEST_CASE("reset restores I exactly, and every step starts from the undeformed state") {
  auto patient = make_torso_patient(48);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  DeformEngine eng(patient, cfg);
  const DeformContact c = voxel_contact({24, 6, 24}, {1, 6, -1});
  const DeformStats a = eng.step(c);
  const std::vector<float> brick_a(eng.deformed_brick(), eng.deformed_brick() + a.chainmail.voi.count());
  CHECK(eng.deformed_volume().data != patient->intensity.data);
  eng.step(voxel_contact({20, 10, 30}, {-4, 3, 2}));
  // the same contact again gives the same J: nothing of the step between is left
  const DeformStats a2 = eng.step(c);
  CHECK(a2.chainmail.moved == a.chainmail.moved);
  CHECK(std::memcmp(brick_a.data(), eng.deformed_brick(), brick_a.size() * sizeof(float)) == 0);
  eng.reset();
  CHECK(eng.deformed_brick() == nullptr);
  CHECK(eng.deformed_volume().data == patient->intensity.data);
  for (const Vec3f& v : eng.backend().displacement()) REQUIRE(v == Vec3f(0, 0, 0));
}
