// One request/reply exchange of protobuf messages on a ZeroMQ socket (REQ, or a DEALER
// used like one), for tests that talk to a server in-process or as a child process.
#pragma once

#include <catch2/catch.hpp>

#include <chrono>
#include <zmq.hpp>

namespace palpsim::test {

/// How long one exchange waits for its reply by default (ms): far above any answer of a
/// healthy server, so that only a lost reply fails the test.
constexpr int kReplyWaitMs = 10000;

/// Sends `request` on `socket` and returns the parsed reply; the test fails when none
/// comes within `timeout_ms` or it does not parse as `Reply`.
template <class Reply, class Request>
Reply exchange(zmq::socket_t& socket, const Request& request, int timeout_ms = kReplyWaitMs) {
  socket.send(zmq::buffer(request.SerializeAsString()), zmq::send_flags::none);
  zmq::pollitem_t it[] = {{socket.handle(), 0, ZMQ_POLLIN, 0}};
  zmq::poll(it, 1, std::chrono::milliseconds(timeout_ms));
  REQUIRE((it[0].revents & ZMQ_POLLIN));
  zmq::message_t m;
  (void)socket.recv(m);
  Reply r;
  REQUIRE(r.ParseFromArray(m.data(), int(m.size())));
  return r;
}

}  // namespace palpsim::test
