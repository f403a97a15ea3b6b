// The stability catalogue's deformation cases (stability_deform.h) on the "cuda"
// backend: palpsim-gpu-stability-tests, CTest labels gpu and stability, run on the GPU
// machine. Every contact is checked for the same invariants as on the CPU, and
// ChainMail must equal the CPU reference exactly (relaxation within float rounding).
// The force model has no GPU implementation, so its half of the catalogue runs in
// palpsim-test-deform-stability only; the cases that hand the force model's contacts to
// the deformation compute them on the CPU here too.
// The elastic model's cases (stability_elastic.h) check the same invariants as on the CPU
// (the backends' agreement is tests/gpu's); they print SKIPPED while the cuda backend
// refuses the model.
// Without a usable CUDA device every case prints SKIPPED and passes (as
// tests/gpu/deform_gpu_test.cpp does; Catch2 v2 has no skip).
#include <catch2/catch.hpp>

#include <cstdio>
#include <string>

#include "stability/stability_deform.h"
#include "stability/stability_elastic.h"

using namespace palpsim;
using namespace palpsim::test;
using namespace palpsim::test::stability;

namespace {

constexpr const char* kExe = "palpsim-gpu-stability-tests";

bool have_gpu() {
  std::string why;
  if (cuda_deform_available(&why)) return true;
  std::printf("SKIPPED: %s\n", why.c_str());
  return false;
}

// a device, and a cuda backend that takes the elastic model (it refuses it at bind() until
// it has one: SKIPPED with its reason)
bool have_gpu_elastic() {
  if (!have_gpu()) return false;
  try {
    make_deform_backend("cuda")->bind(with_skin(make_soft_patient(8)), elastic_config(8));
  } catch (const Error& e) {
    std::printf("SKIPPED: %s\n", e.what());
    return false;
  }
  return true;
}

Case make_case(const char* name) { return Case(name, "cuda", kExe); }

}  // namespace

TEST_CASE("gpu stability: tip inside bone") {
  if (!have_gpu()) return;
  Case c = make_case("tip inside bone");
  deform_tip_inside_bone(c);
}

TEST_CASE("gpu stability: tip exactly on the skin") {
  if (!have_gpu()) return;
  Case c = make_case("tip exactly on the skin");
  deform_on_skin(c);
}

TEST_CASE("gpu stability: tip on a voxel corner") {
  if (!have_gpu()) return;
  Case c = make_case("tip on a voxel corner");
  deform_voxel_corner(c);
}

TEST_CASE("gpu stability: tip on the volume border") {
  if (!have_gpu()) return;
  Case c = make_case("tip on the volume border");
  deform_volume_border(c);
}

TEST_CASE("gpu stability: flat plateaus of F (zero gradient)") {
  if (!have_gpu()) return;
  Case c = make_case("flat plateaus of F");
  deform_flat_plateau(c);
}

TEST_CASE("gpu stability: a 50 mm jump of the tip within 1 ms") {
  if (!have_gpu()) return;
  Case c = make_case("a 50 mm jump of the tip within 1 ms");
  deform_jump_50mm(c);
}

TEST_CASE("gpu stability: a displacement larger than the VOI") {
  if (!have_gpu()) return;
  Case c = make_case("a displacement larger than the VOI");
  deform_displacement_larger_than_voi(c);
}

TEST_CASE("gpu stability: a VOI crossing the volume border") {
  if (!have_gpu()) return;
  Case c = make_case("a VOI crossing the volume border");
  deform_voi_crossing_border(c);
}

TEST_CASE("gpu stability: soft tissue enclosed by bone (Fig. 4 cube)") {
  if (!have_gpu()) return;
  Case c = make_case("soft tissue enclosed by bone");
  deform_enclosed_cube(c);
}

TEST_CASE("gpu stability: relaxation at the stability limit") {
  if (!have_gpu()) return;
  Case c = make_case("relaxation at the stability limit");
  deform_relax_stability_limit(c);
}

TEST_CASE("gpu stability: anisotropic input spacing (0.5 x 0.5 x 5 mm)") {
  if (!have_gpu()) return;
  Case c = make_case("anisotropic input spacing");
  deform_anisotropic(c);
}

TEST_CASE("gpu stability: extreme HU (-3024 and 30000)") {
  if (!have_gpu()) return;
  Case c = make_case("extreme HU");
  deform_extreme_hu(c);
}

TEST_CASE("gpu stability: a million haptic steps on one spot") {
  if (!have_gpu()) return;
  Case c = make_case("a million haptic steps on one spot");
  // the deformation's half: the same contact stepped again and again gives the same J
  deform_one_spot_repeated(c, 1000);
}

TEST_CASE("gpu stability: 100000 random poses including NaN and Inf") {
  if (!have_gpu()) return;
  Case c = make_case("100000 random poses including NaN and Inf");
  // more random contacts than on the CPU (a step is ~0.1 ms here); the CPU reference
  // checks ChainMail and relaxation on every 20th
  deform_random_poses(c, 20000, 20);
}

TEST_CASE("gpu stability: the shipped deformation (multigrid, 5 mm fingertip, cell search) over presses, pushes and jumps") {
  if (!have_gpu()) return;
  Case c = make_case("the shipped deformation (multigrid, 5 mm fingertip, cell search)");
  deform_shipped_multigrid(c, 2000, 1);
}

TEST_CASE("gpu stability: the tip sweeping across a rib at 1 m/s") {
  if (!have_gpu()) return;
  Case c = make_case("the tip sweeping across a rib at 1 m/s");
  deform_rib_sweep(c);
}

// ---------------------------------------------------------------------------------
// the elastic model (stability_elastic.h), with more random contacts than on the CPU

TEST_CASE("gpu stability: tip inside bone (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("tip inside bone (elastic)");
  elastic_tip_inside_bone(c);
}

TEST_CASE("gpu stability: tip exactly on the skin (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("tip exactly on the skin (elastic)");
  elastic_on_skin(c);
}

TEST_CASE("gpu stability: tip on a voxel corner (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("tip on a voxel corner (elastic)");
  elastic_voxel_corner(c);
}

TEST_CASE("gpu stability: tip on the volume border (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("tip on the volume border (elastic)");
  elastic_volume_border(c);
}

TEST_CASE("gpu stability: flat plateaus of F (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("flat plateaus of F (elastic)");
  elastic_flat_plateau(c);
}

TEST_CASE("gpu stability: a 50 mm jump of the tip (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("a 50 mm jump of the tip (elastic)");
  elastic_jump_50mm(c);
}

TEST_CASE("gpu stability: a displacement larger than the VOI (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("a displacement larger than the VOI (elastic)");
  elastic_displacement_larger_than_voi(c);
}

TEST_CASE("gpu stability: a VOI crossing the volume border (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("a VOI crossing the volume border (elastic)");
  elastic_voi_crossing_border(c);
}

TEST_CASE("gpu stability: anisotropic input spacing (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("anisotropic input spacing (elastic)");
  elastic_anisotropic(c);
}

TEST_CASE("gpu stability: extreme HU (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("extreme HU (elastic)");
  elastic_extreme_hu(c);
}

TEST_CASE("gpu stability: one spot stepped again and again (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("one spot stepped again and again (elastic)");
  elastic_one_spot_repeated(c, 200);
}

TEST_CASE("gpu stability: random poses including NaN and Inf (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("random poses including NaN and Inf (elastic)");
  elastic_random_poses(c, 2000);
}

TEST_CASE("gpu stability: the tip sweeping across a rib (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("the tip sweeping across a rib (elastic)");
  elastic_rib_sweep(c);
}

TEST_CASE("gpu stability: Poisson's ratio 0.49 (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("Poisson's ratio 0.49 (elastic)");
  elastic_nu_049(c);
}

TEST_CASE("gpu stability: 2 mm of tissue over bone (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("2 mm of tissue over bone (elastic)");
  elastic_thin_tissue_over_bone(c);
}

TEST_CASE("gpu stability: the sphere entering bone (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("the sphere entering bone (elastic)");
  elastic_sphere_into_bone(c);
}

TEST_CASE("gpu stability: a 40 mm indentation (elastic)", "[elastic]") {
  if (!have_gpu_elastic()) return;
  Case c = make_case("a 40 mm indentation (elastic)");
  elastic_indentation_40mm(c);
}
