// The clients of the haptics server tests (haptics_server_test.cpp, haptics_bad_input_test.cpp,
// haptics_watchdog_test.cpp): DEALERs on the control and pose paths, a path through the
// body, and a server started on the fast test scene.
#pragma once

#include <catch2/catch.hpp>

#include <chrono>
#include <cmath>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>
#include <zmq.hpp>

#include "integration/server_process.h"
#include "palpsim/wire.pb.h"
#include "support/zmq_exchange.h"

namespace palpsim::test::haptics {

namespace v1 = palpsim::v1;

// how long a reply may take before a test gives up on it (loaded 2-core CI machine)
constexpr int kReplyTimeoutMs = 5000;

// a DEALER speaking the control path
class Control {
 public:
  Control(zmq::context_t& ctx, const std::string& addr) : s_(ctx, zmq::socket_type::dealer) {
    s_.set(zmq::sockopt::linger, 0);
    s_.connect(addr);
  }
  /// Sends raw frames and returns the parsed reply (throws on timeout or junk).
  v1::ControlReply raw(const std::vector<std::string>& frames) {
    for (std::size_t i = 0; i < frames.size(); ++i)
      s_.send(zmq::buffer(frames[i]), i + 1 < frames.size() ? zmq::send_flags::sndmore : zmq::send_flags::none);
    v1::ControlReply r;
    if (!reply(r, kReplyTimeoutMs)) throw std::runtime_error("no control reply");
    return r;
  }
  /// Sends a request without waiting for its reply (reply() reads it); returns its request id.
  std::uint64_t send(v1::ControlRequest req, std::uint32_t version = v1::VERSION_CURRENT) {
    req.set_schema_version(version);
    req.set_request_id(++next_id_);
    s_.send(zmq::buffer(req.SerializeAsString()));
    return next_id_;
  }
  /// The next reply if one comes within `timeout_ms` (throws on junk).
  bool reply(v1::ControlReply& r, int timeout_ms) {
    const std::optional<zmq::message_t> m = receive_within(s_, timeout_ms);
    if (!m) return false;
    if (!r.ParseFromArray(m->data(), int(m->size()))) throw std::runtime_error("control reply does not parse");
    return true;
  }
  v1::ControlReply call(v1::ControlRequest req, std::uint32_t version = v1::VERSION_CURRENT) {
    const std::uint64_t id = send(std::move(req), version);
    v1::ControlReply r;
    if (!reply(r, kReplyTimeoutMs)) throw std::runtime_error("no control reply");
    if (version == v1::VERSION_CURRENT) REQUIRE(r.request_id() == id);
    return r;
  }
  v1::OpenReply open(const std::string& name) {
    v1::ControlRequest q;
    q.mutable_open()->set_client_name(name);
    const auto r = call(q);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    REQUIRE(r.has_open());
    return r.open();
  }
  v1::ServerStats stats() {
    v1::ControlRequest q;
    q.mutable_stats();
    const auto r = call(q);
    REQUIRE(r.has_stats());
    return r.stats().server();
  }
  void close(std::uint64_t id) {
    v1::ControlRequest q;
    q.mutable_close()->set_session_id(id);
    REQUIRE(call(q).error().code() == v1::ERROR_NONE);
  }

 private:
  zmq::socket_t s_;
  std::uint64_t next_id_ = 0;
};

// a DEALER speaking the pose path
class Poses {
 public:
  Poses(zmq::context_t& ctx, const std::string& addr) : s_(ctx, zmq::socket_type::dealer) {
    s_.set(zmq::sockopt::linger, 0);
    s_.connect(addr);
  }
  void send_raw(const std::vector<std::string>& frames) {
    for (std::size_t i = 0; i < frames.size(); ++i)
      s_.send(zmq::buffer(frames[i]), i + 1 < frames.size() ? zmq::send_flags::sndmore : zmq::send_flags::none);
  }
  void send(std::uint64_t session, std::uint64_t seq, double x, double y, double z, std::uint32_t version = 1) {
    v1::PoseRequest q;
    q.set_schema_version(version);
    q.set_session_id(session);
    q.set_seq(seq);
    q.mutable_tip_mm()->set_x(x);
    q.mutable_tip_mm()->set_y(y);
    q.mutable_tip_mm()->set_z(z);
    send_raw({q.SerializeAsString()});
  }
  v1::PoseReply recv() {
    const std::optional<zmq::message_t> m = receive_within(s_, kReplyTimeoutMs);
    if (!m) throw std::runtime_error("no pose reply");
    v1::PoseReply r;
    if (!r.ParseFromArray(m->data(), int(m->size()))) throw std::runtime_error("pose reply does not parse");
    return r;
  }
  v1::PoseReply call(std::uint64_t session, std::uint64_t seq, double x, double y, double z) {
    send(session, seq, x, y, z);
    return recv();
  }
  /// True with the next reply in `r` when one comes within `timeout_ms`.
  bool try_recv(v1::PoseReply& r, int timeout_ms) {
    const std::optional<zmq::message_t> m = receive_within(s_, timeout_ms);
    return m && r.ParseFromArray(m->data(), int(m->size()));
  }

 private:
  zmq::socket_t s_;
};

// a point along a path that crosses the body's box from outside to outside (t in [0, 1])
inline void path_point(const v1::PatientInfo& p, double t, int lane, double& x, double& y, double& z) {
  const double cx = 0.5 * (p.body_min_mm().x() + p.body_max_mm().x());
  const double cz = 0.5 * (p.body_min_mm().z() + p.body_max_mm().z());
  x = cx + 10.0 * (lane % 5 - 2);
  z = cz + 8.0 * (lane % 7 - 3);
  const double y0 = p.body_max_mm().y() + 20, y1 = p.body_min_mm().y() - 20;
  y = y0 + (y1 - y0) * (0.5 - 0.5 * std::cos(2 * M_PI * t));  // out, through, and back out
}

struct Started {
  std::string scene;
  std::unique_ptr<ServerProcess> server;
};

// a server on the fast test scene; prep of the 2 mm phantom takes a few seconds (cached after)
inline Started start_server(double timeout_s = 0.5) {
  Started s;
  s.scene = test::temp_file("scene", test::fast_scene_text("integration", timeout_s));
  s.server = std::make_unique<ServerProcess>(s.scene);
  const bool ready = s.server->wait_ready(300);
  INFO("server stderr:\n" << s.server->child().err());
  REQUIRE(ready);
  return s;
}

}  // namespace palpsim::test::haptics
