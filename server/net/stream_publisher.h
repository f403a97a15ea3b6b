// The stream's publisher thread (server/render/README.md, proto/PROTOCOL.md "Frames and
// bricks"): owns the XPUB socket in a ZeroMQ context of its own (its I/O thread never
// sits in front of pose replies), learns from subscriptions who watches which session,
// and sends each watched session's newest frame and brick, the whole-volume key when a
// brick subscriber arrives, and notices when a session closes or a topic names none.
#pragma once

#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <thread>

#include "runtime/session_table.h"
#include "runtime/stream_state.h"
#include "net/zap_handler.h"

namespace palpsim::net {

/// Publishes frames and bricks on one XPUB endpoint.
class StreamPublisher {
 public:
  /// Binds the XPUB socket at `bind` (throws palpsim::Error naming the address when it
  /// cannot); `start` is the server clock's zero. With a CURVE key in `curve` the socket
  /// is a CURVE server with a ZAP handler of its own (its context is its own) and admits
  /// a subscription to a session's topics only from the key that opened the session.
  StreamPublisher(runtime::ServerShared& shared, runtime::StreamState& stream, const std::string& bind,
                  std::chrono::steady_clock::time_point start, const CurveServer& curve = {});
  ~StreamPublisher();
  StreamPublisher(const StreamPublisher&) = delete;
  StreamPublisher& operator=(const StreamPublisher&) = delete;

  /// The bound address (with the real port when bound to "*").
  const std::string& endpoint() const { return endpoint_; }
  /// Starts the thread.
  void start();
  /// Stops it, closes the socket and marks every session unwatched (idempotent).
  void stop();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  std::string endpoint_;
  std::thread thread_;
};

}  // namespace palpsim::net
