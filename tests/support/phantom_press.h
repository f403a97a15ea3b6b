// The accuracy bench's press on the phantom (10 mm into the back over the L3 spinous
// process), shared with the tests that check a backend on the same press.
#pragma once

#include <string>
#include <utility>

#include "core/error.h"
#include "deform/backend.h"
#include "prep/phantom.h"
#include "deform_fixtures.h"

namespace palpsim::test {

/// A press over a spinous process: X 1 mm under the back skin straight above the
/// landmark, x 10 mm anterior of X (into the body, towards the bone).
struct Press {
  std::string landmark = "spinous_tip_L3";
  Vec3 landmark_mm;
  DeformContact contact;
  double press_mm = 10;      // |x - X|
  double skin_depth_mm = 1;  // X below the skin
  double bone_depth_mm = 0;  // spinous tip below X
};

/// The press over L3's spinous tip, from the phantom's closed-form geometry.
inline Press spinous_press(const PhantomGeometry& geo) {
  Press p;
  const Vec3 tip = geo.landmark(p.landmark);
  p.landmark_mm = tip;
  // X: straight above the tip (+y, posterior) where the skin's signed distance is
  // -skin_depth_mm; bisection between the tip (inside) and 80 mm above it (outside)
  auto depth = [&](double y) { return geo.skin_signed_distance_mm({tip.x, y, tip.z}); };
  double lo = tip.y, hi = tip.y + 80;
  if (!(depth(lo) < -p.skin_depth_mm && depth(hi) > 0))
    throw Error("deform accuracy: no skin between " + p.landmark + " and 80 mm above it");
  for (int it = 0; it < 60; ++it) {
    const double mid = 0.5 * (lo + hi);
    (depth(mid) < -p.skin_depth_mm ? lo : hi) = mid;
  }
  const Vec3 X{tip.x, lo, tip.z};
  p.contact = {X, X - Vec3{0, p.press_mm, 0}};
  p.bone_depth_mm = X.y - tip.y;
  return p;
}

/// The phantom as a patient the elastic model can press: intensity and bone mask as
/// patient_from_intensity() makes them, and the body mask C and depth under the skin B
/// from the closed-form skin (a voxel is body when its centre lies inside; B the skin's
/// distance plus half a voxel, as tests/support/synthetic_patient.h and prep make it).
inline PatientPtr elastic_phantom(PhantomCt&& ct) {
  const PhantomGeometry geo = ct.geometry;
  PatientPtr p = patient_from_intensity(std::move(ct.hu), "phantom");
  auto q = std::const_pointer_cast<Patient>(p);  // ours until returned: filled in place, not copied
  const Grid& g = q->grid;
  const double half = 0.5 * std::min(g.spacing_mm.x, std::min(g.spacing_mm.y, g.spacing_mm.z));
  q->body = Volume<std::uint8_t>(g, 0);
  q->dist_skin_mm = Volume<float>(g, 0.0f);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        const double sd = geo.skin_signed_distance_mm(g.to_physical(Vec3{double(i), double(j), double(k)}));
        if (!(sd < 0)) continue;
        q->body.at(i, j, k) = 1;
        q->dist_skin_mm.at(i, j, k) = float(-sd + half);
      }
  return p;
}

}  // namespace palpsim::test
