#include "prep/contrast.h"

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "prep/distance.h"

namespace palpsim {
namespace {

// one region's sums: its core's values and place, its outer layer's cortex
struct RegionSums {
  std::size_t voxels = 0, core = 0, outer = 0, outer_bright = 0, bone = 0;
  double sum = 0, sum2 = 0;
  Vec3 place;
};

// grows each labelled core `steps` 6-neighbour steps into the unlabelled `within`
// voxels; a voxel goes to the core that reaches it first, so touching regions
// (a vessel beside a vertebra) stay apart
void grow_labels(const Volume<std::uint8_t>& within, std::vector<std::uint32_t>& label, int steps) {
  const Grid& g = within.grid;
  const long sx = 1, sy = g.size.x, sz = long(g.size.x) * g.size.y;
  std::vector<std::size_t> front, next;
  for (std::size_t i = 0; i < label.size(); ++i)
    if (label[i]) front.push_back(i);
  for (int step = 0; step < steps && !front.empty(); ++step) {
    next.clear();
    for (std::size_t idx : front) {
      const long i = long(idx % std::size_t(g.size.x)), j = long((idx / std::size_t(g.size.x)) % std::size_t(g.size.y)),
                 k = long(idx / std::size_t(sz));
      const bool ok[6] = {i > 0, i < g.size.x - 1, j > 0, j < g.size.y - 1, k > 0, k < g.size.z - 1};
      const long off[6] = {-sx, sx, -sy, sy, -sz, sz};
      for (int d = 0; d < 6; ++d) {
        if (!ok[d]) continue;
        const std::size_t nb = std::size_t(long(idx) + off[d]);
        if (label[nb] || !within.data[nb]) continue;
        label[nb] = label[idx];
        next.push_back(nb);
      }
    }
    front.swap(next);
  }
}

}  // namespace

double contrast_level(const BoneThresholds& t) { return std::min(t.low, std::max(t.cancellous, t.low - 100)); }

std::vector<ContrastRegion> find_contrast_regions(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                                  const Volume<std::uint8_t>& bone, const BoneThresholds& t,
                                                  const SpineColumn& column, Volume<std::uint8_t>* regions,
                                                  int threads) {
  const Grid& g = image.grid;
  const double voxel_ml = g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z / 1000.0;
  const double h = std::max({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
  if (regions) *regions = Volume<std::uint8_t>(g, 0);
  const double level = contrast_level(t);

  // bright voxels, their thick core, and the core grown back within them (a region)
  Volume<std::uint8_t> bright(g), core(g);
  parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) bright.data[i] = body.data[i] && image.data[i] >= level;
  });
  {
    const Volume<float> d2 = squared_distance_mm2(bright, false, threads);
    const float r2 = float(kContrastCoreMm * kContrastCoreMm);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) core.data[i] = d2.data[i] > r2;
    });
  }
  if (count_nonzero(core) == 0) return {};
  std::vector<std::uint32_t> label;
  const std::uint32_t n = component_labels(core, label);
  grow_labels(bright, label, int(std::ceil(kContrastCoreMm / h)) + 1);

  // per region: the core's values, then its outer layer against the core's mean
  std::vector<RegionSums> sums(n + 1);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        const std::size_t idx = g.index(i, j, k);
        if (!label[idx]) continue;
        RegionSums& r = sums[label[idx]];
        ++r.voxels;
        r.bone += bone.data[idx] != 0;
        r.place += g.to_physical(Vec3{double(i), double(j), double(k)});
        if (!core.data[idx]) continue;
        ++r.core;
        r.sum += image.data[idx], r.sum2 += double(image.data[idx]) * image.data[idx];
      }
  for (std::size_t idx = 0; idx < label.size(); ++idx) {
    RegionSums& r = sums[label[idx]];
    if (!label[idx] || core.data[idx] || r.core == 0) continue;
    ++r.outer;
    r.outer_bright += image.data[idx] >= r.sum / double(r.core) + kShellContrastHu;
  }

  // the regions that are large, homogeneous, without cortex and outside the column
  std::vector<ContrastRegion> found;
  std::vector<std::uint8_t> keep(n + 1, 0);
  for (std::uint32_t l = 1; l <= n; ++l) {
    const RegionSums& r = sums[l];
    if (r.core == 0 || double(r.voxels) * voxel_ml < kMinContrastMl) continue;
    ContrastRegion c;
    c.volume_ml = double(r.voxels) * voxel_ml;
    c.centroid_mm = r.place * (1.0 / double(r.voxels));
    c.mean_hu = r.sum / double(r.core);
    c.sd_hu = std::sqrt(std::max(0.0, r.sum2 / double(r.core) - c.mean_hu * c.mean_hu));
    c.shell_fraction = r.outer ? double(r.outer_bright) / double(r.outer) : 0;
    c.bone_ml = double(r.bone) * voxel_ml;
    const Vec3& a = column.centroid_mm;
    const bool in_column = column.found && c.centroid_mm.z >= column.from_mm - kColumnRadiusMm &&
                           c.centroid_mm.z <= column.to_mm + kColumnRadiusMm &&
                           std::hypot(c.centroid_mm.x - a.x, c.centroid_mm.y - a.y) < kColumnRadiusMm;
    if (c.sd_hu > kMaxContrastSdHu || c.shell_fraction > kMaxShellFraction || in_column) continue;
    keep[l] = 1;
    found.push_back(c);
  }
  if (regions)
    for (std::size_t idx = 0; idx < label.size(); ++idx) regions->data[idx] = keep[label[idx]];
  std::sort(found.begin(), found.end(),
            [](const ContrastRegion& a, const ContrastRegion& b) { return a.volume_ml > b.volume_ml; });
  return found;
}

std::string contrast_regions_json(const std::vector<ContrastRegion>& regions) {
  std::ostringstream s;
  s << std::setprecision(6) << "[";
  for (std::size_t i = 0; i < regions.size(); ++i) {
    const ContrastRegion& r = regions[i];
    s << (i ? ", " : "") << "{\"volume_ml\": " << r.volume_ml << ", \"centroid_mm\": [" << r.centroid_mm.x << ", "
      << r.centroid_mm.y << ", " << r.centroid_mm.z << "], \"mean_hu\": " << r.mean_hu << ", \"sd_hu\": " << r.sd_hu
      << ", \"shell_fraction\": " << r.shell_fraction << ", \"bone_ml\": " << r.bone_ml << "}";
  }
  s << "]";
  return s.str();
}

}  // namespace palpsim
