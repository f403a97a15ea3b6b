// A scalar image on a Grid, owned in a flat vector (i fastest).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <memory>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include "core/grid.h"

namespace palpsim {

/// Blocks of at least this many bytes are placed on 2 MiB boundaries and offered to the
/// kernel as transparent huge pages (Linux's "madvise" mode, Debian's default): a 43 MB
/// volume then takes 21 page faults instead of 10,600, which made the first write of a
/// fresh volume twice as fast (the EDT's first pass on the real CT: 26 -> 13 ms on one
/// thread, palpsim-bench prep). Smaller blocks come from the ordinary heap.
constexpr std::size_t kHugeBlockBytes = std::size_t(4) << 20;
/// The size and alignment of a transparent huge page on x86-64 Linux.
constexpr std::size_t kHugePageBytes = std::size_t(2) << 20;

/// Allocates `bytes` for a volume: huge-page aligned and advised from kHugeBlockBytes on.
inline void* allocate_volume_bytes(std::size_t bytes) {
  if (bytes < kHugeBlockBytes) return ::operator new(bytes);
  const std::size_t rounded = (bytes + kHugePageBytes - 1) / kHugePageBytes * kHugePageBytes;
  void* p = std::aligned_alloc(kHugePageBytes, rounded);
  if (!p) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
  ::madvise(p, rounded, MADV_HUGEPAGE);  // advice only: without THP the pages stay small
#endif
  return p;
}

/// Frees a block from allocate_volume_bytes (the same `bytes`).
inline void free_volume_bytes(void* p, std::size_t bytes) noexcept {
  if (bytes < kHugeBlockBytes)
    ::operator delete(p);
  else
    std::free(p);
}

/// std::allocator, except that an element made without a value is default-initialised
/// (left as it is for numbers) instead of zeroed: a volume that its maker writes whole
/// then costs one pass over memory, and its pages are first touched by the threads that
/// write them, not by one thread zeroing them ahead. Large blocks sit on huge pages
/// (allocate_volume_bytes).
template <typename T>
struct DefaultInitAllocator : std::allocator<T> {
  template <typename U>
  struct rebind {
    using other = DefaultInitAllocator<U>;
  };
  DefaultInitAllocator() = default;
  template <typename U>
  DefaultInitAllocator(const DefaultInitAllocator<U>&) noexcept {}
  T* allocate(std::size_t n) {
    if (n > std::size_t(-1) / sizeof(T)) throw std::bad_array_new_length();
    return static_cast<T*>(allocate_volume_bytes(n * sizeof(T)));
  }
  void deallocate(T* p, std::size_t n) noexcept { free_volume_bytes(p, n * sizeof(T)); }
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

/// The index box of a mask's nonzero voxels: lo and hi inclusive, hi.x < 0 when there is none.
struct IndexBox {
  Vec3i lo{0, 0, 0}, hi{-1, -1, -1};
  bool empty() const { return hi.x < 0; }
};

/// The index box of the voxels of `m` that are not 0 (the body's or bone's extent).
inline IndexBox mask_box(const Volume<std::uint8_t>& m) {
  const Grid& g = m.grid;
  IndexBox b{{g.size.x, g.size.y, g.size.z}, {-1, -1, -1}};
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i)
        if (m.data[g.index(i, j, k)]) {
          b.lo = {std::min(b.lo.x, i), std::min(b.lo.y, j), std::min(b.lo.z, k)};
          b.hi = {std::max(b.hi.x, i), std::max(b.hi.y, j), std::max(b.hi.z, k)};
        }
  return b;
}

}  // namespace palpsim
