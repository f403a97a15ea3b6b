// The pose path's allowance of error replies per connection (server/net/input_budget.h),
// with the clock given explicitly: a burst, then the refill rate, connections apart, and
// a table full of connections.
#include <catch2/catch.hpp>

#include <cstdint>
#include <string>

#include "net/input_budget.h"

using palpsim::net::BadInputBudget;

namespace {

// answers given to connection `id` for `n` bad messages all at `now_ns`
int answered(BadInputBudget& b, const std::string& id, int n, std::int64_t now_ns) {
  int k = 0;
  for (int i = 0; i < n; ++i) k += b.answer(id.data(), id.size(), now_ns);
  return k;
}

}  // namespace

TEST_CASE("a connection's errors are answered up to the burst, then at the refill rate", "[net][budget]") {
  BadInputBudget b(12345);
  const std::int64_t t0 = 1'000'000'000;
  CHECK(answered(b, "flood", 1000, t0) == int(BadInputBudget::kBurst));
  // 10 ms later one more (100 a second), 1 s later a whole burst again, never more
  CHECK(answered(b, "flood", 10, t0 + 10'000'000) == 1);
  CHECK(answered(b, "flood", 1000, t0 + 2'000'000'000) == int(BadInputBudget::kBurst));
}

TEST_CASE("another connection keeps its own allowance", "[net][budget]") {
  BadInputBudget b(7);
  CHECK(answered(b, "flood", 1000, 0) == int(BadInputBudget::kBurst));
  CHECK(answered(b, "honest", 1, 1) == 1);
  CHECK(answered(b, "flood", 1, 2) == 0);
}

TEST_CASE("with more connections than the table holds, the least recently refused makes room", "[net][budget]") {
  BadInputBudget b(99);
  // every entry taken and spent (ids of 4 bytes, as a ROUTER's own routing ids are 5)
  for (int i = 0; i < 4 * BadInputBudget::kEntries; ++i) {
    const std::string id(reinterpret_cast<const char*>(&i), sizeof i);
    answered(b, id, int(BadInputBudget::kBurst), i);
  }
  // a newcomer is answered (it takes a spent entry's place) and then has its own burst
  CHECK(answered(b, "newcomer", 1000, 1'000'000) == int(BadInputBudget::kBurst));
}
