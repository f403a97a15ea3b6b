// Multigrid relaxation (deform.relax_method "multigrid") on the CPU reference: it reaches
// the explicit scheme's fixed point, keeps held elements still and is isotropic.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <random>

#include "core/error.h"
#include "deform/cpu_backend.h"
#include "deform/held_blocks.h"
#include "deform/relax_multigrid.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

// ChainMail from `c`, then relaxation by `method` with `count` iterations or steps
struct Relaxed {
  ChainMailStats st;
  std::vector<Vec3f> before, after;
};

Relaxed relax_with(const PatientPtr& p, DeformConfig cfg, const DeformContact& c, RelaxMethod method, int count) {
  cfg.settings.relax_method = method;
  (method == RelaxMethod::kMultigrid ? cfg.settings.relax_cycles : cfg.settings.relax_iterations) = count;
  CpuDeformBackend b;
  b.bind(p, cfg);
  Relaxed r;
  r.st = b.chainmail(c);
  r.before = b.displacement();
  b.relax();
  r.after = b.displacement();
  return r;
}

double rms(const std::vector<Vec3f>& u) { return rms_distance(u, std::vector<Vec3f>(u.size(), Vec3f{0, 0, 0})); }

}  // namespace

TEST_CASE("multigrid reaches the fixed point of the explicit relaxation, with bone inside") {
  // a 20^3 VOI around a soft cube in a bone shell, pressed into the shell: the explicit
  // scheme's slowest mode decays by 1 - 0.15 * 6 * (1 - cos(pi/21)) ~ 0.99 per step, so
  // 4000 steps leave 1e-17 of it; both must then agree to float rounding
  auto patient = make_cube_patient(28, 14, 2);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 20;
  const DeformContact c = voxel_contact({14, 14, 8}, {0, 1, 3});
  const Relaxed ex = relax_with(patient, cfg, c, RelaxMethod::kExplicit, 4000);
  const Relaxed mg = relax_with(patient, cfg, c, RelaxMethod::kMultigrid, 30);
  REQUIRE(ex.st.moved > 0);
  REQUIRE(moved_bone_count(*patient, ex.st.voi, ex.before) == 0);
  const double d = rms_distance(mg.after, ex.after), scale = rms(ex.after);
  INFO("rms |u_mg - u_explicit| " << d << " voxel, field rms " << scale);
  // 1e-5 of the field: float sums of values up to 3 voxels over thousands of steps
  CHECK(d <= 1e-5 * scale + 1e-6);
  // the explicit 20 steps of the paper stop far from it
  CHECK(rms_distance(relax_with(patient, cfg, c, RelaxMethod::kExplicit, 20).after, ex.after) > 0.1 * scale);
}

TEST_CASE("multigrid on a VOI too thin to coarsen (2 voxels) and one too small to need the grid") {
  // 40 x 40 x 2: every element has a Dirichlet face 1 voxel away along k, so the explicit
  // scheme's slowest mode decays by 1 - 0.15 * 2 * (1 - cos(pi/3)) = 0.85 per step or
  // faster and 2000 steps reach rounding; the plan has one level (Gauss-Seidel and CG only)
  auto thin = make_patient({40, 40, 2}, [](int i, int, int) { return kSoftHu + 0.5f * i; });
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 40;
  const DeformContact c = voxel_contact({20, 20, 1}, {2, -1, 0.4});
  const Relaxed ex = relax_with(thin, cfg, c, RelaxMethod::kExplicit, 2000);
  CHECK(deform::multigrid_plan(ex.st.voi.size, ex.st.grabbed_vox - ex.st.voi.lo).levels == 1);
  const Relaxed mg = relax_with(thin, cfg, c, RelaxMethod::kMultigrid, 30);
  // 1e-5 of the field, as above
  CHECK(rms_distance(mg.after, ex.after) <= 1e-5 * rms(ex.after) + 1e-6);
  // an 8^3 VOI: every level fits in one GPU block
  auto small = make_soft_patient(8);
  cfg.settings.voi_edge = 8;
  const DeformContact s = voxel_contact({4, 4, 4}, {0, 1.5, 0});
  const Relaxed ex8 = relax_with(small, cfg, s, RelaxMethod::kExplicit, 2000);
  CHECK(rms_distance(relax_with(small, cfg, s, RelaxMethod::kMultigrid, 30).after, ex8.after) <= 1e-5 * rms(ex8.after) + 1e-6);
}

TEST_CASE("each multigrid step brings the residual of the steady state down") {
  // torso (bone spine and ribs) and a soft cube in bone, against the residual of
  // ChainMail's field; the factors measured per step lie between 0.1 and 0.6 (conjugate
  // gradients need not fall monotonically in the residual), 6 steps gave 10^4 and 12
  // steps 10^6-10^7, so 6 must give 100x and 12 10^4 (float rounding of the Laplacian of
  // fields up to 7 voxels lies near 1e-7 voxel, below that)
  struct Case {
    const char* name;
    PatientPtr p;
    int voi;
    DeformContact c;
  };
  const Case cases[] = {{"torso", make_torso_patient(64), 48, voxel_contact({32, 10, 32}, {2, 7, -3})},
                        {"cube in bone", make_cube_patient(48, 30, 3), 40, voxel_contact({24, 24, 10}, {0, 0, 5})}};
  for (const Case& k : cases) {
    DeformConfig cfg = preset_config(1);
    cfg.settings.voi_edge = k.voi;
    const Relaxed r0 = relax_with(k.p, cfg, k.c, RelaxMethod::kMultigrid, 0);
    const double res0 = laplacian_rms(*k.p, r0.st.voi, r0.st.grabbed_vox, r0.after);
    REQUIRE(r0.after == r0.before);  // zero steps change nothing
    double prev = res0;
    for (int n : {1, 2, 3, 6, 12}) {
      const Relaxed r = relax_with(k.p, cfg, k.c, RelaxMethod::kMultigrid, n);
      const double res = laplacian_rms(*k.p, r.st.voi, r.st.grabbed_vox, r.after);
      INFO(k.name << ": " << n << " steps, residual " << res << " (start " << res0 << ", factor " << res / prev << ")");
      std::printf("multigrid %s: %d steps, residual rms %.3g voxel (start %.3g)\n", k.name, n, res, res0);
      if (n == 1) CHECK(res < 0.5 * res0);
      if (n == 6) CHECK(res < 1e-2 * res0);
      if (n == 12) CHECK(res < 1e-4 * res0);
      // held elements keep their values exactly: bone stays at 0, the grabbed element at x
      CHECK(moved_bone_count(*k.p, r.st.voi, r.after) == 0);
      const Vec3i g = r.st.grabbed_vox - r.st.voi.lo;
      CHECK(r.after[r.st.voi.index(g.x, g.y, g.z)] == r.before[r.st.voi.index(g.x, g.y, g.z)]);
      prev = res;
    }
  }
}

TEST_CASE("multigrid keeps a zero field zero and moves nothing when X is in bone") {
  auto patient = make_cube_patient(40, 16, 3);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  // no displacement at the grabbed element: the steady state is zero, exactly
  const Relaxed z = relax_with(patient, cfg, voxel_contact({20, 20, 20}, {0, 0, 0}), RelaxMethod::kMultigrid, 6);
  for (const Vec3f& v : z.after) REQUIRE(v == Vec3f(0, 0, 0));
  // X in the bone shell: ChainMail moves nothing and neither does relaxation
  const Relaxed b = relax_with(patient, cfg, voxel_contact({11, 20, 20}, {-4, 2, 0}), RelaxMethod::kMultigrid, 6);
  REQUIRE(b.st.grabbed_in_bone);
  for (const Vec3f& v : b.after) REQUIRE(v == Vec3f(0, 0, 0));
}

TEST_CASE("multigrid relaxation of a press into a homogeneous block is isotropic, the paper's is not") {
  // a point press in the middle of a soft block: the steady state is the discrete
  // harmonic function of the grabbed element, |u| ~ 1/r. At 6 voxels its lattice and
  // VOI-face anisotropy is 1.5% (0.983 measured at VOI 32-64); ChainMail's diamond
  // survives 20 explicit steps there (0.845 measured)
  auto patient = make_soft_patient(56);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 48;
  const DeformContact c = voxel_contact({28, 28, 28}, {0, 0, 4});
  const Relaxed mg = relax_with(patient, cfg, c, RelaxMethod::kMultigrid, cfg.settings.relax_cycles);
  const Relaxed ex = relax_with(patient, cfg, c, RelaxMethod::kExplicit, 20);
  const Vec3i g = mg.st.grabbed_vox - mg.st.voi.lo;
  const double iso_mg = isotropy(mg.st.voi, mg.after, g, 6), iso_ex = isotropy(ex.st.voi, ex.after, g, 6);
  std::printf("isotropy at 6 voxels: multigrid %d steps %.3f, explicit 20 %.3f\n", cfg.settings.relax_cycles, iso_mg,
              iso_ex);
  CHECK(iso_mg >= 0.95);
  CHECK(iso_ex < 0.9);
}

TEST_CASE("multigrid reuses its unit response while the VOI and grabbed element stay, to the bit") {
  // a press on the torso whose tip moves within one voxel (the VOI, centred on the tip
  // voxel, stays), then a voxel on (the VOI moves), then back: the steady state is u = d G
  // (relax_multigrid.h), so a reused G must give the bits of a fresh solve
  auto torso = make_torso_patient(64);
  ReusePress press = reuse_press();
  // the grabbed element alone, and a fingertip (deform.grab_radius_mm) that moves with it
  press.cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);
  INFO("grab_radius_mm " << press.cfg.settings.grab_radius_mm);
  DeformConfig fresh_cfg = press.cfg;
  fresh_cfg.relax_reuse = false;
  CpuDeformBackend reuse, fresh;
  reuse.bind(torso, press.cfg);
  fresh.bind(torso, fresh_cfg);
  for (std::size_t s = 0; s < press.contacts.size(); ++s) {
    const DeformStats a = reuse.step(press.contacts[s]), b = fresh.step(press.contacts[s]);
    INFO("contact " << s);
    CHECK(a.relax_solves == press.solves[s]);
    CHECK(b.relax_solves == 1);
    REQUIRE(a.chainmail.voi.lo == b.chainmail.voi.lo);
    CHECK(reuse.displacement() == fresh.displacement());
  }
}

TEST_CASE("a tip entering another voxel starts the unit response from the last one and stays near the steady state") {
  // each step of the paths against the steady state of its own contact (30 steps from
  // zero: 1e-7 of the field or better, the first test case): every step must land within
  // 1% of it (issue 8's goal; see the prints and kMultigridNearMove), and closer than one
  // step more from zero; a warm step takes relax_warm_cycles steps where the grabbed
  // element moved at most kMultigridNearMove voxels, one more where it moved farther;
  // steps with relax_warm_cycles 0 are unchanged, bit for bit
  auto torso = make_torso_patient(64);
  DeformConfig cfg = reuse_press().cfg;
  cfg.settings.relax_warm_cycles = DeformSettings{}.relax_warm_cycles;
  REQUIRE(cfg.settings.relax_warm_cycles > 0);
  // the grabbed element alone, and a fingertip (deform.grab_radius_mm) that moves with it
  cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);
  INFO("grab_radius_mm " << cfg.settings.grab_radius_mm);
  DeformConfig steady_cfg = cfg, cold_cfg = cfg, off_cfg = cfg;
  steady_cfg.settings.relax_cycles = 30;
  steady_cfg.relax_reuse = false;
  cold_cfg.settings.relax_cycles = cfg.settings.relax_warm_cycles + 1;
  cold_cfg.relax_reuse = false;
  off_cfg.settings.relax_warm_cycles = 0;
  DeformConfig fresh_cfg = cfg;
  fresh_cfg.relax_reuse = false;
  for (const WarmPath& path : warm_paths()) {
    CpuDeformBackend warm, steady, cold, off, fresh;
    warm.bind(torso, cfg);
    steady.bind(torso, steady_cfg);
    cold.bind(torso, cold_cfg);
    off.bind(torso, off_cfg);
    fresh.bind(torso, fresh_cfg);
    for (std::size_t s = 0; s < path.contacts.size(); ++s) {
      const DeformContact& c = path.contacts[s];
      const DeformStats w = warm.step(c);
      steady.step(c);
      cold.step(c);
      const DeformStats o = off.step(c);
      fresh.step(c);
      const std::vector<Vec3f> ref = steady.displacement();
      const double scale = rms(ref), d_warm = rms_distance(warm.displacement(), ref),
                   d_cold = rms_distance(cold.displacement(), ref);
      std::printf("warm start, %s, fingertip %g mm, step %zu: %.4f%% from the steady state (%d steps from zero: %.4f%%)\n",
                  path.name, cfg.settings.grab_radius_mm, s, 100 * d_warm / scale, cfg.settings.relax_warm_cycles,
                  100 * d_cold / scale);
      INFO(path.name << ", step " << s);
      const bool warm_step = s > 0;
      // the grabbed element is the contact's X voxel (voxel_contact)
      bool far = false;
      if (warm_step)
        for (int a = 0; a < 3; ++a)
          far = far || std::abs(c.skin_point_mm[a] - path.contacts[s - 1].skin_point_mm[a]) > deform::kMultigridNearMove;
      CHECK(w.relax_solves == 1);
      CHECK(w.relax_warm == warm_step);
      CHECK(w.relax_cycles ==
            (warm_step ? cfg.settings.relax_warm_cycles + (far ? 1 : 0) : cfg.settings.relax_cycles));
      CHECK_FALSE(o.relax_warm);
      CHECK(off.displacement() == fresh.displacement());
      CHECK(d_warm <= 0.01 * scale);
      if (warm_step) CHECK(d_warm < d_cold);
    }
    // a held element moved by hand: three solves drop G, so the next step starts from zero
    REQUIRE(relax_with_bone_moved(warm, *torso, path.contacts.back()) >= 0);
    const DeformStats after = warm.step(path.contacts.front());
    CHECK_FALSE(after.relax_warm);
    CHECK(after.relax_cycles == cfg.settings.relax_cycles);
  }
}

TEST_CASE("multigrid solves each component when ChainMail moved a held element other than the grabbed one") {
  // soft tissue with three voxels far above the bone threshold outside the bone mask,
  // next to the grabbed element: ChainMail moves them, relaxation holds them where they
  // are (material weight 0), so u is not d G and each component needs its own solve; the
  // result must still be the explicit scheme's fixed point (20^3 VOI: 4000 steps reach
  // it, as in the first case above)
  const std::vector<Vec3i> hot = {{12, 12, 8}, {13, 12, 7}, {12, 13, 9}};
  auto patient = with_hot_voxels(make_soft_patient(24), hot, 3000.0f);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 20;
  const DeformContact c = voxel_contact({12, 12, 6}, {0, 1, 3});
  const Relaxed ex = relax_with(patient, cfg, c, RelaxMethod::kExplicit, 4000);
  const Relaxed mg = relax_with(patient, cfg, c, RelaxMethod::kMultigrid, 30);
  long long moved_hot = 0;
  for (const Vec3i& v : hot) {
    const Vec3i l = v - mg.st.voi.lo;
    const long long e = mg.st.voi.index(l.x, l.y, l.z);
    moved_hot += !(mg.before[e] == Vec3f{0, 0, 0});
    CHECK(mg.after[e] == mg.before[e]);  // held where ChainMail put it
  }
  REQUIRE(moved_hot > 0);
  // 1e-5 of the field, as in the first case
  CHECK(rms_distance(mg.after, ex.after) <= 1e-5 * rms(ex.after) + 1e-6);
  // and no reuse: the same contact again solves the three components again
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  CHECK(b.step(c).relax_solves == 3);
  CHECK(b.step(c).relax_solves == 3);
}

TEST_CASE("a fingertip grab moves the soft tissue within grab_radius_mm with the grabbed element: a dent of its size") {
  // a press into the middle of a soft block (1 mm voxels) with a 3 mm fingertip: every
  // soft element within 3 voxels of the grabbed one takes its displacement d exactly, the
  // rest is the steady state with that ball held (8 steps within 1e-3 of 30: each step
  // gains 3-10x), and 6 voxels out the field is several times the point grab's (a ball of
  // radius R held at 1 gives about R / r, one element about 0.25 / r: 0.5 against 0.04)
  auto patient = make_soft_patient(56);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 48;
  cfg.settings.grab_radius_mm = 3;
  const DeformContact c = voxel_contact({28, 28, 28}, {0, 0, 4});
  const Relaxed finger = relax_with(patient, cfg, c, RelaxMethod::kMultigrid, 8);
  const Relaxed steady = relax_with(patient, cfg, c, RelaxMethod::kMultigrid, 30);
  DeformConfig point_cfg = cfg;
  point_cfg.settings.grab_radius_mm = 0;
  const Relaxed point = relax_with(patient, point_cfg, c, RelaxMethod::kMultigrid, 8);
  const Voi& voi = finger.st.voi;
  const Vec3i g = finger.st.grabbed_vox - voi.lo;
  const Vec3f d = finger.after[voi.index(g.x, g.y, g.z)];
  REQUIRE(d.z == Approx(4.0f));
  int on_finger = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const int r2 = (i - g.x) * (i - g.x) + (j - g.y) * (j - g.y) + (k - g.z) * (k - g.z);
        if (r2 > 9) continue;
        ++on_finger;
        INFO("element " << i << ", " << j << ", " << k);
        CHECK(finger.after[voi.index(i, j, k)] == d);
      }
  CHECK(on_finger == 123);  // the lattice points within radius 3
  CHECK(rms_distance(finger.after, steady.after) <= 1e-3 * rms(steady.after));
  const Vec3i out = g + Vec3i{6, 0, 0};
  const float u6 = finger.after[voi.index(out.x, out.y, out.z)].z, p6 = point.after[voi.index(out.x, out.y, out.z)].z;
  std::printf("u_z 6 voxels beside a 4-voxel press: fingertip 3 mm %.3f, point grab %.3f voxel\n", u6, p6);
  CHECK(u6 > 4 * p6);
  CHECK(u6 < d.z);
  // bone on the fingertip stays held at rest: the torso press with a wide fingertip
  auto torso = make_torso_patient(64);
  DeformConfig tcfg = reuse_press().cfg;
  tcfg.settings.grab_radius_mm = 8;
  const Relaxed t = relax_with(torso, tcfg, reuse_press().contacts.front(), RelaxMethod::kMultigrid, 5);
  CHECK(moved_bone_count(*torso, t.st.voi, t.after) == 0);
}

TEST_CASE("a bad relax_cycles or grab_radius_mm is refused naming the field") {
  auto patient = make_soft_patient(16);
  DeformConfig cfg = preset_config(1);
  CpuDeformBackend b;
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  cfg.settings.relax_cycles = -1;
  CHECK_THROWS_WITH(b.bind(patient, cfg), Catch::Contains("deform.relax_cycles"));
  cfg.settings.relax_cycles = 4;
  // a fingertip only for multigrid (the explicit relaxation grabs one element), 0-20 mm
  cfg.settings.grab_radius_mm = 25;
  CHECK_THROWS_WITH(b.bind(patient, cfg), Catch::Contains("deform.grab_radius_mm"));
  cfg.settings.grab_radius_mm = 3;
  cfg.settings.relax_method = RelaxMethod::kExplicit;
  CHECK_THROWS_WITH(b.bind(patient, cfg), Catch::Contains("deform.grab_radius_mm") && Catch::Contains("multigrid"));
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  CHECK_NOTHROW(b.bind(patient, cfg));
  cfg.settings.grab_radius_mm = 0;
  CHECK_NOTHROW(b.bind(patient, cfg));
  // a step reports the cycles it ran, and no explicit iterations
  const DeformStats st = b.step(voxel_contact({8, 8, 8}, {0, 0, 2}));
  CHECK(st.relax_cycles == 4);
  CHECK(st.relax_iterations == 0);
}

TEST_CASE("the multigrid plan puts the grabbed element on a node of every level") {
  for (const Vec3i& g : {Vec3i{0, 0, 0}, Vec3i{31, 17, 6}, Vec3i{63, 40, 1}}) {
    const deform::MultigridPlan plan = deform::multigrid_plan({64, 52, 7}, g);
    CHECK(plan.levels >= 2);
    Vec3i at = g;
    long long coarse = 0;
    for (int l = 0; l + 1 < plan.levels; ++l) {
      for (int a = 0; a < 3; ++a) {
        REQUIRE((at[a] - plan.origin[l][a]) % 2 == 0);
        at[a] = (at[a] - plan.origin[l][a]) / 2;
        REQUIRE(at[a] < plan.size[l + 1][a]);
        // the last coarse node lies on a fine node
        REQUIRE(2 * (plan.size[l + 1][a] - 1) + plan.origin[l][a] <= plan.size[l][a] - 1);
      }
      CHECK(plan.offset[l + 1] == coarse);
      coarse += deform::node_count(plan.size[l + 1]);
    }
    CHECK(plan.coarse_count == coarse);
    const Vec3i& s = plan.size[plan.levels - 1];
    CHECK(std::min({s.x, s.y, s.z}) < 3);  // coarsened until an axis is too short
  }
}

TEST_CASE("coarse links crossing a held node or a face midway are cut, from both ends, on every level") {
  // random held masks (bone-like: a fifth of the nodes) on VOIs whose faces fall on or
  // between coarse nodes (odd and even sizes, both origins): on level 1 a link is cut
  // exactly where the fine node midway is held or beyond the fine faces; on every level a
  // link between two free nodes is cut from both ends (the operator stays symmetric) and
  // the diagonal is 6 plus the cuts
  std::mt19937 rng(8);
  for (const Vec3i& size : {Vec3i{20, 17, 9}, Vec3i{16, 16, 16}}) {
    for (const Vec3i& g : {Vec3i{6, 5, 4}, Vec3i{7, 8, 3}}) {
      const deform::MultigridPlan plan = deform::multigrid_plan(size, g);
      REQUIRE(plan.levels >= 3);
      std::vector<std::uint8_t> held(std::size_t(deform::node_count(size))), held_coarse(std::size_t(plan.coarse_count));
      std::vector<float> x(held.size()), f(held.size()), res(held.size()), cx(held_coarse.size()), cf(cx.size()),
          cres(cx.size());
      std::uniform_int_distribution<int> die(0, 4);
      for (auto& h : held) h = die(rng) == 0 ? deform::kMultigridHeldAtRest : deform::kMultigridFree;
      std::vector<deform::MultigridLevel> lv(std::size_t(plan.levels));
      lv[0] = deform::MultigridLevel{size, x.data(), f.data(), held.data(), res.data()};
      for (int l = 1; l < plan.levels; ++l) {
        const long long o = plan.offset[l];
        lv[l] = deform::MultigridLevel{plan.size[l], cx.data() + o, cf.data() + o, held_coarse.data() + o, cres.data() + o};
      }
      for (int l = 0; l + 1 < plan.levels; ++l) {
        const deform::MultigridLevel &F = lv[l], &C = lv[l + 1];
        const Vec3i o = plan.origin[l];
        for (int K = 0; K < C.n.z; ++K)
          for (int J = 0; J < C.n.y; ++J)
            for (int I = 0; I < C.n.x; ++I)
              deform::multigrid_coarse_node(C, I, J, K, 0.0f, deform::multigrid_coarse_byte(F, o, I, J, K));
        for (int K = 0; K < C.n.z; ++K)
          for (int J = 0; J < C.n.y; ++J)
            for (int I = 0; I < C.n.x; ++I) {
              const std::uint8_t h = C.held[C.index(I, J, K)];
              const Vec3i c{2 * I + o.x, 2 * J + o.y, 2 * K + o.z};
              REQUIRE(deform::multigrid_held(h) == deform::multigrid_held(F.held[F.index(c.x, c.y, c.z)]));
              if (deform::multigrid_held(h)) continue;
              const int cuts = deform::multigrid_cuts(h);
              int cut_links = 0;
              for (int q = 0; q < 6; ++q) {
                const bool cut = (cuts >> q) & 1;
                cut_links += cut;
                const Vec3i m = c + deform::neighbour_offset(q);
                if (l == 0) CHECK(cut == (!F.inside(m.x, m.y, m.z) || F.held[F.index(m.x, m.y, m.z)] != 0));
                const Vec3i n = Vec3i{I, J, K} + deform::neighbour_offset(q);
                if (!C.inside(n.x, n.y, n.z)) continue;
                const std::uint8_t hn = C.held[C.index(n.x, n.y, n.z)];
                if (deform::multigrid_held(hn)) continue;
                INFO("level " << l + 1 << " node " << I << " " << J << " " << K << " link " << q);
                CHECK(cut == (((deform::multigrid_cuts(hn) >> (q ^ 1)) & 1) != 0));
              }
              CHECK(deform::multigrid_diagonal(cuts) == float(6 + cut_links));
            }
      }
    }
  }
}

TEST_CASE("multigrid steps leave ChainMail out where nothing it moves is held, with the same fields to the bit") {
  // u = d G does not depend on ChainMail's field where every held element but the grabbed
  // one is at rest (relax_multigrid.h), which a VOI without elements held outside the bone
  // mask guarantees (deform::HeldBlocks): steps without ChainMail must give the
  // displacement, J and relaxation counts of steps with it, on every press and path of the
  // multigrid tests above (reused, warm and fresh solves)
  auto torso = make_torso_patient(64);
  const MultigridSteps steps = multigrid_steps();
  const std::vector<DeformContact>& contacts = steps.contacts;
  DeformConfig cfg = steps.cfg;
  REQUIRE(cfg.skip_chainmail);  // the default
  cfg.settings.grab_radius_mm = GENERATE(0.0, 3.0);  // the grabbed element alone, and a fingertip
  INFO("grab_radius_mm " << cfg.settings.grab_radius_mm);
  DeformConfig full_cfg = cfg;
  full_cfg.skip_chainmail = false;
  CpuDeformBackend skip, full;
  skip.bind(torso, cfg);
  full.bind(torso, full_cfg);
  for (std::size_t s = 0; s < contacts.size(); ++s) {
    INFO("contact " << s);
    CHECK(step_without_chainmail_differs(skip, full, contacts[s]) == "");
  }
}

TEST_CASE("ChainMail still runs where the VOI may hold an element outside bone, and only there") {
  // two voxels at 3000 HU outside the bone mask in one corner of a soft block: a VOI that
  // takes in their 8^3 block runs ChainMail (it may move them, and relaxation then holds
  // them where ChainMail put them: u is not d G), one away from it does not; the fields
  // are those of steps that always run ChainMail
  auto patient = with_hot_voxels(make_soft_patient(48), {{40, 40, 40}, {41, 40, 40}}, 3000.0f);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 16;
  cfg.settings.relax_method = RelaxMethod::kMultigrid;
  DeformConfig full_cfg = cfg;
  full_cfg.skip_chainmail = false;
  CpuDeformBackend skip, full;
  skip.bind(patient, cfg);
  full.bind(patient, full_cfg);
  struct Case {
    Vec3i grabbed;
    bool skipped;
  };
  for (const Case& c : {Case{{10, 10, 10}, true}, Case{{38, 38, 38}, false}, Case{{14, 12, 10}, true}}) {
    INFO("grabbed (" << c.grabbed.x << ", " << c.grabbed.y << ", " << c.grabbed.z << ")");
    const DeformContact k = voxel_contact(c.grabbed, {1, 2, -1.5});
    const DeformStats a = skip.step(k), b = full.step(k);
    CHECK(a.chainmail.skipped == c.skipped);
    CHECK_FALSE(b.chainmail.skipped);
    CHECK(skip.displacement() == full.displacement());
    CHECK(std::equal(skip.deformed_brick(), skip.deformed_brick() + a.chainmail.voi.count(), full.deformed_brick()));
  }
  // the explicit relaxation keeps ChainMail's field, so it never skips it
  DeformConfig explicit_cfg = cfg;
  explicit_cfg.settings.relax_method = RelaxMethod::kExplicit;
  CpuDeformBackend ex;
  ex.bind(patient, explicit_cfg);
  CHECK_FALSE(ex.step(voxel_contact({10, 10, 10}, {1, 2, -1.5})).chainmail.skipped);
}

TEST_CASE("HeldBlocks flags every element relaxation holds outside bone, and is shared") {
  // may_hold_outside_bone() must hold wherever the material weight is 0 outside the mask
  // (a scan of intensities across the threshold in steps of a hundredth of a width); the
  // map is conservative per 8^3 block: a VOI holding such an element is always flagged
  // (random VOIs against a brute-force scan)
  const float thr = float(kBoneThresholdHu), width = float(DeformSettings{}.material_width);
  for (int s = -2000; s <= 2000; ++s) {
    const float hu = thr + 0.01f * float(s) * width;
    if (deform::material_weight(hu, false, thr, width) == 0.0f) CHECK(deform::may_hold_outside_bone(hu, false, thr, width));
  }
  CHECK_FALSE(deform::may_hold_outside_bone(5000.0f, true, thr, width));  // bone: ChainMail never moves it
  const std::vector<Vec3i> hot = {{5, 30, 20}, {40, 8, 3}};
  auto patient = with_hot_voxels(make_torso_patient(48), hot, 2500.0f);
  const deform::HeldBlocks map(patient, thr, width);
  CHECK(map.flagged() == 2);
  std::mt19937 rng(5);
  int flagged = 0;
  for (int t = 0; t < 300; ++t) {
    deform::Voi voi;
    for (int a = 0; a < 3; ++a) {
      voi.lo[a] = int(rng() % 48);
      voi.size[a] = 1 + int(rng() % unsigned(48 - voi.lo[a]));
    }
    bool inside = false;
    for (const Vec3i& h : hot)
      inside = inside || (h.x >= voi.lo.x && h.x < voi.lo.x + voi.size.x && h.y >= voi.lo.y &&
                          h.y < voi.lo.y + voi.size.y && h.z >= voi.lo.z && h.z < voi.lo.z + voi.size.z);
    if (inside) CHECK(map.any_in(voi));
    flagged += map.any_in(voi);
  }
  CHECK(flagged < 300);  // and not every VOI
  const auto a = deform::HeldBlocks::of(patient, thr, width), b = deform::HeldBlocks::of(patient, thr, width);
  CHECK(a == b);
  CHECK(deform::HeldBlocks::of(patient, thr + 1, width) != a);
}
