// A scalar image on a Grid, owned in a flat vector (i fastest).
#pragma once

#include <algorithm>
#include <cmath>
#include <memory>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#include "core/grid.h"

namespace palpsim {

/// std::allocator, except that an element made without a value is default-initialised
/// (left as it is for numbers) instead of zeroed: a volume that its maker writes whole
/// then costs one pass over memory, and its pages are first touched by the threads that
/// write them, not by one thread zeroing them ahead.
template <typename T>
struct DefaultInitAllocator : std::allocator<T> {
  template <typename U>
  struct rebind {
    using other = DefaultInitAllocator<U>;
  };
  DefaultInitAllocator() = default;
  template <typename U>
  DefaultInitAllocator(const DefaultInitAllocator<U>&) noexcept {}
  template <typename U>
  void construct(U* p) noexcept(std::is_nothrow_default_constructible<U>::value) {
    ::new (static_cast<void*>(p)) U;
  }
  template <typename U, typename... Args>
  void construct(U* p, Args&&... args) {
    ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
  }
};

/// Tag for a volume whose voxels are left unset, for makers that write every voxel.
struct Uninitialized {};

/// A scalar volume of T on a grid; voxel (i, j, k) is data[grid.index(i, j, k)].
template <typename T>
struct Volume {
  Grid grid;
  std::vector<T, DefaultInitAllocator<T>> data;

  Volume() = default;
  /// Allocates a volume on `g` filled with `fill`.
  explicit Volume(const Grid& g, T fill = T{}) : grid(g), data(g.count(), fill) {}
  /// Allocates a volume on `g` without setting its voxels: the caller writes them all.
  Volume(const Grid& g, Uninitialized) : grid(g), data(g.count()) {}

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

/// True when a continuous voxel index lies within half a voxel of the grid on every
/// axis (false for NaN); this also keeps floor() of it in int range.
inline bool within_grid(const Grid& g, const Vec3& ijk) {
  return ijk.x >= -0.5 && ijk.x <= g.size.x - 0.5 && ijk.y >= -0.5 && ijk.y <= g.size.y - 0.5 &&
         ijk.z >= -0.5 && ijk.z <= g.size.z - 0.5;
}

/// Calls fn(linear_index, weight) for the voxels of a trilinear sample at the
/// continuous index `ijk` (edge voxels replicated, zero weights skipped), so several
/// volumes on one grid can be sampled with one set of weights. `ijk` must be finite
/// and near the grid (see within_grid).
template <typename Fn>
inline void for_each_trilinear_corner(const Grid& g, const Vec3& ijk, Fn&& fn) {
  const int i0 = int(std::floor(ijk.x)), j0 = int(std::floor(ijk.y)), k0 = int(std::floor(ijk.z));
  const double fx = ijk.x - i0, fy = ijk.y - j0, fz = ijk.z - k0;
  const int ii[2] = {std::clamp(i0, 0, g.size.x - 1), std::clamp(i0 + 1, 0, g.size.x - 1)};
  const int jj[2] = {std::clamp(j0, 0, g.size.y - 1), std::clamp(j0 + 1, 0, g.size.y - 1)};
  const int kk[2] = {std::clamp(k0, 0, g.size.z - 1), std::clamp(k0 + 1, 0, g.size.z - 1)};
  const double wx[2] = {1 - fx, fx}, wy[2] = {1 - fy, fy}, wz[2] = {1 - fz, fz};
  for (int dk = 0; dk < 2; ++dk)
    for (int dj = 0; dj < 2; ++dj)
      for (int di = 0; di < 2; ++di) {
        const double w = wx[di] * wy[dj] * wz[dk];
        if (w != 0) fn(g.index(ii[di], jj[dj], kk[dk]), w);
      }
}

/// Trilinear sample of `v` at a continuous voxel index; outside the grid the
/// nearest edge value is used. Returns double for all T.
template <typename T>
double sample_trilinear(const Volume<T>& v, const Vec3& ijk) {
  double acc = 0;
  for_each_trilinear_corner(v.grid, ijk, [&](std::size_t n, double w) { acc += w * double(v.data[n]); });
  return acc;
}

}  // namespace palpsim
