// Small synthetic patients for the deformation tests and benchmarks: only the grid,
// intensity and bone mask are filled (all deformation reads), so these tests do not
// wait for the preprocessing pipeline.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "core/patient.h"
#include "deform/backend.h"

namespace palpsim::test {

/// Hounsfield values of the synthetic tissues.
constexpr float kAirHu = -1000.0f, kSoftHu = 40.0f, kBoneHu = 700.0f, kBoneThresholdHu = 200.0f;

/// A patient on the intensity volume's grid (moved in): bone = intensity above
/// kBoneThresholdHu. Deformation reads nothing else, so only those members are filled.
inline PatientPtr patient_from_intensity(Volume<float>&& intensity, const char* source) {
  auto p = std::make_shared<Patient>();
  p->grid = intensity.grid;
  p->intensity = std::move(intensity);
  p->bone = Volume<std::uint8_t>(p->grid);
  for (std::size_t e = 0; e < p->intensity.data.size(); ++e) {
    p->bone.data[e] = p->intensity.data[e] > kBoneThresholdHu ? 1 : 0;
    p->has_bone = p->has_bone || p->bone.data[e];
  }
  p->source = source;
  return p;
}

/// A patient of `size` voxels whose intensity is hu(i, j, k); bone = intensity above
/// kBoneThresholdHu. Spacing, origin and direction as given (mm).
inline PatientPtr make_patient(const Vec3i& size, const std::function<float(int, int, int)>& hu,
                               const Vec3& spacing_mm = {1, 1, 1}, const Vec3& origin_mm = {0, 0, 0}) {
  Grid g;
  g.size = size;
  g.spacing_mm = spacing_mm;
  g.origin_mm = origin_mm;
  Volume<float> v(g);
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j < size.y; ++j)
      for (int i = 0; i < size.x; ++i) v.at(i, j, k) = hu(i, j, k);
  return patient_from_intensity(std::move(v), "synthetic");
}

/// Soft tissue everywhere, with a gentle ramp so that J differs from I where tissue moves.
inline PatientPtr make_soft_patient(int n) {
  return make_patient({n, n, n}, [](int i, int j, int k) { return kSoftHu + 0.5f * i + 0.25f * j - 0.125f * k; });
}

/// The paper's Fig. 4 objects: a soft cube of edge `cube` in air, centred in an n^3
/// volume; with `bone_shell` > 0 the cube is wrapped in a bone shell that thick.
inline PatientPtr make_cube_patient(int n, int cube, int bone_shell) {
  const int lo = (n - cube) / 2, hi = lo + cube - 1;
  return make_patient({n, n, n}, [=](int i, int j, int k) {
    auto inside = [&](int m) { return i >= lo - m && i <= hi + m && j >= lo - m && j <= hi + m && k >= lo - m && k <= hi + m; };
    if (inside(0)) return kSoftHu + 2.0f * float((i + 2 * j + 3 * k) % 7);  // textured so J shows the motion
    if (bone_shell > 0 && inside(bone_shell)) return kBoneHu;
    return kAirHu;
  });
}

/// A torso-like volume (n^3, 1 mm): an elliptic soft-tissue body in air with a
/// bone "spine" cylinder and a bone "rib" slab, textured so J changes where tissue moves.
inline PatientPtr make_torso_patient(int n) {
  const double c = (n - 1) / 2.0;
  return make_patient({n, n, n}, [=](int i, int j, int k) {
    const double x = (i - c) / (0.45 * n), y = (j - c) / (0.35 * n);
    if (x * x + y * y > 1) return kAirHu;
    const double sx = i - c, sy = j - (c + 0.2 * n);
    if (sx * sx + sy * sy < (0.06 * n) * (0.06 * n)) return kBoneHu;                      // spine along k
    if (std::abs(j - (c - 0.2 * n)) < 2 && std::abs(i - c) > 0.15 * n && (k / 8) % 2 == 0) return kBoneHu;  // ribs
    return float(kSoftHu + 20.0 * std::sin(0.3 * i) * std::cos(0.2 * j) + 10.0 * std::sin(0.25 * k));
  });
}

/// A copy of `p` whose voxels `hot` hold `hu` outside the bone mask: far above the bone
/// threshold the material function is exactly 0 (relaxation holds them) while ChainMail,
/// which knows only the mask, moves them (what contrast or metal outside bone would do).
inline PatientPtr with_hot_voxels(const PatientPtr& p, const std::vector<Vec3i>& hot, float hu) {
  auto q = std::make_shared<Patient>(*p);
  for (const Vec3i& v : hot) {
    q->intensity.at(v.x, v.y, v.z) = hu;
    q->bone.data[q->grid.index(v.x, v.y, v.z)] = 0;
  }
  return q;
}

/// A copy of `p` with its body mask C filled: every voxel above -500 HU (air below), as
/// the tests of the multigrid prime need (deform::expected_skin_voxel reads C).
inline PatientPtr with_body_mask(const PatientPtr& p) {
  auto q = std::make_shared<Patient>(*p);
  q->body = Volume<std::uint8_t>(q->grid);
  for (std::size_t e = 0; e < q->intensity.data.size(); ++e) q->body.data[e] = q->intensity.data[e] > -500.0f ? 1 : 0;
  return q;
}

/// A copy of `p` with its body mask C (as with_body_mask) and the depth under the skin B
/// the elastic model reads for its skin layer: the distance (mm) from a body voxel's centre
/// to the nearest centre of a voxel of the grid outside the body, exact up to `reach_vox`
/// voxels along each axis and that window's least half-width (mm) beyond it (deeper than
/// any skin layer of a test).
inline PatientPtr with_skin(const PatientPtr& p, int reach_vox = 4) {
  auto q = std::const_pointer_cast<Patient>(with_body_mask(p));
  const Grid& g = q->grid;
  const Vec3& h = g.spacing_mm;
  const float beyond = float(reach_vox * std::min({h.x, h.y, h.z}));
  q->dist_skin_mm = Volume<float>(g, 0.0f);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        if (!q->body.at(i, j, k)) continue;
        float best = beyond;
        for (int c = std::max(k - reach_vox, 0); c <= std::min(k + reach_vox, g.size.z - 1); ++c)
          for (int b = std::max(j - reach_vox, 0); b <= std::min(j + reach_vox, g.size.y - 1); ++b)
            for (int a = std::max(i - reach_vox, 0); a <= std::min(i + reach_vox, g.size.x - 1); ++a)
              if (!q->body.at(a, b, c))
                best = std::min(best, float(norm(Vec3{(a - i) * h.x, (b - j) * h.y, (c - k) * h.z})));
        q->dist_skin_mm.at(i, j, k) = best;
      }
  return q;
}

/// The paper's ChainMail presets (voxel edge lengths).
inline DeformConfig preset_config(int preset) {
  DeformConfig c;
  c.bone_threshold = kBoneThresholdHu;
  c.settings.min_dist = preset == 1 ? 0.5 : 0.25;
  c.settings.max_dist = 1.5;
  c.settings.max_sheer = preset == 1 ? 0.5 : 1.0;
  c.settings.backend = DeformBackendChoice::kCpu;
  // the tests and the deform bench check the inversion that resolves every voxel (off in scenes)
  c.settings.invert_search = true;
  return c;
}

/// A contact on a 1 mm grid at the origin: grab voxel g and move it by d voxels.
inline DeformContact voxel_contact(const Vec3i& g, const Vec3& d) {
  return {Vec3(g.x, g.y, g.z), Vec3(g.x + d.x, g.y + d.y, g.z + d.z)};
}

/// A press whose tip moves within one voxel (the VOI, centred on the tip voxel, stays),
/// then a voxel on (the VOI moves), then back, on make_torso_patient(64) with multigrid
/// relaxation at VOI 40: the multigrid reuse tests (cpu and gpu). `solves` is what
/// DeformStats::relax_solves must say at each contact (G is kept for the last VOI only).
struct ReusePress {
  DeformConfig cfg;
  std::vector<DeformContact> contacts;
  std::vector<int> solves;
};

inline ReusePress reuse_press() {
  ReusePress r;
  r.cfg = preset_config(1);
  r.cfg.settings.voi_edge = 40;
  r.cfg.settings.relax_method = RelaxMethod::kMultigrid;
  r.cfg.settings.relax_warm_cycles = 0;  // a new VOI solves from zero, as the fresh solve it is compared with
  r.cfg.voi_hold = false;                // the VOI follows the tip every step (these tests move it)
  const Vec3i g{32, 10, 32};
  for (const Vec3& d : {Vec3{2, 7, -3}, Vec3{2.2, 7.3, -3.1}, Vec3{1.9, 6.8, -2.8}, Vec3{3, 7, -3}, Vec3{2.1, 7.1, -3}})
    r.contacts.push_back(voxel_contact(g, d));
  r.solves = {1, 0, 0, 1, 1};
  return r;
}

/// Paths a tip takes a voxel or more a step on make_torso_patient(64) with multigrid
/// relaxation at VOI 40, so that every step after the first has another VOI or grabbed
/// element: the multigrid warm-start tests (cpu and gpu). Every step after the first
/// starts from the last unit response (deform.relax_warm_cycles), however far it lies.
struct WarmPath {
  const char* name;
  std::vector<DeformContact> contacts;
};

inline std::vector<WarmPath> warm_paths() {
  std::vector<WarmPath> paths(6);
  // pressing into the back a voxel a step: the grabbed element stays, the VOI moves along j
  paths[0].name = "pressing a voxel a step";
  for (int s = 0; s < 6; ++s) paths[0].contacts.push_back(voxel_contact({32, 10, 32}, {2, 3.0 + s, -3}));
  // sliding along the back's skin (k) a voxel a step: grabbed element and VOI move together
  paths[1].name = "sliding along the skin";
  for (int s = 0; s < 6; ++s) paths[1].contacts.push_back(voxel_contact({32, 10, 28 + s}, {2, 7, -3}));
  // pressing 4 voxels a step (a fast tip: the VOI moves 4 voxels)
  paths[2].name = "pressing 4 voxels a step";
  for (int s = 0; s < 3; ++s) paths[2].contacts.push_back(voxel_contact({32, 10, 32}, {2, 1.0 + 4 * s, -3}));
  // sliding 2 voxels a step, the farthest a warm start takes
  paths[3].name = "sliding 2 voxels a step";
  for (int s = 0; s < 6; ++s) paths[3].contacts.push_back(voxel_contact({32, 10, 20 + 2 * s}, {2, 7, -3}));
  // the grabbed element 2 voxels deeper each step, towards the spine
  paths[4].name = "grabbed 2 voxels deeper a step";
  for (int s = 0; s < 6; ++s) paths[4].contacts.push_back(voxel_contact({32, 12 + 2 * s, 32}, {2, 4, -3}));
  // jumps across the torso (10-30 voxels): the last response, from another place, is
  // still the start (0.28-0.72% from the steady state after 2 warm steps, measured)
  paths[5].name = "jumping across the torso";
  for (const Vec3i& g : {Vec3i{32, 10, 32}, Vec3i{32, 24, 32}, Vec3i{20, 30, 20}, Vec3i{44, 36, 40}, Vec3i{12, 30, 50}})
    paths[5].contacts.push_back(voxel_contact(g, {2, 4, -3}));
  return paths;
}

/// Every contact of reuse_press() and warm_paths() in a row, with reuse_press()'s
/// configuration and the default warm start: reused, warm and fresh multigrid solves,
/// for the tests of steps that leave ChainMail out (cpu and gpu).
struct MultigridSteps {
  DeformConfig cfg;
  std::vector<DeformContact> contacts;
};

inline MultigridSteps multigrid_steps() {
  MultigridSteps m;
  m.cfg = reuse_press().cfg;
  m.cfg.settings.relax_warm_cycles = DeformSettings{}.relax_warm_cycles;
  m.contacts = reuse_press().contacts;
  for (const WarmPath& path : warm_paths()) m.contacts.insert(m.contacts.end(), path.contacts.begin(), path.contacts.end());
  return m;
}

/// Steps `skip` (bound with DeformConfig::skip_chainmail) and `full` (without) with
/// contact `c` and says what differs, "" when nothing: `skip` must have left ChainMail out
/// (no sweep, no move, converged) and `full` run it, with the same relaxation counts,
/// displacement, J and inversion residual to the bit.
inline std::string step_without_chainmail_differs(DeformBackend& skip, DeformBackend& full, const DeformContact& c) {
  const DeformStats a = skip.step(c), b = full.step(c);
  if (!a.chainmail.skipped || a.chainmail.sweeps != 0 || a.chainmail.moved != 0 || !a.chainmail.converged)
    return "ChainMail was not left out";
  if (b.chainmail.skipped || b.chainmail.moved <= 0) return "ChainMail did not run without skip_chainmail";
  if (a.relax_solves != b.relax_solves || a.relax_warm != b.relax_warm) return "relaxation counts differ";
  if (skip.displacement() != full.displacement()) return "displacements differ";
  const long long n = a.chainmail.voi.count();
  if (!std::equal(skip.deformed_brick(), skip.deformed_brick() + n, full.deformed_brick())) return "J differs";
  if (a.invert_residual_vox != b.invert_residual_vox) return "inversion residuals differ";
  return "";
}

/// The Table 1 press of `palpsim-bench deform`: near the middle of the volume, 10 mm
/// along -j (anterior), so that every VOI size up to 128 fits unclipped; X is the first
/// voxel from the centre towards -j with soft tissue (no bone, no gas) 3 voxels around.
inline DeformContact table1_press(const Patient& p) {
  const Grid& g = p.grid;
  const int i = g.size.x / 2, k = g.size.z / 2;
  int j = g.size.y / 2;
  auto soft_around = [&](int jj) {
    for (int c = -3; c <= 3; ++c)
      for (int b = -3; b <= 3; ++b)
        for (int a = -3; a <= 3; ++a) {
          const float v = p.intensity.at(i + a, jj + b, k + c);
          if (p.bone.at(i + a, jj + b, k + c) || v < -200.0f) return false;
        }
    return true;
  };
  while (j > g.size.y / 2 - 40 && !soft_around(j)) --j;
  const Vec3 X = g.to_physical({double(i), double(j), double(k)});
  return {X, X - g.axes_to_physical({0, 10.0, 0})};
}

/// One of the random pushes of issue 8, section 4 on make_torso_patient(48): a soft
/// grabbed voxel inside the body, moved 2-11 voxels in a random direction, with preset
/// p1 or p2 and a VOI edge of 16, 32 or 48 (relaxation 20, inversion 8).
struct RandomPush {
  DeformContact contact;
  DeformConfig config;
};

/// `count` random pushes on `torso` (make_torso_patient(48)), the same for a given seed.
inline std::vector<RandomPush> random_pushes(const Patient& torso, int count, unsigned seed) {
  std::uint64_t state = seed * 6364136223846793005ull + 1442695040888963407ull;
  auto uniform = [&](double lo, double hi) {
    // a 64-bit LCG: the pushes must not depend on the standard library's distributions
    state = state * 6364136223846793005ull + 1442695040888963407ull;
    return lo + (hi - lo) * double(state >> 11) * (1.0 / 9007199254740992.0);
  };
  const Vec3i n = torso.grid.size;
  std::vector<RandomPush> out;
  while (int(out.size()) < count) {
    const Vec3i g{int(uniform(4, n.x - 4)), int(uniform(4, n.y - 4)), int(uniform(4, n.z - 4))};
    if (torso.bone.at(g.x, g.y, g.z) || torso.intensity.at(g.x, g.y, g.z) <= kAirHu) continue;
    Vec3 d{uniform(-1, 1), uniform(-1, 1), uniform(-1, 1)};
    const double len = std::sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
    if (len < 0.2 || len > 1) continue;
    d = d * (uniform(2, 11) / len);
    const int i = int(out.size());
    DeformConfig cfg = preset_config(1 + i % 2);
    cfg.settings.voi_edge = 16 * (1 + (i / 2) % 3);
    cfg.settings.relax_iterations = 20;
    cfg.settings.invert_iterations = 8;
    out.push_back({voxel_contact(g, d), cfg});
  }
  return out;
}

}  // namespace palpsim::test

namespace palpsim::test {

/// The largest violation (voxel) of the ChainMail restrictions over all pairs of
/// face neighbours in the VOI that are both soft tissue (bone enforces nothing).
inline double max_restriction_violation(const Patient& p, const Voi& voi, const std::vector<Vec3f>& u,
                                        const DeformSettings& s) {
  double worst = 0;
  auto bone = [&](int i, int j, int k) { return p.bone.at(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k) != 0; };
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        if (bone(i, j, k)) continue;
        const Vec3f& ue = u[voi.index(i, j, k)];
        for (int a = 0; a < 3; ++a) {
          // the neighbour above along axis a
          Vec3i n{i, j, k};
          n[a] += 1;
          if (!voi.contains(n.x, n.y, n.z) || bone(n.x, n.y, n.z)) continue;
          const Vec3f& un = u[voi.index(n.x, n.y, n.z)];
          const double dist = 1.0 + double(un[a]) - double(ue[a]);
          worst = std::max({worst, s.min_dist - dist, dist - s.max_dist});
          for (int b = 0; b < 3; ++b)
            if (b != a) worst = std::max(worst, std::fabs(double(un[b]) - double(ue[b])) - s.max_sheer);
        }
      }
  return worst;
}

/// The smallest determinant of I + grad u, the trilinear displacement field's Jacobian
/// (positive where the deformation keeps orientation: no fold), over every cell of the
/// VOI whose eight voxels are soft tissue (bone enforces no restriction, so soft tissue
/// may pass it): deform::cell_min_det, the corners and centre of each cell.
inline double min_jacobian_det(const Patient& p, const Voi& voi, const std::vector<Vec3f>& u) {
  auto load_u = [&](int i, int j, int k) { return voi.contains(i, j, k) ? u[voi.index(i, j, k)] : Vec3f{0, 0, 0}; };
  auto soft = [&](int i, int j, int k) { return p.bone.at(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k) == 0; };
  double worst = std::numeric_limits<double>::infinity();
  for (int k = 0; k + 1 < voi.size.z; ++k)
    for (int j = 0; j + 1 < voi.size.y; ++j)
      for (int i = 0; i + 1 < voi.size.x; ++i)
        if (deform::untangle_cell_soft(soft, i, j, k)) worst = std::min(worst, double(deform::cell_min_det(load_u, i, j, k)));
  return worst;
}

/// The largest difference of any component of two fields on the same VOI (voxel).
inline float max_abs_diff(const std::vector<Vec3f>& ua, const std::vector<Vec3f>& ub) {
  float worst = 0;
  for (std::size_t e = 0; e < ua.size(); ++e)
    worst = std::max({worst, std::fabs(ua[e].x - ub[e].x), std::fabs(ua[e].y - ub[e].y), std::fabs(ua[e].z - ub[e].z)});
  return worst;
}

/// Number of bone voxels in the VOI whose displacement is not exactly zero.
inline long long moved_bone_count(const Patient& p, const Voi& voi, const std::vector<Vec3f>& u) {
  long long n = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i)
        if (p.bone.at(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k) && u[voi.index(i, j, k)] != Vec3f(0, 0, 0)) ++n;
  return n;
}

/// Number of nodes on the VOI's faces whose displacement is not exactly zero (the elastic
/// model holds them at rest).
inline long long moved_on_faces(const Voi& voi, const std::vector<Vec3f>& u) {
  long long n = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const bool face = i == 0 || j == 0 || k == 0 || i + 1 == voi.size.x || j + 1 == voi.size.y || k + 1 == voi.size.z;
        n += face && !(u[std::size_t(voi.index(i, j, k))] == Vec3f{0, 0, 0});
      }
  return n;
}

/// Presses for the relaxation's reach (deform::relax_reach: only the elements ChainMail's
/// wave and the steps since can have moved are updated): on make_torso_patient(64), a
/// shallow and a deep press (preset p1 and p2), one at the volume's border (a clipped
/// VOI) and one whose grabbed element sits next to the spine; each names its settings.
struct ReachPress {
  const char* name;
  DeformContact contact;
  DeformConfig cfg;
};

inline std::vector<ReachPress> reach_presses() {
  std::vector<ReachPress> v;
  auto add = [&](const char* name, const Vec3i& g, const Vec3& d, int preset, int voi, int iterations) {
    DeformConfig cfg = preset_config(preset);
    cfg.settings.voi_edge = voi;
    cfg.settings.relax_iterations = iterations;
    v.push_back({name, voxel_contact(g, d), cfg});
  };
  add("shallow, p1", {32, 10, 32}, {0.5, 2.5, 0.3}, 1, 48, 20);
  add("deep, p2", {32, 10, 32}, {1.2, 14.0, -2.0}, 2, 48, 40);
  add("clipped at the border", {32, 10, 1}, {2.0, 6.0, -1.5}, 1, 40, 20);
  add("next to the spine", {32, 36, 32}, {3.0, 4.0, 0.0}, 1, 32, 80);
  return v;
}

/// Relaxes `b`'s ChainMail of contact `c` with the first bone element of its VOI displaced
/// by hand: a held element that moved, so multigrid solves each component (3 solves) and
/// drops its unit response. Returns that element's VOI-local index (-1: the VOI has no bone).
inline long long relax_with_bone_moved(DeformBackend& b, const Patient& p, const DeformContact& c) {
  b.chainmail(c);
  std::vector<Vec3f> u = b.displacement();
  const Voi v = b.voi();
  for (long long e = 0; e < v.count(); ++e) {
    const int i = int(e % v.size.x), j = int(e / v.size.x % v.size.y), k = int(e / (v.size.x * v.size.y));
    if (!p.bone.data[p.grid.index(v.lo.x + i, v.lo.y + j, v.lo.z + k)]) continue;
    u[std::size_t(e)] = Vec3f{0.5f, -0.25f, 1.0f};
    b.set_displacement(u);
    b.relax();
    return e;
  }
  return -1;
}

/// Number of voxels outside the VOI where J differs from I (must be 0).
inline long long changed_outside_voi(const Patient& p, const Voi& voi, const Volume<float>& J) {
  long long n = 0;
  const Grid& g = p.grid;
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        const bool in = voi.contains(i - voi.lo.x, j - voi.lo.y, k - voi.lo.z);
        if (!in && J.at(i, j, k) != p.intensity.at(i, j, k)) ++n;
      }
  return n;
}

/// Sum over face-neighbour pairs inside the VOI of |u_e - u_n|^2 (voxel^2): how rough the field is.
inline double roughness(const Voi& voi, const std::vector<Vec3f>& u) {
  double e = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i)
        for (int a = 0; a < 3; ++a) {
          Vec3i n{i, j, k};
          n[a] += 1;
          if (!voi.contains(n.x, n.y, n.z)) continue;
          const Vec3f d = u[voi.index(n.x, n.y, n.z)] - u[voi.index(i, j, k)];
          e += double(d.x) * d.x + double(d.y) * d.y + double(d.z) * d.z;
        }
  return e;
}

/// RMS of |sum of six neighbours - 6 u| (voxel) over the VOI's soft elements other than
/// the grabbed one (patient index `grabbed`), u = 0 outside the VOI: the residual of
/// relaxation's steady state, which relaxation reduces and multigrid drives to rounding.
inline double laplacian_rms(const Patient& p, const Voi& voi, const Vec3i& grabbed, const std::vector<Vec3f>& u) {
  const Vec3i g = grabbed - voi.lo;
  double sum = 0;
  long long n = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        if (p.bone.at(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k) || Vec3i{i, j, k} == g) continue;
        Vec3f l = u[voi.index(i, j, k)] * -6.0f;
        for (int q = 0; q < 6; ++q) {
          const Vec3i m = Vec3i{i, j, k} + deform::neighbour_offset(q);
          if (voi.contains(m.x, m.y, m.z)) l += u[voi.index(m.x, m.y, m.z)];
        }
        sum += double(l.x) * l.x + double(l.y) * l.y + double(l.z) * l.z;
        ++n;
      }
  return n ? std::sqrt(sum / double(n)) : 0;
}

/// RMS of |a - b| over two fields on the same VOI (voxel).
inline double rms_distance(const std::vector<Vec3f>& a, const std::vector<Vec3f>& b) {
  double sum = 0;
  for (std::size_t e = 0; e < a.size(); ++e) {
    const Vec3f v = a[e] - b[e];
    sum += double(v.x) * v.x + double(v.y) * v.y + double(v.z) * v.z;
  }
  return a.empty() ? 0 : std::sqrt(sum / double(a.size()));
}

/// Isotropy of a displacement field around the grabbed element (VOI-local `g`): the mean
/// |u| at distance `d` voxel along the six axes against the mean along the eight body
/// diagonals (trilinear, u = 0 outside the VOI), the smaller over the larger; 1 is
/// isotropic, and ChainMail's diamond (|u| falls with the L1 distance) gives less.
inline double isotropy(const Voi& voi, const std::vector<Vec3f>& u, const Vec3i& g, double d) {
  auto load = [&](int i, int j, int k) { return voi.contains(i, j, k) ? u[voi.index(i, j, k)] : Vec3f{0, 0, 0}; };
  auto mag = [&](double x, double y, double z) {
    const Vec3f v = deform::trilinear<Vec3f>(load, Vec3f(float(g.x + x), float(g.y + y), float(g.z + z)));
    return std::sqrt(double(v.x) * v.x + double(v.y) * v.y + double(v.z) * v.z);
  };
  double axis = 0, diag = 0;
  for (int a = 0; a < 3; ++a)
    for (int s = -1; s <= 1; s += 2) axis += mag(a == 0 ? s * d : 0, a == 1 ? s * d : 0, a == 2 ? s * d : 0) / 6;
  const double c = d / std::sqrt(3.0);
  for (int sx = -1; sx <= 1; sx += 2)
    for (int sy = -1; sy <= 1; sy += 2)
      for (int sz = -1; sz <= 1; sz += 2) diag += mag(sx * c, sy * c, sz * c) / 8;
  const double hi = std::max(axis, diag);
  return hi > 0 ? std::min(axis, diag) / hi : 1;
}

}  // namespace palpsim::test
