// The expected skin point of an approaching tip (approach.h).
#include "deform/approach.h"

#include <algorithm>
#include <cmath>

namespace palpsim::deform {

Vec3 body_centroid_vox(const Patient& p) {
  const Grid& g = p.grid;
  if (p.body.data.size() != g.count()) return {0.5 * (g.size.x - 1), 0.5 * (g.size.y - 1), 0.5 * (g.size.z - 1)};
  double sx = 0, sy = 0, sz = 0, n = 0;
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j) {
      const std::uint8_t* row = &p.body.data[g.index(0, j, k)];
      for (int i = 0; i < g.size.x; ++i)
        if (row[i]) {
          sx += i;
          sy += j;
          sz += k;
          n += 1;
        }
    }
  if (n == 0) return {0.5 * (g.size.x - 1), 0.5 * (g.size.y - 1), 0.5 * (g.size.z - 1)};
  return {sx / n, sy / n, sz / n};
}

bool expected_skin_voxel(const Patient& p, const Vec3& tip_mm, int radius_vox, const Vec3& centroid_vox, Vec3i& out,
                         bool* near) {
  if (near) *near = false;
  if (!std::isfinite(tip_mm.x) || !std::isfinite(tip_mm.y) || !std::isfinite(tip_mm.z)) return false;
  const Grid& g = p.grid;
  if (p.body.data.size() != g.count() || g.count() == 0) return false;  // no body mask
  const Vec3 ti = g.to_index(tip_mm);
  // the tip clamped into the grid (continuous index) and its voxel
  Vec3 tc;
  Vec3i t;
  for (int a = 0; a < 3; ++a) {
    tc[a] = std::clamp(ti[a], 0.0, double(g.size[a] - 1));
    t[a] = int(std::floor(tc[a] + 0.5));
  }
  auto body = [&](int i, int j, int k) { return g.contains(i, j, k) && p.body.data[g.index(i, j, k)] != 0; };
  // rings of growing Chebyshev radius around the tip voxel, the nearest body voxel by
  // distance in mm from the (unclamped) tip; a ring r lies at least (r - 1) voxel edges
  // beyond the clamped tip's voxel, so the search stops once that exceeds the best distance
  const Vec3& h = g.spacing_mm;
  const double h_min = std::min(h.x, std::min(h.y, h.z));
  double best = INFINITY;
  for (int r = 0; r <= radius_vox; ++r) {
    const double ring_min = (r - 1) * h_min;
    if (ring_min > 0 && ring_min * ring_min > best) break;
    auto visit = [&](int i, int j, int k) {
      if (!body(i, j, k)) return;
      const double dx = (i - ti.x) * h.x, dy = (j - ti.y) * h.y, dz = (k - ti.z) * h.z;
      const double d2 = dx * dx + dy * dy + dz * dz;
      if (d2 < best) {
        best = d2;
        out = {i, j, k};
      }
    };
    for (int dk = -r; dk <= r; ++dk)
      for (int dj = -r; dj <= r; ++dj) {
        const int k = t.z + dk, j = t.y + dj;
        if (k < 0 || j < 0 || k >= g.size.z || j >= g.size.y) continue;
        if (std::abs(dk) == r || std::abs(dj) == r) {
          // a face of the ring's cube: the whole row
          for (int di = -r; di <= r; ++di) visit(t.x + di, j, k);
        } else {
          // inside the cube's faces: the row's two ends
          visit(t.x - r, j, k);
          visit(t.x + r, j, k);
        }
      }
  }
  if (best < INFINITY) {
    if (near) *near = true;
    return true;
  }
  // none near: the first body voxel on the way to the body's centroid, half a voxel a step
  const Vec3 d = centroid_vox - tc;
  const int steps = int(std::ceil(2.0 * std::sqrt(d.x * d.x + d.y * d.y + d.z * d.z))) + 1;
  for (int s = 0; s <= steps; ++s) {
    const Vec3 q = tc + d * (double(s) / steps);
    const Vec3i v{int(std::floor(q.x + 0.5)), int(std::floor(q.y + 0.5)), int(std::floor(q.z + 0.5))};
    if (body(v.x, v.y, v.z)) {
      out = v;
      return true;
    }
  }
  return false;
}

}  // namespace palpsim::deform
