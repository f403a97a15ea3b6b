// The energy a closed press exchanges with the force field, as the server's pose path
// renders it: eq. 2 (compute_force) at 1 kHz along a press in and out, once as the model
// gives it and once through the session's passivity observer and controller
// (haptics/passivity.h, what the pose service does with haptics.passivity). For the
// stability catalogue (tests/stability/passivity_test.cpp) and palpsim-bench passivity.
// Energies in mJ (N x mm): the energy the hand put into the field, -sum f_n . (x_{n+1} - x_n),
// each force held until the next pose; negative where the field gave the hand energy.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "core/patient.h"
#include "core/scene.h"
#include "haptics/force_model.h"
#include "haptics/passivity.h"

namespace palpsim::bench {

/// A press along a straight line: from `from_mm` (outside the body) `travel_mm` along the
/// unit `dir` and back, as depth(t) = travel / 2 (1 - cos(2 pi t / period)): a smooth hand
/// that slows to turn (1 kHz poses, one period).
struct PressPath {
  Vec3 from_mm{0, 0, 0};
  Vec3 dir{0, 0, -1};
  double travel_mm = 0;
  double period_s = 2.0;
  bool valid = false;   // the line meets the body within the grid
};

/// What one run of a press gave.
struct PressRun {
  double energy_mj = 0;       // over the whole closed path
  double min_running_mj = 0;  // the lowest running energy along it
  double peak_force_n = 0;
  double removed_mj = 0;      // energy the controller took out (its guessed steps)
  std::uint64_t limited = 0;  // poses it lowered
  std::uint64_t contact_poses = 0;
  std::uint64_t presses = 0;  // presses the observer counted
};

/// The same press without and with the controller.
struct PressEnergy {
  PressRun model;    // eq. 2 as compute_force gives it (haptics.passivity false)
  PressRun served;   // what the pose path sends with haptics.passivity (the default)
};

/// The bounding box of the body mask's voxel centres in index space; false without body.
inline bool body_index_box(const Patient& p, Vec3& lo, Vec3& hi) {
  const Grid& g = p.grid;
  lo = Vec3{1e300, 1e300, 1e300};
  hi = Vec3{-1e300, -1e300, -1e300};
  bool any = false;
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        if (!p.body.at(i, j, k)) continue;
        any = true;
        lo = Vec3{std::min(lo.x, double(i)), std::min(lo.y, double(j)), std::min(lo.z, double(k))};
        hi = Vec3{std::max(hi.x, double(i)), std::max(hi.y, double(j)), std::max(hi.z, double(k))};
      }
  return any;
}

/// A press through the middle of the body's box along the physical direction `dir`: it starts
/// `margin_mm` outside the grid (so also outside a body cut by the grid's face), meets the
/// body where the line first enters it (found in 0.05 mm steps) and goes `depth_mm` further.
inline PressPath press_through_middle(const Patient& p, const Vec3& dir, double depth_mm, double margin_mm = 10) {
  PressPath path;
  path.dir = dir * (1.0 / norm(dir));
  Vec3 lo, hi;
  if (!body_index_box(p, lo, hi)) return path;
  const Grid& g = p.grid;
  const Vec3 centre = g.to_physical((lo + hi) * 0.5);
  // back along -dir out of the grid, then the margin
  double back = 0;
  while (within_grid(g, g.to_index(centre - path.dir * back))) back += 0.5;
  path.from_mm = centre - path.dir * (back + margin_mm);
  for (double s = 0; s <= back + margin_mm; s += 0.05)
    if (inside(sample_patient(p, path.from_mm + path.dir * s))) {
      path.travel_mm = s + depth_mm;
      path.valid = true;
      break;
    }
  return path;
}

/// One run of the press: fresh session state, poses at 1 kHz; `limit` as haptics.passivity.
/// The controller's cut goes into the proxy state's force, as in the pose service.
inline PressRun run_press(const Patient& p, const HapticsSettings& params, const PressPath& path, bool limit) {
  PressRun r;
  ProxyState state{};
  PassivityObserver observer;
  const double dt = 1e-3;
  const int n = int(std::lround(path.period_s / dt));
  Vec3 prev_tip = path.from_mm, prev_f{0, 0, 0};
  double running = 0;
  for (int i = 0; i <= n; ++i) {
    const double depth = 0.5 * path.travel_mm * (1 - std::cos(2 * M_PI * i / n));
    const Vec3 tip = path.from_mm + path.dir * depth;
    running -= dot(prev_f, tip - prev_tip);
    r.min_running_mj = std::min(r.min_running_mj, running);
    ForceSample f = compute_force(p, params, tip, i == 0 ? 0.0 : dt, state);
    const PassivityStep s = observer.pose(tip, f.contact, f.force_n, limit, &state.force_n);
    r.limited += s.limited;
    r.removed_mj += s.removed_mj;
    r.contact_poses += f.contact;
    r.peak_force_n = std::max(r.peak_force_n, norm(f.force_n));
    prev_tip = tip;
    prev_f = f.force_n;
  }
  r.energy_mj = running;
  r.presses = observer.meter().cycles();
  return r;
}

/// The press without and with the controller.
inline PressEnergy press_energy(const Patient& p, const HapticsSettings& params, const PressPath& path) {
  return PressEnergy{run_press(p, params, path, false), run_press(p, params, path, true)};
}

}  // namespace palpsim::bench
