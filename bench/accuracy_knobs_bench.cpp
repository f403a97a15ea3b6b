// palpsim-bench accuracy: every knob against references (a)-(d), the study behind
// bench/results/accuracy.md (bench/accuracy_report.py writes the report).
#include <stdlib.h>

#include <algorithm>
#include <iterator>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "bench/accuracy_press.h"
#include "bench/boussinesq.h"
#include "bench/deform_accuracy.h"
#include "bench/deform_runs.h"
#include "core/error.h"
#include "bench/stats.h"
#include "deform/approach.h"
#include "deform/backend.h"
#include "deform/deform_math.h"
#include "haptics/force_model.h"
#include "net/scene_io.h"
#include "prep/phantom.h"
#include "prep/prepare.h"
#include "tests/support/deform_fixtures.h"
#include "tests/support/phantom_press.h"

// (a) the model's own converged solution: the base with the row's knob at its converged
//     value (relaxation 400, inversion 64, VOI 160), as `deform --accuracy` does;
// (b) Boussinesq's half-space field and the field's isotropy, on a homogeneous block;
// (c) linear-elastic FEM of the phantom press on the base VOI (bench/accuracy_fem.py);
// (d) the force model against eq. 1-2 in double on the phantom's closed-form geometry.

namespace palpsim::bench {
namespace {

// a JSON number (null for a non-finite value)
std::string num(double v) { return json_number(v); }

// the relaxation methods the study runs, each with its iteration (or cycle) counts;
// the relaxation methods and the settings of each that the report times: the paper's
// explicit diffusion (iterations) and the multigrid steady-state solver (steps)
struct RelaxMethod {
  std::string name;
  std::vector<int> iterations;
};
// "multigrid" solves every step from zero (DeformConfig::relax_reuse false: the cost of a
// new VOI or grabbed element with deform.relax_warm_cycles 0); "multigrid warm" reaches the
// press a voxel a step, so every timed step has a new VOI and starts from the last unit
// response (deform.relax_warm_cycles, the settings; relax_cycles 4 for the first solve);
// "multigrid reused" repeats the press, so every timed step reuses the unit response (the
// cost while the tip stays in its voxel); "multigrid primed" is a session's first step, on
// the press, after the prime the server runs while the tip hovers 5 mm above X (a new
// engine each repetition; steps: deform.relax_warm_cycles)
const std::vector<RelaxMethod> kRelaxMethods = {
    {"diffusion", {0, 5, 10, 20, 40, 80, 160, 400}},
    {"multigrid", {1, 2, 3, 4, 5, 8}},
    {"multigrid warm", {1, 2, 3}},
    {"multigrid reused", {4}},  // the default relax_cycles
    {"multigrid primed", {1}},  // the default relax_warm_cycles
};

// the methods whose timed steps are a session's first, primed (run_first_contacts)
bool primes(const std::string& method) { return method == "multigrid primed"; }

// the methods whose timed steps reach the press a voxel at a time (pressing())
bool moves_tip(const std::string& method) { return method == "multigrid warm"; }

// sets relaxation method `method` with `n` iterations (diffusion) or steps (multigrid)
void apply_relax_method(DeformConfig& cfg, const std::string& method, int n) {
  if (method == "diffusion") {
    cfg.settings.relax_method = palpsim::RelaxMethod::kExplicit;
    cfg.settings.relax_iterations = n;
  } else if (method == "multigrid" || method == "multigrid reused") {
    cfg.settings.relax_method = palpsim::RelaxMethod::kMultigrid;
    cfg.settings.relax_cycles = n;
    cfg.relax_reuse = method == "multigrid reused";
  } else if (method == "multigrid warm" || method == "multigrid primed") {
    cfg.settings.relax_method = palpsim::RelaxMethod::kMultigrid;
    cfg.settings.relax_cycles = DeformSettings{}.relax_cycles;
    cfg.settings.relax_warm_cycles = n;
    cfg.relax_reuse = true;
    cfg.voi_hold = !moves_tip(method);  // warm: every step another VOI, what a warm start costs
  } else {
    throw Error("accuracy: relaxation method '" + method + "' is not in this build");
  }
}

// reference (a) of relaxation: the steady state both methods head for, solved by 20
// multigrid steps (each cuts the distance 3-10x: 20 leave it below float rounding)
constexpr int kRefMultigridSteps = 20;

// reference (a): the converged value of each knob (the other knobs at the base)
constexpr int kRefInvertIterations = 64, kRefVoiEdge = 160;
// Poisson's ratio of references (b) and (c): nearly incompressible soft tissue
constexpr double kNu = 0.45;
// Young's modulus of reference (c) (kPa): scales only the reaction force of a displacement-driven press
constexpr double kEKpa = 10.0;
// fields are compared from this distance to the grabbed element on (voxel): the point
// load's singularity and ChainMail's grabbed element are not fields
constexpr double kNearFieldVox = 3.0;

// one setting of one knob: its row label and configuration
struct Setting {
  std::string knob, label;
  DeformConfig cfg;
  Stage stage;
};

// one knob's settings, timed round-robin, and its reference (a): the base with the knob
// at its converged value (none for the ChainMail preset: another preset is another model)
struct Group {
  std::vector<Setting> settings;
  bool has_ref = false;
  DeformConfig ref;
  bool pressing = false;  // timed steps reach the press a voxel at a time (moves_tip)
  bool primed = false;    // timed steps are a new session's first, after a prime (primes)
};

// the errors of one row against the references (NaN where not computed)
struct Errors {
  double a_u_pct = NAN, a_u_rms_vox = NAN, a_J_pct = NAN, a_J_rms_hu = NAN;
  double b_shape_pct = NAN, b_isotropy_pct = NAN, b_ratio6 = NAN;
  double c_u_pct = NAN, c_corr = NAN;
};

// reference (a) of one knob on one backend and what the errors are relative to
struct RefA {
  Voi voi;
  std::vector<Vec3f> u;
  std::vector<float> J, I;  // J and the undeformed image on the reference VOI (HU)
  double u_rms = 0, change_rms_hu = 0;
};

// J of a run carried onto the reference VOI: I outside the run's own VOI
std::vector<float> J_on(const Patient& p, const Voi& target, const Voi& voi, const std::vector<float>& J) {
  std::vector<float> on(std::size_t(target.count()));
  for (int k = 0; k < target.size.z; ++k)
    for (int j = 0; j < target.size.y; ++j)
      for (int i = 0; i < target.size.x; ++i) {
        const Vec3i g = target.lo + Vec3i{i, j, k}, l = g - voi.lo;
        on[target.index(i, j, k)] = voi.contains(l.x, l.y, l.z) ? J[voi.index(l.x, l.y, l.z)] : p.intensity.at(g.x, g.y, g.z);
      }
  return on;
}

// the homogeneous block of reference (b): soft tissue on n^3 voxels of 1 mm, pressed at
// the centre of its +y face by kBlockPressVox into the block
constexpr int kBlockN = 64;
constexpr double kBlockPressVox = 6.0;

// |u| of the block's face layer (j = n - 1) at (i, k), bilinear between voxels (voxel)
double face_magnitude(const Voi& voi, const std::vector<Vec3f>& u, double i, double k) {
  const int j = kBlockN - 1 - voi.lo.y, i0 = int(std::floor(i)), k0 = int(std::floor(k));
  const double fi = i - i0, fk = k - k0;
  Vec3 acc{0, 0, 0};
  for (int di = 0; di < 2; ++di)
    for (int dk = 0; dk < 2; ++dk) {
      const Vec3i l = Vec3i{i0 + di, j + voi.lo.y, k0 + dk} - voi.lo;
      if (!voi.contains(l.x, l.y, l.z)) continue;
      const Vec3f v = u[voi.index(l.x, l.y, l.z)];
      const double w = (di ? fi : 1 - fi) * (dk ? fk : 1 - fk);
      acc += Vec3{v.x * w, v.y * w, v.z * w};
    }
  return norm(acc);
}

// reference (b) errors of one block field: Boussinesq shape error (%) after the
// least-squares scale over kNearFieldVox <= R <= 12 voxel, and isotropy on the face
void block_errors(const Voi& voi, const std::vector<Vec3f>& u, Errors& e) {
  const double c = kBlockN / 2, top = kBlockN - 1;
  // gather model (radial, normal, tangential) and Boussinesq (radial, normal) per voxel
  std::vector<std::array<double, 5>> pts;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const Vec3i g = voi.lo + Vec3i{i, j, k};
        const double dx = g.x - c, dz = g.z - c, depth = top - g.y, r = std::hypot(dx, dz);
        const double R = std::hypot(r, depth);
        if (R < kNearFieldVox || R > 12) continue;
        const Vec3f v = u[voi.index(i, j, k)];
        const double rad = r > 0 ? (v.x * dx + v.z * dz) / r : 0, tan = r > 0 ? (v.z * dx - v.x * dz) / r : std::hypot(v.x, v.z);
        const BoussinesqU b = boussinesq(r, depth, kNu);
        pts.push_back({rad, -double(v.y), tan, b.radial, b.normal});
      }
  double mb = 0, bb = 0;
  for (const auto& p : pts) {
    mb += p[0] * p[3] + p[1] * p[4];
    bb += p[3] * p[3] + p[4] * p[4];
  }
  const double s = bb > 0 ? mb / bb : 0;
  double err = 0;
  for (const auto& p : pts) err += (p[0] - s * p[3]) * (p[0] - s * p[3]) + (p[1] - s * p[4]) * (p[1] - s * p[4]) + p[2] * p[2];
  e.b_shape_pct = s > 0 ? 100 * std::sqrt(err / (s * s * bb)) : NAN;
  // isotropy: |u| at distance r along +i against along the (+i, +k) diagonal, on the face
  double worst = 0;
  for (double r : {4.0, 6.0, 8.0}) {
    const double axis = face_magnitude(voi, u, c + r, c), diag = face_magnitude(voi, u, c + r / M_SQRT2, c + r / M_SQRT2);
    const double ratio = axis > 0 ? diag / axis : NAN;
    if (r == 6.0) e.b_ratio6 = ratio;
    worst = std::max(worst, std::fabs(ratio - 1));
  }
  e.b_isotropy_pct = 100 * worst;
}

// reference (c): the FEM field on the base VOI and which voxels it is compared on
struct RefC {
  Voi voi;
  std::vector<Vec3f> u;
  std::vector<bool> use;  // soft tissue, on the mesh, off the VOI's faces, >= kNearFieldVox from the grabbed element
  std::string stats_json = "null";
  bool ok = false;
};

// relative RMS error (%) and correlation of `u` against reference (c)
void fem_errors(const RefC& c, const Voi& voi, const std::vector<Vec3f>& u, Errors& e) {
  const std::vector<Vec3f> on = field_on(c.voi, voi, u, false);
  double num2 = 0, den2 = 0, sa = 0, sb = 0, saa = 0, sbb = 0, sab = 0, n = 0;
  for (std::size_t v = 0; v < on.size(); ++v) {
    if (!c.use[v]) continue;
    for (int q = 0; q < 3; ++q) {
      const double a = on[v][q], b = c.u[v][q];
      num2 += (a - b) * (a - b);
      den2 += b * b;
      sa += a, sb += b, saa += a * a, sbb += b * b, sab += a * b, n += 1;
    }
  }
  e.c_u_pct = den2 > 0 ? 100 * std::sqrt(num2 / den2) : NAN;
  const double cov = sab - sa * sb / n, va = saa - sa * sa / n, vb = sbb - sb * sb / n;
  e.c_corr = va > 0 && vb > 0 ? cov / std::sqrt(va * vb) : NAN;
}

// reference (c): exports the base press's VOI, solves it with bench/accuracy_fem.py, reads the field
RefC solve_fem(const std::string& python, const Patient& p, const Voi& voi, const Vec3i& grabbed, const Vec3f& grabbed_u,
               const std::string& work_dir) {
  RefC c;
  c.voi = voi;
  const std::string base = work_dir + "/fem-press";
  {
    std::ofstream h(base + ".json");
    h << "{\"size\": [" << voi.size.x << ", " << voi.size.y << ", " << voi.size.z << "], \"grabbed\": ["
      << grabbed.x - voi.lo.x << ", " << grabbed.y - voi.lo.y << ", " << grabbed.z - voi.lo.z << "], \"grabbed_u\": ["
      << num(grabbed_u.x) << ", " << num(grabbed_u.y) << ", " << num(grabbed_u.z) << "], \"nu\": " << num(kNu)
      << ", \"E_kpa\": " << num(kEKpa) << "}\n";
    // labels: 0 air (below -500 HU: outside air and bowel gas), 1 soft tissue, 2 bone (the bone mask)
    std::vector<std::uint8_t> labels(std::size_t(voi.count()));
    for (int k = 0; k < voi.size.z; ++k)
      for (int j = 0; j < voi.size.y; ++j)
        for (int i = 0; i < voi.size.x; ++i) {
          const Vec3i g = voi.lo + Vec3i{i, j, k};
          labels[voi.index(i, j, k)] = p.bone.at(g.x, g.y, g.z) ? 2 : (p.intensity.at(g.x, g.y, g.z) < -500 ? 0 : 1);
        }
    std::ofstream f(base + ".labels.u8", std::ios::binary);
    f.write(reinterpret_cast<const char*>(labels.data()), std::streamsize(labels.size()));
    if (!f || !h) throw Error("accuracy: cannot write the FEM input under " + work_dir);
  }
  const std::string script = std::string(PALPSIM_SOURCE_DIR) + "/bench/accuracy_fem.py";
  if (!run_command(sh_quote(python) + " " + sh_quote(script) + " " + sh_quote(base)))
    throw Error("accuracy: " + script + " failed (reference (c))");
  std::ifstream f(base + ".u_fem.f32", std::ios::binary);
  std::vector<float> raw(std::size_t(voi.count()) * 3);
  f.read(reinterpret_cast<char*>(raw.data()), std::streamsize(raw.size() * sizeof(float)));
  if (!f) throw Error("accuracy: cannot read " + base + ".u_fem.f32");
  std::ifstream st(base + ".fem.json");
  std::stringstream ss;
  ss << st.rdbuf();
  if (!ss.str().empty()) c.stats_json = ss.str();
  c.u.resize(std::size_t(voi.count()));
  c.use.assign(std::size_t(voi.count()), false);
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const long long e = voi.index(i, j, k);
        c.u[e] = {raw[3 * e], raw[3 * e + 1], raw[3 * e + 2]};
        const Vec3i g = voi.lo + Vec3i{i, j, k}, d = g - grabbed;
        const bool face = i == 0 || j == 0 || k == 0 || i == voi.size.x - 1 || j == voi.size.y - 1 || k == voi.size.z - 1;
        c.use[e] = std::isfinite(raw[3 * e]) && !face && !p.bone.at(g.x, g.y, g.z) &&
                   std::sqrt(double(d.x * d.x + d.y * d.y + d.z * d.z)) >= kNearFieldVox;
      }
  c.ok = true;
  return c;
}

// one deformation row of the report
struct ReportRow {
  std::string backend, knob, label;
  Spread step_ms, stage_ms;
  int reps = 0;
  long long moved = 0;
  Errors err;
};

// one force row: a sampling of the force model over one class of tip positions against (d)
struct ForceRow {
  std::string sampling, where;
  long long n = 0, contact_disagree = 0;
  double rms_n = 0, max_n = 0, rel_rms_pct = 0, ref_rms_n = 0, ns_per_pose = 0;
};

// eq. 1 in double on the phantom's closed-form geometry: A = distance to bone, B =
// depth under the skin + h/2 (the prep convention: B is measured to the nearest outside
// voxel centre), 0 outside the body
double force_ref(const PhantomGeometry& geo, const ForceImageSettings& eq, double h, const Vec3& p) {
  const double skin = geo.skin_signed_distance_mm(p);
  if (skin >= 0) return 0;
  const double A = std::max(geo.bone_signed_distance_mm(p), 0.0);
  return eq.alpha / (eq.beta + A) + eq.gamma * (-skin + 0.5 * h);
}

// eq. 2's spring force for a fresh proxy without friction or clamps: f = -k F grad F / |grad F| (N)
Vec3 spring_force(double k, double F, const Vec3& grad) {
  const double g = norm(grad);
  return g > 1e-4 ? grad * (-k * F / g) : Vec3{0, 0, 0};
}

// reference (d): the force model (trilinear, as it runs; and nearest-voxel sampling of
// the same float volumes) against eq. 1-2 in double on the closed-form geometry, grad F
// by central differences of h/8 (8x finer than the voxels)
std::vector<ForceRow> force_study(const Patient& p, const Scene& scene, bool quick) {
  const PhantomGeometry geo;
  const double h = p.grid.spacing_mm.x, k = scene.haptics.stiffness_n_per_mm;
  HapticsSettings hs = scene.haptics;
  hs.friction = 0;
  hs.max_force_n = 1e9;             // no magnitude clamp: the clamp would hide the model's error
  hs.max_force_rate_n_per_s = 1e15; // no rate clamp (a fresh proxy's first pose)
  // tips: a lattice over the back and sides, at depths from 1 mm outside to 40 mm under the
  // skin along -y (anterior); steps of 7.3 mm so tips fall between voxel centres
  const double step = quick ? 14.6 : 7.3;
  const double depths[] = {-1, 0.3, 1, 2, 3.5, 6, 10, 15, 22, 30, 40};
  std::vector<Vec3> tips;
  for (double x = -145; x <= 145; x += step)
    for (double z = -100; z <= 100; z += step) {
      double lo = 0, hi = 150;  // skin above (x, 0, z): the torso's axis is inside
      for (int it = 0; it < 60; ++it) ((geo.skin_signed_distance_mm({x, 0.5 * (lo + hi), z}) < 0) ? lo : hi) = 0.5 * (lo + hi);
      for (double d : depths) tips.push_back({x, lo - d, z});
    }
  // the reference at every tip
  std::vector<Vec3> f_ref(tips.size());
  std::vector<int> cls(tips.size());  // 0 outside, 1 near skin, 2 near bone, 3 interior, 4 in bone
  for (std::size_t t = 0; t < tips.size(); ++t) {
    const Vec3& x = tips[t];
    const double F = force_ref(geo, scene.force_image, h, x), d = h / 8;
    Vec3 grad;
    for (int a = 0; a < 3; ++a) {
      Vec3 e{0, 0, 0};
      e[a] = d;
      grad[a] = (force_ref(geo, scene.force_image, h, x + e) - force_ref(geo, scene.force_image, h, x - e)) / (2 * d);
    }
    const double skin = geo.skin_signed_distance_mm(x), bone = geo.bone_signed_distance_mm(x);
    f_ref[t] = skin < 0 ? spring_force(k, F, grad) : Vec3{0, 0, 0};
    cls[t] = skin >= 0 ? 0 : (bone < 0 ? 4 : (bone < 3 ? 2 : (-skin < 3 ? 1 : 3)));
  }
  // the model: trilinear (compute_force) and nearest voxel (the same float volumes)
  auto trilinear = [&](const Vec3& x, bool& contact) {
    ProxyState st;
    const ForceSample s = compute_force(p, hs, x, kNominalHapticPeriodS, st);
    contact = s.contact;
    return s.force_n;
  };
  auto nearest = [&](const Vec3& x, bool& contact) {
    const Vec3 ijk = p.grid.to_index(x);
    const int i = int(std::lround(ijk.x)), j = int(std::lround(ijk.y)), kk = int(std::lround(ijk.z));
    contact = within_grid(p.grid, ijk) && p.body.at(i, j, kk);
    if (!contact) return Vec3{0, 0, 0};
    const Vec3f g = p.grad_force.at(i, j, kk);
    return spring_force(k, p.force.at(i, j, kk), Vec3{g.x, g.y, g.z});
  };
  std::vector<ForceRow> rows;
  const char* names[] = {"all in soft tissue", "near skin (< 3 mm deep)", "near bone (outside it, < 3 mm)", "interior",
                         "in bone (the tip inside a bone)"};
  for (int m = 0; m < 2; ++m) {
    const std::string sampling = m == 0 ? "trilinear" : "nearest";
    std::vector<Vec3> f(tips.size());
    std::vector<bool> contact(tips.size());
    // errors: the model as it runs (compute_force) and the nearest-voxel variant
    for (std::size_t t = 0; t < tips.size(); ++t) {
      bool c = false;
      f[t] = m == 0 ? trilinear(tips[t], c) : nearest(tips[t], c);
      contact[t] = c;
    }
    // time of the sampling alone (F, grad F and the spring), without the skin-point search
    // that both samplings need: every tip once per pass, several passes, median pass
    std::vector<double> pass_ns;
    volatile double sink = 0;
    for (int rep = 0; rep < (quick ? 3 : 9); ++rep) {
      const auto t0 = std::chrono::steady_clock::now();
      for (const Vec3& x : tips) {
        bool c = false;
        if (m == 0) {
          const PatientSample s = sample_patient(p, x);
          sink = sink + spring_force(k, s.force_mm, s.grad_force).x;
        } else {
          sink = sink + nearest(x, c).x;
        }
      }
      pass_ns.push_back(std::chrono::duration<double, std::nano>(std::chrono::steady_clock::now() - t0).count() /
                        double(tips.size()));
    }
    const double ns = spread(pass_ns).median;
    for (int w = 0; w < 5; ++w) {
      ForceRow r;
      r.sampling = sampling;
      r.where = names[w];
      r.ns_per_pose = ns;
      double e2 = 0, r2 = 0;
      for (std::size_t t = 0; t < tips.size(); ++t) {
        // w = 0: every tip in soft tissue (the proxy's domain; a tip inside bone is a class of its own)
        if (cls[t] == 0 || (w == 0 && cls[t] == 4) || (w > 0 && cls[t] != w)) continue;
        if (!contact[t]) {
          ++r.contact_disagree;
          continue;
        }
        const double e = norm(f[t] - f_ref[t]);
        e2 += e * e;
        r2 += dot(f_ref[t], f_ref[t]);
        r.max_n = std::max(r.max_n, e);
        ++r.n;
      }
      // tips outside the body where the model reports contact also disagree
      for (std::size_t t = 0; t < tips.size(); ++t)
        if (w == 0 && cls[t] == 0 && contact[t]) ++r.contact_disagree;
      r.rms_n = r.n ? std::sqrt(e2 / double(r.n)) : 0;
      r.ref_rms_n = r.n ? std::sqrt(r2 / double(r.n)) : 0;
      r.rel_rms_pct = r2 > 0 ? 100 * std::sqrt(e2 / r2) : 0;
      rows.push_back(r);
    }
  }
  std::printf("force (d): %zu tips, %s\n", tips.size(), "rows follow");
  for (const ForceRow& r : rows)
    std::printf("  %-9s %-38s n %5lld  RMS %.4f N  max %.4f N  %.2f %% of RMS |f_ref| %.3f N  contact disagrees %lld  %.0f ns/pose\n",
                r.sampling.c_str(), r.where.c_str(), r.n, r.rms_n, r.max_n, r.rel_rms_pct, r.ref_rms_n, r.contact_disagree,
                r.ns_per_pose);
  return rows;
}

// the knobs' groups of settings, one knob at a time from `base`, each with its reference (a)
// where it has one (the ChainMail presets have none: another preset is another model)
std::vector<Group> knob_groups(const DeformConfig& base) {
  std::vector<Group> groups;
  for (const RelaxMethod& m : kRelaxMethods) {
    Group g;
    g.has_ref = true;
    g.ref = base;
    g.pressing = moves_tip(m.name);
    g.primed = primes(m.name);
    apply_relax_method(g.ref, "multigrid", kRefMultigridSteps);
    for (int n : m.iterations) {
      DeformConfig cfg = base;
      apply_relax_method(cfg, m.name, n);
      g.settings.push_back({"relaxation " + m.name, std::to_string(n), cfg, Stage::relax});
    }
    groups.push_back(g);
  }
  {
    Group g;
    g.has_ref = true;
    g.ref = base;
    g.ref.settings.invert_iterations = kRefInvertIterations;
    for (int n : {0, 1, 2, 4, 8, 16, 32}) {
      DeformConfig cfg = base;
      cfg.settings.invert_iterations = n;
      g.settings.push_back({"inversion iterations", std::to_string(n), cfg, Stage::invert});
    }
    groups.push_back(g);
  }
  {
    Group g;
    g.has_ref = true;
    g.ref = base;
    g.ref.settings.voi_edge = kRefVoiEdge;
    for (int n : {32, 48, 64, 96, 128}) {
      DeformConfig cfg = base;
      cfg.settings.voi_edge = n;
      g.settings.push_back({"VOI edge", std::to_string(n), cfg, Stage::total});
    }
    groups.push_back(g);
  }
  {
    Group g;
    for (int n : {1, 2}) {
      DeformConfig cfg = test::preset_config(n);
      cfg.settings.voi_edge = base.settings.voi_edge;
      cfg.settings.relax_iterations = base.settings.relax_iterations;
      cfg.settings.invert_iterations = base.settings.invert_iterations;
      g.settings.push_back({"ChainMail preset", "p" + std::to_string(n), cfg, Stage::total});
    }
    groups.push_back(g);
  }
  return groups;
}

// the study's JSON at json_path (a temporary name, then renamed)
void write_report_json(const std::string& json_path, const std::string& device, const ReportOptions& o,
                       const Patient& patient, const test::Press& press, const RefC& fem,
                       const std::vector<ReportRow>& rows, const std::vector<ForceRow>& force) {
  {
    std::ofstream f(json_path + ".tmp");
    f << json_run_header("accuracy", device, o.commit, o.quick) << "\n  \"storage\": \"fp32\",\n  \"phantom\": {\"voxel_mm\": " << num(o.voxel_mm) << ", \"size\": ["
      << patient.grid.size.x << ", " << patient.grid.size.y << ", " << patient.grid.size.z << "]},\n"
      << "  \"press\": {\"landmark\": " << json_str(press.landmark) << ", \"X_mm\": " << json_vec3(press.contact.skin_point_mm)
      << ", \"x_mm\": " << json_vec3(press.contact.tip_mm) << ", \"press_mm\": " << num(press.press_mm)
      << ", \"bone_depth_mm\": " << num(press.bone_depth_mm) << "},\n"
      << "  \"base\": {\"preset\": \"p1\", \"voi_edge\": 64, \"relax_method\": \"diffusion\", \"relax_iterations\": 20, "
         "\"invert_iterations\": 8},\n"
      << "  \"reference_a\": {\"relax_steady_state_multigrid_steps\": " << kRefMultigridSteps << ", \"invert_iterations\": "
      << kRefInvertIterations << ", \"voi_edge\": " << kRefVoiEdge << "},\n"
      << "  \"reference_b\": {\"block_voxels\": " << kBlockN << ", \"press_vox\": " << num(kBlockPressVox)
      << ", \"nu\": " << num(kNu) << ", \"r_min_vox\": " << num(kNearFieldVox) << ", \"r_max_vox\": 12},\n"
      << "  \"reference_c\": {\"nu\": " << num(kNu) << ", \"E_kpa\": " << num(kEKpa) << ", \"voi\": [" << fem.voi.size.x
      << ", " << fem.voi.size.y << ", " << fem.voi.size.z << "], \"computed\": " << (fem.ok ? "true" : "false")
      << ", \"solve\": " << fem.stats_json << "},\n"
      << "  \"rows\": [\n";
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const ReportRow& r = rows[i];
      const Errors& e = r.err;
      f << "    {\"backend\": " << json_str(r.backend) << ", \"knob\": " << json_str(r.knob) << ", \"setting\": "
        << json_str(r.label) << ", \"reps\": " << r.reps << ", \"moved\": " << r.moved << ", \"step\": "
        << json_spread(r.step_ms) << ", \"stage\": " << json_spread(r.stage_ms) << ", \"errors\": {\"a_u_pct\": "
        << num(e.a_u_pct) << ", \"a_u_rms_vox\": " << num(e.a_u_rms_vox) << ", \"a_J_pct\": " << num(e.a_J_pct)
        << ", \"a_J_rms_hu\": " << num(e.a_J_rms_hu) << ", \"b_shape_pct\": " << num(e.b_shape_pct)
        << ", \"b_isotropy_pct\": " << num(e.b_isotropy_pct) << ", \"b_ratio6\": " << num(e.b_ratio6)
        << ", \"c_u_pct\": " << num(e.c_u_pct) << ", \"c_corr\": " << num(e.c_corr) << "}}"
        << (i + 1 < rows.size() ? "," : "") << "\n";
    }
    f << "  ],\n  \"force\": [\n";
    for (std::size_t i = 0; i < force.size(); ++i) {
      const ForceRow& r = force[i];
      f << "    {\"sampling\": " << json_str(r.sampling) << ", \"where\": " << json_str(r.where) << ", \"n\": " << r.n
        << ", \"contact_disagree\": " << r.contact_disagree << ", \"rms_n\": " << num(r.rms_n) << ", \"max_n\": "
        << num(r.max_n) << ", \"rel_rms_pct\": " << num(r.rel_rms_pct) << ", \"ref_rms_n\": " << num(r.ref_rms_n)
        << ", \"ns_per_pose\": " << num(r.ns_per_pose) << "}" << (i + 1 < force.size() ? "," : "") << "\n";
    }
    f << "  ]\n}\n";
    if (!f) throw Error("accuracy: writing " + json_path + " failed");
  }
  if (std::rename((json_path + ".tmp").c_str(), json_path.c_str()) != 0) throw Error("accuracy: cannot write " + json_path);
}

// reference (c): the FEM of the base press on its VOI (none without --python); its inputs
// and results in a new folder under /tmp, named in tmp_dir for the caller to remove
RefC reference_c(const ReportOptions& o, const PatientPtr& patient, const DeformConfig& base, const test::Press& press,
                 std::string& tmp_dir) {
  RefC fem;
  if (!o.python.empty()) {
    char templ[] = "/tmp/palpsim-accuracy-XXXXXX";
    if (!mkdtemp(templ)) throw Error("accuracy: cannot make a temporary folder under /tmp");
    tmp_dir = templ;
    const Run r = run_setting("cpu", patient, base, press.contact, 0, 1, Stage::total);
    const Voi& v = r.last.chainmail.voi;
    const Vec3i g = r.last.chainmail.grabbed_vox, l = g - v.lo;
    std::printf("reference (c): FEM of the base press on its VOI %d x %d x %d (nu %.2f)\n", v.size.x, v.size.y, v.size.z, kNu);
    fem = solve_fem(o.python, *patient, v, g, r.u[v.index(l.x, l.y, l.z)], tmp_dir);
  }
  return fem;
}

}  // namespace

int run_accuracy_report(const ReportOptions& o) {
  const bool report = o.json_only.empty();
  const std::string json_path = report ? o.out_dir + "/accuracy-cpu.json" : o.json_only;
  check_writable(json_path, "accuracy:");
  std::string device;
  // one backend when asked: on the GPU machine only cuda's times are wanted (the errors come from the CPU run)
  const std::vector<std::string> backends = deform_backends(device, "accuracy", o.backend);
  // the phantom press of the deform accuracy study
  const auto [patient, press] = phantom_press(o.voxel_mm);
  const PatientPtr block = test::with_body_mask(
      test::make_patient({kBlockN, kBlockN, kBlockN}, [](int, int, int) { return test::kSoftHu; }));
  const double c = kBlockN / 2;
  const DeformContact block_press{{c, kBlockN - 1.0, c}, {c, kBlockN - 1.0 - kBlockPressVox, c}};
  // where the primed rows' tip hovers before its press: 5 mm out of the skin above X
  const Vec3 X = press.contact.skin_point_mm, dir = (press.contact.tip_mm - X) * (1.0 / norm(press.contact.tip_mm - X));
  const Vec3 hover = X - dir * (5.0 + press.skin_depth_mm), block_hover{c, kBlockN + 4.0, c};

  // the settings: one knob at a time from the base (preset p1, VOI 64, relaxation 20, inversion 8)
  DeformConfig base = test::preset_config(1);
  base.settings.voi_edge = 64;
  base.settings.relax_iterations = 20;
  base.settings.invert_iterations = 8;
  const std::vector<Group> groups = knob_groups(base);

  // reference (c) once, from the base press on the cpu backend
  std::string tmp_dir;
  const RefC fem = reference_c(o, patient, base, press, tmp_dir);

  std::vector<ReportRow> rows;
  for (const std::string& be : backends) {
    const bool gpu = be == "cuda";
    const int warmup = gpu ? 3 : 1;
    const int reps = gpu ? (o.quick ? 10 : 30) : (o.quick ? 2 : 8);
    for (const Group& grp : groups) {
      const std::vector<Setting>& group = grp.settings;
      // reference (a) of this knob on this backend
      RefA ref;
      if (grp.has_ref) {
        DeformConfig rc = grp.ref;
        rc.settings.backend = deform_backend_choice(be);
        const Run ra = run_setting(be, patient, rc, press.contact, 0, 1, Stage::total);
        ref.voi = ra.last.chainmail.voi;
        ref.u = ra.u;
        ref.J = ra.J;
        ref.I = J_on(*patient, ref.voi, Voi{}, {});
        ref.u_rms = field_diff(ref.u, std::vector<Vec3f>(ref.u.size(), Vec3f{0, 0, 0})).rms;
        ref.change_rms_hu = rms_diff(ref.J, ref.I);
      }
      std::vector<DeformConfig> cfgs;
      for (const Setting& s : group) {
        cfgs.push_back(s.cfg);
        cfgs.back().settings.backend = deform_backend_choice(be);
      }
      // the press itself, or reached a voxel a step from 5 voxels short (the last step on it)
      const std::vector<DeformContact> contacts =
          grp.pressing ? pressing(patient->grid, press.contact, 6) : std::vector<DeformContact>{press.contact};
      const std::vector<DeformContact> block_contacts =
          grp.pressing ? pressing(block->grid, block_press, 4) : std::vector<DeformContact>{block_press};
      std::vector<Run> runs;
      if (grp.primed)
        for (const DeformConfig& pc : cfgs) runs.push_back(run_first_contacts(be, patient, pc, press.contact, &hover, warmup, reps));
      else
        runs = run_settings(be, patient, cfgs, contacts, warmup, reps, group.front().stage);
      for (std::size_t s = 0; s < group.size(); ++s) {
        const Run& r = runs[s];
        ReportRow row;
        row.backend = be;
        row.knob = group[s].knob;
        row.label = group[s].label;
        row.step_ms = r.step_ms;
        row.stage_ms = r.stage_ms;
        row.reps = r.reps;
        row.moved = r.last.chainmail.moved;
        // (a): the field and J on the reference VOI
        const Voi& v = r.last.chainmail.voi;
        if (grp.has_ref) {
          row.err.a_u_rms_vox = diff_on_reference(ref.voi, ref.u, v, r.u).rms;
        row.err.a_u_pct = 100 * row.err.a_u_rms_vox / ref.u_rms;
        row.err.a_J_rms_hu = rms_diff(J_on(*patient, ref.voi, v, r.J), ref.J);
        row.err.a_J_pct = 100 * row.err.a_J_rms_hu / ref.change_rms_hu;
        }
        // (b): the same setting on the block
        const Run rb = grp.primed ? run_first_contacts(be, block, cfgs[s], block_press, &block_hover, 0, 1)
                                  : run_settings(be, block, {cfgs[s]}, block_contacts, 0,
                                                 grp.pressing ? int(block_contacts.size()) + 1 : 1, Stage::total)
                                        .front();
        if (grp.pressing && !(r.last.relax_warm && rb.last.relax_warm))
          throw Error("accuracy: a '" + row.label + "' step of " + row.knob + " did not start from the last unit response");
        block_errors(rb.last.chainmail.voi, rb.u, row.err);
        // (c)
        if (fem.ok) fem_errors(fem, v, r.u, row.err);
        std::printf("%-5s %-22s %-4s step %8.3f ms | (a) u %6.2f %% J %6.2f %% | (b) shape %6.2f %% isotropy %6.2f %% | "
                    "(c) u %6.2f %% corr %.3f\n",
                    be.c_str(), row.knob.c_str(), row.label.c_str(), row.step_ms.median, row.err.a_u_pct,
                    row.err.a_J_pct, row.err.b_shape_pct, row.err.b_isotropy_pct, row.err.c_u_pct, row.err.c_corr);
        rows.push_back(row);
      }
    }
  }

  // (d) on the default scene's phantom patient (prep: masks, distances, F, grad F)
  const Scene scene = default_scene();
  const PatientPtr prepared = prepare_patient(scene);
  const std::vector<ForceRow> force = force_study(*prepared, scene, o.quick);

  write_report_json(json_path, device, o, *patient, press, fem, rows, force);
  std::printf("wrote %s\n", json_path.c_str());
  if (!tmp_dir.empty()) run_command("rm -rf " + sh_quote(tmp_dir));
  if (!report) return 0;

  // the report: markdown and plots from this JSON and the GPU machine's
  return write_accuracy_report(o, json_path);
}

int write_accuracy_report(const ReportOptions& o, const std::string& cpu_json) {
  const std::string script = std::string(PALPSIM_SOURCE_DIR) + "/bench/accuracy_report.py";
  std::string cmd = sh_quote(o.python) + " " + sh_quote(script) + " --cpu " + sh_quote(cpu_json) + " --out-dir " +
                    sh_quote(o.out_dir);
  if (!o.gpu_json.empty()) cmd += " --gpu " + sh_quote(o.gpu_json);
  if (!o.elastic_json.empty()) cmd += " --elastic " + sh_quote(o.elastic_json);
  if (!o.elastic_gpu_json.empty()) cmd += " --elastic-gpu " + sh_quote(o.elastic_gpu_json);
  if (!o.forces_json.empty()) cmd += " --forces " + sh_quote(o.forces_json);
  if (!o.halfspace_json.empty()) cmd += " --halfspace " + sh_quote(o.halfspace_json);
  if (!run_command(cmd)) throw Error("accuracy: " + script + " failed");
  return 0;
}

}  // namespace palpsim::bench
