// The hand-over from the haptic path to the deformation path: one slot per session
// holding the newest contact (tip x, skin point X, proxy). The haptic thread writes
// it once per pose without waiting; a deformation worker reads the newest value
// whenever it is ready and never sees a torn one (a seqlock, Boehm's formulation).
#pragma once

#include <atomic>
#include <cstdint>

#include "core/vec3.h"

namespace palpsim {

/// One contact as the deformation path needs it (the paper's X and x).
struct Contact {
  Vec3 tip_mm{0, 0, 0};         // x: the deformed position of the first moved element
  Vec3 skin_point_mm{0, 0, 0};  // X: its undeformed position on the skin
  Vec3 proxy_mm{0, 0, 0};       // p
  double depth_mm = 0;          // depth of x under the skin
  bool contact = false;         // x inside the body
  std::uint64_t seq = 0;        // the pose's sequence number
  std::uint64_t session_id = 0; // the session the pose belongs to (0: cleared), so a reader can
                                // tell a new session's contacts from an old one's in a reused slot
  double server_time_s = 0;     // when the pose was answered
};

/// A single-writer, many-reader slot holding the newest Contact. write() never
/// waits or allocates; read() retries only while a write is in flight (tens of ns).
class ContactSlot {
 public:
  /// Publishes `c` (haptic thread only: one writer).
  void write(const Contact& c) {
    const std::uint64_t v = version_.load(std::memory_order_relaxed);
    version_.store(v + 1, std::memory_order_relaxed);  // odd: write in flight
    std::atomic_thread_fence(std::memory_order_release);
    store(c);
    version_.store(v + 2, std::memory_order_release);
  }

  /// Copies the newest contact into `out`; returns its version (0: nothing written yet).
  /// A reader compares versions to skip contacts it has already processed.
  std::uint64_t read(Contact& out) const {
    for (;;) {
      const std::uint64_t v1 = version_.load(std::memory_order_acquire);
      if (v1 & 1) continue;  // a write is in flight
      load(out);
      std::atomic_thread_fence(std::memory_order_acquire);
      if (version_.load(std::memory_order_relaxed) == v1) return v1 / 2;
    }
  }

  /// Clears the slot (a new session in a reused slot); the writer's thread only.
  void clear() { write(Contact{}); }

 private:
  // fields are relaxed atomics so that a concurrent read is not a data race
  std::atomic<double> v_[10] = {};
  std::atomic<std::uint64_t> seq_{0};
  std::atomic<std::uint64_t> session_id_{0};
  std::atomic<bool> contact_{false};
  std::atomic<std::uint64_t> version_{0};

  void store(const Contact& c) {
    const double v[10] = {c.tip_mm.x,       c.tip_mm.y,       c.tip_mm.z,     c.skin_point_mm.x, c.skin_point_mm.y,
                          c.skin_point_mm.z, c.proxy_mm.x, c.proxy_mm.y, c.proxy_mm.z, c.depth_mm};
    for (int i = 0; i < 10; ++i) v_[i].store(v[i], std::memory_order_relaxed);
    seq_.store(c.seq, std::memory_order_relaxed);
    session_id_.store(c.session_id, std::memory_order_relaxed);
    contact_.store(c.contact, std::memory_order_relaxed);
    server_time_s_.store(c.server_time_s, std::memory_order_relaxed);
  }
  void load(Contact& c) const {
    double v[10];
    for (int i = 0; i < 10; ++i) v[i] = v_[i].load(std::memory_order_relaxed);
    c.tip_mm = {v[0], v[1], v[2]};
    c.skin_point_mm = {v[3], v[4], v[5]};
    c.proxy_mm = {v[6], v[7], v[8]};
    c.depth_mm = v[9];
    c.seq = seq_.load(std::memory_order_relaxed);
    c.session_id = session_id_.load(std::memory_order_relaxed);
    c.contact = contact_.load(std::memory_order_relaxed);
    c.server_time_s = server_time_s_.load(std::memory_order_relaxed);
  }
  std::atomic<double> server_time_s_{0};
};

}  // namespace palpsim
