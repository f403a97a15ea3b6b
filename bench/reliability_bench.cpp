// palpsim-bench reliability: the server under hostile and careless clients and faults, run
// as the real processes (palpsim-server, palpsim-haptic) on loopback. Phases (--phases):
// - flood: flooding clients (garbage, malformed and valid poses at 18 kHz each) beside one
//   honest palpsim-haptic at 1 kHz, in several runs (issue 26, finding 9); per run the
//   honest client's lost replies and round trip, and how long each thread of the server,
//   of the honest client and of the flooders waited for a core (Linux schedstat), which
//   tells starvation from the server's own queueing.
// - soak: 16 honest palpsim-haptic clients pressing at 1 kHz for N minutes beside fuzzing
//   clients (valid messages mutated as libFuzzer does, to the pose and control sockets), a
//   viewer that subscribes and never reads, a viewer killed with -9, and a LoadScene that
//   asks for the cuda backend; the server's RSS over time.
// - faults: the server killed with -9 and started again under a pressing palpsim-haptic
//   (its force must be zero 10 ms after the last reply, and it must reopen its session by
//   itself); frames recorded into a full file system (a small tmpfs, where this process may
//   mount one); a server started on a scene that asks for the cuda backend with no GPU.
// Writes a Markdown report and its JSON (--md, --json; default bench/results/reliability.*).
#include <dirent.h>
#include <sched.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/stat.h>
#include <unistd.h>

#include <google/protobuf/stubs/logging.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "bench/registry.h"
#include "bench/reliability_clients.h"
#include "bench/reliability_probes.h"
#include "bench/stats.h"
#include "core/error.h"
#include "palpsim/wire.pb.h"
#include "tests/integration/haptic_log.h"
#include "tests/integration/server_process.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using bench::json_number;
using bench::machine;
using namespace palpsim::bench::reliability;

namespace {

struct Options {
  std::string json = std::string(PALPSIM_SOURCE_DIR) + "/bench/results/reliability.json";
  std::string md = std::string(PALPSIM_SOURCE_DIR) + "/bench/results/reliability.md";
  std::string commit = "unknown";
  std::string phases = "flood,soak,faults";
  std::string scene = std::string(PALPSIM_SOURCE_DIR) + "/config/scenes/lumbar_phantom.textproto";
  std::vector<std::string> server_args;  // more palpsim-server options
  std::string server_exe = test::build_exe("palpsim-server");  // another build's, for comparisons
  std::string haptic_exe = test::build_exe("palpsim-haptic");  // the same for the flood's honest client
  // flood
  int runs = 5;
  int flooders = 8;
  double flood_rate_hz = 18000;  // messages a second of each flooder
  bool flood_reads = false;      // flooders read their replies
  int hogs = 0;                  // busy threads standing for other programs on the machine
  // soak
  double minutes = 3;
  int honest = 16;
  int fuzzers = 4;
  double fuzz_rate_hz = 2500;    // messages a second of each fuzzing client
  // faults
  int restarts = 3;
};

// --- phases ---------------------------------------------------------------------------------

struct Report {
  std::string date, machine, commit;
  double load_start = 0, load_end = 0;
  std::ostringstream md, json;  // sections, appended by the phases
  std::uint64_t fuzzed = 0, faults = 0, crashes = 0, honest_lost = 0, honest_errors = 0;
  bool memory_flat = true;
  std::vector<std::string> json_sections;
};

// flood: `runs` runs of the flood beside one honest client
void flood_phase(const Options& o, Report& rep) {
  rep.md << "## Flood (issue 26, finding 9)\n\n"
         << o.flooders << " flooding clients (threads of palpsim-bench, one ZeroMQ context each) send "
         << o.flood_rate_hz << " messages a second each to the pose socket, "
         << (o.flood_reads ? "reading" : "never reading")
         << " their replies: valid poses of their own session, poses of unknown sessions, NaN and absurd poses, "
            "random bytes, 2000-byte and truncated messages, three-frame messages. Beside them one honest "
            "`palpsim-haptic` presses three times at 1 kHz (13.5 s, 13500 poses)"
         << (o.hogs ? ", and " + std::to_string(o.hogs) + " busy threads stand for other programs" : std::string())
         << ". Scene `" << o.scene.substr(o.scene.rfind('/') + 1) << "`.\n\n"
         << "| run | honest lost | errors | round trip p50 / p99 / p99.9 | watchdog trips | flood sent | "
            "server: answered poses, bad, unanswered | load |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n";
  std::ostringstream sched_md, js;
  js << "\"flood\": {\"flooders\": " << o.flooders << ", \"rate_hz\": " << o.flood_rate_hz
     << ", \"hogs\": " << o.hogs << ", \"runs\": [";
  for (int run = 1; run <= o.runs; ++run) {
    const double load0 = load_average();
    test::ServerProcess server(o.scene, o.server_args, o.server_exe);
    if (!server.wait_ready(600)) throw Error("palpsim-bench reliability: the server did not start:\n" + server.child().err());
    std::atomic<bool> stop{false};
    Counts counts;
    std::vector<std::thread> threads;
    for (int i = 0; i < o.hogs; ++i)
      threads.emplace_back([&stop] {
        for (volatile std::uint64_t x = 0; !stop.load(std::memory_order_relaxed);) x = x + 1;
      });
    for (int i = 0; i < o.flooders; ++i)
      threads.emplace_back(flood, server.control(), server.pose(), o.flood_rate_hz, o.flood_reads, unsigned(i + 1),
                           std::cref(stop), std::ref(counts));
    sleep_s(0.5);  // the flood is on before the honest client starts
    const auto t0 = Clock::now();
    test::Child honest({o.haptic_exe, "--connect", server.control(), "--name", "honest"});
    std::map<std::string, SchedSampler::Summary> sched;
    {
      SchedSampler sampler({{"server", server.child().pid()}, {"honest", honest.pid()}, {"flooders", ::getpid()}}, 0.1);
      if (honest.wait(120) < 0) std::fprintf(stderr, "palpsim-bench reliability: the honest client ran over 120 s\n");
      sampler.stop();
      sched = sampler.summary();
    }
    const double seconds = seconds_since(t0);
    const v1::ServerStats st = server_stats(server.control());
    stop = true;
    for (auto& t : threads) t.join();
    const HapticSummary h = parse_haptic(honest.out());
    const bool alive = server.child().wait(0) < 0;
    const int rc = server.stop(30);
    rep.crashes += !alive || rc != 0;
    rep.honest_lost += h.parsed ? std::uint64_t(h.lost) : 13500;
    rep.honest_errors += std::uint64_t(h.errors);
    const std::uint64_t bad = st.malformed() + st.unknown_session() + st.bad_pose() + st.absurd_pose() + st.oversized();
    char row[512];
    std::snprintf(row, sizeof row, "| %d | %ld | %ld | %.2f / %.2f / %.2f ms | %ld | %llu | %llu, %llu, %llu | %.1f |\n",
                  run, h.parsed ? h.lost : -1, h.errors, h.p50_us * 1e-3, h.p99_us * 1e-3, h.p999_us * 1e-3, h.trips,
                  (unsigned long long)counts.sent.load(), (unsigned long long)st.poses(), (unsigned long long)bad,
                  (unsigned long long)st.bad_input_unanswered(), load0);
    rep.md << row;
    std::printf("flood run %d: %s", run, row);
    sched_md << "\nRun " << run << ", " << seconds << " s: threads' time on a core and waiting for one\n\n"
             << "| thread | on a core | waiting for a core | most waited in one 0.1 s sample | wake-ups/s |\n"
             << "| --- | --- | --- | --- | --- |\n";
    print_sched(sched_md, sched, seconds);
    js << (run > 1 ? ", " : "") << "{\"honest_lost\": " << (h.parsed ? h.lost : -1) << ", \"errors\": " << h.errors
       << ", \"p50_us\": " << json_number(h.p50_us) << ", \"p99_us\": " << json_number(h.p99_us)
       << ", \"p999_us\": " << json_number(h.p999_us) << ", \"watchdog_trips\": " << h.trips
       << ", \"flood_sent\": " << counts.sent << ", \"server_poses\": " << st.poses() << ", \"server_bad\": " << bad
       << ", \"unanswered\": " << st.bad_input_unanswered() << ", \"load\": " << json_number(load0)
       << ", \"server_exit\": " << rc << "}";
  }
  js << "]}";
  rep.json_sections.push_back(js.str());
  rep.md << sched_md.str() << "\n";
}

// soak: honest clients for N minutes beside fuzzing clients, two viewers and a cuda LoadScene
// the soak's memory over time: RSS at the plateau after the first fifth and at the end, of RSS
// and of RSS less what the open sessions' stages hold (the fuzzers open sessions within their
// quota, and each that deforms holds an engine; that is bounded by the quotas, not a leak)
struct MemorySummary {
  double plateau = 0, end = 0, peak = 0, free_plateau = 0, free_end = 0, held_max = 0;
  int sessions_min = 1 << 30, sessions_max = 0;
  bool flat = false;  // RSS less the stages' at the end within 10 % of its plateau
};

MemorySummary summarize_memory(const std::vector<MemorySample>& samples, double seconds) {
  MemorySummary s;
  for (const MemorySample& m : samples) {
    if (!m.answered) continue;
    if (s.plateau == 0 && m.t_s >= 0.2 * seconds) {
      s.plateau = m.rss_mb;
      s.free_plateau = m.rss_mb - m.held_mb;
    }
    s.peak = std::max(s.peak, m.rss_mb);
    s.end = m.rss_mb;
    s.free_end = m.rss_mb - m.held_mb;
    s.sessions_min = std::min(s.sessions_min, m.sessions);
    s.sessions_max = std::max(s.sessions_max, m.sessions);
    s.held_max = std::max(s.held_max, m.held_mb);
  }
  s.flat = s.free_plateau > 0 && s.free_end <= 1.1 * s.free_plateau;
  return s;
}

// what the fuzzing clients sent and how the server counted it, as a report line
std::string fuzz_line(const Counts& fuzzed, const v1::ServerStats& st) {
  char line[1024];
  std::snprintf(line, sizeof line,
                "- fuzzed messages: **%llu** sent (%llu dropped by the fuzzers' own full queues), %llu replies; the "
                "server counted %llu malformed, %llu unknown session, %llu NaN, %llu absurd, %llu oversized, %llu "
                "bad parameter, %llu not owner; %llu unanswered past their connection's allowance\n",
                (unsigned long long)fuzzed.sent.load(), (unsigned long long)fuzzed.dropped.load(),
                (unsigned long long)fuzzed.replies.load(), (unsigned long long)st.malformed(),
                (unsigned long long)st.unknown_session(), (unsigned long long)st.bad_pose(),
                (unsigned long long)st.absurd_pose(), (unsigned long long)st.oversized(),
                (unsigned long long)st.bad_parameter(), (unsigned long long)st.not_owner(),
                (unsigned long long)st.bad_input_unanswered());
  return line;
}

// the RSS samples, about 20 of them, as report text (s: RSS MB, held by the stages MB, sessions)
std::string memory_series(const std::vector<MemorySample>& samples) {
  std::ostringstream md;
  char line[128];
  const std::size_t stride = std::max<std::size_t>(1, samples.size() / 20);
  for (std::size_t i = 0; i < samples.size(); i += stride) {
    std::snprintf(line, sizeof line, " %.0f: %.0f, %.0f, %d;", samples[i].t_s, samples[i].rss_mb, samples[i].held_mb,
                  samples[i].sessions);
    md << line;
  }
  return md.str();
}

// the RSS samples as JSON: [[t s, RSS MB], ...], "held_mb": [...], "sessions": [...]
std::string memory_json(const std::vector<MemorySample>& samples) {
  std::ostringstream js;
  js << "[";
  for (std::size_t i = 0; i < samples.size(); ++i)
    js << (i ? ", " : "") << "[" << json_number(samples[i].t_s) << ", " << json_number(samples[i].rss_mb) << "]";
  js << "], \"held_mb\": [";
  for (std::size_t i = 0; i < samples.size(); ++i) js << (i ? ", " : "") << json_number(samples[i].held_mb);
  js << "], \"sessions\": [";
  for (std::size_t i = 0; i < samples.size(); ++i) js << (i ? ", " : "") << samples[i].sessions;
  js << "]";
  return js.str();
}

// what happened on the soak's timeline
struct SoakEvents {
  std::string killed_out;  // what the killed viewer had printed
  std::string cuda_reply;  // the reply to the LoadScene asking for cuda
  bool server_died = false;
};

// the faults on the soak's timeline until every honest client is done (or the server died):
// the second viewer killed at a third, a LoadScene of `cuda_scene` at a half
SoakEvents soak_timeline(test::ServerProcess& server, test::Child& killed, const std::string& cuda_scene,
                         const std::vector<std::unique_ptr<test::Child>>& honest, double seconds,
                         Clock::time_point t0, Report& rep) {
  SoakEvents ev;
  bool killed_done = false, cuda_done = false;
  while (seconds_since(t0) < seconds + 5) {
    sleep_s(0.5);
    const double t = seconds_since(t0);
    if (!killed_done && t > seconds / 3) {
      ev.killed_out = killed.out();
      killed.signal(SIGKILL);
      killed.wait(10);
      killed_done = true;
      ++rep.faults;
      std::printf("soak: t = %.0f s, a viewer killed with -9\n", t);
    }
    if (!cuda_done && t > seconds / 2) {
      zmq::context_t ctx(1);
      v1::ControlRequest q;
      q.mutable_load_scene()->set_path(cuda_scene);
      v1::ControlReply r;
      ev.cuda_reply = control_call(ctx, server.control(), q, r, 120000)
                          ? (r.has_error() ? v1::ErrorCode_Name(r.error().code()) + ": " + r.error().message()
                                           : std::string("loaded: ") + r.load_scene().server().scene_name())
                          : std::string("no reply within 120 s");
      cuda_done = true;
      ++rep.faults;
      std::printf("soak: t = %.0f s, LoadScene of a scene asking for cuda: %s\n", t, ev.cuda_reply.c_str());
    }
    if (server.child().wait(0) >= 0) {
      ev.server_died = true;
      break;
    }
    bool all_done = true;
    for (auto& h : honest) all_done = all_done && h->wait(0) >= 0;
    if (all_done) break;
  }
  return ev;
}

// the honest clients' poses, lost replies (a client that printed no summary counts 60000
// lost), error replies and round-trip p99s
struct HonestTotals {
  long lost = 0, errors = 0, steps = 0;
  std::vector<double> p99_us;
};

HonestTotals honest_totals(const std::vector<HapticSummary>& hs) {
  HonestTotals t;
  for (const auto& h : hs) {
    t.lost += h.parsed ? h.lost : 60000;
    t.errors += h.errors;
    t.steps += h.steps;
    t.p99_us.push_back(h.p99_us);
  }
  return t;
}

void soak_phase(const Options& o, Report& rep) {
  const double seconds = o.minutes * 60;
  // the scene's folder holds the cuda scene that a LoadScene asks for
  char tmpl[] = "/tmp/palpsim-rel-XXXXXX";
  const std::string dir = ::mkdtemp(tmpl);
  std::ofstream(dir + "/cuda.textproto")
      << "name: \"cuda without a GPU\"\nphantom { voxel_mm: 2.0 }\ndeform { backend: \"cuda\" }\n"
         "effects { haptics: true chainmail: true }\n";
  std::vector<std::string> args = o.server_args;
  args.insert(args.end(), {"--scene-dir", dir});
  test::ServerProcess server(o.scene, args, o.server_exe);
  if (!server.wait_ready(600)) throw Error("palpsim-bench reliability: the server did not start:\n" + server.child().err());
  v1::ControlReply info;
  if (!server_info(server.control(), info)) throw Error("palpsim-bench reliability: no Info from the server");
  const double rss0 = rss_mb(server.child().pid());
  MemorySampler rss(server.child().pid(), server.control(), 2.0);
  const auto t0 = Clock::now();
  // the honest clients, each on its own lane; the first two watched by the viewers
  std::vector<std::unique_ptr<test::Child>> honest;
  std::vector<std::string> paths;
  for (int i = 0; i < o.honest; ++i) {
    paths.push_back(press_path(info.info().patient(), i, seconds, 0.28 * i));
    std::vector<std::string> a{test::build_exe("palpsim-haptic"), "--connect", server.control(), "--device",
                               "csv:" + paths.back(), "--name", "honest-" + std::to_string(i)};
    if (i < 2) a.insert(a.end(), {"--client-token", "rel-viewer-" + std::to_string(i)});
    honest.push_back(std::make_unique<test::Child>(a));
  }
  sleep_s(1);
  const std::string self = "/proc/" + std::to_string(::getpid()) + "/exe";
  test::Child stalled({self, "reliability", "--role", "viewer", "--control", server.control(), "--token", "rel-viewer-0",
                       "--stall"});
  auto killed = std::make_unique<test::Child>(std::vector<std::string>{
      self, "reliability", "--role", "viewer", "--control", server.control(), "--token", "rel-viewer-1"});
  // the fuzzing clients
  std::atomic<bool> stop{false};
  Counts fuzzed;
  std::vector<std::thread> fuzzers;
  for (int i = 0; i < o.fuzzers; ++i)
    fuzzers.emplace_back(fuzz, server.control(), server.pose(), o.fuzz_rate_hz, unsigned(i + 1), std::cref(stop),
                         std::ref(fuzzed));
  // faults on the timeline: the second viewer killed at a third, a LoadScene asking for cuda at a half
  const SoakEvents ev = soak_timeline(server, *killed, dir + "/cuda.textproto", honest, seconds, t0, rep);
  const std::string &killed_out = ev.killed_out, &cuda_reply = ev.cuda_reply;
  const bool server_died = ev.server_died;
  const v1::ServerStats st = server_stats(server.control());
  stop = true;
  for (auto& t : fuzzers) t.join();
  std::vector<HapticSummary> hs;
  int unfinished = 0;
  for (auto& h : honest) {
    if (h->wait(30) < 0) ++unfinished;
    hs.push_back(parse_haptic(h->out()));
    if (!hs.back().parsed) std::fprintf(stderr, "soak: an honest client said:\n%s\n%s\n", h->out().c_str(), h->err().c_str());
  }
  const std::string stalled_out = stalled.out();
  stalled.signal(SIGTERM);
  stalled.wait(10);
  rss.stop();
  const auto samples = rss.samples();
  const int rc = server_died ? server.child().wait(0) : server.stop(60);
  rep.crashes += server_died || rc != 0;
  rep.fuzzed += fuzzed.sent;
  ++rep.faults;  // the stalled viewer
  const HonestTotals ht = honest_totals(hs);
  const long lost = ht.lost, errors = ht.errors, steps = ht.steps;
  std::vector<double> p99 = ht.p99_us;
  rep.honest_lost += std::uint64_t(lost);
  rep.honest_errors += std::uint64_t(errors);
  const MemorySummary mem = summarize_memory(samples, seconds);
  const bool flat = mem.flat;
  rep.memory_flat = rep.memory_flat && flat;
  std::sort(p99.begin(), p99.end());
  char line[1024];
  std::snprintf(line, sizeof line,
                "- %d honest clients, %.1f min each: %ld poses, **%ld lost**, %ld error replies, %d did not finish; "
                "round trip p99 per client %.2f-%.2f ms (median %.2f ms)\n",
                o.honest, o.minutes, steps, lost, errors, unfinished, p99.empty() ? 0 : p99.front() * 1e-3,
                p99.empty() ? 0 : p99.back() * 1e-3, p99.empty() ? 0 : p99[p99.size() / 2] * 1e-3);
  rep.md << "## Soak\n\n"
         << o.honest << " honest `palpsim-haptic` clients press at 1 kHz, each on its own lane over the back (a press "
                        "every 4.5 s), beside "
         << o.fuzzers << " fuzzing clients at " << o.fuzz_rate_hz
         << " messages a second each (valid poses and control requests mutated as libFuzzer does: bit flips, random "
            "and interesting bytes, insertions, erasures, truncation, splices, repeats; 1 in 50 to the control "
            "socket; some in two frames), for "
         << o.minutes << " min. Scene `" << o.scene.substr(o.scene.rfind('/') + 1) << "`.\n\n"
         << line;
  rep.md << fuzz_line(fuzzed, st);
  rep.md << "- a viewer watching honest-0 subscribed to its frames and bricks and never read: "
         << (stalled_out.find("watching") != std::string::npos ? "subscribed" : "did not subscribe: " + stalled_out)
         << "; a viewer of honest-1 killed with -9 at a third of the run ("
         << (killed_out.find("messages") != std::string::npos ? "it had read frames and bricks" : "it had read nothing")
         << ")\n"
         << "- LoadScene of a scene asking for the cuda backend (no GPU here), at half time: `" << cuda_reply << "`\n";
  std::snprintf(line, sizeof line,
                "- server: %s; RSS %.0f MB at start, %.0f MB after the first fifth, %.0f MB at the end, peak %.0f MB; "
                "%d-%d sessions open (the fuzzers' within their quota), their stages holding up to %.0f MB; RSS less "
                "what the stages hold %.0f MB after the first fifth, %.0f MB at the end (%s)\n",
                server_died ? "**died**" : rc == 0 ? "stopped cleanly at the end" : "did not stop cleanly", rss0, mem.plateau,
                mem.end, mem.peak, mem.sessions_max ? mem.sessions_min : 0, mem.sessions_max, mem.held_max,
                mem.free_plateau, mem.free_end,
                flat ? "flat: the end within 10 % of the plateau" : "**not flat**");
  rep.md << line << "\nOver time (s: RSS MB, held by the stages MB, sessions):";
  rep.md << memory_series(samples);
  rep.md << "\n\n";
  std::ostringstream js;
  js << "\"soak\": {\"minutes\": " << o.minutes << ", \"honest\": " << o.honest << ", \"poses\": " << steps
     << ", \"honest_lost\": " << lost << ", \"honest_errors\": " << errors << ", \"fuzzed\": " << fuzzed.sent
     << ", \"fuzz_replies\": " << fuzzed.replies << ", \"unanswered\": " << st.bad_input_unanswered()
     << ", \"cuda_load_scene\": \"" << (cuda_reply.find("ERROR_") == 0 ? cuda_reply.substr(0, cuda_reply.find(':')) : "other")
     << "\", \"server_died\": " << (server_died ? "true" : "false") << ", \"server_exit\": " << rc
     << ", \"rss_mb\": " << memory_json(samples) << ", \"memory_flat\": " << (flat ? "true" : "false") << "}";
  rep.json_sections.push_back(js.str());
  for (const auto& p : paths) std::remove(p.c_str());
  std::remove((dir + "/cuda.textproto").c_str());
  ::rmdir(dir.c_str());
}

// kill -9 and restart, o.restarts times, under a pressing palpsim-haptic on `scene`: how soon
// its force was zero after the last reply, and whether it reopened its session by itself
void restart_fault(const Options& o, const std::string& scene, Report& rep, std::ostringstream& js) {
  test::ServerProcess first(scene, o.server_args, o.server_exe);
  if (!first.wait_ready(600)) throw Error("palpsim-bench reliability: the server did not start");
  const std::string control = first.control(), pose = first.pose();
  v1::ControlReply info;
  server_info(control, info);
  const double period = 6;  // s between kills
  const std::string path = press_path(info.info().patient(), 5, period * (o.restarts + 1), 0);
  const std::string log = test::temp_file("rel-restart-log", "");
  test::Child client({test::build_exe("palpsim-haptic"), "--connect", control, "--device", "csv:" + path, "--log", log,
                      "--mode", "remote", "--name", "restarted"});
  std::unique_ptr<test::ServerProcess> server;
  std::vector<double> ready_s;
  const auto t0 = Clock::now();
  for (int k = 0; k < o.restarts; ++k) {
    // killed while the press holds 40 mm deep (2-2.5 s into each 4.5 s press)
    sleep_s(std::max(0.0, (period * k + 2.3) - seconds_since(t0)));
    test::Child& victim = server ? server->child() : first.child();
    victim.signal(SIGKILL);
    victim.wait(10);
    ++rep.faults;
    server = std::make_unique<test::ServerProcess>(scene, std::vector<std::string>{"--bind", control, "--pose-bind", pose},
                                                   o.server_exe);
    if (!server->wait_ready(120)) throw Error("palpsim-bench reliability: the server did not start again");
    ready_s.push_back(seconds_since(t0));
  }
  client.wait(period * (o.restarts + 2) + 30);
  const HapticSummary h = parse_haptic(client.out());
  const std::vector<test::HapticLogRow> rows = test::read_haptic_log(log);
  // every gap of over 0.1 s without a new reply: how soon the force was zero, and whether it stayed zero
  int gaps = 0, not_zero = 0;
  double worst_zero_ms = 0, worst_outage_s = 0;
  for (std::size_t i = 1, start = 0; i < rows.size(); ++i) {
    if (rows[i].reply_seq == rows[start].reply_seq) continue;
    if (rows[i].t - rows[start].t > 0.1) {
      ++gaps;
      const test::WatchdogOverGap w = test::watchdog_over_gap(rows, start, i - 1 - start);
      not_zero += w.not_zero != std::string::npos;
      for (std::size_t j = start; j < i; ++j)
        if (rows[j].force() == 0.0) {
          worst_zero_ms = std::max(worst_zero_ms, (rows[j].t - rows[start].t) * 1e3);
          break;
        }
      worst_outage_s = std::max(worst_outage_s, rows[i].t - rows[start].t);
    }
    start = i;
  }
  const int rc = server ? server->stop(30) : -1;
  rep.crashes += rc != 0;
  char line[1024];
  std::snprintf(line, sizeof line,
                "- **kill -9 and restart**, %d times, under `palpsim-haptic --mode remote` pressing (killed 40 mm "
                "deep): %d outages seen in its log; the force was zero at most %.1f ms after the last reply (goal "
                "10 ms; %d outages with a non-zero force 10 ms or more after it); the session reopened %ld times by "
                "itself, the longest outage %.2f s (the restart: prep from the cache and bind); after the last "
                "restart %s\n",
                o.restarts, gaps, worst_zero_ms, not_zero, h.reopens, worst_outage_s,
                rows.size() > 1 && rows.back().reply_seq > rows[rows.size() / 2].reply_seq ? "replies again"
                                                                                          : "**no replies**");
  rep.md << line;
  js << "\"restarts\": {\"kills\": " << o.restarts << ", \"outages\": " << gaps << ", \"worst_zero_ms\": "
     << json_number(worst_zero_ms) << ", \"not_zero_after_10ms\": " << not_zero << ", \"reopens\": " << h.reopens
     << ", \"worst_outage_s\": " << json_number(worst_outage_s) << "}";
  std::remove(path.c_str());
  std::remove(log.c_str());
}

// frames recorded into a full file system (a small tmpfs, where this process may mount one)
void full_disk_fault(const Options& o, Report& rep, std::ostringstream& js) {
  char tmpl[] = "/tmp/palpsim-rel-full-XXXXXX";
  const std::string dir = ::mkdtemp(tmpl);
  std::string skip;
  if (::mount("tmpfs", dir.c_str(), "tmpfs", 0, "size=256k") != 0)
    skip = std::string("this process may not mount a tmpfs (") + std::strerror(errno) + "; it needs root or CAP_SYS_ADMIN)";
  if (skip.empty()) {
    // the scene inside, then the file system filled to the last byte
    std::ofstream(dir + "/scene.textproto")
        << "name: \"full disk\"\nphantom { voxel_mm: 2.0 }\neffects { haptics: true frames: true }\n"
           "render { width: 160 height: 90 max_fps: 30 record_dir: \"" << dir << "/frames\" }\n";
    {
      std::ofstream fill(dir + "/fill", std::ios::binary);
      const std::string block(4096, 'x');
      while (fill.write(block.data(), std::streamsize(block.size())) && fill.flush()) {
      }
    }
    test::ServerProcess server(dir + "/scene.textproto", o.server_args, o.server_exe);
    const bool ready = server.wait_ready(600);
    MemorySampler rss(server.child().pid(), server.control(), 1.0);
    test::Child client({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--name", "beside-full-disk"});
    client.wait(60);
    rss.stop();
    const HapticSummary h = parse_haptic(client.out());
    const v1::ServerStats st = server_stats(server.control());
    const std::string err = server.child().err();
    int error_lines = 0;
    for (std::size_t at = err.find("recording frames"); at != std::string::npos; at = err.find("recording frames", at + 1))
      ++error_lines;
    const auto samples = rss.samples();
    const bool alive = ready && server.child().wait(0) < 0;
    const int rc = server.stop(30);
    rep.crashes += !alive || rc != 0;
    rep.honest_lost += h.parsed ? std::uint64_t(h.lost) : 13500;
    ++rep.faults;
    const std::string first = err.find("recording frames") != std::string::npos
                                  ? err.substr(err.find("recording frames"), err.find('\n', err.find("recording frames")) - err.find("recording frames"))
                                  : std::string("none");
    char line[1400];
    std::snprintf(line, sizeof line,
                  "- **record folder on a full file system** (a 256 KiB tmpfs, filled): the server %s; a client "
                  "beside it pressed 13.5 s: %ld lost, %ld errors; %llu frames rendered; the log has %d lines about "
                  "recording, the first: `%s`; RSS %.0f-%.0f MB\n",
                  alive && rc == 0 ? "kept serving and stopped cleanly" : "**died or did not stop cleanly**",
                  h.parsed ? h.lost : -1, h.errors,
                  (unsigned long long)(st.has_stream() ? st.stream().frames_rendered() : 0), error_lines,
                  first.substr(0, 300).c_str(), samples.empty() ? 0 : samples.front().rss_mb,
                  samples.empty() ? 0 : samples.back().rss_mb);
    rep.md << line;
    js << ", \"full_disk\": {\"server_ok\": " << (alive && rc == 0 ? "true" : "false") << ", \"lost\": " << h.lost
       << ", \"error_lines\": " << error_lines << "}";
    ::umount(dir.c_str());
  } else {
    rep.md << "- record folder on a full file system: **skipped**: " << skip << "\n";
    js << ", \"full_disk\": {\"skipped\": \"" << skip << "\"}";
  }
  ::rmdir(dir.c_str());
}

// a server started on a scene that asks for the cuda backend where there is no GPU
void cuda_start_fault(const Options& o, Report& rep, std::ostringstream& js) {
  const std::string cuda = test::temp_file("rel-cuda", "name: \"cuda\"\nphantom { voxel_mm: 2.0 }\n"
                                                        "deform { backend: \"cuda\" }\neffects { haptics: true chainmail: true }\n");
  test::ServerProcess server(cuda, o.server_args, o.server_exe);
  const int rc = server.child().wait(300);
  const std::string err = server.child().err();
  const auto at = err.find("palpsim-server: error:");
  const std::string said = at == std::string::npos ? "(nothing)" : err.substr(at, err.find('\n', at) - at);
  ++rep.faults;
  rep.crashes += rc != 1 && rc != 0;  // 1: refused with a message; a signal would be 128+
  rep.md << "- **cuda backend with no GPU**: `palpsim-server` on a scene asking for it exits with status " << rc
         << ": `" << said << "`\n\n";
  js << ", \"cuda_start\": {\"exit\": " << rc << "}";
  std::remove(cuda.c_str());
}

// faults: kill -9 and restart under a pressing client; a full file system for recorded
// frames; a server started on a cuda scene with no GPU
void faults_phase(const Options& o, Report& rep) {
  rep.md << "## Faults\n\n";
  std::ostringstream js;
  js << "\"faults\": {";
  // a small scene: the phantom at 2 mm, haptics only (the restarts measure the client)
  const std::string scene = test::temp_file("rel-scene", test::fast_scene_text("reliability", 30));
  restart_fault(o, scene, rep, js);
  full_disk_fault(o, rep, js);
  cuda_start_fault(o, rep, js);
  js << "}";
  rep.json_sections.push_back(js.str());
  std::remove(scene.c_str());
}

bool has_phase(const Options& o, const std::string& p) {
  return ("," + o.phases + ",").find("," + p + ",") != std::string::npos;
}

}  // namespace

PALPSIM_BENCH(reliability, "hostile clients and faults: flood, soak, kill -9 (writes bench/results/reliability.md)") {
  Options o;
  std::string command = "build/palpsim-bench reliability";  // as given, for the report
  for (int i = 1; i < argc; ++i) command += std::string(" ") + argv[i];
  std::string role, role_control, role_token;
  bool role_stall = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw Error("palpsim-bench reliability: " + a + " needs a value");
      return argv[++i];
    };
    if (a == "--json") o.json = value();
    else if (a == "--md") o.md = value();
    else if (a == "--commit") o.commit = value();
    else if (a == "--phases") o.phases = value();
    else if (a == "--scene") o.scene = value();
    else if (a == "--server-arg") o.server_args.push_back(value());
    else if (a == "--server-exe") o.server_exe = value();
    else if (a == "--haptic-exe") o.haptic_exe = value();
    else if (a == "--runs") o.runs = std::stoi(value());
    else if (a == "--flooders") o.flooders = std::stoi(value());
    else if (a == "--flood-rate") o.flood_rate_hz = std::stod(value());
    else if (a == "--flood-reads") o.flood_reads = true;
    else if (a == "--hogs") o.hogs = std::stoi(value());
    else if (a == "--minutes") o.minutes = std::stod(value());
    else if (a == "--honest") o.honest = std::stoi(value());
    else if (a == "--fuzzers") o.fuzzers = std::stoi(value());
    else if (a == "--fuzz-rate") o.fuzz_rate_hz = std::stod(value());
    else if (a == "--restarts") o.restarts = std::stoi(value());
    else if (a == "--role") role = value();  // internal: a viewer process of the soak
    else if (a == "--control") role_control = value();
    else if (a == "--token") role_token = value();
    else if (a == "--stall") role_stall = true;
    else {
      std::fprintf(stderr,
                   "usage: palpsim-bench reliability [--phases flood,soak,faults] [--md FILE] [--json FILE] [--commit C]\n"
                   "       [--scene FILE] [--server-arg ARG]... [--server-exe FILE] [--haptic-exe FILE]\n"
                   "       flood:  [--runs 5] [--flooders 8] [--flood-rate 18000] [--flood-reads] [--hogs 0]\n"
                   "       soak:   [--minutes 3] [--honest 16] [--fuzzers 4] [--fuzz-rate 2500]\n"
                   "       faults: [--restarts 3]\n");
      return 2;
    }
  }
  if (role == "viewer") return run_viewer(role_control, role_token, role_stall);
  spdlog::set_level(spdlog::level::warn);
  google::protobuf::SetLogHandler(nullptr);  // mutated strings that are not UTF-8 would each log a line
  Report rep;
  {
    const std::time_t now = std::time(nullptr);
    char d[32];
    std::strftime(d, sizeof d, "%Y-%m-%d %H:%M", std::localtime(&now));
    rep.date = d;
  }
  rep.machine = machine();
  rep.commit = o.commit;
  rep.load_start = load_average();
  std::printf("machine: %s, load average %.2f\n", rep.machine.c_str(), rep.load_start);
  const auto t0 = Clock::now();
  if (has_phase(o, "flood")) flood_phase(o, rep);
  if (has_phase(o, "soak")) soak_phase(o, rep);
  if (has_phase(o, "faults")) faults_phase(o, rep);
  rep.load_end = load_average();
  const bool pass = rep.crashes == 0 && rep.honest_lost == 0 && rep.honest_errors == 0 && rep.memory_flat &&
                    (!has_phase(o, "soak") || rep.fuzzed >= 1000000);
  std::ostringstream head;
  head << "# Reliability: palpsim-bench reliability\n\n"
       << "Taken " << rep.date << " on " << rep.machine << " at commit " << rep.commit
       << ", phases " << o.phases << ", " << std::lround(seconds_since(t0)) << " s in all. The machine is shared "
       << "with other engineers' builds and tests: load average " << rep.load_start << " at the start, "
       << rep.load_end << " at the end. Command: `" << command << "`.\n\n"
       << "| | result | goal |\n| --- | --- | --- |\n"
       << "| messages fuzzed | " << rep.fuzzed << " | 10^6 |\n"
       << "| faults injected | " << rep.faults << " | |\n"
       << "| crashes | " << rep.crashes << " | 0 |\n"
       << "| honest replies lost | " << rep.honest_lost << " | 0 |\n"
       << "| honest error replies | " << rep.honest_errors << " | 0 |\n"
       << "| server memory | " << (rep.memory_flat ? "flat" : "not flat") << " | flat |\n\n";
  const std::string md = head.str() + rep.md.str();
  std::fputs(md.c_str(), stdout);
  if (!o.md.empty()) {
    std::ofstream f(o.md);
    if (!f) throw Error("palpsim-bench reliability: cannot write --md " + o.md);
    f << md;
  }
  if (!o.json.empty()) {
    std::ofstream f(o.json);
    if (!f) throw Error("palpsim-bench reliability: cannot write --json " + o.json);
    f << "{\n  \"area\": \"reliability\",\n  \"date\": \"" << rep.date << "\",\n  \"machine\": \"" << rep.machine
      << "\",\n  \"commit\": \"" << rep.commit << "\",\n  \"phases\": \"" << o.phases << "\",\n  \"load_start\": "
      << json_number(rep.load_start) << ",\n  \"load_end\": " << json_number(rep.load_end) << ",\n  \"fuzzed\": "
      << rep.fuzzed << ",\n  \"faults\": " << rep.faults << ",\n  \"crashes\": " << rep.crashes
      << ",\n  \"honest_lost\": " << rep.honest_lost << ",\n  \"honest_errors\": " << rep.honest_errors
      << ",\n  \"memory_flat\": " << (rep.memory_flat ? "true" : "false") << ",\n  \"pass\": " << (pass ? "true" : "false");
    for (const auto& s : rep.json_sections) f << ",\n  " << s;
    f << "\n}\n";
  }
  return pass ? 0 : 1;
}
