// The elastic model's references in palpsim-bench accuracy --elastic (bench/elastic_refs.h):
// Hertz's force and surface profile, the patient refined 2x, the skin point and the block.
#include <catch2/catch.hpp>

#include <cmath>

#include "bench/elastic_refs.h"

using namespace palpsim;
using namespace palpsim::bench;

TEST_CASE("Hertz's force grows as d^1.5 and its surface profile is continuous at the contact radius", "[bench]") {
  // 4/3 E / (1 - nu^2) sqrt(R) d^1.5: E 12 kPa, nu 0.45, R 4 mm, d 1 mm -> 0.016 / 0.7975 * 2 N
  CHECK(hertz_force_n(12, 0.45, 4, 1) == Approx(4.0 / 3.0 * 0.012 / (1 - 0.45 * 0.45) * 2).epsilon(1e-12));
  CHECK(hertz_force_n(12, 0.45, 4, 2) / hertz_force_n(12, 0.45, 4, 1) == Approx(std::pow(2.0, 1.5)).epsilon(1e-12));
  const double R = 8, d = 1.6, a = std::sqrt(R * d);
  CHECK(hertz_surface_mm(0, R, d) == d);
  // both branches give a^2 / 2R at r = a (to 1e-6 of it: the outer branch's asin near 1)
  CHECK(hertz_surface_mm(a * (1 - 1e-10), R, d) == Approx(a * a / (2 * R)).epsilon(1e-6));
  CHECK(hertz_surface_mm(a * (1 + 1e-10), R, d) == Approx(a * a / (2 * R)).epsilon(1e-6));
  // far out, a point load's 1 / r: 4 a^3 / (3 pi R r), within 0.1 % at 200 contact radii
  CHECK(hertz_surface_mm(200 * a, R, d) == Approx(4 * a * a * a / (3 * M_PI * R * 200 * a)).epsilon(1e-3));
  CHECK(hertz_surface_mm(-1.0, R, d) == hertz_surface_mm(1.0, R, d));
}

TEST_CASE("refine_half keeps the coarse nodes and ends the tissue where the coarse model does", "[bench]") {
  // a block of 1 mm voxels, body for j <= 6, a bone voxel at (5, 3, 5), a body corner notch
  auto p = elastic_block({10, 10, 10}, 1.0, 6, 40);
  auto q = std::make_shared<Patient>(*p);
  q->bone.at(5, 3, 5) = 1;
  q->body.at(3, 6, 3) = 0;  // a notch in the skin layer
  q->intensity.at(4, 2, 4) = 100;
  const deform::Voi voi{{2, 1, 2}, {6, 7, 6}};
  const auto f = refine_half(*q, voi);
  REQUIRE(f->grid.size == Vec3i{11, 13, 11});
  CHECK(f->grid.spacing_mm.x == 0.5);
  // fine node 2 i lies on coarse node i, with its values
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const Vec3i c = voi.lo + Vec3i{i, j, k};
        const Vec3 at = f->grid.to_physical(Vec3(2 * i, 2 * j, 2 * k)) - q->grid.to_physical(Vec3(c.x, c.y, c.z));
        REQUIRE(norm(at) < 1e-12);
        REQUIRE(f->body.at(2 * i, 2 * j, 2 * k) == q->body.at(c.x, c.y, c.z));
        REQUIRE(f->bone.at(2 * i, 2 * j, 2 * k) == q->bone.at(c.x, c.y, c.z));
        REQUIRE(f->intensity.at(2 * i, 2 * j, 2 * k) == q->intensity.at(c.x, c.y, c.z));
      }
  // between the skin layer (j 6 -> fine 10) and the air above (fine 12): outside (mean 1/2)
  CHECK(f->body.at(4, 11, 4) == 0);
  CHECK(f->body.at(4, 9, 4) == 1);
  // beside the notch (coarse (3, 6, 3) outside): the face centre between it and three body
  // nodes (mean 3/4) is body, the edge midpoint towards it (mean 1/2) is not
  CHECK(f->body.at(3, 10, 3) == 1);  // fine (3, 10, 3): coarse (3..4, 6, 3..4) three of four body
  CHECK(f->body.at(2, 10, 3) == 0);  // fine (2, 10, 3): coarse (3, 6, 3..4): one of two body
  // the bone voxel alone: its neighbours halfway are not bone (mean 1/2)
  CHECK(f->bone.at(6, 4, 6) == 1);
  CHECK(f->bone.at(7, 4, 6) == 0);
  CHECK(f->has_bone);
  // intensity and depth: means of the nodes around (100 and 40 -> 70 halfway)
  CHECK(f->intensity.at(5, 2, 4) == Approx(70));
  CHECK(f->dist_skin_mm.at(4, 9, 4) == Approx(0.5 * (q->dist_skin_mm.at(4, 5, 4) + q->dist_skin_mm.at(4, 6, 4))));
}

TEST_CASE("the skin point lies where the trilinear body mask is 1/2, and the block's depth is prep's", "[bench]") {
  // body for j <= 6: C falls from 1 at node 6 to 0 at node 7, so 1/2 at y = 6.5 mm
  auto p = elastic_block({10, 10, 10}, 1.0, 6, 40);
  const Vec3 X = skin_point_along(*p, {4.3, 2.0, 5.1}, {0, 1, 0});
  CHECK(X.y == Approx(6.5).margin(1e-5));
  CHECK(X.x == 4.3);
  CHECK(body_at(*p, p->grid.to_index(X)) == Approx(0.5).margin(1e-5));
  // a ray that never leaves the body is refused
  CHECK_THROWS_AS(skin_point_along(*p, {4.0, 2.0, 5.0}, {0, -1, 0}, 2.0), Error);
  // B to the first outside node: 1 mm at the skin layer, 7 mm at j = 0; 0 in the air
  CHECK(p->dist_skin_mm.at(3, 6, 3) == 1.0f);
  CHECK(p->dist_skin_mm.at(3, 0, 3) == 7.0f);
  CHECK(p->dist_skin_mm.at(3, 7, 3) == 0.0f);
  CHECK(p->intensity.at(3, 7, 3) == -1000.0f);
}
