// The thread of a worker that reads the world (the deformation worker, the render
// thread) and the world-pinning rule both keep: the world served when the thread starts
// stays alive until the thread has copied what it needs, each world it picks up is
// marked seen, and a stopped thread pins none (ServerShared's *_seen_generation).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>
#include <thread>

#include "runtime/setup_gate.h"
#include "runtime/world.h"

namespace palpsim::runtime {

/// One worker thread that follows the world being served, so that each worker keeps the
/// pinning rule, its start-up hand-shake and its stop in one place.
class WorkerThread {
 public:
  /// `world`: the world being served (ServerShared::world); `seen_generation`: where this
  /// thread says which world generation it has picked up (max: no thread).
  WorkerThread(const std::atomic<const World*>& world, std::atomic<std::uint64_t>& seen_generation)
      : world_(world), seen_(seen_generation) {}
  ~WorkerThread() { stop(); }
  WorkerThread(const WorkerThread&) = delete;
  WorkerThread& operator=(const WorkerThread&) = delete;

  /// Pins the world served now, starts `body` on a thread named `name` with nice value
  /// `nice` (and SCHED_IDLE when `idle`; core/thread.h says why), and waits until the body
  /// opens the set-up gate; throws palpsim::Error with the set-up's error after stopping
  /// the thread when it failed. Does nothing while the thread runs.
  void start(const char* name, int nice, bool idle, std::function<void()> body);
  /// Asks the thread to stop, joins it and pins no world any more (idempotent).
  void stop();

  /// (worker) true once stop() was asked.
  bool stopping() const { return stop_.load(std::memory_order_relaxed); }
  /// (worker) the world generation it works with: the world it pinned may go once older.
  void picked_up(std::uint64_t generation) { seen_.store(generation, std::memory_order_release); }
  /// (worker) calls `set_up` when the world being served is not `generation` (the one the
  /// thread works with); after the first set-up opens the gate. False when that first
  /// set-up failed and the thread must end.
  bool follow_world(std::uint64_t generation, const std::function<void()>& set_up);
  /// (worker) the hand-shake with start(): fail() with the first set-up's error, open() when over.
  SetupGate& setup() { return setup_; }

 private:
  const std::atomic<const World*>& world_;
  std::atomic<std::uint64_t>& seen_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  bool first_ = true;  // (worker) the first set-up is still to come
  SetupGate setup_;
};

}  // namespace palpsim::runtime
