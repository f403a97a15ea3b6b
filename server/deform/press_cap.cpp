// The elastic press held short of bone (press_cap.h).
#include "deform/press_cap.h"

#include <algorithm>
#include <cmath>

#include "core/volume.h"

namespace palpsim::deform {

PressTissue tissue_along_press(const Patient& patient, const DeformContact& contact, double reach_mm) {
  PressTissue out;
  const Vec3 d = contact.tip_mm - contact.skin_point_mm;
  const double len = norm(d);
  if (!(len > 0) || !(reach_mm > 0) || patient.dist_bone_mm.data.empty()) return out;
  const Vec3 n = d * (1.0 / len);
  const Grid& g = patient.grid;
  const Vec3& h = g.spacing_mm;
  const double voxel = std::min({h.x, h.y, h.z});
  // bone is reached where A (the distance to the nearest bone voxel's centre) falls to
  // half a voxel: the bone voxel's face. Each step goes A less that half voxel, which no
  // bone can lie within, and at least a tenth of a voxel
  for (double t = 0; t <= reach_mm;) {
    const Vec3 ijk = g.to_index(contact.skin_point_mm + n * t);
    if (!within_grid(g, ijk)) return out;
    const double a = sample_trilinear(patient.dist_bone_mm, ijk);
    if (a <= 0.5 * voxel) {
      out.bone = true;
      out.thickness_mm = t;
      return out;
    }
    t += std::max(a - 0.5 * voxel, 0.1 * voxel);
  }
  return out;
}

DeformContact cap_press_at_bone(const Patient& patient, const DeformContact& contact, double min_tissue_fraction) {
  if (!(min_tissue_fraction > 0)) return contact;
  const Vec3 d = contact.tip_mm - contact.skin_point_mm;
  const double depth = norm(d);
  if (!(depth > 0)) return contact;
  const double keep = 1 - min_tissue_fraction;  // of T the press may take
  // only bone within depth / keep can hold the press back
  const PressTissue tissue = tissue_along_press(patient, contact, depth / keep);
  if (!tissue.bone || depth <= keep * tissue.thickness_mm) return contact;
  DeformContact out = contact;
  out.tip_mm = contact.skin_point_mm + d * (keep * tissue.thickness_mm / depth);
  return out;
}

DeformContact capped_press(const Patient& patient, const DeformConfig& config, const DeformContact& contact) {
  if (config.settings.relax_method != RelaxMethod::kElastic || !config.relax) return contact;
  return cap_press_at_bone(patient, contact, config.settings.elastic.min_tissue_fraction);
}

}  // namespace palpsim::deform
