// ChainMail on the CPU reference: the paper's Table 2 counts, the restrictions after
// convergence, bone, the first element, VOIs at the border, the sweep cap.
#include <catch2/catch.hpp>

#include "deform/cpu_backend.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

// float rounding of u_n + limit for |u| up to 64 voxels is a few ulps of 64 (7.6e-6 each)
constexpr double kRestrictionTol = 4 * 64 * 1.2e-7;

struct Table2Row {
  int d;
  long long p1, p2;
};

// one element moved d voxels along `axis` (sign `dir`) in a whole-volume domain that
// holds the whole deformation: it spreads at most one voxel per sweep, 2d - 1 sweeps
ChainMailStats table2_case(int preset, int d, int axis, int dir, bool* touched_border) {
  const int n = 4 * d + 5, c = n / 2;
  auto patient = make_soft_patient(n);
  DeformConfig cfg = preset_config(preset);
  cfg.settings.whole_volume = true;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  Vec3 disp{0, 0, 0};
  disp[axis] = dir * d;
  const ChainMailStats st = b.chainmail(voxel_contact({c, c, c}, disp));
  // no element on the domain's faces may have moved, or the domain was too small
  const auto u = b.displacement();
  *touched_border = false;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i)
        if ((i == 0 || j == 0 || k == 0 || i == n - 1 || j == n - 1 || k == n - 1) &&
            u[st.voi.index(i, j, k)] != Vec3f(0, 0, 0))
          *touched_border = true;
  CHECK(max_restriction_violation(*patient, st.voi, u, cfg.settings) <= 0.0);  // quarter-voxel values are exact
  return st;
}

// ChainMail's field of one push of `d` voxels along a diagonal (i, j and k all moved) in
// a soft whole volume, restrictions checked, and the smallest Jacobian determinant of its
// trilinear field
double diagonal_push_min_det(DeformConfig cfg, int d) {
  const int n = 4 * d + 5, c = n / 2;
  auto patient = make_soft_patient(n);
  cfg.settings.whole_volume = true;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  const ChainMailStats st = b.chainmail(voxel_contact({c, c, c}, {double(d), -0.5 * d, 0.25 * d}));
  REQUIRE(st.converged);
  const auto u = b.displacement();
  REQUIRE(max_restriction_violation(*patient, st.voi, u, cfg.settings) <= kRestrictionTol);
  const double det = min_jacobian_det(*patient, st.voi, u);
  std::printf("diagonal push d = %d, minDist %g, maxSheer %g: min det(I + grad u) = %g\n", d, cfg.settings.min_dist,
              cfg.settings.max_sheer, det);
  return det;
}

}  // namespace

// Why keeping ChainMail's restrictions cannot by itself make the deformation invertible
// (issue 8, section 4): the columns of I + grad u inside a cell are blends of the cell's
// edges, and each edge along axis a has its a-component in [minDist, maxDist] and the
// others within maxSheer. With minDist > 2 maxSheer every column is strictly diagonally
// dominant with a positive diagonal, so det > 0 everywhere; the paper's presets (p1: 0.5
// and 0.5, p2: 0.25 and 1) do not meet that, and edges such as (0.5, 0.5, 0) along i and
// (0.5, 0.5, 0) along j are allowed and give det 0.
TEST_CASE("ChainMail's field keeps det(I + grad u) > 0 when minDist > 2 maxSheer") {
  DeformConfig cfg = preset_config(1);
  cfg.settings.min_dist = 0.6;
  cfg.settings.max_sheer = 0.25;
  // each column's diagonal exceeds the sum of its off-diagonal magnitudes by at least
  // 0.6 - 2 * 0.25 = 0.1, and det is at least the product of the three margins
  // (Ostrowski's bound for diagonally dominant matrices): 0.1^3 = 1e-3
  CHECK(diagonal_push_min_det(cfg, 6) >= 1e-3);
}

// Pinned: under the paper's presets ChainMail's converged field folds (det <= 0 in some
// cell) although every restriction holds, so projecting the relaxed field back onto the
// restrictions cannot make the inversion fold-free (measured: server/deform/README.md).
// [!shouldfail]: a fix makes this test fail, and the tag should go then.
TEST_CASE("known limitation: ChainMail's field folds under the paper's presets [issue 8]", "[!shouldfail]") {
  for (int preset = 1; preset <= 2; ++preset) CHECK(diagonal_push_min_det(preset_config(preset), 6) > 0);
}

TEST_CASE("chainmail reproduces the paper's Table 2 moved-element counts (d = 3, 5, 10, 20)") {
  const Table2Row rows[] = {{3, 230, 56}, {5, 1158, 259}, {10, 9918, 2120}, {20, 82238, 17309}};
  for (const auto& r : rows)
    for (int preset = 1; preset <= 2; ++preset) {
      INFO("d = " << r.d << ", p" << preset);
      bool border = true;
      const ChainMailStats st = table2_case(preset, r.d, 0, +1, &border);
      CHECK(st.moved == (preset == 1 ? r.p1 : r.p2));
      CHECK(st.sweeps == 2 * r.d);  // 2d - 1 sweeps move elements, the last one is quiet
      CHECK(st.converged);
      CHECK_FALSE(border);
    }
}

TEST_CASE("chainmail counts do not depend on the axis or direction of the move") {
  for (int axis = 0; axis < 3; ++axis)
    for (int dir = -1; dir <= 1; dir += 2) {
      INFO("axis " << axis << " direction " << dir);
      bool border = true;
      CHECK(table2_case(1, 5, axis, dir, &border).moved == 1158);
      CHECK(table2_case(2, 5, axis, dir, &border).moved == 259);
    }
}

TEST_CASE("after convergence every restriction holds and the first element sits at x") {
  // an oblique, non-integer move on a patient with spacing 0.8 mm and an offset origin
  auto patient = make_patient({40, 36, 32}, [](int i, int j, int) { return kSoftHu + float(i - j); },
                              {0.8, 0.8, 0.8}, {-12.0, 30.0, 5.5});
  for (int preset = 1; preset <= 2; ++preset) {
    DeformConfig cfg = preset_config(preset);
    cfg.settings.voi_edge = 32;
    CpuDeformBackend b;
    b.bind(patient, cfg);
    const Grid& g = patient->grid;
    const Vec3 X = g.to_physical({20, 18, 16});
    const Vec3 x = X + Vec3{3.3, -2.1, 4.45};
    const ChainMailStats st = b.chainmail({X, x});
    REQUIRE(st.converged);
    CHECK(st.grabbed_vox == Vec3i(20, 18, 16));
    CHECK(st.moved > 0);
    const auto u = b.displacement();
    CHECK(max_restriction_violation(*patient, st.voi, u, cfg.settings) <= kRestrictionTol);
    // the first element's deformed position is x (to float precision of the displacement)
    const Vec3i l = st.grabbed_vox - st.voi.lo;
    const Vec3f ug = u[st.voi.index(l.x, l.y, l.z)];
    const Vec3 xi = g.to_index(x);
    CHECK(std::fabs(st.grabbed_vox.x + ug.x - xi.x) < 1e-5);
    CHECK(std::fabs(st.grabbed_vox.y + ug.y - xi.y) < 1e-5);
    CHECK(std::fabs(st.grabbed_vox.z + ug.z - xi.z) < 1e-5);
  }
}

TEST_CASE("bone never moves and enforces nothing under chainmail") {
  // soft cube wrapped in a bone shell, pushed hard into the shell
  auto patient = make_cube_patient(48, 16, 4);
  for (int preset = 1; preset <= 2; ++preset) {
    DeformConfig cfg = preset_config(preset);
    cfg.settings.whole_volume = true;  // local and patient indices agree
    CpuDeformBackend b;
    b.bind(patient, cfg);
    const ChainMailStats st = b.chainmail(voxel_contact({24, 24, 24}, {6, 0, 0}));
    REQUIRE(st.converged);
    const auto u = b.displacement();
    CHECK(moved_bone_count(*patient, st.voi, u) == 0);
    // soft elements keep their restrictions among themselves; against bone they may not
    CHECK(max_restriction_violation(*patient, st.voi, u, cfg.settings) <= kRestrictionTol);
    // the shell stops the spread: nothing outside the shell moved
    long long outside = 0;
    for (int k = 0; k < 48; ++k)
      for (int j = 0; j < 48; ++j)
        for (int i = 0; i < 48; ++i) {
          const bool beyond = i < 12 || i > 35 || j < 12 || j > 35 || k < 12 || k > 35;
          if (beyond && u[st.voi.index(i, j, k)] != Vec3f(0, 0, 0)) ++outside;
        }
    CHECK(outside == 0);
  }
}

TEST_CASE("a VOI at the volume border is clipped and chainmail stays inside it") {
  auto patient = make_soft_patient(40);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  // grab a corner voxel and pull it outwards past the border
  const ChainMailStats st = b.chainmail(voxel_contact({1, 38, 0}, {-3, 3, -2}));
  // the cube around x = (-2, 41, -2) spans -18..13, 25..56, -18..13 before clipping
  CHECK(st.voi.lo == Vec3i(0, 25, 0));
  CHECK(st.voi.size == Vec3i(14, 15, 14));
  CHECK(st.converged);
  CHECK(st.moved > 0);
  CHECK(max_restriction_violation(*patient, st.voi, b.displacement(), cfg.settings) <= kRestrictionTol);
}

TEST_CASE("X on the volume's outer face grabs the border voxel; X beyond it is refused") {
  // the volume reaches half a voxel past the border voxels' centres; where the grid cuts
  // the body the skin point may lie on that face (unit spacing, origin 0: index = mm)
  auto patient = make_soft_patient(40);
  CpuDeformBackend b;
  b.bind(patient, preset_config(1));
  const ChainMailStats st = b.chainmail({Vec3(20, 39.5, 20), Vec3(20, 36.5, 20)});
  CHECK(st.grabbed_vox == Vec3i(20, 39, 20));
  CHECK(st.converged);
  CHECK(st.moved > 0);
  const ChainMailStats low = b.chainmail({Vec3(-0.5, 20, 20), Vec3(2.5, 20, 20)});
  CHECK(low.grabbed_vox == Vec3i(0, 20, 20));
  // a tenth of a voxel beyond the face is outside the volume
  CHECK_THROWS_WITH(b.chainmail({Vec3(20, 39.6, 20), Vec3(20, 36.5, 20)}), Catch::Contains("outside the patient grid"));
}

TEST_CASE("a displacement larger than half the VOI keeps the grabbed element inside the VOI") {
  auto patient = make_soft_patient(96);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  // 24 voxels > 16: the VOI centred on x is shifted back until it holds X's voxel
  const ChainMailStats st = b.chainmail(voxel_contact({30, 48, 48}, {24, 0, 0}));
  CHECK(st.voi.lo.x == 30);
  CHECK(st.voi.size == Vec3i(32, 32, 32));
  CHECK(st.converged);
  const auto u = b.displacement();
  CHECK(u[st.voi.index(0, 16, 16)] == Vec3f(24, 0, 0));
  CHECK(max_restriction_violation(*patient, st.voi, u, cfg.settings) <= kRestrictionTol);
}

TEST_CASE("the tip inside bone: soft tissue follows, bone stays; X in bone moves nothing") {
  auto patient = make_cube_patient(48, 16, 4);  // shell spans 12..15 and 32..35
  DeformConfig cfg = preset_config(2);
  cfg.settings.voi_edge = 48;
  CpuDeformBackend b;
  b.bind(patient, cfg);
  // x lies inside the shell
  ChainMailStats st = b.chainmail(voxel_contact({28, 24, 24}, {5, 0, 0}));
  CHECK(st.converged);
  CHECK_FALSE(st.grabbed_in_bone);
  CHECK(moved_bone_count(*patient, st.voi, b.displacement()) == 0);
  // X itself in bone: nothing moves
  st = b.chainmail(voxel_contact({13, 24, 24}, {-4, 2, 0}));
  CHECK(st.grabbed_in_bone);
  CHECK(st.moved == 0);
  for (const Vec3f& v : b.displacement()) REQUIRE(v == Vec3f(0, 0, 0));
}

TEST_CASE("the sweep cap turns a long propagation into reported non-convergence") {
  auto patient = make_soft_patient(48);
  DeformConfig cfg = preset_config(1);
  cfg.settings.whole_volume = true;
  cfg.settings.max_sweeps = 7;  // d = 10 needs 20
  CpuDeformBackend b;
  b.bind(patient, cfg);
  const ChainMailStats st = b.chainmail(voxel_contact({24, 24, 24}, {10, 0, 0}));
  CHECK_FALSE(st.converged);
  CHECK(st.sweeps == 7);
}
