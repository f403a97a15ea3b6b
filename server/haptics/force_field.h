// The per-pose math of the force model (the paper's eq. 2 with friction, spring and
// clamps) on any grid of the volumes it reads: the whole patient on the server, or a
// patch of it (force_patch.h) in the thin haptic client, which compiles this same
// header. Header-only and free of ITK, ZeroMQ and protobuf; no allocation, no locks.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "core/grid.h"
#include "core/scene.h"
#include "core/vec3.h"
#include "core/volume.h"

namespace palpsim {

/// A session's proxy state between poses (a few dozen bytes, trivially copyable).
/// Value-initialise it (`ProxyState{}`) for a fresh session or a reset.
struct ProxyState {
  Vec3 proxy_mm{0, 0, 0};      // proxy of the previous pose (valid when in_contact)
  Vec3 direction{0, 0, 0};     // last good unit gradient direction of F (valid when has_direction)
  Vec3 force_n{0, 0, 0};       // force sent for the previous pose (for the rate clamp)
  bool in_contact = false;     // the previous pose was inside the body
  bool has_direction = false;  // direction holds a usable unit vector
  bool has_previous = false;   // a previous pose exists (else dt is taken as one haptic period)
};

/// The haptic period assumed when no previous pose gives dt (s): 1 kHz.
constexpr double kNominalHapticPeriodS = 1e-3;

/// Trilinear samples of the volumes that the force model reads, at one point.
struct PatientSample {
  double body = 0;          // C, in [0, 1]; >= 0.5 counts as inside
  double dist_skin_mm = 0;  // B (0 where the grid carries no B, as a patch does not)
  double force_mm = 0;      // F
  Vec3 grad_force{0, 0, 0}; // grad F (mm/mm, physical axes)
  bool in_grid = false;     // the point lies within half a voxel of the grid
};

/// The volumes of the force model on one grid, i fastest: the patient's, or a patch's.
/// `dist_skin_mm` may be null (a patch carries no B; samples then read 0).
struct FieldView {
  const Grid* grid = nullptr;
  const std::uint8_t* body = nullptr;    // C (0 or 1)
  const float* dist_skin_mm = nullptr;   // B (mm) or null
  const float* force_mm = nullptr;       // F (mm)
  const Vec3f* grad_force = nullptr;     // grad F (mm/mm)
};

/// True when a sample counts as inside the body.
inline bool inside(const PatientSample& s) { return s.in_grid && s.body >= 0.5; }

/// Samples the view trilinearly at a continuous voxel index of its grid with one set of
/// weights (edge voxels replicated). kForce = false reads C and B only (the skin search).
/// Beyond half a voxel outside the grid everything is zero and in_grid is false.
template <bool kForce>
PatientSample sample_field(const FieldView& v, const Vec3& ijk) {
  PatientSample s;
  if (!within_grid(*v.grid, ijk)) return s;
  s.in_grid = true;
  for_each_trilinear_corner(*v.grid, ijk, [&](std::size_t n, double w) {
    s.body += w * v.body[n];
    if (v.dist_skin_mm) s.dist_skin_mm += w * v.dist_skin_mm[n];
    if constexpr (kForce) {
      s.force_mm += w * v.force_mm[n];
      const Vec3f& gf = v.grad_force[n];
      s.grad_force += Vec3{gf.x * w, gf.y * w, gf.z * w};
    }
  });
  return s;
}

/// The force clamps of every force model: `f` (N) limited to params.max_force_n, then to a
/// change of at most params.max_force_rate_n_per_s * dt from `previous_n`, the force sent
/// for the previous pose (`dt_s` <= 0: no previous pose, kNominalHapticPeriodS). A blend of
/// two forces within the magnitude limit stays within it, so the result keeps both. Sets
/// `clamped` when either changed the force.
inline Vec3 clamp_force(Vec3 f, const Vec3& previous_n, const HapticsSettings& params, double dt_s, bool& clamped) {
  const double fn = norm(f);
  if (fn > params.max_force_n) {
    f *= params.max_force_n / fn;
    clamped = true;
  }
  const double dt = dt_s > 0 ? dt_s : kNominalHapticPeriodS;
  const double max_step_n = params.max_force_rate_n_per_s * dt;
  const Vec3 df = f - previous_n;
  const double dfn = norm(df);
  if (dfn > max_step_n) {
    f = previous_n + df * (max_step_n / dfn);
    clamped = true;
  }
  return f;
}

/// What eq. 2, friction, the spring and the clamps give for one pose.
struct ProxyStep {
  Vec3 force_n{0, 0, 0};   // f = k (x - p), clamped; exactly zero outside the body
  Vec3 proxy_mm{0, 0, 0};  // p after friction (the tip itself outside the body)
  Vec3 direction{0, 0, 0}; // the unit direction eq. 2 used (valid when has_direction)
  bool has_direction = false;
  bool contact = false;    // the tip is inside the body
  bool clamped = false;    // the magnitude or the rate clamp changed the force
  bool reset = false;      // a non-finite value reset the state (corrupt input)
};

/// Runs eq. 2 with friction, spring, magnitude and rate clamps for device tip `tip_mm`
/// given the sample `s` of the volumes there, and advances `state`. `dt_s` is the time
/// since the previous pose (<= 0 or none: kNominalHapticPeriodS); it scales the rate clamp.
inline ProxyStep proxy_step(const PatientSample& s, const HapticsSettings& params, const Vec3& tip_mm, double dt_s,
                            ProxyState& state) {
  ProxyStep out;
  out.proxy_mm = tip_mm;
  const bool first = !state.has_previous;
  state.has_previous = true;

  // outside the body: exactly zero force, the proxy follows the tip
  if (!inside(s)) {
    state.in_contact = false;
    state.force_n = Vec3{0, 0, 0};
    return out;
  }
  out.contact = true;

  // direction of eq. 2: the normalised gradient, or the last good one where it is too small
  const double gn = norm(s.grad_force);
  if (gn >= params.min_gradient_norm && std::isfinite(gn)) {
    out.direction = s.grad_force * (1.0 / gn);
    out.has_direction = true;
  } else if (state.has_direction) {
    out.direction = state.direction;
    out.has_direction = true;
  }

  // eq. 2 proxy, then friction: interpolate with the previous proxy while in contact
  Vec3 proxy = out.has_direction ? tip_mm + out.direction * std::max(s.force_mm, 0.0) : tip_mm;
  if (state.in_contact) proxy = proxy * (1.0 - params.friction) + state.proxy_mm * params.friction;

  // spring, then the clamps
  const Vec3 f = clamp_force((tip_mm - proxy) * params.stiffness_n_per_mm, state.force_n, params,
                             first ? 0.0 : dt_s, out.clamped);

  // a non-finite value (corrupt volumes) resets the state instead of poisoning it
  if (!is_finite(f) || !is_finite(proxy)) {
    state = ProxyState{};
    ProxyStep zero;
    zero.proxy_mm = tip_mm;
    zero.reset = true;
    return zero;
  }
  if (out.has_direction) {
    state.direction = out.direction;
    state.has_direction = true;
  }
  state.in_contact = true;
  state.proxy_mm = proxy;
  state.force_n = f;
  out.force_n = f;
  out.proxy_mm = proxy;
  return out;
}

}  // namespace palpsim
