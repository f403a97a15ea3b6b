// The haptic client's control requests (clients/haptic/control_link.h) against servers
// that never answer as they should. The hang it guards against: palpsim-haptic without
// keys against a CURVE server did not exit within 60 s once on a loaded machine
// (security_server_test). The server's ZMTP greeting names CURVE, the client's NULL: the
// client drops that connection for good (a protocol error, no reconnect), and when that
// happened before its first request was queued, a blocking send on the REQ socket, which
// then had no connection at all, waited forever.
#include <catch2/catch.hpp>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <future>
#include <string>
#include <thread>
#include <zmq.hpp>

#include "control_link.h"

namespace v1 = palpsim::v1;

namespace {

// a TCP listener on a free loopback port that plays a CURVE server's first move: it sends
// a ZMTP 3.0 greeting naming the CURVE mechanism to the first connection, then waits until
// the client drops the connection
class CurveGreeter {
 public:
  CurveGreeter() {
    fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(::bind(fd_, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0);
    REQUIRE(::listen(fd_, 4) == 0);
    socklen_t n = sizeof a;
    ::getsockname(fd_, reinterpret_cast<sockaddr*>(&a), &n);
    port_ = ntohs(a.sin_port);
    dropped_ = std::async(std::launch::async, [this] { return serve(); });
  }
  ~CurveGreeter() { ::close(fd_); }
  std::string address() const { return "tcp://127.0.0.1:" + std::to_string(port_); }
  // true once the client has closed the connection (within 30 s, a bound no healthy run nears)
  bool client_dropped() { return dropped_.get(); }

 private:
  int fd_ = -1, port_ = 0;
  std::future<bool> dropped_;

  bool serve() {
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, 30000) != 1) return false;
    const int c = ::accept(fd_, nullptr, nullptr);
    // signature, version 3.0, mechanism "CURVE" (20 bytes), as-server, filler (31 bytes)
    unsigned char greeting[64] = {0xFF, 0, 0, 0, 0, 0, 0, 0, 0, 0x7F, 3, 0, 'C', 'U', 'R', 'V', 'E'};
    greeting[32] = 1;
    bool dropped = ::write(c, greeting, sizeof greeting) == ssize_t(sizeof greeting);
    // read what the client sends until it closes the connection
    char buf[256];
    for (pollfd q{c, POLLIN, 0}; dropped;) {
      if (::poll(&q, 1, 30000) != 1) dropped = false;
      else if (::read(c, buf, sizeof buf) <= 0) break;
    }
    ::close(c);
    return dropped;
  }
};

v1::ControlRequest info_request() {
  v1::ControlRequest q;
  q.set_schema_version(v1::VERSION_CURRENT);
  q.mutable_info();
  return q;
}

}  // namespace

TEST_CASE("a request after the server refused the handshake fails at its deadline instead of hanging",
          "[haptic][control]") {
  CurveGreeter server;
  zmq::context_t ctx(1);
  palpsim::haptic::ControlLink link(ctx, server.address(), {}, false);
  zmq::socket_t& s = link.socket();  // connects
  // the client has dropped the connection (mechanism mismatch), and once its socket has
  // taken that in (reading ZMQ_EVENTS processes its pending commands) it can send nowhere
  REQUIRE(server.client_dropped());
  bool can_send = true;
  for (int i = 0; i < 3000 && can_send; ++i) {
    can_send = s.get(zmq::sockopt::events) & ZMQ_POLLOUT;
    if (can_send) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  REQUIRE_FALSE(can_send);
  auto call = std::async(std::launch::async, [&] {
    try {
      link.call(info_request(), 500);
    } catch (const std::exception& e) {
      return std::string(e.what());
    }
    return std::string("a reply");
  });
  // 500 ms asked for; 30 s is far beyond any scheduling delay: a call still running then hangs
  if (call.wait_for(std::chrono::seconds(30)) != std::future_status::ready) {
    std::fprintf(stderr, "ControlLink::call did not return within 30 s of a 500 ms deadline: it hangs\n");
    std::_Exit(1);  // the hung thread cannot be joined, nor its context closed
  }
  const std::string what = call.get();
  CHECK(what.find("no reply from a palpsim-server at " + server.address() + " within 500 ms") != std::string::npos);
  CHECK(what.find("--server-key") != std::string::npos);  // the hint for a client without keys
  // a request started without waiting is refused at once too (never queued, never waited for)
  CHECK_FALSE(link.start(info_request()));
  CHECK_FALSE(link.waiting());
}

TEST_CASE("a silent server: the call ends at its deadline, and a started request is given up for a fresh one",
          "[haptic][control]") {
  zmq::context_t ctx(1);
  zmq::socket_t server(ctx, zmq::socket_type::router);
  server.set(zmq::sockopt::linger, 0);
  server.bind("tcp://127.0.0.1:*");
  const std::string address = server.get(zmq::sockopt::last_endpoint);
  palpsim::haptic::ControlLink link(ctx, address, {}, false);
  CHECK_THROWS_WITH(link.call(info_request(), 200), Catch::Contains("within 200 ms"));
  // the REQ that lost its reply is replaced: the next request goes out and its reply is taken
  REQUIRE(link.start(info_request()));
  CHECK(link.waiting());
  zmq::pollitem_t items[] = {{server.handle(), 0, ZMQ_POLLIN, 0}};
  zmq::message_t id, empty, body;
  // the unanswered first request comes first, from the first socket; then the second
  for (int k = 0; k < 2; ++k) {
    REQUIRE(zmq::poll(items, 1, std::chrono::seconds(10)) == 1);
    (void)server.recv(id);
    (void)server.recv(empty);
    (void)server.recv(body);
  }
  v1::ControlReply answer;
  answer.set_schema_version(v1::VERSION_CURRENT);
  answer.mutable_info()->set_scene_name("silent no more");
  server.send(id, zmq::send_flags::sndmore);
  server.send(zmq::const_buffer(nullptr, 0), zmq::send_flags::sndmore);
  server.send(zmq::buffer(answer.SerializeAsString()), zmq::send_flags::none);
  v1::ControlReply got;
  bool parsed = false;
  for (int i = 0; i < 1000 && !link.take(got, &parsed); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  CHECK(parsed);
  CHECK(got.info().scene_name() == "silent no more");
  CHECK_FALSE(link.waiting());
}
