// The CUDA backend's multigrid relaxation against the CPU reference: the same fields on
// the phantom press and with bone, the unit response reused and restarted as on the cpu,
// primes, and steps without ChainMail equal to steps with it.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cfloat>
#include <chrono>
#include <cstdio>
#include <random>

#include <cuda_runtime.h>

#include "cuda/device_patient.h"
#include "deform/backend.h"
#include "deform/engine.h"
#include "gpu/gpu_pair.h"
#include "support/deform_fixtures.h"
#include "support/phantom_press.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
using namespace palpsim::test;
using namespace palpsim::test::gpu;

TEST_CASE("gpu multigrid relaxation matches the cpu on the phantom press and with bone") {
  if (!have_gpu()) return;
  // the grabbed element alone, and a fingertip (deform.grab_radius_mm) that moves with it
  const double radius = GENERATE(0.0, 3.0);
  // the accuracy bench's press over L3 (VOI 64) and a soft cube in a bone shell
  PhantomCt ct = make_phantom(340.0 / 255.0);
  const Press press = spinous_press(ct.geometry);
  const PatientPtr phantom = patient_from_intensity(std::move(ct.hu), "phantom");
  const PatientPtr cube = make_cube_patient(64, 40, 3);
  // a VOI too thin to coarsen (the whole grid sweeps its one level) and one whose
  // levels all fit in block 0
  const PatientPtr thin = make_patient({64, 64, 2}, [](int i, int, int) { return kSoftHu + 0.5f * i; });
  const PatientPtr small = make_soft_patient(8);
  // held elements that ChainMail moves (material weight 0 outside the bone mask): one
  // scalar solve per component instead of the unit response
  const PatientPtr hot = with_hot_voxels(make_soft_patient(64), {{32, 32, 34}, {33, 32, 33}, {32, 33, 35}}, 3000.0f);
  struct Case {
    const char* name;
    PatientPtr p;
    DeformContact c;
  };
  const Case cases[] = {{"phantom press", phantom, press.contact},
                        {"cube in bone", cube, voxel_contact({32, 32, 13}, {1, 0, 5})},
                        {"thin VOI", thin, voxel_contact({32, 32, 1}, {2, -1, 0.4})},
                        {"8^3 VOI", small, voxel_contact({4, 4, 4}, {0, 1.5, 0})},
                        {"moved held voxels", hot, voxel_contact({32, 32, 32}, {0, 1, 3})}};
  for (const Case& k : cases)
    for (int steps : {1, 6, 20}) {
      DeformConfig cfg = preset_config(1);
      cfg.settings.voi_edge = 64;
      cfg.settings.relax_method = RelaxMethod::kMultigrid;
      cfg.settings.relax_cycles = steps;
      cfg.settings.grab_radius_mm = radius;
      Pair b(k.p, cfg);
      same_chainmail(b, k.c);
      b.cpu->relax();
      b.gpu->relax();
      const auto ua = b.cpu->displacement(), ug = b.gpu->displacement();
      const float worst = max_abs_diff(ua, ug);
      // the same operations in the same order up to FMA contraction and the order of the
      // dot products' sums (block sums and atomics on the GPU): each step's step lengths
      // agree to ~1e-6 relative, and conjugate gradients carry such differences on without
      // growing them much in 20 steps; 1e-4 of the largest displacement (about 1000 float
      // ulps) bounds that and lies 100 times below the 1% accuracy the steps are chosen for
      const float tol = 1e-4f * std::max(1.0f, max_abs(ua));
      INFO(k.name << ", " << steps << " steps, fingertip " << radius << " mm: max |u_cpu - u_gpu| " << worst
                  << " voxel, tolerance " << tol);
      std::printf("multigrid %s, %d steps, fingertip %g mm: max |u_cpu - u_gpu| = %g voxel (tolerance %g)\n", k.name,
                  steps, radius, worst, tol);
      CHECK(worst <= tol);
      CHECK(moved_bone_count(*k.p, b.gpu->voi(), ug) == 0);
    }
}

TEST_CASE("gpu multigrid reuses its unit response to the bit, and as the cpu does") {
  if (!have_gpu()) return;
  // the cpu case of tests/unit/deform_relax_multigrid_test.cpp: a tip moving within one
  // voxel (the VOI stays), a voxel on, and back
  auto torso = make_torso_patient(64);
  ReusePress press = reuse_press();
  press.cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);  // the grabbed element alone, and a fingertip
  INFO("grab_radius_mm " << press.cfg.settings.grab_radius_mm);
  DeformConfig fresh_cfg = press.cfg;
  fresh_cfg.relax_reuse = false;
  auto cpu = make_deform_backend("cpu"), reuse = make_deform_backend("cuda"), fresh = make_deform_backend("cuda");
  cpu->bind(torso, press.cfg);
  reuse->bind(torso, press.cfg);
  fresh->bind(torso, fresh_cfg);
  // the cpu's field against a gpu's: FMA contraction and the order of the dot products'
  // sums, as in the case above
  auto close = [&](const std::vector<Vec3f>& ua, const std::vector<Vec3f>& ug) {
    return max_abs_diff(ua, ug) <= 1e-4f * std::max(1.0f, max_abs(ua));
  };
  for (std::size_t s = 0; s < press.contacts.size(); ++s) {
    const DeformContact& c = press.contacts[s];
    const DeformStats a = cpu->step(c), r = reuse->step(c), f = fresh->step(c);
    INFO("contact " << s);
    CHECK(a.relax_solves == press.solves[s]);
    CHECK(r.relax_solves == press.solves[s]);
    CHECK(f.relax_solves == 1);
    // to the bit: the step lengths are floats of double dot products, and the atomics'
    // order changes those doubles by ~1e-16 relative, which a float rounding crosses
    // with a probability near 1e-8 per step length
    CHECK(reuse->displacement() == fresh->displacement());
    CHECK(close(cpu->displacement(), reuse->displacement()));
  }
  // the same VOI with a bone element displaced by hand (a held element that moved): three
  // solves, as on the cpu, after which G is gone and the next clean step solves afresh
  const DeformContact c = press.contacts.back();
  for (DeformBackend* b : {cpu.get(), reuse.get()}) REQUIRE(relax_with_bone_moved(*b, *torso, c) >= 0);
  CHECK(close(cpu->displacement(), reuse->displacement()));
  const DeformStats r = reuse->step(c);
  fresh->step(c);
  CHECK(r.relax_solves == 1);
  CHECK(reuse->displacement() == fresh->displacement());
}

TEST_CASE("gpu multigrid starts a new unit response from the last one as the cpu does") {
  if (!have_gpu()) return;
  // the cpu case of tests/unit/deform_relax_multigrid_test.cpp: paths whose every step
  // enters another voxel (deform.relax_warm_cycles, the default), each path after a
  // solve from zero; then a held element moved by hand (three solves, G gone) and the
  // next step solves from zero again on both
  auto torso = make_torso_patient(64);
  DeformConfig cfg = reuse_press().cfg;
  cfg.settings.relax_warm_cycles = DeformSettings{}.relax_warm_cycles;
  cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);  // the grabbed element alone, and a fingertip
  INFO("grab_radius_mm " << cfg.settings.grab_radius_mm);
  for (const WarmPath& path : warm_paths()) {
    auto cpu = make_deform_backend("cpu"), gpu = make_deform_backend("cuda");
    cpu->bind(torso, cfg);
    gpu->bind(torso, cfg);
    for (std::size_t s = 0; s < path.contacts.size(); ++s) {
      const DeformStats a = cpu->step(path.contacts[s]), g = gpu->step(path.contacts[s]);
      const auto ua = cpu->displacement(), ug = gpu->displacement();
      const float worst = max_abs_diff(ua, ug);
      // FMA contraction and the order of the dot products' sums, as in the cases above; a
      // warm start carries the last step's difference on, which its steps do not grow
      const float tol = 1e-4f * std::max(1.0f, max_abs(ua));
      INFO(path.name << ", step " << s << ": max |u_cpu - u_gpu| " << worst << " voxel, tolerance " << tol);
      CHECK(a.relax_warm == (s > 0));
      CHECK(g.relax_warm == a.relax_warm);
      CHECK(g.relax_cycles == a.relax_cycles);
      CHECK(g.relax_solves == 1);
      CHECK(worst <= tol);
      CHECK(moved_bone_count(*torso, gpu->voi(), ug) == 0);
    }
    if (path.contacts.size() < 2) continue;
    const DeformContact c = path.contacts.front();
    for (DeformBackend* b : {cpu.get(), gpu.get()}) REQUIRE(relax_with_bone_moved(*b, *torso, path.contacts.back()) >= 0);
    const DeformStats a = cpu->step(c), g = gpu->step(c);
    INFO(path.name << ", after three solves");
    CHECK_FALSE(a.relax_warm);
    CHECK_FALSE(g.relax_warm);
    CHECK(g.relax_cycles == cfg.settings.relax_cycles);
  }
}

TEST_CASE("gpu prime solves the unit response as the cpu does, and leaves the deformation in place") {
  if (!have_gpu()) return;
  // the cpu cases of tests/unit/deform_relax_multigrid_test.cpp on both backends: a prime
  // between steps touches neither the field nor J; a step onto the primed contact reuses
  // it; a session's first contact after a prime on its approach starts warm
  auto torso = with_body_mask(make_torso_patient(64));
  DeformConfig cfg = reuse_press().cfg;
  cfg.settings.relax_warm_cycles = DeformSettings{}.relax_warm_cycles;
  cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);
  INFO("grab_radius_mm " << cfg.settings.grab_radius_mm);
  // FMA contraction and the order of the dot products' sums, as in the cases above
  auto close = [&](const std::vector<Vec3f>& ua, const std::vector<Vec3f>& ug) {
    return max_abs_diff(ua, ug) <= 1e-4f * std::max(1.0f, max_abs(ua));
  };
  auto cpu = make_deform_backend("cpu"), gpu = make_deform_backend("cuda");
  cpu->bind(torso, cfg);
  gpu->bind(torso, cfg);
  const DeformContact c1 = voxel_contact({32, 10, 32}, {2, 5, -3}), far = voxel_contact({20, 14, 24}, {1, 3, 0});
  for (DeformBackend* b : {cpu.get(), gpu.get()}) b->step(c1);
  const std::vector<Vec3f> u = gpu->displacement();
  const std::vector<float> J(gpu->deformed_brick(), gpu->deformed_brick() + gpu->voi().count());
  const DeformPrime pa = cpu->prime(far), pg = gpu->prime(far);
  CHECK(pg.solved);
  Vec3i held;
  REQUIRE(gpu->unit_response(held));
  CHECK(held == Vec3i{20, 14, 24});
  CHECK(pg.warm == pa.warm);
  CHECK(pg.steps == pa.steps);
  CHECK(pg.voi == pa.voi);
  CHECK(gpu->displacement() == u);
  CHECK(std::equal(J.begin(), J.end(), gpu->deformed_brick()));
  const DeformStats a = cpu->step(far), g = gpu->step(far);
  CHECK(a.relax_solves == 0);
  CHECK(g.relax_solves == 0);
  CHECK(close(cpu->displacement(), gpu->displacement()));
  // a prime may not come between the halves of a step
  gpu->begin_step(c1);
  CHECK_THROWS_WITH(gpu->prime(far), Catch::Contains("between begin_step() and end_step()"));
  gpu->end_step();
  // a new session's first contact, primed on the approach from above the skin
  auto cpu2 = make_deform_backend("cpu"), gpu2 = make_deform_backend("cuda");
  cpu2->bind(torso, cfg);
  gpu2->bind(torso, cfg);
  const Vec3 X(34, 10, 29);
  for (DeformBackend* b : {cpu2.get(), gpu2.get()}) REQUIRE(b->prime({X, X}).solved);
  const DeformContact first = voxel_contact({34, 10, 29}, {0, 1, 0});
  const DeformStats a2 = cpu2->step(first), g2 = gpu2->step(first);
  CHECK(a2.relax_warm);
  CHECK(g2.relax_warm);
  CHECK(g2.relax_cycles == a2.relax_cycles);
  CHECK(close(cpu2->displacement(), gpu2->displacement()));
}

TEST_CASE("gpu multigrid steps without ChainMail equal steps with it, to the bit, as on the cpu") {
  if (!have_gpu()) return;
  // the cpu case of tests/unit/deform_relax_multigrid_test.cpp: where no element ChainMail
  // moves is held (deform::HeldBlocks) a multigrid step leaves ChainMail out (its kernel
  // sets the grabbed element alone), and u = d G, J and the counts are those of steps that
  // run it; the unit response and the inversion are the same launches on the same data
  auto torso = make_torso_patient(64);
  const MultigridSteps steps = multigrid_steps();
  const std::vector<DeformContact>& contacts = steps.contacts;
  DeformConfig cfg = steps.cfg;
  cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);  // the grabbed element alone, and a fingertip
  INFO("grab_radius_mm " << cfg.settings.grab_radius_mm);
  DeformConfig full_cfg = cfg;
  full_cfg.skip_chainmail = false;
  auto skip = make_deform_backend("cuda"), full = make_deform_backend("cuda");
  skip->bind(torso, cfg);
  full->bind(torso, full_cfg);
  for (std::size_t s = 0; s < contacts.size(); ++s) {
    INFO("contact " << s);
    CHECK(step_without_chainmail_differs(*skip, *full, contacts[s]) == "");
  }
}
