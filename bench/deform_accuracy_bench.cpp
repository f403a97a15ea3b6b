// palpsim-bench deform --accuracy: what accuracy costs in time (see deform_accuracy.h).
// One press: X 1 mm under the back skin straight above the L3 spinous tip of the
// phantom, x 10 mm anterior of X (into the body, towards the bone). The base is the
// scene default (preset p1, VOI 64, relaxation 20, inversion 8); one knob varies at a
// time and is compared with a reference that differs from the base in that knob only:
//   relax_iterations {0..160} vs 400: RMS and max |u - u_ref| (voxel), RMS of the
//     discrete Laplacian of u over soft voxels (voxel; lower is smoother);
//   relax_cycles {1..8} (relax_method multigrid; 0: explicit 20) vs multigrid 40 steps,
//     the converged steady state: RMS |u - u_ref| over RMS |u_ref|, max |u - u_ref|,
//     the Laplacian's RMS, and isotropy at 6 voxels on a homogeneous block;
//   invert_iterations {0..32} vs 64: max and mean inversion residual |p + u(p) - y|
//     (voxel) and RMS |J - J_ref| (HU), over the VOI and over the voxels the reference
//     resolved (residual <= 0.1 voxel; a fold's few unresolved voxels swing J by
//     hundreds of HU with the iteration count and dominate the plain RMS);
//   voi_edge {32..128} vs ref_voi_edge: fraction of the reference's displacement
//     energy (sum |u|^2) outside the VOI, for the reference at relaxation 20 and 400,
//     and RMS |u - u_ref| over the reference's VOI (u = 0 outside the setting's VOI).
// Times: median (p10, p90) of whole steps and of the knob's stage, after warm-up.
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

namespace palpsim::bench {
namespace {

using deform::Voi;
using test::Press;
using test::spinous_press;
using test::laplacian_rms;

// a JSON number (null for a non-finite value)
std::string num(double v) { return json_number(v); }

std::string json_vec(const Vec3& v) { return "[" + num(v.x) + ", " + num(v.y) + ", " + num(v.z) + "]"; }

// the inversion residual |p + u(p) - y| of every VOI voxel after `iterations`
// fixed-point steps (the backends' own invert_point on the backend's field)
struct Residual {
  double max = 0, mean = 0;
  std::vector<float> each;  // per VOI voxel (voxel), i fastest
};

Residual invert_residuals(const Voi& voi, const std::vector<Vec3f>& u, int iterations) {
  auto load_u = [&](int i, int j, int k) { return voi.contains(i, j, k) ? u[voi.index(i, j, k)] : Vec3f{0, 0, 0}; };
  Residual r;
  r.each.resize(std::size_t(voi.count()));
  double sum = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        float res = 0;
        deform::invert_point(load_u, Vec3f(float(i), float(j), float(k)), iterations, res);
        r.max = std::max(r.max, double(res));
        r.each[voi.index(i, j, k)] = res;
        sum += res;
      }
  r.mean = sum / double(std::max(1LL, voi.count()));
  return r;
}

// true when the patient voxel (gi, gj, gk) lies in the box
bool in_box(const Voi& v, int gi, int gj, int gk) { return v.contains(gi - v.lo.x, gj - v.lo.y, gk - v.lo.z); }

// fraction of the reference field's energy (sum |u|^2) that lies outside the box `voi`
double energy_outside(const Voi& ref_voi, const std::vector<Vec3f>& u_ref, const Voi& voi) {
  double all = 0, out = 0;
  for (int k = 0; k < ref_voi.size.z; ++k)
    for (int j = 0; j < ref_voi.size.y; ++j)
      for (int i = 0; i < ref_voi.size.x; ++i) {
        const Vec3f& v = u_ref[ref_voi.index(i, j, k)];
        const double e = double(v.x) * v.x + double(v.y) * v.y + double(v.z) * v.z;
        all += e;
        if (!in_box(voi, ref_voi.lo.x + i, ref_voi.lo.y + j, ref_voi.lo.z + k)) out += e;
      }
  return all > 0 ? out / all : 0;
}

// one table row: a setting of one knob on one backend and what it cost and gave
struct Row {
  std::string backend, knob;
  int setting = 0;
  bool reference = false;
  Spread step_ms, stage_ms;
  int reps = 0;
  long long voi_voxels = 0, moved = 0;
  std::vector<std::pair<std::string, double>> metrics;  // name (with unit) and value, in table order
};

Row make_row(const std::string& backend, const std::string& knob, int setting, bool reference, const Run& r) {
  Row row;
  row.backend = backend;
  row.knob = knob;
  row.setting = setting;
  row.reference = reference;
  row.step_ms = r.step_ms;
  row.stage_ms = r.stage_ms;
  row.reps = r.reps;
  row.voi_voxels = r.last.chainmail.voi.count();
  row.moved = r.last.chainmail.moved;
  return row;
}

// prints one knob's rows of one backend as a markdown table (no stage column when
// stage_name is empty: the knob's cost is the whole step)
void print_table(const std::vector<Row>& rows, const std::string& backend, const std::string& knob,
                 const std::string& stage_name, const std::string& caption) {
  std::vector<const Row*> sel;
  for (const Row& r : rows)
    if (r.backend == backend && r.knob == knob) sel.push_back(&r);
  if (sel.empty()) return;
  const bool stage = !stage_name.empty();
  std::printf("\n%s: %s (%s)\n\n| %s | step ms (p10-p90) |", backend.c_str(), knob.c_str(), caption.c_str(),
              knob.c_str());
  if (stage) std::printf(" %s ms |", stage_name.c_str());
  for (const auto& m : sel.front()->metrics) std::printf(" %s |", m.first.c_str());
  std::printf("\n|---|---|%s", stage ? "---|" : "");
  for (std::size_t m = 0; m < sel.front()->metrics.size(); ++m) std::printf("---|");
  std::printf("\n");
  for (const Row* r : sel) {
    std::printf("| %s%d | %.3f (%.3f-%.3f)%s |", r->reference ? "ref " : "", r->setting, r->step_ms.median,
                r->step_ms.p10, r->step_ms.p90, r->reps == 1 ? " 1 run" : "");
    if (stage) std::printf(" %.3f |", r->stage_ms.median);
    for (const auto& m : r->metrics) std::printf(" %.4g |", m.second);
    std::printf("\n");
  }
  std::fflush(stdout);
}

// one backend's knob studies against their references, each adding its rows and printing
// its table (run_deform_accuracy runs those --study asks for)
struct KnobStudy {
  const AccuracyOptions& o;
  std::string be;              // the backend
  PatientPtr patient;          // the phantom
  const test::Press& press;
  DeformConfig cfg;            // the base on this backend
  int warmup = 1, reps = 1;    // untimed and timed steps of each setting
  std::vector<Row>& rows;
  static constexpr int relax_set[] = {0, 5, 10, 20, 40, 80, 160};
  static constexpr int invert_set[] = {0, 1, 2, 4, 8, 16, 32};
  static constexpr int voi_set[] = {32, 48, 64, 96, 128};

  // relaxation iterations against relaxation to ref_relax_iterations on the same VOI
  void relax_iterations() {
    DeformConfig c = cfg;
    c.settings.relax_iterations = o.ref_relax_iterations;
    const Run ref = run_setting(be, patient, c, press.contact, 0, 1, Stage::relax);
    if (ref.last.chainmail.grabbed_in_bone || ref.last.chainmail.moved == 0)
      throw Error("deform accuracy: the press moves nothing (X in bone?)");
    const Voi& voi = ref.last.chainmail.voi;
    const Vec3i grabbed = ref.last.chainmail.grabbed_vox;
    Row rr = make_row(be, "relax_iterations", o.ref_relax_iterations, true, ref);
    rr.metrics = {{"u_rms_diff_vox", 0}, {"u_max_diff_vox", 0}, {"laplacian_rms_vox", laplacian_rms(*patient, voi, grabbed, ref.u)}};
    std::vector<DeformConfig> cs;
    for (int n : relax_set) {
      cs.push_back(c);
      cs.back().settings.relax_iterations = n;
    }
    const std::vector<Run> runs = run_settings(be, patient, cs, press.contact, warmup, reps, Stage::relax);
    for (std::size_t s = 0; s < cs.size(); ++s) {
      const int n = relax_set[s];
      const Run& r = runs[s];
      if (!(r.last.chainmail.voi == voi)) throw Error("deform accuracy: the VOI changed between runs");
      const Diff d = field_diff(r.u, ref.u);
      Row row = make_row(be, "relax_iterations", n, false, r);
      row.metrics = {{"u_rms_diff_vox", d.rms}, {"u_max_diff_vox", d.max},
                     {"laplacian_rms_vox", laplacian_rms(*patient, voi, grabbed, r.u)}};
      rows.push_back(row);
    }
    rows.push_back(rr);
    print_table(rows, be, "relax_iterations", "relax",
                "VOI 64, inversion 8; reference: relaxation " + std::to_string(o.ref_relax_iterations));
  }

  // multigrid steps against the converged steady state (multigrid, ref_multigrid_cycles
  // steps); setting 0 is the paper's explicit 20 steps on the same scale. Isotropy on
  // a homogeneous block (VOI 64, centre grabbed and pushed 4 voxels) at 6 voxels.
  void relax_cycles() {
    DeformConfig c = cfg;
    c.settings.relax_method = palpsim::RelaxMethod::kMultigrid;
    c.settings.relax_cycles = o.ref_multigrid_cycles;
    const Run ref = run_setting(be, patient, c, press.contact, 0, 1, Stage::relax);
    const Voi& voi = ref.last.chainmail.voi;
    const Vec3i grabbed = ref.last.chainmail.grabbed_vox;
    const double ref_rms = field_diff(ref.u, std::vector<Vec3f>(ref.u.size(), Vec3f{0, 0, 0})).rms;
    std::vector<DeformConfig> cs;
    std::vector<int> settings{0};
    cs.push_back(cfg);  // explicit, relax_iterations 20
    for (int n = 1; n <= 8; ++n) {
      cs.push_back(c);
      cs.back().settings.relax_cycles = n;
      settings.push_back(n);
    }
    cs.push_back(c);
    settings.push_back(o.ref_multigrid_cycles);
    // the rows solve every step (relax_reuse false); the same steps reusing the unit
    // response (the press repeated) give each row's relax_ms_reused
    const std::size_t rows_n = cs.size();
    for (std::size_t s = 0; s < rows_n; ++s) cs[s].relax_reuse = false;
    for (std::size_t s = 1; s + 1 < rows_n; ++s) {
      cs.push_back(cs[s]);
      cs.back().relax_reuse = true;
    }
    const std::vector<Run> runs = run_settings(be, patient, cs, press.contact, warmup, reps, Stage::relax);
    const PatientPtr block = test::make_soft_patient(72);
    const DeformContact push = test::voxel_contact({36, 36, 36}, {0, 0, 4});
    const std::vector<Run> on_block = run_settings(be, block, cs, push, 0, 1, Stage::relax);
    for (std::size_t s = 0; s < rows_n; ++s) {
      const Run& r = runs[s];
      if (!(r.last.chainmail.voi == voi)) throw Error("deform accuracy: the VOI changed between runs");
      const Diff d = field_diff(r.u, ref.u);
      const ChainMailStats& bs = on_block[s].last.chainmail;
      Row row = make_row(be, "relax_cycles", settings[s], s + 1 == rows_n, r);
      const bool reused = s >= 1 && s + 1 < rows_n;
      const Run* w = reused ? &runs[rows_n + s - 1] : nullptr;
      row.metrics = {{"u_rms_diff_rel", d.rms / ref_rms}, {"u_max_diff_vox", d.max},
                     {"laplacian_rms_vox", laplacian_rms(*patient, voi, grabbed, r.u)},
                     {"isotropy6_block", test::isotropy(bs.voi, on_block[s].u, bs.grabbed_vox - bs.voi.lo, 6)},
                     {"relax_ms_reused", w ? w->stage_ms.median : NAN},
                     {"solves_reused", w ? double(w->last.relax_solves) : NAN}};
      rows.push_back(row);
    }
    print_table(rows, be, "relax_cycles", "relax",
                "relax_method multigrid, VOI 64, inversion 8, each step solving afresh; 0: explicit 20 "
                "instead; reference: multigrid " +
                    std::to_string(o.ref_multigrid_cycles) +
                    "; u_rms_diff_rel over the reference's RMS; relax_ms_reused: the same press repeated, "
                    "the unit response reused (solves_reused 0)");
    warm_cycles(c, ref.u, voi, grabbed, ref_rms, block, push);
    primed(c);
  }

  // warm starts: the tip reaching the press a voxel a step (from 5 voxels short), so
  // that every step has another VOI and starts from the last step's unit response
  // (relax_warm_cycles steps); the last step is the press itself
  void warm_cycles(const DeformConfig& c, const std::vector<Vec3f>& ref_u, const Voi& voi, const Vec3i& grabbed,
                   double ref_rms, const PatientPtr& block, const DeformContact& push) {
    std::vector<DeformConfig> ws;
    const int warm_set[] = {1, 2, 3, 4};
    for (int n : warm_set) {
      ws.push_back(c);
      ws.back().settings.relax_cycles = DeformSettings{}.relax_cycles;
      ws.back().settings.relax_warm_cycles = n;
      ws.back().voi_hold = false;  // every step another VOI
    }
    const std::vector<Run> warm =
        run_settings(be, patient, ws, pressing(patient->grid, press.contact, 6), warmup, reps, Stage::relax);
    const std::vector<Run> warm_block = run_settings(be, block, ws, pressing(block->grid, push, 4), 0, 8, Stage::relax);
    for (std::size_t s = 0; s < ws.size(); ++s) {
      const Run& r = warm[s];
      if (!(r.last.chainmail.voi == voi)) throw Error("deform accuracy: the VOI changed between runs");
      if (!r.last.relax_warm || !warm_block[s].last.relax_warm)
        throw Error("deform accuracy: a relax_warm_cycles step did not start from the last unit response");
      const Diff d = field_diff(r.u, ref_u);
      const ChainMailStats& bs = warm_block[s].last.chainmail;
      Row row = make_row(be, "relax_warm_cycles", warm_set[s], false, r);
      row.metrics = {{"u_rms_diff_rel", d.rms / ref_rms}, {"u_max_diff_vox", d.max},
                     {"laplacian_rms_vox", laplacian_rms(*patient, voi, grabbed, r.u)},
                     {"isotropy6_block", test::isotropy(bs.voi, warm_block[s].u, bs.grabbed_vox - bs.voi.lo, 6)}};
      rows.push_back(row);
    }
    print_table(rows, be, "relax_warm_cycles", "relax",
                "relax_method multigrid, VOI 64, inversion 8, the tip a voxel deeper every step (a new VOI "
                "each, from 5 voxels short of the press), each solve started from the last unit response; "
                "reference as above");
  }

  // a session's first contact: a new engine each repetition, its first step the tip a
  // voxel under X (a new press), after a prime where the tip hovering 5 mm out of the
  // skin above X (setting -1: no prime, from zero; 0: straight above; 3: 3 voxels aside
  // of X, across the press) is expected to touch (deform::expected_skin_voxel,
  // as the server does); against that contact's own steady state
  void primed(const DeformConfig& c) {
    const Vec3 X = press.contact.skin_point_mm, x = press.contact.tip_mm;
    const Grid& grid = patient->grid;
    const Vec3 dir = (x - X) * (1.0 / norm(x - X));
    const double h = grid.spacing_mm.x;
    const DeformContact first{X, X + dir * h};
    DeformConfig fc = c;
    fc.settings.relax_cycles = DeformSettings{}.relax_cycles;
    fc.settings.relax_warm_cycles = DeformSettings{}.relax_warm_cycles;
    DeformConfig sc = c;
    sc.relax_reuse = false;
    const Run fref = run_setting(be, patient, sc, first, 0, 1, Stage::relax);
    const double fref_rms = field_diff(fref.u, std::vector<Vec3f>(fref.u.size(), Vec3f{0, 0, 0})).rms;
    // a direction across the press (the press runs along -y: x)
    const Vec3 across = std::fabs(dir.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 0, 1};
    for (const int aside : {-1, 0, 3}) {
      const Vec3 hover = X - dir * (5.0 + press.skin_depth_mm) + across * (std::max(aside, 0) * h);
      int prime_steps = 0;
      const Run r = run_first_contacts(be, patient, fc, first, aside >= 0 ? &hover : nullptr, warmup, reps, &prime_steps);
      if (aside < 0 && r.last.relax_warm) throw Error("deform accuracy: a first contact without a prime started warm");
      const Diff d = field_diff(r.u, fref.u);
      Row row = make_row(be, "relax_primed", aside, false, r);
      row.metrics = {{"u_rms_diff_rel", d.rms / fref_rms},
                     {"u_max_diff_vox", d.max},
                     {"steps", double(r.last.relax_cycles)},
                     {"prime_steps", aside >= 0 ? double(prime_steps) : NAN}};
      rows.push_back(row);
    }
    print_table(rows, be, "relax_primed", "relax",
                "relax_method multigrid (defaults), VOI 64: a session's first contact, the tip a voxel under "
                "X, each repetition a new engine; -1: no prime (from zero); 0: primed where a tip hovering "
                "5 mm above X expects to touch, k: the hovering tip k voxels aside; prime_steps: the "
                "prime's own solve (before the contact, as much GPU as setting -1's relaxation; waited for "
                "before the step, as the approach leaves time for it); "
                "reference: that contact's steady state (multigrid " +
                    std::to_string(o.ref_multigrid_cycles) + ")");
  }

  // inversion iterations against inversion with ref_invert_iterations on the same field
  void invert_iterations() {
    DeformConfig c = cfg;
    c.settings.invert_iterations = o.ref_invert_iterations;
    const Run ref = run_setting(be, patient, c, press.contact, 0, 1, Stage::invert);
    const Voi& voi = ref.last.chainmail.voi;
    // the voxels the reference resolved: J there does not depend on where a fold's iteration stopped
    const Residual ref_res = invert_residuals(voi, ref.u, o.ref_invert_iterations);
    std::vector<bool> resolved(ref_res.each.size());
    for (std::size_t e = 0; e < resolved.size(); ++e) resolved[e] = ref_res.each[e] <= deform::kInvertResolvedVox;
    auto add = [&](int n, bool reference, const Run& r) {
      const Residual res = invert_residuals(voi, r.u, n);
      Row row = make_row(be, "invert_iterations", n, reference, r);
      row.metrics = {{"residual_max_vox", res.max},
                     {"residual_mean_vox", res.mean},
                     {"unresolved", double(r.last.invert_unresolved)},
                     {"J_rms_diff_hu", rms_diff(r.J, ref.J)},
                     {"J_rms_diff_resolved_hu", rms_diff(r.J, ref.J, resolved)}};
      rows.push_back(row);
    };
    std::vector<DeformConfig> cs;
    for (int n : invert_set) {
      cs.push_back(c);
      cs.back().settings.invert_iterations = n;
    }
    const std::vector<Run> runs = run_settings(be, patient, cs, press.contact, warmup, reps, Stage::invert);
    for (std::size_t s = 0; s < cs.size(); ++s) {
      const int n = invert_set[s];
      const Run& r = runs[s];
      if (!(r.last.chainmail.voi == voi)) throw Error("deform accuracy: the VOI changed between runs");
      add(n, false, r);
    }
    add(o.ref_invert_iterations, true, ref);
    print_table(rows, be, "invert_iterations", "invert",
                "VOI 64, relaxation 20; reference: inversion " + std::to_string(o.ref_invert_iterations));
  }

  // VOI edge against a VOI of ref_voi_edge (relaxation 20 as the base, and 400)
  void voi_edge() {
    DeformConfig c = cfg;
    c.settings.voi_edge = o.ref_voi_edge;
    c.invert = false;  // the references need the field only
    const Run ref = run_setting(be, patient, c, press.contact, 0, 1, Stage::total);
    c.settings.relax_iterations = o.ref_relax_iterations;
    const Run ref_long = run_setting(be, patient, c, press.contact, 0, 1, Stage::total);
    const Voi& rv = ref.last.chainmail.voi;
    const std::string long_name = "clipped_energy_relax" + std::to_string(o.ref_relax_iterations);
    std::vector<DeformConfig> cs;
    for (int edge : voi_set) {
      cs.push_back(cfg);
      cs.back().settings.voi_edge = edge;
    }
    const std::vector<Run> runs = run_settings(be, patient, cs, press.contact, warmup, reps, Stage::total);
    for (std::size_t s = 0; s < cs.size(); ++s) {
      const int edge = voi_set[s];
      const Run& r = runs[s];
      const Voi& v = r.last.chainmail.voi;
      const Diff d = diff_on_reference(rv, ref.u, v, r.u);
      Row row = make_row(be, "voi_edge", edge, false, r);
      row.metrics = {{"clipped_energy_relax20", energy_outside(rv, ref.u, v)},
                     {long_name, energy_outside(ref_long.last.chainmail.voi, ref_long.u, v)},
                     {"u_rms_diff_vox", d.rms},
                     {"u_max_diff_vox", d.max}};
      rows.push_back(row);
    }
    Row row = make_row(be, "voi_edge", o.ref_voi_edge, true, ref);
    row.metrics = {{"clipped_energy_relax20", 0}, {long_name, 0}, {"u_rms_diff_vox", 0}, {"u_max_diff_vox", 0}};
    rows.push_back(row);
    print_table(rows, be, "voi_edge", "",
                "relaxation 20, inversion 8; reference: VOI " + std::to_string(o.ref_voi_edge) +
                    " without inversion (time 1 run)");
  }
};

// the study's JSON (written to a temporary name and renamed, so no half-written file is left)
void write_json(const AccuracyOptions& o, const std::string& device, const Grid& grid, const test::Press& press,
                const DeformConfig& base, const std::vector<Row>& rows) {
  const Vec3 X = press.contact.skin_point_mm, x = press.contact.tip_mm;
  const std::string tmp = o.json + ".tmp";
  {
    std::ofstream f(tmp);
    if (!f) throw Error("deform accuracy: cannot write --json " + o.json);
    const std::time_t now = std::time(nullptr);
    char date[32];
    std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
    f << "{\n  \"area\": \"deform-accuracy\",\n  \"date\": \"" << date << "\",\n  \"device\": " << json_str(device)
      << ",\n  \"host_cpu\": " << json_str(cpu_model()) << ",\n  \"host_threads\": "
      << std::thread::hardware_concurrency() << ",\n  \"commit\": " << json_str(o.commit)
      << ",\n  \"quick\": " << (o.quick ? "true" : "false") << ",\n  \"phantom\": {\"voxel_mm\": " << num(o.voxel_mm)
      << ", \"size\": [" << grid.size.x << ", " << grid.size.y << ", " << grid.size.z << "]},\n"
      << "  \"press\": {\"landmark\": " << json_str(press.landmark) << ", \"landmark_mm\": " << json_vec(press.landmark_mm)
      << ", \"X_mm\": " << json_vec(X) << ", \"x_mm\": " << json_vec(x) << ", \"press_mm\": " << num(press.press_mm)
      << ", \"skin_depth_mm\": " << num(press.skin_depth_mm) << ", \"bone_depth_mm\": " << num(press.bone_depth_mm)
      << "},\n  \"base\": {\"preset\": \"p1\", \"voi_edge\": " << base.settings.voi_edge
      << ", \"relax_iterations\": " << base.settings.relax_iterations
      << ", \"invert_iterations\": " << base.settings.invert_iterations << "},\n"
      << "  \"reference\": {\"relax_iterations\": " << o.ref_relax_iterations
      << ", \"invert_iterations\": " << o.ref_invert_iterations << ", \"voi_edge\": " << o.ref_voi_edge
      << ", \"multigrid_cycles\": " << o.ref_multigrid_cycles << "},\n"
      << "  \"rows\": [\n";
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const Row& r = rows[i];
      f << "    {\"backend\": " << json_str(r.backend) << ", \"knob\": " << json_str(r.knob)
        << ", \"setting\": " << r.setting << ", \"reference\": " << (r.reference ? "true" : "false")
        << ", \"reps\": " << r.reps << ", \"voi_voxels\": " << r.voi_voxels << ", \"moved\": " << r.moved
        << ", \"step\": " << json_spread(r.step_ms) << ", \"stage\": " << json_spread(r.stage_ms) << ", \"metrics\": {";
      for (std::size_t m = 0; m < r.metrics.size(); ++m)
        f << (m ? ", " : "") << json_str(r.metrics[m].first) << ": " << num(r.metrics[m].second);
      f << "}}" << (i + 1 < rows.size() ? "," : "") << "\n";
    }
    f << "  ]\n}\n";
    if (!f) throw Error("deform accuracy: writing --json " + o.json + " failed");
  }
  if (std::rename(tmp.c_str(), o.json.c_str()) != 0) throw Error("deform accuracy: cannot rename " + tmp + " to " + o.json);
  std::printf("wrote %s\n", o.json.c_str());
}

}  // namespace

std::vector<std::string> deform_backends(std::string& device, const std::string& who, const std::string& only) {
  if (!only.empty() && only != "cpu" && only != "cuda")
    throw Error(who + ": --backend " + only + " is unknown; use cpu or cuda");
  std::vector<std::string> backends{"cpu"};
  std::string why;
  device = "cpu only";
  if (cuda_deform_available(&why)) {
    backends.push_back("cuda");
    device = why;
  }
  if (!who.empty()) std::printf("%s: backends cpu%s (%s)\n", who.c_str(), backends.size() > 1 ? ", cuda" : "", why.c_str());
  if (!only.empty()) {
    if (std::find(backends.begin(), backends.end(), only) == backends.end())
      throw Error(who + ": --backend " + only + " is not available here (" + device + ": " + why + ")");
    backends.assign(1, only);
  }
  return backends;
}

void check_writable(const std::string& path, const std::string& what) {
  const std::string probe = path + ".tmp";
  const bool ok = bool(std::ofstream(probe));
  std::remove(probe.c_str());
  if (!ok) throw Error(what + " cannot write " + path + " (its folder is missing or read-only)");
}

int run_deform_accuracy(const AccuracyOptions& o) {
  // bad options fail before minutes of work: the reference VOI and the JSON's folder
  if (o.ref_voi_edge < 128 || o.ref_voi_edge > 1024)
    throw Error("deform accuracy: --ref-voi " + std::to_string(o.ref_voi_edge) +
                " must lie in [128, 1024] voxel (at least the largest VOI setting, 128)");
  const std::string studies[] = {"relax_iterations", "relax_cycles", "invert_iterations", "voi_edge"};
  if (!o.study.empty() && std::find(std::begin(studies), std::end(studies), o.study) == std::end(studies))
    throw Error("deform accuracy: --study " + o.study + " is unknown; use relax_iterations, relax_cycles, "
                "invert_iterations or voi_edge");
  auto wanted = [&](const std::string& knob) { return o.study.empty() || o.study == knob; };
  if (!o.json.empty()) check_writable(o.json, "deform accuracy: --json");
  std::string device;
  const std::vector<std::string> backends = deform_backends(device, "deform accuracy", o.backend);
  const auto [patient, press] = phantom_press(o.voxel_mm);
  const Grid& grid = patient->grid;
  const Vec3 X = press.contact.skin_point_mm;
  std::printf("phantom %d x %d x %d at %.3f mm; press %.0f mm along -y (anterior) at X = (%.1f, %.1f, %.1f) mm, "
              "%.0f mm under the skin, %.1f mm above %s\n",
              grid.size.x, grid.size.y, grid.size.z, o.voxel_mm, press.press_mm, X.x, X.y, X.z, press.skin_depth_mm,
              press.bone_depth_mm, press.landmark.c_str());

  // the base: the scene defaults with the paper's preset p1
  DeformConfig base = test::preset_config(1);
  base.settings.voi_edge = 64;
  base.settings.relax_iterations = 20;
  base.settings.invert_iterations = 8;

  std::vector<Row> rows;
  for (const std::string& be : backends) {
    const bool gpu = be == "cuda";
    KnobStudy k{o, be, patient, press, base, gpu ? 3 : 1, gpu ? (o.quick ? 10 : 30) : (o.quick ? 2 : 10), rows};
    k.cfg.settings.backend = deform_backend_choice(be);
    if (wanted("relax_iterations")) k.relax_iterations();
    if (wanted("relax_cycles")) k.relax_cycles();
    if (wanted("invert_iterations")) k.invert_iterations();
    if (wanted("voi_edge")) k.voi_edge();
  }
  if (!o.json.empty()) write_json(o, device, grid, press, base, rows);
  return 0;
}

}  // namespace palpsim::bench
