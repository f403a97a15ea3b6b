// The probes of palpsim-bench reliability (reliability_bench.cpp): the load average, a
// process's RSS, its threads' time on a core and waiting for one (Linux schedstat), and the
// server's RSS beside what its stages hold, sampled over time.
#pragma once

#include <sys/types.h>

#include <atomic>
#include <cstdlib>
#include <fstream>
#include <map>
#include <ostream>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "bench/reliability_clients.h"

namespace palpsim::bench::reliability {

// the 1-minute load average
inline double load_average() {
  double l = 0;
  std::ifstream("/proc/loadavg") >> l;
  return l;
}

// the resident set of process `pid` (MB; 0 when it is gone)
inline double rss_mb(pid_t pid) {
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
inline std::map<int, ThreadTimes> read_threads(pid_t pid) {
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

inline void print_sched(std::ostream& out, const std::map<std::string, SchedSampler::Summary>& sched, double seconds) {
  char line[256];
  for (const auto& [name, s] : sched) {
    if (s.run_s + s.wait_s < 0.01 * seconds) continue;  // idle threads
    std::snprintf(line, sizeof line, "| %s | %.2f s (%.1f %%) | %.2f s (%.1f %%) | %.1f ms | %.0f |\n", name.c_str(),
                  s.run_s, 100 * s.run_s / seconds, s.wait_s, 100 * s.wait_s / seconds, 1e3 * s.worst_wait_s,
                  s.wakeups / seconds);
    out << line;
  }
}

}  // namespace palpsim::bench::reliability
