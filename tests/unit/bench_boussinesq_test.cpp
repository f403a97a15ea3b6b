// Reference (b) of `palpsim-bench accuracy` (bench/boussinesq.h): Boussinesq's point-load
// field against values known in closed form.
#include <catch2/catch.hpp>

#include <cmath>

#include "bench/boussinesq.h"

using palpsim::bench::boussinesq;

// the closed form is evaluated in double from a few operations: 1e-12 relative covers rounding
constexpr double kRel = 1e-12;

TEST_CASE("Boussinesq: surface settlement is P (1 - nu) / (2 pi G r), radial P (1 - 2 nu) / (4 pi G r) inwards") {
  const double P = 2.5, G = 3.0, nu = 0.3, r = 7.0;
  const auto u = boussinesq(r, 0.0, nu, P, G);
  CHECK(u.normal == Approx(P * (1 - nu) / (2 * M_PI * G * r)).epsilon(kRel));
  CHECK(u.radial == Approx(-P * (1 - 2 * nu) / (4 * M_PI * G * r)).epsilon(kRel));
}

TEST_CASE("Boussinesq: on the load's axis u_z = P (3 - 2 nu) / (4 pi G z) and u_r = 0") {
  const double P = 1.0, G = 1.0, nu = 0.45, z = 4.0;
  const auto u = boussinesq(0.0, z, nu, P, G);
  CHECK(u.normal == Approx(P * (3 - 2 * nu) / (4 * M_PI * G * z)).epsilon(kRel));
  CHECK(u.radial == 0.0);
}

TEST_CASE("Boussinesq: incompressible (nu = 0.5) surface points move only downwards, and the field scales as 1/R") {
  CHECK(boussinesq(5.0, 0.0, 0.5).radial == Approx(0.0).margin(1e-15));  // (1 - 2 nu) = 0: no radial term at z = 0
  const auto a = boussinesq(3.0, 4.0, 0.45), b = boussinesq(6.0, 8.0, 0.45);  // same direction, twice as far
  CHECK(b.normal == Approx(a.normal / 2).epsilon(kRel));
  CHECK(b.radial == Approx(a.radial / 2).epsilon(kRel));
}
