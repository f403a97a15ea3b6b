// One session on a palpsim-server run as a child process (integration tests): a DEALER
// for control requests and one for poses, opened on construction; poses at 1 kHz on the
// client's clock, each answered without error; the session's stats.
#pragma once

#include <catch2/catch.hpp>

#include <cstdint>
#include <string>
#include <zmq.hpp>

#include "core/vec3.h"
#include "palpsim/wire.pb.h"
#include "support/zmq_exchange.h"

namespace palpsim::test {

/// A session opened under `client_name` on the server at `control` and `pose` endpoints.
struct PoseSession {
  zmq::context_t ctx{1};
  zmq::socket_t ctl{ctx, zmq::socket_type::dealer};
  zmq::socket_t pose{ctx, zmq::socket_type::dealer};
  palpsim::v1::OpenReply open;  // the server's answer (session id, ServerInfo)
  std::uint64_t id = 0;
  std::uint64_t seq = 0;        // of the last pose sent
  int timeout_ms = kReplyWaitMs;

  PoseSession(const std::string& control, const std::string& pose_endpoint, const char* client_name,
              int reply_timeout_ms = kReplyWaitMs)
      : timeout_ms(reply_timeout_ms) {
    ctl.set(zmq::sockopt::linger, 0);
    pose.set(zmq::sockopt::linger, 0);
    ctl.connect(control);
    pose.connect(pose_endpoint);
    palpsim::v1::ControlRequest q;
    q.set_schema_version(1);
    q.mutable_open()->set_client_name(client_name);
    const auto r = exchange<palpsim::v1::ControlReply>(ctl, q, timeout_ms);
    REQUIRE(r.has_open());
    open = r.open();
    id = open.session_id();
  }

  /// One pose with the tip at `tip_mm`, the client's clock 1 s + 1 ms per pose; the test
  /// fails unless it is answered without error. Returns the reply.
  palpsim::v1::PoseReply send(const Vec3& tip_mm) {
    palpsim::v1::PoseRequest p;
    p.set_schema_version(1);
    p.set_session_id(id);
    p.set_seq(++seq);
    p.set_client_time_s(1 + seq * 1e-3);
    p.mutable_tip_mm()->set_x(tip_mm.x);
    p.mutable_tip_mm()->set_y(tip_mm.y);
    p.mutable_tip_mm()->set_z(tip_mm.z);
    const auto r = exchange<palpsim::v1::PoseReply>(pose, p, timeout_ms);
    REQUIRE(r.error().code() == palpsim::v1::ERROR_NONE);
    REQUIRE(r.seq() == seq);
    return r;
  }

  /// The server's and this session's stats.
  palpsim::v1::StatsReply stats() {
    palpsim::v1::ControlRequest q;
    q.set_schema_version(1);
    q.mutable_stats()->set_session_id(id);
    const auto r = exchange<palpsim::v1::ControlReply>(ctl, q, timeout_ms);
    REQUIRE(r.has_stats());
    return r.stats();
  }
};

}  // namespace palpsim::test
