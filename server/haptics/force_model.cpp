#include "haptics/force_model.h"

#include <algorithm>
#include <cmath>

namespace palpsim {
namespace {

// the smallest voxel edge of the patient grid (mm); the grid is isotropic in practice
double voxel_mm(const Patient& p) {
  return std::min(p.grid.spacing_mm.x, std::min(p.grid.spacing_mm.y, p.grid.spacing_mm.z));
}

// C and B only: what the skin search needs
PatientSample sample_skin(const Patient& patient, const Vec3& p_mm) {
  return sample_field<false>(patient_view(patient), patient.grid.to_index(p_mm));
}

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

// the paper's skin point: where the line through x and p crosses the skin on the side of
// x away from p (along -grad F where x and p coincide); false where that line runs
// nearly along the skin and meets it, or only the grid's face, beyond three depths (a
// line up to ~70 degrees off the skin's normal)
bool line_skin_point(const Patient& patient, const Vec3& tip_mm, const Vec3& proxy_mm, const ProxyStep& step,
                     double depth_mm, Vec3& x_mm) {
  Vec3 away = tip_mm - proxy_mm;
  double an = norm(away);
  if (!(an > 1e-9) && step.has_direction) {
    away = -step.direction;
    an = 1;
  }
  if (!(an > 1e-9)) return false;
  const double reach_mm = 3.0 * depth_mm + 2.0 * voxel_mm(patient);
  return skin_crossing(patient, tip_mm, away * (1.0 / an), depth_mm, reach_mm, x_mm);
}

}  // namespace

FieldView patient_view(const Patient& patient) {
  return FieldView{&patient.grid, patient.body.data.data(), patient.dist_skin_mm.data.data(), patient.force.data.data(),
                   patient.grad_force.data.data()};
}

PatientSample sample_patient(const Patient& patient, const Vec3& p_mm) {
  return sample_field<true>(patient_view(patient), patient.grid.to_index(p_mm));
}

double depth_from_sample(const Patient& patient, const PatientSample& s) {
  return std::max(0.0, s.dist_skin_mm - 0.5 * voxel_mm(patient));
}

ForceSample compute_force(const Patient& patient, const HapticsSettings& params, const Vec3& tip_mm, double dt_s,
                          ProxyState& state) {
  ForceSample out;
  out.proxy_mm = tip_mm;
  out.skin_point_mm = tip_mm;

  // eq. 2 with friction, spring and clamps (force_field.h, the code the haptic client runs too)
  const PatientSample s = sample_patient(patient, tip_mm);
  const ProxyStep step = proxy_step(s, params, tip_mm, dt_s, state);
  if (step.reset) {
    out.reset = true;
    return out;
  }
  if (!step.contact) return out;
  out.contact = true;
  out.clamped = step.clamped;
  out.depth_mm = depth_from_sample(patient, s);
  const Vec3& proxy = step.proxy_mm;

  // skin point X: the paper's line where the scene asks for it and that line meets the
  // skin near the tip, else the skin point nearest to the tip (it moves with the tip,
  // not with grad F's direction, which turns quickly beside bone)
  if (params.skin_point != SkinPointRule::kLine ||
      !line_skin_point(patient, tip_mm, proxy, step, out.depth_mm, out.skin_point_mm))
    out.skin_point_mm = nearest_skin_point(patient, tip_mm, out.depth_mm);

  // a non-finite value (a corrupt patient) resets the session instead of poisoning it
  if (!is_finite(out.skin_point_mm) || !std::isfinite(out.depth_mm)) {
    state = ProxyState{};
    ForceSample zero;
    zero.proxy_mm = tip_mm;
    zero.skin_point_mm = tip_mm;
    zero.reset = true;
    return zero;
  }
  out.force_n = step.force_n;
  out.proxy_mm = proxy;
  return out;
}

}  // namespace palpsim
