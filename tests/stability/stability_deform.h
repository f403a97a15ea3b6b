// The deformation half of the stability catalogue (issue 8, section 5), written once
// and run on every backend the machine has: "cpu" by palpsim-test-deform-stability
// (CTest label stability), "cuda" by palpsim-gpu-stability-tests (label gpu). Each case
// drives a DeformRun (stability_deform_run.h, which lists the invariants it checks after
// every contact); each case function takes a Case (name, backend, seed) and prints it on
// failure.
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "stability/stability_deform_run.h"

namespace palpsim::test::stability {

// ---------------------------------------------------------------------------------
// the catalogue's deformation cases

/// The tip inside bone: soft elements pushed into the Fig. 4 cube's bone shell and
/// through it into the air beyond; X itself in bone (nothing may move).
inline void deform_tip_inside_bone(Case& c) {
  INFO(c.describe());
  // soft cube voxels 12..27, bone shell 8..11 and 28..31, air beyond
  auto p = make_cube_patient(40, 16, 4);
  for (int preset = 1; preset <= 2; ++preset) {
    INFO("preset p" << preset);
    DeformRun r(c, p, config(preset, 24));
    r.contact(voxel_contact({20, 20, 20}, {9, 0, 0}), {true, 0});     // x inside the shell
    r.contact(voxel_contact({20, 20, 20}, {0, -14, 0}), {true, 0});   // x through it, in the air
    r.contact(voxel_contact({26, 26, 26}, {4, 4, 4}), {true, 0});     // into the shell's corner
    auto shell_point = [&](double margin) {
      // a random point of the shell (voxel centres 8..11 or 28..31 along one axis)
      Vec3 x{c.uniform(8, 31), c.uniform(8, 31), c.uniform(8, 31)};
      const int a = c.integer(0, 2);
      x[a] = c.integer(0, 1) ? c.uniform(28 - margin, 31 + margin) : c.uniform(8 - margin, 11 + margin);
      return x;
    };
    for (int s = 0; s < 6; ++s) {
      const Vec3 X{c.uniform(12.6, 26.4), c.uniform(12.6, 26.4), c.uniform(12.6, 26.4)};
      r.contact({X, shell_point(0.4)}, {true, 0});
    }
    for (int s = 0; s < 4; ++s) {
      // X in bone: rounded to a shell voxel (0.4 voxel from its centre at most)
      Vec3 X = shell_point(0.0);
      for (int a = 0; a < 3; ++a) X[a] = std::round(X[a]) + c.uniform(-0.4, 0.4);
      r.contact({X, X + Vec3{c.uniform(-6, 6), c.uniform(-6, 6), c.uniform(-6, 6)}}, {true, 1});
    }
  }
}

/// `presses` contacts with X exactly on the slab's skin plane (z = 39.5 mm lies on voxel
/// faces, so rounding X to a voxel is a tie) and the tip up to `depth_mm` under it, then
/// the contacts the force model makes for `tips` tips on and a hair under the skin; returns
/// the latter's outcomes.
inline std::vector<Outcome> skin_contacts(Case& c, DeformRun& r, int presses, int tips, double depth_mm) {
  for (int s = 0; s < presses; ++s) {
    const Vec3 X{std::floor(c.uniform(3, 56)) + (s % 2 ? 0.5 : c.uniform(0, 1)), c.uniform(3, 56), kSlabSkinZ};
    r.contact({X, X + Vec3{c.uniform(-3, 3), c.uniform(-3, 3), -c.uniform(0, depth_mm)}});
  }
  std::vector<Outcome> out;
  for (int s = 0; s < tips; ++s) {
    // tips on the skin plane above voxel centres (C samples exactly 0.5: inside) and a
    // hair under it anywhere: the hand-over must accept the force model's X
    const Vec3 tip = s % 2 ? Vec3{double(c.integer(1, 58)), double(c.integer(1, 58)), kSlabSkinZ}
                           : Vec3{c.uniform(1, 58), c.uniform(1, 58), kSlabSkinZ - c.uniform(1e-6, 1e-3)};
    DeformContact k;
    REQUIRE(haptic_contact(r.patient(), tip, k));
    out.push_back(r.contact(k));
  }
  return out;
}

/// X exactly on the skin and the contacts the force model makes for tips on and just
/// under the skin (skin_contacts).
inline void deform_on_skin(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, config(1, 24));
  skin_contacts(c, r, 6, 8, 10);
}

/// X and x exactly on voxel corners (every rounding a tie, trilinear weights 1/2), on
/// the slab and on the bone ball centred on a voxel corner.
inline void deform_voxel_corner(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, config(2, 24));
  auto corner = [&](int lo, int hi) { return Vec3{c.integer(lo, hi) + 0.5, c.integer(lo, hi) + 0.5, c.integer(lo, 37) + 0.5}; };
  for (int s = 0; s < 6; ++s) {
    const Vec3 X = corner(2, 56);
    r.contact({X, X + Vec3{c.integer(-5, 5) + 0.5, c.integer(-5, 5) + 0.5, double(c.integer(-8, 2))}});
  }
  const HapticPatient ball = corner_ball();
  DeformRun rb(c, ball.patient, config(1, 24));
  rb.contact({{19.5, 19.5, 19.5}, {19.5, 19.5, 30.5}}, {true, 1});  // the ball's centre: a bone corner
  for (int s = 0; s < 4; ++s) {
    // corners next to the bone ball's surface (radius 5 mm), pushed towards it
    const Vec3 d{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
    Vec3 X = Vec3{19.5, 19.5, 19.5} + d * (7.0 / std::max(norm(d), 1e-9));
    for (int a = 0; a < 3; ++a) X[a] = std::floor(X[a]) + 0.5;
    rb.contact({X, X - d * (4.0 / std::max(norm(d), 1e-9))});
  }
}

/// X on the grid's faces, edges and corners (where the body is cut by the volume's
/// border), x beyond the grid; X just beyond the accepted tolerance is refused and the
/// backend stays usable.
inline void deform_volume_border(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  const double lo = -0.5, hi = 59.5;  // the grid's faces (mm; voxel centres 0..59)
  DeformRun r(c, h.patient, config(1, 20));
  for (int s = 0; s < 10; ++s) {
    // 1 to 3 coordinates on a face (a face, an edge or a corner), 1e-3 voxel either side
    Vec3 X{c.uniform(0, 59), c.uniform(0, 59), c.uniform(0, 38)};
    const int faces = 1 + s % 3;
    for (int f = 0; f < faces; ++f) {
      const int a = (s + f) % 3;
      const double tweak = (s % 4 == 0) ? 0.0 : c.uniform(-1e-3, 1e-3);
      X[a] = (a == 2 || c.integer(0, 1) == 0 ? lo : hi) + tweak;
    }
    Vec3 x = X;
    for (int a = 0; a < 3; ++a) x[a] += X[a] <= lo + 0.01 ? -c.uniform(0, 20) : (X[a] >= hi - 0.01 ? c.uniform(0, 20) : c.uniform(-4, 4));
    const Outcome o = r.contact({X, x});
    if (s % 3 == 0) r.same_as_fresh({X, x}, o);
  }
  // beyond the face's tolerance (2e-3 voxel): refused, then the backend works as new
  r.refused({{lo - 3e-3, 30, 20}, {lo - 5, 30, 20}});
  r.refused({{30, hi + 1.0, 20}, {30, 58, 20}});
  const DeformContact k{{-0.5, 30, 20}, {-4.5, 31, 17}};
  r.same_as_fresh(k, r.contact(k));
}

/// Flat plateaus: a volume of one constant intensity (a flat material function, J must
/// stay that constant) and the force model's contacts on the slab whose F is flat deep
/// down (zero gradient: the proxy keeps no direction).
inline void deform_flat_plateau(Case& c) {
  INFO(c.describe());
  DeformRun r(c, constant_patient(32), config(2, 24, 40));
  for (int s = 0; s < 6; ++s) {
    const Vec3 X{c.uniform(4, 27), c.uniform(4, 27), c.uniform(4, 27)};
    r.contact({X, X + Vec3{c.uniform(-7, 7), c.uniform(-7, 7), c.uniform(-7, 7)}});
  }
  const HapticPatient h = plateau_slab();
  DeformRun rh(c, h.patient, config(1, 24));
  for (int s = 0; s < 6; ++s) {
    DeformContact k;
    if (haptic_contact(*h.patient, {c.uniform(2, 57), c.uniform(2, 57), c.uniform(5, 38)}, k)) rh.contact(k);
  }
}

/// `count` pairs of contacts 50 mm apart on r's 64-voxel grid (a random push from X1,
/// then the same from X2): the second must equal a fresh backend's (DeformRun::same_as_fresh).
inline void jumps_50mm(Case& c, DeformRun& r, int count) {
  for (int s = 0; s < count; ++s) {
    Vec3 X1, X2;
    do {
      X1 = {c.uniform(2, 61), c.uniform(2, 61), c.uniform(2, 61)};
      const Vec3 d{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
      X2 = X1 + d * (50.0 / std::max(norm(d), 1e-9));
    } while (!(X2.x > 0 && X2.x < 63 && X2.y > 0 && X2.y < 63 && X2.z > 0 && X2.z < 63));
    const Vec3 push{c.uniform(-6, 6), c.uniform(-6, 6), c.uniform(-6, 6)};
    r.contact({X1, X1 + push});
    const DeformContact k2{X2, X2 + push};
    r.same_as_fresh(k2, r.contact(k2));
  }
}

/// A 50 mm jump between two contacts: the second step must not see the first (each
/// step starts from undeformed: compared bit for bit with a fresh backend).
inline void deform_jump_50mm(Case& c) {
  INFO(c.describe());
  auto p = make_torso_patient(64);
  for (int preset = 1; preset <= 2; ++preset) {
    INFO("preset p" << preset);
    DeformRun r(c, p, config(preset, 24));
    jumps_50mm(c, r, 4);
  }
}

/// Displacements larger than the VOI (16 voxels): 20, 40 and 100 voxels, along the
/// axes and diagonals, some ending outside the grid.
inline void deform_displacement_larger_than_voi(Case& c) {
  INFO(c.describe());
  auto p = make_torso_patient(64);
  for (int preset = 1; preset <= 2; ++preset) {
    INFO("preset p" << preset);
    DeformRun r(c, p, config(preset, 16));
    for (double d : {20.0, 40.0, 100.0}) {
      r.contact(voxel_contact({32, 20, 32}, {d, 0, 0}));
      r.contact(voxel_contact({32, 20, 32}, {0, 0, -d}));
      const Vec3 X{c.uniform(12, 52), c.uniform(12, 52), c.uniform(12, 52)};
      const Vec3 dir{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)};
      r.contact({X, X + dir * (d / std::max(norm(dir), 1e-9))});
    }
  }
}

/// VOIs clipped by the volume's border: X near faces, edges and corners with the VOI
/// reaching outside; a VOI edge larger than the grid; the whole volume as VOI.
inline void deform_voi_crossing_border(Case& c) {
  INFO(c.describe());
  const HapticPatient h = slab();
  DeformRun r(c, h.patient, config(2, 32));
  for (int s = 0; s < 8; ++s) {
    Vec3 X{c.uniform(0, 6), c.uniform(0, 6), c.uniform(0, 6)};
    for (int a = 0; a < 3; ++a)
      if (c.integer(0, 1) && a != 2) X[a] = 59 - X[a];
    r.contact({X, X + Vec3{c.uniform(-8, 8), c.uniform(-8, 8), c.uniform(-8, 8)}});
  }
  DeformRun big(c, h.patient, config(1, 100, 10));  // the VOI edge exceeds the 60-voxel grid
  big.contact({{3, 56, 30}, {9, 50, 24}});
  DeformConfig whole = config(1, 16, 10);
  whole.settings.whole_volume = true;
  DeformRun w(c, make_torso_patient(24), whole);
  w.contact({{1, 12, 22}, {6, 9, 16}});
}

/// Soft tissue enclosed by bone (the paper's Fig. 4 cube): pushes towards, into and
/// through the shell with both presets and 0, 20 and 40 relaxation iterations. Beyond
/// the invariants, nothing outside the soft cube may move: u = 0 and J = I exactly.
inline void deform_enclosed_cube(Case& c) {
  INFO(c.describe());
  auto p = make_cube_patient(40, 16, 4);  // soft 12..27, bone 8..11 and 28..31
  for (int preset = 1; preset <= 2; ++preset)
    for (int iters : {0, 20, 40}) {
      INFO("preset p" << preset << ", " << iters << " relaxation iterations");
      DeformRun r(c, p, config(preset, 32, iters));
      std::vector<DeformContact> ks;
      for (int a = 0; a < 3; ++a)
        for (double d : {-10.0, -6.0, 6.0, 10.0}) {
          Vec3 dv{0, 0, 0};
          dv[a] = d;
          ks.push_back(voxel_contact({20, 20, 20}, dv));
        }
      ks.push_back(voxel_contact({12, 20, 20}, {-3, 0, 0}));  // a face element pushed into the bone
      ks.push_back(voxel_contact({27, 27, 27}, {2, 2, 2}));   // the inner corner, outward
      ks.push_back(voxel_contact({14, 25, 13}, {8, -7, 9}));  // across the cube
      for (int s = 0; s < 2; ++s) {
        const Vec3 X{c.uniform(12, 27), c.uniform(12, 27), c.uniform(12, 27)};
        ks.push_back({X, X + Vec3{c.uniform(-12, 12), c.uniform(-12, 12), c.uniform(-12, 12)}});
      }
      for (const DeformContact& k : ks) {
        const Outcome o = r.contact(k, {true, 0});
        const Voi& v = o.chainmail.voi;
        long long leaked_u = 0, leaked_j = 0;
        for (int kk = 0; kk < v.size.z; ++kk)
          for (int j = 0; j < v.size.y; ++j)
            for (int i = 0; i < v.size.x; ++i) {
              const int gi = v.lo.x + i, gj = v.lo.y + j, gk = v.lo.z + kk;
              const bool soft = gi >= 12 && gi <= 27 && gj >= 12 && gj <= 27 && gk >= 12 && gk <= 27;
              if (soft) continue;
              const long long n = v.index(i, j, kk);
              leaked_u += o.u[std::size_t(n)] != Vec3f(0, 0, 0);
              leaked_j += o.j[std::size_t(n)] != p->intensity.at(gi, gj, gk);
            }
        INFO("X " << fmt(k.skin_point_mm) << ", x " << fmt(k.tip_mm) << ": " << leaked_u
                  << " voxels outside the soft cube moved, " << leaked_j << " have J != I");
        REQUIRE(leaked_u == 0);
        REQUIRE(leaked_j == 0);
      }
    }
}

/// Relaxation at the stability limit: relax_step = 1/6 exactly, 400 iterations, on a
/// ChainMail field and on a checkerboard (the explicit scheme's least damped mode: at
/// 1/6 its amplification is exactly -1), with soft tissue (material 1) and tissue at the
/// bone threshold (material 1/2) beside bone. A step above 1/6 is refused.
inline void deform_relax_stability_limit(Case& c) {
  INFO(c.describe());
  DeformConfig cfg = config(1, 24, 400);
  cfg.settings.relax_step = deform::kRelaxStableStep;
  // above the limit by one part in a billion: refused with the limit in the message
  {
    DeformConfig over = cfg;
    over.settings.relax_step = deform::kRelaxStableStep * (1 + 1e-9);
    auto b = make_deform_backend(c.backend);
    REQUIRE_THROWS_WITH(b->bind(make_soft_patient(8), over), Catch::Contains("stable limit"));
  }
  // soft tissue everywhere, and tissue exactly at the threshold beside a bone slab
  const PatientPtr soft = make_soft_patient(24);
  const PatientPtr half = make_patient({24, 24, 24}, [](int i, int, int) { return i >= 18 ? kBoneHu : kBoneThresholdHu; });
  for (const PatientPtr& p : {soft, half}) {
    DeformRun r(c, p, cfg);
    const DeformContact k = voxel_contact({9, 12, 12}, {c.uniform(-6, 6), c.uniform(-6, 6), c.uniform(-6, 6)});
    const Outcome o = r.contact(k);
    // a checkerboard of amplitude 3 voxel on the soft elements of the same VOI
    std::vector<Vec3f> u0(o.u.size());
    const Voi& v = o.chainmail.voi;
    for (int kk = 0; kk < v.size.z; ++kk)
      for (int j = 0; j < v.size.y; ++j)
        for (int i = 0; i < v.size.x; ++i) {
          const bool bone = p->bone.at(v.lo.x + i, v.lo.y + j, v.lo.z + kk) != 0;
          const float s = ((i + j + kk) % 2 ? 3.0f : -3.0f);
          u0[std::size_t(v.index(i, j, kk))] = bone ? Vec3f(0, 0, 0) : Vec3f(s, -s, 0.5f * s);
        }
    // the grabbed element keeps whatever it holds: a smaller value, so the check below
    // sees the checkerboard's own amplitude
    const Vec3i gl = o.chainmail.grabbed_vox - v.lo;
    u0[std::size_t(v.index(gl.x, gl.y, gl.z))] = Vec3f(1, -1, 0.5f);
    const auto u = r.relax_field(k, u0);
    // 400 iterations at the limit must not have let it grow: checked in relax_field;
    // and it must not be frozen either (the boundary damps the mode)
    CHECK(max_abs_component(u) < 3.0f);
  }
}

#ifdef PALPSIM_STABILITY_PREP
/// `count` contacts the force model makes at random tips in the grid of `h` (of at most
/// ten times as many tries), each deformed with `cfg` and checked by DeformRun.
inline void deform_haptic_contacts(Case& c, const HapticPatient& h, const DeformConfig& cfg, int count) {
  DeformRun rp(c, h.patient, cfg);
  const Grid& g = h.patient->grid;
  int n = 0;
  for (int s = 0; s < 10 * count && n < count; ++s) {
    const Vec3 tip = g.to_physical({c.uniform(0, g.size.x - 1), c.uniform(0, g.size.y - 1), c.uniform(0, g.size.z - 1)});
    DeformContact k;
    if (haptic_contact(*h.patient, tip, k)) {
      rp.contact(k);
      ++n;
    }
  }
  REQUIRE(n == count);
}
#endif

/// The anisotropic grid itself (0.5 x 0.5 x 5 mm voxels): pushes of a few mm, i.e. up to
/// 20 voxels along x and y and one along z; with prep, the contacts the force model makes
/// on a patient prepared from a 0.5 x 0.5 x 5 mm CT.
inline void deform_anisotropic(Case& c) {
  INFO(c.describe());
  DeformRun r(c, anisotropic_grid_patient(), config(1, 24));
  for (int s = 0; s < 6; ++s) {
    const Vec3 X{c.uniform(1, 22), c.uniform(1, 22), c.uniform(1, 32)};
    r.contact({X, X + Vec3{c.uniform(-8, 8), c.uniform(-8, 8), c.uniform(-12, 6)}});
  }
#ifdef PALPSIM_STABILITY_PREP
  const HapticPatient h = prep_anisotropic_patient();
  deform_haptic_contacts(c, h, config(2, 32), 6);
#endif
}

/// Extreme HU: -3024 around the body and a 30000 HU metal rod (material function
/// saturated at both ends); with prep, the force model's contacts on such a CT.
inline void deform_extreme_hu(Case& c) {
  INFO(c.describe());
  auto p = extreme_hu_patient();
  for (int preset = 1; preset <= 2; ++preset) {
    DeformRun r(c, p, config(preset, 24));
    r.contact(voxel_contact({20, 14, 16}, {0, 5, 0}), {true, 0});   // into the metal rod
    r.contact(voxel_contact({20, 20, 16}, {3, 0, 0}), {true, 1});   // X in the metal
    r.contact(voxel_contact({20, 20, 29}, {0, 0, 6}), {true, 0});   // out of the body into -3024 HU
    for (int s = 0; s < 4; ++s) {
      const Vec3 X{c.uniform(3, 36), c.uniform(3, 36), c.uniform(3, 31)};
      r.contact({X, X + Vec3{c.uniform(-8, 8), c.uniform(-8, 8), c.uniform(-8, 8)}});
    }
  }
#ifdef PALPSIM_STABILITY_PREP
  const HapticPatient h = prep_extreme_hu_patient();
  deform_haptic_contacts(c, h, config(1, 24), 6);
#endif
}

/// One spot, many steps: the deformation of the same contact, stepped again and again
/// through step(), is bit for bit the same every time (no drift between steps).
inline void deform_one_spot_repeated(Case& c, int steps) {
  INFO(c.describe());
  auto p = make_torso_patient(48);
  DeformRun r(c, p, config(1, 24));
  const DeformContact k{{24.3, 8.2, 23.7}, {25.1, 14.6, 22.9}};
  const Outcome first = r.contact(k);
  DeformBackend& b = r.backend();
  for (int s = 0; s < steps; ++s) {
    b.step(k);
    const auto u = b.displacement();
    const float* j = b.deformed_brick();
    long long du = 0, dj = 0;
    for (std::size_t n = 0; n < u.size(); ++n) du += u[n] != first.u[n];
    for (std::size_t n = 0; n < first.j.size(); ++n) dj += j[n] != first.j[n];
    INFO("step " << s << ": " << du << " displacements and " << dj << " J voxels differ from the first step");
    REQUIRE(du == 0);
    REQUIRE(dj == 0);
  }
}

/// Random contacts, a tenth of them corrupt (NaN, +-Inf, X outside the grid, x absurdly
/// far): the corrupt ones are refused with palpsim::Error and the backend stays usable
/// (the next good contact equals a fresh backend's, bit for bit).
inline void deform_random_poses(Case& c, int count, int compare_every) {
  INFO(c.describe());
  auto p = make_torso_patient(40);
  const double nan = std::numeric_limits<double>::quiet_NaN(), inf = std::numeric_limits<double>::infinity();
  long long refusals = 0;
  // half the contacts under each of the paper's presets (p2's large pushes near bone and
  // clipped VOIs broke restrictions before chainmail_clamp() pulled one way only)
  for (int preset = 1; preset <= 2; ++preset) {
    DeformRun r(c, p, config(preset, 16, 10), compare_every);
    bool after_refusal = false;
    for (int s = 0; s < count / 2; ++s) {
      Vec3 X{c.uniform(-0.5, 39.5), c.uniform(-0.5, 39.5), c.uniform(-0.5, 39.5)};
      Vec3 x = X + Vec3{c.uniform(-10, 10), c.uniform(-10, 10), c.uniform(-10, 10)};
      const int kind = c.integer(0, 99);
      bool bad = false;
      if (kind < 3) {
        const bool in_x = c.integer(0, 1) == 1;
        const int a = c.integer(0, 2);
        (in_x ? x : X)[a] = kind == 0 ? nan : (kind == 1 ? inf : -inf);
        bad = true;
      } else if (kind < 5) {
        const int a = c.integer(0, 2);
        X[a] = c.integer(0, 1) ? c.uniform(-1e6, -0.51) : c.uniform(39.51, 1e6);  // X outside the grid
        bad = true;
      } else if (kind < 7) {
        const int a = c.integer(0, 2);
        x[a] = c.integer(0, 1) ? 1e300 : -2e8;  // x absurdly far (|index| >= 1e8)
        bad = true;
      } else if (kind < 10) {
        x = X + Vec3{c.uniform(-1, 1), c.uniform(-1, 1), c.uniform(-1, 1)} * 1e4;  // far, but accepted
      }
      const DeformContact k{X, x};
      if (bad) {
        r.refused(k);
        after_refusal = true;
        ++refusals;
        continue;
      }
      // x 1e4 voxels away may need more sweeps than the cap over a 16-voxel VOI: the state
      // must stay finite and bone still, convergence is not required there
      const Outcome o = r.contact(k, {kind >= 10, -1});
      if (after_refusal) r.same_as_fresh(k, o);
      after_refusal = false;
    }
  }
  REQUIRE(refusals > 0);
}

/// The shipped scenes' deformation (multigrid, a 5 mm fingertip, the inversion's cell
/// search, ChainMail left out where it cannot matter) on `count` contacts over the torso:
/// presses deepening a voxel a step (unit responses reused and warm-started), random
/// pushes anywhere (fresh solves, clipped VOIs, X in bone), jumps across the torso and
/// the grid's faces, and primes between them.
inline void deform_shipped_multigrid(Case& c, int count, int compare_every) {
  INFO(c.describe());
  auto p = make_torso_patient(48);
  DeformConfig cfg = config(1, 24, 0);
  cfg.relax = true;
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  cfg.settings.grab_radius_mm = 5;
  cfg.settings.invert_search = true;
  cfg.settings.untangle = false;
  DeformRun r(c, p, cfg, compare_every);
  long long skipped = 0, in_bone = 0, primes = 0;
  Vec3 X{24, 24, 24}, x = X;
  for (int s = 0; s < count; ++s) {
    // now and then the tip was out of the body in between: a prime anywhere (the server's
    // guess of the next contact), bone and the grid's faces included
    if (c.integer(0, 9) == 0) {
      const Vec3 P{c.uniform(-0.5, 47.5), c.uniform(-0.5, 47.5), c.uniform(-0.5, 47.5)};
      primes += r.prime({P, P});
    }
    const int kind = c.integer(0, 99);
    if (kind < 50 && s > 0) {
      x += Vec3{c.uniform(-0.3, 0.3), c.uniform(-0.3, 0.3), c.uniform(0.5, 1.2)};  // the press goes on
    } else if (kind < 80) {
      X = {c.uniform(-0.5, 47.5), c.uniform(-0.5, 47.5), c.uniform(-0.5, 47.5)};  // a new press anywhere
      x = X + Vec3{c.uniform(-4, 4), c.uniform(-4, 4), c.uniform(-4, 4)};
    } else if (kind < 90) {
      x = X + Vec3{c.uniform(-12, 12), c.uniform(-12, 12), c.uniform(-12, 12)};  // a jump of the tip
    } else {
      // X on a face of the grid
      X = {c.uniform(-0.5, 47.5), c.uniform(-0.5, 47.5), c.uniform(-0.5, 47.5)};
      X[c.integer(0, 2)] = c.integer(0, 1) ? -0.5 : 47.5;
      x = X + Vec3{c.uniform(-6, 6), c.uniform(-6, 6), c.uniform(-6, 6)};
    }
    if (s % 50 == 25) {
      // X in the spine (along k through voxel (23, 33)): nothing may move
      X = {23, 33, c.uniform(4, 44)};
      x = X + Vec3{c.uniform(-3, 3), c.uniform(-6, 0), c.uniform(-3, 3)};
    }
    const Outcome o = r.contact({X, x}, {true, -1});
    skipped += o.chainmail.skipped;
    in_bone += o.chainmail.grabbed_in_bone;
  }
  // the kinds of step the case is for were there
  REQUIRE(skipped > 0);
  REQUIRE(in_bone > 0);
  REQUIRE(primes > 0);
}

/// The contacts of a tip sweeping across the rib at 1 m/s (the hand-over of every 16th
/// pose of the haptic sweep: 16 mm apart), deformed with `cfg`.
inline void deform_rib_sweep(Case& c, const DeformConfig& cfg = config(1, 24)) {
  INFO(c.describe());
  const HapticPatient h = rib();
  DeformRun r(c, h.patient, cfg);
  for (double depth : {6.0, 11.0}) {
    ProxyState st{};
    for (int n = 0; n <= 56; ++n) {
      const Vec3 tip{2.0 + n, 20.3, kSlabSkinZ - depth};
      const ForceSample f = compute_force(*h.patient, HapticsSettings{}, tip, 1e-3, st);
      if (f.contact && n % 8 == 0) r.contact({f.skin_point_mm, tip});
    }
  }
  REQUIRE(r.contacts() >= 10);
}

}  // namespace palpsim::test::stability
