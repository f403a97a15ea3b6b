// The pose path's allowance of error replies per connection: a token bucket per ROUTER
// routing id in a fixed table, so that a connection that sends garbage (or poses the
// server refuses) as fast as it can gets its first errors answered and then costs the
// pose thread a receive and a parse each, no error reply, no work for the I/O thread.
// Owned by the pose thread: no locks, no allocation after construction.
#pragma once

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>

namespace palpsim::net {

/// Error replies the pose path sends one connection: at most kRepliesPerS a second on
/// average, kBurst at once. A client that follows the protocol gets no error replies; one
/// whose session has gone (a restarted server, a timeout) still hears of it at once.
class BadInputBudget {
 public:
  static constexpr double kRepliesPerS = 100;
  static constexpr double kBurst = 100;
  /// Connections tracked at once; beyond that the least recently refused one's bucket is
  /// given to the newcomer (which then starts with a full burst).
  static constexpr int kEntries = 1024;
  /// Entries looked at for one connection (from its hash's place on).
  static constexpr int kProbe = 8;

  /// `seed` keys the hash of routing ids (from the OS's random source), so that which
  /// connections share a bucket differs from server to server.
  explicit BadInputBudget(std::uint64_t seed) : seed_(seed) {}

  /// True when an error reply to the connection with routing id `id` (`len` bytes) at
  /// `now_ns` (steady clock) is within its allowance, which it then uses; false when it
  /// is spent (the message goes unanswered).
  bool answer(const char* id, std::size_t len, std::int64_t now_ns) {
    const std::uint64_t key = hash(id, len);
    const std::size_t home = std::size_t(key % kEntries);
    Entry* found = nullptr;
    Entry* oldest = nullptr;
    for (int k = 0; k < kProbe && !found; ++k) {
      Entry& e = table_[(home + std::size_t(k)) % kEntries];
      if (e.key == key) found = &e;
      else if (!oldest || e.seen_ns < oldest->seen_ns) oldest = &e;
    }
    if (!found) {
      *oldest = Entry{key, now_ns, kBurst - 1};
      return true;
    }
    const double dt_s = double(now_ns - found->seen_ns) * 1e-9;
    found->seen_ns = now_ns;
    if (dt_s > 0) found->tokens = std::min(kBurst, found->tokens + dt_s * kRepliesPerS);
    if (found->tokens < 1) return false;
    found->tokens -= 1;
    return true;
  }

 private:
  struct Entry {
    std::uint64_t key = 0;     // the routing id's hash (0: free)
    std::int64_t seen_ns = 0;  // its last error
    double tokens = 0;         // replies it may still get now
  };
  std::array<Entry, kEntries> table_{};
  std::uint64_t seed_;

  // FNV-1a over the seed and the id's bytes, never 0
  std::uint64_t hash(const char* id, std::size_t len) const {
    std::uint64_t h = 1469598103934665603ull ^ seed_;
    for (std::size_t i = 0; i < len; ++i) {
      h ^= std::uint8_t(id[i]);
      h *= 1099511628211ull;
    }
    return h ? h : 1;
  }
};

}  // namespace palpsim::net
