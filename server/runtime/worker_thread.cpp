// The worker thread's start, stop and world following (worker_thread.h).
#include "runtime/worker_thread.h"

#include "core/error.h"
#include "core/thread.h"

namespace palpsim::runtime {

void WorkerThread::start(const char* name, int nice, bool idle, std::function<void()> body) {
  if (thread_.joinable()) return;
  // the world being served now may not be freed before the worker has copied what it needs
  const World* w = world_.load(std::memory_order_acquire);
  seen_.store(w ? w->generation : 0, std::memory_order_release);
  thread_ = std::thread([name, nice, idle, body = std::move(body)] {
    name_this_thread(name);
    // below the threads that serve poses (core/thread.h says why SCHED_IDLE); llvmpipe's
    // rasteriser threads, started from the render thread, inherit it
    lower_this_thread(nice, idle);
    body();
  });
  const std::string error = setup_.wait();
  if (!error.empty()) {
    stop();
    throw Error(error);
  }
}

void WorkerThread::stop() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
  seen_.store(~std::uint64_t(0), std::memory_order_release);
}

bool WorkerThread::follow_world(std::uint64_t generation, const std::function<void()>& set_up) {
  const World* w = world_.load(std::memory_order_acquire);
  if (!w || w->generation == generation) return true;
  set_up();
  if (!first_) return true;
  first_ = false;
  setup_.open();
  return setup_.error().empty();
}

}  // namespace palpsim::runtime
