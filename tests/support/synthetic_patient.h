// Synthetic patients with closed-form skin and bone, for tests and benchmarks that must
// not wait for the preprocessing pipeline: every Patient member is filled, distances
// are computed analytically from signed distance functions, F by eq. 1 and grad F by
// central differences (as the prep pipeline does).
#pragma once

#include <algorithm>
#include <cmath>
#include <functional>
#include <memory>

#include "core/patient.h"
#include "core/scene.h"

namespace palpsim::test {

/// Eq. 1 parameters of the paper (rib cage values).
struct Eq1 {
  double alpha = 200.0 / 3.0;  // mm^2
  double beta = 2.0;           // mm
  double gamma = 1.0 / 60.0;   // 1
};

/// A signed distance (mm) at a physical point (mm): negative inside.
using Sdf = std::function<double(const Vec3&)>;

/// Builds a patient on an n^3 grid of `h_mm` voxels with origin (0, 0, 0) from the skin
/// and bone signed distances. Conventions of the prep pipeline: a voxel is body when its
/// centre is inside the skin; B is the distance to the nearest outside voxel centre,
/// which for a skin on the voxel boundary is -sdf + h/2; A is the distance to bone (0 in bone).
inline std::shared_ptr<Patient> make_patient(int n, double h_mm, const Sdf& skin, const Sdf& bone, const Eq1& eq = {}) {
  auto p = std::make_shared<Patient>();
  Grid g;
  g.size = {n, n, n};
  g.spacing_mm = {h_mm, h_mm, h_mm};
  p->grid = g;
  p->intensity = Volume<float>(g, -1000.f);
  p->body = Volume<std::uint8_t>(g, 0);
  p->bone = Volume<std::uint8_t>(g, 0);
  p->dist_bone_mm = Volume<float>(g, 0.f);
  p->dist_skin_mm = Volume<float>(g, 0.f);
  p->force = Volume<float>(g, 0.f);
  p->grad_force = Volume<Vec3f>(g, Vec3f{0, 0, 0});
  // masks and distances voxel by voxel
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        const Vec3 x = g.to_physical(Vec3{double(i), double(j), double(k)});
        const double ds = skin(x), db = bone(x);
        const bool in_body = ds < 0;
        const bool in_bone = in_body && db < 0;
        const std::size_t m = g.index(i, j, k);
        p->body.data[m] = in_body;
        p->bone.data[m] = in_bone;
        p->has_bone = p->has_bone || in_bone;
        p->intensity.data[m] = in_bone ? 700.f : (in_body ? 40.f : -1000.f);
        p->dist_bone_mm.data[m] = float(std::max(db, 0.0));
        p->dist_skin_mm.data[m] = in_body ? float(-ds + 0.5 * h_mm) : 0.f;
        p->force.data[m] = in_body ? float(eq.alpha / (eq.beta + p->dist_bone_mm.data[m]) + eq.gamma * p->dist_skin_mm.data[m]) : 0.f;
      }
  // grad F by central differences (one-sided at the border), in mm/mm
  auto f_at = [&](int i, int j, int k) { return double(p->force.at_clamped(i, j, k)); };
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        auto d = [&](int a0, int a1, int b0, int b1, int c0, int c1, int lo, int hi) {
          return (f_at(a1, b1, c1) - f_at(a0, b0, c0)) / (double(hi - lo) * h_mm);
        };
        const int il = std::max(i - 1, 0), ih = std::min(i + 1, n - 1);
        const int jl = std::max(j - 1, 0), jh = std::min(j + 1, n - 1);
        const int kl = std::max(k - 1, 0), kh = std::min(k + 1, n - 1);
        p->grad_force.at(i, j, k) = Vec3f{float(d(il, ih, j, j, k, k, il, ih)), float(d(i, i, jl, jh, k, k, jl, jh)),
                                          float(d(i, i, j, j, kl, kh, kl, kh))};
      }
  p->source = "synthetic";
  return p;
}

/// Distance (mm) from a point to an axis-aligned box [lo, hi]; negative inside (depth).
inline double box_sdf(const Vec3& x, const Vec3& lo, const Vec3& hi) {
  const Vec3 c = (lo + hi) * 0.5, e = (hi - lo) * 0.5;
  const Vec3 q{std::fabs(x.x - c.x) - e.x, std::fabs(x.y - c.y) - e.y, std::fabs(x.z - c.z) - e.z};
  const Vec3 qp{std::max(q.x, 0.0), std::max(q.y, 0.0), std::max(q.z, 0.0)};
  return norm(qp) + std::min(std::max(q.x, std::max(q.y, q.z)), 0.0);
}

/// The skin plane of slab_patient (mm): body below it (z smaller), outward normal +z.
constexpr double kSlabSkinZ = 39.5;

/// A 60 mm cube at 1 mm: a slab of tissue under the plane z = 39.5 mm (outward normal +z)
/// with a bone block [24.5, 35.5] x [24.5, 35.5] x [14.5, 25.5] mm (voxel centres 25..35, 15..25).
inline std::shared_ptr<Patient> slab_patient() {
  return make_patient(
      60, 1.0, [](const Vec3& x) { return x.z - kSlabSkinZ; },
      [](const Vec3& x) { return box_sdf(x, {24.5, 24.5, 14.5}, {35.5, 35.5, 25.5}); });
}

/// A point of slab_patient's skin over its bone block (x, y in mm): bone lies 14 mm under it.
constexpr double kSlabBoneX = 30, kSlabBoneY = 30;

/// `scene` deforming by the elastic model under a 5 mm fingertip, without friction: the
/// skin point is then a function of the tip, so tips pressing on past where bone holds the
/// press (deform.elastic.min_tissue_fraction) are one contact, which J already stands for.
inline Scene& elastic_without_friction(Scene& scene) {
  scene.haptics.friction = 0;
  scene.deform.relax_method = RelaxMethod::kElastic;
  scene.deform.grab_radius_mm = 5;
  return scene;
}

/// A 64 mm cube at 1 mm: a ball of tissue, radius 28 mm around (32, 32, 32), with a bone
/// ball of radius 8 mm at its centre.
inline std::shared_ptr<Patient> sphere_patient() {
  const Vec3 c{32, 32, 32};
  return make_patient(
      64, 1.0, [c](const Vec3& x) { return norm(x - c) - 28.0; }, [c](const Vec3& x) { return norm(x - c) - 8.0; });
}

}  // namespace palpsim::test
