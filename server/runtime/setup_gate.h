// The hand-shake between a worker thread's first set-up and the start() that waits for
// it (the deformation worker and the render thread): start() returns when the thread has
// set itself up, and throws the set-up's error when it could not.
#pragma once

#include <condition_variable>
#include <mutex>
#include <string>

namespace palpsim::runtime {

/// Opened once by the worker thread when its first set-up is over, failed or not.
class SetupGate {
 public:
  /// (worker) the first set-up failed with `error`; ignored once the gate is open.
  void fail(const std::string& error) {
    std::lock_guard<std::mutex> lock(mu_);
    if (!open_) error_ = error;
  }
  /// (worker) the first set-up is over; later calls do nothing.
  void open() {
    std::lock_guard<std::mutex> lock(mu_);
    open_ = true;
    cv_.notify_all();
  }
  /// True once open() was called.
  bool is_open() const {
    std::lock_guard<std::mutex> lock(mu_);
    return open_;
  }
  /// The first set-up's error ("" when it succeeded or is not over).
  std::string error() const {
    std::lock_guard<std::mutex> lock(mu_);
    return error_;
  }
  /// (starter) waits until the gate is open; returns the set-up's error ("" on success).
  std::string wait() {
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait(lock, [this] { return open_; });
    return error_;
  }

 private:
  mutable std::mutex mu_;
  std::condition_variable cv_;
  bool open_ = false;
  std::string error_;
};

}  // namespace palpsim::runtime
