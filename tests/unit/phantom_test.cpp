// The built-in phantom alone: grid, determinism, HU of each tissue, the closed-form
// geometry (exact distances, landmarks), enclosed bowel gas, the table apart from the body.
#include <catch2/catch.hpp>

#include <cmath>
#include <cstring>
#include <random>
#include <vector>

#include "core/error.h"
#include "prep/phantom.h"

using namespace palpsim;
namespace hu = palpsim::phantom_hu;

namespace {

// the voxel nearest to a physical point (the phantom's direction is identity)
float hu_at(const Volume<float>& v, const Vec3& p) {
  const Vec3 ijk = v.grid.to_index(p);
  return v.at(int(std::lround(ijk.x)), int(std::lround(ijk.y)), int(std::lround(ijk.z)));
}

// the phantom at 1 mm and 2 mm, generated once for the whole file
const PhantomCt& phantom_1mm() {
  static const PhantomCt ct = make_phantom(1.0);
  return ct;
}
const PhantomCt& phantom_2mm() {
  static const PhantomCt ct = make_phantom(2.0);
  return ct;
}

}  // namespace

TEST_CASE("the phantom grid: fixed origin, identity direction, extent covered at every voxel size") {
  for (double h : {0.25, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0}) {
    const Grid g = phantom_grid(h);
    INFO("voxel " << h << " mm");
    CHECK(g.spacing_mm == Vec3(h, h, h));
    CHECK(g.origin_mm == Vec3(-170, -145, -110));
    CHECK(g.direction == Grid{}.direction);
    // the last voxel centre lies within the extent, one more would not (1e-9: rounding)
    const Vec3 extent{340, 270, 220};
    for (int a = 0; a < 3; ++a) {
      CHECK((g.size[a] - 1) * h <= extent[a] + 1e-9);
      CHECK(g.size[a] * h > extent[a] + 1e-9);
    }
  }
  CHECK(phantom_grid(1.0).size == Vec3i(341, 271, 221));
  CHECK(phantom_grid(0.5).size == Vec3i(681, 541, 441));
  // the generated volume is on that grid
  CHECK(phantom_2mm().hu.grid.same_geometry(phantom_grid(2.0)));
  CHECK(phantom_2mm().hu.data.size() == phantom_grid(2.0).count());
}

TEST_CASE("a voxel size outside 0.25-4 mm is refused naming phantom.voxel_mm") {
  for (double h : {0.0, 0.2, -1.0, 4.5, std::nan("")}) {
    INFO("voxel " << h);
    CHECK_THROWS_AS(phantom_grid(h), Error);
    CHECK_THROWS_WITH(make_phantom(h), Catch::Contains("phantom.voxel_mm"));
  }
}

TEST_CASE("the phantom is deterministic") {
  const PhantomCt again = make_phantom(2.0);
  const auto& first = phantom_2mm().hu;
  REQUIRE(again.hu.grid.same_geometry(first.grid));
  CHECK(std::memcmp(again.hu.data.data(), first.data.data(), first.bytes()) == 0);
  // and not trivially so: the texture makes neighbouring muscle voxels differ
  const Vec3 muscle{70, 60, 0};
  CHECK(hu_at(first, muscle) != hu_at(first, muscle + Vec3{2, 0, 0}));
}

TEST_CASE("HU at known points of each tissue") {
  const PhantomCt& ct = phantom_1mm();
  const PhantomGeometry& g = ct.geometry;
  // every point below lies at least 2 voxels inside its tissue, so partial volume
  // does not touch it; the tolerance is the texture amplitude
  const double tex = hu::kTextureAmplitude + 1e-3;
  struct Point {
    const char* what;
    Vec3 p;
    float expected;
  };
  const Point points[] = {
      {"air above the back", {0, 120, 0}, hu::kAir},
      {"air beside the flank", {163, 0, 0}, hu::kAir},
      {"air between body and table", {0, -112, 0}, hu::kAir},
      {"subcutaneous fat of the back", {0, 102, 0}, hu::kFat},
      {"back muscle", {70, 60, 0}, hu::kMuscle},
      {"abdominal cavity", {0, -30, 40}, hu::kViscera},
      {"L3 body interior", {0, 6, -6}, hu::kCancellousVertebra},
      {"L3 anterior cortex (2 mm, at 1 mm voxels)", {0, -9, -6}, hu::kCortical},
      {"L3/L4 disc", {0, 6, -23}, hu::kDisc},
      {"spinal canal", {0, 31, -6}, hu::kCanal},
      {"gas in the ascending colon", {-85, -22, -10}, hu::kAir},
      {"fluid in the ascending colon", {-85, -40, -10}, hu::kBowelFluid},
      {"table shell", {0, -115, 0}, hu::kTableShell},
      {"table core", {0, -127, 0}, hu::kTableCore},
  };
  for (const Point& pt : points) {
    INFO(pt.what << " at (" << pt.p.x << ", " << pt.p.y << ", " << pt.p.z << ")");
    CHECK(hu_at(ct.hu, pt.p) == Approx(pt.expected).margin(tex));
  }
  // gas and outside air carry no texture
  CHECK(hu_at(ct.hu, {0, 120, 0}) == hu::kAir);
  CHECK(hu_at(ct.hu, {-85, -22, -10}) == hu::kAir);
  // the geometry agrees with the points it classifies
  CHECK(g.in_bowel_gas({-85, -22, -10}));
  CHECK_FALSE(g.in_bowel_gas({-85, -40, -10}));
  CHECK(g.in_table({0, -115, 0}));
  CHECK(g.in_table({0, -127, 0}));
  CHECK_FALSE(g.in_table({0, -112, 0}));
  CHECK(g.skin_signed_distance_mm({0, 120, 0}) == Approx(10).margin(1e-9));
  CHECK(g.bone_signed_distance_mm({0, 6, -6}) < -10);
  // the vertebral body interior is deliberately below the default bone threshold
  // (200 HU), so the bone mask's hole filling is exercised
  CHECK(hu_at(ct.hu, {0, 6, -6}) < 200);
}

TEST_CASE("the volume agrees with the geometry everywhere (2 mm)") {
  const PhantomCt& ct = phantom_2mm();
  const PhantomGeometry& geo = ct.geometry;
  const Grid& gr = ct.hu.grid;
  const double h = gr.spacing_mm.x;
  // partial volume reaches half a voxel from a surface (the SDF ramp): voxels
  // farther than h/2 from every surface of the class hold pure tissue (+- texture)
  std::size_t air_bad = 0, bone_bad = 0, soft_bad = 0, gas_bad = 0, checked = 0;
  for (int k = 0; k < gr.size.z; ++k)
    for (int j = 0; j < gr.size.y; ++j)
      for (int i = 0; i < gr.size.x; ++i) {
        const Vec3 p = gr.to_physical({double(i), double(j), double(k)});
        const float v = ct.hu.at(i, j, k);
        const double skin = geo.skin_signed_distance_mm(p);
        ++checked;
        if (skin > 0.5 * h) {
          // outside: air, or the table (table HU between core and shell)
          const bool near_table = geo.in_table(p) || geo.in_table(p + Vec3{0, h, 0}) || geo.in_table(p - Vec3{0, h, 0}) ||
                                  geo.in_table(p + Vec3{h, 0, 0}) || geo.in_table(p - Vec3{h, 0, 0});
          if (!near_table && v != hu::kAir) ++air_bad;
          continue;
        }
        if (skin > -2 * h) continue;  // skin, fat and their partial volume
        const double bone = geo.bone_signed_distance_mm(p);
        if (bone < -0.5 * h && v < hu::kCancellousVertebra - hu::kTextureAmplitude) ++bone_bad;
        if (bone > 0.5 * h && v >= 200) ++soft_bad;  // soft tissue stays below the bone threshold
        if (geo.in_bowel_gas(p) && v > -400) {
          // gas voxels are dark unless they touch the wall or the fluid level (partial volume)
          bool edge = false;
          for (const Vec3& o : {Vec3{h, 0, 0}, Vec3{-h, 0, 0}, Vec3{0, h, 0}, Vec3{0, -h, 0}, Vec3{0, 0, h}, Vec3{0, 0, -h}})
            edge = edge || !geo.in_bowel_gas(p + o * 0.5);
          if (!edge) ++gas_bad;
        }
      }
  CHECK(checked == gr.count());
  CHECK(air_bad == 0);
  CHECK(bone_bad == 0);
  CHECK(soft_bad == 0);
  CHECK(gas_bad == 0);
}

TEST_CASE("the skin distance is exact (against a densely sampled outline)") {
  const PhantomGeometry geo;
  // the outline: the skin's zero set found along rays from the axis by bisection
  std::vector<Vec3> outline;
  const int n = 50000;
  for (int s = 0; s < n; ++s) {
    const double a = 2 * 3.14159265358979323846 * s / n;
    const Vec3 dir{std::cos(a), std::sin(a), 0};
    double lo = 0, hi = 400;
    for (int it = 0; it < 60; ++it) {
      const double mid = 0.5 * (lo + hi);
      (geo.skin_signed_distance_mm(dir * mid) < 0 ? lo : hi) = mid;
    }
    outline.push_back(dir * lo);
  }
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> ux(-200, 200), uy(-160, 160), uz(-100, 100);
  for (int t = 0; t < 150; ++t) {
    const Vec3 p{ux(rng), uy(rng), uz(rng)};
    double best = 1e300;
    for (const Vec3& q : outline) best = std::min(best, std::hypot(p.x - q.x, p.y - q.y));
    const double d = geo.skin_signed_distance_mm(p);
    INFO("p = (" << p.x << ", " << p.y << ", " << p.z << ")");
    // outline points are < 0.02 mm apart: the nearest one is within 0.01 mm of the truth
    CHECK(std::abs(d) == Approx(best).margin(0.012));
    // z does not matter: the torso is a cylinder cut by the volume
    CHECK(geo.skin_signed_distance_mm({p.x, p.y, 0}) == d);
  }
}

TEST_CASE("the bone distance is a true distance outside bone") {
  const PhantomGeometry geo;
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> ux(-150, 150), uy(-100, 100), uz(-110, 110);
  int on_surface = 0, outside = 0;
  for (int t = 0; t < 4000; ++t) {
    const Vec3 p{ux(rng), uy(rng), uz(rng)};
    const Vec3 q = p + Vec3{ux(rng), uy(rng), uz(rng)} * 0.05;
    const double dp = geo.bone_signed_distance_mm(p), dq = geo.bone_signed_distance_mm(q);
    // 1-Lipschitz everywhere (inside too): never more than the distance moved
    CHECK(std::abs(dp - dq) <= norm(p - q) + 1e-9);
    if (dp <= 0.5 || dp > 40) continue;
    ++outside;
    // following the gradient by the distance lands on a surface; with the
    // Lipschitz bound this makes the distance exact (points on the medial axis,
    // where the gradient is undefined, are the rare exceptions)
    const double e = 1e-5;
    const Vec3 grad = Vec3{geo.bone_signed_distance_mm(p + Vec3{e, 0, 0}) - geo.bone_signed_distance_mm(p - Vec3{e, 0, 0}),
                           geo.bone_signed_distance_mm(p + Vec3{0, e, 0}) - geo.bone_signed_distance_mm(p - Vec3{0, e, 0}),
                           geo.bone_signed_distance_mm(p + Vec3{0, 0, e}) - geo.bone_signed_distance_mm(p - Vec3{0, 0, e})} /
                      (2 * e);
    if (std::abs(norm(grad) - 1) < 1e-3 && std::abs(geo.bone_signed_distance_mm(p - grad * dp)) < 1e-3) ++on_surface;
  }
  REQUIRE(outside > 500);
  CHECK(on_surface >= 0.98 * outside);
}

TEST_CASE("spinous process tips lie 20-40 mm under the back skin") {
  const PhantomGeometry geo;
  const PhantomCt& ct = phantom_1mm();
  int tips = 0;
  for (const PhantomLandmark& l : geo.landmarks()) {
    if (l.name.rfind("spinous_tip_", 0) != 0) continue;
    ++tips;
    INFO(l.name << " at (" << l.p_mm.x << ", " << l.p_mm.y << ", " << l.p_mm.z << ")");
    // on the bone surface, on the midline
    CHECK(std::abs(geo.bone_signed_distance_mm(l.p_mm)) < 1e-9);
    CHECK(l.p_mm.x == 0);
    // the posterior-most bone of its level: scanning down from the skin along the
    // midline, the first bone within +-15 mm of the tip's height is at the tip
    double first_y = -1e9;
    for (double z = l.p_mm.z - 15; z <= l.p_mm.z + 15; z += 0.25)
      for (double y = 109.5; y > l.p_mm.y - 10; y -= 0.05)
        if (geo.bone_signed_distance_mm({0, y, z}) <= 0) {
          first_y = std::max(first_y, y);
          break;
        }
    CHECK(first_y == Approx(l.p_mm.y).margin(0.06));  // the scan step
    // the depth under the skin
    const double depth = -geo.skin_signed_distance_mm(l.p_mm);
    CHECK(depth >= 20);
    CHECK(depth <= 40);
    // in the CT: bone just under the tip, soft tissue above it up to the skin
    CHECK(hu_at(ct.hu, l.p_mm - Vec3{0, 2, 0}) >= 200);
    for (double y = l.p_mm.y + 2; y < 110 - 3; y += 1) CHECK(hu_at(ct.hu, {0, y, l.p_mm.z}) < 200);
  }
  CHECK(tips == 7);  // T12, L1-L5, S1
}

TEST_CASE("iliac crests and ribs are palpable landmarks on the bone surface") {
  const PhantomGeometry geo;
  for (const char* side : {"left", "right"}) {
    const Vec3 crest = geo.landmark(std::string("iliac_crest_top_") + side);
    INFO(side);
    CHECK(std::abs(geo.bone_signed_distance_mm(crest)) < 1e-9);
    // the highest bone point of its flank: nothing above it at the crest's x, y
    for (double dz = 0.5; dz < 60; dz += 0.5) CHECK(geo.bone_signed_distance_mm(crest + Vec3{0, 0, dz}) > 0);
    // at the level of L4 (Tuffier's line): between the L4 and L3 body centres
    CHECK(crest.z > -40);
    CHECK(crest.z < -6);
    CHECK(std::abs(crest.x) > 100);
    CHECK(-geo.skin_signed_distance_mm(crest) > 10);
    CHECK(-geo.skin_signed_distance_mm(crest) < 40);
    for (int n : {10, 11, 12}) {
      const Vec3 rib = geo.landmark("rib" + std::to_string(n) + "_" + side);
      INFO("rib " << n);
      CHECK(std::abs(geo.bone_signed_distance_mm(rib)) < 1e-9);
      CHECK(-geo.skin_signed_distance_mm(rib) > 10);
      CHECK(-geo.skin_signed_distance_mm(rib) < 30);
      CHECK(std::abs(rib.z) < 110);  // inside the volume
    }
  }
  // vertebral body centres lie deep in bone, on the midline, one per spinous process
  int bodies = 0;
  for (const PhantomLandmark& l : geo.landmarks()) {
    if (l.name.rfind("vertebral_body_", 0) != 0) continue;
    ++bodies;
    INFO(l.name);
    CHECK(geo.bone_signed_distance_mm(l.p_mm) < -8);
    CHECK(l.p_mm.x == 0);
    const Vec3 tip = geo.landmark("spinous_tip_" + l.name.substr(15));
    CHECK(tip.y - l.p_mm.y > 60);           // the process points backwards (+y)
    CHECK(std::abs(tip.z - l.p_mm.z) < 17);  // at its own level (the pitch is 34 mm)
  }
  CHECK(bodies == 7);
  CHECK_THROWS_WITH(geo.landmark("spinous_tip_C7"), Catch::Contains("spinous_tip_C7"));
}

TEST_CASE("bowel gas is enclosed in the abdomen") {
  for (double h : {1.0, 2.0}) {
    const PhantomCt& p = h == 1.0 ? phantom_1mm() : phantom_2mm();
    const Grid& g = p.hu.grid;
    INFO("voxel " << h << " mm");
    // flood fill from the volume border through air (below the default air threshold)
    std::vector<std::uint8_t> reached(g.count(), 0);
    std::vector<std::size_t> stack;
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const bool border = i == 0 || j == 0 || k == 0 || i == g.size.x - 1 || j == g.size.y - 1 || k == g.size.z - 1;
          const std::size_t idx = g.index(i, j, k);
          if (border && p.hu.data[idx] < -400) {
            reached[idx] = 1;
            stack.push_back(idx);
          }
        }
    const std::size_t sx = 1, sy = std::size_t(g.size.x), sz = sy * g.size.y;
    while (!stack.empty()) {
      const std::size_t idx = stack.back();
      stack.pop_back();
      const int i = int(idx % sy), j = int((idx / sy) % g.size.y), k = int(idx / sz);
      const std::pair<bool, std::size_t> nb[] = {{i > 0, idx - sx}, {i + 1 < g.size.x, idx + sx}, {j > 0, idx - sy},
                                                 {j + 1 < g.size.y, idx + sy}, {k > 0, idx - sz}, {k + 1 < g.size.z, idx + sz}};
      for (const auto& [ok, n] : nb)
        if (ok && !reached[n] && p.hu.data[n] < -400) {
          reached[n] = 1;
          stack.push_back(n);
        }
    }
    std::size_t gas = 0, gas_reached = 0, gas_dark = 0;
    double min_depth = 1e9;
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const Vec3 pt = g.to_physical({double(i), double(j), double(k)});
          if (!p.geometry.in_bowel_gas(pt)) continue;
          ++gas;
          gas_reached += reached[g.index(i, j, k)];
          gas_dark += p.hu.at(i, j, k) < -400;
          min_depth = std::min(min_depth, -p.geometry.skin_signed_distance_mm(pt));
        }
    const double gas_ml = gas * h * h * h / 1000;
    CHECK(gas_ml > 20);           // there is gas to find
    CHECK(gas_reached == 0);      // no gas voxel connects to outside air
    CHECK(gas_dark > gas / 2);    // and it is dark (the rest is partial volume at the wall)
    CHECK(min_depth > 15);        // well inside the body
    // the outside air was found (the fill ran)
    CHECK(reached[g.index(0, 0, 0)] == 1);
  }
}

TEST_CASE("the table lies under the patient, apart from it") {
  const PhantomCt& ct = phantom_2mm();
  const Grid& g = ct.hu.grid;
  std::size_t table = 0;
  double min_gap = 1e9;
  for (int k = 0; k < g.size.z; k += 3)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        const Vec3 p = g.to_physical({double(i), double(j), double(k)});
        if (!ct.geometry.in_table(p)) continue;
        ++table;
        min_gap = std::min(min_gap, ct.geometry.skin_signed_distance_mm(p));
        CHECK(p.y < -110);  // anterior of the prone patient (low y)
      }
  CHECK(table > 1000);
  // separated by an air gap of at least 3 mm (4 mm at the midline by design)
  CHECK(min_gap >= 3);
  // the table's shell is above the air threshold, its core below it
  CHECK(hu_at(ct.hu, {0, -115, 0}) > -400);
  CHECK(hu_at(ct.hu, {0, -127, 0}) < -400);
}
