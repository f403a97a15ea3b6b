// The preprocessing pipeline on the built-in phantom, against its closed-form
// geometry: body mask C vs the skin, bone mask vs the bones, distance maps A and
// B vs the exact distances, F = eq. 1, F = 0 outside, grad F = central differences.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <string>

#include "prep/phantom.h"
#include "prep/prepare.h"
#include "support/prepared_phantom.h"

using namespace palpsim;

namespace {

const Patient& patient_2mm() {
  static const PatientPtr p = test::prepared_phantom(2.0);
  return *p;
}
const Patient& patient_1mm() {
  static const PatientPtr p = test::prepared_phantom(1.0);
  return *p;
}

// counts failures of one check and keeps the first few for the report
struct Failures {
  std::size_t count = 0;
  std::string first;
  void add(const Vec3& p, const std::string& what) {
    if (count++ < 5) {
      char buf[256];
      std::snprintf(buf, sizeof buf, "  (%.1f, %.1f, %.1f): %s\n", p.x, p.y, p.z, what.c_str());
      first += buf;
    }
  }
};

// one check: no failure, else the first few in the message
void expect_none(const char* what, const Failures& f) {
  INFO(what << " (" << f.count << " voxels):\n" << f.first);
  CHECK(f.count == 0);
}

std::string fmt(const char* f, double a, double b = 0) {
  char buf[128];
  std::snprintf(buf, sizeof buf, f, a, b);
  return buf;
}

// distance (mm) from p to the nearer of the grid's first and last z slices; the
// torso and some bones (ribs 10-11, ilia, S1) continue beyond them
double z_margin(const Grid& g, const Vec3& p) {
  const double z0 = g.origin_mm.z, z1 = g.origin_mm.z + (g.size.z - 1) * g.spacing_mm.z;
  return std::min(p.z - z0, z1 - p.z);
}

// the masks, A and B against the closed form at every `stride`-th voxel along each axis
void check_masks_and_distances(const Patient& pt, const Scene& defaults, int stride) {
  const PhantomGeometry geo;
  const Grid& g = pt.grid;
  const double h = g.spacing_mm.x;
  const double closing = defaults.prep.bone_closing_mm;
  Failures body_in, body_out, table, gas, bone_in, bone_out, a_range, b_range;
  double a_err_sum = 0, b_err_sum = 0;
  std::size_t a_n = 0, b_n = 0, body_far = 0, bone_deep = 0, bone_far = 0, table_n = 0, gas_n = 0;
  for (int k = 0; k < g.size.z; k += stride)
    for (int j = 0; j < g.size.y; j += stride)
      for (int i = 0; i < g.size.x; i += stride) {
        const Vec3 p = g.to_physical({double(i), double(j), double(k)});
        const std::size_t idx = g.index(i, j, k);
        const double skin = geo.skin_signed_distance_mm(p);
        const bool c = pt.body.data[idx] != 0;

        // body mask: the partial-volume threshold (-400 HU between air and 30 HU
        // skin) puts the mask's surface within 0.1 voxel of the skin, so every voxel
        // more than one voxel from the skin is classified right
        if (skin < -h) {
          ++body_far;
          if (!c) body_in.add(p, fmt("inside the skin by %.2f mm but not body", -skin));
        } else if (skin > h) {
          if (c) body_out.add(p, fmt("outside the skin by %.2f mm but body", skin));
        }
        if (geo.in_table(p)) {
          ++table_n;
          if (c) table.add(p, "table voxel in the body mask");
        }
        if (geo.in_bowel_gas(p)) {
          ++gas_n;
          if (!c) gas.add(p, "bowel gas outside the body mask");
        }

        // bone mask: voxel centres within 0.35 voxel outside a bone surface are
        // above the threshold by partial volume and the interiors are filled, so
        // bone deeper than one voxel (texture, digital shells) is bone; the closing
        // adds voxels at most its radius from thresholded bone, so nothing farther
        // than the radius plus one voxel is
        const double bone_d = geo.bone_signed_distance_mm(p);
        const bool b = pt.bone.data[idx] != 0;
        if (bone_d < -h) {
          ++bone_deep;
          if (!b) bone_in.add(p, fmt("inside bone by %.2f mm but not bone", -bone_d));
        } else if (bone_d > closing + h) {
          ++bone_far;
          if (b) bone_out.add(p, fmt("%.2f mm from bone but bone (closing %.1f mm)", bone_d, closing));
        }

        // A, distance to the nearest bone voxel centre, where the nearest bone point
        // lies inside the volume (z_margin): the nearest bone voxel is at most 0.35
        // voxel (threshold) plus the closing radius outside the surface, so A >=
        // d - r - 0.5 voxel; a bone voxel centre lies within 0.87 voxel (half the
        // diagonal) of the point 0.65 voxel under the nearest surface point (where
        // partial volume reaches the threshold even against fat), so A <= d + 1.6 voxel
        const float a = pt.dist_bone_mm.data[idx];
        if (bone_d > 0 && bone_d < 60 && z_margin(g, p) > bone_d + h) {
          if (a < bone_d - closing - 0.5 * h || a > bone_d + 1.6 * h)
            a_range.add(p, fmt("A = %.2f mm, exact distance %.2f mm", a, bone_d));
          if (bone_d > 2 * h) {
            a_err_sum += a - bone_d;
            ++a_n;
          }
        }
        if (b && a != 0) a_range.add(p, "bone voxel with A != 0");

        // B, depth under the skin to the nearest outside voxel centre: the body mask
        // check above puts every outside voxel at most one voxel inside the skin, so
        // B >= depth - 1 voxel; an outside voxel centre lies within 0.87 voxel of the
        // point 0.9 voxel outside the nearest skin point, so B <= depth + 2 voxels.
        // Near the first and last slice the cut may count as outside: left out.
        const float bd = pt.dist_skin_mm.data[idx];
        if (!c && bd != 0) b_range.add(p, "outside voxel with B != 0");
        if (c && skin < 0 && z_margin(g, p) > -skin + 2 * h) {
          if (bd < -skin - h || bd > -skin + 2 * h) b_range.add(p, fmt("B = %.2f mm, depth %.2f mm", bd, -skin));
          if (-skin > 2 * h) {
            b_err_sum += bd + skin;
            ++b_n;
          }
        }
      }

  REQUIRE(body_far > 100000);
  REQUIRE(table_n > 0);
  REQUIRE(gas_n > 0);
  REQUIRE(bone_deep > 0);
  REQUIRE(bone_far > 0);
  expect_none("voxels inside the skin but not body", body_in);
  expect_none("voxels outside the skin but body", body_out);
  expect_none("table voxels in the body", table);
  expect_none("bowel gas voxels outside the body", gas);
  expect_none("deep bone voxels missing from the bone mask", bone_in);
  expect_none("far voxels in the bone mask", bone_out);
  expect_none("A out of its bounds", a_range);
  expect_none("B out of its bounds", b_range);
  // on average, the distance to voxel centres exceeds the distance to the surface
  // by a fraction of a voxel (the surface lies between centres): mean error in [-0.25, 1] voxel
  const double a_mean = a_err_sum / std::max<std::size_t>(a_n, 1), b_mean = b_err_sum / std::max<std::size_t>(b_n, 1);
  std::printf("phantom %.1f mm: mean(A - exact) = %.3f mm over %zu voxels, mean(B - depth) = %.3f mm over %zu voxels\n",
              h, a_mean, a_n, b_mean, b_n);
  CHECK(a_mean > -0.25 * h);
  CHECK(a_mean < 1.0 * h);
  CHECK(b_mean > -0.25 * h);
  CHECK(b_mean < 1.0 * h);
}

// the vertebral bodies and A behind the spinous tips
void check_vertebrae(const Patient& pt, const Scene& defaults) {
  const PhantomGeometry geo;
  const Grid& g = pt.grid;
  const double h = g.spacing_mm.x;
  // every vertebral body (T12-L5 centres) is bone throughout, its cancellous
  // interior (180 HU, below the threshold) included
  for (const char* level : {"T12", "L1", "L2", "L3", "L4", "L5"}) {
    const Vec3 ijk = g.to_index(geo.landmark(std::string("vertebral_body_") + level));
    const int i = int(std::lround(ijk.x)), j = int(std::lround(ijk.y)), k = int(std::lround(ijk.z));
    INFO("vertebral body " << level);
    REQUIRE(geo.bone_signed_distance_mm(g.to_physical({double(i), double(j), double(k)})) < -8);
    CHECK(pt.intensity.at(i, j, k) < defaults.prep.bone_threshold);
    CHECK(pt.bone.at(i, j, k) == 1);
  }

  Failures a_tight;
  // tight bounds where the bone is convex and the closing adds nothing: straight
  // behind each spinous tip, A follows the exact distance from -0.5 to +1.6 voxels
  for (const PhantomLandmark& l : geo.landmarks()) {
    if (l.name.rfind("spinous_tip_", 0) != 0) continue;
    const Vec3 ijk = g.to_index(l.p_mm);
    const int i = int(std::lround(ijk.x)), k = int(std::lround(ijk.z));
    for (int j = int(std::ceil(ijk.y)) + 2; j < g.size.y; ++j) {
      const Vec3 p = g.to_physical({double(i), double(j), double(k)});
      if (geo.skin_signed_distance_mm(p) > -h) break;
      const double d = geo.bone_signed_distance_mm(p);
      const float a = pt.dist_bone_mm.at(i, j, k);
      if (a < d - 0.5 * h || a > d + 1.6 * h) a_tight.add(p, l.name + fmt(": A = %.2f mm, exact %.2f mm", a, d));
    }
  }
  expect_none("A behind the spinous tips", a_tight);
}

// F and grad F against eq. 1 and central differences
void check_force_image(const Patient& pt, const Scene& defaults) {
  const Grid& g = pt.grid;
  const double h = g.spacing_mm.x;
  // F = eq. 1 at sampled voxels (float arithmetic: relative 1e-5), F = 0 outside
  const ForceImageSettings& f = defaults.force_image;
  std::size_t f_bad = 0, f_outside_bad = 0, f_n = 0;
  for (std::size_t idx = 0; idx < g.count(); idx += 7) {
    const double cc = pt.body.data[idx] ? 1.0 : 0.0;
    const double a = pt.dist_bone_mm.data[idx], bd = pt.dist_skin_mm.data[idx];
    const double expected = f.alpha * cc / (f.beta + a) + f.gamma * bd;
    const double got = pt.force.data[idx];
    ++f_n;
    if (std::abs(got - expected) > 1e-5 * std::abs(expected) + 1e-6) ++f_bad;
    if (!pt.body.data[idx] && got != 0) ++f_outside_bad;
  }
  CHECK(f_n > 1000);
  CHECK(f_bad == 0);
  CHECK(f_outside_bad == 0);

  // grad F (physical axes; identity direction) = central differences of F at
  // interior voxels (float: 1e-4 of the difference scale)
  std::size_t g_bad = 0, g_n = 0;
  for (int k = 1; k + 1 < g.size.z; k += 5)
    for (int j = 1; j + 1 < g.size.y; j += 3)
      for (int i = 1; i + 1 < g.size.x; i += 3) {
        const Vec3f gr = pt.grad_force.at(i, j, k);
        const double cd[3] = {(pt.force.at(i + 1, j, k) - pt.force.at(i - 1, j, k)) / (2 * h),
                              (pt.force.at(i, j + 1, k) - pt.force.at(i, j - 1, k)) / (2 * h),
                              (pt.force.at(i, j, k + 1) - pt.force.at(i, j, k - 1)) / (2 * h)};
        ++g_n;
        for (int a = 0; a < 3; ++a)
          if (std::abs(gr[a] - cd[a]) > 1e-4 * std::abs(cd[a]) + 1e-5) ++g_bad;
      }
  CHECK(g_n > 1000);
  CHECK(g_bad == 0);
}

// every check of this file on one prepared phantom; the voxel-wise comparisons
// visit every `stride`-th voxel along each axis
void check_patient(const Patient& pt, const Scene& defaults, int stride) {
  const Grid& g = pt.grid;
  const double h = g.spacing_mm.x;
  REQUIRE(g.spacing_mm.y == h);
  REQUIRE(g.spacing_mm.z == h);
  REQUIRE(pt.has_bone);
  INFO("voxel " << h << " mm");
  check_masks_and_distances(pt, defaults, stride);
  check_vertebrae(pt, defaults);
  check_force_image(pt, defaults);
}

}  // namespace

TEST_CASE("the phantom patient at 2 mm matches the closed-form geometry") {
  check_patient(patient_2mm(), Scene{}, 1);
}

TEST_CASE("the phantom patient at 1 mm matches the closed-form geometry") {
  // every second voxel along each axis (2.6 million) keeps the run short
  check_patient(patient_1mm(), Scene{}, 2);
}
