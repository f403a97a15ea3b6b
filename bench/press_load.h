// Server load for the benchmarks that run a real palpsim-server in process (render,
// server): n haptic clients, each on its own session and thread, pressing at 1 kHz on the
// back's midline, timing every round trip; and the control request helper they share.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include <zmq.hpp>

#include "palpsim/wire.pb.h"

namespace palpsim::bench {

/// The client token every request of the bench's clients carries.
inline constexpr const char* kBenchClientToken = "palpsim-bench";

/// Sends one control request (schema version set) and returns the reply.
inline v1::ControlReply control(zmq::socket_t& s, v1::ControlRequest q) {
  q.set_schema_version(1);
  // every bench client acts as one client (PROTOCOL.md, "Who may connect"): a viewer
  // thread may watch, and the bench read the stats of, the sessions its press threads
  // opened on other connections
  q.set_client_token(kBenchClientToken);
  s.send(zmq::buffer(q.SerializeAsString()), zmq::send_flags::none);
  zmq::message_t m;
  (void)s.recv(m);
  v1::ControlReply r;
  r.ParseFromArray(m.data(), int(m.size()));
  return r;
}

/// What press_sessions() did: each client's round trips (us, after the warm-up), session
/// id, and poses answered in contact (warm-up included; a pose a millisecond, so this is
/// the client's time in the body in ms: steps are asked for only then).
struct PressResult {
  std::vector<std::vector<double>> rtt_us;
  std::vector<std::uint64_t> ids;
  std::vector<long> contact_poses;
};

/// Opens `n` sessions on the server at `control_endpoint`, each pressed by its own
/// client thread at 1 kHz for `seconds` after a 200 ms warm-up: a 1 Hz press 0..30 mm
/// deep along the back's midline (x at the body's centre, from 5 mm above the body's
/// top in y), sessions 8 mm apart in z around L3 (closer when more than 20, so that all
/// stay within 160 mm), clients spread over the millisecond.
/// `on_open`, when given, gets each client's index and session id as it opens, before
/// `opened`, when given, counts it (watchers wait for n). `before_close`,
/// when given, runs on each client thread after its last pose and before it closes its
/// session, with the client index, its control socket and session id (to read the
/// session's stats).
inline PressResult press_sessions(const std::string& control_endpoint, const v1::PatientInfo& pi, int n,
                                  double seconds, std::atomic<int>* opened = nullptr,
                                  const std::function<void(int, std::uint64_t)>& on_open = {},
                                  const std::function<void(int, zmq::socket_t&, std::uint64_t)>& before_close = {}) {
  using Clock = std::chrono::steady_clock;
  PressResult out;
  out.rtt_us.resize(n);
  out.ids.assign(n, 0);
  out.contact_poses.assign(n, 0);
  std::atomic<int> local_opened{0};
  std::atomic<int>& count = opened ? *opened : local_opened;
  std::vector<std::thread> threads;
  const double cx = 0.5 * (pi.body_min_mm().x() + pi.body_max_mm().x());
  const int base = count.load();
  for (int c = 0; c < n; ++c)
    threads.emplace_back([&, c] {
      zmq::context_t ctx(1);
      zmq::socket_t ctl(ctx, zmq::socket_type::req), pose(ctx, zmq::socket_type::dealer);
      ctl.set(zmq::sockopt::linger, 0);
      pose.set(zmq::sockopt::linger, 0);
      ctl.connect(control_endpoint);
      v1::ControlRequest q;
      q.mutable_open()->set_client_name("bench press " + std::to_string(c));
      const v1::ControlReply r = control(ctl, q);
      out.ids[c] = r.open().session_id();
      pose.connect(r.open().pose_endpoint());
      if (on_open) on_open(c, out.ids[c]);
      ++count;
      while (count < base + n) std::this_thread::sleep_for(std::chrono::milliseconds(1));
      // 8 mm apart, closer where that would leave the body (the phantom spans about
      // 220 mm in z): all n within 160 mm around L3
      const double z = -5 + std::min(8.0, 160.0 / std::max(1, n)) * (c - n / 2);
      const double top = pi.body_max_mm().y() + 5;
      zmq::pollitem_t it[] = {{pose.handle(), 0, ZMQ_POLLIN, 0}};
      zmq::message_t m;
      v1::PoseRequest pr;
      pr.set_schema_version(1);
      pr.set_session_id(out.ids[c]);
      std::string bytes;
      const auto t0 = Clock::now() + std::chrono::microseconds(1000 * c / std::max(1, n));
      const long steps = long(seconds * 1000), warm = 200;
      out.rtt_us[c].reserve(steps);
      // one pose per millisecond, each timed from send to reply
      for (long s = 0; s < steps + warm; ++s) {
        std::this_thread::sleep_until(t0 + std::chrono::microseconds(1000 * s));
        const double depth = 30 * (0.5 - 0.5 * std::cos(2 * M_PI * s / 1000.0));
        pr.set_seq(std::uint64_t(s + 1));
        pr.set_client_time_s(s * 1e-3);
        pr.mutable_tip_mm()->set_x(cx);
        pr.mutable_tip_mm()->set_y(top - depth);
        pr.mutable_tip_mm()->set_z(z);
        pr.SerializeToString(&bytes);
        const auto ts = Clock::now();
        pose.send(zmq::buffer(bytes), zmq::send_flags::none);
        zmq::poll(it, 1, std::chrono::milliseconds(1000));
        if (!(it[0].revents & ZMQ_POLLIN)) continue;
        (void)pose.recv(m);
        if (s >= warm) out.rtt_us[c].push_back(std::chrono::duration<double, std::micro>(Clock::now() - ts).count());
        v1::PoseReply reply;
        if (reply.ParseFromArray(m.data(), int(m.size())) && reply.contact()) ++out.contact_poses[c];
      }
      if (before_close) before_close(c, ctl, out.ids[c]);
      v1::ControlRequest cl;
      cl.mutable_close()->set_session_id(out.ids[c]);
      control(ctl, cl);
    });
  for (auto& t : threads) t.join();
  return out;
}

}  // namespace palpsim::bench
