// Several sessions on the CUDA backend at once against each stepping alone: steps in
// flight side by side with a share of the GPU, a shared multigrid scratch taken in turns,
// and batches of sessions stepped by shared launches, bit for bit.
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

TEST_CASE("steps of several sessions in flight at once, each with a share of the GPU, equal steps one at a time") {
  if (!have_gpu()) return;
  auto torso = make_torso_patient(96);
  DeformConfig cfg = preset_config(2);
  cfg.settings.voi_edge = 48;
  cfg.settings.backend = DeformBackendChoice::kCuda;
  // four sessions pressing at different points, and one session stepping them in turn
  const std::vector<DeformContact> k = four_presses();
  DeformEngine alone(torso, cfg);
  std::vector<std::vector<float>> j_alone(4);
  std::vector<DeformStats> st_alone(4);
  for (int s = 0; s < 4; ++s) {
    st_alone[s] = alone.step(k[s]);
    j_alone[s].assign(alone.deformed_brick(), alone.deformed_brick() + alone.voi().count());
  }
  std::vector<std::unique_ptr<DeformEngine>> sessions;
  for (int s = 0; s < 4; ++s) sessions.push_back(std::make_unique<DeformEngine>(torso, cfg));
  for (int share : {1, 4}) {
    for (auto& e : sessions) e->backend().set_gpu_share(share);
    for (int s = 0; s < 4; ++s) sessions[s]->begin_step(k[s]);
    for (int s = 0; s < 4; ++s) {
      const DeformStats st = sessions[s]->end_step();
      INFO("share " << share << ", session " << s);
      // ChainMail is exact whatever the grid; relaxation and inversion sum in the same
      // order per element whatever the number of blocks (each element is one thread's),
      // so the fields and J equal the session alone's to the bit
      CHECK(st.chainmail.moved == st_alone[s].chainmail.moved);
      CHECK(st.chainmail.sweeps == st_alone[s].chainmail.sweeps);
      CHECK(st.invert_unresolved == st_alone[s].invert_unresolved);
      const std::vector<float> j(sessions[s]->deformed_brick(), sessions[s]->deformed_brick() + sessions[s]->voi().count());
      CHECK(j == j_alone[s]);
    }
  }
  // the halves refuse to be misused
  CHECK_THROWS_WITH(sessions[0]->end_step(), Catch::Contains("end_step() without begin_step()"));
  sessions[0]->begin_step(k[0]);
  CHECK_THROWS_WITH(sessions[0]->begin_step(k[0]), Catch::Contains("begin_step() twice"));
  sessions[0]->end_step();
}

TEST_CASE("multigrid sessions share one solver scratch, in turns when in flight at once, and step as alone") {
  if (!have_gpu()) return;
  // four multigrid sessions on one patient hold one scratch (residuals, directions, coarse
  // levels): their own memory is their two unit responses and flags. Begun together on
  // their own streams, their solves take turns on it (share 1), or use scratches of their
  // own (share 4); either way each equals a twin stepping the same contacts alone
  auto torso = make_torso_patient(96);
  DeformConfig cfg = preset_config(2);
  cfg.settings.voi_edge = 48;
  cfg.settings.backend = DeformBackendChoice::kCuda;
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  const std::vector<DeformContact> k = four_presses();
  std::vector<std::unique_ptr<DeformEngine>> sessions, twins;
  for (int s = 0; s < 4; ++s) {
    sessions.push_back(std::make_unique<DeformEngine>(torso, cfg));
    twins.push_back(std::make_unique<DeformEngine>(torso, cfg));
  }
  const Vec3 deeper{0.0, 1.0, 0.0};
  for (int share : {1, 4, 1}) {
    for (auto& e : sessions) e->backend().set_gpu_share(share);
    for (int s = 0; s < 4; ++s) sessions[s]->begin_step({k[s].skin_point_mm, k[s].tip_mm + deeper * double(share)});
    for (int s = 0; s < 4; ++s) {
      const DeformStats st = sessions[s]->end_step();
      const DeformStats a = twins[s]->step({k[s].skin_point_mm, k[s].tip_mm + deeper * double(share)});
      INFO("share " << share << ", session " << s);
      CHECK(st.relax_solves == a.relax_solves);
      CHECK(st.relax_warm == a.relax_warm);
      CHECK(sessions[s]->backend().displacement() == twins[s]->backend().displacement());
      const std::vector<float> j(sessions[s]->deformed_brick(), sessions[s]->deformed_brick() + sessions[s]->voi().count());
      CHECK(j == std::vector<float>(twins[s]->deformed_brick(), twins[s]->deformed_brick() + twins[s]->voi().count()));
    }
  }
  // one shared scratch, counted once; each session's own: G, the last G, three flags (and
  // the scratch it made for share 4)
  const DeformMemory m0 = sessions[0]->backend().memory(), m1 = sessions[1]->backend().memory();
  CHECK(m0.shared_scratch_bytes > 0);
  CHECK(m0.shared_scratch_bytes == m1.shared_scratch_bytes);
  const std::size_t capacity = 48 * 48 * 48;
  CHECK(twins[0]->backend().memory().relax_bytes == 2 * capacity * sizeof(float) + 3 * sizeof(int));
  CHECK(m0.relax_bytes == 2 * capacity * sizeof(float) + 3 * sizeof(int) + m0.shared_scratch_bytes);
}

TEST_CASE("a batch of sessions stepped by shared launches equals each session stepping alone, bit for bit") {
  if (!have_gpu()) return;
  auto torso = make_torso_patient(96);
  // 40 pushes (more than one warp of sessions: the batched ChainMail scans them 32 at a
  // time), among them a grabbed element in the spine's bone (nothing moves) and one at
  // the volume's border (a clipped VOI); a second round on other pushes resets the first's
  std::vector<DeformContact> pushes;
  for (const RandomPush& p : random_pushes(*torso, 2 * 40, 11)) pushes.push_back(p.contact);
  REQUIRE(torso->bone.at(47, 67, 40));
  pushes[3] = voxel_contact({47, 67, 40}, {0.0, -4.0, 0.0});
  pushes[45] = voxel_contact({6, 48, 48}, {5.0, 1.0, 0.0});
  const int n = 40;
  // the default sweep cap, and one that stops most of them early (capped, not converged)
  for (int max_sweeps : {DeformSettings{}.max_sweeps, 7}) {
    DeformConfig cfg = preset_config(2);
    cfg.settings.voi_edge = 48;
    cfg.settings.backend = DeformBackendChoice::kCuda;
    cfg.settings.max_sweeps = max_sweeps;
    DeformEngine alone(torso, cfg);
    std::vector<std::unique_ptr<DeformEngine>> sessions;
    std::vector<DeformBackend*> backends;
    for (int s = 0; s < n; ++s) {
      sessions.push_back(std::make_unique<DeformEngine>(torso, cfg));
      backends.push_back(&sessions.back()->backend());
    }
    int capped = 0, in_bone = 0, clipped = 0;
    for (int round = 0; round < 2; ++round) {
      std::vector<DeformContact> k(pushes.begin() + round * n, pushes.begin() + round * n + n);
      const std::vector<DeformStats> st = step_batch(sessions, backends, k);
      for (int s = 0; s < n; ++s) {
        INFO("max_sweeps " << max_sweeps << ", round " << round << ", session " << s);
        const DeformStats a = alone.step(k[s]);
        check_same_step(st[s], a, *sessions[s], alone, n);
        capped += !a.chainmail.converged;
        in_bone += a.chainmail.grabbed_in_bone;
        clipped += a.chainmail.voi.count() < 48LL * 48 * 48;
      }
    }
    // the cases the batch must handle were there
    CHECK(in_bone >= 1);
    CHECK(clipped >= 1);
    if (max_sweeps == 7) CHECK(capped >= 10);
    // a refused contact leaves its session out; the others are stepped
    std::vector<DeformContact> k(pushes.begin(), pushes.begin() + 4);
    k[2].skin_point_mm = Vec3(-50.0, 0.0, 0.0);
    std::vector<DeformBackend*> four(backends.begin(), backends.begin() + 4);
    const std::vector<std::exception_ptr> errors = DeformBackend::begin_steps(four, k);
    CHECK(!errors[0]);
    REQUIRE(errors[2]);
    CHECK_THROWS_WITH(std::rethrow_exception(errors[2]), Catch::Contains("outside the patient grid"));
    CHECK_THROWS_WITH(four[2]->end_step(), Catch::Contains("end_step() without begin_step()"));
    for (int s : {0, 1, 3}) {
      const DeformStats b = four[s]->end_step();
      CHECK(b.batch == 3);
      const DeformStats a = alone.step(k[s]);
      CHECK(b.chainmail.moved == a.chainmail.moved);
      CHECK(four[s]->displacement() == alone.backend().displacement());
    }
  }
}

TEST_CASE("a batch of multigrid sessions equals each session stepping alone, bit for bit") {
  if (!have_gpu()) return;
  // multigrid sessions share a batch's reset, ChainMail (its start alone where skipped),
  // inversion and wait, their solves one launch each on the batch's stream: each must
  // equal a twin stepping the same contacts alone (the same unit responses kept between
  // rounds: a reuse, a warm start or a fresh solve as the twin has); among the sessions a
  // grabbed element in bone and a clipped VOI
  auto torso = make_torso_patient(96);
  const int n = 12;
  std::vector<DeformContact> pushes;
  for (const RandomPush& p : random_pushes(*torso, n, 5)) pushes.push_back(p.contact);
  REQUIRE(torso->bone.at(47, 67, 40));
  pushes[3] = voxel_contact({47, 67, 40}, {0.0, -4.0, 0.0});
  pushes[7] = voxel_contact({6, 48, 48}, {5.0, 1.0, 0.0});
  DeformConfig cfg = preset_config(2);
  cfg.settings.voi_edge = 48;
  cfg.settings.backend = DeformBackendChoice::kCuda;
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  cfg.settings.relax_warm_cycles = DeformSettings{}.relax_warm_cycles;
  // the grabbed element alone, a fingertip, and (-1) sessions alternating between the two
  // in one batch: each session's fingertip travels with its batch item
  const double radius = GENERATE(0.0, 3.0, -1.0);
  INFO("grab_radius_mm " << radius);
  cfg.voi_hold = false;  // a voxel deeper moves the VOI: a warm start
  std::vector<std::unique_ptr<DeformEngine>> sessions, twins;
  std::vector<DeformBackend*> backends;
  for (int s = 0; s < n; ++s) {
    DeformConfig own = cfg;
    own.settings.grab_radius_mm = radius >= 0 ? radius : (s % 2 ? 3.0 : 0.0);
    sessions.push_back(std::make_unique<DeformEngine>(torso, own));
    twins.push_back(std::make_unique<DeformEngine>(torso, own));
    backends.push_back(&sessions.back()->backend());
  }
  // the same contacts again (reuse), a voxel deeper (warm), then far off (fresh)
  const Vec3 deeper{0.0, 1.0, 0.0};
  int skipped = 0, solves = 0, warm = 0, reused = 0;
  for (int round = 0; round < 4; ++round) {
    std::vector<DeformContact> k = pushes;
    for (DeformContact& c : k) {
      if (round >= 2) c.tip_mm = c.tip_mm + deeper;
      // 9 voxels along k, towards the middle: the grabbed element too far for a warm start
      const Vec3 far{0.0, 0.0, c.skin_point_mm.z < 48 ? 9.0 : -9.0};
      if (round == 3) c = {c.skin_point_mm + far, c.tip_mm + far};
    }
    const std::vector<DeformStats> st = step_batch(sessions, backends, k);
    for (int s = 0; s < n; ++s) {
      INFO("round " << round << ", session " << s);
      const DeformStats a = twins[s]->step(k[s]);
      check_same_step(st[s], a, *sessions[s], *twins[s], n);
      CHECK(st[s].chainmail.skipped == a.chainmail.skipped);
      CHECK(st[s].relax_solves == a.relax_solves);
      CHECK(st[s].relax_warm == a.relax_warm);
      CHECK(st[s].relax_cycles == a.relax_cycles);
      skipped += a.chainmail.skipped;
      solves += a.relax_solves;
      warm += a.relax_warm;
      reused += a.relax_solves == 0;
    }
  }
  // the kinds of step the batch must handle were there
  CHECK(skipped >= n);
  CHECK(reused >= 1);
  CHECK(warm >= 1);
  CHECK(solves >= n);
}

TEST_CASE("a batch of sessions with the inversion's cell search equals each session alone, bit for bit") {
  if (!have_gpu()) return;
  // 16 sessions pressing the phantom's back 25 mm deep at 8 mm apart along the spine
  // (bench/press_load.h's pattern): each folds and sends hundreds of voxels to the
  // search, which the batched scatter, solve, pick and search kernels must answer as a
  // session stepping alone does. Prints the inversion's time per session both ways (a
  // figure to read, not a bound)
  const SearchPress sp = search_press();
  const PatientPtr& phantom = sp.phantom;
  const Vec3 X0 = sp.X;
  DeformConfig cfg = sp.cfg;
  cfg.settings.backend = DeformBackendChoice::kCuda;
  const int n = 16;
  std::vector<DeformContact> k;
  for (int s = 0; s < n; ++s) {
    const Vec3 X{X0.x, X0.y, X0.z + 8.0 * (s - n / 2)};
    k.push_back({X, X - Vec3{0, 25, 0}});
  }
  DeformEngine alone(phantom, cfg);
  std::vector<std::unique_ptr<DeformEngine>> sessions;
  std::vector<DeformBackend*> backends;
  for (int s = 0; s < n; ++s) {
    sessions.push_back(std::make_unique<DeformEngine>(phantom, cfg));
    backends.push_back(&sessions.back()->backend());
  }
  double batch_invert_ms = 0, alone_invert_ms = 0;
  for (int round = 0; round < 3; ++round) {
    const std::vector<DeformStats> st = step_batch(sessions, backends, k);
    for (int s = 0; s < n; ++s) {
      INFO("round " << round << ", session " << s);
      const DeformStats a = alone.step(k[s]);
      const DeformStats& b = st[s];
      check_same_step(b, a, *sessions[s], alone, n);
      if (round > 0) {
        batch_invert_ms += b.times.invert_ms;
        alone_invert_ms += a.times.invert_ms;
      }
    }
  }
  std::printf("batch of %d with the cell search: inversion %.3f ms a session's share in the batch, %.3f ms alone\n", n,
              batch_invert_ms / (2 * n), alone_invert_ms / (2 * n));
}

TEST_CASE("a batch of elastic sessions equals each session stepping alone", "[elastic]") {
  if (!have_gpu()) return;
  // 8 sessions pressing the phantom's back at 8 mm apart along the spine with the scenes'
  // elastic model (VOI 64, the fingertip of 5 mm, the inversion's cell search), half of
  // them with the unit press (haptics.force_model "elastic": each solve takes its own
  // settings in a batch): from rest 10 mm, a voxel deeper (warm), the same again (nothing
  // moved), then 12 mm along the spine (the VOI moved). They share the batch's reset,
  // inversion and wait, their solves one cooperative launch each on the batch's stream,
  // each on the whole device as alone. Solved to 1e-6 so that a differing stop cannot part
  // them (the dot products' block sums meet in another order from run to run: the fields
  // agree to rounding, 1e-6 of the largest component bounds it, as in
  // deform_gpu_elastic_test.cpp's sessions begun together)
  PhantomCt ct = make_phantom(340.0 / 255.0);
  const Press press = spinous_press(ct.geometry);
  const PatientPtr phantom = elastic_phantom(std::move(ct));
  DeformConfig cfg = phantom_elastic_config();
  cfg.settings.backend = DeformBackendChoice::kCuda;
  cfg.settings.invert_search = true;
  cfg.settings.elastic.tolerance = 1e-6;
  cfg.settings.elastic.max_iterations = 400;
  const int n = 8;
  const Vec3 X0 = press.contact.skin_point_mm, in = (press.contact.tip_mm - X0) / press.press_mm;
  const double h = phantom->grid.spacing_mm.x;
  std::vector<std::unique_ptr<DeformEngine>> sessions, twins;
  std::vector<DeformBackend*> backends;
  for (int s = 0; s < n; ++s) {
    DeformConfig own = cfg;
    own.elastic_stiffness = s % 2 == 1;
    sessions.push_back(std::make_unique<DeformEngine>(phantom, own));
    twins.push_back(std::make_unique<DeformEngine>(phantom, own));
    backends.push_back(&sessions.back()->backend());
  }
  int stiff = 0, warm = 0;
  for (int round = 0; round < 4; ++round) {
    std::vector<DeformContact> k;
    for (int s = 0; s < n; ++s) {
      const Vec3 X = X0 + Vec3{0, 0, 8.0 * (s - n / 2) + (round == 3 ? 12.0 : 0.0)};
      k.push_back({X, X + in * (10.0 + (round >= 1 ? h : 0.0))});
    }
    const std::vector<DeformStats> st = step_batch(sessions, backends, k);
    for (int s = 0; s < n; ++s) {
      INFO("round " << round << ", session " << s);
      const DeformStats a = twins[s]->step(k[s]);
      const DeformStats& b = st[s];
      CHECK(b.batch == n);
      CHECK(b.chainmail.voi == a.chainmail.voi);
      CHECK(b.elastic.contact == a.elastic.contact);
      CHECK(b.elastic.contact_nodes == a.elastic.contact_nodes);
      CHECK(b.elastic.warm == a.elastic.warm);
      CHECK(b.elastic.rounds == a.elastic.rounds);
      CHECK(b.elastic.converged);
      CHECK(b.elastic.inverted_cells == a.elastic.inverted_cells);
      const std::vector<Vec3f> ub = sessions[s]->backend().displacement(), ua = twins[s]->backend().displacement();
      CHECK(max_abs_diff(ub, ua) <= 1e-6f * max_abs(ua));
      CHECK(b.elastic.force_n.y == Approx(a.elastic.force_n.y).epsilon(1e-5));
      CHECK(b.elastic.stiffness_n_per_mm == Approx(a.elastic.stiffness_n_per_mm).epsilon(1e-5));
      // J from fields within 1e-6 of each other: each source moves by under 1e-4 voxel, J
      // by under 0.1 HU where the image's gradient is 1000 HU a voxel; only a fold's
      // search may pick another of two near-equal sources (a few voxels of a VOI)
      CHECK(b.invert_unresolved == a.invert_unresolved);
      const long long count = b.chainmail.voi.count();
      const float *jb = sessions[s]->deformed_brick(), *ja = twins[s]->deformed_brick();
      REQUIRE(jb);
      long long apart = 0;
      for (long long e = 0; e < count; ++e) apart += std::fabs(jb[e] - ja[e]) > 0.1f;
      CHECK(apart <= 16);
      stiff += b.elastic.stiffness_n_per_mm > 0;
      warm += b.elastic.warm;
    }
  }
  // the kinds of step the batch must handle were there: the unit press, warm starts
  CHECK(stiff >= n / 2);
  CHECK(warm >= n);
}
