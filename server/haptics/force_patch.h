// A patch of the force model's volumes (C, F, grad F) on a box of the patient grid: what
// the server sends a far haptic client (PoseReply.local_model, proto/PROTOCOL.md) so that
// it renders eq. 2 at its own rate between replies. Sampling a patch gives the forces the
// whole patient gives wherever the patch covers the point (force_field.h does the math
// for both). Header-only, compiled into the server and the thin haptic client.
#pragma once

#include <cstdint>
#include <vector>

#include "haptics/force_field.h"

namespace palpsim {

/// C, F and grad F on a box of the patient grid, with what a client needs to run eq. 2.
struct ForcePatch {
  Grid grid;                          // the box as a grid: size, spacing, direction, origin = its first voxel (mm)
  Vec3i lo{0, 0, 0};                  // the box's first voxel on the patient grid
  Vec3i patient_size{0, 0, 0};        // the patient grid's size (voxels), for its borders
  std::vector<std::uint8_t> body;     // C, i fastest
  std::vector<float> force_mm;        // F (mm)
  std::vector<Vec3f> grad_force;      // grad F (mm/mm, physical axes)
  HapticsSettings params;             // the session's haptics parameters when the patch was made
  std::uint64_t version = 0;          // the server's patch number (grows per session); 0: empty
  std::uint64_t generation = 0;       // the scene generation whose patient it was cut from
  Vec3 center_mm{0, 0, 0};            // the point its box was centred on: the tip, led by its velocity

  /// True when the patch holds samples.
  bool valid() const { return version != 0 && grid.count() != 0 && body.size() == grid.count(); }

  /// The volumes as a FieldView on the box's grid.
  FieldView view() const { return FieldView{&grid, body.data(), nullptr, force_mm.data(), grad_force.data()}; }

  /// Samples C, F and grad F at a physical point (mm) as the whole patient would: true when
  /// the patch decides the sample (the point's trilinear corners lie in the box, or the point
  /// is beyond the patient grid's border next to the box: outside the body), false when the
  /// point needs voxels the patch does not hold (then `out` is untouched).
  bool sample(const Vec3& p_mm, PatientSample& out) const {
    if (!valid()) return false;
    const Vec3 ijk = grid.to_index(p_mm);
    for (int a = 0; a < 3; ++a) {
      // below the box: covered only where the box starts at the patient grid's border,
      // whose edge replication the box's own replicates exactly
      const bool low_border = lo[a] == 0, high_border = lo[a] + grid.size[a] == patient_size[a];
      if (!(ijk[a] >= 0) && !low_border) return false;
      if (!(ijk[a] <= grid.size[a] - 1) && !high_border) return false;
    }
    // beyond half a voxel outside the patient grid sample_field gives "outside", as the server does
    out = sample_field<true>(view(), ijk);
    return true;
  }
};

}  // namespace palpsim
