// Where bone stops the fingertip: the elastic model's press held short of the bone under
// it (deform.elastic.min_tissue_fraction), on the host before either backend steps.
#pragma once

#include "core/patient.h"
#include "deform/backend.h"

namespace palpsim::deform {

/// The tissue under a press, along its direction n (from the skin point X to the tip x).
struct PressTissue {
  bool bone = false;       // bone lies along n within the distance searched
  double thickness_mm = 0; // T: from X along n to the bone (where A falls to half a voxel); 0 without bone
};

/// The distance from X along n = (x - X) / |x - X| to bone, searched up to `reach_mm`
/// (sphere tracing on A, the distance map to bone, so no bone is stepped over); no bone
/// when none lies within reach, the ray leaves the grid, or x == X.
PressTissue tissue_along_press(const Patient& patient, const DeformContact& contact, double reach_mm);

/// The contact the elastic model presses: the tip x moved back along n to depth
/// (1 - f) T below X where the press |x - X| would go deeper, T the tissue under X along n
/// and f = `min_tissue_fraction` (0: the contact as given). Beyond that depth the linear
/// model squeezes the tissue column past half its thickness (at the default 0.5), where
/// its cells fold, and on to the skin passing through bone, which a finger cannot do.
/// Idempotent; the skin point X is kept.
DeformContact cap_press_at_bone(const Patient& patient, const DeformContact& contact, double min_tissue_fraction);

/// cap_press_at_bone() with the configuration's fraction for an elastic scene; every
/// other relaxation gets the contact as given.
DeformContact capped_press(const Patient& patient, const DeformConfig& config, const DeformContact& contact);

}  // namespace palpsim::deform
