#include "haptics/patch_cut.h"

#include <algorithm>
#include <cmath>
#include <cstring>

namespace palpsim {

Vec3i patch_box(const Grid& g, const Vec3& center_mm, int edge, Vec3i& size) {
  const Vec3 ijk = g.to_index(center_mm);
  Vec3i lo;
  for (int a = 0; a < 3; ++a) {
    size[a] = std::min(edge, g.size[a]);
    // the nearest voxel (a far or non-finite centre goes to the border), then the box inside the grid
    const double c = std::isfinite(ijk[a]) ? std::clamp(std::round(ijk[a]), -1.0, double(g.size[a])) : 0.0;
    lo[a] = std::clamp(int(c) - size[a] / 2, 0, g.size[a] - size[a]);
  }
  return lo;
}

void gather_patch(const Patient& p, const Vec3i& lo, const Vec3i& size, std::uint8_t* body, float* force_mm,
                  Vec3f* grad_force) {
  // one contiguous row along i per (j, k)
  const std::size_t row = std::size_t(size.x);
  std::size_t out = 0;
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j < size.y; ++j, out += row) {
      const std::size_t in = p.grid.index(lo.x, lo.y + j, lo.z + k);
      std::memcpy(body + out, p.body.data.data() + in, row * sizeof(std::uint8_t));
      std::memcpy(force_mm + out, p.force.data.data() + in, row * sizeof(float));
      std::memcpy(grad_force + out, p.grad_force.data.data() + in, row * sizeof(Vec3f));
    }
}

Grid patch_grid(const Grid& g, const Vec3i& lo, const Vec3i& size) {
  Grid b = g;
  b.size = size;
  b.origin_mm = g.to_physical(Vec3(lo));
  return b;
}

ForcePatch cut_patch(const Patient& patient, const Vec3& center_mm, int edge, const HapticsSettings& params,
                     std::uint64_t version) {
  ForcePatch out;
  Vec3i size;
  out.lo = patch_box(patient.grid, center_mm, edge, size);
  out.grid = patch_grid(patient.grid, out.lo, size);
  out.patient_size = patient.grid.size;
  const std::size_t n = out.grid.count();
  out.body.resize(n);
  out.force_mm.resize(n);
  out.grad_force.resize(n);
  gather_patch(patient, out.lo, size, out.body.data(), out.force_mm.data(), out.grad_force.data());
  out.params = params;
  out.version = version;
  out.center_mm = center_mm;
  return out;
}

}  // namespace palpsim
