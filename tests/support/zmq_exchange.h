// One request/reply exchange of protobuf messages on a ZeroMQ socket (REQ, or a DEALER
// used like one), for tests that talk to a server in-process or as a child process.
#pragma once

#include <catch2/catch.hpp>

#include <chrono>
#include <optional>
#include <zmq.hpp>

namespace palpsim::test {

/// How long one exchange waits for its reply by default (ms): far above any answer of a
/// healthy server, so that only a lost reply fails the test.
constexpr int kReplyWaitMs = 10000;

/// The next message on `socket` when one comes within `timeout_ms`, else nothing.
inline std::optional<zmq::message_t> receive_within(zmq::socket_t& socket, int timeout_ms) {
  zmq::pollitem_t it[] = {{socket.handle(), 0, ZMQ_POLLIN, 0}};
  zmq::poll(it, 1, std::chrono::milliseconds(timeout_ms));
  if (!(it[0].revents & ZMQ_POLLIN)) return std::nullopt;
  zmq::message_t m;
  (void)socket.recv(m);
  return m;
}

/// The next message on `socket` parsed as `Reply` when one comes within `timeout_ms`, else
/// nothing; the test fails when it does not parse.
template <class Reply>
std::optional<Reply> reply_within(zmq::socket_t& socket, int timeout_ms) {
  const std::optional<zmq::message_t> m = receive_within(socket, timeout_ms);
  if (!m) return std::nullopt;
  Reply r;
  REQUIRE(r.ParseFromArray(m->data(), int(m->size())));
  return r;
}

/// Sends `request` on `socket` and returns the parsed reply; the test fails when none
/// comes within `timeout_ms` or it does not parse as `Reply`.
template <class Reply, class Request>
Reply exchange(zmq::socket_t& socket, const Request& request, int timeout_ms = kReplyWaitMs) {
  socket.send(zmq::buffer(request.SerializeAsString()), zmq::send_flags::none);
  const std::optional<Reply> r = reply_within<Reply>(socket, timeout_ms);
  REQUIRE(r);
  return *r;
}

}  // namespace palpsim::test
