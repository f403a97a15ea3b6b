#include "deform/held_blocks.h"

#include <algorithm>

#include "core/shared_cache.h"

namespace palpsim::deform {

HeldBlocks::HeldBlocks(const PatientPtr& patient, float threshold, float width)
    : patient_(patient), threshold_(threshold), width_(width) {
  const Patient& p = *patient;
  const Vec3i& n = p.grid.size;
  for (int a = 0; a < 3; ++a) blocks_[a] = (n[a] + kEdge - 1) / kEdge;
  flag_.assign(std::size_t(blocks_.x) * blocks_.y * blocks_.z, 0);
  // one pass in memory order; a row's flags go to its blocks
  for (int k = 0; k < n.z; ++k)
    for (int j = 0; j < n.y; ++j) {
      const std::size_t row = p.grid.index(0, j, k);
      const float* I = p.intensity.data.data() + row;
      const std::uint8_t* bone = p.bone.data.data() + row;
      std::uint8_t* f = flag_.data() + (std::size_t(k / kEdge) * blocks_.y + j / kEdge) * blocks_.x;
      for (int i = 0; i < n.x; ++i)
        if (may_hold_outside_bone(I[i], bone[i] != 0, threshold, width)) f[i / kEdge] = 1;
    }
  flagged_ = std::count(flag_.begin(), flag_.end(), std::uint8_t(1));
}

std::shared_ptr<const HeldBlocks> HeldBlocks::of(const PatientPtr& patient, float threshold, float width) {
  static SharedCache<const HeldBlocks> maps;
  return maps.get(
      [&](const HeldBlocks& m) { return m.patient_.lock() == patient && m.threshold_ == threshold && m.width_ == width; },
      [&] { return std::make_shared<const HeldBlocks>(patient, threshold, width); });
}

bool HeldBlocks::any_in(const Voi& voi) const {
  if (voi.count() <= 0) return false;
  Vec3i lo, hi;
  for (int a = 0; a < 3; ++a) {
    lo[a] = std::max(voi.lo[a], 0) / kEdge;
    hi[a] = std::min((voi.lo[a] + voi.size[a] - 1) / kEdge, blocks_[a] - 1);
  }
  for (int k = lo.z; k <= hi.z; ++k)
    for (int j = lo.y; j <= hi.y; ++j) {
      const std::uint8_t* f = flag_.data() + (std::size_t(k) * blocks_.y + j) * blocks_.x;
      for (int i = lo.x; i <= hi.x; ++i)
        if (f[i]) return true;
    }
  return false;
}

}  // namespace palpsim::deform
