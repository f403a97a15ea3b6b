// The newest-wins hand-over (core/latest.h) that carries J and frames between the
// server's threads: the reader gets the newest value, never a torn one, and nothing
// queues; a value overwritten before it was taken is reported as replaced.
#include <catch2/catch.hpp>

#include <array>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

#include "core/latest.h"

using palpsim::Latest;

TEST_CASE("Latest hands over the newest value and says when one was replaced", "[core]") {
  Latest<int> h;
  CHECK_FALSE(h.fresh());
  CHECK_FALSE(h.take());  // nothing published yet
  h.back() = 1;
  CHECK_FALSE(h.publish());  // the first value replaces nothing
  CHECK(h.fresh());
  CHECK(h.fresh());  // asking takes nothing
  h.back() = 2;
  CHECK(h.publish());  // 1 was never taken: replaced
  REQUIRE(h.take());
  CHECK_FALSE(h.fresh());
  CHECK(h.front() == 2);  // the newest, not the first
  CHECK_FALSE(h.take());  // taken already; front() stays
  CHECK(h.front() == 2);
  h.back() = 3;
  CHECK_FALSE(h.publish());  // 2 was taken
  REQUIRE(h.take());
  CHECK(h.front() == 3);
}

TEST_CASE("Latest between two threads: values only grow and are never torn", "[core]") {
  // a value of many words, all equal: a torn read would mix two of them
  struct Big {
    std::array<std::uint64_t, 64> w{};
  };
  Latest<Big> h;
  constexpr std::uint64_t kCount = 200000;
  std::atomic<bool> done{false};
  std::thread writer([&] {
    for (std::uint64_t v = 1; v <= kCount; ++v) {
      h.back().w.fill(v);
      h.publish();
    }
    done = true;
  });
  std::uint64_t last = 0, taken = 0, torn = 0, backwards = 0;
  for (;;) {
    // read `done` before taking: once the writer is done, one more take gets its last value
    const bool finished = done.load();
    if (h.take()) {
      const Big& b = h.front();
      for (std::uint64_t x : b.w) torn += x != b.w[0];
      backwards += b.w[0] < last;
      last = b.w[0];
      ++taken;
      continue;
    }
    if (finished) break;
  }
  writer.join();
  CHECK(torn == 0);
  CHECK(backwards == 0);
  CHECK(taken > 0);
  CHECK(last == kCount);  // the very last value published is the one the reader ends on
}
