// palpsim-bench deform: the paper's Table 2 (ChainMail time and moved elements for
// d = 3 ... 30, p1 and p2) and Table 1 (time per stage: reset, ChainMail, relax, untangle,
// invert, upload, total) for VOI 32, 64, 96, 128 and the whole phantom volume, and the
// elastic model's step (from rest, while the tip moves, 16 sessions begun together) at VOI
// 64, on every backend this build and machine have, in one run. GPU figures are printed
// next to the floor from ../shared/docs/DEVICE.md or the goal that bounds them.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "bench/deform_accuracy.h"
#include "bench/registry.h"
#include "bench/stats.h"
#include "core/error.h"
#include "deform/backend.h"
#include "prep/phantom.h"
#include "tests/support/deform_fixtures.h"
#include "tests/support/phantom_press.h"

using namespace palpsim;

namespace {

using bench::json_spread;
using bench::spread;
using bench::Spread;

struct Options {
  std::string json;
  std::string commit = "unknown";
  bool quick = false;    // fewer repetitions and no d = 30 / whole volume on the cpu
  double voxel_mm = 340.0 / 255.0;  // the phantom at ~256 voxels across
  std::string only;      // --backend: run this backend alone (empty: every one there is)
  bool untangle = false; // --untangle: Table 1 with deform.untangle on (off in scenes by default)
  bool elastic_only = false;  // --elastic: the elastic rows alone
  ElasticSettings elastic;    // the elastic model's settings (--elastic-degrees F,C,L sets the V-cycle's degrees,
                              // --elastic-unit-tolerance T the shipped rows' unit press tolerance, the scenes' 0.01)
};

struct Table2Row {
  std::string backend;
  int preset, d;
  long long moved;
  int sweeps;
  bool converged;
  Spread chainmail, wall;
};

struct Table1Row {
  std::string backend, voi;
  long long voxels;
  long long moved;
  double residual;
  long long unresolved;
  long long folded_before, folded_after;  // untangling's folded cells
  Spread reset, chainmail, relax, untangle, invert, upload, total;
};

struct ElasticRow {
  std::string backend, what;
  int voi = 0;
  int sessions = 1;             // begun together
  int iterations = 0;           // CG steps of the last step (contact rounds; the unit press apart)
  int stiffness_iterations = 0; // ... of its unit press
  int rounds = 0;               // ... its contact rounds (each a solve and a pass over the set)
  int contact_nodes = 0;
  double force_n = 0;           // |F| of the last step (N)
  Spread relax, total;          // the elastic stage and the whole step (ms)
  double steps_per_s = 0;       // begun together: steps a second, per session
  double own_mb = 0;            // a session's own memory (DeformMemory::total, MiB)
  double shared_mb = 0;         // the solver scratch its sessions share (MiB)
  // the last step against the same steps converged (percent; -1: not compared)
  double u_err_pct = -1;        // relative RMS of u over the VOI
  double force_err_pct = -1;    // |F| / |F converged| - 1
  double stiffness_err_pct = -1;
  bool stiffness = false;       // the step solved the unit press (its stiffness compared), in CG steps or none
  double superposed_pct = -1;   // the timed steps that superposed the unit press (no solve); -1: not counted
};

// one backend's Table 2: whole-volume soft domain big enough for the whole deformation
void table2(const std::string& name, const Options& o, std::vector<Table2Row>& rows) {
  const int ds[] = {3, 5, 10, 20, 30};
  for (int preset = 1; preset <= 2; ++preset)
    for (int d : ds) {
      const bool gpu = name == "cuda";
      if (!gpu && o.quick && d > 10) continue;
      const int n = 4 * d + 5, c = n / 2;
      DeformConfig cfg = test::preset_config(preset);
      cfg.settings.whole_volume = true;
      cfg.relax = false;
      cfg.invert = false;
      auto b = make_deform_backend(name);
      b->bind(test::make_soft_patient(n), cfg);
      const DeformContact contact = test::voxel_contact({c, c, c}, {double(d), 0, 0});
      const int reps = gpu ? (o.quick ? 10 : 50) : (d <= 10 ? 10 : (d == 20 ? 3 : 1));
      std::vector<double> cm, wall;
      DeformStats st;
      for (int r = -2; r < reps; ++r) {  // two warm-up runs
        st = b->step(contact);
        if (r < 0) continue;
        cm.push_back(st.times.chainmail_ms);
        wall.push_back(st.times.total_ms - st.times.reset_ms);
      }
      rows.push_back({name, preset, d, st.chainmail.moved, st.chainmail.sweeps, st.chainmail.converged, spread(cm),
                      spread(wall)});
      const Table2Row& r = rows.back();
      std::printf("table2 %-4s p%d d=%2d  moved %7lld  sweeps %3d  chainmail %8.3f ms (p10 %.3f, p90 %.3f)%s\n",
                  name.c_str(), preset, d, r.moved, r.sweeps, r.chainmail.median, r.chainmail.p10, r.chainmail.p90,
                  gpu && d == 30 && preset == 1
                      ? "  [goal 1 ms; floor: one launch + sync 8.5 us, plus 2d = 60 grid barriers]"
                      : "");
      std::fflush(stdout);
    }
}

// the DEVICE.md floor that bounds a GPU stage at a given VOI edge
std::string relax_floor(int edge) {
  switch (edge) {
    case 64: return "floor: 20 float4 7-point sweeps in a CUDA graph, 64^3: 66 us";
    case 96: return "floor: 20 float4 7-point sweeps in a CUDA graph, 96^3: 177 us";
    case 128: return "floor: 20 float4 7-point sweeps in a CUDA graph, 128^3: 555 us";
    default: return "floor: 3.0 TB/s device copy; 20 sweeps read and write the field";
  }
}

// one backend's Table 1 on the phantom
void table1(const std::string& name, const Options& o, const PatientPtr& patient, std::vector<Table1Row>& rows) {
  const bool gpu = name == "cuda";
  const DeformContact contact = test::table1_press(*patient);
  for (int edge : {32, 64, 96, 128, 0}) {
    if (!gpu && o.quick && edge == 0) continue;
    DeformConfig cfg = test::preset_config(1);
    cfg.settings.relax_iterations = 20;
    cfg.settings.invert_iterations = 8;
    cfg.settings.untangle = o.untangle;
    cfg.settings.voi_edge = edge ? edge : 64;
    cfg.settings.whole_volume = edge == 0;
    auto b = make_deform_backend(name);
    b->bind(patient, cfg);
    const int reps = gpu ? (o.quick ? 10 : 50) : (edge == 0 ? 1 : (edge <= 64 ? 10 : 3));
    std::vector<double> t[7];
    DeformStats st;
    for (int r = -2; r < reps; ++r) {
      st = b->step(contact);
      if (r < 0) continue;
      const DeformTimes& x = st.times;
      const double v[7] = {x.reset_ms, x.chainmail_ms, x.relax_ms, x.untangle_ms, x.invert_ms, x.upload_ms, x.total_ms};
      for (int s = 0; s < 7; ++s) t[s].push_back(v[s]);
    }
    Table1Row row{name, edge ? std::to_string(edge) : "whole", st.chainmail.voi.count(), st.chainmail.moved,
                  st.invert_residual_vox, st.invert_unresolved, st.untangle.folded_before, st.untangle.folded_after,
                  spread(t[0]), spread(t[1]), spread(t[2]), spread(t[3]), spread(t[4]), spread(t[5]), spread(t[6])};
    rows.push_back(row);
    std::printf("table1 %-4s VOI %-5s (%lld voxels, moved %lld, folded %lld -> %lld, residual %.3f vox, %lld unresolved) "
                "median ms: reset %.3f  chainmail %.3f  relax %.3f  untangle %.3f  invert %.3f  upload %.3f  total %.3f "
                "(p90 %.3f)\n",
                name.c_str(), row.voi.c_str(), row.voxels, row.moved, row.folded_before, row.folded_after, row.residual,
                row.unresolved, row.reset.median, row.chainmail.median, row.relax.median, row.untangle.median,
                row.invert.median, row.upload.median, row.total.median, row.total.p90);
    if (gpu) {
      std::printf("       relax %.3f ms  [%s]\n", row.relax.median, relax_floor(edge).c_str());
      if (edge == 64 && o.untangle)
        std::printf("       untangle %.3f ms  [goal: well under relax's 0.087 ms]\n", row.untangle.median);
      std::printf("       upload %.3f ms of %.2f MB  [floor: pinned copy 1 MB 26 us]\n", row.upload.median,
                  row.voxels * 4.0 / 1048576.0);
      if (edge == 64) std::printf("       total %.3f ms  [goal 0.5 ms]\n", row.total.median);
      if (edge == 128) std::printf("       total %.3f ms  [goal 2 ms]\n", row.total.median);
    }
    std::fflush(stdout);
  }
}

// a row's words for the unit press stopped at `t` with the force and stiffness by reciprocity
std::string reciprocal_words(double t) {
  char b[64];
  std::snprintf(b, sizeof b, ", unit press to %g, reciprocal", t);
  return b;
}

// one backend's elastic rows, issue 25's goals: VOI 64 on the phantom (with its body mask
// and B), the fingertip of 5 mm, the scenes' solver settings and the unit press that
// haptics.force_model "elastic" asks for, pressing over L3. A step from rest (reset()
// before each: the VOI set up and solved from zero), a step while the tip moves a voxel
// (alternating between two depths a voxel apart: the VOI held, the last field the start),
// and on cuda 16 sessions at 16 points along the spine begun together, each with a share
// of 16 as the server sets it (an elastic step keeps the whole device: they step in turn)
struct ElasticBench {
  std::string name;
  const Options& o;
  PatientPtr phantom;
  bool gpu;
  DeformConfig cfg;
  Vec3 X, in;  // the skin point over L3 (mm) and the press direction (unit)
  double depth = 6, h;

  ElasticBench(const std::string& backend, const Options& opt, const PatientPtr& p, const test::Press& press)
      : name(backend), o(opt), phantom(p), gpu(backend == "cuda"), cfg(test::preset_config(1)),
        X(press.contact.skin_point_mm), in((press.contact.tip_mm - X) / press.press_mm), h(p->grid.spacing_mm.x) {
    cfg.settings.relax_method = RelaxMethod::kElastic;
    cfg.settings.elastic = o.elastic;
    cfg.settings.grab_radius_mm = 5;
    cfg.settings.voi_edge = 64;
    cfg.settings.invert_search = true;  // as the scenes ship (deform.invert_search)
    cfg.elastic_stiffness = true;
    // the rows name what they turn on: from the last field alone, the unit press to the
    // round's tolerance unless a row says otherwise
    cfg.settings.elastic.predict = false;
    cfg.settings.elastic.stiffness_tolerance = 0;
  }

  // step s's press at skin point `at`: 6 mm deep, a voxel deeper on odd steps
  DeformContact contact(const Vec3& at, int s) const { return DeformContact{at, at + in * (depth + (s & 1) * h)}; }

  ElasticRow row(const std::string& what, const std::vector<double>& relax, const std::vector<double>& total,
                 const DeformStats& st, const DeformMemory& m) const {
    ElasticRow r;
    r.backend = name;
    r.what = what;
    r.voi = 64;
    r.iterations = st.elastic.iterations;
    r.stiffness_iterations = st.elastic.stiffness_iterations;
    r.rounds = st.elastic.rounds;
    r.contact_nodes = st.elastic.contact_nodes;
    r.force_n = norm(st.elastic.force_n);
    r.relax = spread(relax);
    r.total = spread(total);
    r.own_mb = m.total() / 1048576.0;
    r.shared_mb = m.shared_scratch_bytes / 1048576.0;
    return r;
  }

  // the field, force and stiffness of row `r`'s last step (`u`, `st`) against the same
  // step converged (`ref`, `ref_st`)
  static void against(ElasticRow& r, const std::vector<Vec3f>& u, const DeformStats& st, const std::vector<Vec3f>& ref,
                      const DeformStats& ref_st, bool stiffness) {
    double d2 = 0, u2 = 0;
    for (std::size_t e = 0; e < u.size() && e < ref.size(); ++e) {
      d2 += double(dot(u[e] - ref[e], u[e] - ref[e]));
      u2 += double(dot(ref[e], ref[e]));
    }
    r.u_err_pct = u2 > 0 ? 100 * std::sqrt(d2 / u2) : -1;
    r.force_err_pct = 100 * (norm(st.elastic.force_n) / norm(ref_st.elastic.force_n) - 1);
    r.stiffness = stiffness;
    if (stiffness) r.stiffness_err_pct = 100 * (st.elastic.stiffness_n_per_mm / ref_st.elastic.stiffness_n_per_mm - 1);
  }

  // the solver's settings converged (tolerance 1e-6, 12 contact rounds): the rows' reference
  DeformConfig converged() const {
    DeformConfig conv = cfg;
    conv.settings.elastic.tolerance = 1e-6;
    conv.settings.elastic.stiffness_tolerance = 0;  // the unit press to 1e-6 too, whatever --elastic-unit-tolerance says
    conv.settings.elastic.contact_rounds = 12;
    conv.settings.elastic.max_iterations = 400;
    return conv;
  }

  // from rest: reset() before each step (one warm-up run), the unit press to the round's
  // tolerance, or to `stiffness_tolerance` with the force by reciprocity (the shipped
  // settings, above 0); the last step against the same step converged
  ElasticRow from_rest(double stiffness_tolerance = 0) const {
    DeformConfig c = cfg;
    c.settings.elastic.stiffness_tolerance = stiffness_tolerance;
    auto b = make_deform_backend(name);
    b->bind(phantom, c);
    const int reps = gpu ? (o.quick ? 10 : 50) : (o.quick ? 1 : 3);
    std::vector<double> relax, total;
    DeformStats st;
    for (int r = -1; r < reps; ++r) {
      b->reset();
      st = b->step(contact(X, 0));
      if (r < 0) continue;
      relax.push_back(st.times.relax_ms);
      total.push_back(st.times.total_ms);
    }
    auto ref = make_deform_backend(name);
    ref->bind(phantom, converged());
    const DeformStats ref_st = ref->step(contact(X, 0));
    ElasticRow r = row(std::string("from rest") + (stiffness_tolerance > 0 ? reciprocal_words(stiffness_tolerance) : ""),
                       relax, total, st, b->memory());
    against(r, b->displacement(), st, ref->displacement(), ref_st, true);
    return r;
  }

  // step s's press while the tip slides along the spine (`slide`): 6 mm deep, half a voxel
  // a step to and fro over 4 voxels (a new contact set each step; the VOI held)
  DeformContact sliding(int s) const {
    const int t = s % 16, half_voxels = t < 8 ? t : 16 - t;
    const Vec3 at = X + Vec3{0, 0, 0.5 * h * half_voxels};
    return DeformContact{at, at + in * depth};
  }

  // step s's press while the tip presses in and out along n: 6 to 6.6 mm deep and back,
  // 0.05 mm a step (a tip at 50 mm/s stepped at 1 kHz: most steps superpose the unit press,
  // deform::elastic_superposes, a step now and then solves where the contact set changes)
  DeformContact pressing(int s) const {
    const int t = s % 24, steps = t < 12 ? t : 24 - t;
    return DeformContact{X, X + in * (depth + 0.05 * steps)};
  }

  // how the tip moves in moving(): a voxel along n and back, sliding, pressing 0.05 mm a step
  enum class Motion { kVoxel = 0, kSlide = 1, kPress = 2 };

  // config c's steps while the tip moves (`motion`; two warm-up steps), their times and how
  // many superposed when asked; the last field
  std::vector<Vec3f> moving(const DeformConfig& c, std::vector<double>* relax, std::vector<double>* total,
                            DeformStats& st, DeformMemory* mem, Motion motion = Motion::kVoxel,
                            int* superposed = nullptr) const {
    const int reps = gpu ? (o.quick ? 24 : 120) : (o.quick ? 2 : 6);
    auto m = make_deform_backend(name);
    m->bind(phantom, c);
    for (int r = -2; r < reps; ++r) {
      const int s = r + 2;
      st = m->step(motion == Motion::kSlide ? sliding(s) : motion == Motion::kPress ? pressing(s) : contact(X, s));
      if (r < 0 || !relax) continue;
      relax->push_back(st.times.relax_ms);
      total->push_back(st.times.total_ms);
      if (superposed) *superposed += st.elastic.superposed;
    }
    if (mem) *mem = m->memory();
    return m->displacement();
  }

  // what a row of `motion` is called
  static const char* motion_words(Motion motion) {
    return motion == Motion::kSlide ? "tip sliding half a voxel"
           : motion == Motion::kPress ? "tip pressing 0.05 mm a step"
                                      : "tip moving a voxel";
  }

  // while the tip moves a voxel: with the unit press (the elastic force model) and without
  // (eq. 2's force), each from the last field alone and predicted (deform.elastic.predict);
  // then sliding and pressing 0.05 mm a step with the shipped settings; each row's last
  // field, force and stiffness against the same steps converged (tolerance 1e-6, 12 contact
  // rounds: the history only picks the VOI)
  void moving_rows(std::vector<ElasticRow>& rows) const {
    const DeformConfig conv = converged();
    // each motion's steps converged (indexed by Motion)
    struct Reference {
      std::vector<Vec3f> u;
      DeformStats st;
    };
    Reference refs[3];
    for (const Motion m : {Motion::kVoxel, Motion::kSlide, Motion::kPress}) {
      Reference& ref = refs[int(m)];
      ref.u = moving(conv, nullptr, nullptr, ref.st, nullptr, m);
    }
    struct Moving {
      bool stiffness, predict;
      double stiffness_tolerance;  // 0: the unit press to the round's tolerance
      Motion motion;
    };
    const double unit_tol = o.elastic.stiffness_tolerance;  // the shipped rows' (the scenes' 0.01 by default)
    const Motion vox = Motion::kVoxel;
    for (const Moving& mv : {Moving{true, false, 0, vox}, Moving{true, true, 0, vox}, Moving{true, true, unit_tol, vox},
                             Moving{false, false, 0, vox}, Moving{false, true, 0, vox},
                             Moving{true, true, unit_tol, Motion::kSlide}, Moving{true, true, unit_tol, Motion::kPress}}) {
      DeformConfig c = cfg;
      c.elastic_stiffness = mv.stiffness;
      c.settings.elastic.predict = mv.predict;
      c.settings.elastic.stiffness_tolerance = mv.stiffness_tolerance;
      std::vector<double> relax, total;
      DeformStats st;
      DeformMemory mem;
      int superposed = 0;
      const std::vector<Vec3f> u = moving(c, &relax, &total, st, &mem, mv.motion, &superposed);
      const Reference& ref = refs[int(mv.motion)];
      ElasticRow r = row(std::string(motion_words(mv.motion)) + (mv.stiffness ? "" : ", no unit press") +
                             (mv.predict ? ", predicted" : "") +
                             (mv.stiffness_tolerance > 0 ? reciprocal_words(mv.stiffness_tolerance) : ""),
                         relax, total, st, mem);
      against(r, u, st, ref.u, ref.st, mv.stiffness);
      r.superposed_pct = relax.empty() ? -1 : 100.0 * superposed / double(relax.size());
      rows.push_back(r);
    }
  }

  // 16 sessions begun together, the tip moving a voxel, predicted or not (and the unit press
  // to `stiffness_tolerance` with the force by reciprocity, the shipped settings, above 0),
  // each with the share the server gives it
  ElasticRow sessions_row(bool predict, double stiffness_tolerance = 0) const {
    const int n = 16, rounds = o.quick ? 10 : 50;
    std::vector<std::unique_ptr<DeformBackend>> sessions;
    for (int s = 0; s < n; ++s) {
      sessions.push_back(make_deform_backend(name));
      DeformConfig c = cfg;
      c.settings.elastic.predict = predict;
      c.settings.elastic.stiffness_tolerance = stiffness_tolerance;
      sessions.back()->bind(phantom, c);
      sessions.back()->set_gpu_share(n);
    }
    auto at = [&](int s) { return X + Vec3{0, 0, 8.0 * (s - n / 2)}; };
    std::vector<double> relax, total;
    DeformStats st;
    auto t0 = std::chrono::steady_clock::now();
    for (int r = -2; r < rounds; ++r) {
      if (r == 0) t0 = std::chrono::steady_clock::now();
      for (int s = 0; s < n; ++s) sessions[s]->begin_step(contact(at(s), r + 2));
      for (int s = 0; s < n; ++s) {
        st = sessions[s]->end_step();
        if (r < 0) continue;
        relax.push_back(st.times.relax_ms);
        total.push_back(st.times.total_ms);
      }
    }
    const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    ElasticRow r = row(std::string("16 sessions begun together, tip moving a voxel") + (predict ? ", predicted" : "") +
                           (stiffness_tolerance > 0 ? reciprocal_words(stiffness_tolerance) : ""),
                       relax, total, st, sessions[0]->memory());
    r.sessions = n;
    r.steps_per_s = rounds / wall_s;
    return r;
  }
};

// one elastic row as the bench prints it, with its goal on cuda
void print_elastic_row(const ElasticRow& r, bool gpu) {
  std::printf("elastic %-4s VOI %d %-45s median ms: relax %.3f (p10 %.3f, p90 %.3f)  total %.3f  CG steps %d + %d "
              "(unit press), %d round%s, %d contact nodes, F %.3f N, own %.1f MiB, shared scratch %.1f MiB",
              r.backend.c_str(), r.voi, r.what.c_str(), r.relax.median, r.relax.p10, r.relax.p90, r.total.median,
              r.iterations, r.stiffness_iterations, r.rounds, r.rounds == 1 ? "" : "s", r.contact_nodes, r.force_n,
              r.own_mb, r.shared_mb);
  if (r.sessions > 1) std::printf(", %.0f steps/s per session", r.steps_per_s);
  if (r.u_err_pct >= 0) std::printf("; against converged: u %.2f %%, F %+.2f %%", r.u_err_pct, r.force_err_pct);
  if (r.u_err_pct >= 0 && r.stiffness) std::printf(", stiffness %+.2f %%", r.stiffness_err_pct);
  if (r.superposed_pct >= 0) std::printf("; %.0f %% superposed", r.superposed_pct);
  std::printf("\n");
  if (!gpu) return;
  if (r.what.rfind("from rest", 0) == 0) std::printf("       [goal: at most 2 ms from rest]\n");
  if (r.what.rfind("tip moving a voxel", 0) == 0 || r.what.rfind("tip sliding", 0) == 0 ||
      r.what.rfind("tip pressing", 0) == 0)
    std::printf("       [goal: at most 1 ms while the tip moves, aim 0.5 ms]\n");
  if (r.sessions > 1) std::printf("       [goal: 16 sessions at 300 steps/s or more each, at most 32 MB per session]\n");
}

// one backend's elastic rows (ElasticBench), printed as they are added
void elastic_rows(const std::string& name, const Options& o, const PatientPtr& phantom, const test::Press& press,
                  std::vector<ElasticRow>& rows) {
  const ElasticBench b(name, o, phantom, press);
  const std::size_t first = rows.size();
  rows.push_back(b.from_rest());
  rows.push_back(b.from_rest(o.elastic.stiffness_tolerance));
  b.moving_rows(rows);
  // on cuda: 16 sessions as the server steps them, from the last field alone, predicted, and
  // with the shipped settings
  if (b.gpu) {
    rows.push_back(b.sessions_row(false));
    rows.push_back(b.sessions_row(true));
    rows.push_back(b.sessions_row(true, o.elastic.stiffness_tolerance));
  }
  for (std::size_t i = first; i < rows.size(); ++i) print_elastic_row(rows[i], b.gpu);
  std::fflush(stdout);
}

}  // namespace

PALPSIM_BENCH(deform, "ChainMail Table 2, per-stage Table 1 and the elastic step on cpu and cuda [--json FILE] [--quick] "
                      "[--commit C] [--backend cpu|cuda] [--untangle] [--elastic: the elastic rows alone] [--elastic-unit-tolerance T: "
                      "the shipped rows' unit press tolerance, 0.01] [--elastic-degrees F,C,L: "
                      "the V-cycle's Chebyshev degrees]; "
                      "--accuracy [--ref-voi N] [--study KNOB] [--backend B]: accuracy vs time of relaxation, multigrid, "
                      "inversion and VOI (deform_accuracy.h)") {
  Options o;
  bool accuracy = false;  // the accuracy-vs-time study instead of Tables 1 and 2
  int ref_voi = bench::AccuracyOptions{}.ref_voi_edge;
  std::string study;  // accuracy: one knob's study only ("" = all)
  for (int a = 1; a < argc; ++a) {
    const std::string s = argv[a];
    if (s == "--json" && a + 1 < argc) o.json = argv[++a];
    else if (s == "--commit" && a + 1 < argc) o.commit = argv[++a];
    else if (s == "--quick") o.quick = true;
    else if (s == "--backend" && a + 1 < argc) o.only = argv[++a];
    else if (s == "--untangle") o.untangle = true;
    else if (s == "--elastic") o.elastic_only = true;
    else if (s == "--elastic-degrees" && a + 1 < argc) {
      ElasticSettings& e = o.elastic;
      if (std::sscanf(argv[++a], "%d,%d,%d", &e.smooth_degree, &e.coarse_smooth_degree, &e.coarsest_degree) != 3) {
        std::fprintf(stderr, "palpsim-bench deform: --elastic-degrees wants F,C,L (three integers), not '%s'\n", argv[a]);
        return 2;
      }
    }
    else if (s == "--elastic-unit-tolerance" && a + 1 < argc) {
      o.elastic.stiffness_tolerance = std::atof(argv[++a]);
      if (!(o.elastic.stiffness_tolerance > 0 && o.elastic.stiffness_tolerance < 1)) {
        std::fprintf(stderr, "palpsim-bench deform: --elastic-unit-tolerance wants a relative residual in (0, 1), not '%s'\n",
                     argv[a]);
        return 2;
      }
    }
    else if (s == "--accuracy") accuracy = true;
    else if (s == "--ref-voi" && a + 1 < argc) ref_voi = std::atoi(argv[++a]);
    else if (s == "--study" && a + 1 < argc) study = argv[++a];
    else {
      std::fprintf(stderr, "palpsim-bench deform: unknown argument '%s'\n", s.c_str());
      return 2;
    }
  }
  try {
    // the accuracy study (bench/deform_accuracy_bench.cpp)
    if (accuracy) {
      bench::AccuracyOptions ao;
      ao.json = o.json;
      ao.commit = o.commit;
      ao.quick = o.quick;
      ao.voxel_mm = o.voxel_mm;
      ao.ref_voi_edge = ref_voi;
      ao.study = study;
      ao.backend = o.only;
      return bench::run_deform_accuracy(ao);
    }
    // every backend this build and machine have
    std::string device;
    const std::vector<std::string> backends = bench::deform_backends(device, "deform bench", o.only);

    std::vector<Table2Row> t2;
    if (!o.elastic_only)
      for (const auto& b : backends) table2(b, o, t2);

    auto t0 = std::chrono::steady_clock::now();
    PhantomCt ct = make_phantom(o.voxel_mm);
    const test::Press press = test::spinous_press(ct.geometry);
    const PatientPtr patient = test::patient_from_intensity(Volume<float>(ct.hu), "phantom");
    std::printf("phantom %d x %d x %d at %.3f mm (%.1f s to make)\n", patient->grid.size.x, patient->grid.size.y,
                patient->grid.size.z, o.voxel_mm,
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    std::vector<Table1Row> t1;
    if (!o.elastic_only)
      for (const auto& b : backends) table1(b, o, patient, t1);

    // the elastic model needs the body mask and B as well
    t0 = std::chrono::steady_clock::now();
    const PatientPtr elastic_patient = test::elastic_phantom(std::move(ct));
    std::printf("phantom's body mask and B (%.1f s)\n",
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    std::printf("elastic model: the V-cycle's Chebyshev degrees %d (finest), %d (coarse), %d (coarsest)\n",
                o.elastic.smooth_degree, o.elastic.coarse_smooth_degree, o.elastic.coarsest_degree);
    std::vector<ElasticRow> el;
    for (const auto& b : backends) elastic_rows(b, o, elastic_patient, press, el);

    if (!o.json.empty()) {
      std::ofstream f(o.json);
      if (!f) throw Error("palpsim-bench deform: cannot write --json " + o.json);
      const std::time_t now = std::time(nullptr);
      char date[32];
      std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
      f << "{\n  \"area\": \"deform\",\n  \"date\": \"" << date << "\",\n  \"device\": \"" << device
        << "\",\n  \"commit\": \"" << o.commit << "\",\n  \"quick\": " << (o.quick ? "true" : "false")
        << ",\n  \"phantom\": {\"voxel_mm\": " << o.voxel_mm << ", \"size\": [" << patient->grid.size.x << ", "
        << patient->grid.size.y << ", " << patient->grid.size.z << "]},\n  \"elastic_degrees\": [" << o.elastic.smooth_degree
        << ", " << o.elastic.coarse_smooth_degree << ", " << o.elastic.coarsest_degree
        << "],\n  \"elastic_unit_tolerance\": " << o.elastic.stiffness_tolerance << ",\n  \"table2\": [\n";
      for (std::size_t i = 0; i < t2.size(); ++i) {
        const auto& r = t2[i];
        f << "    {\"backend\": \"" << r.backend << "\", \"preset\": \"p" << r.preset << "\", \"d\": " << r.d
          << ", \"moved\": " << r.moved << ", \"sweeps\": " << r.sweeps
          << ", \"converged\": " << (r.converged ? "true" : "false") << ", \"chainmail\": " << json_spread(r.chainmail)
          << ", \"wall\": " << json_spread(r.wall) << "}" << (i + 1 < t2.size() ? "," : "") << "\n";
      }
      f << "  ],\n  \"table1\": [\n";
      for (std::size_t i = 0; i < t1.size(); ++i) {
        const auto& r = t1[i];
        f << "    {\"backend\": \"" << r.backend << "\", \"voi\": \"" << r.voi << "\", \"voxels\": " << r.voxels
          << ", \"moved\": " << r.moved << ", \"invert_residual_vox\": " << r.residual << ", \"invert_unresolved\": " << r.unresolved
          << ", \"reset\": " << json_spread(r.reset) << ", \"chainmail\": " << json_spread(r.chainmail)
          << ", \"folded_before\": " << r.folded_before << ", \"folded_after\": " << r.folded_after
          << ", \"relax\": " << json_spread(r.relax) << ", \"untangle\": " << json_spread(r.untangle)
          << ", \"invert\": " << json_spread(r.invert)
          << ", \"upload\": " << json_spread(r.upload) << ", \"total\": " << json_spread(r.total) << "}"
          << (i + 1 < t1.size() ? "," : "") << "\n";
      }
      f << "  ],\n  \"elastic\": [\n";
      for (std::size_t i = 0; i < el.size(); ++i) {
        const auto& r = el[i];
        f << "    {\"backend\": \"" << r.backend << "\", \"what\": \"" << r.what << "\", \"voi\": " << r.voi
          << ", \"sessions\": " << r.sessions << ", \"iterations\": " << r.iterations
          << ", \"stiffness_iterations\": " << r.stiffness_iterations << ", \"rounds\": " << r.rounds
          << ", \"contact_nodes\": " << r.contact_nodes
          << ", \"force_n\": " << bench::json_number(r.force_n) << ", \"relax\": " << json_spread(r.relax)
          << ", \"total\": " << json_spread(r.total) << ", \"steps_per_s_per_session\": "
          << bench::json_number(r.steps_per_s) << ", \"own_mib\": " << bench::json_number(r.own_mb)
          << ", \"shared_scratch_mib\": " << bench::json_number(r.shared_mb)
          << ", \"vs_converged\": {\"u_pct\": " << bench::json_number(r.u_err_pct) << ", \"force_pct\": "
          << bench::json_number(r.force_err_pct) << ", \"stiffness_pct\": " << bench::json_number(r.stiffness_err_pct)
          << "}, \"superposed_pct\": " << bench::json_number(r.superposed_pct) << "}" << (i + 1 < el.size() ? "," : "")
          << "\n";
      }
      f << "  ]\n}\n";
      std::printf("wrote %s\n", o.json.c_str());
    }
  } catch (const Error& e) {
    std::fprintf(stderr, "palpsim-bench deform: %s\n", e.what());
    return 1;
  }
  return 0;
}
