// Recall and precision of a bone mask against reference bone within a distance, the
// shared CTs' reference labels on a patient grid, and thick slabs made from thin slices;
// shared by the bone mask's tests and bench/bone_bench.cpp.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <map>
#include <set>
#include <string>
#include <stdexcept>
#include <utility>
#include <vector>

#include "core/volume.h"
#include "prep/ct_io.h"
#include "prep/distance.h"

namespace palpsim::test {

// recall and precision of a bone mask against reference bone, each within `tol_mm`
struct Agreement {
  std::size_t ref = 0, ref_hit = 0, pred = 0, pred_hit = 0;
  double recall() const { return ref ? double(ref_hit) / double(ref) : 0; }
  double precision() const { return pred ? double(pred_hit) / double(pred) : 0; }
};

// `ref` and `pred` on one grid; `ignore` voxels (neither bone nor not) count for neither
inline Agreement agreement(const Volume<std::uint8_t>& ref, const Volume<std::uint8_t>& pred,
                    const Volume<std::uint8_t>& ignore, double tol_mm) {
  const Volume<float> to_pred = distance_to_mask_mm(pred);
  Volume<std::uint8_t> ref_or_ignored = ref;
  for (std::size_t i = 0; i < ref.data.size(); ++i) ref_or_ignored.data[i] |= ignore.data[i];
  const Volume<float> to_ref = distance_to_mask_mm(ref_or_ignored);
  Agreement a;
  for (std::size_t i = 0; i < ref.data.size(); ++i) {
    if (ref.data[i]) ++a.ref, a.ref_hit += to_pred.data[i] <= tol_mm;
    if (pred.data[i] && !ignore.data[i]) ++a.pred, a.pred_hit += to_ref.data[i] <= tol_mm;
  }
  return a;
}

// TotalSegmentator's labels of the shared DICOM series on a patient grid (nearest label
// voxel of each patient voxel centre): bone = T11, T12 (33, 32), humeri (69, 70), ribs
// 6-12 (97-103, 109-115); costal cartilage (117) calcifies with age and is as rigid, so
// it is neither counted as missed bone nor as a false one; the spine = T11 and T12
struct LabelReference {
  Volume<std::uint8_t> bone, cartilage, spine;
  Volume<std::uint8_t> id;  // the label itself (0-255) on the patient grid
};

// the reference's rib labels, left 6-12 (97-103) and right 6-12 (109-115)
inline std::vector<int> rib_label_ids() {
  std::vector<int> ids;
  for (int id = 97; id <= 103; ++id) ids.push_back(id);
  for (int id = 109; id <= 115; ++id) ids.push_back(id);
  return ids;
}
// "rib 7 left" for a rib label id, the name of a few others (TotalSegmentator's ids), the
// label number otherwise
inline std::string label_name(int id) {
  if (id >= 97 && id <= 103) return "rib " + std::to_string(id - 91) + " left";
  if (id >= 109 && id <= 115) return "rib " + std::to_string(id - 103) + " right";
  if (id == 32) return "T12";
  if (id == 33) return "T11";
  if (id >= 27 && id <= 31) return "L" + std::to_string(32 - id);
  if (id == 0) return "no label";
  if (id == 7) return "pancreas";
  if (id == 52) return "aorta";
  if (id == 63) return "inferior vena cava";
  if (id == 64) return "portal and splenic vein";
  if (id == 79) return "spinal cord";
  if (id == 86 || id == 87) return "back muscles";
  if (id == 117) return "costal cartilage";
  return "label " + std::to_string(id);
}
inline LabelReference dicom_label_reference(const Grid& g, const Volume<float>& labels) {
  const std::set<int> bone_ids = {32, 33, 69, 70, 97, 98, 99, 100, 101, 102, 103,
                                  109, 110, 111, 112, 113, 114, 115};
  const Grid& lg = labels.grid;
  LabelReference r{Volume<std::uint8_t>(g, 0), Volume<std::uint8_t>(g, 0), Volume<std::uint8_t>(g, 0),
                   Volume<std::uint8_t>(g, 0)};
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        const Vec3 c = lg.to_index(g.to_physical({double(i), double(j), double(k)}));
        const int li = int(std::lround(c.x)), lj = int(std::lround(c.y)), lk = int(std::lround(c.z));
        if (!lg.contains(li, lj, lk)) continue;
        const int id = int(std::lround(labels.at(li, lj, lk)));
        r.bone.at(i, j, k) = bone_ids.count(id) > 0;
        r.cartilage.at(i, j, k) = id == 117;
        r.spine.at(i, j, k) = id == 32 || id == 33;
        r.id.at(i, j, k) = std::uint8_t(std::clamp(id, 0, 255));
      }
  return r;
}

// the reference's label of the spinal cord (the canal's contents)
constexpr int kSpinalCordLabel = 79;

// below this value (HU) a voxel of disc_reference() is soft tissue, the disc itself;
// at or above it mostly the end plates and the bone that the labels leave between two
// vertebrae (the shared DICOM series at 2 mm: its disc voxels in the mask had a median of
// 144 HU, those outside 58 HU)
constexpr float kDiscSoftHu = 110;

// the disc between two vertebrae's labels (`upper_id`, `lower_id`): voxels of neither,
// along grid axis k (axial) between a voxel of one and a voxel of the other at most
// `max_gap_mm` apart, in the same column (i, j)
inline Volume<std::uint8_t> disc_reference(const Volume<std::uint8_t>& ids, int upper_id, int lower_id,
                                           double max_gap_mm = 15) {
  const Grid& g = ids.grid;
  Volume<std::uint8_t> disc(g, 0);
  const int gap = int(max_gap_mm / g.spacing_mm.z);
  for (int j = 0; j < g.size.y; ++j)
    for (int i = 0; i < g.size.x; ++i) {
      int last = -1, last_k = -1;  // the last vertebra label seen along k and where
      for (int k = 0; k < g.size.z; ++k) {
        const int id = ids.at(i, j, k);
        if (id != upper_id && id != lower_id) continue;
        if (last >= 0 && last != id && k - last_k - 1 <= gap)
          for (int m = last_k + 1; m < k; ++m) disc.at(i, j, m) = 1;
        last = id, last_k = k;
      }
    }
  return disc;
}

// TotalSegmentator's labels of the shared abdomen (ct/abdomen-lumbar-3mm.nii.gz), one
// NIfTI mask per structure in `dir` (rib_left_7.nii.gz, vertebrae_T12.nii.gz, sacrum,
// hip_*, femur_*, humerus_*: the per-structure files of its tests/reference_files/
// example_seg/ at commit 5de6e4d, made for that very CT), on a patient grid: bone = all
// of them; the spine = the vertebrae; `id` in the DICOM series' numbering (ribs 91 + n
// left, 103 + n right, T11 33, T12 32, L1-L5 31-27), 1 for other bone. Missing files
// count as empty; `found` says how many were read.
struct AbdomenReference {
  LabelReference labels;
  int found = 0;
};
inline AbdomenReference abdomen_label_reference(const Grid& g, const std::string& dir) {
  AbdomenReference a;
  LabelReference& r = a.labels;
  r = LabelReference{Volume<std::uint8_t>(g, 0), Volume<std::uint8_t>(g, 0), Volume<std::uint8_t>(g, 0),
                     Volume<std::uint8_t>(g, 0)};
  std::vector<std::pair<std::string, int>> files;
  for (int n = 1; n <= 12; ++n) {
    files.push_back({"rib_left_" + std::to_string(n), 91 + n});
    files.push_back({"rib_right_" + std::to_string(n), 103 + n});
  }
  files.push_back({"vertebrae_T11", 33});
  files.push_back({"vertebrae_T12", 32});
  for (int n = 1; n <= 5; ++n) files.push_back({"vertebrae_L" + std::to_string(n), 32 - n});
  for (const char* other : {"sacrum", "hip_left", "hip_right", "femur_left", "femur_right", "humerus_left",
                            "humerus_right"})
    files.push_back({other, 1});
  for (const auto& [name, id] : files) {
    const std::string path = dir + "/" + name + ".nii.gz";
    if (!std::filesystem::exists(path)) continue;
    ++a.found;
    const Volume<float> lab = read_ct(path, PrepSettings{}).image;
    const Grid& lg = lab.grid;
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const Vec3 c = lg.to_index(g.to_physical({double(i), double(j), double(k)}));
          const int li = int(std::lround(c.x)), lj = int(std::lround(c.y)), lk = int(std::lround(c.z));
          if (!lg.contains(li, lj, lk) || lab.at(li, lj, lk) < 0.5) continue;
          r.bone.at(i, j, k) = 1;
          r.spine.at(i, j, k) |= id >= 27 && id <= 33;
          r.id.at(i, j, k) = std::uint8_t(id);
        }
  }
  return a;
}

// recall within `tol_mm` of each label id of `ids` (voxels of that label with a `pred`
// voxel within tol_mm over all of them), keyed by id
inline std::map<int, Agreement> recall_per_label(const Volume<std::uint8_t>& ids, const Volume<std::uint8_t>& pred,
                                                 const std::vector<int>& which, double tol_mm) {
  const Volume<float> to_pred = distance_to_mask_mm(pred);
  std::map<int, Agreement> r;
  for (int id : which) r[id];
  for (std::size_t i = 0; i < ids.data.size(); ++i) {
    const auto it = r.find(ids.data[i]);
    if (it == r.end()) continue;
    ++it->second.ref;
    it->second.ref_hit += to_pred.data[i] <= tol_mm;
  }
  return r;
}

// the volume a thick-slice scanner makes of `image`: every `n` consecutive slices
// along grid axis k averaged into one slab n times as thick, centred between them
// (slices left over at the end are dropped)
inline Volume<float> average_slabs(const Volume<float>& image, int n) {
  const Grid& g = image.grid;
  if (n < 1 || g.size.z < n) throw std::invalid_argument("average_slabs: fewer slices than a slab");
  Grid s = g;
  s.size.z = g.size.z / n;
  s.spacing_mm.z = g.spacing_mm.z * n;
  s.origin_mm = g.to_physical({0, 0, 0.5 * (n - 1)});
  Volume<float> out(s, 0.0f);
  const std::size_t plane = std::size_t(g.size.x) * g.size.y;
  for (int k = 0; k < s.size.z; ++k)
    for (int m = 0; m < n; ++m)
      for (std::size_t p = 0; p < plane; ++p)
        out.data[std::size_t(k) * plane + p] += image.data[std::size_t(k * n + m) * plane + p] / float(n);
  return out;
}

// `labels` on average_slabs' grid: the label most of a slab's n slices hold at each
// voxel (what a segmentation of the thick slices would draw); a tie goes to the
// label of the first of them that is not background (a structure half in the slab
// shows at half contrast, still visible)
inline Volume<float> majority_slabs(const Volume<float>& labels, int n) {
  const Grid& g = labels.grid;
  Volume<float> out(average_slabs(labels, n).grid, 0.0f);
  const std::size_t plane = std::size_t(g.size.x) * g.size.y;
  for (int k = 0; k < out.grid.size.z; ++k)
    for (std::size_t p = 0; p < plane; ++p) {
      float best = 0;
      int best_count = 0;
      for (int m = 0; m < n; ++m) {
        const float v = labels.data[std::size_t(k * n + m) * plane + p];
        int count = 0;
        for (int q = 0; q < n; ++q) count += labels.data[std::size_t(k * n + q) * plane + p] == v;
        if (count > best_count || (count == best_count && best == 0 && v != 0)) best = v, best_count = count;
      }
      out.data[std::size_t(k) * plane + p] = best;
    }
  return out;
}

}  // namespace palpsim::test
