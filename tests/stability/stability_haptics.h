// The force-model half of the stability catalogue (issue 8, section 5). The force model
// runs on the CPU only (every backend shares it), so these checks run in the CPU
// executable. HapticRun::pose() calls compute_force() for one pose of a session and
// checks, without asking the code under test what the answer should be:
// - the force is finite and within the magnitude clamp (max_force_n);
// - in contact, it changes by at most max_force_rate_n_per_s * dt per pose (dt taken as
//   one nominal haptic period for the first pose and for dt <= 0 or NaN); out of contact
//   it is exactly zero;
// - outside the body it is zero: a tip more than one voxel outside the closed-form skin
//   (every trilinear corner then lies outside: the skin distance is 1-Lipschitz and the
//   corners are within sqrt(3)/2 voxel) or outside the grid is never in contact, and
//   one more than a voxel inside, within the grid's voxel centres, always is;
// - for a finite tip, proxy, skin point X and depth are finite; in contact X lies in
//   the patient grid (the deformation accepts it) and within the reach the model
//   states (three depths and four voxels of the tip); depth >= 0;
// - the session state stays finite, and no pose of a valid patient triggers the
//   corrupt-patient reset.
// Failures are counted; finish() reports the first one with its pose number.
#pragma once

#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>
#include <string>

#include "haptics/force_model.h"
#include "stability/stability_case.h"
#include "stability/stability_patients.h"

namespace palpsim::test::stability {

class HapticRun {
 public:
  HapticRun(const HapticPatient& h, const HapticsSettings& s = {}) : h_(h), s_(s) {
    const Vec3& sp = h.patient->grid.spacing_mm;
    voxel_mm_ = std::min({sp.x, sp.y, sp.z});
  }

  /// One pose of the session; checks it and returns the model's answer.
  ForceSample pose(const Vec3& tip, double dt_s = 1e-3) {
    const bool first = !st_.has_previous;
    const ForceSample f = compute_force(*h_.patient, s_, tip, dt_s, st_);
    ++poses_;
    contacts_ += f.contact;
    clamped_ += f.clamped;
    const bool tip_finite = is_finite(tip);
    const Grid& g = h_.patient->grid;
    const double fn = norm(f.force_n);
    if (!is_finite(f.force_n)) fail("force is not finite", tip, dt_s, f);
    // the magnitude clamp rescales: 1e-12 relative is its rounding
    if (fn > s_.max_force_n * (1 + 1e-12)) fail("force above max_force_n", tip, dt_s, f);
    if (f.reset) fail("the corrupt-patient reset fired on a valid patient", tip, dt_s, f);
    if (!f.contact) {
      if (!(f.force_n == Vec3{0, 0, 0})) fail("force not exactly zero out of contact", tip, dt_s, f);
    } else {
      const double dt = (first || !(dt_s > 0)) ? kNominalHapticPeriodS : dt_s;
      const double step = norm(f.force_n - last_);
      max_step_ratio_ = std::max(max_step_ratio_, step / (s_.max_force_rate_n_per_s * dt));
      // the rate clamp blends the previous force towards the new one: 1e-12 N and
      // relative of rounding
      if (step > s_.max_force_rate_n_per_s * dt * (1 + 1e-12) + 1e-12) fail("force step above the rate clamp", tip, dt_s, f);
      if (!tip_finite) fail("contact for a non-finite tip", tip, dt_s, f);
      if (!is_finite(f.proxy_mm) || !is_finite(f.skin_point_mm) || !std::isfinite(f.depth_mm) || f.depth_mm < 0)
        fail("proxy, X or depth not finite (or depth < 0) in contact", tip, dt_s, f);
      // X must be accepted by the deformation: within the grid's outer faces (2e-3 voxel
      // of bisection tolerance, as DeformBackend allows)
      const Vec3 xi = g.to_index(f.skin_point_mm);
      for (int a = 0; a < 3; ++a)
        if (!(xi[a] >= -0.5 - 2e-3 && xi[a] <= g.size[a] - 0.5 + 2e-3)) fail("X outside the patient grid", tip, dt_s, f);
      // the skin search looks at most three depths and four voxels away (1e-6 mm rounding)
      if (norm(f.skin_point_mm - tip) > 3 * f.depth_mm + 4 * voxel_mm_ + 1e-6) fail("X farther than the model's reach", tip, dt_s, f);
    }
    if (tip_finite && (!is_finite(f.proxy_mm) || !is_finite(f.skin_point_mm))) fail("proxy or X not finite", tip, dt_s, f);
    if (!is_finite(st_.proxy_mm) || !is_finite(st_.direction) || !is_finite(st_.force_n)) fail("state not finite", tip, dt_s, f);
    if (tip_finite) {
      const Vec3 ti = g.to_index(tip);
      bool in_grid = true, in_centres = true;
      for (int a = 0; a < 3; ++a) {
        in_grid = in_grid && ti[a] >= -0.5 && ti[a] <= g.size[a] - 0.5;
        in_centres = in_centres && ti[a] >= 0 && ti[a] <= g.size[a] - 1;
      }
      if (!in_grid && f.contact) fail("contact outside the patient grid", tip, dt_s, f);
      if (h_.skin) {
        const double sd = h_.skin(tip);
        if (sd > voxel_mm_ && f.contact) fail("contact more than a voxel outside the skin", tip, dt_s, f);
        if (sd < -voxel_mm_ && in_centres && !f.contact) fail("no contact more than a voxel inside the skin", tip, dt_s, f);
      }
    }
    last_ = f.contact ? f.force_n : Vec3{0, 0, 0};
    return f;
  }

  /// A fresh session (as after a reset request).
  void reset() {
    st_ = ProxyState{};
    last_ = Vec3{0, 0, 0};
  }

  /// Reports the first failure, if any (with the case's INFO in scope).
  void finish() {
    std::ostringstream k;
    for (const auto& [what, n] : kinds_) k << n << " x " << what << "; ";
    INFO(h_.what << ": " << poses_ << " poses, " << contacts_ << " in contact, " << clamped_ << " clamped, largest force step "
                 << max_step_ratio_ << " of the rate clamp's limit; " << failures_ << " failed checks (" << k.str()
                 << "); first: " << first_);
    REQUIRE(failures_ == 0);
  }

  const ProxyState& state() const { return st_; }
  long long contacts() const { return contacts_; }
  long long clamped() const { return clamped_; }
  long long poses() const { return poses_; }
  /// The largest force change of a pose in contact over what the rate clamp allowed it (<= 1).
  double max_step_ratio() const { return max_step_ratio_; }
  const HapticsSettings& settings() const { return s_; }

 private:
  void fail(const char* what, const Vec3& tip, double dt, const ForceSample& f) {
    ++kinds_[what];
    if (failures_++ > 0) return;
    std::ostringstream s;
    s.precision(17);
    s << what << " at pose " << poses_ - 1 << ": tip (" << tip.x << ", " << tip.y << ", " << tip.z << ") mm, dt " << dt
      << " s -> force (" << f.force_n.x << ", " << f.force_n.y << ", " << f.force_n.z << ") N, |f| " << norm(f.force_n)
      << ", previous (" << last_.x << ", " << last_.y << ", " << last_.z << "), contact " << f.contact << ", depth "
      << f.depth_mm << ", X (" << f.skin_point_mm.x << ", " << f.skin_point_mm.y << ", " << f.skin_point_mm.z
      << "), proxy (" << f.proxy_mm.x << ", " << f.proxy_mm.y << ", " << f.proxy_mm.z << ")";
    first_ = s.str();
  }

  HapticPatient h_;
  HapticsSettings s_;
  ProxyState st_{};
  Vec3 last_{0, 0, 0};
  double voxel_mm_ = 1;
  long long poses_ = 0, contacts_ = 0, clamped_ = 0, failures_ = 0;
  double max_step_ratio_ = 0;
  std::string first_ = "none";
  std::map<std::string, long long> kinds_;  // failed checks by kind
};

/// Every volume the force model reads is finite (A may be +inf only without bone).
inline void require_finite_patient(const Patient& p) {
  long long bad = 0;
  for (std::size_t n = 0; n < p.grid.count(); ++n) {
    bad += !std::isfinite(p.force.data[n]) || !is_finite(p.grad_force.data[n]) || !std::isfinite(p.dist_skin_mm.data[n]) ||
           !std::isfinite(p.intensity.data[n]) || (p.has_bone && !std::isfinite(p.dist_bone_mm.data[n]));
  }
  INFO(p.source << ": " << bad << " voxels with a non-finite value");
  REQUIRE(bad == 0);
}

/// Poses `n` tips drawn by the case over the whole grid and 2 voxels beyond each face,
/// resetting the session every 50 poses so that runs start afresh throughout.
inline void poses_over_grid(HapticRun& r, const Grid& g, Case& c, int n) {
  for (int s = 0; s < n; ++s) {
    if (s % 50 == 0) r.reset();
    r.pose(g.to_physical({c.uniform(-2, g.size.x + 1), c.uniform(-2, g.size.y + 1), c.uniform(-2, g.size.z + 1)}));
  }
}

}  // namespace palpsim::test::stability
