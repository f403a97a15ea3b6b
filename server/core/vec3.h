// Small 3-vector used for positions (mm, LPS), voxel indices and displacements.
#pragma once

#include <cmath>

#include "core/hd.h"

namespace palpsim {

/// A 3-vector of T; positions are millimetres in the CT's physical space (LPS)
/// unless a name says otherwise (`_vox` for continuous voxel indices).
template <typename T>
struct Vec3T {
  T x{0}, y{0}, z{0};

  PALPSIM_HD Vec3T() = default;
  PALPSIM_HD Vec3T(T x_, T y_, T z_) : x(x_), y(y_), z(z_) {}
  template <typename U>
  PALPSIM_HD explicit Vec3T(const Vec3T<U>& o) : x(T(o.x)), y(T(o.y)), z(T(o.z)) {}

  PALPSIM_HD T& operator[](int i) { return i == 0 ? x : (i == 1 ? y : z); }
  PALPSIM_HD T operator[](int i) const { return i == 0 ? x : (i == 1 ? y : z); }
  PALPSIM_HD Vec3T operator+(const Vec3T& o) const { return {x + o.x, y + o.y, z + o.z}; }
  PALPSIM_HD Vec3T operator-(const Vec3T& o) const { return {x - o.x, y - o.y, z - o.z}; }
  PALPSIM_HD Vec3T operator-() const { return {-x, -y, -z}; }
  PALPSIM_HD Vec3T operator*(T s) const { return {x * s, y * s, z * s}; }
  PALPSIM_HD Vec3T operator/(T s) const { return {x / s, y / s, z / s}; }
  PALPSIM_HD Vec3T& operator+=(const Vec3T& o) { x += o.x; y += o.y; z += o.z; return *this; }
  PALPSIM_HD Vec3T& operator-=(const Vec3T& o) { x -= o.x; y -= o.y; z -= o.z; return *this; }
  PALPSIM_HD Vec3T& operator*=(T s) { x *= s; y *= s; z *= s; return *this; }
  PALPSIM_HD bool operator==(const Vec3T& o) const { return x == o.x && y == o.y && z == o.z; }
  PALPSIM_HD bool operator!=(const Vec3T& o) const { return !(*this == o); }
};

template <typename T>
PALPSIM_HD Vec3T<T> operator*(T s, const Vec3T<T>& v) { return v * s; }
template <typename T>
PALPSIM_HD T dot(const Vec3T<T>& a, const Vec3T<T>& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename T>
PALPSIM_HD Vec3T<T> cross(const Vec3T<T>& a, const Vec3T<T>& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
template <typename T>
PALPSIM_HD T norm(const Vec3T<T>& v) { return std::sqrt(dot(v, v)); }
template <typename T>
PALPSIM_HD bool is_finite(const Vec3T<T>& v) {
  return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z);
}

using Vec3 = Vec3T<double>;
using Vec3f = Vec3T<float>;
using Vec3i = Vec3T<int>;

}  // namespace palpsim
