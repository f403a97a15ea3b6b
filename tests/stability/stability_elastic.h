// The elastic model (deform.relax_method "elastic") on the stability catalogue (issue 25,
// section 5): the catalogue's deformation cases where a fingertip sphere pressing the skin
// makes sense, and the model's own hard cases. Written once and run on every backend, as
// stability_deform.h's cases: "cpu" by palpsim-test-deform-stability (CTest label
// stability), "cuda" by palpsim-gpu-stability-tests once that backend has the model.
// DeformRun::elastic_contact() checks every contact (stability_deform.h's file comment).
//
// Cases of the catalogue left out, and why:
// - soft tissue enclosed by bone (the Fig. 4 cube): the finger touches the skin, and that
//   tissue has none (bone all round), so every press leaves it at rest; the finger pressing
//   into a bone shell from the skin is "tip inside bone" below;
// - relaxation at the stability limit: the explicit scheme's step, which the model has not;
// - the shipped multigrid deformation: that configuration itself; the elastic model's
//   presses, warm steps and jumps are the random poses and the rib sweep here;
// - the flat plateau of I (one constant intensity): a body without skin, nothing to press;
//   the plateau of F (the force model's X) is kept.
// The deformation-only patients (intensity and bone) get a body mask and the depth under
// the skin (with_skin), which the model reads.
#pragma once

#include <cmath>
#include <limits>
#include <vector>

#include "stability/stability_deform.h"

namespace palpsim::test::stability {

/// A press along -z on a patient whose skin is the slab's plane z = kSlabSkinZ: X on the
/// skin above (x, y) mm, the tip `depth_mm` under it.
inline DeformContact skin_press(double x_mm, double y_mm, double depth_mm) {
  return {{x_mm, y_mm, kSlabSkinZ}, {x_mm, y_mm, kSlabSkinZ - depth_mm}};
}

/// The tip inside bone: the finger pressed from the skin of the Fig. 4 body into its bone
/// shell (the force model's X for tips in the shell), and X itself in bone.
inline void elastic_tip_inside_bone(Case& c) {
  INFO(c.describe());
  const HapticPatient h = enclosed_cube();  // skin 1.5..37.5 mm, bone shell 9.5..29.5 around soft 13.5..25.5
  DeformRun r(c, h.patient, elastic_config(24));
  int n = 0;
  for (int s = 0; s < 40 && n < 6; ++s) {
    // a random point of the shell, 4 mm thick along one axis
    Vec3 tip{c.uniform(10, 29), c.uniform(10, 29), c.uniform(10, 29)};
    const int a = c.integer(0, 2);
    tip[a] = c.integer(0, 1) ? c.uniform(25.6, 29.4) : c.uniform(9.6, 13.4);
    DeformContact k;
    if (haptic_contact(*h.patient, tip, k)) {
      r.contact(k);
      ++n;
    }
  }
  REQUIRE(n == 6);
  // X in the shell (a bone voxel), pressed on inwards and outwards
  r.contact(voxel_contact({11, 20, 20}, {6, 0, 0}), {true, 1});
  r.contact(voxel_contact({20, 28, 20}, {0, -4, 3}), {true, 1});
}

/// X exactly on the skin plane (a rounding tie) with tips up to 6 mm under it, and the
/// force model's contacts for tips on and a hair under the skin (skin_contacts).
inline void elastic_on_skin(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, elastic_config(24));
  // a press of a micrometre at most moves the skin by that at most
  for (const Outcome& o : skin_contacts(c, r, 4, 4, 6)) CHECK(max_abs_component(o.u) <= 1e-3f);
}

/// X and the tip on voxel corners (every rounding a tie), on the slab and around the bone
/// ball centred on a voxel corner.
inline void elastic_voxel_corner(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, elastic_config(24));
  for (int s = 0; s < 4; ++s) {
    const Vec3 X{c.integer(2, 56) + 0.5, c.integer(2, 56) + 0.5, kSlabSkinZ};
    r.contact({X, X + Vec3{c.integer(-3, 3) + 0.5, c.integer(-3, 3) + 0.5, -double(c.integer(1, 8))}});
  }
  const HapticPatient ball = corner_ball();  // body radius 18 mm, bone radius 5 mm around (19.5, 19.5, 19.5)
  DeformRun rb(c, ball.patient, elastic_config(24));
  rb.contact({{19.5, 19.5, 19.5}, {19.5, 19.5, 30.5}}, {true, 1});  // X at the bone ball's centre
  for (int s = 0; s < 3; ++s) {
    // from the body's skin towards the bone ball, the tip on a corner
    const Vec3 d{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
    const Vec3 u = d * (1.0 / std::max(norm(d), 1e-9));
    Vec3 X = Vec3{19.5, 19.5, 19.5} + u * 17.9, x = Vec3{19.5, 19.5, 19.5} + u * 9.0;
    for (int a = 0; a < 3; ++a) x[a] = std::floor(x[a]) + 0.5;
    rb.contact({X, x});
  }
}

/// X on the grid's faces, edges and corners where they cut the body, the tip beyond the
/// grid or inside; contacts outside the grid's tolerance are refused and the next step works.
inline void elastic_volume_border(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  const double lo = -0.5, hi = 59.5;
  DeformRun r(c, h.patient, elastic_config(20));
  for (int s = 0; s < 6; ++s) {
    Vec3 X{c.uniform(0, 59), c.uniform(0, 59), kSlabSkinZ};
    const int faces = 1 + s % 2;
    for (int f = 0; f < faces; ++f) X[(s + f) % 2] = (c.integer(0, 1) == 0 ? lo : hi) + (s % 3 == 0 ? 0.0 : c.uniform(-1e-3, 1e-3));
    Vec3 x = X + Vec3{0, 0, -c.uniform(1, 8)};
    for (int a = 0; a < 2; ++a) x[a] += X[a] <= lo + 0.01 ? -c.uniform(0, 6) : (X[a] >= hi - 0.01 ? c.uniform(0, 6) : 0.0);
    r.contact({X, x});
  }
  r.refused({{lo - 3e-3, 30, kSlabSkinZ}, {lo - 5, 30, 30}});
  r.refused({{30, hi + 1.0, kSlabSkinZ}, {30, 58, 30}});
  r.contact({{-0.5, 30, kSlabSkinZ}, {-0.5, 31, kSlabSkinZ - 5}});
}

/// The force model's contacts on the slab whose F is flat deep down (zero gradient: the
/// proxy keeps no direction; X then comes from the skin's normal alone).
inline void elastic_flat_plateau(Case& c) {
  INFO(c.describe());
  const HapticPatient h = plateau_slab();
  DeformRun r(c, h.patient, elastic_config(24));
  int n = 0;
  for (int s = 0; s < 20 && n < 4; ++s) {
    DeformContact k;
    if (haptic_contact(*h.patient, {c.uniform(4, 55), c.uniform(4, 55), c.uniform(20, 38)}, k)) {
      r.contact(k);
      ++n;
    }
  }
  REQUIRE(n == 4);
}

/// A 50 mm jump between two presses on the torso: the second press's VOI (24 voxels)
/// shares nothing with the first's, and its step equals a fresh backend's bit for bit.
inline void elastic_jump_50mm(Case& c) {
  INFO(c.describe());
  const PatientPtr p = with_skin(make_torso_patient(64));
  DeformRun r(c, p, elastic_config(24));
  jumps_50mm(c, r, 3);
}

/// Tips 20, 40 and 100 voxels from X with a 16-voxel VOI, along the axes and at random.
inline void elastic_displacement_larger_than_voi(Case& c) {
  INFO(c.describe());
  const PatientPtr p = with_skin(make_torso_patient(64));
  DeformRun r(c, p, elastic_config(16));
  for (double d : {20.0, 40.0, 100.0}) {
    r.contact(voxel_contact({32, 20, 32}, {d, 0, 0}), {false, -1});
    r.contact(voxel_contact({32, 60, 32}, {0, -d, 0}), {false, -1});  // from the torso's skin inwards
    const Vec3 X{c.uniform(12, 52), c.uniform(12, 52), c.uniform(12, 52)};
    const Vec3 dir{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
    r.contact({X, X + dir * (d / std::max(norm(dir), 1e-9))}, {false, -1});
  }
}

/// VOIs clipped by the grid: presses near its corners, a VOI edge larger than the grid and
/// the whole volume as VOI.
inline void elastic_voi_crossing_border(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, elastic_config(32));
  for (int s = 0; s < 4; ++s) {
    Vec3 X{c.uniform(0, 6), c.uniform(0, 6), kSlabSkinZ};
    for (int a = 0; a < 2; ++a)
      if (c.integer(0, 1)) X[a] = 59 - X[a];
    r.contact({X, X + Vec3{c.uniform(-6, 6), c.uniform(-6, 6), -c.uniform(1, 10)}});
  }
  const PatientPtr torso = with_skin(make_torso_patient(24));
  DeformRun big(c, torso, elastic_config(100));  // the VOI edge exceeds the 24-voxel grid
  big.contact({{12, 20.6, 12}, {12.5, 16, 11}});
  DeformConfig whole = elastic_config(16);
  whole.settings.whole_volume = true;
  DeformRun w(c, torso, whole);
  w.contact({{3, 12, 12}, {7, 11, 13}});
}

/// The anisotropic grid (0.5 x 0.5 x 5 mm voxels) pressed a few mm; with prep, the force
/// model's contacts on a patient prepared from a 0.5 x 0.5 x 5 mm CT.
inline void elastic_anisotropic(Case& c) {
  INFO(c.describe());
  const PatientPtr p = with_skin(anisotropic_grid_patient());  // skin at z = 32.5 mm, a bone bar below
  DeformRun r(c, p, elastic_config(24));
  for (int s = 0; s < 4; ++s) {
    const Vec3 X{c.uniform(1, 22), c.uniform(1, 22), 32.5};
    r.contact({X, X + Vec3{c.uniform(-2, 2), c.uniform(-2, 2), -c.uniform(1, 12)}});
  }
#ifdef PALPSIM_STABILITY_PREP
  const HapticPatient h = prep_anisotropic_patient();
  deform_haptic_contacts(c, h, elastic_config(32), 3);
#endif
}

/// Extreme HU (-3024 around the body, a 30000 HU metal rod): the modulus table saturates at
/// both ends; with prep, the force model's contacts on such a CT.
inline void elastic_extreme_hu(Case& c) {
  INFO(c.describe());
  const PatientPtr p = with_skin(extreme_hu_patient());  // body 4..35 x 4..35 x 4..29, metal rod at 18..22
  DeformRun r(c, p, elastic_config(24));
  r.contact({{20, 20, 29.5}, {20, 20, 21}});      // down onto the metal rod
  r.contact({{12, 20, 29.5}, {12, 20, 24}});      // beside it
  r.contact(voxel_contact({20, 20, 16}, {3, 0, 0}), {true, 1});  // X in the metal
  for (int s = 0; s < 2; ++s) {
    const Vec3 X{c.uniform(5, 34), c.uniform(5, 34), 29.5};
    r.contact({X, X + Vec3{c.uniform(-3, 3), c.uniform(-3, 3), -c.uniform(1, 9)}});
  }
#ifdef PALPSIM_STABILITY_PREP
  const HapticPatient h = prep_extreme_hu_patient();
  deform_haptic_contacts(c, h, elastic_config(24), 3);
#endif
}

/// One spot, many steps: the same contact stepped again and again starts each step from
/// the last one's field, already the solution, and only puts the contact nodes back on the
/// sphere, which rounds. The field must not drift:
/// - each step stays within the solve's own accuracy of the first one's (the tolerance times
///   its largest displacement): where rounding puts the warm start's residual a hair over the
///   tolerance a CG step runs (the GPU's sums run in another order: seen on the H200, 1.2e-5
///   voxel of 4.3), which moves the field by less than the tolerance allows;
/// - over the second half of the steps consecutive fields agree within a few ulps of the
///   largest displacement (8 FLT_EPSILON; the CPU measured 1 ulp): once settled, a repeated
///   step changes nothing but rounding, so nothing accumulates.
inline void elastic_one_spot_repeated(Case& c, int steps) {
  INFO(c.describe());
  const PatientPtr p = with_skin(make_torso_patient(48));
  const DeformConfig cfg = elastic_config(24);
  DeformRun r(c, p, cfg);
  const DeformContact k{{24.3, 40.4, 23.7}, {25.1, 35.6, 22.9}};
  const Outcome first = r.contact(k);
  REQUIRE(first.elastic.contact);
  const float scale = max_abs_component(first.u);
  float worst = 0, settled = 0;
  std::vector<Vec3f> last = first.u;
  for (int s = 0; s < steps; ++s) {
    const Outcome o = r.contact(k);
    worst = std::max(worst, max_abs_diff(o.u, first.u));
    if (s >= steps / 2) settled = std::max(settled, max_abs_diff(o.u, last));
    last = o.u;
  }
  INFO("over " << steps << " steps the field moved by " << worst << " voxel at most from the first, "
               << settled << " from one step to the next over the second half, of " << scale);
  CHECK(worst <= cfg.settings.elastic.tolerance * scale);
  CHECK(settled <= 8 * FLT_EPSILON * scale);
}

/// Random presses over the torso, a tenth of them corrupt (NaN, +-Inf, X outside the grid,
/// x absurdly far: refused, the backend stays usable): new presses anywhere, presses going
/// on a voxel a step (warm starts), jumps of the tip, X in the spine.
inline void elastic_random_poses(Case& c, int count) {
  INFO(c.describe());
  const PatientPtr p = with_skin(make_torso_patient(40));
  const double nan = std::numeric_limits<double>::quiet_NaN(), inf = std::numeric_limits<double>::infinity();
  DeformRun r(c, p, elastic_config(16));
  long long refusals = 0, pressed = 0;
  Vec3 X{20, 33.4, 20}, x = X;
  for (int s = 0; s < count; ++s) {
    const int kind = c.integer(0, 99);
    if (kind < 40 && s > 0) {
      x += Vec3{c.uniform(-0.3, 0.3), c.uniform(-1.2, -0.5), c.uniform(-0.3, 0.3)};  // the press goes on
    } else if (kind < 75) {
      X = {c.uniform(-0.5, 39.5), c.uniform(-0.5, 39.5), c.uniform(-0.5, 39.5)};  // a new press anywhere
      x = X + Vec3{c.uniform(-6, 6), c.uniform(-6, 6), c.uniform(-6, 6)};
    } else if (kind < 90) {
      x = X + Vec3{c.uniform(-12, 12), c.uniform(-12, 12), c.uniform(-12, 12)};  // a jump of the tip
    } else {
      // corrupt
      Vec3 bx = X, bt = x;
      const int what = c.integer(0, 4), a = c.integer(0, 2);
      if (what < 3) (c.integer(0, 1) ? bx : bt)[a] = what == 0 ? nan : (what == 1 ? inf : -inf);
      else if (what == 3) bx[a] = c.integer(0, 1) ? c.uniform(-1e6, -0.51) : c.uniform(39.51, 1e6);
      else bt[a] = c.integer(0, 1) ? 1e300 : -2e8;
      r.refused({bx, bt});
      ++refusals;
      continue;
    }
    const Outcome o = r.contact({X, x}, {false, -1});
    pressed += o.elastic.contact;
  }
  REQUIRE(refusals > 0);
  REQUIRE(pressed > 0);
}

/// The contacts of a tip sweeping across the rib at 1 m/s (deform_rib_sweep: the VOI
/// follows the tip, each step warm from the last).
inline void elastic_rib_sweep(Case& c) { deform_rib_sweep(c, elastic_config(24)); }

// ---------------------------------------------------------------------------------
// the elastic model's own hard cases

/// Poisson's ratio 0.49 (lambda 16 times mu): presses over soft tissue and over bone,
/// deepening a voxel a step, must converge as at 0.45.
inline void elastic_nu_049(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, elastic_config(24, 0.49));
  const double x0 = c.uniform(8, 14), y0 = c.uniform(8, 14);
  for (double d : {1.0, 2.0, 3.0, 5.0, 8.0}) REQUIRE(r.contact(skin_press(x0, y0, d)).elastic.contact);
  for (double d : {4.0, 9.0, 14.0}) r.contact(skin_press(30.2, 29.7, d));  // over the bone block
}

/// 2 mm of tissue over bone: a bone block whose top lies 2 mm under the skin plane,
/// pressed 1 to 10 mm (the sphere enters the bone past 2 mm and squeezes the tissue
/// between them flat).
inline void elastic_thin_tissue_over_bone(Case& c) {
  INFO(c.describe());
  auto skin = [](const Vec3& x) { return x.z - kSlabSkinZ; };
  const PatientPtr p = make_patient(48, 1.0, skin, [](const Vec3& x) {
    return box_sdf(x, {10.5, 10.5, 20.5}, {37.5, 37.5, kSlabSkinZ - 2.0});
  });
  DeformRun r(c, p, elastic_config(24));
  for (double d : {1.0, 2.0, 3.0, 5.0, 10.0}) r.contact(skin_press(24.2, 23.8, d), {false, 0});
  for (int s = 0; s < 3; ++s)
    r.contact(skin_press(c.uniform(12, 36), c.uniform(12, 36), c.uniform(1, 8)), {false, 0});
  r.contact(skin_press(10.4, 24, 6), {false, 0});  // over the block's edge
}

/// The sphere entering bone: presses over the slab's bone block (14 mm of tissue over it)
/// to 25 mm, straight and obliquely.
inline void elastic_sphere_into_bone(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();  // bone block [24.5, 35.5]^2 x [14.5, 25.5] mm
  DeformRun r(c, h.patient, elastic_config(32));
  for (double d : {10.0, 14.0, 16.0, 20.0, 25.0}) r.contact(skin_press(30.3, 29.6, d), {false, 0});
  const Vec3 X{c.uniform(22, 38), c.uniform(22, 38), kSlabSkinZ};
  r.contact({X, X + Vec3{c.uniform(-8, 8), c.uniform(-8, 8), -20}}, {false, 0});
}

/// A 40 mm indentation: tissue above the plane z = 5.5 mm (42 mm of it; the skin faces -z,
/// so X rounds into the body), pressed along +z to 40 mm, the tissue left under the sphere
/// squeezed to a sliver against the grid's held top face. Its cells fold; the folds are
/// reported (DeformStats::elastic.inverted_cells, checked against the field), nothing is
/// NaN, J stays finite and the step does not throw.
inline void elastic_indentation_40mm(Case& c) {
  INFO(c.describe());
  const PatientPtr p = make_patient(48, 1.0, [](const Vec3& x) { return 5.5 - x.z; }, [](const Vec3&) { return 1e9; });
  DeformRun r(c, p, elastic_config(48));
  const Vec3 X{c.uniform(22, 26), c.uniform(22, 26), 5.5};
  Outcome o;
  for (double d : {15.0, 40.0}) {
    o = r.contact({X, X + Vec3{0, 0, d}}, {false, 0});
    REQUIRE(o.elastic.contact);
  }
  INFO("at 40 mm: " << o.elastic.inverted_cells << " inverted cells, force " << fmt(o.elastic.force_n) << " N");
  REQUIRE(o.elastic.inverted_cells > 0);
}

}  // namespace palpsim::test::stability
