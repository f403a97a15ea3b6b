// The catalogue's patients that go through prep (build_patient: resampling, masks,
// distance maps, F, grad F), so the hard input reaches the simulation the way a CT does.
#include <cmath>

#include "prep/prepare.h"
#include "stability/stability_patients.h"

namespace palpsim::test::stability {

HapticPatient prep_anisotropic_patient() {
  static const HapticPatient h = [] {
    // 0.5 x 0.5 x 5 mm voxels: 64 x 56 in-plane, 8 thick slices (35 mm)
    Grid g;
    g.size = {64, 56, 8};
    g.spacing_mm = {0.5, 0.5, 5.0};
    g.origin_mm = {-15.75, -13.75, -17.5};
    Volume<float> v(g, -1000.0f);
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const Vec3 x = g.to_physical({double(i), double(j), double(k)});
          const double e = (x.x / 14.0) * (x.x / 14.0) + (x.y / 11.0) * (x.y / 11.0);
          if (e > 1) continue;
          float hu = float(40 + 20 * std::sin(0.9 * x.x) * std::cos(0.7 * x.y));
          // a bone rod along z (a spinous process seen in thick slices)
          if (std::hypot(x.x, x.y - 4.0) < 3.0) hu = 800;
          // a rib in one slice only: partial volume leaves it at 500 HU
          if (k == 4 && std::fabs(x.y + 6.0) < 2.5 && std::fabs(x.x) < 12.0) hu = 500;
          v.at(i, j, k) = hu;
        }
    Scene scene;  // prep.spacing_mm = 0: the smallest input spacing, 0.5 mm
    return HapticPatient{build_patient(v, scene, "stability: CT at 0.5 x 0.5 x 5 mm"), Sdf{}, "prep 0.5 x 0.5 x 5 mm"};
  }();
  return h;
}

HapticPatient prep_extreme_hu_patient() {
  static const HapticPatient h = [] {
    // 1 mm, 48 x 48 x 24; -3024 HU outside a 23 mm field of view (scanner padding)
    Grid g;
    g.size = {48, 48, 24};
    g.spacing_mm = {1, 1, 1};
    Volume<float> v(g, -3024.0f);
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const double x = i - 23.5, y = j - 23.5;
          if (std::hypot(x, y) > 23) continue;  // outside the field of view
          float hu = -1000;
          if ((x / 19) * (x / 19) + (y / 15) * (y / 15) <= 1) hu = float(40 + 30 * std::sin(0.5 * i + 0.2 * k));
          const double rb = std::hypot(x - 2, y + 3);
          if (rb < 6) hu = rb > 4.5 ? 1000.0f : 300.0f;        // a bone: cortex and marrow
          if (std::hypot(x - 2, y + 3) < 2) hu = 30000.0f;     // a metal screw in it
          if (std::hypot(x + 9, y - 6) < 1.5) hu = 30000.0f;   // and a metal clip in soft tissue
          v.at(i, j, k) = hu;
        }
    Scene scene;
    return HapticPatient{build_patient(v, scene, "stability: CT with -3024 and 30000 HU"), Sdf{}, "prep extreme HU"};
  }();
  return h;
}

}  // namespace palpsim::test::stability
