// Passivity of a rendered force (a time-domain passivity observer and controller): the
// energy the hand has put into the force field along its path, and the limit on a force
// that would give more back than that. Energies are in mJ (N x mm = mJ). Header-only on
// core's header-only types, shared by the server's pose path (PassivityObserver, per
// session) and the thin haptic client (clients/haptic/local_model.h). No allocation, no
// locks: both run once per pose or loop step.
#pragma once

#include <algorithm>
#include <cstdint>

#include "core/vec3.h"

namespace palpsim {

/// The energy (mJ = N mm) a force has taken from the hand along a path, -sum f . dx, per
/// contact episode (from the first force to the release: one press): >= 0 for a passive
/// rendering, which may store and dissipate energy but never gives more back. Each force
/// acts until the next step (a zero-order hold): the hand feels f_{n-1} . (x_n - x_{n-1}).
class EnergyMeter {
 public:
  /// The tip moved by `dx_mm` while the force last set was held.
  void move(const Vec3& dx_mm) {
    energy_mj_ -= dot(force_n_, dx_mm);
    if (in_episode_) min_running_mj_ = std::min(min_running_mj_, energy_mj_);
  }
  /// The force from now on (N). `active`: a force field acts on the tip (the tip is in
  /// contact, or the force before any bound is not zero). An episode ends when no field
  /// acts and the force is zero now and was zero before (a watchdog stop in contact does
  /// not end one); its energy is then kept as the last cycle's and the running one restarts at 0.
  void set_force(const Vec3& f_n, bool active) {
    const Vec3 zero{0, 0, 0};
    if (active || f_n != zero) {
      in_episode_ = true;
    } else if (in_episode_ && force_n_ == zero) {
      // released: no field, and a zero force twice in a row
      in_episode_ = false;
      last_cycle_mj_ = energy_mj_;
      min_cycle_mj_ = cycles_ == 0 ? energy_mj_ : std::min(min_cycle_mj_, energy_mj_);
      ++cycles_;
      energy_mj_ = 0;
    }
    force_n_ = f_n;
  }
  /// The current episode's energy so far (mJ).
  double energy_mj() const { return energy_mj_; }
  /// True between an episode's first force and its release.
  bool in_episode() const { return in_episode_; }
  /// Completed episodes, the last one's and the smallest energy, and the smallest running
  /// energy seen inside any episode (mJ).
  std::uint64_t cycles() const { return cycles_; }
  double last_cycle_mj() const { return last_cycle_mj_; }
  double min_cycle_mj() const { return min_cycle_mj_; }
  double min_running_mj() const { return min_running_mj_; }

 private:
  Vec3 force_n_{0, 0, 0};
  double energy_mj_ = 0, last_cycle_mj_ = 0, min_cycle_mj_ = 0, min_running_mj_ = 0;
  bool in_episode_ = false;
  std::uint64_t cycles_ = 0;
};

/// The passivity controller: where force `f_n` (N), held over a next step guessed as
/// `step_mm` (the last step), would give the hand more than the stored `energy_mj` (mJ),
/// the part of f along the step is cut to what the energy allows (to zero when none is
/// left: the force is never turned into a push against the hand). Returns the energy (mJ)
/// the cut removes over the guessed step: 0 when f is left as it is.
inline double limit_to_energy(Vec3& f_n, const Vec3& step_mm, double energy_mj) {
  const double dn = norm(step_mm);
  if (!(dn > 1e-9)) return 0;
  const Vec3 u = step_mm * (1.0 / dn);
  const double along = dot(f_n, u);
  const double allowed = std::max(energy_mj, 0.0) / dn;
  if (!(along > allowed)) return 0;
  f_n -= u * (along - allowed);
  return (along - allowed) * dn;
}

/// What the server's observer did at one pose.
struct PassivityStep {
  bool limited = false;     // the controller lowered the force
  double removed_mj = 0;    // the energy that cut removes over the guessed step (mJ)
  bool released = false;    // a press ended at this pose (its energy is EnergyMeter::last_cycle_mj)
};

/// A session's passivity observer and controller on the server's pose path (the scene's
/// haptics.passivity): it follows the energy the hand puts into the force field, press by
/// press, and limits each reply's force so that over the next step (guessed as the last
/// one) the field gives back at most what the hand put in, so that a client without its
/// own controller is safe too. Value-initialise it for a fresh session or a reset.
class PassivityObserver {
 public:
  /// One pose: the tip is at `tip_mm`, in contact or not (`contact`, the force model's), and
  /// the model says `f_n` (N), which the controller may lower in place when `limit` is set
  /// (with `limit` false it only observes). Outside the body f is zero and stays zero.
  /// `held_n`: the force model's record of the force sent (its rate clamp starts from it),
  /// set to the lowered force when the controller acts; may be null.
  PassivityStep pose(const Vec3& tip_mm, bool contact, Vec3& f_n, bool limit, Vec3* held_n = nullptr) {
    PassivityStep out;
    const Vec3 dx = has_previous_ ? tip_mm - tip_mm_ : Vec3{0, 0, 0};
    meter_.move(dx);
    if (limit) {
      out.removed_mj = limit_to_energy(f_n, dx, meter_.energy_mj());
      out.limited = out.removed_mj > 0;
      if (out.limited && held_n) *held_n = f_n;
    }
    const std::uint64_t cycles = meter_.cycles();
    meter_.set_force(f_n, contact);
    out.released = meter_.cycles() != cycles;
    tip_mm_ = tip_mm;
    has_previous_ = true;
    return out;
  }
  /// The energy meter: this press's energy so far, completed presses, smallest energies.
  const EnergyMeter& meter() const { return meter_; }

 private:
  EnergyMeter meter_;
  Vec3 tip_mm_{0, 0, 0};  // the previous pose's tip
  bool has_previous_ = false;
};

}  // namespace palpsim
