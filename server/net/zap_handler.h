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
#include <vector>
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

/// The least time between two log lines about refused handshakes (s).
constexpr double kRefusalLogPeriodS = 5;

/// Refused CURVE handshakes for the log, rate-limited: the first refusal after a quiet
/// period gets a line at once (the peer's address, the client's public key, why); those
/// after it are counted per address and key and told in one summary line once the
/// period since the last line has passed. A client that retries a thousand times a
/// second costs one line per period, and a summary names `max_peers` peers at most (the
/// others are counted), so no client can make the log grow faster than that.
class RefusalLog {
 public:
  /// `period_s`: the least time between two lines; `max_peers`: the peers a summary names.
  explicit RefusalLog(double period_s = kRefusalLogPeriodS, std::size_t max_peers = 8)
      : period_s_(period_s), max_peers_(max_peers) {}
  /// Records one refusal at `now_s` (seconds on any steady clock): the peer's address
  /// (ZAP's address frame), the client's z85 public key ("" when it sent none) and why.
  /// Returns the line to log now, or "" when the refusal is only counted.
  std::string refused(const std::string& address, const std::string& key, const std::string& why, double now_s);
  /// The summary of the refusals counted since the last line, once `period_s` has passed
  /// since that line (or at once with `force`); "" when there is nothing to tell yet.
  std::string flush(double now_s, bool force = false);

 private:
  struct Peer {
    std::string address, key, why;
    std::uint64_t count = 0;
  };
  double period_s_;
  std::size_t max_peers_;
  bool logged_ = false;     // a line was logged (last_line_s_ is its time)
  double last_line_s_ = 0;
  std::vector<Peer> peers_;  // counted since the last line, at most max_peers_
  std::uint64_t others_ = 0;  // refusals of peers beyond those
};

/// Makes `socket` a CURVE server with the z85 secret key `secret_z85` and the palpsim ZAP
/// domain; before bind. Every connection then needs a handler's approval.
void make_curve_server(zmq::socket_t& socket, const std::string& secret_z85);

/// Answers ZAP requests of one context on a thread of its own.
class ZapHandler {
 public:
  /// Binds inproc://zeromq.zap.01 in `ctx` (before any CURVE socket of `ctx` binds) and
  /// starts the thread. Each refused connection adds one to `refused`, each admitted one
  /// to `admitted`; both outlive the handler. Refusals are logged (warn) through a
  /// RefusalLog of `log_period_s`.
  ZapHandler(zmq::context_t& ctx, std::shared_ptr<const AllowList> allowed, std::atomic<std::uint64_t>& refused,
             std::atomic<std::uint64_t>& admitted, double log_period_s = kRefusalLogPeriodS);
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
  RefusalLog log_;  // (handler thread)
  std::thread thread_;

  void run();
};

}  // namespace palpsim::net
