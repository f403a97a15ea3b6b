#include "render/camera.h"

#include <algorithm>
#include <cmath>

namespace palpsim::render {

namespace {
constexpr double kPi = 3.14159265358979323846;

// true when the nearest voxel of continuous index `ijk` is a body voxel
bool in_body(const Patient& p, const Vec3& ijk) {
  const int i = int(std::lround(ijk.x)), j = int(std::lround(ijk.y)), k = int(std::lround(ijk.z));
  return p.grid.contains(i, j, k) && p.body.data[p.grid.index(i, j, k)] != 0;
}
}  // namespace

Vec3 normalized(const Vec3& v) {
  const double n = norm(v);
  return n > 0 ? v / n : v;
}

int view_width(int width, int height) { return width - std::min(height / 3, width); }

Camera orbit_camera(const Grid& g, const ViewSettings& view, const Vec3& target_mm) {
  Camera c;
  const double az = view.azimuth_deg * kPi / 180, el = view.elevation_deg * kPi / 180;
  const Vec3 extent{g.size.x * g.spacing_mm.x, g.size.y * g.spacing_mm.y, g.size.z * g.spacing_mm.z};
  const double radius_mm = 0.5 * norm(extent);
  const double half_fov = kHalfFovDeg * kPi / 180;
  c.dist_mm = radius_mm / std::sin(half_fov);
  c.tan_h = std::tan(half_fov) / view.zoom;
  const Vec3 to_eye{std::sin(az) * std::cos(el), std::cos(az) * std::cos(el), std::sin(el)};
  c.eye = target_mm + to_eye * c.dist_mm;
  c.fwd = -to_eye;
  c.right = normalized(cross(c.fwd, Vec3{0, 0, 1}));
  c.up = cross(c.right, c.fwd);
  c.view_w = view_width(view.width, view.height);
  c.height = view.height;
  c.aspect = double(c.view_w) / view.height;
  return c;
}

Vec3 frame_target(const ViewSettings& view, bool has_tip, const Vec3& tip_mm, const Vec3& body_center_mm) {
  return (view.look_at_tip && has_tip) ? tip_mm : view.center_set ? view.center_mm : body_center_mm;
}

Vec3 body_center(const Grid& g, const Vec3i& body_lo, const Vec3i& body_hi) {
  if (body_hi.x < 0) return g.to_physical((Vec3(g.size) - Vec3{1, 1, 1}) * 0.5);
  return g.to_physical((Vec3(body_lo) + Vec3(body_hi)) * 0.5);
}

Vec3 body_center(const Patient& p) {
  const IndexBox b = mask_box(p.body);
  return body_center(p.grid, b.lo, b.hi);
}

std::optional<Vec3> pixel_ray(const Camera& c, double x_px, double y_px) {
  if (!(x_px >= 0 && x_px < c.view_w && y_px >= 0 && y_px < c.height)) return std::nullopt;
  // the ray caster's mapping: ndc from the pixel, screen right and up scaled to the frame edges
  const double nx = 2 * x_px / c.view_w - 1, ny = 1 - 2 * y_px / c.height;
  return normalized(c.fwd + c.right * (nx * c.tan_h * c.aspect) + c.up * (ny * c.tan_h));
}

std::optional<Vec3> first_body_hit(const Patient& p, const Vec3& origin_mm, const Vec3& dir) {
  const Grid& g = p.grid;
  const Vec3 o = g.to_index(origin_mm);
  const Vec3 a = g.physical_to_axes(dir);
  const Vec3 d{a.x / g.spacing_mm.x, a.y / g.spacing_mm.y, a.z / g.spacing_mm.z};  // voxel per mm
  // the ray's stretch inside the grid's voxel box (slab method, t in mm)
  double t0 = 0, t1 = 1e300;
  const double lo[3] = {-0.5, -0.5, -0.5}, hi[3] = {g.size.x - 0.5, g.size.y - 0.5, g.size.z - 0.5};
  const double os[3] = {o.x, o.y, o.z}, ds[3] = {d.x, d.y, d.z};
  for (int ax = 0; ax < 3; ++ax) {
    if (std::abs(ds[ax]) < 1e-12) {
      if (os[ax] < lo[ax] || os[ax] > hi[ax]) return std::nullopt;
      continue;
    }
    double ta = (lo[ax] - os[ax]) / ds[ax], tb = (hi[ax] - os[ax]) / ds[ax];
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
  }
  if (t0 > t1) return std::nullopt;
  // march in steps of a quarter of the smallest voxel edge, then bisect the crossing
  const double step_mm = 0.25 * std::min({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
  double prev = t0;
  for (double t = t0; t <= t1 + step_mm; t += step_mm) {
    const double tt = std::min(t, t1);
    if (in_body(p, o + d * tt)) {
      double out = prev, in = tt;
      if (tt == t0) return origin_mm + dir * tt;  // the ray starts inside the body
      const double tol_mm = 0.01 * std::min({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
      while (in - out > tol_mm) {
        const double mid = 0.5 * (in + out);
        (in_body(p, o + d * mid) ? in : out) = mid;
      }
      return origin_mm + dir * in;
    }
    prev = tt;
  }
  return std::nullopt;
}

}  // namespace palpsim::render
