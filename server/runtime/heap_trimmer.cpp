#include "runtime/heap_trimmer.h"

#include <spdlog/spdlog.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include "core/thread.h"

namespace palpsim::runtime {

void configure_heap() {
#if defined(__GLIBC__)
  mallopt(M_MMAP_THRESHOLD, int(kHeapMmapThresholdBytes));
#endif
}

HeapFigures heap_figures() {
  HeapFigures f;
#if defined(__GLIBC__) && (__GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 33))
  const struct mallinfo2 m = mallinfo2();
  f.in_use = m.uordblks;
  f.free = m.fordblks;
  f.mapped = m.hblkhd;
#endif
  return f;
}

std::size_t resident_bytes() {
  std::FILE* f = std::fopen("/proc/self/statm", "r");
  if (!f) return 0;
  unsigned long long size = 0, resident = 0;
  const int n = std::fscanf(f, "%llu %llu", &size, &resident);
  std::fclose(f);
  return n == 2 ? std::size_t(resident) * std::size_t(::sysconf(_SC_PAGESIZE)) : 0;
}

std::size_t trim_heap() {
#if defined(__GLIBC__)
  const std::size_t before = resident_bytes();
  malloc_trim(0);
  const std::size_t after = resident_bytes();
  return before > after ? before - after : 0;
#else
  return 0;
#endif
}

bool TrimPolicy::due(std::size_t resident_bytes, std::size_t free_bytes) {
  least_resident_ = std::min(least_resident_, resident_bytes);
  least_free_ = std::min(least_free_, free_bytes);
  const std::size_t step = std::max(min_step_, least_resident_ / 32);
  return free_bytes >= step && (free_bytes - least_free_ >= step || resident_bytes - least_resident_ >= step);
}

HeapTrimmer::HeapTrimmer(double period_s, std::size_t min_step_bytes, std::atomic<bool>* requested)
    : period_s_(period_s), policy_(min_step_bytes), requested_(requested) {
  thread_ = std::thread([this] {
    name_this_thread("palpsim-heap");
    run();
  });
}

HeapTrimmer::~HeapTrimmer() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stop_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void HeapTrimmer::run() {
  std::unique_lock<std::mutex> lock(mu_);
  while (!wake_.wait_for(lock, std::chrono::duration<double>(period_s_), [this] { return stop_; })) {
    // the policy looks every time (its baselines follow memory down); a request trims anyway
    const bool due = policy_.due(resident_bytes(), heap_figures().free);
    const bool asked = requested_ && requested_->exchange(false, std::memory_order_acq_rel);
    if (!due && !asked) continue;
    // the trim itself, without the stop lock (the destructor need not wait for it)
    lock.unlock();
    const auto t0 = std::chrono::steady_clock::now();
    const std::size_t dropped = trim_heap();
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    policy_.trimmed(resident_bytes(), heap_figures().free);
    spdlog::debug("heap: gave {:.1f} MB of freed memory back to the system in {:.1f} ms", double(dropped) / 1048576.0,
                  ms);
    lock.lock();
  }
}

}  // namespace palpsim::runtime
