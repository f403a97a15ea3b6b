// The ZAP handler (ZeroMQ RFC 27) of a CURVE server: admits a connection only when the
// client's public key is on the operator's allow-list, and names the connection by that
// key (the "User-Id" property of every message it sends, which the server reads to know
// who sent what). ZAP requests go to inproc://zeromq.zap.01 of the socket's own context,
// so a context with CURVE sockets needs one handler.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>
#include <unordered_set>
#include <zmq.hpp>

namespace palpsim::net {

/// The ZAP domain the server's sockets name.
constexpr const char* kZapDomain = "palpsim";

/// The client public keys a server admits (z85), shared by its handlers.
using AllowList = std::unordered_set<std::string>;

/// A server's CURVE settings, shared by its sockets: off while `secret_key` is "".
struct CurveServer {
  std::string secret_key;                    // z85
  std::shared_ptr<const AllowList> allowed;  // the client public keys admitted
};

/// Makes `socket` a CURVE server with the z85 secret key `secret_z85` and the palpsim ZAP
/// domain; before bind. Every connection then needs a handler's approval.
void make_curve_server(zmq::socket_t& socket, const std::string& secret_z85);

/// Answers ZAP requests of one context on a thread of its own.
class ZapHandler {
 public:
  /// Binds inproc://zeromq.zap.01 in `ctx` (before any CURVE socket of `ctx` binds) and
  /// starts the thread. Each refused connection adds one to `refused`, each admitted one
  /// to `admitted`; both outlive the handler.
  ZapHandler(zmq::context_t& ctx, std::shared_ptr<const AllowList> allowed, std::atomic<std::uint64_t>& refused,
             std::atomic<std::uint64_t>& admitted);
  /// Stops the thread and closes the socket.
  ~ZapHandler();
  ZapHandler(const ZapHandler&) = delete;
  ZapHandler& operator=(const ZapHandler&) = delete;

 private:
  zmq::socket_t socket_;
  std::shared_ptr<const AllowList> allowed_;
  std::atomic<std::uint64_t>& refused_;
  std::atomic<std::uint64_t>& admitted_;
  std::atomic<bool> stop_{false};
  std::thread thread_;

  void run();
};

}  // namespace palpsim::net
