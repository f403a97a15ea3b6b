// bench/press_forces.h, the accuracy report's comparison of the two force models for one
// press: on a slab of soft tissue (1 mm voxels) both forces point out of the body, the
// elastic one grows with depth (eq. 2's follows the distance to bone as well), the elastic force a pose reply carries for a held tip is the step's own f0,
// and a scene without the elastic step is refused naming the field.
#include <catch2/catch.hpp>

#include "bench/press_forces.h"
#include "support/synthetic_patient.h"

using namespace palpsim;

namespace {

// the slab with the elastic model at VOI 32 (a fingertip of 5 mm) on the cpu backend
Scene elastic_scene() {
  Scene s;
  s.name = "press_forces test";
  s.deform.relax_method = RelaxMethod::kElastic;
  s.deform.grab_radius_mm = 5;
  s.deform.voi_edge = 32;
  s.deform.backend = DeformBackendChoice::kCpu;
  s.effects.chainmail = true;
  s.effects.relaxation = true;
  return s;
}

}  // namespace

TEST_CASE("press_forces gives eq. 2's force and the elastic model's as a server would report them", "[bench][elastic]") {
  const auto p = test::slab_patient();
  const Scene scene = elastic_scene();
  // away from the bone block (x, y in 24.5..35.5), pressing down (-z) from 5 mm above the skin
  const Vec3 from{12, 12, test::kSlabSkinZ + 5};
  double last_elastic = 0;
  for (const double depth : {2.0, 4.0}) {
    INFO("depth " << depth << " mm");
    const bench::PressForces f = bench::press_forces(p, scene, from, {12, 12, test::kSlabSkinZ - depth});
    REQUIRE(f.contact);
    CHECK(f.depth_mm == Approx(depth).margin(0.5));  // B is trilinear between voxel centres (1 mm)
    // both out of the body (+z); the elastic force grows with depth
    CHECK(f.proxy_n.z > 0);
    REQUIRE(f.model.contact);
    CHECK(f.model.normal.z < -0.99);
    CHECK(f.elastic_n.z > 0.99 * norm(f.elastic_n));
    CHECK(f.elastic_n.z > last_elastic);
    CHECK(f.model.stiffness_n_per_mm > 0);
    CHECK(f.run.converged);
    // below max_force_n the held tip's reply carries the step's force itself (rounding only)
    REQUIRE(norm(f.model.f0_n) < scene.haptics.max_force_n);
    CHECK(norm(f.elastic_n - f.model.f0_n) < 1e-12);
    std::printf("depth %.0f mm: proxy %.4f N, elastic %.4f N (k %.4f N/mm, %d contact nodes, %d CG steps, %.0f ms)\n",
                depth, f.proxy_n.z, f.elastic_n.z, f.model.stiffness_n_per_mm, f.model.contact_nodes, f.run.iterations,
                f.step_ms);
    last_elastic = f.elastic_n.z;
  }
  // a tip outside the body: no contact, no force of either model
  const bench::PressForces out = bench::press_forces(p, scene, from, {12, 12, test::kSlabSkinZ + 2});
  CHECK_FALSE(out.contact);
  CHECK(out.proxy_n == Vec3{0, 0, 0});
  CHECK(out.elastic_n == Vec3{0, 0, 0});
  // another relaxation has no elastic force
  Scene mg = scene;
  mg.deform.relax_method = RelaxMethod::kMultigrid;
  try {
    bench::press_forces(p, mg, from, {12, 12, test::kSlabSkinZ - 2});
    FAIL("a multigrid scene was not refused");
  } catch (const Error& e) {
    CHECK(std::string(e.what()).find("deform.relax_method") != std::string::npos);
  }
}
