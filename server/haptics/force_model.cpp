#include "haptics/force_model.h"

#include <algorithm>
#include <cmath>

namespace palpsim {
namespace {

// the smallest voxel edge of the patient grid (mm); the grid is isotropic in practice
double voxel_mm(const Patient& p) {
  return std::min(p.grid.spacing_mm.x, std::min(p.grid.spacing_mm.y, p.grid.spacing_mm.z));
}

bool inside(const PatientSample& s) { return s.in_grid && s.body >= 0.5; }

// the patient's volumes at p_mm, trilinearly with one set of weights; kForce = false
// reads C and B only, what the skin search needs (a third of the reads, decided at
// compile time so the haptic path pays nothing for the choice)
template <bool kForce>
PatientSample sample_volumes(const Patient& patient, const Vec3& p_mm) {
  PatientSample s;
  const Vec3 ijk = patient.grid.to_index(p_mm);
  // outside the grid (or not finite): outside the body
  if (!within_grid(patient.grid, ijk)) return s;
  s.in_grid = true;
  for_each_trilinear_corner(patient.grid, ijk, [&](std::size_t n, double w) {
    s.body += w * patient.body.data[n];
    s.dist_skin_mm += w * patient.dist_skin_mm.data[n];
    if constexpr (kForce) {
      s.force_mm += w * patient.force.data[n];
      const Vec3f& gf = patient.grad_force.data[n];
      s.grad_force += Vec3{gf.x * w, gf.y * w, gf.z * w};
    }
  });
  return s;
}

// C and B only: what the skin search needs
PatientSample sample_skin(const Patient& patient, const Vec3& p_mm) { return sample_volumes<false>(patient, p_mm); }

// the skin crossing of the ray tip + t * out (0 <= t <= max_len_mm), found by stepping
// at most the depth under the skin (a distance to the skin, so no crossing is stepped
// over when the step is larger than a quarter voxel) and then bisecting the last step;
// false when the ray leaves the grid or max_len_mm inside the body
bool skin_crossing(const Patient& patient, const Vec3& tip_mm, const Vec3& out, double tip_depth_mm,
                   double max_len_mm, Vec3& crossing_mm) {
  const double h = voxel_mm(patient);
  double t_in = 0, t_out = -1;
  double t = std::max(tip_depth_mm, 0.25 * h);
  for (int it = 0; it < 64 && t <= max_len_mm; ++it) {
    const PatientSample s = sample_skin(patient, tip_mm + out * t);
    if (!inside(s)) {
      t_out = t;
      break;
    }
    t_in = t;
    t += std::max(depth_from_sample(patient, s), 0.25 * h);
  }
  // no crossing, or only the grid's face (where the body is cut by the volume's border)
  if (t_out < 0 || !sample_skin(patient, tip_mm + out * t_out).in_grid) return false;
  // bisection of the last step to a thousandth of a voxel
  for (int it = 0; it < 24 && t_out - t_in > 1e-3 * h; ++it) {
    const double mid = 0.5 * (t_in + t_out);
    if (inside(sample_skin(patient, tip_mm + out * mid)))
      t_in = mid;
    else
      t_out = mid;
  }
  crossing_mm = tip_mm + out * (0.5 * (t_in + t_out));
  return true;
}

// p_mm moved into the box of the grid's voxel centres (index space, so oblique grids too)
Vec3 clamp_to_voxel_centres(const Grid& g, const Vec3& p_mm) {
  Vec3 ijk = g.to_index(p_mm);
  for (int a = 0; a < 3; ++a) ijk[a] = std::clamp(ijk[a], 0.0, double(g.size[a] - 1));
  return g.to_physical(ijk);
}

// the point where the segment from `from_mm` (in the grid) to `to_mm` leaves the grid's
// outer faces (half a voxel beyond the border voxels' centres), or `to_mm` when it does not
Vec3 cut_at_grid(const Grid& g, const Vec3& from_mm, const Vec3& to_mm) {
  const Vec3 a = g.to_index(from_mm), b = g.to_index(to_mm);
  double t = 1;
  for (int k = 0; k < 3; ++k) {
    const double lo = -0.5, hi = g.size[k] - 0.5, d = b[k] - a[k];
    if (b[k] < lo && d < 0) t = std::min(t, (lo - a[k]) / d);
    if (b[k] > hi && d > 0) t = std::min(t, (hi - a[k]) / d);
  }
  return from_mm + (to_mm - from_mm) * std::max(t, 0.0);
}

// the skin point nearest to the tip: out along -grad B (B = depth under the skin, by
// central differences of one voxel), then the crossing on that line
Vec3 nearest_skin_point(const Patient& patient, const Vec3& tip_mm, double depth_mm) {
  const double h = voxel_mm(patient);
  const Grid& g = patient.grid;
  Vec3 grad_b{0, 0, 0};
  for (int a = 0; a < 3; ++a) {
    Vec3 e{0, 0, 0};
    e[a] = h;
    // the probes stay within the grid's voxel centres: beyond the grid B samples as 0,
    // which is no skin but missing data, and where the grid cuts the body (every CT's
    // first and last slice) it turned the gradient towards the grid's face, so X was put
    // outside the grid and the deformation refused the contact (stability catalogue,
    // tests/stability: "tip on the volume border")
    const Vec3 p1 = clamp_to_voxel_centres(g, tip_mm + e), p0 = clamp_to_voxel_centres(g, tip_mm - e);
    const double span = p1[a] - p0[a];
    if (span > 1e-9 * h)
      grad_b[a] = (sample_skin(patient, p1).dist_skin_mm - sample_skin(patient, p0).dist_skin_mm) / span;
  }
  const double gn = norm(grad_b);
  if (!(gn > 1e-9)) return tip_mm;
  const Vec3 out = grad_b * (-1.0 / gn);
  Vec3 x;
  if (skin_crossing(patient, tip_mm, out, depth_mm, 3.0 * depth_mm + 4.0 * h, x)) return x;
  // no crossing within reach: a depth along the line, but never beyond the grid's faces,
  // since X must lie in the patient grid for the deformation (it refuses other contacts)
  return cut_at_grid(g, tip_mm, tip_mm + out * depth_mm);
}

}  // namespace

PatientSample sample_patient(const Patient& patient, const Vec3& p_mm) { return sample_volumes<true>(patient, p_mm); }

double depth_from_sample(const Patient& patient, const PatientSample& s) {
  return std::max(0.0, s.dist_skin_mm - 0.5 * voxel_mm(patient));
}

ForceSample compute_force(const Patient& patient, const HapticsSettings& params, const Vec3& tip_mm, double dt_s,
                          ProxyState& state) {
  ForceSample out;
  out.proxy_mm = tip_mm;
  out.skin_point_mm = tip_mm;
  const bool first = !state.has_previous;
  state.has_previous = true;

  // outside the body: exactly zero force, the proxy follows the tip
  const PatientSample s = sample_patient(patient, tip_mm);
  if (!inside(s)) {
    state.in_contact = false;
    state.force_n = Vec3{0, 0, 0};
    return out;
  }
  out.contact = true;
  out.depth_mm = depth_from_sample(patient, s);

  // direction of eq. 2: the normalised gradient, or the last good one where it is too small
  const double gn = norm(s.grad_force);
  Vec3 dir{0, 0, 0};
  bool have_dir = false;
  if (gn >= params.min_gradient_norm && std::isfinite(gn)) {
    dir = s.grad_force * (1.0 / gn);
    state.direction = dir;
    state.has_direction = true;
    have_dir = true;
  } else if (state.has_direction) {
    dir = state.direction;
    have_dir = true;
  }

  // eq. 2 proxy, then friction: interpolate with the previous proxy while in contact
  Vec3 proxy = have_dir ? tip_mm + dir * std::max(s.force_mm, 0.0) : tip_mm;
  if (state.in_contact) proxy = proxy * (1.0 - params.friction) + state.proxy_mm * params.friction;

  // spring, then the magnitude clamp, then the rate clamp (a blend of two forces within
  // the magnitude limit stays within it)
  Vec3 f = (tip_mm - proxy) * params.stiffness_n_per_mm;
  const double fn = norm(f);
  if (fn > params.max_force_n) {
    f *= params.max_force_n / fn;
    out.clamped = true;
  }
  const double dt = (first || !(dt_s > 0)) ? kNominalHapticPeriodS : dt_s;
  const double max_step_n = params.max_force_rate_n_per_s * dt;
  const Vec3 df = f - state.force_n;
  const double dfn = norm(df);
  if (dfn > max_step_n) {
    f = state.force_n + df * (max_step_n / dfn);
    out.clamped = true;
  }

  // skin point X: along the line through x and p, on the side of x away from p
  Vec3 away = tip_mm - proxy;
  double an = norm(away);
  if (!(an > 1e-9) && have_dir) {
    away = -dir;
    an = 1;
  }
  // where that line runs nearly along the skin it meets the skin far from the tip, or
  // only the grid's face: beyond three depths (a line up to ~70 degrees off the skin's
  // normal) the skin point nearest to the tip stands in, so X stays where the finger is
  const double reach_mm = 3.0 * out.depth_mm + 2.0 * voxel_mm(patient);
  if (!(an > 1e-9) || !skin_crossing(patient, tip_mm, away * (1.0 / an), out.depth_mm, reach_mm, out.skin_point_mm))
    out.skin_point_mm = nearest_skin_point(patient, tip_mm, out.depth_mm);

  // a non-finite value (a corrupt patient) resets the session instead of poisoning it
  if (!is_finite(f) || !is_finite(proxy) || !is_finite(out.skin_point_mm) || !std::isfinite(out.depth_mm)) {
    state = ProxyState{};
    ForceSample zero;
    zero.proxy_mm = tip_mm;
    zero.skin_point_mm = tip_mm;
    zero.reset = true;
    return zero;
  }
  state.in_contact = true;
  state.proxy_mm = proxy;
  state.force_n = f;
  out.force_n = f;
  out.proxy_mm = proxy;
  return out;
}

}  // namespace palpsim
