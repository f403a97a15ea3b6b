// Untangling (issue 8, section 4): after relaxation the deformation must be invertible
// (det(I + grad u) > 0 in every soft cell), so that the inversion resolves every voxel,
// and the change it makes must stay next to the folds. The measuring run behind the
// figures of server/deform/README.md is the hidden test "[.measure]":
//   palpsim-test-deform-untangle "[.measure]"
#include <catch2/catch.hpp>

#include <algorithm>
#include <climits>
#include <cstdint>
#include <cmath>
#include <cstdio>
#include <vector>

#include "deform/cpu_backend.h"
#include "deform/deform_math.h"
#include "deform/invert_scatter.h"
#include "prep/phantom.h"
#include "support/deform_fixtures.h"
#include "support/phantom_press.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

// what one push leaves on the cpu backend, with or without untangling
struct Result {
  DeformStats st;
  std::vector<Vec3f> u;  // the field the inversion read
  std::vector<float> j;  // J on the VOI
  double min_det = 0;    // min_jacobian_det of u
};

Result run(const PatientPtr& p, DeformConfig cfg, const DeformContact& c, bool untangle, int invert_iterations) {
  cfg.settings.untangle = untangle;
  cfg.settings.invert_iterations = invert_iterations;
  CpuDeformBackend b;
  b.bind(p, cfg);
  Result r;
  r.st = b.step(c);
  r.u = b.displacement();
  const float* j = b.deformed_brick();
  r.j.assign(j, j + r.st.chainmail.voi.count());
  r.min_det = min_jacobian_det(*p, r.st.chainmail.voi, r.u);
  return r;
}

// root mean square and maximum of |a - b| over the field (voxel)
std::pair<double, double> field_change(const std::vector<Vec3f>& a, const std::vector<Vec3f>& b) {
  double sum = 0, worst = 0;
  for (std::size_t e = 0; e < a.size(); ++e) {
    const Vec3f d = a[e] - b[e];
    const double n2 = double(d.x) * d.x + double(d.y) * d.y + double(d.z) * d.z;
    sum += n2;
    worst = std::max(worst, std::sqrt(n2));
  }
  return {std::sqrt(sum / double(std::max<std::size_t>(a.size(), 1))), worst};
}

// root mean square of J - J_ref (HU)
double rms(const std::vector<float>& a, const std::vector<float>& b) {
  double sum = 0;
  for (std::size_t e = 0; e < a.size(); ++e) sum += (double(a[e]) - b[e]) * (double(a[e]) - b[e]);
  return std::sqrt(sum / double(std::max<std::size_t>(a.size(), 1)));
}

// the phantom of `palpsim-bench deform` (340 mm over 256 voxels), built once
const PatientPtr& phantom() {
  static const PatientPtr p = patient_from_intensity(make_phantom(340.0 / 255.0).hu, "phantom");
  return p;
}

// the Table 1 configuration: preset p1, VOI 64, relaxation 20
DeformConfig table1_config() {
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 64;
  cfg.settings.relax_iterations = 20;
  return cfg;
}

// one line of the measuring run: relaxation alone against relaxation and untangling,
// each against its own 64-iteration inversion
void measure(const char* name, const PatientPtr& p, const DeformConfig& cfg, const DeformContact& c) {
  const Result a = run(p, cfg, c, false, 8), b = run(p, cfg, c, true, 8);
  const Result a64 = run(p, cfg, c, false, 64), b64 = run(p, cfg, c, true, 64);
  const auto [du_rms, du_max] = field_change(b.u, a.u);
  std::printf("%-10s VOI %3lld^3 | off: det %7.3f unres %4lld res %6.3f J8-J64 %6.2f HU | on: folded %4lld -> %lld "
              "rounds %d sweeps %2d moved %4lld det %6.3f unres %lld res %6.4f J8-J64 %6.2f HU | du rms %.4f max %.3f "
              "vox, J64 on-off %.2f HU, %.3f ms\n",
              name, (long long)std::cbrt(double(a.st.chainmail.voi.count())), a.min_det, a.st.invert_unresolved,
              a.st.invert_residual_vox, rms(a.j, a64.j), b.st.untangle.folded_before, b.st.untangle.folded_after,
              b.st.untangle.rounds, b.st.untangle.sweeps, b.st.untangle.moved, b.min_det, b.st.invert_unresolved,
              b.st.invert_residual_vox, rms(b.j, b64.j), du_rms, du_max, rms(b64.j, a64.j), b.st.times.untangle_ms);
}

// VOI voxels Newton alone (invert_point, without the inversion's cell search) leaves
// unresolved (residual above kInvertResolvedVox): where it stalls next to folds, bone and
// the VOI's faces
long long newton_unresolved(const Voi& voi, const std::vector<Vec3f>& u, int iterations) {
  auto load_u = [&](int i, int j, int k) { return voi.contains(i, j, k) ? u[voi.index(i, j, k)] : Vec3f{0, 0, 0}; };
  long long n = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        float r = 0;
        deform::invert_point(load_u, Vec3f(float(i), float(j), float(k)), iterations, r);
        n += r > deform::kInvertResolvedVox;
      }
  return n;
}

// J's RMS error against 64 inversion iterations must not grow with more iterations; the
// iteration counts and errors go to the message
void check_error_falls(const PatientPtr& p, const DeformConfig& cfg, const DeformContact& c, bool untangle) {
  const Result ref = run(p, cfg, c, untangle, 64);
  double prev = 1e30;
  for (int it : {0, 1, 2, 4, 8, 16, 32}) {
    const double err = rms(run(p, cfg, c, untangle, it).j, ref.j);
    INFO("untangle " << untangle << ", inversion " << it << " iterations: J's RMS error " << err << " HU, previous "
                     << prev);
    CHECK(err <= prev);
    prev = err;
  }
}

}  // namespace

TEST_CASE("untangling leaves det(I + grad u) > 0 in every soft cell of 40 random pushes") {
  const PatientPtr torso = make_torso_patient(48);
  long long folded_before = 0, newton_left_off = 0, newton_left_on = 0;
  for (const RandomPush& push : random_pushes(*torso, 40, 8)) {
    const Result off = run(torso, push.config, push.contact, false, 8), on = run(torso, push.config, push.contact, true, 8);
    const Voi& voi = on.st.chainmail.voi;
    INFO("X " << push.contact.skin_point_mm.x << "," << push.contact.skin_point_mm.y << ","
              << push.contact.skin_point_mm.z << " d " << on.st.chainmail.grabbed_u_vox.x << ","
              << on.st.chainmail.grabbed_u_vox.y << "," << on.st.chainmail.grabbed_u_vox.z << ": folded "
              << on.st.untangle.folded_before << " -> " << on.st.untangle.folded_after << ", min det " << on.min_det
              << ", unresolved " << on.st.invert_unresolved << " (residual " << on.st.invert_residual_vox
              << "), relaxation alone " << off.st.invert_unresolved << " (residual " << off.st.invert_residual_vox << ")");
    CHECK(on.st.untangle.folded_after == 0);
    CHECK(on.min_det > 0);
    // every voxel finds its source, with untangling and without (the cell search stops at
    // kInvertSearchVox = 0.01 voxel; 0.05 is issue 8's goal, measured at most 0.0098)
    CHECK(on.st.invert_unresolved == 0);
    CHECK(on.st.invert_residual_vox < 0.05);
    CHECK(off.st.invert_unresolved == 0);
    CHECK(off.st.invert_residual_vox < 0.05);
    folded_before += on.st.untangle.folded_before;
    newton_left_off += newton_unresolved(voi, off.u, 8);
    newton_left_on += newton_unresolved(voi, on.u, 8);
  }
  // relaxation alone folds, and Newton alone leaves voxels there (measured: 9 of 40 pushes
  // with untangling, 1-11 voxels each, next to bone or a VOI face): the search is what
  // resolves them, and the checks above mean something
  INFO("Newton alone leaves " << newton_left_off << " voxels unresolved without untangling, " << newton_left_on
                              << " with");
  CHECK(folded_before > 40);
  CHECK(newton_left_off > 0);
  CHECK(newton_left_on > 0);
}

TEST_CASE("J's error falls with inversion iterations on random pushes, with untangling and without") {
  // the cell search starts from y - u(y), not from Newton's last point, so a voxel that
  // Newton leaves at 64 iterations gets the same source at fewer; the rest is Newton's
  // own convergence (the first 10 of the 40 pushes: a second each)
  const PatientPtr torso = make_torso_patient(48);
  const auto pushes = random_pushes(*torso, 10, 8);
  for (const RandomPush& push : pushes)
    for (bool untangle : {true, false}) check_error_falls(torso, push.config, push.contact, untangle);
}

TEST_CASE("untangling the Table 1 press: no fold, every voxel resolved, J's error falls with iterations") {
  const PatientPtr& p = phantom();
  const DeformContact c = table1_press(*p);
  const DeformConfig cfg = table1_config();
  const Result off = run(p, cfg, c, false, 8), on = run(p, cfg, c, true, 8);
  const Result ref = run(p, cfg, c, true, 64);
  INFO("folded " << on.st.untangle.folded_before << " -> " << on.st.untangle.folded_after << ", min det " << on.min_det
                 << ", unresolved " << on.st.invert_unresolved << ", residual " << on.st.invert_residual_vox);
  // relaxation alone folds here (measured: min det -1.3, one voxel unresolved at 0.144 voxel)
  CHECK(off.min_det < 0);
  CHECK(on.st.untangle.folded_before > 0);
  CHECK(on.st.untangle.folded_after == 0);
  CHECK(on.min_det > 0);
  CHECK(on.st.invert_unresolved == 0);
  CHECK(on.st.invert_residual_vox < 0.05);
  // the change stays next to the grabbed element: measured RMS 0.052 voxel over the
  // 64^3 VOI (1373 elements moved, 0.5 %, the most 4.1 voxel, along the press), so 0.1
  // voxel and 1 % of the VOI leave room for float differences of the relaxed field only;
  // J moves by 0.29 HU RMS (both inverted to 64 iterations), bound 1 HU
  const auto [du_rms, du_max] = field_change(on.u, off.u);
  INFO("untangling's change: RMS " << du_rms << " voxel, max " << du_max << " voxel, " << on.st.untangle.moved
                                   << " elements");
  CHECK(du_rms < 0.1);
  CHECK(on.st.untangle.moved < on.st.chainmail.voi.count() / 100);
  CHECK(rms(run(p, cfg, c, false, 64).j, ref.j) < 1.0);
  // J's error against 64 iterations never grows with more iterations (Newton with
  // backtracking on a fold-free field), and is gone at 16 (measured: 0 HU from 8 on)
  double prev = 1e30;
  for (int it : {0, 1, 2, 4, 8, 16, 32}) {
    const double err = rms(run(p, cfg, c, true, it).j, ref.j);
    INFO("inversion " << it << " iterations: J's RMS error " << err << " HU, previous " << prev);
    CHECK(err <= prev);
    prev = err;
  }
  CHECK(prev == 0.0);
}

TEST_CASE("untangling: the measuring run (40 random pushes and the Table 1 press)", "[.measure]") {
  const PatientPtr torso = make_torso_patient(48);
  const auto pushes = random_pushes(*torso, 40, 8);
  for (std::size_t i = 0; i < pushes.size(); ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "push %2zu p%d", i, i % 2 ? 2 : 1);
    measure(name, torso, pushes[i].config, pushes[i].contact);
  }
  measure("table 1", phantom(), table1_config(), table1_press(*phantom()));
}

TEST_CASE("deform.invert_search: off, Newton's answer stands next to the fold; on, every voxel resolves") {
  const PatientPtr& p = phantom();
  const DeformContact c = table1_press(*p);
  DeformConfig cfg = table1_config();
  cfg.settings.invert_search = false;
  const Result newton = run(p, cfg, c, false, 8);
  cfg.settings.invert_search = true;
  const Result searched = run(p, cfg, c, false, 8);
  INFO("unresolved " << newton.st.invert_unresolved << " / " << searched.st.invert_unresolved << ", residual "
                     << newton.st.invert_residual_vox << " / " << searched.st.invert_residual_vox);
  // relaxation alone folds here, and Newton stalls at one voxel (measured: 0.144 voxel);
  // the search finds its source within its 0.01 voxel stopping point (0.05: the goal)
  CHECK(newton.st.invert_unresolved >= 1);
  CHECK(searched.st.invert_unresolved == 0);
  CHECK(searched.st.invert_residual_vox < 0.05);
  // the search takes only voxels Newton left above 0.01 voxel, and here only the one it
  // left unresolved is above that (measured: J differs in 1 voxel); 8 leaves room for a
  // few voxels between 0.01 and 0.1 voxel on another compiler's rounding, and fails if the
  // flag also changed voxels Newton had resolved
  std::size_t differ = 0;
  for (std::size_t e = 0; e < newton.j.size(); ++e) differ += newton.j[e] != searched.j[e];
  INFO(differ << " voxels of J differ");
  CHECK(differ >= 1);
  CHECK(differ <= 8);
}

// Both backends find a queued voxel's source without walking the rings: every cell of
// the search that can reach a queued voxel is solved from its centre (pass 0) for each
// queued voxel its deformed box holds, and the voxel takes, among its cells in rings up
// to the first ring with a source within kInvertSearchVox, the lowest residual, then the
// lowest ring, then the lowest index in the ring (search_ring_index()); a voxel with no
// such ring goes to the ring search (invert_scatter.h's scatter_search() on the cpu,
// cuda/invert.cu's kernels on the GPU). This checks scatter_search() against
// invert_search() itself, bit for bit, on every voxel Newton leaves in 40 random pushes,
// the Table 1 press and presses over L3 15-30 mm deep; that the cpu backend's J with the
// search is invert_voxel()'s, the definition, voxel by voxel; and that the inverse of
// search_ring_cell() is one.
TEST_CASE("the cell search's scatter picks the source the ring search picks") {
  for (int r = 0; r <= 9; ++r)
    for (int idx = 0; idx < deform::search_ring_size(r); ++idx)
      REQUIRE(deform::search_ring_index(r, deform::search_ring_cell(r, idx)) == idx);
  const PatientPtr torso = make_torso_patient(48);
  const std::vector<RandomPush> pushes = random_pushes(*torso, 40, 8);
  struct Case {
    PatientPtr p;
    DeformConfig cfg;
    DeformContact c;
  };
  std::vector<Case> cases;
  for (const RandomPush& push : pushes) cases.push_back({torso, push.config, push.contact});
  cases.push_back({phantom(), table1_config(), table1_press(*phantom())});
  // the server's lumbar scene presses the spinous processes this deep
  const Vec3 X = spinous_press(make_phantom(340.0 / 255.0).geometry).contact.skin_point_mm;
  for (double depth_mm : {15.0, 20.0, 25.0, 30.0}) cases.push_back({phantom(), table1_config(), {X, X - Vec3{0, depth_mm, 0}}});
  long long compared = 0, to_rings = 0, searched = 0, scattered = 0, j_differ = 0;
  for (std::size_t n = 0; n < cases.size(); ++n) {
    const Case& cs = cases[n];
    const Result res = run(cs.p, cs.cfg, cs.c, false, 8);
    const Voi& voi = res.st.chainmail.voi;
    const Vec3i size = voi.size;
    auto load_u = [&](int i, int j, int k) {
      if (!voi.contains(i, j, k)) return Vec3f{0, 0, 0};
      return res.u[voi.index(i, j, k)];
    };
    // the voxels Newton leaves, as the cpu backend queues them
    std::vector<int> slot(std::size_t(voi.count()), -1);
    std::vector<deform::SearchVoxel> queue;
    for (int k = 0; k < size.z; ++k)
      for (int j = 0; j < size.y; ++j)
        for (int i = 0; i < size.x; ++i) {
          const Vec3f y{float(i), float(j), float(k)};
          float r;
          const Vec3f p = deform::invert_point(load_u, y, cs.cfg.settings.invert_iterations, r);
          if (!(r > deform::kInvertSearchVox)) continue;
          int rmax;
          slot[voi.index(i, j, k)] = int(queue.size());
          queue.push_back({{i, j, k}, deform::search_centre(size, y - deform::trilinear<Vec3f>(load_u, y), rmax), p, r});
        }
    REQUIRE(deform::scatter_search(load_u, size, queue, slot));
    for (const deform::SearchVoxel& q : queue) {
      if (!q.found) {
        ++to_rings;
        continue;
      }
      const Vec3f y{float(q.v.x), float(q.v.y), float(q.v.z)};
      float want_r;
      const Vec3f want = deform::invert_search(load_u, size, y, y - deform::trilinear<Vec3f>(load_u, y), want_r);
      INFO("case " << n << ", voxel " << y.x << " " << y.y << " " << y.z << ": scatter " << q.residual
                   << ", ring search " << want_r);
      REQUIRE(q.residual == want_r);
      REQUIRE(q.p.x == want.x);
      REQUIRE(q.p.y == want.y);
      REQUIRE(q.p.z == want.z);
      ++compared;
    }
    // the cpu backend with the search on, on the same field: J as invert_voxel() defines it
    DeformConfig on = cs.cfg;
    on.settings.invert_search = true;
    CpuDeformBackend b;
    b.bind(cs.p, on);
    b.chainmail(cs.c);
    b.set_displacement(res.u);
    const InvertStats st = b.invert();
    b.upload();
    const float* jb = b.deformed_brick();
    const Patient& pt = *cs.p;
    auto load_i = [&](int i, int j, int k) {
      const Vec3i g{std::clamp(voi.lo.x + i, 0, pt.grid.size.x - 1), std::clamp(voi.lo.y + j, 0, pt.grid.size.y - 1),
                    std::clamp(voi.lo.z + k, 0, pt.grid.size.z - 1)};
      return pt.intensity.data[pt.grid.index(g.x, g.y, g.z)];
    };
    for (int k = 0; k < size.z; ++k)
      for (int j = 0; j < size.y; ++j)
        for (int i = 0; i < size.x; ++i) {
          float r;
          const Vec3f x0 = deform::invert_voxel(load_u, size, Vec3f(float(i), float(j), float(k)),
                                                on.settings.invert_iterations, true, r);
          j_differ += jb[voi.index(i, j, k)] != deform::trilinear<float>(load_i, x0);
        }
    CHECK(st.searched == (long long)queue.size());
    searched += st.searched;
    scattered += st.scattered;
  }
  std::printf("scatter: %lld voxels picked as the ring search picks, %lld left to the rings; the cpu backend "
              "searched %lld, %lld decided on pass 0, J differs from invert_voxel() in %lld voxels\n",
              compared, to_rings, searched, scattered, j_differ);
  CHECK(j_differ == 0);
  CHECK(scattered == compared);
  CHECK(searched == compared + to_rings);
  // the pushes and presses leave voxels to the search (measured on this compiler: 1,384
  // picked, 76 of them in the pushes and Table 1's press, none left to the rings); 500
  // fails if the deep presses stopped folding and the test compared little
  CHECK(compared >= 500);
}

TEST_CASE("cell_may_fold: a cell it lets go has det(I + grad u) > 0; every folded cell it keeps") {
  // random corner displacements (voxels) at scales from a tenth of the bound to twice a
  // voxel: whatever cell_may_fold() calls safe must have cell_min_det() > 0 (it leaves a
  // margin of 0.1^3 there, far above float rounding), and every cell whose min det is not
  // positive must be kept. The largest scales fold many cells, the smallest none.
  std::uint32_t state = 12345u;
  auto uniform = [&]() {
    state = state * 1664525u + 1013904223u;
    return float(state >> 8) / float(1u << 24) * 2.0f - 1.0f;
  };
  int let_go = 0, folded = 0;
  for (float scale : {0.03f, 0.1f, 0.15f, 0.3f, 0.6f, 1.0f, 2.0f}) {
    for (int t = 0; t < 4000; ++t) {
      Vec3f c[8];
      for (Vec3f& v : c) v = Vec3f{uniform(), uniform(), uniform()} * scale;
      auto load = [&](int i, int j, int k) { return c[i + 2 * j + 4 * k]; };
      const bool may = deform::cell_may_fold(load, 0, 0, 0);
      const float det = deform::cell_min_det(load, 0, 0, 0);
      if (!may) {
        ++let_go;
        REQUIRE(det > 0.0f);
      }
      if (!(det > 0.0f)) {
        ++folded;
        REQUIRE(may);
      }
      // the elastic step's count takes a cell as folded exactly where its min det is not positive
      REQUIRE(deform::cell_folded(load, 0, 0, 0) == !(det > 0.0f));
    }
  }
  // the draws reached both sides
  CHECK(let_go > 1000);
  CHECK(folded > 1000);
  // a cell that does not move is let go
  auto still = [](int, int, int) { return Vec3f{0.5f, -0.25f, 0.0f}; };
  CHECK_FALSE(deform::cell_may_fold(still, 0, 0, 0));
}
