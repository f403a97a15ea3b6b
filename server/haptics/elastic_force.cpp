#include "haptics/elastic_force.h"

#include <algorithm>
#include <cmath>

#include "haptics/force_field.h"

namespace palpsim {
namespace {

// The energy bound guesses the next step as the recent steps' exponential mean with this
// weight for the newest (a time constant of about 4 poses). The last step alone is a poor
// guess for a trembling hand: on seeded paths with 0.02 mm of jitter a pose and models made
// to pump energy, the hand gained 13-50 % of the energy it put in with the last step as the
// guess, 0.04-0.9 % with this mean (weights 0.1-0.5 gave much the same; tests/unit/
// haptics_elastic_force_test.cpp); smooth paths gain under 0.1 % either way.
constexpr double kStepSmoothing = 0.25;

// K v for a row-major 3x3 K
Vec3 mul(const std::array<double, 9>& k, const Vec3& v) {
  return {k[0] * v.x + k[1] * v.y + k[2] * v.z, k[3] * v.x + k[4] * v.y + k[5] * v.z,
          k[6] * v.x + k[7] * v.y + k[8] * v.z};
}

// f without its part along n that would pull the finger into the body (dot(f, n) > 0)
Vec3 never_pull(const Vec3& f, const Vec3& n) {
  const double along = dot(f, n);
  return along > 0 ? f - n * along : f;
}

}  // namespace

ElasticModel make_elastic_model(const Grid& grid, const Vec3& tip_mm, bool contact, const Vec3& force_axes_n,
                                const Vec3& normal_axes, double stiffness_n_per_mm, double depth_mm,
                                int contact_nodes) {
  ElasticModel m;
  m.x0_mm = tip_mm;
  const Vec3 f = grid.axes_to_physical(force_axes_n);
  const Vec3 n = grid.axes_to_physical(normal_axes);
  const double nn = norm(n);
  // a step without contact, or with a value no force can be made of, renders no force
  if (!contact || !is_finite(f) || !is_finite(tip_mm) || !(nn > 0.5) || !std::isfinite(nn) ||
      !std::isfinite(stiffness_n_per_mm) || !std::isfinite(depth_mm))
    return m;
  m.contact = true;
  m.f0_n = f;
  m.normal = n * (1.0 / nn);
  // a negative stiffness (a solve that did not converge) would make the force grow outwards
  m.stiffness_n_per_mm = std::max(0.0, stiffness_n_per_mm);
  const Vec3& u = m.normal;
  const double nv[3] = {u.x, u.y, u.z};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) m.k_n_per_mm[std::size_t(3 * r + c)] = -m.stiffness_n_per_mm * nv[r] * nv[c];
  m.depth_mm = depth_mm;
  m.contact_nodes = contact_nodes;
  return m;
}

Vec3 elastic_model_force(const ElasticModel& m, const Vec3& x_mm) {
  if (!m.contact) return Vec3{0, 0, 0};
  return never_pull(m.f0_n + mul(m.k_n_per_mm, x_mm - m.x0_mm), m.normal);
}

ElasticRenderStep render_elastic(ElasticRenderState& s, const ElasticModel* fresh, const HapticsSettings& params,
                                 const Vec3& tip_mm, bool contact, double dt_s, double now_s) {
  ElasticRenderStep out;
  const bool first = !s.has_previous;
  s.has_previous = true;
  if (first) s.tip_mm = tip_mm;  // no step before the first pose
  // the tip's step since the last pose, and the smoothed step that guesses the next one
  const Vec3 dx = tip_mm - s.tip_mm;
  s.step_mm = s.step_mm * (1.0 - kStepSmoothing) + dx * kStepSmoothing;

  // outside the body: exactly zero, and the press's model, jumps and store are dropped
  if (!contact) {
    s.model = ElasticModel{};
    s.offset_n = Vec3{0, 0, 0};
    s.force_n = Vec3{0, 0, 0};
    s.stored_mj = 0;
    s.in_contact = false;
    s.left_s = now_s;
    s.tip_mm = tip_mm;
    return out;
  }
  // the tip entered: nothing stored yet, and the step into the body did no work (no force)
  if (!s.in_contact) {
    s.in_contact = true;
    s.stored_mj = 0;
    s.force_n = Vec3{0, 0, 0};
  }

  // a newer model of this press: what it changes at x is the jump; the rest of it is rendered
  // on top of the new model and taken away a step at a time below
  if (fresh && fresh->pose_server_time_s > s.left_s) {
    const Vec3 before = elastic_model_force(s.model, tip_mm) + s.offset_n;
    const Vec3 after = elastic_model_force(*fresh, tip_mm);
    out.updated = true;
    out.jump_n = norm(after - before);
    out.jump_bounded = out.jump_n > params.elastic_max_jump_n;
    s.model = *fresh;
    s.offset_n = before - after;
  }
  const double on = norm(s.offset_n);
  s.offset_n = on > params.elastic_max_jump_n ? s.offset_n * (1.0 - params.elastic_max_jump_n / on) : Vec3{0, 0, 0};

  // the energy the hand put into the tissue over the last step: the previous force acted over it
  s.stored_mj -= dot(s.force_n, dx);

  // the model, the jumps' rest, never pulling; then the clamps eq. 2 has
  Vec3 f = clamp_force(never_pull(elastic_model_force(s.model, tip_mm) + s.offset_n, s.model.normal), s.force_n,
                       params, first ? 0.0 : dt_s, out.clamped);

  // the energy bound: over the guessed next step the force gives back at most what is stored
  const double give = dot(f, s.step_mm);
  if (give > 0 && give > s.stored_mj) {
    f *= std::max(0.0, s.stored_mj) / give;
    out.passivity_limited = true;
  }

  // a non-finite value (a corrupt model) resets the state instead of poisoning it
  if (!is_finite(f) || !std::isfinite(s.stored_mj)) {
    s = ElasticRenderState{};
    s.has_previous = true;
    s.left_s = now_s;
    s.tip_mm = tip_mm;
    ElasticRenderStep zero;
    zero.reset = true;
    return zero;
  }
  s.force_n = f;
  s.tip_mm = tip_mm;
  out.force_n = f;
  return out;
}

}  // namespace palpsim
