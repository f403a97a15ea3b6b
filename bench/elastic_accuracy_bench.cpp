// palpsim-bench accuracy --elastic: the elastic model (deform.relax_method "elastic") and the
// ChainMail family (the paper's explicit relaxation, the shipped multigrid diffusion) against
// references a correct elasticity solver can meet, on the shipped configuration
// (config/scenes/lumbar_phantom.textproto: the phantom at 1 mm, VOI 64, the fingertip of
// 5 mm), with what each costs (issue 25, sections 3 and 4):
//   (i)   verification: the FEM of the same problem (bench/accuracy_fem.py `contact`: the same
//         voxels, element, moduli, held nodes and sphere contact) on the phantom press and a block;
//   (ii)  discretisation: the same problem on the patient refined 2x over the VOI (elastic_refs.h,
//         refine_half), solved by the CPU elastic solver, which (i) shows to be that FEM;
//   (iii) Hertz: a sphere of R = 8 mm pressed R/20 .. R/5 into a 96^3 block of 1 mm voxels at
//         nu 0.45 and 0.49, beside the FEM of the same element in axisymmetric form (accuracy_fem.py `hertz`,
//         selective reduced integration and, to show locking, full integration);
//   (iv)  Hertz's surface profile under the fingertip;
//   (v)   every row (model, mode, setting; timed on each backend through make_deform_backend)
//         against the references above;
//   and the VOI: the elastic press on VOI 64 against VOI 96 and 128 (what the held faces cost).
// The JSON it writes is what bench/accuracy_report.py turns into bench/results/accuracy.md.
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "bench/deform_accuracy.h"
#include "bench/deform_runs.h"
#include "bench/elastic_fem_runs.h"
#include "bench/elastic_refs.h"
#include "bench/stats.h"
#include "core/error.h"
#include "deform/backend.h"
#include "deform/relax_elastic.h"
#include "net/scene_io.h"
#include "prep/phantom.h"
#include "prep/prepare.h"

namespace palpsim::bench {
namespace {

// a reference solve of the elastic model: to float rounding (the relative residual stalls near
// 1e-6 in float), contact rounds until no node changes, no inversion (only the field is compared)
DeformConfig converged(DeformConfig c) {
  c.settings.elastic.tolerance = 1e-6;
  c.settings.elastic.max_iterations = 400;
  c.settings.elastic.contact_rounds = 40;
  c.invert = false;
  return c;
}

// the shipped press: X where the haptic path puts it, on the skin (trilinear C = 1/2) straight
// above L3's spinous tip (kPressLandmark), x kPressMm anterior of it (into the body, towards the bone)
constexpr double kPressMm = 10;

// the block of the shipped configuration: 1 mm voxels, a sphere of the scene's radius pressed
// kBlockPressRatio of it (R / 5, Hertz's range) at the centre of the skin; the VOI as the scene
// sets it (centred on the tip: the tissue reaches about voi_edge / 2 below the skin)
constexpr double kBlockPressRatio = 0.2;


// one row: a model in one mode at one setting, and its configuration
struct RowSpec {
  std::string model, mode, setting;
  DeformConfig cfg;
};

// what a row measured
struct RowResult {
  RowSpec spec;
  std::string backend;
  Spread step_ms, relax_ms;
  int reps = 0;
  int cg_steps = -1;   // elastic: CG steps of the last step
  double force_n = NAN;  // elastic: |force| of the last step on the phantom press
  // errors (%; NaN where not computed)
  double fem_u = NAN, fem_f = NAN, fine_u = NAN, fine_f = NAN, hertz_f = NAN, profile = NAN;
};

// the field of a backend in mm (its displacement is in voxels along the grid axes)
std::vector<Vec3> in_mm(const std::vector<Vec3f>& u_vox, const Vec3& h) {
  std::vector<Vec3> out(u_vox.size());
  for (std::size_t e = 0; e < u_vox.size(); ++e) out[e] = {u_vox[e].x * h.x, u_vox[e].y * h.y, u_vox[e].z * h.z};
  return out;
}

// the nodes fields are compared on: body, not bone, off the VOI's faces (held in every model)
std::vector<bool> compared_nodes(const Patient& p, const Voi& v) {
  std::vector<bool> use(std::size_t(v.count()), false);
  for (int k = 1; k + 1 < v.size.z; ++k)
    for (int j = 1; j + 1 < v.size.y; ++j)
      for (int i = 1; i + 1 < v.size.x; ++i) {
        const std::size_t g = p.grid.index(v.lo.x + i, v.lo.y + j, v.lo.z + k);
        use[std::size_t(v.index(i, j, k))] = p.body.data[g] && !p.bone.data[g];
      }
  return use;
}

// relative RMS error (%) of `u` against `ref` over the nodes `use` accepts
double rel_rms_pct(const std::vector<Vec3>& u, const std::vector<Vec3>& ref, const std::vector<bool>& use) {
  double num = 0, den = 0;
  for (std::size_t e = 0; e < ref.size(); ++e) {
    if (!use[e]) continue;
    const Vec3 d = u[e] - ref[e];
    num += dot(d, d);
    den += dot(ref[e], ref[e]);
  }
  return den > 0 ? 100 * std::sqrt(num / den) : NAN;
}


// the deviation of v from ref in percent of ref
double pct(double v, double ref) { return ref != 0 ? 100 * (v - ref) / ref : NAN; }

// one solve of the elastic model on the CPU, kept for comparisons
struct Solved {
  Voi voi;
  std::vector<Vec3f> u_vox;  // as the backend holds it (voxel)
  std::vector<Vec3> u;       // mm
  deform::ElasticRun run;
  double seconds = 0;
};

// a converged elastic solve of `contact` on `patient` (cpu)
Solved solve_elastic(const PatientPtr& patient, const DeformConfig& cfg, const DeformContact& contact) {
  auto b = make_deform_backend("cpu");
  b->bind(patient, cfg);
  const auto t0 = std::chrono::steady_clock::now();
  const DeformStats st = b->step(contact);
  Solved s;
  s.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  s.voi = b->voi();
  s.u_vox = b->displacement();
  s.u = in_mm(s.u_vox, patient->grid.spacing_mm);
  s.run = st.elastic;
  if (!s.run.contact) throw Error("elastic accuracy: a reference press touched nothing");
  std::printf("  elastic solve: VOI %d x %d x %d, %d CG steps, %d rounds%s, %d contact nodes, force %.5g N, %.1f s\n",
              s.voi.size.x, s.voi.size.y, s.voi.size.z, s.run.iterations, s.run.rounds,
              s.run.contact_settled ? "" : " (unsettled)", s.run.contact_nodes, norm(s.run.force_n), s.seconds);
  return s;
}

// the fine solve (ii): the patient refined 2x over `voi`, the whole refined grid the VOI
Solved solve_fine(const Patient& p, const Voi& voi, DeformConfig cfg, const DeformContact& contact) {
  cfg.settings.whole_volume = true;
  return solve_elastic(refine_half(p, voi), cfg, contact);
}

// the fine field at the coarse nodes (fine node 2 i is coarse node i of `voi`)
std::vector<Vec3> coarse_of_fine(const Voi& voi, const Solved& fine) {
  std::vector<Vec3> out(std::size_t(voi.count()));
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i)
        out[std::size_t(voi.index(i, j, k))] = fine.u[std::size_t(fine.voi.index(2 * i, 2 * j, 2 * k))];
  return out;
}

// the displacement into the block along +x from the axis on the skin (r mm, w mm), for the report's plot
std::string profile_json(const Patient& b, int skin_j, const Voi& voi, const std::vector<Vec3>& u_mm, int reach) {
  const int ci = b.grid.size.x / 2, ck = b.grid.size.z / 2;
  std::ostringstream r, w;
  for (int di = 0; di <= reach; ++di) {
    const Vec3i l = Vec3i{ci + di, skin_j, ck} - voi.lo;
    if (!voi.contains(l.x, l.y, l.z)) break;
    r << (di ? ", " : "") << json_number(di * b.grid.spacing_mm.x);
    w << (di ? ", " : "") << json_number(-u_mm[std::size_t(voi.index(l.x, l.y, l.z))].y);
  }
  return "{\"r_mm\": [" + r.str() + "], \"w_mm\": [" + w.str() + "]}";
}

// the rows: the paper's explicit relaxation, the shipped multigrid diffusion and the elastic
// model, each in the modes a session meets (the first press of a contact; the tip moving on a
// voxel a step; the press repeated) at the settings that trade accuracy for time
std::vector<RowSpec> row_specs(const DeformConfig& shipped, bool quick) {
  std::vector<RowSpec> v;
  // the paper: explicit diffusion, one grabbed element (its grab radius is 0), relax_iterations
  for (int it : quick ? std::vector<int>{20} : std::vector<int>{20, 80, 320}) {
    DeformConfig c = shipped;
    c.settings.relax_method = RelaxMethod::kExplicit;
    c.settings.grab_radius_mm = 0;
    c.settings.relax_iterations = it;
    v.push_back({"explicit (paper)", "every step", std::to_string(it) + " iterations", c});
  }
  // the shipped multigrid diffusion (grab radius 5 mm; asked for, whatever the scene file
  // says): from zero every step (relax_cycles), and as the server runs it while the tip
  // moves a voxel a step (the VOI held within voi_edge / 8 voxels, warm starts) and while it
  // rests (the unit response reused)
  DeformConfig mg = shipped;
  mg.settings.relax_method = RelaxMethod::kMultigrid;
  for (int cyc : quick ? std::vector<int>{4} : std::vector<int>{1, 2, 4, 8}) {
    DeformConfig c = mg;
    c.settings.relax_cycles = cyc;
    c.relax_reuse = false;
    v.push_back({"multigrid (shipped)", "from zero", std::to_string(cyc) + " steps", c});
  }
  v.push_back({"multigrid (shipped)", "tip moving", "as shipped", mg});
  v.push_back({"multigrid (shipped)", "press repeated", "as shipped", mg});
  // the elastic model: tolerance at the default cap, and caps at the default tolerance
  DeformConfig el = shipped;
  el.settings.relax_method = RelaxMethod::kElastic;
  // as DeformConfig::from_scene sets it for an elastic scene: the unit press whenever the
  // model predicts (and so the prediction from it, and superposed steps)
  el.elastic_stiffness = el.settings.elastic.predict;
  const ElasticSettings def;
  auto elastic = [&](const std::string& mode, double tol, int cap) {
    DeformConfig c = el;
    c.settings.elastic.tolerance = tol;
    c.settings.elastic.max_iterations = cap;
    char s[64];
    std::snprintf(s, sizeof s, "tol %g, cap %d", tol, cap);
    v.push_back({"elastic", mode, s, c});
  };
  const std::vector<double> tols = quick ? std::vector<double>{1e-3} : std::vector<double>{1e-1, 1e-2, 1e-3, 1e-4};
  for (double t : tols) elastic("from rest", t, def.max_iterations);
  if (!quick)
    for (int cap : {4, 8, 16}) elastic("from rest", def.tolerance, cap);
  for (double t : tols) elastic("tip moving", t, def.max_iterations);
  if (!quick)
    for (int cap : {1, 2, 4}) elastic("tip moving", def.tolerance, cap);
  elastic("press repeated", def.tolerance, def.max_iterations);
  return v;
}

// the rows' timed steps on one backend, each mode's settings round-robin (so that a shared
// machine's load spreads over them): "from rest" a new engine each step (a session's first press),
// "tip moving" the press reached a voxel a step, the others the press itself again and again
std::vector<Run> run_rows(const std::string& backend, const PatientPtr& patient, const std::vector<RowSpec>& specs,
                          const DeformContact& press, bool gpu, bool quick) {
  const int warmup = gpu ? 3 : 1;
  const int reps = gpu ? (quick ? 10 : 30) : (quick ? 2 : 8);
  std::vector<Run> runs(specs.size());
  for (const char* kind : {"from rest", "tip moving", "press"}) {
    std::vector<std::size_t> at;
    std::vector<DeformConfig> cfgs;
    for (std::size_t i = 0; i < specs.size(); ++i) {
      const std::string& m = specs[i].mode;
      if (m == kind || (std::string(kind) == "press" && m != "from rest" && m != "tip moving")) {
        at.push_back(i);
        cfgs.push_back(specs[i].cfg);
      }
    }
    if (cfgs.empty()) continue;
    std::vector<Run> r;
    if (std::string(kind) == "from rest")
      r = run_first_contacts(backend, patient, cfgs, press, warmup, gpu ? 10 : (quick ? 1 : 4));
    else if (std::string(kind) == "tip moving")
      r = run_settings(backend, patient, cfgs, pressing(patient->grid, press, 6), warmup, reps + 4, Stage::relax);
    else
      r = run_settings(backend, patient, cfgs, press, warmup, reps, Stage::relax);
    for (std::size_t k = 0; k < at.size(); ++k) runs[at[k]] = std::move(r[k]);
  }
  return runs;
}

}  // namespace

// references (i) and (ii) of one case: the elastic model converged (`s`, its compared nodes
// `u`), the FEM of the same problem (`f`; none without `python`) and the model on the patient
// refined 2x (`fs`, on the coarse nodes `fu`); their figures as JSON
std::string case_json(const char* name, const PatientPtr& p, const DeformConfig& cfg, const DeformContact& c,
                      const std::string& python, const std::string& work, Solved& s, Fem& f, Solved& fs,
                      std::vector<Vec3>& fu, std::vector<bool>& u) {
  std::printf("reference %s: the elastic model converged\n", name);
  s = solve_elastic(p, converged(cfg), c);
  u = compared_nodes(*p, s.voi);
  if (!python.empty()) {
    std::printf("reference %s (i): the FEM of the same problem (bench/accuracy_fem.py contact)\n", name);
    f = solve_fem_contact(python, work, name, *p, s.voi, cfg, c);
  }
  std::printf("reference %s (ii): the elastic model on the patient refined 2x\n", name);
  fs = solve_fine(*p, s.voi, converged(cfg), c);
  fu = coarse_of_fine(s.voi, fs);
  const double F = norm(s.run.force_n), Ff = norm(fs.run.force_n);
  std::ostringstream j;
  j << "{\"voi\": {\"lo\": [" << s.voi.lo.x << ", " << s.voi.lo.y << ", " << s.voi.lo.z << "], \"size\": [" << s.voi.size.x
    << ", " << s.voi.size.y << ", " << s.voi.size.z << "]}, \"compared_nodes\": "
    << std::count(u.begin(), u.end(), true) << ",\n      \"elastic\": {\"iterations\": " << s.run.iterations
    << ", \"rounds\": " << s.run.rounds << ", \"settled\": " << (s.run.contact_settled ? "true" : "false")
    << ", \"contact_nodes\": " << s.run.contact_nodes << ", \"force_n\": " << json_vec3(s.run.force_n)
    << ", \"seconds\": " << json_number(s.seconds) << "},\n      \"fem\": ";
  if (f.ok) {
    double max_mm = 0;
    for (std::size_t e = 0; e < u.size(); ++e)
      if (u[e]) max_mm = std::max(max_mm, norm(s.u[e] - f.u[e]));
    j << "{\"stats\": " << f.stats << "},\n      \"verification\": {\"u_pct\": " << json_number(rel_rms_pct(s.u, f.u, u))
      << ", \"force_pct\": " << json_number(pct(F, norm(f.force_n))) << ", \"max_diff_mm\": " << json_number(max_mm)
      << "}";
  } else {
    j << "null, \"verification\": null";
  }
  j << ",\n      \"fine\": {\"size\": [" << fs.voi.size.x << ", " << fs.voi.size.y << ", " << fs.voi.size.z
    << "], \"iterations\": " << fs.run.iterations << ", \"rounds\": " << fs.run.rounds
    << ", \"contact_nodes\": " << fs.run.contact_nodes << ", \"force_n\": " << json_vec3(fs.run.force_n)
    << ", \"seconds\": " << json_number(fs.seconds) << "},\n      \"discretisation\": {\"u_pct\": "
    << json_number(rel_rms_pct(s.u, fu, u)) << ", \"force_pct\": " << json_number(pct(F, Ff)) << "}}";
  return j.str();
}

// references (iii) and (iv): the elastic model pressing large blocks of `block_el`'s tissue
// against Hertz (and, with o.python, the FEM); the rows' JSON, and in `profile` the profile
// of the 96^3 block's deepest press
std::string hertz_json(const DeformConfig& block_el, const ElasticStudyOptions& o, const std::string& work,
                       std::string& profile) {
  std::ostringstream refs_json;
  bool first = true;
  for (const int n : {96, 128}) {
    const PatientPtr hb = elastic_block({n, n, n}, 1.0, n - kHertzAir, kBlockHu);
    for (const double hnu : kHertzNus)
      for (const double d : kHertzDepths) {
        if (n == 128 && (d != kHertzDepths[2] || o.quick)) continue;  // the larger block: the deepest press only
        if (o.quick && (d != kHertzDepths[2] || hnu != kHertzNus[0])) continue;
        DeformConfig c = block_el;
        c.settings.whole_volume = true;
        c.settings.grab_radius_mm = kHertzR;
        c.settings.elastic.poisson = hnu;
        const double e = deform::elastic_table_e(c.elastic_params().material.table, kBlockHu);
        std::printf("reference (iii): Hertz, block %d^3, R %g mm, d %g mm, nu %g\n", n, kHertzR, d, hnu);
        const DeformContact hc = block_press(*hb, n - kHertzAir, d);
        const Solved hs = solve_elastic(hb, converged(c), hc);
        const double F = norm(hs.run.force_n), Fh = hertz_force_n(e, hnu, kHertzR, d);
        refs_json << (first ? "\n      " : ",\n      ") << "{\"block_n\": " << n << ", \"nu\": " << json_number(hnu)
                  << ", \"radius_mm\": " << json_number(kHertzR) << ", \"depth_mm\": " << json_number(d)
                  << ", \"e_kpa\": " << json_number(e) << ", \"hertz_n\": " << json_number(Fh)
                  << ", \"elastic_n\": " << json_number(F) << ", \"ratio\": " << json_number(F / Fh)
                  << ", \"iterations\": " << hs.run.iterations << ", \"rounds\": " << hs.run.rounds
                  << ", \"contact_nodes\": " << hs.run.contact_nodes << ", \"seconds\": " << json_number(hs.seconds)
                  << ", \"profile_pct\": " << json_number(profile_error(*hb, n - kHertzAir, hs.voi, hs.u, kHertzR, d));
        first = false;
        if (n == 96 && !o.python.empty()) {
          std::printf("reference (iii): the FEM, converged; and at the voxels' 1 mm, reduced and fully integrated\n");
          refs_json << ", \"fem\": " << solve_fem_hertz(o.python, work, kHertzR, d, hnu, e, kHertzFemH0, false)
                    << ", \"fem_voxel\": " << solve_fem_hertz(o.python, work, kHertzR, d, hnu, e, kHertzFemVoxelH0, false)
                    << ", \"fem_full\": " << solve_fem_hertz(o.python, work, kHertzR, d, hnu, e, kHertzFemVoxelH0, true);
        }
        refs_json << "}";
        if (n == 96 && hnu == kHertzNus[0] && d == kHertzDepths[2]) {
          const double a = std::sqrt(kHertzR * d);
          std::ostringstream pj;
          pj << "{\"block_n\": " << n << ", \"nu\": " << json_number(hnu) << ", \"radius_mm\": " << json_number(kHertzR)
             << ", \"depth_mm\": " << json_number(d) << ", \"a_mm\": " << json_number(a) << ", \"within_radii\": "
             << json_number(kProfileRadii) << ", \"elastic_pct\": "
             << json_number(profile_error(*hb, n - kHertzAir, hs.voi, hs.u, kHertzR, d)) << ", \"elastic\": "
             << profile_json(*hb, n - kHertzAir, hs.voi, hs.u, int(std::ceil(6 * a))) << "}";
          profile = pj.str();
        }
      }
  }
  return refs_json.str();
}

// what holding the VOI's faces costs: the elastic press converged on VOIs of 64, 96 and 128
// against the largest (`ref` is the shipped VOI's, `use` its compared nodes), and each one's
// first step from rest; as JSON rows
std::string voi_json(const PatientPtr& patient, const DeformConfig& el, const DeformConfig& shipped,
                     const DeformContact& press, const Solved& ref, const std::vector<bool>& use) {
  std::ostringstream refs_json;
  std::printf("reference: the elastic press on larger VOIs\n");
  struct VoiRun {
    int edge;
    Solved s;
    double step_ms;
    int steps;
  };
  std::vector<VoiRun> vr;
  for (const int edge : {64, 96, 128}) {
    DeformConfig c = el;
    c.settings.voi_edge = edge;
    VoiRun v{edge, edge == shipped.settings.voi_edge ? ref : solve_elastic(patient, converged(c), press), 0, 0};
    const Run first_step = run_first_contacts("cpu", patient, c, press, nullptr, 0, 1);
    v.step_ms = first_step.step_ms.median;
    v.steps = first_step.last.elastic.iterations;
    vr.push_back(std::move(v));
  }
  const VoiRun& big = vr.back();
  for (std::size_t i = 0; i < vr.size(); ++i) {
    const VoiRun& v = vr[i];
    const Vec3& h = patient->grid.spacing_mm;
    const std::vector<Vec3> a = in_mm(field_on(ref.voi, v.s.voi, v.s.u_vox, false), h),
                            b = in_mm(field_on(ref.voi, big.s.voi, big.s.u_vox, false), h);
    refs_json << (i ? ",\n      " : "\n      ") << "{\"edge\": " << v.edge << ", \"force_n\": " << json_number(norm(v.s.run.force_n))
              << ", \"force_pct\": " << json_number(pct(norm(v.s.run.force_n), norm(big.s.run.force_n)))
              << ", \"u_pct\": " << json_number(rel_rms_pct(a, b, use)) << ", \"converged_iterations\": "
              << v.s.run.iterations << ", \"converged_s\": " << json_number(v.s.seconds)
              << ", \"step_ms\": " << json_number(v.step_ms) << ", \"step_iterations\": " << v.steps << "}";
  }
  return refs_json.str();
}

// the FEM's folder: --work (made, and checked writable), else a new one under /tmp
// (`temporary`: to remove at the end) when the references run the FEM, else none
std::string work_folder(const ElasticStudyOptions& o, bool& temporary) {
  std::string work = o.work_dir;
  if (o.references && !o.python.empty() && work.empty()) {
    char templ[] = "/tmp/palpsim-elastic-XXXXXX";
    if (!mkdtemp(templ)) throw Error("accuracy --elastic: cannot make a temporary folder under /tmp");
    work = templ;
    temporary = true;
  } else if (!work.empty()) {
    mkdir(work.c_str(), 0755);
    check_writable(work + "/probe", "accuracy --elastic: --work");
  }
  return work;
}

// one row's setting on the block, in the row's mode: from rest, the tip moving (from half the
// depth), or the press repeated
Run block_run(const std::string& be, const PatientPtr& block, const DeformConfig& bc, const DeformContact& bpress,
              const std::string& mode, double block_d) {
  if (mode == "from rest") return run_first_contacts(be, block, bc, bpress, nullptr, 0, 1);
  if (mode == "tip moving") {
    const DeformContact half{bpress.skin_point_mm, bpress.skin_point_mm - Vec3{0, block_d / 2, 0}};
    return run_settings(be, block, {bc}, std::vector<DeformContact>{bpress, half}, 0, 2, Stage::relax).front();
  }
  return run_setting(be, block, bc, bpress, 0, 2, Stage::relax);
}

// the rows as JSON lines
std::string rows_json(const std::vector<RowResult>& rows) {
  std::ostringstream f;
  for (std::size_t i = 0; i < rows.size(); ++i) {
    const RowResult& r = rows[i];
    f << "    {\"backend\": " << json_str(r.backend) << ", \"model\": " << json_str(r.spec.model) << ", \"mode\": "
      << json_str(r.spec.mode) << ", \"setting\": " << json_str(r.spec.setting) << ", \"reps\": " << r.reps
      << ", \"step\": " << json_spread(r.step_ms) << ", \"relax\": " << json_spread(r.relax_ms)
      << ", \"cg_steps\": " << (r.cg_steps >= 0 ? std::to_string(r.cg_steps) : "null") << ", \"force_n\": "
      << json_number(r.force_n) << ", \"errors\": {\"fem_u_pct\": " << json_number(r.fem_u)
      << ", \"fem_force_pct\": " << json_number(r.fem_f) << ", \"fine_u_pct\": " << json_number(r.fine_u)
      << ", \"fine_force_pct\": " << json_number(r.fine_f) << ", \"hertz_force_pct\": " << json_number(r.hertz_f)
      << ", \"profile_pct\": " << json_number(r.profile) << "}}" << (i + 1 < rows.size() ? "," : "") << "\n";
  }
  return f.str();
}

// one row's times (and, for the elastic model, its CG steps and force) from its run
RowResult row_of(const RowSpec& spec, const std::string& be, const Run& run) {
  RowResult r;
  r.spec = spec;
  r.backend = be;
  r.step_ms = run.step_ms;
  r.relax_ms = run.stage_ms;
  r.reps = run.reps;
  if (spec.model == "elastic") {
    r.cg_steps = run.last.elastic.iterations;
    r.force_n = norm(run.last.elastic.force_n);
  }
  return r;
}

// one row's step time and errors on stdout
void print_row(const RowResult& r) {
  std::printf("%-4s %-20s %-14s %-18s step %9.3f ms | FEM u %7.3g %% F %7.3g %% | h/2 u %7.3g %% F %7.3g %% | "
              "Hertz F %7.3g %% profile %7.3g %%\n",
              r.backend.c_str(), r.spec.model.c_str(), r.spec.mode.c_str(), r.spec.setting.c_str(), r.step_ms.median,
              r.fem_u, r.fem_f, r.fine_u, r.fine_f, r.hertz_f, r.profile);
}

int run_elastic_accuracy(const ElasticStudyOptions& o) {
  check_writable(o.json, "accuracy --elastic:");
  std::string device;
  const std::vector<std::string> backends = deform_backends(device, "accuracy --elastic", o.backend);
  const bool refs = o.references;
  bool temporary = false;
  const std::string work = work_folder(o, temporary);

  // the shipped scene, its patient through prep, and the press
  const std::string scene_file = "config/scenes/lumbar_phantom.textproto";
  const Scene scene = load_scene_file(std::string(PALPSIM_SOURCE_DIR) + "/" + scene_file);
  const PatientPtr patient = prepare_patient(scene);
  DeformConfig shipped = DeformConfig::from_scene(scene, patient.get());
  DeformConfig el = shipped;
  el.settings.relax_method = RelaxMethod::kElastic;
  el.settings.backend = DeformBackendChoice::kCpu;
  const PhantomGeometry geo;
  const Vec3 X = skin_point_along(*patient, geo.landmark(kPressLandmark), Vec3{0, 1, 0});
  const DeformContact press{X, X - Vec3{0, kPressMm, 0}};
  const double R = shipped.settings.grab_radius_mm, nu = el.settings.elastic.poisson;
  std::printf("accuracy --elastic: %s, phantom %.3g mm, VOI %d, fingertip %g mm; press %g mm at X = (%.2f, %.2f, %.2f) mm "
              "above %s\n",
              scene_file.c_str(), patient->grid.spacing_mm.x, shipped.settings.voi_edge, R, kPressMm, X.x, X.y, X.z,
              kPressLandmark);

  // the block of the shipped configuration: homogeneous (no skin layer), pressed R / 5
  const PatientPtr block = elastic_block(kBlockSize, 1.0, kBlockSkinJ, kBlockHu);
  DeformConfig block_el = el;
  block_el.settings.elastic.skin_thickness_mm = 0;
  const double block_d = kBlockPressRatio * R;
  const DeformContact bpress = block_press(*block, kBlockSkinJ, block_d);
  const double block_e = deform::elastic_table_e(block_el.elastic_params().material.table, kBlockHu);
  const double block_hertz = hertz_force_n(block_e, nu, R, block_d);

  std::ostringstream refs_json;
  Solved ref, bref, fine, bfine;
  Fem fem, bfem;
  std::vector<Vec3> fine_u, bfine_u;
  std::vector<bool> use, buse;
  if (refs) {
    const bool with_fem = !o.python.empty();
    // (i) and (ii) on the phantom press and on the block
    refs_json << "{\n    \"press\": " << case_json("press", patient, el, press, o.python, work, ref, fem, fine, fine_u, use);
    refs_json << ",\n    \"block\": " << case_json("block", block, block_el, bpress, o.python, work, bref, bfem, bfine, bfine_u, buse);
    refs_json << ",\n    \"block_hertz_pct\": {\"elastic\": " << json_number(pct(norm(bref.run.force_n), block_hertz))
              << ", \"fine\": " << json_number(pct(norm(bfine.run.force_n), block_hertz)) << "}";
    if (with_fem)
      refs_json << ",\n    \"block_fem_hertz\": " << solve_fem_hertz(o.python, work, R, block_d, nu, block_e, kHertzFemH0, false);

    // (iii) Hertz on large blocks, (iv) the profile
    refs_json << ",\n    \"hertz\": [";
    std::string profile;
    refs_json << hertz_json(block_el, o, work, profile);
    refs_json << "\n    ],\n    \"profile\": " << (profile.empty() ? "null" : profile);

    // the VOI: what holding its faces costs, against the largest
    refs_json << ",\n    \"voi\": [" << voi_json(patient, el, shipped, press, ref, use);
    refs_json << "\n    ]\n  }";
  }

  // the rows on every backend
  std::vector<RowResult> rows;
  for (const std::string& be : backends) {
    const bool gpu = be == "cuda";
    std::vector<RowSpec> specs = row_specs(shipped, o.quick);
    for (RowSpec& spec : specs) spec.cfg.settings.backend = deform_backend_choice(be);
    const std::vector<Run> runs = run_rows(be, patient, specs, press, gpu, o.quick);
    for (std::size_t i = 0; i < specs.size(); ++i) {
      const RowSpec& spec = specs[i];
      const Run& run = runs[i];
      RowResult r = row_of(spec, be, run);
      const bool elastic = spec.model == "elastic";
      if (refs) {
        const std::vector<Vec3> u = in_mm(field_on(ref.voi, run.last.chainmail.voi, run.u, false), patient->grid.spacing_mm);
        if (fem.ok) r.fem_u = rel_rms_pct(u, fem.u, use);
        r.fine_u = rel_rms_pct(u, fine_u, use);
        if (elastic) {
          if (fem.ok) r.fem_f = pct(r.force_n, norm(fem.force_n));
          r.fine_f = pct(r.force_n, norm(fine.run.force_n));
        }
        // the same setting on the block: Hertz's force and profile
        DeformConfig bc = spec.cfg;
        if (elastic) bc.settings.elastic.skin_thickness_mm = 0;
        const Run br = block_run(be, block, bc, bpress, spec.mode, block_d);
        const std::vector<Vec3> bu = in_mm(br.u, block->grid.spacing_mm);
        r.profile = profile_error(*block, kBlockSkinJ, br.last.chainmail.voi, bu, R, block_d);
        if (elastic) r.hertz_f = pct(norm(br.last.elastic.force_n), block_hertz);
      }
      print_row(r);
      rows.push_back(r);
    }
  }

  // the JSON (temporary name, then rename)
  {
    std::ofstream f(o.json + ".tmp");
    f << json_run_header("accuracy-elastic", device, o.commit, o.quick) << "\n  \"scene\": " << json_str(scene_file) << ",\n  \"voxel_mm\": " << json_number(patient->grid.spacing_mm.x)
      << ",\n  \"voi_edge\": " << shipped.settings.voi_edge << ",\n  \"finger_radius_mm\": " << json_number(R)
      << ",\n  \"poisson\": " << json_number(nu) << ",\n  \"elastic_defaults\": {\"tolerance\": "
      << json_number(ElasticSettings{}.tolerance) << ", \"max_iterations\": " << ElasticSettings{}.max_iterations
      << ", \"contact_rounds\": " << ElasticSettings{}.contact_rounds << ", \"unit_press\": " << (ElasticSettings{}.predict ? "true" : "false") << ", \"stiffness_tolerance\": "
      << json_number(ElasticSettings{}.stiffness_tolerance) << "},\n  \"press\": {\"landmark\": "
      << json_str(kPressLandmark) << ", \"X_mm\": " << json_vec3(press.skin_point_mm) << ", \"x_mm\": "
      << json_vec3(press.tip_mm) << ", \"press_mm\": " << json_number(kPressMm) << "},\n  \"block\": {\"size\": ["
      << kBlockSize.x << ", " << kBlockSize.y << ", " << kBlockSize.z << "], \"skin_j\": " << kBlockSkinJ
      << ", \"hu\": " << json_number(kBlockHu) << ", \"e_kpa\": " << json_number(block_e) << ", \"radius_mm\": "
      << json_number(R) << ", \"depth_mm\": " << json_number(block_d) << ", \"hertz_n\": " << json_number(block_hertz)
      << ", \"profile_within_radii\": " << json_number(kProfileRadii) << "},\n  \"references\": "
      << (refs ? refs_json.str() : "null") << ",\n  \"rows\": [\n";
    f << rows_json(rows);
    f << "  ]\n}\n";
    if (!f) throw Error("accuracy --elastic: writing " + o.json + " failed");
  }
  if (std::rename((o.json + ".tmp").c_str(), o.json.c_str()) != 0) throw Error("accuracy --elastic: cannot write " + o.json);
  std::printf("wrote %s\n", o.json.c_str());
  if (temporary) run_command("rm -rf " + sh_quote(work));
  return 0;
}

}  // namespace palpsim::bench
