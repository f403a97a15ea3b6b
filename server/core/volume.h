// A scalar image on a Grid, owned in a flat vector (i fastest).
#pragma once

#include <algorithm>
#include <cmath>
#include <vector>

#include "core/grid.h"

namespace palpsim {

/// A scalar volume of T on a grid; voxel (i, j, k) is data[grid.index(i, j, k)].
template <typename T>
struct Volume {
  Grid grid;
  std::vector<T> data;

  Volume() = default;
  /// Allocates a volume on `g` filled with `fill`.
  explicit Volume(const Grid& g, T fill = T{}) : grid(g), data(g.count(), fill) {}

  T& at(int i, int j, int k) { return data[grid.index(i, j, k)]; }
  const T& at(int i, int j, int k) const { return data[grid.index(i, j, k)]; }
  /// Value at (i, j, k) with indices clamped to the grid (edge replication).
  const T& at_clamped(int i, int j, int k) const {
    i = std::clamp(i, 0, grid.size.x - 1);
    j = std::clamp(j, 0, grid.size.y - 1);
    k = std::clamp(k, 0, grid.size.z - 1);
    return data[grid.index(i, j, k)];
  }
  /// Bytes held by the voxels.
  std::size_t bytes() const { return data.size() * sizeof(T); }
};

/// Trilinear sample of `v` at a continuous voxel index; outside the grid the
/// nearest edge value is used. Returns double for all T.
template <typename T>
double sample_trilinear(const Volume<T>& v, const Vec3& ijk) {
  const int i0 = int(std::floor(ijk.x)), j0 = int(std::floor(ijk.y)), k0 = int(std::floor(ijk.z));
  const double fx = ijk.x - i0, fy = ijk.y - j0, fz = ijk.z - k0;
  double acc = 0;
  for (int dk = 0; dk < 2; ++dk)
    for (int dj = 0; dj < 2; ++dj)
      for (int di = 0; di < 2; ++di) {
        const double w = (di ? fx : 1 - fx) * (dj ? fy : 1 - fy) * (dk ? fz : 1 - fz);
        if (w != 0) acc += w * double(v.at_clamped(i0 + di, j0 + dj, k0 + dk));
      }
  return acc;
}

}  // namespace palpsim
