// The force model's physical invariants on synthetic patients with closed-form skin and
// bone (tests/support/synthetic_patient.h): zero outside, growth with depth, bone makes
// it stiffer, it points out of the body, friction makes the proxy lag, clamps hold.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>

#include "haptics/force_model.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
using palpsim::test::kSlabSkinZ;

namespace {

// parameters without friction and with clamps far away, so |f| = k F(x) exactly
HapticsSettings unclamped() {
  HapticsSettings s;
  s.friction = 0;
  s.max_force_n = 100;
  s.max_force_rate_n_per_s = 1e7;
  return s;
}

// the force of a single pose from a fresh state
ForceSample fresh(const Patient& p, const HapticsSettings& s, const Vec3& x) {
  ProxyState st{};
  return compute_force(p, s, x, 1e-3, st);
}

}  // namespace

TEST_CASE("force is exactly zero outside the body", "[haptics]") {
  const auto p = test::slab_patient();
  const HapticsSettings s;
  ProxyState st{};
  // above the skin plane, outside the grid on every side, and kilometres away
  const Vec3 outside[] = {{30, 30, 39.9}, {30, 30, 45}, {5, 5, 59}, {-3, 30, 20}, {30, 70, 20},
                          {30, 30, -2},   {1e6, 0, 0},  {0, -1e6, 1e6}};
  for (const Vec3& x : outside) {
    // enter the body first so that the state holds a proxy and a force
    compute_force(*p, s, {30, 30, 30}, 1e-3, st);
    const ForceSample f = compute_force(*p, s, x, 1e-3, st);
    INFO("tip " << x.x << " " << x.y << " " << x.z);
    CHECK(f.force_n.x == 0.0);
    CHECK(f.force_n.y == 0.0);
    CHECK(f.force_n.z == 0.0);
    CHECK_FALSE(f.contact);
    CHECK(f.depth_mm == 0.0);
    CHECK(f.proxy_mm == x);
    CHECK(f.skin_point_mm == x);
    CHECK_FALSE(st.in_contact);
  }
}

TEST_CASE("force grows with depth at a point away from bone", "[haptics]") {
  const auto p = test::slab_patient();
  const HapticsSettings s = unclamped();
  // a column far from the bone block, from just under the skin down to the level of the
  // bone block's bottom (below it, moving deeper moves away from bone)
  double last = 0;
  for (double depth = 0.25; depth <= 24; depth += 0.5) {
    const Vec3 x{8, 8, kSlabSkinZ - depth};
    const ForceSample f = fresh(*p, s, x);
    INFO("depth " << depth);
    REQUIRE(f.contact);
    // B is linear in z for the slab, so its trilinear sample is exact up to float rounding
    CHECK(f.depth_mm == Approx(depth).margin(1e-4));
    // eq. 2 without friction or clamps: |f| = k F(x) (1e-9 relative: double rounding)
    const PatientSample ps = sample_patient(*p, x);
    CHECK(norm(f.force_n) == Approx(s.stiffness_n_per_mm * ps.force_mm).epsilon(1e-9));
    CHECK(norm(f.force_n) > last);
    last = norm(f.force_n);
  }
}

TEST_CASE("force is larger near bone than far from it at the same depth", "[haptics]") {
  const auto p = test::slab_patient();
  const HapticsSettings s = unclamped();
  for (double depth : {1.0, 3.0, 6.0, 10.0}) {
    const ForceSample near_bone = fresh(*p, s, {30, 30, kSlabSkinZ - depth});
    const ForceSample far_bone = fresh(*p, s, {8, 8, kSlabSkinZ - depth});
    INFO("depth " << depth);
    CHECK(near_bone.depth_mm == Approx(far_bone.depth_mm).margin(1e-4));
    CHECK(norm(near_bone.force_n) > 1.5 * norm(far_bone.force_n));
  }
}

TEST_CASE("force points out of the body and X lies on the skin", "[haptics]") {
  const HapticsSettings s = unclamped();
  SECTION("slab: outward normal +z, under either rule for X") {
    const auto p = test::slab_patient();
    for (SkinPointRule rule : {SkinPointRule::kNormal, SkinPointRule::kLine}) {
      HapticsSettings rs = s;
      rs.skin_point = rule;
      for (double x = 3; x <= 57; x += 6)
        for (double depth : {0.5, 2.0, 7.0, 12.0}) {
          const Vec3 tip{x, 31.3, kSlabSkinZ - depth};
          const ForceSample f = fresh(*p, rs, tip);
          INFO((rule == SkinPointRule::kLine ? "line" : "normal") << " rule, x " << x << " depth " << depth);
          REQUIRE(f.contact);
          CHECK(f.force_n.z > 0);
          // the paper's rule: where the ray from x away from p meets the skin plane z =
          // 39.5 inside the grid and within three depths (+2 voxels) of the tip, X is that
          // point: on the line through x and p, on the far side of x from p (bisection to
          // well under 0.01 mm of the C = 0.5 level). Otherwise (the default rule, or the
          // ray runs nearly along the skin, or leaves through a side of the grid first) X
          // is the skin point straight above the tip
          const Vec3 a = f.skin_point_mm - tip, b = tip - f.proxy_mm;
          const Vec3 u = b * (1.0 / norm(b));
          const Vec3 hit = tip + u * ((kSlabSkinZ - tip.z) / u.z);
          const bool on_line = rule == SkinPointRule::kLine && hit.x > -0.5 && hit.x < 59.5 && hit.y > -0.5 &&
                               hit.y < 59.5 && norm(hit - tip) <= 3 * depth + 2;
          if (on_line) {
            CHECK(norm(cross(a, b)) <= 1e-6 * norm(a) * norm(b) + 1e-9);
            CHECK(dot(a, b) > 0);
            CHECK(f.skin_point_mm.x == Approx(hit.x).margin(0.01));
            CHECK(f.skin_point_mm.y == Approx(hit.y).margin(0.01));
            CHECK(f.skin_point_mm.z == Approx(kSlabSkinZ).margin(0.01));
          } else {
            // on the skin plane within the bisection's and B's interpolation error (0.05 mm
            // at 1 mm voxels); grad B is +z, up to one voxel of central-difference error
            // sideways (near the grid's side faces, where the probes are clamped to the grid)
            CHECK(f.skin_point_mm.z == Approx(kSlabSkinZ).margin(0.05));
            CHECK(std::hypot(f.skin_point_mm.x - tip.x, f.skin_point_mm.y - tip.y) < 1.0);
          }
        }
    }
  }
  SECTION("sphere with a bone core: force along the outward radius") {
    const auto p = test::sphere_patient();
    const Vec3 c{32, 32, 32};
    for (int n = 0; n < 40; ++n) {
      // points on a spiral shell between the bone core and the skin
      const double t = (n + 0.5) / 40, phi = n * 2.39996, z = 1 - 2 * t, r = std::sqrt(1 - z * z);
      const Vec3 u{r * std::cos(phi), r * std::sin(phi), z};
      for (double radius : {14.0, 20.0, 26.0}) {
        const ForceSample f = fresh(*p, s, c + u * radius);
        INFO("n " << n << " radius " << radius);
        REQUIRE(f.contact);
        // at least 0.9 of the force is radial: grad F is radial up to voxelisation
        CHECK(dot(f.force_n, u) > 0.9 * norm(f.force_n));
        // X within a voxel of the radius-28 skin sphere (the mask is voxelised)
        CHECK(norm(f.skin_point_mm - c) == Approx(28.0).margin(1.0));
      }
    }
  }
}

TEST_CASE("X stays on the skin near the tip where the line through x and p runs along the skin", "[haptics]") {
  // the paper's rule beside the slab's bone block, 19.5 mm deep: grad F points at the bone
  // (-x), so the line through x and p runs parallel to the skin and leaves the body only
  // through the grid's face at x = 60 mm; X must be the skin point above the tip instead
  const auto p = test::slab_patient();
  const Vec3 tip{38, 30, 20};
  HapticsSettings line = unclamped();
  line.skin_point = SkinPointRule::kLine;
  const ForceSample r = fresh(*p, line, tip);
  REQUIRE(r.contact);
  INFO("X = " << r.skin_point_mm.x << ", " << r.skin_point_mm.y << ", " << r.skin_point_mm.z);
  // on the skin plane within the bisection's and B's interpolation error (0.05 mm at 1 mm voxels)
  CHECK(std::abs(r.skin_point_mm.z - kSlabSkinZ) < 0.05);
  // straight above the tip: grad B is +z here, up to one voxel of central-difference error
  CHECK(std::abs(r.skin_point_mm.x - tip.x) < 1.0);
  CHECK(std::abs(r.skin_point_mm.y - tip.y) < 1.0);
}

TEST_CASE("X moves with the tip, not with grad F, on a press beside bone", "[haptics]") {
  // straight down beside the slab's bone block (its face at x = 35.5 mm), 0.05 mm a pose
  // from the skin to 24 mm deep, with the default rule: grad F turns from +z towards the
  // bone, so the paper's line swings sideways, but X must stay straight above the tip:
  // at most 0.5 voxel (0.5 mm) sideways, a press of 1 mm moving X by well under 1 mm, so
  // that the deformation grabs the same voxel all the way down
  const auto p = test::slab_patient();
  for (double x : {36.7, 38.2, 41.2}) {
    ProxyState st{};
    Vec3 last{0, 0, -1};
    int changes = 0;
    for (double depth = 0.05; depth <= 24; depth += 0.05) {
      const Vec3 tip{x, 30.2, kSlabSkinZ - depth};
      const ForceSample f = compute_force(*p, HapticsSettings{}, tip, 1e-3, st);
      INFO("x " << x << " depth " << depth << ": X " << f.skin_point_mm.x << ", " << f.skin_point_mm.y << ", "
                << f.skin_point_mm.z);
      REQUIRE(f.contact);
      CHECK(f.skin_point_mm.z == Approx(kSlabSkinZ).margin(0.05));
      CHECK(std::hypot(f.skin_point_mm.x - tip.x, f.skin_point_mm.y - tip.y) < 0.5);
      if (last.z > 0 && (std::lround(last.x) != std::lround(f.skin_point_mm.x) ||
                         std::lround(last.y) != std::lround(f.skin_point_mm.y)))
        ++changes;
      last = f.skin_point_mm;
    }
    INFO("x " << x);
    CHECK(changes == 0);
  }
}

TEST_CASE("friction makes the proxy lag behind a sliding tip", "[haptics]") {
  const auto p = test::slab_patient();
  HapticsSettings none = unclamped(), sticky = unclamped();
  sticky.friction = 0.5;
  ProxyState a{}, b{};
  const double step_mm = 0.1;  // per pose, along +x at constant depth, far from the bone
  ForceSample fa, fb;
  double q_step = 0;  // how far the frictionless proxy q moved in the last step
  for (int n = 0; n <= 100; ++n) {
    const Vec3 tip{5 + n * step_mm, 8, kSlabSkinZ - 4};
    const double q_before = fa.proxy_mm.x;
    fa = compute_force(*p, none, tip, 1e-3, a);
    fb = compute_force(*p, sticky, tip, 1e-3, b);
    q_step = fa.proxy_mm.x - q_before;
  }
  // steady state of p_n = (1 - mu) q_n + mu p_(n-1) with q moving v per step: lag mu v / (1 - mu);
  // v changes slowly along the path (grad F turns), hence 2 % of the lag as tolerance
  const double expected_lag = 0.5 * q_step / (1 - 0.5);
  REQUIRE(expected_lag > 0.05);
  CHECK(fa.proxy_mm.x - fb.proxy_mm.x == Approx(expected_lag).epsilon(0.02));
  // the lagging proxy pulls the tip back: a force component against the motion
  CHECK(fb.force_n.x > fa.force_n.x + 0.9 * none.stiffness_n_per_mm * expected_lag);
}

TEST_CASE("the magnitude and rate clamps hold", "[haptics]") {
  const auto p = test::slab_patient();
  HapticsSettings s;
  s.stiffness_n_per_mm = 2.0;  // with F ~ 33 mm at bone, k F is ~ 66 N: far over the limit
  s.max_force_n = 3.3;
  s.max_force_rate_n_per_s = 500;
  const double dt = 1e-3;
  ProxyState st{};
  Vec3 last{0, 0, 0};
  bool any_clamped = false;
  // a jerky path: in and out of the body, onto the bone and away, in big steps
  for (int n = 0; n < 400; ++n) {
    const double t = n * 0.037;
    const Vec3 tip{30 + 25 * std::sin(3.1 * t), 30 + 20 * std::cos(1.7 * t), 30 + 12 * std::sin(5.3 * t)};
    const ForceSample f = compute_force(*p, s, tip, dt, st);
    INFO("step " << n);
    // 1e-12 N: rounding of the rescaling
    CHECK(norm(f.force_n) <= s.max_force_n + 1e-12);
    // leaving the body drops the force to exactly zero (no energy is added); otherwise
    // the change per step is at most rate * dt
    if (f.contact) CHECK(norm(f.force_n - last) <= s.max_force_rate_n_per_s * dt + 1e-12);
    any_clamped = any_clamped || f.clamped;
    last = f.force_n;
  }
  CHECK(any_clamped);
}

TEST_CASE("where the gradient vanishes the last good direction is kept", "[haptics]") {
  const auto p = test::slab_patient();
  HapticsSettings s = unclamped();
  ProxyState st{};
  const ForceSample first = compute_force(*p, s, {8, 8, 30}, 1e-3, st);
  REQUIRE(st.has_direction);
  const Vec3 dir = st.direction;
  // a threshold above every |grad F| of the patient: no sample defines a direction now
  s.min_gradient_norm = 1.0;
  const Vec3 tip{12, 9, 28};
  const ForceSample second = compute_force(*p, s, tip, 1e-3, st);
  REQUIRE(second.contact);
  CHECK(is_finite(second.force_n));
  const Vec3 d = second.proxy_mm - tip;
  // the proxy moved along the old direction (1e-9: double rounding)
  CHECK(norm(cross(d, dir)) <= 1e-9 * norm(d));
  CHECK(dot(d, dir) > 0);
  CHECK(first.contact);
  // a fresh session without any good direction: no direction, no force, nothing divided by ~0
  ProxyState blank{};
  const ForceSample none = compute_force(*p, s, tip, 1e-3, blank);
  CHECK(none.contact);
  CHECK(norm(none.force_n) == 0.0);
  CHECK(none.proxy_mm == tip);
}

TEST_CASE("a corrupt patient resets the session instead of poisoning it", "[haptics]") {
  auto p = test::slab_patient();
  ProxyState st{};
  compute_force(*p, HapticsSettings{}, {30, 30, 30}, 1e-3, st);
  // a NaN in F around the tip
  for (float& f : p->force.data) f = std::numeric_limits<float>::quiet_NaN();
  const ForceSample f = compute_force(*p, HapticsSettings{}, {30, 30, 30.2}, 1e-3, st);
  CHECK(f.reset);
  CHECK(norm(f.force_n) == 0.0);
  CHECK_FALSE(st.has_direction);
  CHECK_FALSE(st.in_contact);
}
