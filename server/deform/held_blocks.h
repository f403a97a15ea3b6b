// Where a multigrid relaxation step may hold an element that ChainMail can move, so that
// a step whose VOI has none can leave ChainMail out: its steady state u = d G does not
// depend on ChainMail's field then (relax_multigrid.h, "Linearity").
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "core/patient.h"
#include "deform/deform_math.h"

namespace palpsim::deform {

/// True where relaxation may hold an element outside the bone mask (ChainMail moves every
/// element outside it): relaxation holds an element of material weight 0, i.e. where
/// tanhf((I - threshold) / width) rounds to 1, which glibc's tanhf first does at 9.011
/// (measured; 1 - tanh is half the float spacing below 1 there). The GPU's tanhf is within
/// 2 ulp, so it cannot reach 1 before 1 - tanh falls to 2.5 ulp, at 8.2; 1 - tanh(7) is 28
/// ulp, so 7 widths flag every such element on either backend, and a few more. NaN
/// intensities are held by neither.
inline bool may_hold_outside_bone(float intensity, bool bone, float threshold, float width) {
  return !bone && intensity - threshold >= 7.0f * width;
}

/// Blocks of kEdge^3 patient voxels, each flagged when an element in it may be held
/// outside the bone mask (may_hold_outside_bone). Built once per patient, material
/// threshold and width, and shared by the sessions that use them.
class HeldBlocks {
 public:
  static constexpr int kEdge = 8;

  /// The map of `patient` for the material function's `threshold` and `width` (HU):
  /// the one already built for them while any holder keeps it, else a new one (one pass
  /// over the patient: a comparison per voxel).
  static std::shared_ptr<const HeldBlocks> of(const PatientPtr& patient, float threshold, float width);

  /// Builds the map (of() shares it; tests build their own).
  HeldBlocks(const PatientPtr& patient, float threshold, float width);

  /// True when some element of `voi` (patient voxel indices) may be held outside the
  /// bone mask; false guarantees that none is.
  bool any_in(const Voi& voi) const;

  /// Flagged blocks, of all.
  long long flagged() const { return flagged_; }

 private:
  std::weak_ptr<const Patient> patient_;
  float threshold_ = 0, width_ = 0;
  Vec3i blocks_{0, 0, 0};
  std::vector<std::uint8_t> flag_;  // per block, i fastest
  long long flagged_ = 0;
};

}  // namespace palpsim::deform
