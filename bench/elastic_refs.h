// The elastic model's references in `palpsim-bench accuracy --elastic`
// (elastic_accuracy_bench.cpp): Hertz's sphere on a half-space, the patient refined 2x over a
// VOI (the discretisation reference), the skin point where the haptic path puts X, and the
// homogeneous block the Hertz rows press. Header-only, so that tests/unit checks them.
#pragma once

#include <cmath>
#include <memory>
#include <utility>
#include <vector>

#include "core/error.h"
#include "core/patient.h"
#include "deform/backend.h"
#include "deform/deform_math.h"

namespace palpsim::bench {

/// The landmark the shipped press goes over: X on the skin straight above it (the phantom's
/// PhantomGeometry names it).
inline constexpr const char* kPressLandmark = "spinous_tip_L3";

/// The homogeneous block of the shipped configuration's Hertz press (elastic_block()): 96 x
/// 72 x 96 voxels of 1 mm, the skin the node layer j = 68, soft tissue of 40 HU.
inline const Vec3i kBlockSize{96, 72, 96};
inline constexpr int kBlockSkinJ = 68;
inline constexpr float kBlockHu = 40;

/// Hertz's force (N) of a rigid sphere of radius r_mm pressed d_mm into an elastic half-space
/// of Young's modulus e_kpa and Poisson ratio nu: 4/3 E / (1 - nu^2) sqrt(R) d^(3/2).
inline double hertz_force_n(double e_kpa, double nu, double r_mm, double d_mm) {
  return 4.0 / 3.0 * (e_kpa * 1e-3) / (1 - nu * nu) * std::sqrt(r_mm) * std::pow(d_mm, 1.5);
}

/// Hertz's surface displacement into the half-space (mm) at distance r_mm from the axis of a
/// sphere of radius R_mm pressed d_mm: d - r^2 / 2R inside the contact radius a = sqrt(R d),
/// ((2 a^2 - r^2) asin(a / r) + a sqrt(r^2 - a^2)) / (pi R) outside (Johnson, Contact
/// Mechanics, eq. 3.42); it does not depend on E or nu.
inline double hertz_surface_mm(double r_mm, double R_mm, double d_mm) {
  const double a = std::sqrt(R_mm * d_mm), r = std::fabs(r_mm);
  if (r <= a) return d_mm - r * r / (2 * R_mm);
  return ((2 * a * a - r * r) * std::asin(a / r) + a * std::sqrt(r * r - a * a)) / (M_PI * R_mm);
}

/// Hertz's blocks (accuracy --elastic (iii), accuracy --halfspace): n^3 voxels of 1 mm, the
/// whole block the VOI, the skin node layer kHertzAir - 1 below the top, a sphere of kHertzR
/// mm pressed kHertzDepths at Poisson ratios kHertzNus.
inline constexpr double kHertzR = 8;
inline constexpr int kHertzAir = 3;
inline const double kHertzDepths[] = {kHertzR / 20, kHertzR / 10, kHertzR / 5};
inline const double kHertzNus[] = {0.45, 0.49};

/// The profile compares skin nodes within this many contact radii a = sqrt(R d) of the axis.
inline constexpr double kProfileRadii = 3;

/// The displacement (mm) of an elastic half-space (Young's modulus e_kpa, Poisson ratio nu)
/// under a normal point load of p_n N on its surface, at r_mm from the load's axis and z_mm
/// (>= 0) below the surface: {radial, positive away from the axis; along the load, into the
/// body} (Boussinesq; Johnson, Contact Mechanics, eq. 3.22). On the surface: -(1 - 2 nu)(1 +
/// nu) P / (2 pi E r) and (1 - nu^2) P / (pi E r).
inline std::pair<double, double> boussinesq_mm(double p_n, double e_kpa, double nu, double r_mm, double z_mm) {
  const double e = e_kpa * 1e-3;  // N/mm^2
  const double rho = std::hypot(r_mm, z_mm);
  const double c = (1 + nu) * p_n / (2 * M_PI * e);
  const double ur = c * (r_mm * z_mm / (rho * rho * rho) - (1 - 2 * nu) * r_mm / (rho * (rho + z_mm)));
  const double uz = c * (z_mm * z_mm / (rho * rho * rho) + 2 * (1 - nu) / rho);
  return {ur, uz};
}

/// The patient refined 2x over the box `voi`: a grid of 2 (n - 1) + 1 nodes per axis at half
/// the spacing whose node 2 i is the VOI's node i (same physical place, origin at the VOI's
/// first voxel), so that the same VOI faces are held. Every coarse node keeps its values; a
/// node between coarse nodes takes the mean of the 2, 4 or 8 around it (the trilinear
/// interpolant at that point) of the intensity and of B (dist_skin_mm), and is body (bone)
/// where the mean of the body (bone) mask is above 1/2, the rule elastic_tip_inside() applies
/// to the skin: a node halfway between a body node and an outside one is outside, so the
/// tissue ends at the coarse skin nodes as in the coarse model, and its staircase is
/// smoothed where most of the surrounding nodes are body. Only what the elastic model reads
/// is filled (intensity, body, bone, dist_skin_mm).
inline std::shared_ptr<Patient> refine_half(const Patient& p, const deform::Voi& voi) {
  auto f = std::make_shared<Patient>();
  Grid g = p.grid;
  g.size = {2 * voi.size.x - 1, 2 * voi.size.y - 1, 2 * voi.size.z - 1};
  g.spacing_mm = p.grid.spacing_mm * 0.5;
  g.origin_mm = p.grid.to_physical(Vec3(voi.lo.x, voi.lo.y, voi.lo.z));
  f->grid = g;
  f->intensity = Volume<float>(g, 0.f);
  f->body = Volume<std::uint8_t>(g, 0);
  f->bone = Volume<std::uint8_t>(g, 0);
  f->dist_skin_mm = Volume<float>(g, 0.f);
  for (int K = 0; K < g.size.z; ++K)
    for (int J = 0; J < g.size.y; ++J)
      for (int I = 0; I < g.size.x; ++I) {
        // the coarse nodes around fine node (I, J, K): 1 or 2 along each axis
        double hu = 0, body = 0, bone = 0, depth = 0;
        int n = 0;
        for (int c = (K & 1); c >= 0; --c)
          for (int b = (J & 1); b >= 0; --b)
            for (int a = (I & 1); a >= 0; --a) {
              const std::size_t e = p.grid.index(voi.lo.x + I / 2 + a, voi.lo.y + J / 2 + b, voi.lo.z + K / 2 + c);
              hu += p.intensity.data[e];
              body += p.body.data[e] ? 1 : 0;
              bone += p.bone.data[e] ? 1 : 0;
              depth += p.dist_skin_mm.data[e];
              ++n;
            }
        const std::size_t m = g.index(I, J, K);
        f->intensity.data[m] = float(hu / n);
        f->body.data[m] = body / n > 0.5 ? 1 : 0;
        f->bone.data[m] = bone / n > 0.5 ? 1 : 0;
        f->dist_skin_mm.data[m] = float(depth / n);
        f->has_bone = f->has_bone || f->bone.data[m];
      }
  f->source = p.source + " refined 2x";
  return f;
}

/// The body mask C at a continuous voxel index, trilinear (0 outside the grid).
inline double body_at(const Patient& p, const Vec3& ijk) {
  const Vec3f t{float(ijk.x), float(ijk.y), float(ijk.z)};
  return deform::trilinear<float>(
      [&](int i, int j, int k) { return p.grid.contains(i, j, k) ? float(p.body.data[p.grid.index(i, j, k)] != 0) : 0.0f; },
      t);
}

/// The skin point X (mm) on the ray from `inside_mm` (in the body) along `dir` (unit): where the
/// trilinear body mask C falls to 1/2, the skin the haptic path puts X on and elastic_tip_inside()
/// tests (bisection to 1e-6 mm within `reach_mm`). Throws when the ray does not leave the body.
inline Vec3 skin_point_along(const Patient& p, const Vec3& inside_mm, const Vec3& dir, double reach_mm = 200) {
  auto in = [&](double t) { return body_at(p, p.grid.to_index(inside_mm + dir * t)) > 0.5; };
  if (!in(0) || in(reach_mm)) throw Error("elastic accuracy: no skin on the ray from the press's landmark");
  double lo = 0, hi = reach_mm;
  while (hi - lo > 1e-6) {
    const double mid = 0.5 * (lo + hi);
    (in(mid) ? lo : hi) = mid;
  }
  return inside_mm + dir * (0.5 * (lo + hi));
}

/// A homogeneous block for the Hertz rows: `size` voxels of h_mm, body (soft tissue of `hu`) on
/// the nodes j <= skin_j, air above; B (depth under the skin) as prep measures it, to the first
/// outside node: (skin_j + 1 - j) h.
inline std::shared_ptr<Patient> elastic_block(const Vec3i& size, double h_mm, int skin_j, float hu) {
  auto p = std::make_shared<Patient>();
  Grid g;
  g.size = size;
  g.spacing_mm = {h_mm, h_mm, h_mm};
  p->grid = g;
  p->intensity = Volume<float>(g, -1000.f);
  p->body = Volume<std::uint8_t>(g, 0);
  p->bone = Volume<std::uint8_t>(g, 0);
  p->dist_skin_mm = Volume<float>(g, 0.f);
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j <= skin_j && j < size.y; ++j)
      for (int i = 0; i < size.x; ++i) {
        const std::size_t m = g.index(i, j, k);
        p->intensity.data[m] = hu;
        p->body.data[m] = 1;
        p->dist_skin_mm.data[m] = float((skin_j + 1 - j) * h_mm);
      }
  p->source = "block";
  return p;
}

/// A block press: X on the skin node at the centre of the top, x d_mm below it (along -y)
inline DeformContact block_press(const Patient& b, int skin_j, double d_mm) {
  const Vec3 X = b.grid.to_physical(Vec3(b.grid.size.x / 2, skin_j, b.grid.size.z / 2));
  return {X, X - Vec3{0, d_mm, 0}};
}

/// Hertz's surface profile against a field on a block pressed by block_press(): relative RMS (%)
/// of the displacement into the block (-u_y) over the skin nodes within kProfileRadii contact
/// radii of the axis, against hertz_surface_mm()
inline double profile_error(const Patient& b, int skin_j, const deform::Voi& voi, const std::vector<Vec3>& u_mm, double R, double d) {
  const double a = std::sqrt(R * d), h = b.grid.spacing_mm.x;
  const int ci = b.grid.size.x / 2, ck = b.grid.size.z / 2, reach = int(std::ceil(kProfileRadii * a / h));
  double num = 0, den = 0;
  for (int dk = -reach; dk <= reach; ++dk)
    for (int di = -reach; di <= reach; ++di) {
      const double r = h * std::hypot(di, dk);
      if (r > kProfileRadii * a) continue;
      const Vec3i l = Vec3i{ci + di, skin_j, ck + dk} - voi.lo;
      const double w = voi.contains(l.x, l.y, l.z) ? -u_mm[std::size_t(voi.index(l.x, l.y, l.z))].y : 0.0;
      const double wh = hertz_surface_mm(r, R, d);
      num += (w - wh) * (w - wh);
      den += wh * wh;
    }
  return den > 0 ? 100 * std::sqrt(num / den) : NAN;
}

}  // namespace palpsim::bench
