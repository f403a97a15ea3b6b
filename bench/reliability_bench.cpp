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
#include "bench/stats.h"
#include "core/error.h"
#include "palpsim/wire.pb.h"
#include "tests/integration/haptic_log.h"
#include "tests/integration/server_process.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using bench::json_number;
using bench::machine;
using Clock = std::chrono::steady_clock;

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

double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

void sleep_s(double s) { std::this_thread::sleep_for(std::chrono::duration<double>(s)); }

// the 1-minute load average
double load_average() {
  double l = 0;
  std::ifstream("/proc/loadavg") >> l;
  return l;
}

// the resident set of process `pid` (MB; 0 when it is gone)
double rss_mb(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(in, line);)
    if (line.rfind("VmRSS:", 0) == 0) return std::atof(line.c_str() + 6) / 1024.0;
  return 0;
}

// --- threads' time on a core and waiting for one (Linux schedstat) ------------------

// one thread's cumulative times as /proc/PID/task/TID gives them
struct ThreadTimes {
  std::string name;
  double run_s = 0, wait_s = 0;
  double wakeups = 0;  // its voluntary context switches (sleeps, so wake-ups)
};

// every thread of process `pid` by thread id
std::map<int, ThreadTimes> read_threads(pid_t pid) {
  std::map<int, ThreadTimes> out;
  const std::string base = "/proc/" + std::to_string(pid) + "/task";
  DIR* d = opendir(base.c_str());
  if (!d) return out;
  while (dirent* e = readdir(d)) {
    if (e->d_name[0] == '.') continue;
    const std::string dir = base + "/" + e->d_name;
    ThreadTimes t;
    std::getline(std::ifstream(dir + "/comm"), t.name);
    // field 41 of stat, the scheduling policy: SCHED_FIFO and SCHED_IDLE threads are marked
    std::string stat;
    std::getline(std::ifstream(dir + "/stat"), stat);
    std::istringstream fields(stat.substr(std::min(stat.size(), stat.rfind(')') + 2)));
    std::string f;
    for (int k = 3; k <= 41 && fields >> f; ++k)
      if (k == 41 && (f == "1" || f == "5")) t.name += f == "1" ? " (FIFO)" : " (IDLE)";
    unsigned long long run_ns = 0, wait_ns = 0;
    if (!(std::ifstream(dir + "/schedstat") >> run_ns >> wait_ns)) continue;
    t.run_s = double(run_ns) * 1e-9;
    t.wait_s = double(wait_ns) * 1e-9;
    std::ifstream st(dir + "/status");
    for (std::string line; std::getline(st, line);)
      if (line.rfind("voluntary_ctxt_switches:", 0) == 0) t.wakeups = std::atof(line.c_str() + 24);
    out[std::atoi(e->d_name)] = t;
  }
  closedir(d);
  return out;
}

// samples the threads of some processes every `period_s`: per "process/thread name" the
// time on a core, the time runnable but waiting for one, the most waited within one period
// (the period itself stretches when the sampler waits) and the wake-ups
class SchedSampler {
 public:
  struct Summary {
    double run_s = 0, wait_s = 0, worst_wait_s = 0, wakeups = 0;
  };
  SchedSampler(std::vector<std::pair<std::string, pid_t>> procs, double period_s)
      : procs_(std::move(procs)), period_s_(period_s) {
    for (const auto& [label, pid] : procs_) last_[pid] = read_threads(pid);
    thread_ = std::thread([this] { loop(); });
  }
  ~SchedSampler() { stop(); }
  void stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  std::map<std::string, Summary> summary() const {
    std::lock_guard<std::mutex> lock(mu_);
    return sum_;
  }

 private:
  std::vector<std::pair<std::string, pid_t>> procs_;
  double period_s_;
  std::map<pid_t, std::map<int, ThreadTimes>> last_;
  std::map<std::string, Summary> sum_;
  mutable std::mutex mu_;
  std::atomic<bool> stop_{false};
  std::thread thread_;

  void loop() {
    while (!stop_) {
      sleep_s(period_s_);
      std::lock_guard<std::mutex> lock(mu_);
      for (const auto& [label, pid] : procs_) {
        auto now = read_threads(pid);
        std::map<std::string, Summary> per;  // this period, per name
        for (const auto& [tid, t] : now) {
          const auto it = last_[pid].find(tid);
          const bool known = it != last_[pid].end();
          Summary& s = per[label + "/" + t.name];
          s.run_s += t.run_s - (known ? it->second.run_s : 0);
          s.wait_s += t.wait_s - (known ? it->second.wait_s : 0);
          s.wakeups += t.wakeups - (known ? it->second.wakeups : 0);
        }
        for (const auto& [name, s] : per) {
          Summary& a = sum_[name];
          a.run_s += s.run_s;
          a.wait_s += s.wait_s;
          a.wakeups += s.wakeups;
          a.worst_wait_s = std::max(a.worst_wait_s, s.wait_s);
        }
        if (!now.empty()) last_[pid] = std::move(now);
      }
    }
  }
};

// --- clients ------------------------------------------------------------------------------

// one control request on a fresh REQ socket; false when no reply came within `timeout_ms`
bool control_call(zmq::context_t& ctx, const std::string& endpoint, v1::ControlRequest q, v1::ControlReply& out,
                  int timeout_ms = 5000) {
  zmq::socket_t s(ctx, zmq::socket_type::req);
  s.set(zmq::sockopt::linger, 0);
  s.set(zmq::sockopt::sndtimeo, timeout_ms);
  s.connect(endpoint);
  q.set_schema_version(v1::VERSION_CURRENT);
  if (!s.send(zmq::buffer(q.SerializeAsString()), zmq::send_flags::none)) return false;
  zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}};
  zmq::poll(items, 1, std::chrono::milliseconds(timeout_ms));
  if (!(items[0].revents & ZMQ_POLLIN)) return false;
  zmq::message_t m;
  (void)s.recv(m);
  return out.ParseFromArray(m.data(), int(m.size()));
}

// the server's stats (cleared when it did not answer)
v1::ServerStats server_stats(const std::string& control) {
  zmq::context_t ctx(1);
  v1::ControlRequest q;
  q.mutable_stats();
  v1::ControlReply r;
  return control_call(ctx, control, q, r) ? r.stats().server() : v1::ServerStats{};
}

// the server's RSS beside what its stages say they hold (ServerStats.stages' bytes_allocated: the
// sessions' deformation engines, frames, bricks and the spares) and its open sessions, every
// `period_s`: RSS minus that is the memory no open session accounts for, which must stay flat
// while sessions come and go within their quotas
struct MemorySample {
  double t_s = 0, rss_mb = 0, held_mb = 0;
  int sessions = 0;
  bool answered = false;  // the stats request got its reply
};
class MemorySampler {
 public:
  MemorySampler(pid_t pid, std::string control, double period_s)
      : pid_(pid), control_(std::move(control)), period_s_(period_s), t0_(Clock::now()) {
    thread_ = std::thread([this] {
      while (!stop_) {
        MemorySample m;
        m.t_s = seconds_since(t0_);
        m.rss_mb = rss_mb(pid_);
        const v1::ServerStats st = server_stats(control_);
        m.answered = st.stages_size() > 0;
        for (const auto& g : st.stages()) m.held_mb += double(g.bytes_allocated()) / (1024.0 * 1024.0);
        m.sessions = int(st.sessions_open());
        {
          std::lock_guard<std::mutex> lock(mu_);
          samples_.push_back(m);
        }
        for (int i = 0; i < 10 && !stop_; ++i) sleep_s(period_s_ / 10);
      }
    });
  }
  ~MemorySampler() { stop(); }
  void stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  std::vector<MemorySample> samples() const {
    std::lock_guard<std::mutex> lock(mu_);
    return samples_;
  }

 private:
  pid_t pid_;
  std::string control_;
  double period_s_;
  Clock::time_point t0_;
  std::vector<MemorySample> samples_;
  mutable std::mutex mu_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

// a pose of `session` at `tip`
v1::PoseRequest pose_request(std::uint64_t session, std::uint64_t seq, double x, double y, double z) {
  v1::PoseRequest q;
  q.set_schema_version(v1::VERSION_CURRENT);
  q.set_session_id(session);
  q.set_seq(seq);
  q.set_client_time_s(1e-3 * double(seq));
  q.mutable_tip_mm()->set_x(x);
  q.mutable_tip_mm()->set_y(y);
  q.mutable_tip_mm()->set_z(z);
  return q;
}

// what flooding or fuzzing clients sent and got back
struct Counts {
  std::atomic<std::uint64_t> sent{0}, dropped{0}, replies{0};
};

// paces a client at `rate_hz` messages a second in bursts each millisecond; calls
// `send_one(n)` for message n until `stop`, and `each_ms()` after every burst
void paced(double rate_hz, const std::atomic<bool>& stop, const std::function<void(std::uint64_t)>& send_one,
           const std::function<void()>& each_ms) {
  const double per_ms = rate_hz * 1e-3;
  double owed = 0;
  auto next = Clock::now();
  for (std::uint64_t n = 0; !stop.load(std::memory_order_relaxed);) {
    next += std::chrono::milliseconds(1);
    std::this_thread::sleep_until(next);
    // a client that fell behind (descheduled) does not make up for it in one burst
    if (Clock::now() - next > std::chrono::milliseconds(10)) next = Clock::now();
    for (owed += per_ms; owed >= 1; owed -= 1) send_one(n++);
    each_ms();
  }
}

// one flooding client on its own ZeroMQ context (as a separate program would be): opens a
// session of its own, then sends `rate_hz` messages a second to the pose socket without
// waiting (a full queue drops them): valid poses for its session, poses of unknown
// sessions, NaN and absurd poses, random bytes, oversized and truncated messages, messages
// of three frames. Reads its replies only when `read`.
void flood(const std::string& control, const std::string& pose, double rate_hz, bool read, unsigned seed,
           const std::atomic<bool>& stop, Counts& counts) {
  zmq::context_t ctx(1);
  v1::ControlRequest open;
  open.set_client_token("flooder-" + std::to_string(seed));
  open.mutable_open()->set_client_name("flooder");
  v1::ControlReply opened;
  const std::uint64_t session =
      control_call(ctx, control, open, opened) && opened.has_open() ? opened.open().session_id() : 0;
  const double y = opened.open().server().patient().body_max_mm().y() - 5;
  zmq::socket_t s(ctx, zmq::socket_type::dealer);
  s.set(zmq::sockopt::linger, 0);
  s.connect(pose);
  std::mt19937_64 rng(seed);
  std::vector<std::string> kinds;
  for (int i = 0; i < 4; ++i) kinds.push_back(pose_request(session, 1, 0, y, 0).SerializeAsString());
  kinds.push_back(pose_request(session ^ 0x5a5a5a5a000ull, 1, 0, y, 0).SerializeAsString());
  kinds.push_back(pose_request(session, 1, std::nan(""), y, 0).SerializeAsString());
  kinds.push_back(pose_request(session, 1, 1e9, y, 0).SerializeAsString());
  for (int i = 0; i < 4; ++i) {
    std::string g(1 + rng() % 120, '\0');
    for (char& c : g) c = char(rng());
    kinds.push_back(g);
  }
  kinds.push_back(std::string(2000, 'x'));
  kinds.push_back(kinds[0].substr(0, kinds[0].size() / 2));
  zmq::message_t in;
  paced(
      rate_hz, stop,
      [&](std::uint64_t n) {
        const std::string& m = kinds[n % kinds.size()];
        bool ok = false;
        if (n % 97 == 0) {
          ok = bool(s.send(zmq::buffer(m), zmq::send_flags::sndmore | zmq::send_flags::dontwait));
          if (ok) s.send(zmq::buffer(m), zmq::send_flags::sndmore);
          if (ok) s.send(zmq::buffer(m), zmq::send_flags::none);
        } else {
          ok = bool(s.send(zmq::buffer(m), zmq::send_flags::dontwait));
        }
        (ok ? counts.sent : counts.dropped).fetch_add(1, std::memory_order_relaxed);
      },
      [&] {
        if (read)
          while (s.recv(in, zmq::recv_flags::dontwait)) counts.replies.fetch_add(1, std::memory_order_relaxed);
      });
}

// libFuzzer's kinds of mutation on a message's bytes, a few at a time
std::string mutate(std::string m, const std::vector<std::string>& seeds, std::mt19937_64& rng) {
  const int n = 1 + int(rng() % 4);
  for (int k = 0; k < n; ++k) {
    const std::size_t size = m.size();
    switch (rng() % 8) {
      case 0:  // flip a bit
        if (size) m[rng() % size] ^= char(1 << (rng() % 8));
        break;
      case 1:  // a random byte
        if (size) m[rng() % size] = char(rng());
        break;
      case 2:  // insert bytes
        m.insert(size ? rng() % size : 0, std::string(1 + rng() % 8, char(rng())));
        break;
      case 3:  // erase bytes
        if (size > 1) m.erase(rng() % size, 1 + rng() % std::min<std::size_t>(8, size - 1));
        break;
      case 4:  // truncate
        if (size) m.resize(rng() % size);
        break;
      case 5: {  // an interesting number over 1, 2, 4 or 8 bytes
        static const std::uint64_t kInteresting[] = {0, 1, 0x7f, 0x80, 0xff, 0x7fff, 0xffffffff, ~0ull, 1ull << 63};
        const std::uint64_t v = kInteresting[rng() % (sizeof kInteresting / sizeof *kInteresting)];
        const std::size_t w = std::size_t(1) << (rng() % 4);
        if (size >= w) std::memcpy(&m[rng() % (size - w + 1)], &v, w);
        break;
      }
      case 6: {  // splice in a piece of another seed
        const std::string& o = seeds[rng() % seeds.size()];
        if (!o.empty()) {
          const std::size_t a = rng() % o.size();
          m.insert(size ? rng() % size : 0, o.substr(a, 1 + rng() % (o.size() - a)));
        }
        break;
      }
      default:  // repeat a stretch
        if (size > 1) {
          const std::size_t a = rng() % size;
          m.insert(a, m.substr(a, 1 + rng() % std::min<std::size_t>(16, size - a)));
        }
        break;
    }
  }
  return m;
}

// the valid messages a fuzzing client mutates: poses of every shape, and every control request
// but LoadScene with a scene text (the soak keeps its scene; scene text is the scene fuzzer's)
void fuzz_seeds(std::uint64_t session, const v1::PatientInfo& p, std::vector<std::string>& poses,
                std::vector<std::string>& controls) {
  const double x = 0.5 * (p.body_min_mm().x() + p.body_max_mm().x()), y = p.body_max_mm().y() - 5,
               z = 0.5 * (p.body_min_mm().z() + p.body_max_mm().z());
  v1::PoseRequest q = pose_request(session, 7, x, y, z);
  poses.push_back(q.SerializeAsString());
  q.set_reset_proxy(true);
  poses.push_back(q.SerializeAsString());
  q.set_local_model_edge(12);
  q.set_local_model_period_s(0.05);
  q.set_renders_locally(true);
  poses.push_back(q.SerializeAsString());
  std::vector<v1::ControlRequest> c(9);
  c[0].mutable_open()->set_client_name("fuzz");
  c[1].mutable_close()->set_session_id(session);
  c[2].mutable_reset()->set_session_id(session);
  c[3].mutable_set_parameter()->set_session_id(session);
  c[3].mutable_set_parameter()->set_name("stiffness_n_per_mm");
  c[3].mutable_set_parameter()->set_value(0.3);
  c[4].mutable_stats()->set_session_id(session);
  c[5].mutable_info();
  c[6].mutable_watch()->set_session_id(session);
  c[6].mutable_watch()->set_frames(true);
  c[6].mutable_watch()->mutable_view()->set_width(64);
  c[6].mutable_watch()->mutable_view()->set_height(48);
  c[7].mutable_load_scene()->set_path("missing.textproto");
  c[8].mutable_watch()->set_bricks(true);
  c[8].mutable_watch()->set_hold_s(1);
  for (auto& r : c) {
    r.set_schema_version(v1::VERSION_CURRENT);
    r.set_request_id(42);
    controls.push_back(r.SerializeAsString());
  }
}

// one fuzzing client: mutated messages to the pose socket (49 in 50) and to the control
// socket (1 in 50: every refusal there is logged), sometimes in several frames; it reads
// and counts whatever comes back
void fuzz(const std::string& control, const std::string& pose, double rate_hz, unsigned seed,
          const std::atomic<bool>& stop, Counts& counts) {
  zmq::context_t ctx(1);
  v1::ControlRequest open;
  const std::string token = "fuzzer-" + std::to_string(seed);
  open.set_client_token(token);
  open.mutable_open()->set_client_name("fuzzer");
  v1::ControlReply opened;
  control_call(ctx, control, open, opened);
  std::vector<std::string> poses, controls;
  fuzz_seeds(opened.open().session_id(), opened.open().server().patient(), poses, controls);
  std::vector<std::string> all = poses;
  all.insert(all.end(), controls.begin(), controls.end());
  zmq::socket_t ps(ctx, zmq::socket_type::dealer), cs(ctx, zmq::socket_type::dealer);
  for (zmq::socket_t* s : {&ps, &cs}) s->set(zmq::sockopt::linger, 0);
  ps.connect(pose);
  cs.connect(control);
  std::mt19937_64 rng(seed * 7919);
  zmq::message_t in;
  paced(
      rate_hz, stop,
      [&](std::uint64_t) {
        const bool to_control = rng() % 50 == 0;
        const auto& seeds = to_control ? controls : poses;
        zmq::socket_t& s = to_control ? cs : ps;
        // 1 in 16 as it is: valid poses and requests of its own session keep those paths busy too
        std::string m = rng() % 16 ? mutate(seeds[rng() % seeds.size()], all, rng) : seeds[rng() % seeds.size()];
        // the client token is kept on most control messages, so that they reach its sessions
        bool ok;
        if (rng() % 64 == 0) {
          ok = bool(s.send(zmq::buffer(m), zmq::send_flags::sndmore | zmq::send_flags::dontwait));
          if (ok) s.send(zmq::buffer(mutate(m, all, rng)), zmq::send_flags::none);
        } else {
          if (to_control && rng() % 4) {
            v1::ControlRequest r;
            if (r.ParseFromString(m)) {
              r.set_client_token(token);
              m = r.SerializeAsString();
            }
          }
          ok = bool(s.send(zmq::buffer(m), zmq::send_flags::dontwait));
        }
        (ok ? counts.sent : counts.dropped).fetch_add(1, std::memory_order_relaxed);
      },
      [&] {
        for (zmq::socket_t* s : {&ps, &cs})
          while (s->recv(in, zmq::recv_flags::dontwait)) counts.replies.fetch_add(1, std::memory_order_relaxed);
      });
}

// a viewer (this program again, as a child process): watches the newest session of client
// token `token` on `control` (frames and bricks, a small view), then reads what comes, or
// with `stall` subscribes and never reads. Prints what it got when stopped.
int run_viewer(const std::string& control, const std::string& token, bool stall) {
  zmq::context_t ctx(1);
  v1::ControlRequest w;
  w.set_client_token(token);
  w.mutable_watch()->set_frames(true);
  w.mutable_watch()->set_bricks(true);
  w.mutable_watch()->mutable_view()->set_width(320);
  w.mutable_watch()->mutable_view()->set_height(180);
  v1::ControlReply r;
  for (int i = 0; i < 100 && !(control_call(ctx, control, w, r) && r.has_watch()); ++i) sleep_s(0.1);
  if (!r.has_watch()) {
    std::fprintf(stderr, "viewer: no watch: %s\n", r.error().message().c_str());
    return 1;
  }
  zmq::socket_t sub(ctx, zmq::socket_type::sub);
  sub.set(zmq::sockopt::linger, 0);
  sub.set(zmq::sockopt::rcvhwm, 4);
  sub.connect(r.watch().stream_endpoint());
  sub.set(zmq::sockopt::subscribe, r.watch().frame_topic());
  sub.set(zmq::sockopt::subscribe, r.watch().brick_topic());
  std::printf("viewer: watching %016llx%s\n", (unsigned long long)r.watch().session_id(), stall ? ", never reading" : "");
  std::fflush(stdout);
  std::signal(SIGTERM, [](int) { std::_Exit(0); });
  std::uint64_t got = 0;
  for (zmq::message_t m;;) {
    if (stall) {
      sleep_s(1);
      continue;
    }
    if (sub.recv(m)) ++got;
    if (got % 50 == 1) {
      std::printf("viewer: %llu messages\n", (unsigned long long)got);
      std::fflush(stdout);
    }
  }
}

// --- palpsim-haptic -------------------------------------------------------------------------

// what palpsim-haptic printed at exit
struct HapticSummary {
  bool parsed = false;
  long steps = 0, replies = 0, errors = 0, lost = 0, trips = 0, missed = 0, reopens = 0;
  double p50_us = 0, p99_us = 0, p999_us = 0;
};

HapticSummary parse_haptic(const std::string& out) {
  HapticSummary h;
  const auto steps = out.find(" steps at ");
  if (steps == std::string::npos) return h;
  const auto a = out.rfind("palpsim-haptic: ", steps);
  if (a == std::string::npos) return h;
  double rate = 0;
  h.parsed = std::sscanf(out.c_str() + a,
                         "palpsim-haptic: %ld steps at %lf Hz, %ld replies, %ld errors, %ld lost, %ld watchdog trips\n"
                         "round trip p50 %lf us, p99 %lf us, p99.9 %lf us; missed deadlines %ld",
                         &h.steps, &rate, &h.replies, &h.errors, &h.lost, &h.trips, &h.p50_us, &h.p99_us, &h.p999_us,
                         &h.missed) == 10;
  const auto r = out.find("session reopened ");
  if (r != std::string::npos) h.reopens = std::atol(out.c_str() + r + 17);
  return h;
}

// a path for palpsim-haptic's csv device: presses 40 mm deep into the back at 20 mm/s, held
// 0.5 s, one every 4.5 s, for `seconds`, at lane `lane` of 16 over the back, from `t0_s`
std::string press_path(const v1::PatientInfo& p, int lane, double seconds, double t0_s) {
  const double x = 0.5 * (p.body_min_mm().x() + p.body_max_mm().x()) + (lane % 4 - 1.5) * 20;
  const double z = 0.5 * (p.body_min_mm().z() + p.body_max_mm().z()) + (lane / 4 % 4 - 1.5) * 30;
  const double y = p.body_max_mm().y() + 10;
  std::ostringstream s;
  s << "t,x,y,z\n0," << x << ',' << y << ',' << z << '\n';
  for (double t = t0_s; t + 4.5 <= seconds; t += 4.5)
    s << t << ',' << x << ',' << y << ',' << z << '\n'
      << t + 2 << ',' << x << ',' << y - 40 << ',' << z << '\n'
      << t + 2.5 << ',' << x << ',' << y - 40 << ',' << z << '\n'
      << t + 4.5 << ',' << x << ',' << y << ',' << z << '\n';
  s << seconds << ',' << x << ',' << y << ',' << z << '\n';
  return test::temp_file("rel-path", s.str());
}

// --- phases ---------------------------------------------------------------------------------

struct Report {
  std::string date, machine, commit;
  double load_start = 0, load_end = 0;
  std::ostringstream md, json;  // sections, appended by the phases
  std::uint64_t fuzzed = 0, faults = 0, crashes = 0, honest_lost = 0, honest_errors = 0;
  bool memory_flat = true;
  std::vector<std::string> json_sections;
};

void print_sched(std::ostream& out, const std::map<std::string, SchedSampler::Summary>& sched, double seconds) {
  char line[256];
  for (const auto& [name, s] : sched) {
    if (s.run_s + s.wait_s < 0.01 * seconds) continue;  // idle threads
    std::snprintf(line, sizeof line, "| %s | %.2f s (%.1f %%) | %.2f s (%.1f %%) | %.1f ms | %.0f |\n", name.c_str(),
                  s.run_s, 100 * s.run_s / seconds, s.wait_s, 100 * s.wait_s / seconds, 1e3 * s.worst_wait_s,
                  s.wakeups / seconds);
    out << line;
  }
}

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
  {
    zmq::context_t ctx(1);
    v1::ControlRequest q;
    q.mutable_info();
    if (!control_call(ctx, server.control(), q, info)) throw Error("palpsim-bench reliability: no Info from the server");
  }
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
  std::string killed_out, cuda_reply;
  bool killed_done = false, cuda_done = false, server_died = false;
  while (seconds_since(t0) < seconds + 5) {
    sleep_s(0.5);
    const double t = seconds_since(t0);
    if (!killed_done && t > seconds / 3) {
      killed_out = killed->out();
      killed->signal(SIGKILL);
      killed->wait(10);
      killed_done = true;
      ++rep.faults;
      std::printf("soak: t = %.0f s, a viewer killed with -9\n", t);
    }
    if (!cuda_done && t > seconds / 2) {
      zmq::context_t ctx(1);
      v1::ControlRequest q;
      q.mutable_load_scene()->set_path(dir + "/cuda.textproto");
      v1::ControlReply r;
      cuda_reply = control_call(ctx, server.control(), q, r, 120000)
                       ? (r.has_error() ? v1::ErrorCode_Name(r.error().code()) + ": " + r.error().message()
                                        : std::string("loaded: ") + r.load_scene().server().scene_name())
                       : std::string("no reply within 120 s");
      cuda_done = true;
      ++rep.faults;
      std::printf("soak: t = %.0f s, LoadScene of a scene asking for cuda: %s\n", t, cuda_reply.c_str());
    }
    if (server.child().wait(0) >= 0) {
      server_died = true;
      break;
    }
    bool all_done = true;
    for (auto& h : honest) all_done = all_done && h->wait(0) >= 0;
    if (all_done) break;
  }
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
  long lost = 0, errors = 0, steps = 0;
  std::vector<double> p99;
  for (const auto& h : hs) {
    lost += h.parsed ? h.lost : 60000;
    errors += h.errors;
    steps += h.steps;
    p99.push_back(h.p99_us);
  }
  rep.honest_lost += std::uint64_t(lost);
  rep.honest_errors += std::uint64_t(errors);
  // memory: the plateau after the first fifth against the end, of RSS and of RSS less what the
  // open sessions' stages hold (the fuzzers open sessions within their quota, and each that
  // deforms holds an engine; that is bounded by the quotas, not a leak)
  double plateau = 0, end = 0, peak = 0, free_plateau = 0, free_end = 0;
  int sessions_min = 1 << 30, sessions_max = 0;
  double held_max = 0;
  for (const MemorySample& m : samples) {
    if (!m.answered) continue;
    if (plateau == 0 && m.t_s >= 0.2 * seconds) {
      plateau = m.rss_mb;
      free_plateau = m.rss_mb - m.held_mb;
    }
    peak = std::max(peak, m.rss_mb);
    end = m.rss_mb;
    free_end = m.rss_mb - m.held_mb;
    sessions_min = std::min(sessions_min, m.sessions);
    sessions_max = std::max(sessions_max, m.sessions);
    held_max = std::max(held_max, m.held_mb);
  }
  const bool flat = free_plateau > 0 && free_end <= 1.1 * free_plateau;
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
  rep.md << line;
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
                server_died ? "**died**" : rc == 0 ? "stopped cleanly at the end" : "did not stop cleanly", rss0, plateau,
                end, peak, sessions_max ? sessions_min : 0, sessions_max, held_max, free_plateau, free_end,
                flat ? "flat: the end within 10 % of the plateau" : "**not flat**");
  rep.md << line << "\nOver time (s: RSS MB, held by the stages MB, sessions):";
  const std::size_t stride = std::max<std::size_t>(1, samples.size() / 20);
  for (std::size_t i = 0; i < samples.size(); i += stride) {
    std::snprintf(line, sizeof line, " %.0f: %.0f, %.0f, %d;", samples[i].t_s, samples[i].rss_mb, samples[i].held_mb,
                  samples[i].sessions);
    rep.md << line;
  }
  rep.md << "\n\n";
  std::ostringstream js;
  js << "\"soak\": {\"minutes\": " << o.minutes << ", \"honest\": " << o.honest << ", \"poses\": " << steps
     << ", \"honest_lost\": " << lost << ", \"honest_errors\": " << errors << ", \"fuzzed\": " << fuzzed.sent
     << ", \"fuzz_replies\": " << fuzzed.replies << ", \"unanswered\": " << st.bad_input_unanswered()
     << ", \"cuda_load_scene\": \"" << (cuda_reply.find("ERROR_") == 0 ? cuda_reply.substr(0, cuda_reply.find(':')) : "other")
     << "\", \"server_died\": " << (server_died ? "true" : "false") << ", \"server_exit\": " << rc
     << ", \"rss_mb\": [";
  for (std::size_t i = 0; i < samples.size(); ++i)
    js << (i ? ", " : "") << "[" << json_number(samples[i].t_s) << ", " << json_number(samples[i].rss_mb) << "]";
  js << "], \"held_mb\": [";
  for (std::size_t i = 0; i < samples.size(); ++i) js << (i ? ", " : "") << json_number(samples[i].held_mb);
  js << "], \"sessions\": [";
  for (std::size_t i = 0; i < samples.size(); ++i) js << (i ? ", " : "") << samples[i].sessions;
  js << "], \"memory_flat\": " << (flat ? "true" : "false") << "}";
  rep.json_sections.push_back(js.str());
  for (const auto& p : paths) std::remove(p.c_str());
  std::remove((dir + "/cuda.textproto").c_str());
  ::rmdir(dir.c_str());
}

// faults: kill -9 and restart under a pressing client; a full file system for recorded
// frames; a server started on a cuda scene with no GPU
void faults_phase(const Options& o, Report& rep) {
  rep.md << "## Faults\n\n";
  std::ostringstream js;
  js << "\"faults\": {";
  // a small scene: the phantom at 2 mm, haptics only (the restarts measure the client)
  const std::string scene = test::temp_file("rel-scene", test::fast_scene_text("reliability", 30));
  {
    test::ServerProcess first(scene, o.server_args, o.server_exe);
    if (!first.wait_ready(600)) throw Error("palpsim-bench reliability: the server did not start");
    const std::string control = first.control(), pose = first.pose();
    v1::ControlReply info;
    {
      zmq::context_t ctx(1);
      v1::ControlRequest q;
      q.mutable_info();
      control_call(ctx, control, q, info);
    }
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
  // frames recorded into a full file system
  {
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
  // a server asked for the cuda backend where there is no GPU
  {
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
