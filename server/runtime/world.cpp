#include "runtime/world.h"

#include <algorithm>

#include "core/volume.h"
#include "render/camera.h"

namespace palpsim::runtime {

std::unique_ptr<World> make_world(const Scene& scene, PatientPtr patient, std::uint64_t generation) {
  auto w = std::make_unique<World>();
  w->scene = scene;
  w->patient = std::move(patient);
  w->generation = generation;
  const Grid& g = w->patient->grid;
  // grid bounds: the eight corners of the voxel box
  Vec3 lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  auto grow = [](Vec3& a, Vec3& b, const Vec3& p) {
    a = {std::min(a.x, p.x), std::min(a.y, p.y), std::min(a.z, p.z)};
    b = {std::max(b.x, p.x), std::max(b.y, p.y), std::max(b.z, p.z)};
  };
  for (int c = 0; c < 8; ++c) {
    const Vec3 ijk{(c & 1) ? g.size.x - 0.5 : -0.5, (c & 2) ? g.size.y - 0.5 : -0.5, (c & 4) ? g.size.z - 0.5 : -0.5};
    grow(lo, hi, g.to_physical(ijk));
  }
  w->bounds_min_mm = lo;
  w->bounds_max_mm = hi;
  // body bounds: index box of the body voxels, then its corners in physical space
  const IndexBox box = mask_box(w->patient->body);
  const Vec3i bl = box.lo, bh = box.hi;
  if (!box.empty()) {
    Vec3 a{1e300, 1e300, 1e300}, b{-1e300, -1e300, -1e300};
    for (int c = 0; c < 8; ++c)
      grow(a, b, g.to_physical(Vec3{double((c & 1) ? bh.x : bl.x), double((c & 2) ? bh.y : bl.y),
                                    double((c & 4) ? bh.z : bl.z)}));
    w->body_min_mm = a;
    w->body_max_mm = b;
  }
  w->body_center_mm = render::body_center(g, bl, bh);
  return w;
}

}  // namespace palpsim::runtime
