// The heap trimmer (runtime/heap_trimmer.h): when its policy trims, and that a trim gives
// back memory freed in the middle of glibc's heap, which free() alone keeps resident.
#include <catch2/catch.hpp>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <thread>
#include <vector>

#include "runtime/heap_trimmer.h"

using namespace palpsim;

namespace {

constexpr std::size_t kMB = std::size_t(1) << 20;

// 96 MB in blocks of 96 KB (below any mmap threshold glibc uses by default: they come
// from the heap), every other one freed by free_half(): the blocks kept between them stop
// the freed ones from merging into the top of the heap, which free() itself gives back
struct Fragments {
  static constexpr std::size_t kBlock = 96 * 1024;
  std::vector<char*> blocks;
  Fragments() {
    for (int i = 0; i < 1024; ++i) {
      blocks.push_back(static_cast<char*>(std::malloc(kBlock)));
      std::memset(blocks.back(), (i & 0x7f) + 1, kBlock);  // resident
    }
  }
  // a sum over every page, so that none of the blocks is optimised away
  unsigned sum() const {
    unsigned s = 0;
    for (char* b : blocks)
      if (b)
        for (std::size_t k = 0; k < kBlock; k += 4096) s += static_cast<unsigned char>(b[k]);
    return s;
  }
  // frees the even blocks: 48 MB
  void free_half() {
    for (std::size_t i = 0; i < blocks.size(); i += 2) {
      std::free(blocks[i]);
      blocks[i] = nullptr;
    }
  }
  ~Fragments() {
    for (char* b : blocks) std::free(b);
  }
};

}  // namespace

TEST_CASE("the trim policy: a step freed since the last trim, or a step of regrowth", "[net][memory]") {
  runtime::TrimPolicy p(4 * kMB);
  // step: 1/32 of resident memory, at least 4 MB: 8 MB at 256 MB
  CHECK_FALSE(p.due(256 * kMB, 10 * kMB));
  CHECK_FALSE(p.due(256 * kMB, 17 * kMB));  // 7 MB more free: below the step
  CHECK(p.due(256 * kMB, 18 * kMB));        // 8 MB freed into the arenas since
  p.trimmed(230 * kMB, 18 * kMB);
  CHECK_FALSE(p.due(230 * kMB, 18 * kMB));
  // the free memory used again and freed again between two looks: resident memory grew
  CHECK(p.due(238 * kMB, 18 * kMB));
  // ... but not when the arenas hold less than a step: the growth is live memory
  CHECK_FALSE(p.due(238 * kMB, 7 * kMB));
  p.trimmed(238 * kMB, 7 * kMB);
  // big blocks went back by themselves: the baseline follows down, the step with it
  CHECK_FALSE(p.due(100 * kMB, 7 * kMB));
  CHECK(p.due(104 * kMB, 7 * kMB));  // 4 MB over 100 MB: the least step
}

TEST_CASE("a trim gives back memory freed in the middle of the heap; free() alone does not", "[net][memory]") {
  Fragments f;
  CHECK(f.sum() > 0);
  const std::size_t before = runtime::resident_bytes();
  REQUIRE(before > 0);
  f.free_half();
  // free() kept the 48 MB (at most a few blocks went back): the point of the trimmer
  const std::size_t after_free = runtime::resident_bytes();
  CHECK(after_free + 8 * kMB > before);
  // 48 MB freed, in whole pages but for the chunk headers: 40 MB leaves room for what
  // other threads of this test process allocate meanwhile
  const std::size_t dropped = runtime::trim_heap();
  INFO("resident " << before / kMB << " MB, after free " << after_free / kMB << " MB, trim gave back "
                   << dropped / kMB << " MB");
  CHECK(dropped >= 40 * kMB);
}

TEST_CASE("the trimmer's thread trims by itself once memory is freed", "[net][memory]") {
  Fragments f;
  CHECK(f.sum() > 0);
  // a look every 20 ms; the first look sets the baselines
  runtime::HeapTrimmer trimmer(0.02, 4 * kMB);
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const std::size_t before = runtime::resident_bytes();
  f.free_half();
  // the next looks see 48 MB more free in the arenas and trim; 10 s covers a loaded machine
  std::size_t now = before;
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (now + 40 * kMB > before && std::chrono::steady_clock::now() < end) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    now = runtime::resident_bytes();
  }
  INFO("resident " << before / kMB << " MB before the free, " << now / kMB << " MB after");
  CHECK(now + 40 * kMB <= before);
}

TEST_CASE("a request trims where the policy would not, and is cleared", "[net][memory]") {
  Fragments f;
  CHECK(f.sum() > 0);
  // a step of 1 TB: the policy never trims; only the request can
  std::atomic<bool> requested{false};
  runtime::HeapTrimmer trimmer(0.02, std::size_t(1) << 40, &requested);
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const std::size_t before = runtime::resident_bytes();
  f.free_half();
  // unasked, the 48 MB freed stay resident over many looks (40 MB: what other threads
  // allocate meanwhile leaves room, as above)
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  CHECK(runtime::resident_bytes() + 40 * kMB > before);
  // asked, the next look trims and clears the request; 10 s covers a loaded machine
  requested.store(true);
  std::size_t now = before;
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while ((requested.load() || now + 40 * kMB > before) && std::chrono::steady_clock::now() < end) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    now = runtime::resident_bytes();
  }
  INFO("resident " << before / kMB << " MB before the free, " << now / kMB << " MB after the request");
  CHECK_FALSE(requested.load());
  CHECK(now + 40 * kMB <= before);
}
