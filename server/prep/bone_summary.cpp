// The bone mask's summary: bone per region, the vertebral column, warnings.
#include <algorithm>
#include <cmath>
#include <sstream>
#include <vector>

#include "core/error.h"
#include "prep/flood.h"
#include "prep/pipeline.h"

namespace palpsim {
namespace {

// what one axial slice shows of the spine region
struct SliceSpine {
  bool body = false;       // the slice holds body
  double area_mm2 = 0;     // bone in the spine region
  double x = 0, y = 0, z = 0;  // the region's bone centroid (LPS, mm); z also without bone
  bool canal = false;      // the region's bone encloses a canal-sized hole
};

// whether the 2D mask `m` (nu x nv, row-major in u) encloses a 4-connected hole of
// min_px..max_px pixels
bool encloses_hole(const std::vector<std::uint8_t>& m, int nu, int nv, std::size_t min_px, std::size_t max_px) {
  std::vector<std::uint8_t> seen(m.size(), 0);
  std::vector<int> queue;
  const auto visit = [&](int a, int c) {
    const int p = c * nu + a;
    if (!seen[p] && !m[p]) seen[p] = 1, queue.push_back(p);
  };
  const auto flood = [&](std::size_t first) { flood_4(queue, first, nu, nv, visit); };
  // the background reachable from the slice's border, then each hole in turn
  for (int a = 0; a < nu; ++a) visit(a, 0), visit(a, nv - 1);
  for (int c = 0; c < nv; ++c) visit(0, c), visit(nu - 1, c);
  flood(0);
  for (int p0 = 0; p0 < nu * nv; ++p0) {
    if (seen[p0] || m[p0]) continue;
    const std::size_t first = queue.size();
    visit(p0 % nu, p0 / nu);
    flood(first);
    const std::size_t n = queue.size() - first;
    if (n >= min_px && n <= max_px) return true;
  }
  return false;
}

// each axial slice's body centroid, the spine region's bone (area, centroid, canal),
// and the bone per region into `s`
std::vector<SliceSpine> measure_slices(const Volume<std::uint8_t>& body, const Volume<std::uint8_t>& bone,
                                       BoneSummary& s, std::size_t counts[5]) {
  const Grid& g = body.grid;
  const int ax = axial_axis(g), u = ax == 0 ? 1 : 0, v = ax == 2 ? 1 : 2;
  const int n[3] = {g.size.x, g.size.y, g.size.z};
  const double sp[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z};
  const double pixel_mm2 = sp[u] * sp[v];
  std::vector<SliceSpine> out(static_cast<std::size_t>(n[ax]));
  std::vector<std::uint8_t> region(std::size_t(n[u]) * n[v]);
  for (int s_ = 0; s_ < n[ax]; ++s_) {
    SliceSpine& sl = out[std::size_t(s_)];
    // the body's centroid in this slice (physical x, y, z)
    double cx = 0, cy = 0, cz = 0;
    std::size_t cn = 0;
    int ijk[3];
    ijk[ax] = s_;
    for (int b = 0; b < n[v]; ++b)
      for (int a = 0; a < n[u]; ++a) {
        ijk[u] = a, ijk[v] = b;
        if (!body.at(ijk[0], ijk[1], ijk[2])) continue;
        const Vec3 p = g.to_physical(Vec3{double(ijk[0]), double(ijk[1]), double(ijk[2])});
        cx += p.x, cy += p.y, cz += p.z, ++cn;
      }
    if (cn == 0) continue;
    sl.body = true;
    ++s.body_slices;
    counts[0] += cn;
    cx /= double(cn), cy /= double(cn), sl.z = cz / double(cn);
    // each bone voxel to its region; the spine region's bone as a 2D mask
    std::size_t in_spine = 0;
    std::fill(region.begin(), region.end(), 0);
    for (int b = 0; b < n[v]; ++b)
      for (int a = 0; a < n[u]; ++a) {
        ijk[u] = a, ijk[v] = b;
        if (!bone.at(ijk[0], ijk[1], ijk[2])) continue;
        const Vec3 p = g.to_physical(Vec3{double(ijk[0]), double(ijk[1]), double(ijk[2])});
        if (p.x > cx + kSpineHalfWidthMm) ++counts[2];
        else if (p.x < cx - kSpineHalfWidthMm) ++counts[3];
        else if (p.y < cy - kSpineAnteriorMm) ++counts[4];
        else {
          ++in_spine, sl.x += p.x, sl.y += p.y;
          region[std::size_t(b) * n[u] + a] = 1;
        }
      }
    counts[1] += in_spine;
    sl.area_mm2 = double(in_spine) * pixel_mm2;
    if (in_spine == 0) continue;
    sl.x /= double(in_spine), sl.y /= double(in_spine);
    if (sl.area_mm2 >= kSpineMinAreaMm2) {
      ++s.spine_slices;
      sl.canal = encloses_hole(region, n[u], n[v], std::size_t(std::ceil(kCanalMinMm2 / pixel_mm2)),
                               std::size_t(kCanalMaxMm2 / pixel_mm2));
    }
  }
  return out;
}

// the longest chain of slices with spine-region bone joined across disc-sized gaps
// with a small centroid shift: [first, last] slice indices; first > last when none
std::pair<int, int> longest_chain(const std::vector<SliceSpine>& sl) {
  int best_first = 1, best_last = 0, first = -1, prev = -1;
  for (int s = 0; s < int(sl.size()); ++s) {
    if (!(sl[s].area_mm2 >= kSpineMinAreaMm2)) continue;
    const bool joins = prev >= 0 && std::abs(sl[s].z - sl[prev].z) <= kMaxDiscGapMm + 1e-6 &&
                       std::abs(sl[s].x - sl[prev].x) <= kMaxColumnShiftMm;
    if (!joins) first = s;
    prev = s;
    if (s - first > best_last - best_first) best_first = first, best_last = s;
  }
  return {best_first, best_last};
}

// the column found in the slices [first, last]: extent, segments, canal, verdict
SpineColumn judge_column(const std::vector<SliceSpine>& sl, int first, int last, int body_slices) {
  SpineColumn c;
  if (first > last) {
    c.reason = "no bone behind the body's centre near its midline";
    return c;
  }
  c.slices = last - first + 1;
  c.from_mm = std::min(sl[first].z, sl[last].z), c.to_mm = std::max(sl[first].z, sl[last].z);
  c.length_mm = c.to_mm - c.from_mm;
  double wsum = 0;
  for (int s = first; s <= last; ++s) {
    const SliceSpine& x = sl[s];
    if (x.area_mm2 >= kSpineMinAreaMm2) ++c.bone_slices;
    c.canal_slices += x.canal;
    c.centroid_mm += Vec3{x.x, x.y, x.z} * x.area_mm2, wsum += x.area_mm2;
  }
  if (wsum > 0) c.centroid_mm = c.centroid_mm * (1.0 / wsum);
  // segments: runs of at least kMinSegmentMm of slices between disc levels, where the
  // area falls below kSegmentLevel of the largest within kMaxDiscGapMm on both sides
  const double spacing = c.slices > 1 ? c.length_mm / double(c.slices - 1) : 1.0;
  const int reach = std::max(1, int(std::lround(kMaxDiscGapMm / spacing)));
  const auto peak = [&](int from, int to) {
    double m = 0;
    for (int s = std::max(from, first); s <= std::min(to, last); ++s) m = std::max(m, sl[s].area_mm2);
    return m;
  };
  int run = 0;
  for (int s = first; s <= last + 1; ++s) {
    const bool disc = s > last || sl[s].area_mm2 < kSegmentLevel * std::min(peak(s - reach, s - 1), peak(s + 1, s + reach));
    if (!disc) {
      ++run;
      continue;
    }
    c.segments += double(run) * spacing >= kMinSegmentMm;
    run = 0;
  }
  // the verdict
  std::ostringstream why;
  const bool long_enough = 2 * c.slices >= body_slices;
  const bool canal = double(c.canal_slices) >= kCanalMinFraction * double(c.slices) && c.canal_slices >= 2;
  const bool vertebrae = c.segments >= 2 || c.length_mm < kTwoVertebraeMm;
  c.found = long_enough && canal && vertebrae;
  why << "bone near the posterior midline over " << std::lround(c.length_mm) << " mm (" << c.slices << " of "
      << body_slices << " axial slices) with " << c.segments << " vertebra-like segment" << (c.segments == 1 ? "" : "s")
      << " and a spinal canal in " << c.canal_slices << " slices";
  if (!long_enough) why << ": shorter than half the body";
  else if (!canal) why << ": no spinal canal enclosed by its bone";
  else if (!vertebrae) why << ": no vertebrae (bodies between discs)";
  c.reason = why.str();
  return c;
}

}  // namespace

BoneSummary summarize_bone(const Volume<std::uint8_t>& body, const Volume<std::uint8_t>& bone) {
  const Grid& g = body.grid;
  if (!(bone.grid.size == g.size)) throw Error("summarize_bone: the body and bone masks are on different grids");
  BoneSummary s;
  const double voxel_ml = g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z / 1000.0;
  // voxels of: body, spine, left, right, anterior
  std::size_t n[5] = {0, 0, 0, 0, 0};
  const std::vector<SliceSpine> slices = measure_slices(body, bone, s, n);
  s.body_ml = double(n[0]) * voxel_ml;
  s.spine_ml = double(n[1]) * voxel_ml;
  s.left_ml = double(n[2]) * voxel_ml;
  s.right_ml = double(n[3]) * voxel_ml;
  s.anterior_ml = double(n[4]) * voxel_ml;
  s.bone_ml = s.spine_ml + s.left_ml + s.right_ml + s.anterior_ml;
  s.bone_fraction = s.body_ml > 0 ? s.bone_ml / s.body_ml : 0;
  const auto [first, last] = longest_chain(slices);
  s.column = judge_column(slices, first, last, s.body_slices);
  s.spine_found = s.column.found;

  // the warnings
  std::ostringstream w;
  if (s.bone_ml == 0) {
    s.warnings.push_back("no bone found: the force image has no bone term; check prep.bone_threshold and the CT");
  } else if (!s.spine_found) {
    w << "no spine found: " << s.column.reason
      << "; check the bone mask (bone.nrrd), the field of view and prep.bone_threshold";
    s.warnings.push_back(w.str());
    w.str("");
  }
  if (s.bone_fraction > kMaxBoneFraction) {
    w << "bone is " << std::lround(100 * s.bone_fraction) << "% of the body, above the plausible "
      << std::lround(100 * kMaxBoneFraction)
      << "%: contrast, metal or a bone threshold too low; check prep.bone_threshold (where the scene leaves it "
         "out, it is chosen from the image)";
    s.warnings.push_back(w.str());
  }
  return s;
}

}  // namespace palpsim
