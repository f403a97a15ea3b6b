// The stability catalogue of issue 8, section 5, on the CPU: one TEST_CASE per named
// hard case, each running the force model's checks (stability_haptics.h) and the
// deformation's on the "cpu" backend (stability_deform.h). The same deformation cases
// run on "cuda" in catalogue_gpu_test.cpp (palpsim-gpu-stability-tests, label gpu), and
// the elastic model's (stability_elastic.h, tag [elastic]) in both.
// A failure prints the case, the backend and the seed; PALPSIM_STABILITY_SEED=<seed>
// reruns the same draws.
#include <catch2/catch.hpp>

#include <cfloat>
#include <chrono>
#include <cstdio>
#include <functional>
#include <limits>
#include <vector>

#include "deform/cpu_backend.h"
#include "stability/stability_deform.h"
#include "stability/stability_elastic.h"
#include "stability/stability_haptics.h"

using namespace palpsim;
using namespace palpsim::test;
using namespace palpsim::test::stability;

namespace {

constexpr const char* kExe = "palpsim-test-deform-stability";

Case make_case(const char* name) { return Case(name, "cpu", kExe); }

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// a tip moving in a straight line from a to b in `steps` poses, dt apart
void line(HapticRun& r, const Vec3& a, const Vec3& b, int steps, double dt = 1e-3) {
  for (int s = 0; s <= steps; ++s) r.pose(a + (b - a) * (double(s) / steps), dt);
}

}  // namespace

TEST_CASE("stability: tip inside bone") {
  Case c = make_case("tip inside bone");
  INFO(c.describe());
  {
    // the slab's bone block [24.5, 35.5]^2 x [14.5, 25.5] mm: random tips inside it,
    // fresh and continuing sessions, and a press from the skin straight through it
    HapticRun r(slab());
    for (int s = 0; s < 4000; ++s) {
      if (s % 50 == 0) r.reset();
      r.pose({c.uniform(24.5, 35.5), c.uniform(24.5, 35.5), c.uniform(14.5, 25.5)});
    }
    line(r, {30.2, 29.8, 45}, {30.2, 29.8, 0}, 450);
    r.finish();
    // F ~ alpha / beta = 33 mm in bone: k F = 8 N, so the clamp must have been working
    CHECK(r.clamped() > 1000);
    // the Fig. 4 situation: bone shell around soft tissue
    HapticRun e(enclosed_cube());
    for (int s = 0; s < 4000; ++s) {
      if (s % 50 == 0) e.reset();
      e.pose({c.uniform(9.5, 29.5), c.uniform(9.5, 29.5), c.uniform(9.5, 29.5)});
    }
    e.finish();
  }
  deform_tip_inside_bone(c);
}

TEST_CASE("stability: tip exactly on the skin") {
  Case c = make_case("tip exactly on the skin");
  INFO(c.describe());
  {
    const HapticPatient h = slab();
    HapticRun r(h);
    for (int s = 0; s < 2000; ++s) {
      // on the skin plane z = 39.5 mm above voxel centres: C samples exactly 0.5 (inside
      // by the model's rule) and B exactly h/2, so the depth is exactly 0 (weights 1 and
      // 1/2 are exact in binary)
      r.reset();
      const Vec3 tip{double(c.integer(0, 59)), double(c.integer(0, 59)), kSlabSkinZ};
      const ForceSample f = r.pose(tip);
      INFO("tip on the skin (" << tip.x << ", " << tip.y << ", " << tip.z << ")");
      REQUIRE(f.contact);
      REQUIRE(f.depth_mm == 0.0);
      // a nanometre above: outside, no force at all
      const ForceSample o = r.pose(tip + Vec3{0, 0, 1e-6});
      REQUIRE_FALSE(o.contact);
      // anywhere else on the plane the weights' rounding decides the tie (C = 0.5 +- 1e-16):
      // either way the depth is 0 up to that rounding
      r.reset();
      const Vec3 any{c.uniform(0, 59), c.uniform(0, 59), kSlabSkinZ};
      const ForceSample a = r.pose(any);
      INFO("tip on the skin (" << any.x << ", " << any.y << ", " << any.z << ")");
      REQUIRE(a.depth_mm <= 1e-12);
    }
    // sliding along the skin plane, and in and out across it by a hair
    r.reset();
    line(r, {2, 3, kSlabSkinZ}, {57, 55, kSlabSkinZ}, 3000);
    for (int s = 0; s < 3000; ++s) r.pose({10 + 0.01 * s, 30, kSlabSkinZ + (s % 2 ? 1e-9 : -1e-9)});
    r.finish();
    // on a curved skin: the sphere of radius 28 mm (the mask is voxelised around it)
    const auto sp = sphere_patient();
    HapticRun q({sp, [](const Vec3& x) { return norm(x - Vec3{32, 32, 32}) - 28.0; }, "sphere"});
    for (int s = 0; s < 3000; ++s) {
      const Vec3 d{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
      q.pose(Vec3{32, 32, 32} + d * (28.0 / std::max(norm(d), 1e-9)));
    }
    q.finish();
  }
  deform_on_skin(c);
}

TEST_CASE("stability: tip on a voxel corner") {
  Case c = make_case("tip on a voxel corner");
  INFO(c.describe());
  {
    // voxel corners (half-integer mm on these 1 mm grids): every trilinear weight 1/2
    HapticRun r(slab());
    for (int s = 0; s < 4000; ++s) {
      if (s % 20 == 0) r.reset();
      r.pose({c.integer(-1, 59) + 0.5, c.integer(-1, 59) + 0.5, c.integer(-1, 45) + 0.5});
    }
    r.finish();
    // the corner at the centre of a bone ball: grad F cancels there by symmetry
    const HapticPatient ball = corner_ball();
    HapticRun b(ball);
    const ForceSample f = b.pose({19.5, 19.5, 19.5});
    CHECK(f.contact);
    CHECK(is_finite(f.force_n));
    for (int s = 0; s < 4000; ++s) {
      if (s % 20 == 0) b.reset();
      b.pose({c.integer(0, 39) + 0.5, c.integer(0, 39) + 0.5, c.integer(0, 39) + 0.5});
    }
    b.finish();
  }
  deform_voxel_corner(c);
}

TEST_CASE("stability: tip on the volume border") {
  Case c = make_case("tip on the volume border");
  INFO(c.describe());
  {
    // the slab's body is cut by the grid's faces at -0.5 and 59.5 mm (x, y) and -0.5 (z)
    HapticRun r(slab());
    const double faces[] = {-0.5, 59.5};
    for (int s = 0; s < 6000; ++s) {
      if (s % 10 == 0) r.reset();
      Vec3 tip{c.uniform(-1, 60), c.uniform(-1, 60), c.uniform(-1, 42)};
      // one to three coordinates on a face, exactly or a hair either side
      const int n = 1 + s % 3;
      for (int k = 0; k < n; ++k) {
        const int a = c.integer(0, 2);
        const double hair = (s % 4 == 0) ? 0.0 : c.uniform(-1e-9, 1e-9);
        tip[a] = (a == 2 ? -0.5 : faces[c.integer(0, 1)]) + hair;
      }
      r.pose(tip);
    }
    // out through each face at depth 10 mm, 0.1 mm per pose: contact until the face,
    // exactly zero beyond
    r.reset();
    line(r, {5, 30, 29.5}, {-3, 30, 29.5}, 80);
    r.reset();
    line(r, {55, 30, 29.5}, {63, 30, 29.5}, 80);
    r.reset();
    line(r, {30, 4, 20}, {30, -4, 20}, 80);
    r.reset();
    line(r, {10, 10, 5}, {10, 10, -3}, 80);
    r.reset();
    line(r, {2, 2, 2}, {-2, -2, -2}, 80);  // through a corner of the grid
    r.finish();
  }
  deform_volume_border(c);
}

TEST_CASE("stability: flat plateaus of F (zero gradient)") {
  Case c = make_case("flat plateaus of F");
  INFO(c.describe());
  {
    const HapticPatient h = plateau_slab();
    const Patient& p = *h.patient;
    // the patient has both a flat plateau (grad F exactly 0) and a ramp
    long long flat = 0, ramp = 0;
    for (std::size_t n = 0; n < p.grid.count(); ++n)
      if (p.body.data[n]) (p.grad_force.data[n] == Vec3f(0, 0, 0) ? flat : ramp) += 1;
    INFO(flat << " body voxels with zero grad F, " << ramp << " with a gradient");
    REQUIRE(flat > 10000);
    REQUIRE(ramp > 1000);
    HapticRun r(h);
    // deep in the plateau a fresh session has no direction: no force, nothing divided by 0
    const ForceSample f0 = r.pose({30, 30, 10});
    REQUIRE(f0.contact);
    REQUIRE(norm(f0.force_n) == 0.0);
    // from the ramp (far from bone, just under the skin) down into the plateau: the last
    // good direction is kept, so the force stays on
    r.reset();
    line(r, {4, 4, 39}, {4, 4, 5}, 340);
    REQUIRE(r.state().has_direction);
    const ForceSample deep = r.pose({4, 4, 5});
    CHECK(norm(deep.force_n) > 0.0);
    // the scene's smallest min_gradient_norm (1e-12) on the same plateau
    HapticsSettings tiny;
    tiny.min_gradient_norm = 1e-12;
    HapticRun t(h, tiny);
    for (int s = 0; s < 6000; ++s) {
      if (s % 100 == 0) {
        r.reset();
        t.reset();
      }
      const Vec3 tip{c.uniform(-1, 60), c.uniform(-1, 60), c.uniform(-1, 42)};
      r.pose(tip);
      t.pose(tip);
    }
    r.finish();
    t.finish();
  }
  deform_flat_plateau(c);
}

TEST_CASE("stability: a 50 mm jump of the tip within 1 ms") {
  Case c = make_case("a 50 mm jump of the tip within 1 ms");
  INFO(c.describe());
  {
    // jumps of exactly 50 mm between random points (in and out of the body, into bone),
    // one pose 1 ms, 0.1 ms or 1 us after the other: the rate clamp bounds every change
    HapticRun r(slab());
    long long jumps = 0;
    for (int s = 0; s < 20000; ++s) {
      const Vec3 a{c.uniform(0, 59), c.uniform(0, 59), c.uniform(0, 45)};
      const Vec3 d{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
      const Vec3 b = a + d * (50.0 / std::max(norm(d), 1e-9));
      const double dt = s % 3 == 0 ? 1e-3 : (s % 3 == 1 ? 1e-4 : 1e-6);
      r.pose(a, 1e-3);
      r.pose(b, dt);
      ++jumps;
    }
    r.finish();
    CHECK(r.clamped() > 1000);  // the clamp had to act: the test is not vacuous
  }
  deform_jump_50mm(c);
}

TEST_CASE("stability: a displacement larger than the VOI") {
  Case c = make_case("a displacement larger than the VOI");
  deform_displacement_larger_than_voi(c);
}

TEST_CASE("stability: a VOI crossing the volume border") {
  Case c = make_case("a VOI crossing the volume border");
  deform_voi_crossing_border(c);
}

TEST_CASE("stability: soft tissue enclosed by bone (Fig. 4 cube)") {
  Case c = make_case("soft tissue enclosed by bone");
  INFO(c.describe());
  {
    HapticRun r(enclosed_cube());
    // presses from the skin through the shell into the enclosed tissue, along each axis
    for (int a = 0; a < 3; ++a) {
      Vec3 from{19.7, 19.3, 19.6}, to = from;
      from[a] = 39;
      to[a] = 19.5;
      r.reset();
      line(r, from, to, 195);
    }
    r.finish();
  }
  deform_enclosed_cube(c);
}

TEST_CASE("stability: relaxation at the stability limit") {
  Case c = make_case("relaxation at the stability limit");
  deform_relax_stability_limit(c);
  // the check must be able to fail: the same checkerboard relaxed with a step above the
  // limit (0.25, allowed only by calling the kernel directly) grows without bound
  INFO(c.describe());
  auto p = make_soft_patient(16);
  DeformConfig cfg = config(1, 16, 0);
  CpuDeformBackend b;
  b.bind(p, cfg);
  const ChainMailStats st = b.chainmail(voxel_contact({8, 8, 8}, {0, 0, 0}));
  deform::CpuState s;
  s.u.resize(std::size_t(st.voi.count()));
  s.u_next.resize(s.u.size());
  s.weight.resize(s.u.size());
  for (int k = 0; k < 16; ++k)
    for (int j = 0; j < 16; ++j)
      for (int i = 0; i < 16; ++i) s.u[std::size_t(st.voi.index(i, j, k))] = Vec3f((i + j + k) % 2 ? 1.f : -1.f, 0, 0);
  deform::relax_cpu(*p, st, 20, 0.25f, float(cfg.bone_threshold), 50.0f, s);
  CHECK(max_abs_component(s.u) > 100.0f);
}

#ifdef PALPSIM_STABILITY_PREP
TEST_CASE("stability: anisotropic input spacing (0.5 x 0.5 x 5 mm)") {
  Case c = make_case("anisotropic input spacing");
  INFO(c.describe());
  {
    const HapticPatient h = prep_anisotropic_patient();
    const Patient& p = *h.patient;
    INFO("prepared grid " << p.grid.size.x << " x " << p.grid.size.y << " x " << p.grid.size.z << " at "
                          << p.grid.spacing_mm.x << " mm");
    REQUIRE(p.grid.spacing_mm.x == 0.5);
    REQUIRE(p.grid.spacing_mm.z == 0.5);
    REQUIRE(p.has_bone);
    require_finite_patient(p);
    HapticRun r(h);
    poses_over_grid(r, p.grid, c, 20000);
    // along z, across the thick slices' interpolated steps, at 1 m/s through bone
    for (double y : {-6.0, 0.0, 4.0}) {
      r.reset();
      line(r, {0.3, y, -20}, {0.3, y, 20}, 40);
      r.reset();
      line(r, {0.3, y, -20}, {0.3, y, 20}, 160, 2.5e-4);
    }
    r.finish();
    CHECK(r.contacts() > 1000);
  }
  deform_anisotropic(c);
}

TEST_CASE("stability: extreme HU (-3024 and 30000)") {
  Case c = make_case("extreme HU");
  INFO(c.describe());
  {
    const HapticPatient h = prep_extreme_hu_patient();
    const Patient& p = *h.patient;
    REQUIRE(p.has_bone);
    require_finite_patient(p);
    HapticRun r(h);
    poses_over_grid(r, p.grid, c, 20000);
    r.finish();
    CHECK(r.contacts() > 1000);
  }
  deform_extreme_hu(c);
}
#else
TEST_CASE("stability: anisotropic input spacing (0.5 x 0.5 x 5 mm)") {
  Case c = make_case("anisotropic input spacing");
  std::printf("SKIPPED (prep part): this build has no palpsim_prep\n");
  deform_anisotropic(c);
}

TEST_CASE("stability: extreme HU (-3024 and 30000)") {
  Case c = make_case("extreme HU");
  std::printf("SKIPPED (prep part): this build has no palpsim_prep\n");
  deform_extreme_hu(c);
}
#endif

namespace {

// how far proxy and force strayed from the reference cycle, and where
struct Drift {
  double proxy_mm = 0, force_n = 0;
  long long at_pose = -1;
};

// `cycles` cycles of the closed path `tips` (one pose each, 1 ms apart); cycle 0 is the
// warm-up (a fresh session's friction memory decays as 0.2^n: below 1e-16 after 23
// poses), cycle 1 the reference; every later pose is compared with the reference pose
// of the same phase
Drift drift_run(HapticRun& r, const std::vector<Vec3>& tips, int cycles) {
  const std::size_t period = tips.size();
  std::vector<Vec3> ref_p(period), ref_f(period);
  Drift d;
  for (int cyc = 0; cyc < cycles; ++cyc)
    for (std::size_t ph = 0; ph < period; ++ph) {
      const ForceSample f = r.pose(tips[ph]);
      if (cyc == 1) {
        ref_p[ph] = f.proxy_mm;
        ref_f[ph] = f.force_n;
      } else if (cyc > 1) {
        const double dp = norm(f.proxy_mm - ref_p[ph]), df = norm(f.force_n - ref_f[ph]);
        if (dp > d.proxy_mm || df > d.force_n) d.at_pose = (long long)cyc * (long long)period + (long long)ph;
        d.proxy_mm = std::max(d.proxy_mm, dp);
        d.force_n = std::max(d.force_n, df);
      }
    }
  return d;
}

// no drift: the state contracts (friction keeps 0.2 of the previous proxy, the rate
// clamp only follows its target), so after the warm-up the poses repeat to rounding
// (~1e-14 mm at 30 mm); 1e-9 mm and 1e-9 N leave five orders of magnitude for rounding
// yet catch any accumulation (1e-15 per pose grows to 1e-9 over a million poses)
constexpr double kDriftProxyMm = 1e-9, kDriftForceN = 1e-9;

void require_no_drift(const char* what, const Drift& d, const HapticRun& r) {
  std::printf("%s: %lld poses, %lld in contact, %lld clamped; largest deviation from the first cycle: proxy %.3g mm, "
              "force %.3g N (pose %lld)\n",
              what, r.poses(), r.contacts(), r.clamped(), d.proxy_mm, d.force_n, d.at_pose);
  INFO(what << ": largest deviation from the first cycle: proxy " << d.proxy_mm << " mm, force " << d.force_n
            << " N at pose " << d.at_pose << " (tolerances " << kDriftProxyMm << " mm, " << kDriftForceN << " N)");
  CHECK(d.proxy_mm <= kDriftProxyMm);
  CHECK(d.force_n <= kDriftForceN);
}

}  // namespace

TEST_CASE("stability: a million haptic steps on one spot") {
  Case c = make_case("a million haptic steps on one spot");
  INFO(c.describe());
  const auto t0 = std::chrono::steady_clock::now();
  // held 9 mm under the skin, 5 mm above the bone block, with a hand's tremor: 1 um of
  // seeded jitter repeating every second (1000 poses), so the cycles are identical input
  std::vector<Vec3> tips(1000);
  for (Vec3& t : tips) t = Vec3{30.2, 29.7, 30.5} + Vec3{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)} * 1e-3;
  HapticRun r(slab());
  const Drift d = drift_run(r, tips, 1000);
  r.finish();
  REQUIRE(r.contacts() == 1000000);
  require_no_drift("one spot", d, r);
  std::printf("one spot: %.2f s for 1e6 poses\n", seconds_since(t0));
  deform_one_spot_repeated(c, 30);
}

TEST_CASE("stability: a million haptic steps along a closed path") {
  Case c = make_case("a million haptic steps along a closed path");
  INFO(c.describe());
  const auto t0 = std::chrono::steady_clock::now();
  const double two_pi = 6.283185307179586;
  {
    // a circle of radius 8 mm, 6 mm under the skin, over the edges of the bone block
    // (where grad F turns), once a second: 50 mm/s; 1000 cycles
    std::vector<Vec3> tips(1000);
    for (std::size_t n = 0; n < tips.size(); ++n) {
      const double a = two_pi * double(n) / double(tips.size());
      tips[n] = {30 + 8 * std::cos(a), 30 + 8 * std::sin(a), kSlabSkinZ - 6};
    }
    HapticRun r(slab());
    const Drift d = drift_run(r, tips, 1000);
    r.finish();
    REQUIRE(r.contacts() == 1000000);
    require_no_drift("closed path under the skin", d, r);
  }
  {
    // an ellipse across the skin (in and out of the body every cycle) over the rib, with
    // a stiff device so the magnitude and rate clamps act: 200 cycles of 500 poses
    std::vector<Vec3> tips(500);
    for (std::size_t n = 0; n < tips.size(); ++n) {
      const double a = two_pi * double(n) / double(tips.size());
      tips[n] = {30.5 + 12 * std::cos(a), 20.2, kSlabSkinZ - 4 + 6 * std::sin(a)};
    }
    HapticsSettings stiff;
    stiff.stiffness_n_per_mm = 1.0;
    HapticRun r(rib(), stiff);
    const Drift d = drift_run(r, tips, 200);
    r.finish();
    REQUIRE(r.clamped() > 1000);
    require_no_drift("closed path across the skin", d, r);
  }
  std::printf("closed paths: %.2f s for 1.1e6 poses\n", seconds_since(t0));
}

TEST_CASE("stability: 100000 random poses including NaN and Inf") {
  Case c = make_case("100000 random poses including NaN and Inf");
  INFO(c.describe());
  const auto t0 = std::chrono::steady_clock::now();
  const double nan = std::numeric_limits<double>::quiet_NaN(), inf = std::numeric_limits<double>::infinity();
  const double odd[] = {nan, inf, -inf, 1e300, -1e300, DBL_MAX, -DBL_MAX, 1e20, -1e20, 5e-324, -0.0, 1e-310};
  const double odd_dt[] = {0.0, -1e-3, nan, inf, -inf, 5e-324, 1e-300, 1e300, 1e-9};
  const HapticPatient h = slab();
  HapticRun r(h);
  // every 50th contact goes to the deformation, as the server hands contacts over
  DeformRun d(c, h.patient, config(1, 16, 10));
  Vec3 tip{30, 30, 30};
  long long contacts = 0, non_finite = 0;
  for (int s = 0; s < 100000; ++s) {
    if (s % 1000 == 0) r.reset();
    const int kind = c.integer(0, 99);
    double dt = 1e-3;
    if (kind < 60) {
      tip = {c.uniform(-5, 65), c.uniform(-5, 65), c.uniform(-5, 65)};
    } else if (kind < 75) {
      if (!is_finite(tip)) tip = {30, 30, 30};
      tip += Vec3{c.uniform(-0.5, 0.5), c.uniform(-0.5, 0.5), c.uniform(-0.5, 0.5)};
    } else if (kind < 80) {
      // exact special places: the grid's faces, the skin plane, voxel corners
      tip = {c.integer(-1, 60) + 0.5, c.integer(-1, 60) + 0.5, c.integer(0, 1) ? kSlabSkinZ : -0.5};
    } else if (kind < 94) {
      // one to three components NaN, +-Inf, huge, subnormal or -0
      tip = {c.uniform(-5, 65), c.uniform(-5, 65), c.uniform(-5, 65)};
      const int n = c.integer(1, 3);
      for (int k = 0; k < n; ++k) {
        const int a = c.integer(0, 2);
        tip[a] = odd[c.integer(0, int(sizeof odd / sizeof odd[0]) - 1)];
      }
    } else {
      tip = {c.uniform(-5, 65), c.uniform(-5, 65), c.uniform(-5, 65)};
      dt = odd_dt[c.integer(0, int(sizeof odd_dt / sizeof odd_dt[0]) - 1)];
    }
    non_finite += !is_finite(tip);
    const ForceSample f = r.pose(tip, dt);
    if (f.contact && ++contacts % 50 == 0) d.contact({f.skin_point_mm, tip});
  }
  r.finish();
  REQUIRE(non_finite > 3000);
  REQUIRE(d.contacts() > 300);
  std::printf("random poses: %lld poses (%lld non-finite), %lld contacts, %lld handed to the deformation, %.2f s\n",
              r.poses(), non_finite, contacts, d.contacts(), seconds_since(t0));
  deform_random_poses(c, 2000, 1);
}

TEST_CASE("stability: the shipped deformation (multigrid, 5 mm fingertip, cell search) over presses, pushes and jumps") {
  Case c = make_case("the shipped deformation (multigrid, 5 mm fingertip, cell search)");
  deform_shipped_multigrid(c, 300, 1);
}

TEST_CASE("stability: the tip sweeping across a rib at 1 m/s") {
  Case c = make_case("the tip sweeping across a rib at 1 m/s");
  INFO(c.describe());
  const HapticPatient h = rib();
  HapticsSettings stiff;  // a stiffer device: the rib's edges then ask for more than the rate clamp allows
  stiff.stiffness_n_per_mm = 1.0;
  stiff.max_force_n = 10;
  for (const HapticsSettings& s : {HapticsSettings{}, stiff})
    for (double hz : {1000.0, 4000.0}) {
      const double dt = 1.0 / hz, step_mm = 1000.0 * dt;  // 1 m/s
      HapticRun r(h, s);
      double over_rib = 0, away = 0;
      // above the rib (its top is 7 mm deep), grazing it, through it and below it
      for (double depth : {3.0, 6.0, 7.0, 8.0, 11.0, 14.0, 20.0}) {
        r.reset();
        const int n = int(std::lround(59.0 / step_mm));
        for (int k = 0; k <= 2 * n; ++k) {
          // across and back
          const double x = 0.5 + step_mm * (k <= n ? k : 2 * n - k);
          const ForceSample f = r.pose({x, 20.2 + 0.1 * depth, kSlabSkinZ - depth}, dt);
          if (depth == 6.0 && std::fabs(x - 30.5) < 2) over_rib = std::max(over_rib, norm(f.force_n));
          if (depth == 6.0 && std::fabs(x - 5) < 1) away = std::max(away, norm(f.force_n));
        }
      }
      INFO("stiffness " << s.stiffness_n_per_mm << " N/mm, " << hz << " Hz: peak over the rib " << over_rib
                        << " N, away from it " << away << " N; largest step " << r.max_step_ratio()
                        << " of the rate clamp's " << s.max_force_rate_n_per_s * dt << " N");
      r.finish();
      // the sweep really crosses the rib: it is felt
      CHECK(over_rib > 2 * away);
      std::printf("rib sweep k = %.2f N/mm at %.0f Hz: largest force step %.4f of the rate clamp's %.4f N, %lld clamped\n",
                  s.stiffness_n_per_mm, hz, r.max_step_ratio(), s.max_force_rate_n_per_s * dt, r.clamped());
    }
  deform_rib_sweep(c);
}

namespace {

// A push under the paper's preset p2 near bone, found by the stability catalogue and a
// survey of random pushes on make_torso_patient(n): ChainMail on the CPU reference must
// converge, and returns the largest restriction violation between soft face neighbours
// (voxel). Each restriction is one clamp of a float against its neighbour's float plus a
// limit: a few ulps of the largest coordinate (displacements below 62 voxel: 4 ulps of 64).
struct P2Push {
  int n, voi;
  Vec3 X, x;
};
constexpr double kP2RestrictionTol = 4.0 * FLT_EPSILON * 64;

double p2_push_violation(const P2Push& r) {
  auto p = make_torso_patient(r.n);
  DeformConfig cfg = config(2, r.voi);
  CpuDeformBackend b;
  b.bind(p, cfg);
  const ChainMailStats st = b.chainmail({r.X, r.x});
  REQUIRE(st.converged);
  const double viol = max_restriction_violation(*p, st.voi, b.displacement(), cfg.settings);
  std::printf("p2 push X (%g %g %g): restriction violated by %g voxel after convergence\n", r.X.x, r.X.y, r.X.z, viol);
  return viol;
}

}  // namespace

// Issue 8's ChainMail bug, fixed: an element used to be clamped only against the
// neighbours that moved in the previous sweep, so a later clamp could take it out of the
// box of a neighbour that no longer moves (the grabbed element, or one that has settled)
// and a quiet sweep ended the run with the restriction broken (here by 1 voxel). Now an
// element is clamped against every neighbour that has moved in an earlier sweep
// (server/deform/chainmail.cpp and cuda/chainmail.cu alike).
TEST_CASE("ChainMail keeps its restrictions next to elements that stopped moving (preset p2 near bone) [issue 8]") {
  // random poses, seed 20240801, contact 524 of the catalogue
  CHECK(p2_push_violation({48, 48, {11.653826141846126, 9.7823523282849365, 5.1527107785491184},
                           {30.464565804672375, 22.65169110807161, -6.0009171800053087}}) <= kP2RestrictionTol);
}

// Issue 8's last ChainMail bug, fixed: the VOI is clipped at the volume border (6 voxels
// wide along i) and the grabbed element is displaced 8.9 voxels beyond it; an element was
// pulled by neighbours whose boxes did not overlap (the neighbour along +j allowed its u_z
// up to -2.23 voxel, the one along +k from -1.98), the last clamp won and a quiet sweep
// ended the run 0.25 voxel (minDist) off. A neighbour moved one way only pulls that way
// now (chainmail_clamp()), and the restrictions' solution is reached.
TEST_CASE("ChainMail keeps its restrictions where two neighbours' full boxes would not overlap (p2, clipped VOI) [issue 8]") {
  CHECK(p2_push_violation({40, 16, {34.475528833882343, 15.887227523706539, 34.74798598294349},
                           {42.939564058958211, 17.256031169232529, 24.767021691015621}}) <= kP2RestrictionTol);
}

// ---------------------------------------------------------------------------------
// the elastic model (stability_elastic.h): the catalogue's cases where a fingertip
// pressing the skin makes sense, with fewer random contacts than the fast models (a step
// solves the VOI's elasticity: tens of ms on this CPU), and its own hard cases

TEST_CASE("stability: tip inside bone (elastic)", "[elastic]") {
  Case c = make_case("tip inside bone (elastic)");
  elastic_tip_inside_bone(c);
}

TEST_CASE("stability: tip exactly on the skin (elastic)", "[elastic]") {
  Case c = make_case("tip exactly on the skin (elastic)");
  elastic_on_skin(c);
}

TEST_CASE("stability: tip on a voxel corner (elastic)", "[elastic]") {
  Case c = make_case("tip on a voxel corner (elastic)");
  elastic_voxel_corner(c);
}

TEST_CASE("stability: tip on the volume border (elastic)", "[elastic]") {
  Case c = make_case("tip on the volume border (elastic)");
  elastic_volume_border(c);
}

TEST_CASE("stability: flat plateaus of F (elastic)", "[elastic]") {
  Case c = make_case("flat plateaus of F (elastic)");
  elastic_flat_plateau(c);
}

TEST_CASE("stability: a 50 mm jump of the tip (elastic)", "[elastic]") {
  Case c = make_case("a 50 mm jump of the tip (elastic)");
  elastic_jump_50mm(c);
}

TEST_CASE("stability: a displacement larger than the VOI (elastic)", "[elastic]") {
  Case c = make_case("a displacement larger than the VOI (elastic)");
  elastic_displacement_larger_than_voi(c);
}

TEST_CASE("stability: a VOI crossing the volume border (elastic)", "[elastic]") {
  Case c = make_case("a VOI crossing the volume border (elastic)");
  elastic_voi_crossing_border(c);
}

TEST_CASE("stability: anisotropic input spacing (elastic)", "[elastic]") {
  Case c = make_case("anisotropic input spacing (elastic)");
  elastic_anisotropic(c);
}

TEST_CASE("stability: extreme HU (elastic)", "[elastic]") {
  Case c = make_case("extreme HU (elastic)");
  elastic_extreme_hu(c);
}

TEST_CASE("stability: one spot stepped again and again (elastic)", "[elastic]") {
  Case c = make_case("one spot stepped again and again (elastic)");
  elastic_one_spot_repeated(c, 20);
}

TEST_CASE("stability: random poses including NaN and Inf (elastic)", "[elastic]") {
  Case c = make_case("random poses including NaN and Inf (elastic)");
  elastic_random_poses(c, 150);
}

TEST_CASE("stability: the tip sweeping across a rib (elastic)", "[elastic]") {
  Case c = make_case("the tip sweeping across a rib (elastic)");
  elastic_rib_sweep(c);
}

TEST_CASE("stability: Poisson's ratio 0.49 (elastic)", "[elastic]") {
  Case c = make_case("Poisson's ratio 0.49 (elastic)");
  elastic_nu_049(c);
}

TEST_CASE("stability: 2 mm of tissue over bone (elastic)", "[elastic]") {
  Case c = make_case("2 mm of tissue over bone (elastic)");
  elastic_thin_tissue_over_bone(c);
}

TEST_CASE("stability: the sphere entering bone (elastic)", "[elastic]") {
  Case c = make_case("the sphere entering bone (elastic)");
  elastic_sphere_into_bone(c);
}

TEST_CASE("stability: a 40 mm indentation (elastic)", "[elastic]") {
  Case c = make_case("a 40 mm indentation (elastic)");
  elastic_indentation_40mm(c);
}
