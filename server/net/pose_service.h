// The haptic thread: owns the pose socket and answers every PoseRequest at once from
// the immutable patient and its session's proxy state. Talks to the control thread
// only through ServerShared's atomics; no locks, no logging, no allocation per pose
// (protobuf messages and buffers are reused; ZeroMQ copies the reply into its own frame).
#pragma once

#include <chrono>
#include <cstdint>
#include <zmq.hpp>

#include "runtime/session_table.h"

namespace palpsim::net {

/// Nanoseconds of the steady clock since `start`.
inline std::int64_t ns_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - start).count();
}

/// Serves the pose socket (a bound ROUTER) until shared.stop is set; wakes at least
/// every `idle_poll_ms` to pick up a new world and to see the stop flag.
void run_pose_service(zmq::socket_t& socket, runtime::ServerShared& shared, std::chrono::steady_clock::time_point start,
                      int idle_poll_ms = 50);

}  // namespace palpsim::net
