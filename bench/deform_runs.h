// Shared by the accuracy benches (deform_accuracy_bench.cpp, elastic_accuracy_bench.cpp):
// timing settings on a deformation backend (any make_deform_backend() name), presses reached
// a voxel at a time, fields carried between VOIs, and the small JSON and shell helpers.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "bench/stats.h"
#include "core/error.h"
#include "deform/approach.h"
#include "deform/backend.h"

namespace palpsim::bench {

using deform::Voi;

/// The stage whose time a run reports beside the whole step's.
enum class Stage { relax, invert, total };

/// One setting run on one backend: times of whole steps and of one stage, and what the last step left.
struct Run {
  Spread step_ms, stage_ms;
  int reps = 0;
  DeformStats last;
  std::vector<Vec3f> u;  // displacement after the last step (VOI, i fastest)
  std::vector<float> J;  // J on the VOI (empty without inversion)
};

/// Runs the settings `cfgs` on one backend, one engine each, timed round-robin (every
/// repetition steps each setting once) so that load from other processes on a shared
/// machine spreads over all settings instead of skewing the ones that ran during it.
/// The repetitions take `contacts` in turn, backwards, so that the last one is contacts[0]
/// (two contacts a voxel apart: every step enters another voxel).
inline std::vector<Run> run_settings(const std::string& backend, const PatientPtr& patient,
                              const std::vector<DeformConfig>& cfgs, const std::vector<DeformContact>& contacts,
                              int warmup, int reps, Stage stage) {
  std::vector<std::unique_ptr<DeformBackend>> engines;
  for (const DeformConfig& c : cfgs) {
    engines.push_back(make_deform_backend(backend));
    engines.back()->bind(patient, c);
  }
  std::vector<Run> runs(cfgs.size());
  std::vector<std::vector<double>> step(cfgs.size()), part(cfgs.size());
  const int n_contacts = int(contacts.size());
  for (int i = -warmup; i < reps; ++i)
    for (std::size_t s = 0; s < cfgs.size(); ++s) {
      runs[s].last = engines[s]->step(contacts[(reps - 1 - i) % n_contacts]);
      if (i < 0) continue;
      const DeformTimes& t = runs[s].last.times;
      step[s].push_back(t.total_ms);
      part[s].push_back(stage == Stage::relax ? t.relax_ms : (stage == Stage::invert ? t.invert_ms : t.total_ms));
    }
  for (std::size_t s = 0; s < cfgs.size(); ++s) {
    Run& r = runs[s];
    r.step_ms = spread(step[s]);
    r.stage_ms = spread(part[s]);
    r.reps = reps;
    r.u = engines[s]->displacement();
    if (cfgs[s].invert) r.J.assign(engines[s]->deformed_brick(), engines[s]->deformed_brick() + engines[s]->voi().count());
    if (!r.last.chainmail.converged) throw Error("deform accuracy: ChainMail hit deform.max_sweeps on " + backend);
  }
  return runs;
}

/// run_settings() with every repetition on one contact.
inline std::vector<Run> run_settings(const std::string& backend, const PatientPtr& patient,
                              const std::vector<DeformConfig>& cfgs, const DeformContact& contact, int warmup,
                              int reps, Stage stage) {
  return run_settings(backend, patient, cfgs, std::vector<DeformContact>{contact}, warmup, reps, stage);
}

/// The contact `c` with the tip `k` voxels further along the press (its largest axis in
/// voxel space; k < 0: back towards the skin): each voxel on, the VOI moves (the warm starts' case).
inline DeformContact tip_moved(const Grid& grid, const DeformContact& c, int k) {
  const Vec3 t = grid.to_index(c.tip_mm), d = t - grid.to_index(c.skin_point_mm);
  int a = 0;
  for (int b = 1; b < 3; ++b)
    if (std::fabs(d[b]) > std::fabs(d[a])) a = b;
  Vec3 t2 = t;
  t2[a] += d[a] < 0 ? -k : k;
  return DeformContact{c.skin_point_mm, grid.to_physical(t2)};
}

/// A press reached a voxel at a time: `c` and the tip 1..n-1 voxels short of it, which
/// run_settings() takes from the shallowest to `c` (then back to the shallowest: a jump).
inline std::vector<DeformContact> pressing(const Grid& grid, const DeformContact& c, int n) {
  std::vector<DeformContact> v;
  for (int k = 0; k < n; ++k) v.push_back(tip_moved(grid, c, -k));
  return v;
}

/// One setting, timed alone.
inline Run run_setting(const std::string& backend, const PatientPtr& patient, const DeformConfig& cfg,
                const DeformContact& contact, int warmup, int reps, Stage stage) {
  return run_settings(backend, patient, {cfg}, contact, warmup, reps, stage).front();
}

/// A session's first step on `contact`, timed: a new engine every repetition; with `hover_mm`,
/// after a prime where a tip hovering there expects to touch (deform::expected_skin_voxel, as
/// the server's worker guesses it), waited for before the step (in the server it runs while
/// the tip approaches): the times are the step's own. `prime_steps` gets the prime's steps.
inline Run run_first_contacts(const std::string& backend, const PatientPtr& patient, const DeformConfig& cfg,
                       const DeformContact& contact, const Vec3* hover_mm, int warmup, int reps, int* prime_steps = nullptr) {
  std::vector<double> step, relax;
  Run r;
  const Vec3 centroid = deform::body_centroid_vox(*patient);
  for (int i = -warmup; i < reps; ++i) {
    auto b = make_deform_backend(backend);
    b->bind(patient, cfg);
    if (hover_mm) {
      Vec3i v;
      if (!deform::expected_skin_voxel(*patient, *hover_mm, cfg.settings.voi_edge / 2, centroid, v))
        throw Error("deform accuracy: no skin voxel below the hovering tip");
      const Vec3 V = patient->grid.to_physical(Vec3(v.x, v.y, v.z));
      const DeformPrime pr = b->prime({V, V});
      if (!pr.solved) throw Error("deform accuracy: the prime solved nothing");
      if (prime_steps) *prime_steps = pr.steps;
      b->wait();
    }
    r.last = b->step(contact);
    if (hover_mm && !r.last.relax_warm) throw Error("deform accuracy: a first contact after a prime did not start warm");
    if (i < 0) continue;
    step.push_back(r.last.times.total_ms);
    relax.push_back(r.last.times.relax_ms);
    if (i + 1 == reps) {
      r.u = b->displacement();
      if (cfg.invert) r.J.assign(b->deformed_brick(), b->deformed_brick() + b->voi().count());
    }
  }
  r.step_ms = spread(step);
  r.stage_ms = spread(relax);
  r.reps = reps;
  return r;
}

/// Sessions' first steps on `contact` for several settings, timed round-robin (every repetition
/// makes a new engine for each setting in turn, as run_settings() spreads a shared machine's
/// load): the times are the first step's, set-up included; u and J are the last repetition's.
inline std::vector<Run> run_first_contacts(const std::string& backend, const PatientPtr& patient,
                                           const std::vector<DeformConfig>& cfgs, const DeformContact& contact,
                                           int warmup, int reps) {
  std::vector<Run> runs(cfgs.size());
  std::vector<std::vector<double>> step(cfgs.size()), relax(cfgs.size());
  for (int i = -warmup; i < reps; ++i)
    for (std::size_t s = 0; s < cfgs.size(); ++s) {
      auto b = make_deform_backend(backend);
      b->bind(patient, cfgs[s]);
      Run& r = runs[s];
      r.last = b->step(contact);
      if (i < 0) continue;
      step[s].push_back(r.last.times.total_ms);
      relax[s].push_back(r.last.times.relax_ms);
      if (i + 1 == reps) {
        r.u = b->displacement();
        if (cfgs[s].invert) r.J.assign(b->deformed_brick(), b->deformed_brick() + b->voi().count());
      }
    }
  for (std::size_t s = 0; s < cfgs.size(); ++s) {
    runs[s].step_ms = spread(step[s]);
    runs[s].stage_ms = spread(relax[s]);
    runs[s].reps = reps;
  }
  return runs;
}

/// RMS and max of |a - b| over two fields on the same VOI (voxel).
struct Diff {
  double rms = 0, max = 0;
};

/// The RMS and max of |a - b| over every element of two fields on the same VOI.
inline Diff field_diff(const std::vector<Vec3f>& a, const std::vector<Vec3f>& b) {
  Diff d;
  double sum = 0;
  for (std::size_t e = 0; e < a.size(); ++e) {
    const Vec3f v = a[e] - b[e];
    const double n2 = double(v.x) * v.x + double(v.y) * v.y + double(v.z) * v.z;
    sum += n2;
    d.max = std::max(d.max, std::sqrt(n2));
  }
  d.rms = a.empty() ? 0 : std::sqrt(sum / double(a.size()));
  return d;
}

/// The field `u` on box `voi` carried onto box `target` (patient voxel indices): 0 where
/// `voi` does not reach; with `strict`, a voxel of `voi` outside `target` throws.
inline std::vector<Vec3f> field_on(const Voi& target, const Voi& voi, const std::vector<Vec3f>& u, bool strict) {
  std::vector<Vec3f> on(std::size_t(target.count()), Vec3f{0, 0, 0});
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const Vec3i r = voi.lo + Vec3i{i, j, k} - target.lo;
        if (!target.contains(r.x, r.y, r.z)) {
          if (strict) throw Error("deform accuracy: a VOI reaches outside the reference VOI");
          continue;
        }
        on[target.index(r.x, r.y, r.z)] = u[voi.index(i, j, k)];
      }
  return on;
}

/// The first "model name" of /proc/cpuinfo, for a JSON's machine description.
inline std::string cpu_model() {
  std::ifstream f("/proc/cpuinfo");
  std::string line;
  while (std::getline(f, line))
    if (line.rfind("model name", 0) == 0) {
      const auto c = line.find(':');
      if (c != std::string::npos) return line.substr(line.find_first_not_of(' ', c + 1));
    }
  return "unknown";
}

/// The string as a JSON string literal (quotes and backslashes escaped, control characters as spaces).
inline std::string json_str(const std::string& s) {
  std::string o = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') o += '\\';
    o += (unsigned char)c < 0x20 ? ' ' : c;
  }
  return o + "\"";
}

/// The first members of a bench JSON, from "{" to the "quick" member and its comma: the area, the
/// date (UTC, now), the device, the host's CPU and threads, the commit and whether the run was quick.
inline std::string json_run_header(const std::string& area, const std::string& device, const std::string& commit,
                                   bool quick) {
  const std::time_t now = std::time(nullptr);
  char date[32];
  std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
  return "{\n  \"area\": " + json_str(area) + ",\n  \"date\": \"" + date + "\",\n  \"device\": " + json_str(device) +
         ",\n  \"host_cpu\": " + json_str(cpu_model()) + ",\n  \"host_threads\": " +
         std::to_string(std::thread::hardware_concurrency()) + ",\n  \"commit\": " + json_str(commit) +
         ",\n  \"quick\": " + (quick ? "true" : "false") + ",";
}

/// Runs `command` through the shell; true when it exited 0.
inline bool run_command(const std::string& command) {
  std::fflush(stdout);
  const int rc = std::system(command.c_str());
  return rc == 0;
}

/// The string quoted for /bin/sh (single quotes).
inline std::string sh_quote(const std::string& s) {
  std::string o = "'";
  for (char ch : s) o += ch == '\'' ? std::string("'\\''") : std::string(1, ch);
  return o + "'";
}

}  // namespace palpsim::bench
