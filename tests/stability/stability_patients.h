// The small synthetic patients of the stability catalogue (issue 8, section 5), shared
// by the CPU executable (palpsim-test-deform-stability) and the GPU one
// (palpsim-gpu-stability-tests). Every patient is a few hundred thousand voxels at most
// so that the whole catalogue runs in seconds on the 2-core CI machine.
//
// Two families:
// - full patients (tests/support/synthetic_patient.h: masks, A, B, F, grad F from
//   closed-form signed distances) for the force model and the hand-over of its
//   contacts to the deformation; their skin is known in closed form (`skin`), so the
//   haptic checks can tell "outside the body" without asking the code under test;
// - deformation-only patients (tests/support/deform_fixtures.h: intensity and bone).
// Patients that go through prep's build_patient (anisotropic input spacing, extreme
// HU) are built in stability_prep_patients.cpp when palpsim_prep exists
// (PALPSIM_STABILITY_PREP).
#pragma once

#include <algorithm>
#include <cmath>
#include <memory>

#include "support/deform_fixtures.h"
#include "support/synthetic_patient.h"

namespace palpsim::test::stability {

/// A full patient and the closed-form signed distance of its skin (mm, negative inside).
struct HapticPatient {
  PatientPtr patient;
  Sdf skin;           // exact skin of the construction (voxel centres with skin < 0 are body);
                      // empty for patients made by prep (its masks are not closed-form)
  const char* what;   // for failure messages
};

/// Recomputes grad F by central differences (one-sided at the border), in mm/mm, as
/// tests/support/synthetic_patient.h and prep do, after a test changed F.
inline void recompute_grad_force(Patient& p) {
  const Grid& g = p.grid;
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        Vec3f d;
        for (int a = 0; a < 3; ++a) {
          Vec3i lo{i, j, k}, hi{i, j, k};
          lo[a] = std::max(lo[a] - 1, 0);
          hi[a] = std::min(hi[a] + 1, g.size[a] - 1);
          const double f1 = p.force.at(hi.x, hi.y, hi.z), f0 = p.force.at(lo.x, lo.y, lo.z);
          d[a] = hi[a] == lo[a] ? 0.f : float((f1 - f0) / (double(hi[a] - lo[a]) * g.spacing_mm[a]));
        }
        p.grad_force.at(i, j, k) = d;
      }
}

/// The slab of tests/support/synthetic_patient.h: 60 mm cube at 1 mm, skin plane
/// z = 39.5 mm (body below), a bone block [24.5, 35.5]^2 x [14.5, 25.5] mm. The body
/// reaches the grid's faces at x, y = -0.5 and 59.5 mm and z = -0.5 mm.
inline HapticPatient slab() {
  return {slab_patient(), [](const Vec3& x) { return x.z - kSlabSkinZ; }, "slab"};
}

/// A rib under the skin: the slab's skin plane (z = 39.5 mm) over a bone cylinder
/// along y, radius 4 mm, axis at x = 30.5, z = 28.5 mm (its top 7 mm under the skin),
/// on a 61 mm cube at 1 mm.
inline HapticPatient rib() {
  auto skin = [](const Vec3& x) { return x.z - kSlabSkinZ; };
  auto p = make_patient(61, 1.0, skin, [](const Vec3& x) { return std::hypot(x.x - 30.5, x.z - 28.5) - 4.0; });
  return {p, skin, "rib"};
}

/// The paper's Fig. 4 situation for the force model: a 40 mm cube body at 1 mm whose
/// centre holds a 12 mm soft cube enclosed by a 4 mm bone shell (F is high and its
/// gradient turns sharply inside the shell).
inline HapticPatient enclosed_cube() {
  auto skin = [](const Vec3& x) { return box_sdf(x, {1.5, 1.5, 1.5}, {37.5, 37.5, 37.5}); };
  auto bone = [](const Vec3& x) {
    const double outer = box_sdf(x, {9.5, 9.5, 9.5}, {29.5, 29.5, 29.5});
    const double inner = box_sdf(x, {13.5, 13.5, 13.5}, {25.5, 25.5, 25.5});
    return std::max(outer, -inner);
  };
  return {make_patient(40, 1.0, skin, bone), skin, "enclosed cube"};
}

/// A ball of bone centred exactly on a voxel corner (20, 20, 20) mm of a 40 mm cube at
/// 1 mm, inside a body ball of radius 18 mm: by symmetry grad F sampled at that corner
/// is (nearly) exactly zero, and it is the corner of eight bone voxels.
inline HapticPatient corner_ball() {
  const Vec3 c{19.5, 19.5, 19.5};
  return {make_patient(
              40, 1.0, [c](const Vec3& x) { return norm(x - c) - 18.0; },
              [c](const Vec3& x) { return norm(x - c) - 5.0; }),
          [c](const Vec3& x) { return norm(x - c) - 18.0; }, "corner ball"};
}

/// The slab with F cut off at `plateau_mm` (the skin side keeps its ramp): wherever eq. 1
/// would exceed it F is flat, so grad F is exactly zero there (deep tissue and the bone
/// block); the layer where F crosses the cut has a one-sided, small gradient.
inline HapticPatient plateau_slab(double plateau_mm = 3.0) {
  auto p = slab_patient();
  for (float& f : p->force.data) f = std::min(f, float(plateau_mm));
  recompute_grad_force(*p);
  return {p, [](const Vec3& x) { return x.z - kSlabSkinZ; }, "plateau slab"};
}

/// Deformation-only: soft tissue of one constant intensity (a flat plateau of I and of
/// the material function), no bone, n^3 at 1 mm.
inline PatientPtr constant_patient(int n, float hu = kSoftHu) {
  return make_patient({n, n, n}, [hu](int, int, int) { return hu; });
}

/// Deformation-only: the extremes of a real CT's range. -3024 HU (scanner padding
/// outside the field of view) around a soft-tissue block textured by +-50 HU, holding a
/// 30000 HU metal insert (bone by threshold) and a 700 HU bone plate; 40^3 at 1 mm.
inline PatientPtr extreme_hu_patient() {
  return make_patient({40, 40, 40}, [](int i, int j, int k) {
    const bool body = i >= 4 && i < 36 && j >= 4 && j < 36 && k >= 4 && k < 30;
    if (!body) return -3024.0f;
    if (std::abs(i - 20) <= 2 && std::abs(j - 20) <= 2 && k >= 12 && k <= 20) return 30000.0f;  // metal rod
    if (k >= 8 && k <= 9 && i >= 10 && i < 30) return kBoneHu;                                    // bone plate
    return float(kSoftHu + 50.0 * std::sin(0.7 * i + 0.3 * j) * std::cos(0.5 * k));
  });
}

/// Deformation-only: the anisotropic grid itself (0.5 x 0.5 x 5 mm voxels, 48 x 48 x 10),
/// soft tissue below z = 32.5 mm with a bone bar: ChainMail's restrictions are in voxel
/// edge lengths, so a push of a few mm is 10x more voxels along x, y than along z.
inline PatientPtr anisotropic_grid_patient() {
  return make_patient(
      {48, 48, 10},
      [](int i, int j, int k) {
        if (k > 6) return kAirHu;
        if (k >= 2 && k <= 3 && j >= 20 && j <= 27) return kBoneHu;  // a bar along x
        return float(kSoftHu + 15.0 * std::sin(0.4 * i) + 10.0 * std::cos(0.3 * j) + 5.0 * k);
      },
      {0.5, 0.5, 5.0});
}

#ifdef PALPSIM_STABILITY_PREP
/// A small CT with 0.5 x 0.5 x 5 mm voxels (thick slices: a torso ellipse with a
/// bone rod and a rib along x), prepared by prep's build_patient onto its isotropic grid
/// (0.5 mm: the smallest input spacing). Built once (static), in stability_prep_patients.cpp.
HapticPatient prep_anisotropic_patient();
/// A small CT at 1 mm with -3024 HU outside a circular field of view, a 30000 HU metal
/// rod inside a bone and soft tissue, prepared by prep's build_patient. Built once.
HapticPatient prep_extreme_hu_patient();
#endif

}  // namespace palpsim::test::stability
