// The CUDA backend's elastic model (deform.relax_method "elastic") against the CPU
// reference: slabs with bone, clipped and small VOIs, the lumbar phantom, predicted warm
// starts, and sessions begun together.
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

// ---- the elastic model (deform.relax_method "elastic"): cuda against the cpu reference ----
//
// Both backends run the same passes in the same order (relax_elastic.cpp, relax_elastic.cu)
// on the same floats, but the GPU sums in another order (its node gathers, the coarse
// levels' eight lanes a node, block sums and atomics of the dot products) and fuses
// multiply-adds. Each conjugate-gradient step's alpha and beta then agree to ~1e-6
// relative, the iterates drift apart by about that much a step, and the fields agree to
// rounding as long as both take the same steps. Two things can make them take different
// ones, and the tolerances below say how each is handled:
// - a solve whose residual at some step lies within rounding of the tolerance stops there on
//   one backend and a step later on the other: the fields then differ by one step's
//   correction, about the tolerance times the field (a V-cycle step cuts the residual 5-10
//   times). The cases with solves to 1e-6 make that negligible (strict bounds); the cases
//   with the scenes' 1e-3 bound it (looser bounds).
// - a node whose force along n, or whose penetration of the sphere, lies within rounding of
//   0 (a tie) leaves or joins the contact set on one backend only. Such a node carries
//   nearly nothing either way (no force, or it sits on the sphere already), so the counts
//   may differ by up to two nodes; the field and force bounds are then 10 times looser and
//   the case says so in its output.

namespace {

// an elastic scene's settings: the fingertip of 5 mm, VOI `edge`, solves to `tolerance`
// (relative residual; the scenes ship 1e-3) in at most 400 steps, up to 8 contact rounds,
// and the unit press for the stiffness when asked, solved to `tolerance` too (not to the
// scenes' 0.01 with the stiffness by reciprocity: stopped that early, the two backends'
// unit presses keep their rounding differences at the size of that tolerance's error, and
// k parted by up to 1e-3 on the H100 at 31323f9, above the strict bound; the case with
// reciprocity below bounds that setting)
DeformConfig elastic_config(int edge, double tolerance, bool stiffness) {
  DeformConfig cfg = preset_config(1);
  cfg.settings.relax_method = RelaxMethod::kElastic;
  cfg.settings.grab_radius_mm = 5;
  cfg.settings.voi_edge = edge;
  cfg.settings.elastic.tolerance = tolerance;
  cfg.settings.elastic.stiffness_tolerance = 0;
  cfg.settings.elastic.max_iterations = 400;
  cfg.settings.elastic.contact_rounds = 8;
  cfg.elastic_stiffness = stiffness;
  return cfg;
}

// how close the two backends' elastic steps must come (with identical contact sets)
struct ElasticTol {
  double field_rms;  // RMS |u_cuda - u_cpu| over RMS |u_cpu|
  double field_max;  // max |u_cuda - u_cpu| over max |u_cpu|
  double force;      // |F_cuda - F_cpu| / |F_cpu|
  double stiffness;  // the stiffness's likewise
};

// solves to 1e-6: rounding alone, drifting over 20-60 steps, bounded 10-100 times above
// the ~1e-6 relative that float sums of this size reach; where one side takes a CG step more
// (the residual crosses 1e-6 a step apart) the fields part by a few 1e-4 RMS (measured on the
// H200: 1.65e-4 at 11 against 10 steps, the forces 2e-6 apart), so 5e-4 RMS
constexpr ElasticTol kStrict{5e-4, 1e-3, 1e-4, 1e-4};
// the scenes' 1e-3: one step more or fewer on one side (see above), a few times the tolerance
constexpr ElasticTol kShipped{5e-3, 2e-2, 5e-3, 5e-3};
// the scenes' 1e-3 with the unit press stopped at 0.01 and the stiffness by reciprocity: k
// lies above the exact one by the unit press's energy error squared, which a unit CG step
// more or fewer on one side moves by about 1 % (the bench's defaults row lies 0.6-0.9 %
// above converged): 3 % for the stiffness
constexpr ElasticTol kShippedReciprocal{5e-3, 2e-2, 5e-3, 3e-2};

double rms(const std::vector<Vec3f>& u) {
  double s = 0;
  for (const Vec3f& v : u) s += double(v.x) * v.x + double(v.y) * v.y + double(v.z) * v.z;
  return u.empty() ? 0.0 : std::sqrt(s / double(u.size()));
}

double rms_diff(const std::vector<Vec3f>& a, const std::vector<Vec3f>& b) {
  double s = 0;
  for (std::size_t e = 0; e < a.size(); ++e) {
    const Vec3f d = a[e] - b[e];
    s += double(d.x) * d.x + double(d.y) * d.y + double(d.z) * d.z;
  }
  return a.empty() ? 0.0 : std::sqrt(s / double(a.size()));
}

// one step of both backends on contact `c`, compared; returns the cpu's run
deform::ElasticRun check_elastic_step(Pair& b, const DeformContact& c, const ElasticTol& tol, const std::string& what) {
  const DeformStats sc = b.cpu->step(c), sg = b.gpu->step(c);
  const deform::ElasticRun &ec = sc.elastic, &eg = sg.elastic;
  INFO(what);
  REQUIRE(sg.chainmail.voi == sc.chainmail.voi);
  CHECK(sg.batch == 1);
  // what the host works out alike on both: the press's depth and direction, the warm start
  CHECK(eg.depth_mm == ec.depth_mm);
  CHECK(eg.normal == ec.normal);
  CHECK(eg.warm == ec.warm);
  CHECK(eg.prediction == ec.prediction);
  REQUIRE(eg.contact == ec.contact);
  // a superposed step on one side only where a tie joined or left the set on the other
  const bool superposed_apart = eg.superposed != ec.superposed;
  const std::vector<Vec3f> uc = b.cpu->displacement(), ug = b.gpu->displacement();
  REQUIRE(uc.size() == ug.size());
  CHECK(moved_bone_count(b.gpu->patient(), sg.chainmail.voi, ug) == 0);
  CHECK(sg.invert_nonfinite == 0);
  if (!ec.contact) {
    // the tissue at rest on both, exactly
    CHECK(max_abs(ug) == 0.0f);
    CHECK(max_abs(uc) == 0.0f);
    CHECK(eg.force_n.z == 0.0);
    std::printf("elastic %s: no contact on either\n", what.c_str());
    return ec;
  }
  // the contact sets: equal, or apart by ties (see above)
  const int tie = std::abs(eg.contact_nodes - ec.contact_nodes);
  CHECK(tie <= 2);
  if (tie == 0) CHECK_FALSE(superposed_apart);
  const double loose = tie == 0 ? 1.0 : 10.0;
  const double field_rms = rms_diff(uc, ug) / rms(uc);
  const double field_max = max_abs_diff(uc, ug) / double(max_abs(uc));
  const double force = norm(eg.force_n - ec.force_n) / norm(ec.force_n);
  const double stiffness =
      ec.stiffness_n_per_mm > 0 ? std::fabs(eg.stiffness_n_per_mm - ec.stiffness_n_per_mm) / ec.stiffness_n_per_mm : 0.0;
  std::printf("elastic %s: %s%d / %d contact nodes%s, %d / %d CG steps in %d / %d rounds, %d / %d for the unit press, "
              "F %.6g / %.6g N (%.2e), k %.6g / %.6g N/mm (%.2e), u RMS %.2e max %.2e of the field, folded %lld / %lld\n",
              what.c_str(), ec.superposed ? (eg.superposed ? "superposed, " : "superposed on the cpu, ") : (eg.superposed ? "superposed on cuda, " : ""),
              ec.contact_nodes, eg.contact_nodes, tie ? " (a tie)" : "", ec.iterations, eg.iterations,
              ec.rounds, eg.rounds, ec.stiffness_iterations, eg.stiffness_iterations, norm(ec.force_n),
              norm(eg.force_n), force, ec.stiffness_n_per_mm, eg.stiffness_n_per_mm, stiffness, field_rms, field_max,
              ec.inverted_cells, eg.inverted_cells);
  CHECK(field_rms <= tol.field_rms * loose);
  CHECK(field_max <= tol.field_max * loose);
  CHECK(force <= tol.force * loose);
  CHECK(stiffness <= tol.stiffness * loose);
  CHECK(eg.converged == ec.converged);
  // the same solves to within a step each (a residual at the threshold), and a round more
  // or fewer where a tie changed the set late
  CHECK(std::abs(eg.rounds - ec.rounds) <= (tie == 0 ? 0 : 1));
  CHECK(std::abs(eg.iterations - ec.iterations) <= 2 * std::max(ec.rounds, eg.rounds));
  CHECK(std::abs(eg.stiffness_iterations - ec.stiffness_iterations) <= 2);
  if (tie == 0) CHECK(eg.contact_settled == ec.contact_settled);
  // folded cells: those whose smallest det(I + grad u) lies within the fields' difference of
  // 0 may count on one side only (the phantom's 10 mm press folds about 70 cells)
  CHECK(std::abs(eg.inverted_cells - ec.inverted_cells) <= 2 + ec.inverted_cells / 20);
  return ec;
}

// a box of `size` 1 mm voxels: soft tissue (kSoftHu) below the plane z = skin_z mm, air
// above, no bone, with the body mask and B (as synthetic_patient.h makes them)
PatientPtr flat_slab(const Vec3i& size, double skin_z) {
  auto q = std::make_shared<Patient>(*make_patient(size, [&](int, int, int k) { return k < skin_z ? kSoftHu : kAirHu; }));
  q->body = Volume<std::uint8_t>(q->grid, 0);
  q->dist_skin_mm = Volume<float>(q->grid, 0.0f);
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j < size.y; ++j)
      for (int i = 0; i < size.x; ++i)
        if (k < skin_z) {
          q->body.at(i, j, k) = 1;
          q->dist_skin_mm.at(i, j, k) = float(skin_z - k + 0.5);
        }
  return q;
}

}  // namespace

TEST_CASE("gpu elastic steps equal the cpu's on a slab with bone: from rest, warm, the VOI moved, released, reset", "[elastic]") {
  if (!have_gpu()) return;
  // the 60 mm slab over a bone block 14 mm under the skin (synthetic_patient.h), VOI 32
  // (levels 32, 17, 9 on the grid, 5 and 3 in block 0), solves to 1e-6, with the unit press
  auto slab = slab_patient();
  Pair b(slab, elastic_config(32, 1e-6, true));
  const Vec3 skin{30, 30, kSlabSkinZ};
  const Vec3 down{0, 0, -1};
  check_elastic_step(b, {skin, skin + down * 4.0}, kStrict, "slab from rest, 4 mm");
  const deform::ElasticRun warm = check_elastic_step(b, {skin, skin + down * 5.0}, kStrict, "slab a voxel deeper");
  CHECK(warm.warm);
  // 6 voxels aside: beyond the VOI's hold (32 / 8 = 4 voxels), so both set a new VOI up
  // and carry the field and contact set over
  const Vec3 aside{6, 0, 0};
  check_elastic_step(b, {skin + aside, skin + aside + down * 5.0}, kStrict, "slab, the VOI moved 6 voxels");
  // released: the tip above the skin presses nothing
  check_elastic_step(b, {skin + aside, skin + aside - down * 3.0}, kStrict, "slab released");
  check_elastic_step(b, {skin, skin + down * 3.0}, kStrict, "slab pressed again after the release");
  // reset() forgets the field: the next press starts from rest on both
  b.cpu->reset();
  b.gpu->reset();
  const deform::ElasticRun fresh = check_elastic_step(b, {skin, skin + down * 4.0}, kStrict, "slab after reset");
  CHECK_FALSE(fresh.warm);
}

TEST_CASE("gpu elastic steps equal the cpu's on clipped and small VOIs, through every level layout", "[elastic]") {
  if (!have_gpu()) return;
  auto slab = slab_patient();
  const Vec3 down{0, 0, -1};
  // sections, so that a slow tool (racecheck) can take one at a time (-c "name")
  // a press 3 voxels from the volume's corner: the VOI clipped to 19 x 19 x 32 (odd and
  // even sizes: coarse nodes beyond the fine grid)
  SECTION("VOI clipped at the border") {
    Pair b(slab, elastic_config(32, 1e-6, true));
    const Vec3 skin{3, 3, kSlabSkinZ};
    check_elastic_step(b, {skin, skin + down * 3.0}, kStrict, "VOI clipped at the border");
    check_elastic_step(b, {skin, skin + down * 4.0}, kStrict, "VOI clipped at the border, a voxel deeper");
  }
  // VOI edges whose plans run level 0 alone (4: too small to coarsen) and one or two coarse
  // levels (8: 8, 5; 16: 16, 9, 5), all on the grid; with PALPSIM_ELASTIC_BLOCK_NODES=1000
  // (scripts/gpu-check.sh) 8 and 16 put their coarse levels in block 0 and the VOI clipped
  // at the border splits them (10 x 10 x 17 on the grid, 6 x 6 x 9 and 4 x 4 x 5 in block 0);
  // by default only a plan ending on 4^3 nodes (a VOI of 48: 48, 25, 13, 7, 4) has a level
  // there
  for (int edge : {4, 8, 16})
    DYNAMIC_SECTION("VOI " << edge) {
      Pair b(slab, elastic_config(edge, 1e-6, true));
      const Vec3 skin{30, 30, kSlabSkinZ};
      check_elastic_step(b, {skin, skin + down * 2.0}, kStrict, "VOI " + std::to_string(edge));
      check_elastic_step(b, {skin, skin + down * 3.0}, kStrict, "VOI " + std::to_string(edge) + ", a voxel deeper");
    }
  // a flat VOI (64 x 64 x 6, the volume's height): its coarsest level (33 x 33 x 4) too large
  // for block 0, smoothed on the grid
  SECTION("flat VOI") {
    auto flat = flat_slab({64, 64, 6}, 3.5);
    Pair b(flat, elastic_config(64, 1e-6, false));
    const Vec3 skin{32, 32, 3.5};
    check_elastic_step(b, {skin, skin + down * 1.5}, kStrict, "flat VOI");
  }
}

TEST_CASE("gpu elastic steps equal the cpu's with other V-cycle degrees", "[elastic]") {
  if (!have_gpu()) return;
  auto slab = slab_patient();
  const Vec3 down{0, 0, -1};
  // other V-cycle degrees (finest, coarse, coarsest; even and odd, so that the smoothings
  // end in the other buffer), on VOI 64 (the whole 60-voxel slab: level 1 of 31^3 nodes in
  // tiles, far air on its faces), 32 (every level on the grid) and 16 (block 0's levels)
  for (const int edge : {64, 32, 16})
    DYNAMIC_SECTION("VOI " << edge) {
      for (const deform::ElasticDegrees& deg : {deform::ElasticDegrees{4, 5, 3}, deform::ElasticDegrees{2, 2, 12}}) {
        DeformConfig cfg = elastic_config(edge, 1e-6, true);
        cfg.settings.elastic.smooth_degree = deg.fine;
        cfg.settings.elastic.coarse_smooth_degree = deg.coarse;
        cfg.settings.elastic.coarsest_degree = deg.coarsest;
        Pair b(slab, cfg);
        const Vec3 skin{30, 30, kSlabSkinZ};
        const std::string what = "VOI " + std::to_string(edge) + ", degrees " + std::to_string(deg.fine) + ", " +
                                 std::to_string(deg.coarse) + ", " + std::to_string(deg.coarsest);
        check_elastic_step(b, {skin, skin + down * 2.0}, kStrict, what);
        check_elastic_step(b, {skin, skin + down * 3.0}, kStrict, what + ", a voxel deeper");
      }
    }
}

TEST_CASE("gpu elastic steps equal the cpu's on the lumbar phantom as the scenes ship them", "[elastic]") {
  if (!have_gpu()) return;
  // the accuracy bench's press over L3 (X 1 mm under the back skin, x 10 mm anterior),
  // VOI 64, the fingertip of 5 mm, the scenes' solver settings, with the unit press
  PhantomCt ct = make_phantom(340.0 / 255.0);
  const Press press = spinous_press(ct.geometry);
  const PatientPtr phantom = elastic_phantom(std::move(ct));
  DeformConfig cfg = phantom_elastic_config();
  cfg.elastic_stiffness = true;
  Pair b(phantom, cfg);
  const Vec3 X = press.contact.skin_point_mm, in = (press.contact.tip_mm - X) / press.press_mm;
  const double h = phantom->grid.spacing_mm.x;
  check_elastic_step(b, {X, X + in * 4.0}, kShipped, "phantom from rest, 4 mm");
  check_elastic_step(b, {X, X + in * (4.0 + h)}, kShipped, "phantom a voxel deeper");
  check_elastic_step(b, press.contact, kShipped, "phantom at 10 mm");
  // 12 mm along the spine: beyond the VOI's hold (64 / 8 voxels, 10.7 mm)
  const Vec3 along{0, 0, 12};
  check_elastic_step(b, {X + along, press.contact.tip_mm + along}, kShipped, "phantom, the VOI moved 12 mm");
  check_elastic_step(b, {X + along, X + along - in * 3.0}, kShipped, "phantom released");
}

TEST_CASE("gpu elastic steps equal the cpu's with the warm start predicted and the force by reciprocity", "[elastic]") {
  if (!have_gpu()) return;
  // the phantom's press over L3 as above, the tip moving a voxel in and out along n, then
  // sliding along the spine: with
  // the unit press (predicted from it, the unit press to 0.01 and the force by reciprocity)
  // and without (predicted by the depths' ratio)
  PhantomCt ct = make_phantom(340.0 / 255.0);
  const Press press = spinous_press(ct.geometry);
  const PatientPtr phantom = elastic_phantom(std::move(ct));
  const Vec3 X = press.contact.skin_point_mm, in = (press.contact.tip_mm - X) / press.press_mm;
  const double h = phantom->grid.spacing_mm.x;
  for (const bool stiffness : {true, false}) {
    DeformConfig cfg = phantom_elastic_config();
    cfg.settings.elastic.predict = true;
    cfg.settings.elastic.stiffness_tolerance = stiffness ? 0.01 : 0.0;
    cfg.elastic_stiffness = stiffness;
    Pair b(phantom, cfg);
    const std::string with = stiffness ? "with the unit press" : "without the unit press";
    const ElasticTol tol = stiffness ? kShippedReciprocal : kShipped;
    const deform::ElasticRun first = check_elastic_step(b, {X, X + in * 6.0}, tol, "predicted, from rest, " + with);
    CHECK(first.prediction == deform::ElasticPredict::kNone);
    for (int s = 1; s <= 4; ++s) {
      const deform::ElasticRun r = check_elastic_step(b, {X, X + in * (6.0 + (s & 1) * h)}, tol,
                                                      "predicted, step " + std::to_string(s) + ", " + with);
      CHECK(r.prediction == (stiffness ? deform::ElasticPredict::kUnit : deform::ElasticPredict::kScale));
    }
    // sliding half a voxel a step along the spine (the bench's slide): the last field and
    // unit press moved with the tip across n (deform::elastic_shifted)
    for (int s = 1; s <= 3; ++s) {
      const Vec3 at = X + Vec3{0, 0, 0.5 * h * s};
      const deform::ElasticRun r =
          check_elastic_step(b, {at, at + in * 6.0}, tol, "sliding, step " + std::to_string(s) + ", " + with);
      CHECK(r.warm);
    }
    // then 0.05 mm deeper a step (a tip at 50 mm/s, 1 kHz) along n from the last slide:
    // with the unit press most of these superpose (deform::elastic_superposes) on both
    int superposed = 0;
    const Vec3 at = X + Vec3{0, 0, 1.5 * h};
    for (int s = 1; s <= 12; ++s) {
      const deform::ElasticRun r = check_elastic_step(b, {at, at + in * (6.0 + 0.05 * s)}, tol,
                                                      "0.05 mm deeper, step " + std::to_string(s) + ", " + with);
      superposed += r.superposed;
    }
    // and back out 0.05 mm a step: the finger pulls the set's outer nodes off as it goes
    // (elastic_predicted_pull), so steps the host lets superpose find the set changed at
    // their start and solve, the others superpose
    int superposed_out = 0;
    for (int s = 11; s >= 0; --s) {
      const deform::ElasticRun r = check_elastic_step(b, {at, at + in * (6.0 + 0.05 * s)}, tol,
                                                      "0.05 mm back, step " + std::to_string(s) + ", " + with);
      superposed_out += r.superposed;
    }
    if (stiffness) {
      CHECK(superposed >= 6);
      CHECK(superposed_out >= 1);
    } else {
      CHECK(superposed == 0);
      CHECK(superposed_out == 0);
    }
  }
}

TEST_CASE("gpu elastic sessions begun together or batched equal sessions alone; their own memory", "[elastic]") {
  if (!have_gpu()) return;
  // four sessions pressing the slab at four points, begun together with a share of 4, or
  // batched (begin_steps; an elastic step keeps the whole device either way, the solves
  // taking turns on the shared scratch), against twins stepping alone. Not to the bit: another number of blocks sums the dot products in
  // another order, which changes a float step length with a probability near 1e-8; 1e-6 of
  // the field bounds what such a change would leave after a solve to 1e-6
  auto slab = slab_patient();
  DeformConfig cfg = elastic_config(32, 1e-6, true);
  cfg.settings.backend = DeformBackendChoice::kCuda;
  std::vector<DeformContact> k;
  for (const Vec3& at : {Vec3{24, 24, 0}, Vec3{36, 24, 0}, Vec3{24, 36, 0}, Vec3{36, 36, 0}}) {
    const Vec3 skin{at.x, at.y, kSlabSkinZ};
    k.push_back({skin, skin - Vec3{0, 0, 4}});
  }
  std::vector<std::unique_ptr<DeformEngine>> sessions, twins;
  std::vector<DeformBackend*> backends;
  for (int s = 0; s < 4; ++s) {
    sessions.push_back(std::make_unique<DeformEngine>(slab, cfg));
    twins.push_back(std::make_unique<DeformEngine>(slab, cfg));
    backends.push_back(&sessions.back()->backend());
  }
  const Vec3 deeper{0, 0, -1};
  int round = 0;
  for (int share : {4, 1, 4}) {
    std::vector<DeformContact> now;
    for (const DeformContact& c : k) now.push_back({c.skin_point_mm, c.tip_mm + deeper * double(round)});
    std::vector<DeformStats> st;
    for (auto& e : sessions) e->backend().set_gpu_share(share);
    if (share == 1) {
      // begin_steps: one batch (its reset, inversion and wait shared; the solves one launch
      // each on the batch's stream)
      st = step_batch(sessions, backends, now);
    } else {
      for (int s = 0; s < 4; ++s) sessions[s]->begin_step(now[s]);
      for (int s = 0; s < 4; ++s) st.push_back(sessions[s]->end_step());
    }
    for (int s = 0; s < 4; ++s) {
      const DeformStats a = twins[s]->step(now[s]);
      INFO("share " << share << ", session " << s);
      CHECK(st[s].batch == (share == 1 ? 4 : 1));
      CHECK(st[s].elastic.contact_nodes == a.elastic.contact_nodes);
      CHECK(st[s].elastic.warm == a.elastic.warm);
      const std::vector<Vec3f> us = sessions[s]->backend().displacement(), ua = twins[s]->backend().displacement();
      CHECK(max_abs_diff(us, ua) <= 1e-6f * max_abs(ua));
      CHECK(st[s].elastic.force_n.z == Approx(a.elastic.force_n.z).epsilon(1e-6));
    }
    ++round;
  }
  // the session's own memory: ChainMail's fields and stamps, J and its pinned copy, and the
  // elastic field, unit press, the last reactions of both at the contact nodes (two floats a
  // node of level 0), flags and moduli of every level (level 0's 32^3 and the
  // coarse levels 17^3, 9^3, 5^3), every level's lmax, level 0's tile list (count,
  // then list and marks of its 1 x 8 x 8 tiles of 32 x 4 x 4 nodes); the shared scratch
  // and the body copy counted apart
  const std::size_t n = 32 * 32 * 32, total = n + 17 * 17 * 17 + 9 * 9 * 9 + 5 * 5 * 5;
  const std::size_t elastic_own =
      8 * n * sizeof(float) + total * (1 + sizeof(float)) + 16 * sizeof(float) + (1 + 2 * 64) * sizeof(int);
  const DeformMemory m = twins[0]->backend().memory();
  CHECK(m.relax_bytes == elastic_own);
  CHECK(m.shared_scratch_bytes > 0);
  // the body copy beside the intensity and bone copy: 5 bytes a voxel each
  CHECK(m.shared_patient_bytes == 2 * slab->grid.count() * 5);
  // a session that stepped with a share of 4 holds no scratch of its own either
  CHECK(sessions[0]->backend().memory().relax_bytes == elastic_own);
  std::printf("elastic VOI 32 session memory: own %.2f MB (chainmail %.2f, relax %.2f, invert %.2f), shared scratch "
              "%.2f MB, shared patient %.2f MB\n",
              m.total() / 1048576.0, m.chainmail_bytes / 1048576.0, m.relax_bytes / 1048576.0,
              m.invert_bytes / 1048576.0, m.shared_scratch_bytes / 1048576.0, m.shared_patient_bytes / 1048576.0);
}
