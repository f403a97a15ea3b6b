// Recall and precision of a bone mask against reference bone within a distance,
// shared by the bone mask's tests.
#pragma once

#include <cstddef>
#include <cmath>
#include <cstdint>
#include <set>

#include "core/volume.h"
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
};
inline LabelReference dicom_label_reference(const Grid& g, const Volume<float>& labels) {
  const std::set<int> bone_ids = {32, 33, 69, 70, 97, 98, 99, 100, 101, 102, 103,
                                  109, 110, 111, 112, 113, 114, 115};
  const Grid& lg = labels.grid;
  LabelReference r{Volume<std::uint8_t>(g, 0), Volume<std::uint8_t>(g, 0), Volume<std::uint8_t>(g, 0)};
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
      }
  return r;
}

}  // namespace palpsim::test
