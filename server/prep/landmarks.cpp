#include "prep/landmarks.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>

#include "prep/pipeline.h"

namespace palpsim {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// what one axial slice holds: the body's left-right centre, the posterior-most bone near
// it, and the lateral bone on each side
struct Slice {
  double z_mm = 0;                                   // the slice's mean physical z
  double x_lo = INFINITY, x_hi = -INFINITY;          // the body's left-right extent (mm)
  Vec3 tip{kNaN, -INFINITY, kNaN};                   // posterior-most bone near the centre
  double lateral_mm2[2] = {0, 0};                    // bone beyond kCrestLateralMm: right (0), left (1)
  Vec3 lateral_sum[2] = {{0, 0, 0}, {0, 0, 0}};      // their physical sum, for the centroid
  std::size_t lateral_n[2] = {0, 0};
  double centre() const { return 0.5 * (x_lo + x_hi); }
};

// the per-slice summaries, ordered from inferior to superior
std::vector<Slice> slices_of(const Patient& p) {
  const Grid& g = p.grid;
  const int ax = axial_axis(g);
  std::vector<Slice> s(std::size_t(g.size[ax]));
  std::vector<std::size_t> n(s.size(), 0);
  const double pixel_mm2 = g.spacing_mm[(ax + 1) % 3] * g.spacing_mm[(ax + 2) % 3];
  for (int pass = 0; pass < 2; ++pass)
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const std::size_t idx = g.index(i, j, k);
          if (!p.body.data[idx]) continue;
          const Vec3i ijk{i, j, k};
          Slice& sl = s[std::size_t(ijk[ax])];
          const Vec3 q = g.to_physical(Vec3{double(i), double(j), double(k)});
          if (pass == 0) {
            sl.x_lo = std::min(sl.x_lo, q.x), sl.x_hi = std::max(sl.x_hi, q.x);
            sl.z_mm += q.z, ++n[std::size_t(ijk[ax])];
            continue;
          }
          if (!p.bone.data[idx]) continue;
          const double dx = q.x - sl.centre();
          if (std::abs(dx) <= kSpinousHalfWidthMm && q.y > sl.tip.y) sl.tip = q;
          if (std::abs(dx) > kCrestLateralMm) {
            const int side = dx > 0 ? 1 : 0;
            sl.lateral_mm2[side] += pixel_mm2;
            sl.lateral_sum[side] = sl.lateral_sum[side] + q;
            ++sl.lateral_n[side];
          }
        }
  std::vector<Slice> out;
  for (std::size_t i = 0; i < s.size(); ++i)
    if (n[i]) s[i].z_mm /= double(n[i]), out.push_back(s[i]);
  std::sort(out.begin(), out.end(), [](const Slice& a, const Slice& b) { return a.z_mm < b.z_mm; });
  return out;
}

// the tips: maxima of the posterior-most bone's y along z that stand out, far enough apart
std::vector<Vec3> spinous_tips(const std::vector<Slice>& s) {
  std::vector<std::size_t> peaks;
  for (std::size_t a = 0; a < s.size(); ++a) {
    // the whole window lies in the image: at its ends a slope would pass for a peak
    const bool inside = !s.empty() && s[a].z_mm - s.front().z_mm >= 0.5 * kSpinousSpacingMm &&
                        s.back().z_mm - s[a].z_mm >= 0.5 * kSpinousSpacingMm;
    if (!std::isfinite(s[a].tip.x) || !inside) continue;
    bool top = true;
    double low = INFINITY;
    for (std::size_t b = 0; b < s.size() && top; ++b) {
      if (b == a || std::abs(s[b].z_mm - s[a].z_mm) > 0.5 * kSpinousSpacingMm) continue;
      const double y = std::isfinite(s[b].tip.x) ? s[b].tip.y : -INFINITY;
      if (y > s[a].tip.y || (y == s[a].tip.y && b < a)) top = false;
      low = std::min(low, y);
    }
    if (top && s[a].tip.y - low >= kSpinousProminenceMm) peaks.push_back(a);
  }
  // the highest first; a peak within kSpinousSpacingMm of a kept one is dropped
  std::sort(peaks.begin(), peaks.end(), [&](std::size_t a, std::size_t b) { return s[a].tip.y > s[b].tip.y; });
  std::vector<Vec3> tips;
  for (std::size_t a : peaks) {
    // the middle of the run of slices as far back as the peak (within half a millimetre):
    // a process's flat posterior edge spans several slices, the peak is its first
    std::size_t first = a, last = a;
    const auto level = [&](std::size_t b) { return std::isfinite(s[b].tip.x) && s[b].tip.y >= s[a].tip.y - 0.5; };
    while (first > 0 && level(first - 1)) --first;
    while (last + 1 < s.size() && level(last + 1)) ++last;
    const Vec3 tip = s[(first + last) / 2].tip;
    bool apart = true;
    for (const Vec3& t : tips) apart = apart && std::abs(t.z - tip.z) >= kSpinousSpacingMm;
    if (apart) tips.push_back(tip);
  }
  std::sort(tips.begin(), tips.end(), [](const Vec3& a, const Vec3& b) { return a.z > b.z; });
  return tips;
}

// the top of the bone on `side` that the lowest slice holds, followed up to its last slice
// before a gap; false when the lowest slice holds none or no gap comes
bool crest_top(const std::vector<Slice>& s, int side, Vec3& top) {
  if (s.empty() || s[0].lateral_n[side] == 0) return false;
  std::size_t last = 0;
  while (last + 1 < s.size() && s[last + 1].lateral_n[side] > 0) ++last;
  if (last + 1 >= s.size()) return false;
  top = s[last].lateral_sum[side] * (1.0 / double(s[last].lateral_n[side]));
  return true;
}

// whether the body holds the physical point (false beyond the grid)
bool in_body(const Patient& p, const Vec3& q) {
  const Vec3 c = p.grid.to_index(q);
  const int i = int(std::lround(c.x)), j = int(std::lround(c.y)), k = int(std::lround(c.z));
  return p.grid.contains(i, j, k) && p.body.at(i, j, k);
}

// the skin above `bone` along +y, the press start beyond it, and the normal's angle to +y
SkinLandmark above(const Patient& p, const std::string& name, const Vec3& bone) {
  const double h = std::min({p.grid.spacing_mm.x, p.grid.spacing_mm.y, p.grid.spacing_mm.z});
  const Vec3 up{0, 1, 0};
  double t = 0;
  while (t < 400 && in_body(p, bone + up * (t + 0.25 * h))) t += 0.25 * h;
  SkinLandmark l;
  l.name = name;
  l.bone_mm = bone;
  l.depth_mm = t + 0.125 * h;
  l.skin_mm = bone + up * l.depth_mm;
  l.press_start_mm = l.skin_mm + up * kPressStandoffMm;
  l.press_travel_mm = kPressStandoffMm + l.depth_mm + kPressBeyondBoneMm;
  // the outward normal: -grad B a voxel and a half under the skin, by central differences
  const Vec3 c = p.grid.to_index(l.skin_mm - up * (1.5 * h));
  const int i = int(std::lround(c.x)), j = int(std::lround(c.y)), k = int(std::lround(c.z));
  Vec3 grad{0, 0, 0};
  const Vec3i at{i, j, k};
  for (int a = 0; a < 3; ++a) {
    Vec3i lo = at, hi = at;
    lo[a] = std::max(0, at[a] - 1), hi[a] = std::min(p.grid.size[a] - 1, at[a] + 1);
    if (!p.grid.contains(i, j, k) || hi[a] == lo[a]) continue;
    grad[a] = (p.dist_skin_mm.at(hi.x, hi.y, hi.z) - p.dist_skin_mm.at(lo.x, lo.y, lo.z)) /
              ((hi[a] - lo[a]) * p.grid.spacing_mm[a]);
  }
  const Vec3 n = p.grid.axes_to_physical(grad) * -1.0;
  const double len = norm(n);
  l.normal_angle_deg = len > 0 ? std::acos(std::clamp(n.y / len, -1.0, 1.0)) * 180.0 / M_PI : kNaN;
  return l;
}

}  // namespace

std::vector<SkinLandmark> find_landmarks(const Patient& p) {
  std::vector<SkinLandmark> out;
  if (!p.has_bone) return out;
  const std::vector<Slice> s = slices_of(p);
  int n = 0;
  for (const Vec3& tip : spinous_tips(s)) {
    SkinLandmark l = above(p, "spinous process " + std::to_string(n + 1), tip);
    if (l.depth_mm <= kMaxLandmarkDepthMm) out.push_back(l), ++n;
  }
  const char* sides[2] = {"iliac crest right", "iliac crest left"};
  for (int side : {1, 0}) {
    Vec3 top;
    if (!crest_top(s, side, top)) continue;
    const SkinLandmark l = above(p, sides[side], top);
    if (l.depth_mm <= kMaxLandmarkDepthMm) out.push_back(l);
  }
  return out;
}

std::string press_argument(const SkinLandmark& l) {
  char b[128];
  std::snprintf(b, sizeof b, "press:%.1f,%.1f,%.1f,%.1f", l.press_start_mm.x, l.press_start_mm.y, l.press_start_mm.z,
                l.press_travel_mm);
  return b;
}

}  // namespace palpsim
