// Reference (b) of `palpsim-bench accuracy`: Boussinesq's closed-form displacement
// field of a point load on the flat face of a homogeneous, isotropic, linear-elastic
// half-space (Johnson, Contact Mechanics, eq. 3.19; Timoshenko & Goodier sec. 138).
#pragma once

#include <cmath>

namespace palpsim::bench {

/// Displacement at one point under a normal point load: radial (away from the load's
/// line of action) and normal (positive into the half-space), in the unit of
/// load / (shear modulus x length).
struct BoussinesqU {
  double radial = 0, normal = 0;
};

/// Boussinesq's field at lateral distance r and depth z >= 0 below the load (same
/// length unit, r^2 + z^2 > 0), for load P, shear modulus G and Poisson's ratio nu:
///   u_r = P / (4 pi G R) (r z / R^2 - (1 - 2 nu) r / (R + z)),
///   u_z = P / (4 pi G R) (2 (1 - nu) + z^2 / R^2),   R = sqrt(r^2 + z^2).
/// Once normalised the field's shape depends on nu alone.
inline BoussinesqU boussinesq(double r, double z, double nu, double P = 1, double G = 1) {
  const double R = std::sqrt(r * r + z * z);
  const double c = P / (4.0 * M_PI * G * R);
  return {c * (r * z / (R * R) - (1.0 - 2.0 * nu) * r / (R + z)), c * (2.0 * (1.0 - nu) + z * z / (R * R))};
}

}  // namespace palpsim::bench
