// palpsim-bench server: many sessions deforming on one server (issue 10). For each
// session count, that many haptic clients press at 1 kHz (bench/press_load.h) on a
// server in this process whose scene asks for ChainMail, relaxation and inversion (no
// frames); each session's deformation steps per second, its dropped contacts, its own
// memory and the patient's shared copy come from the server's stats, and the haptic
// round trip is set beside the same clients on a server without deformation, in rounds
// of (without, with) back to back. Goal on the H100 at VOI 64: each of 16 sessions at
// least 500 steps/s, each of 64 at least 120, at most 16 MB per added session, round
// trip p99 within 1.3x of the run without deformation.
#include <algorithm>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <mutex>
#include <sstream>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "bench/press_load.h"
#include "bench/registry.h"
#include "bench/stats.h"
#include "core/error.h"
#include "deform/backend.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "palpsim/wire.pb.h"
#include "prep/prepare.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using bench::control;
using bench::json_number;
using bench::machine;
using bench::quantile;

namespace {

struct Options {
  std::string json;
  std::string commit = "unknown";  // the build's commit, copied into the JSON
  std::string scene = std::string(PALPSIM_SOURCE_DIR) + "/config/scenes/lumbar_phantom.textproto";
  std::vector<int> sessions{1, 4, 16, 64};
  double seconds = 5;          // pressing per run, after the 0.2 s warm-up
  int rounds = 1;              // rounds of (without, with deformation) per session count
  int voi_edge = 64;           // deform.voi_edge (voxel)
  std::string backend;         // deform.backend ("" = the scene's)
  int nice = 19;               // the deformation worker's nice value
  bool idle = true;            // and SCHED_IDLE for it (the server's --background idle)
  int concurrency = net::ServerOptions{}.deform_concurrency;  // steps in flight at once
  int batch = net::ServerOptions{}.deform_batch;              // sessions sharing one launch per stage, at most
};

// one session count: what each session got and what the server held
struct Row {
  int sessions = 0;
  std::string backend;
  std::vector<double> steps_per_s;     // per session, over its pressing time
  std::vector<double> served_per_s;    // per session: contacts stepped or already current (no step needed), per second
  std::vector<double> contact_share;   // per session: share of its pressing time in the body
  std::vector<double> steps_per_contact_s;  // per session, over its time in the body (steps are asked for only then)
  std::vector<double> solve_share;     // per session, multigrid scenes: steps that solved, of all
  std::vector<double> superposed_share;  // per session, elastic scenes: steps that superposed, of all
  std::vector<double> stage_ms[5];     // per session, mean per step: reset, ChainMail, relax, invert, upload (a batch's share)
  std::vector<double> dropped_share;   // per session: contacts dropped / (steps + dropped)
  std::vector<double> step_ms;         // per session: mean whole step (ms)
  std::vector<double> own_bytes;       // per session: its engine's own memory
  double server_bytes = 0;             // every deformation stage, server-wide, with all sessions open
  // of the deformation thread's time over the runs with deformation (not the runs without,
  // when the server has no session and its worker naps): in steps (enqueueing, waiting for
  // the GPU), napping for want of a new contact (every press client is above the body about
  // a quarter of each 1 Hz press, all in phase), and the rest (passes, reports)
  double worker_step_share = 0, worker_sleep_share = 0;
  double batched_share = 0, mean_batch = 0;  // steps run in batches, of all; their mean batch size
  std::vector<double> rtt_with, rtt_without;  // round trips (us), pooled over rounds
  std::vector<double> ratios;          // per round: p99 with / p99 without deformation
};

// reads the command line into `o`; false after printing the usage (--help)
bool parse_options(int argc, char** argv, Options& o) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw Error("palpsim-bench server: " + a + " needs a value");
      return argv[++i];
    };
    if (a == "--json") o.json = value();
    else if (a == "--commit") o.commit = value();
    else if (a == "--scene") o.scene = value();
    else if (a == "--seconds") o.seconds = std::stod(value());
    else if (a == "--rounds") o.rounds = std::max(1, std::stoi(value()));
    else if (a == "--voi") o.voi_edge = std::stoi(value());
    else if (a == "--backend") o.backend = value();
    else if (a == "--nice") o.nice = std::stoi(value());
    else if (a == "--concurrency") o.concurrency = std::max(1, std::stoi(value()));
    else if (a == "--batch") o.batch = std::min(64, std::max(1, std::stoi(value())));
    else if (a == "--background") {
      const std::string p = value();
      if (p != "idle" && p != "nice") throw Error("palpsim-bench server: --background " + p + ": expected idle or nice");
      o.idle = p == "idle";
    }
    else if (a == "--sessions") {
      o.sessions.clear();
      std::stringstream ss(value());
      for (std::string item; std::getline(ss, item, ',');) o.sessions.push_back(std::stoi(item));
    } else if (a == "--help" || a == "-h") {
      std::printf(
          "usage: palpsim-bench server [--sessions 1,4,16,64] [--seconds S per run (5)] [--rounds N (1)]\n"
          "                            [--voi EDGE (64)] [--backend auto|cpu|cuda] [--nice N (19)]\n"
          "                            [--background idle|nice (idle, as palpsim-server)] [--concurrency K] [--batch N (64)]\n"
          "                            [--scene FILE] [--json FILE] [--commit C]\n");
      return false;
    } else {
      throw Error("palpsim-bench server: unknown argument '" + a + "'");
    }
  }
  return true;
}

// the servers' options: free loopback ports, the worker's priority, concurrency and batches;
// one bench client opens every session, so its quota is the scene's max_sessions
net::ServerOptions server_options(const Options& o, int max_sessions) {
  net::ServerOptions so;
  so.control_bind = "tcp://127.0.0.1:*";
  so.pose_bind = "tcp://127.0.0.1:*";
  so.stream_bind = "tcp://127.0.0.1:*";
  so.deform_nice = o.nice;
  so.background_idle = o.idle;
  so.deform_concurrency = o.concurrency;
  so.deform_batch = o.batch;
  so.max_sessions_per_client = max_sessions;
  return so;
}

// one session count's row on stdout: stage times, steps, batching, memory and round trips
void print_row(const Row& r, const Options& o) {
  const int n = r.sessions;
  double gpu_ms = 0;  // the stages' sum: the step's share of the batch's GPU time
  for (int k = 0; k < 5; ++k) gpu_ms += quantile(r.stage_ms[k], 0.5);
  std::printf("%2d sessions: mean stage times per step (ms, a batch's share), medians over sessions: reset %.4f "
              "ChainMail %.4f relax %.4f invert %.4f upload/counters %.4f, GPU %.4f of a %.4f ms step\n",
              n, quantile(r.stage_ms[0], 0.5), quantile(r.stage_ms[1], 0.5), quantile(r.stage_ms[2], 0.5),
              quantile(r.stage_ms[3], 0.5), quantile(r.stage_ms[4], 0.5), gpu_ms, quantile(r.step_ms, 0.5));
  const double own_mb = quantile(r.own_bytes, 0.5) / (1 << 20);
  std::printf(
      "%2d sessions (%s, VOI %d, %s, %d in flight, batches of up to %d): steps/s per session min %.0f median %.0f "
      "(in the body %.0f%% of the time: %.0f per second of contact); "
      "%.0f%% of steps batched, %.1f sessions a batch; step %.3f ms; dropped %.0f%%; worker in steps %.0f%%, napping %.0f%%; own "
      "memory %.1f MB per session, deformation server-wide %.1f MB; round trip p50 %.0f / p99 %.0f us with "
      "deformation, p99 %.0f us without (ratio %.2f, median of %zu rounds)\n",
      n, r.backend.c_str(), o.voi_edge, o.idle ? "SCHED_IDLE" : "nice", o.concurrency, o.batch,
      r.steps_per_s.empty() ? 0.0 : *std::min_element(r.steps_per_s.begin(), r.steps_per_s.end()),
      quantile(r.steps_per_s, 0.5), 100 * quantile(r.contact_share, 0.5), quantile(r.steps_per_contact_s, 0.5),
      100 * r.batched_share, r.mean_batch, quantile(r.step_ms, 0.5), 100 * quantile(r.dropped_share, 0.5), 100 * r.worker_step_share,
      100 * r.worker_sleep_share, own_mb,
      r.server_bytes / (1 << 20), quantile(r.rtt_with, 0.5), quantile(r.rtt_with, 0.99),
      quantile(r.rtt_without, 0.99), quantile(r.ratios, 0.5), r.ratios.size());
  if (!r.solve_share.empty())
    std::printf("%2d sessions: multigrid steps that solved (not reusing the unit response), median over sessions: %.1f%%\n",
                n, 100 * quantile(r.solve_share, 0.5));
  if (!r.superposed_share.empty())
    std::printf("%2d sessions: elastic steps that superposed the unit press (no solve), median over sessions: %.1f%%\n",
                n, 100 * quantile(r.superposed_share, 0.5));
  // contacts J already stood for (a held tip, an elastic press held short of bone) need no
  // step: served with the steps, they are what a session got
  std::printf("%2d sessions: contacts served per second per session (stepped, or already current), min %.0f median %.0f\n",
              n, r.served_per_s.empty() ? 0.0 : *std::min_element(r.served_per_s.begin(), r.served_per_s.end()),
              quantile(r.served_per_s, 0.5));
}

// memory per added session: the growth of the server's deformation memory over counts
void print_memory_growth(const std::vector<Row>& rows) {
  for (std::size_t i = 1; i < rows.size(); ++i) {
    const double added = double(rows[i].sessions - rows[i - 1].sessions);
    if (added > 0)
      std::printf("memory per added session, %d -> %d sessions: %.1f MB\n", rows[i - 1].sessions, rows[i].sessions,
                  (rows[i].server_bytes - rows[i - 1].server_bytes) / added / (1 << 20));
  }
}

// the rows as --json
void write_json(const Options& o, const std::vector<Row>& rows) {
  std::ofstream out(o.json);
  if (!out) throw Error("palpsim-bench server: cannot write --json " + o.json);
  char date[32];
  const std::time_t now = std::time(nullptr);
  std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
  out << "{\n  \"bench\": \"server\",\n  \"commit\": \"" << o.commit << "\",\n  \"date\": \"" << date
      << "\",\n  \"machine\": \"" << machine()
      << "\",\n  \"background\": \"" << (o.idle ? "idle" : "nice") << "\",\n  \"concurrency\": " << o.concurrency << ",\n  \"batch\": " << o.batch << ",\n  \"voi_edge\": " << o.voi_edge << ",\n  \"seconds\": " << json_number(o.seconds)
      << ",\n  \"rows\": [\n";
  for (std::size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    out << "    {\"sessions\": " << r.sessions << ", \"backend\": \"" << r.backend << "\", \"steps_per_s_min\": "
        << json_number(r.steps_per_s.empty() ? 0.0 : *std::min_element(r.steps_per_s.begin(), r.steps_per_s.end()))
        << ", \"steps_per_s_median\": " << json_number(quantile(r.steps_per_s, 0.5))
        << ", \"served_per_s_median\": " << json_number(quantile(r.served_per_s, 0.5))
        << ", \"contact_share_median\": " << json_number(quantile(r.contact_share, 0.5))
        << ", \"steps_per_contact_s_median\": " << json_number(quantile(r.steps_per_contact_s, 0.5))
        << ", \"multigrid_solve_share_median\": " << json_number(quantile(r.solve_share, 0.5))
        << ", \"elastic_superposed_share_median\": " << json_number(quantile(r.superposed_share, 0.5))
        << ", \"step_ms_median\": " << json_number(quantile(r.step_ms, 0.5))
        << ", \"stage_ms_median\": {\"reset\": " << json_number(quantile(r.stage_ms[0], 0.5))
        << ", \"chainmail\": " << json_number(quantile(r.stage_ms[1], 0.5))
        << ", \"relax\": " << json_number(quantile(r.stage_ms[2], 0.5))
        << ", \"invert\": " << json_number(quantile(r.stage_ms[3], 0.5))
        << ", \"upload\": " << json_number(quantile(r.stage_ms[4], 0.5)) << "}"
        << ", \"dropped_share_median\": " << json_number(quantile(r.dropped_share, 0.5))
        << ", \"worker_step_share\": " << json_number(r.worker_step_share)
        << ", \"worker_sleep_share\": " << json_number(r.worker_sleep_share)
        << ", \"batched_share\": " << json_number(r.batched_share) << ", \"mean_batch\": " << json_number(r.mean_batch)
        << ", \"own_bytes_median\": " << json_number(quantile(r.own_bytes, 0.5))
        << ", \"deform_bytes_server\": " << json_number(r.server_bytes)
        << ", \"rtt_p50_us_with\": " << json_number(quantile(r.rtt_with, 0.5))
        << ", \"rtt_p99_us_with\": " << json_number(quantile(r.rtt_with, 0.99))
        << ", \"rtt_p50_us_without\": " << json_number(quantile(r.rtt_without, 0.5))
        << ", \"rtt_p99_us_without\": " << json_number(quantile(r.rtt_without, 0.99))
        << ", \"rtt_p99_ratio_median_of_rounds\": " << json_number(quantile(r.ratios, 0.5)) << "}"
        << (i + 1 < rows.size() ? ",\n" : "\n");
  }
  out << "  ]\n}\n";
  std::printf("wrote %s\n", o.json.c_str());
}

int run(int argc, char** argv) {
  Options o;
  if (!parse_options(argc, argv, o)) return 0;
  const Scene base = load_scene_file(o.scene);
  PrepReport report;
  const PatientPtr patient = prepare_patient(base, &report);
  std::printf("patient: %s, %d x %d x %d at %.2f mm\nmachine: %s\n", patient->source.c_str(), patient->grid.size.x,
              patient->grid.size.y, patient->grid.size.z, patient->grid.spacing_mm.x, machine().c_str());
  spdlog::set_level(spdlog::level::warn);

  // two servers on the same patient: with deformation, and haptics only
  Scene deform = base;
  deform.effects.chainmail = deform.effects.relaxation = deform.effects.inversion = true;
  deform.effects.frames = deform.effects.bricks = false;
  deform.deform.voi_edge = o.voi_edge;
  if (!o.backend.empty()) deform.deform.backend = deform_backend_choice(o.backend);
  const int most = *std::max_element(o.sessions.begin(), o.sessions.end());
  deform.server.max_sessions = std::max(deform.server.max_sessions, most);
  Scene plain = deform;
  plain.effects.chainmail = plain.effects.relaxation = plain.effects.inversion = false;
  const net::ServerOptions so = server_options(o, deform.server.max_sessions);
  net::Server with(deform, patient, nullptr, so), without(plain, patient, nullptr, so);
  with.start();
  without.start();
  zmq::context_t ctx(1);
  zmq::socket_t ctl(ctx, zmq::socket_type::req);
  ctl.connect(with.control_endpoint());
  v1::ControlRequest iq;
  iq.mutable_info();
  const v1::PatientInfo pi = control(ctl, iq).info().patient();

  std::vector<Row> rows;
  for (int n : o.sessions) {
    Row row;
    row.sessions = n;
    std::mutex mu;
    v1::ControlRequest sq;
    sq.mutable_stats();
    double wall = 0, step_s = 0, sleep_s = 0, steps = 0, batched = 0, batches = 0;
    for (int round = 0; round < o.rounds; ++round) {
      // haptics only, then the same clients with deformation
      const bench::PressResult a = bench::press_sessions(without.control_endpoint(), pi, n, o.seconds);
      std::vector<double> steps_of(std::size_t(n), 0.0);  // each client's session's steps
      const v1::ServerStats before = control(ctl, sq).stats().server();
      const bench::PressResult b = bench::press_sessions(
          with.control_endpoint(), pi, n, o.seconds, nullptr, {}, [&](int c, zmq::socket_t& s, std::uint64_t id) {
            v1::ControlRequest q;
            q.mutable_stats()->set_session_id(id);
            const v1::ControlReply r = control(s, q);
            const v1::DeformSessionStats& d = r.stats().session().deform();
            const double pressing_s = o.seconds + 0.2;  // the warm-up steps too
            std::lock_guard<std::mutex> lock(mu);
            row.backend = d.backend();
            row.steps_per_s.push_back(double(d.steps()) / pressing_s);
            row.served_per_s.push_back(double(d.steps() + d.contacts_current()) / pressing_s);
            steps_of[std::size_t(c)] = double(d.steps());
            if (d.steps() > 0 && d.multigrid_solves() > 0)
              row.solve_share.push_back(double(d.multigrid_solves()) / double(d.steps()));
            if (d.steps() > 0 && d.has_elastic())
              row.superposed_share.push_back(double(d.elastic_superposed()) / double(d.steps()));
            const double offered = double(d.steps() + d.contacts_dropped());
            row.dropped_share.push_back(offered > 0 ? double(d.contacts_dropped()) / offered : 0.0);
            row.step_ms.push_back(d.mean().total_ms());
            const v1::DeformTimes& m = d.mean();
            const double stage[5] = {m.reset_ms(), m.chainmail_ms(), m.relax_ms(), m.invert_ms(), m.upload_ms()};
            for (int k = 0; k < 5; ++k) row.stage_ms[k].push_back(stage[k]);
            row.own_bytes.push_back(double(d.bytes_allocated()));
            // the server's memory once, while every session is still open
            if (c == 0 && round == 0) {
              v1::ControlRequest sq;
              sq.mutable_stats();
              const v1::ServerStats st = control(s, sq).stats().server();
              for (const auto& stage : st.stages())
                if (stage.name() == "chainmail" || stage.name() == "relaxation" || stage.name() == "inversion")
                  row.server_bytes += double(stage.bytes_allocated());
            }
          });
      // each session's steps over its client's time in the body (a pose a millisecond)
      for (int c = 0; c < n; ++c) {
        const double contact_s = 1e-3 * double(b.contact_poses[std::size_t(c)]);
        row.contact_share.push_back(contact_s / (o.seconds + 0.2));
        if (contact_s > 0) row.steps_per_contact_s.push_back(steps_of[std::size_t(c)] / contact_s);
      }
      // the worker's time over this run with deformation
      const v1::ServerStats after = control(ctl, sq).stats().server();
      wall += after.deform_worker_wall_s() - before.deform_worker_wall_s();
      step_s += after.deform_worker_step_s() - before.deform_worker_step_s();
      sleep_s += after.deform_worker_sleep_s() - before.deform_worker_sleep_s();
      steps += double(after.deform_steps() - before.deform_steps());
      batched += double(after.deform_batched_steps() - before.deform_batched_steps());
      batches += double(after.deform_batches() - before.deform_batches());
      std::vector<double> ra, rb;
      for (const auto& v : a.rtt_us) ra.insert(ra.end(), v.begin(), v.end());
      for (const auto& v : b.rtt_us) rb.insert(rb.end(), v.begin(), v.end());
      const double pa = quantile(ra, 0.99);
      if (pa > 0) row.ratios.push_back(quantile(rb, 0.99) / pa);
      row.rtt_without.insert(row.rtt_without.end(), ra.begin(), ra.end());
      row.rtt_with.insert(row.rtt_with.end(), rb.begin(), rb.end());
    }
    if (wall > 0) {
      row.worker_step_share = step_s / wall;
      row.worker_sleep_share = sleep_s / wall;
    }
    row.batched_share = steps > 0 ? batched / steps : 0.0;
    row.mean_batch = batches > 0 ? batched / batches : 1.0;
    rows.push_back(row);
    print_row(rows.back(), o);
    std::fflush(stdout);
  }
  with.stop();
  without.stop();

  print_memory_growth(rows);

  if (!o.json.empty()) write_json(o, rows);
  return 0;
}

}  // namespace

PALPSIM_BENCH(server, "many sessions deforming on one server: steps/s per session, memory, haptic round trip") {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-bench server: %s\n", e.what());
    return 1;
  }
}
