// An in-process client of net::Server for the unit tests of the network edge: loopback
// server options on free ports, pose requests, and a session of a REQ (control) and a
// DEALER (poses) that opens itself on construction.
#pragma once

#include <catch2/catch.hpp>

#include <cstdint>
#include <string>
#include <utility>
#include <zmq.hpp>

#include "core/vec3.h"
#include "net/server.h"
#include "palpsim/wire.pb.h"
#include "support/zmq_exchange.h"

namespace palpsim::test {

/// Server options that bind control and poses on loopback ports the system picks, so
/// tests running side by side never collide.
inline net::ServerOptions loopback_options() {
  net::ServerOptions o;
  o.control_bind = "tcp://127.0.0.1:*";
  o.pose_bind = "tcp://127.0.0.1:*";
  // ctest runs other suites beside these: a SCHED_IDLE worker could wait for them to end
  o.background_idle = false;
  return o;
}

/// A pose request of schema version 1 for `session_id`: tip at `tip_mm`, client clock
/// `client_time_s`, proxy reset when `reset`.
inline palpsim::v1::PoseRequest pose_request(std::uint64_t session_id, std::uint64_t seq, const Vec3& tip_mm,
                                             double client_time_s, bool reset = false) {
  palpsim::v1::PoseRequest q;
  q.set_schema_version(1);
  q.set_session_id(session_id);
  q.set_seq(seq);
  q.set_client_time_s(client_time_s);
  q.set_reset_proxy(reset);
  q.mutable_tip_mm()->set_x(tip_mm.x);
  q.mutable_tip_mm()->set_y(tip_mm.y);
  q.mutable_tip_mm()->set_z(tip_mm.z);
  return q;
}

/// The stage called `name` in a stats reply's stage list, or nullptr.
inline const palpsim::v1::StageInfo* stage(const google::protobuf::RepeatedPtrField<palpsim::v1::StageInfo>& stages,
                                           const std::string& name) {
  for (const auto& s : stages)
    if (s.name() == name) return &s;
  return nullptr;
}

/// One session on a running server: a REQ for control requests and a DEALER for poses,
/// opened under `client_name` on construction (the session id is in `id`). Every control
/// request carries `client_token`: clients with the same token act on each other's
/// sessions; with none, a session is its own REQ's alone (PROTOCOL.md, "Who may connect").
struct NetClient {
  zmq::context_t ctx{1};
  zmq::socket_t ctl{ctx, zmq::socket_type::req};
  zmq::socket_t pose{ctx, zmq::socket_type::dealer};
  std::uint64_t id = 0;
  std::string client_token;

  NetClient(const net::Server& s, const char* client_name, std::string token = "")
      : client_token(std::move(token)) {
    ctl.set(zmq::sockopt::linger, 0);
    pose.set(zmq::sockopt::linger, 0);
    ctl.connect(s.control_endpoint());
    pose.connect(s.pose_endpoint());
    palpsim::v1::ControlRequest q;
    q.mutable_open()->set_client_name(client_name);
    const auto r = call(q);
    REQUIRE(r.has_open());
    id = r.open().session_id();
  }

  /// One control request (schema version 1 filled in) and its reply.
  palpsim::v1::ControlReply call(palpsim::v1::ControlRequest q) {
    q.set_schema_version(1);
    q.set_client_token(client_token);
    return exchange<palpsim::v1::ControlReply>(ctl, q);
  }

  /// The server's stats with this session's.
  palpsim::v1::StatsReply stats() {
    palpsim::v1::ControlRequest q;
    q.mutable_stats()->set_session_id(id);
    const auto r = call(q);
    REQUIRE(r.has_stats());
    return r.stats();
  }

  /// One pose of this session and its reply, as it came (errors are the caller's to check).
  palpsim::v1::PoseReply send_pose(std::uint64_t seq, const Vec3& tip_mm, double client_time_s, bool reset = false) {
    return exchange<palpsim::v1::PoseReply>(pose, pose_request(id, seq, tip_mm, client_time_s, reset));
  }
};

}  // namespace palpsim::test
