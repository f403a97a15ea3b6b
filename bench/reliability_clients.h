// The clients of palpsim-bench reliability (reliability_bench.cpp): control requests, paced
// fuzzing clients that mutate valid messages as libFuzzer does, a viewer (stalled or not),
// and palpsim-haptic's summary and press paths.
#pragma once

#include <google/protobuf/stubs/logging.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "core/error.h"
#include "palpsim/wire.pb.h"
#include "tests/integration/server_process.h"

namespace palpsim::bench::reliability {

namespace v1 = palpsim::v1;
using Clock = std::chrono::steady_clock;

inline double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

inline void sleep_s(double s) { std::this_thread::sleep_for(std::chrono::duration<double>(s)); }

// --- clients ------------------------------------------------------------------------------

// one control request on a fresh REQ socket; false when no reply came within `timeout_ms`
inline bool control_call(zmq::context_t& ctx, const std::string& endpoint, v1::ControlRequest q, v1::ControlReply& out,
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
inline v1::ServerStats server_stats(const std::string& control) {
  zmq::context_t ctx(1);
  v1::ControlRequest q;
  q.mutable_stats();
  v1::ControlReply r;
  return control_call(ctx, control, q, r) ? r.stats().server() : v1::ServerStats{};
}

// the server's Info reply; false when none came
inline bool server_info(const std::string& control, v1::ControlReply& info) {
  zmq::context_t ctx(1);
  v1::ControlRequest q;
  q.mutable_info();
  return control_call(ctx, control, q, info);
}

// a pose of `session` at `tip`
inline v1::PoseRequest pose_request(std::uint64_t session, std::uint64_t seq, double x, double y, double z) {
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
inline void paced(double rate_hz, const std::atomic<bool>& stop, const std::function<void(std::uint64_t)>& send_one,
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
inline void flood(const std::string& control, const std::string& pose, double rate_hz, bool read, unsigned seed,
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
inline std::string mutate(std::string m, const std::vector<std::string>& seeds, std::mt19937_64& rng) {
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
inline void fuzz_seeds(std::uint64_t session, const v1::PatientInfo& p, std::vector<std::string>& poses,
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
inline void fuzz(const std::string& control, const std::string& pose, double rate_hz, unsigned seed,
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
inline int run_viewer(const std::string& control, const std::string& token, bool stall) {
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
  std::printf("viewer: watching %016llx%s\n", (unsigned long long)r.watch().session_id(),
              stall ? ", never reading" : "");
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

inline HapticSummary parse_haptic(const std::string& out) {
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
inline std::string press_path(const v1::PatientInfo& p, int lane, double seconds, double t0_s) {
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

}  // namespace palpsim::bench::reliability
