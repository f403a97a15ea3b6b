// The accuracy bench's press on the phantom (10 mm into the back over the L3 spinous
// process), shared with the tests that check a backend on the same press.
#pragma once

#include <string>

#include "core/error.h"
#include "deform/backend.h"
#include "prep/phantom.h"

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

}  // namespace palpsim::test
