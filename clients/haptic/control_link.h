// The haptic client's control requests (open and close a session): one at a time, each
// bounded in time whatever the server does (silent, gone, or refusing this client's
// handshake), either waited for (start-up and exit) or started and picked up later by
// the loop, which never waits on the network (reopening a session after the server
// restarted).
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <zmq.hpp>

#include "palpsim/wire.pb.h"

namespace palpsim::haptic {

/// Control requests to one server address on REQ sockets. A REQ that lost its reply can
/// send nothing more, so every request that follows an unanswered one goes out on a fresh
/// socket; and a REQ whose connection was refused in the ZeroMQ handshake (a CURVE server
/// to a client without keys, a mechanism mismatch) drops that connection for good and would
/// hold a blocking send forever, so sends never block beyond the request's deadline.
class ControlLink {
 public:
  /// `setup` prepares each new socket before it connects (CURVE keys; may be empty);
  /// `curve` picks the hint that a silent server's error names.
  ControlLink(zmq::context_t& ctx, std::string address, std::function<void(zmq::socket_t&)> setup, bool curve);

  /// Sends `request` and waits for its reply, `timeout_ms` at most for both; throws
  /// std::runtime_error naming the address and what went wrong: no reply in time (with
  /// why a server may stay silent), a reply that does not parse, or an error reply.
  v1::ControlReply call(const v1::ControlRequest& request, int timeout_ms);

  /// Sends `request` without waiting for the reply (a request still waiting is given up).
  /// False when it could not even be queued.
  bool start(const v1::ControlRequest& request);
  /// True, with the reply in `reply`, once the reply to the started request has come;
  /// never waits. A reply that does not parse counts as come: `parsed` (when given) says
  /// which.
  bool take(v1::ControlReply& reply, bool* parsed = nullptr);
  /// True while a started request has no reply yet.
  bool waiting() const { return waiting_; }

  /// The socket requests go out on now (made on first use), for tests that watch it.
  zmq::socket_t& socket();

 private:
  zmq::context_t& ctx_;
  std::string address_;
  std::function<void(zmq::socket_t&)> setup_;
  bool curve_;
  std::unique_ptr<zmq::socket_t> socket_;
  bool waiting_ = false;  // the socket's request has no reply yet (a REQ then sends nothing more)

  // the socket to send on: a fresh one when the current one still waits for a reply
  zmq::socket_t& ready_socket();
};

}  // namespace palpsim::haptic
