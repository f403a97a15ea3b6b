// The geometry of a voxel grid: size, spacing, origin and direction (ITK's LPS).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

#include "core/vec3.h"

namespace palpsim {

/// A voxel grid in physical space. Physical point of voxel index (i, j, k):
/// origin + direction * (spacing .* (i, j, k)), as in ITK; all in millimetres.
struct Grid {
  Vec3i size{0, 0, 0};                 // voxels along i, j, k
  Vec3 spacing_mm{1, 1, 1};            // voxel edge lengths
  Vec3 origin_mm{0, 0, 0};             // physical position of voxel (0,0,0)'s centre
  std::array<double, 9> direction{1, 0, 0, 0, 1, 0, 0, 0, 1};  // row-major 3x3, columns = axes

  /// Number of voxels.
  std::size_t count() const { return std::size_t(size.x) * size.y * size.z; }
  /// Linear index of voxel (i, j, k); i runs fastest.
  std::size_t index(int i, int j, int k) const {
    return (std::size_t(k) * size.y + j) * size.x + i;
  }
  /// True when (i, j, k) lies inside the grid.
  bool contains(int i, int j, int k) const {
    return i >= 0 && j >= 0 && k >= 0 && i < size.x && j < size.y && k < size.z;
  }
  /// Physical point (mm) of a continuous voxel index.
  Vec3 to_physical(const Vec3& ijk) const {
    const Vec3 s{ijk.x * spacing_mm.x, ijk.y * spacing_mm.y, ijk.z * spacing_mm.z};
    const auto& d = direction;
    return origin_mm + Vec3{d[0] * s.x + d[1] * s.y + d[2] * s.z, d[3] * s.x + d[4] * s.y + d[5] * s.z,
                            d[6] * s.x + d[7] * s.y + d[8] * s.z};
  }
  /// Continuous voxel index of a physical point (mm); direction is orthonormal.
  Vec3 to_index(const Vec3& p_mm) const {
    const Vec3 r = p_mm - origin_mm;
    const auto& d = direction;
    // the inverse of an orthonormal direction matrix is its transpose
    const Vec3 s{d[0] * r.x + d[3] * r.y + d[6] * r.z, d[1] * r.x + d[4] * r.y + d[7] * r.z,
                 d[2] * r.x + d[5] * r.y + d[8] * r.z};
    return {s.x / spacing_mm.x, s.y / spacing_mm.y, s.z / spacing_mm.z};
  }
  /// Rotates a vector given along the grid axes (i, j, k) into physical space (no scaling).
  Vec3 axes_to_physical(const Vec3& v) const {
    const auto& d = direction;
    return {d[0] * v.x + d[1] * v.y + d[2] * v.z, d[3] * v.x + d[4] * v.y + d[5] * v.z,
            d[6] * v.x + d[7] * v.y + d[8] * v.z};
  }
  /// Rotates a physical vector onto the grid axes (no scaling).
  Vec3 physical_to_axes(const Vec3& v) const {
    const auto& d = direction;
    return {d[0] * v.x + d[3] * v.y + d[6] * v.z, d[1] * v.x + d[4] * v.y + d[7] * v.z,
            d[2] * v.x + d[5] * v.y + d[8] * v.z};
  }
  /// True when both grids describe the same voxels in the same place.
  bool same_geometry(const Grid& o) const {
    return size == o.size && spacing_mm == o.spacing_mm && origin_mm == o.origin_mm && direction == o.direction;
  }
};

}  // namespace palpsim
