// A newest-wins hand-over between two threads (a triple buffer): one writer fills its
// own buffer and publishes it; one reader takes the newest published buffer whenever it
// is ready. Neither ever waits for the other and nothing queues: a value published
// before the reader took the previous one replaces it. Buffers are reused, so values
// holding vectors stop allocating once they have grown to their working size.
#pragma once

#include <atomic>
#include <cstdint>

namespace palpsim {

/// Single-writer, single-reader newest-wins hand-over of T values.
template <typename T>
class Latest {
 public:
  /// The writer's buffer: fill it, then publish(). Holds whatever was there before
  /// (an older value), so the writer overwrites every field it means to send.
  T& back() { return buf_[back_]; }

  /// Makes back() the newest value (writer only). Returns true when it replaced a value
  /// the reader had not taken yet (one value lost: newest wins).
  bool publish() {
    const std::uint8_t old = middle_.exchange(std::uint8_t(back_ | kFresh), std::memory_order_acq_rel);
    back_ = old & kIndex;
    return (old & kFresh) != 0;
  }

  /// Takes the newest published value into front() (reader only); false, leaving
  /// front() as it was, when nothing was published since the last take.
  bool take() {
    if ((middle_.load(std::memory_order_acquire) & kFresh) == 0) return false;
    front_ = middle_.exchange(front_, std::memory_order_acq_rel) & kIndex;
    return true;
  }

  /// True when a value was published since the last take() (reader only): a newer
  /// value waits, to be taken when the reader needs it.
  bool fresh() const { return (middle_.load(std::memory_order_acquire) & kFresh) != 0; }

  /// The reader's buffer: the value of the last successful take().
  T& front() { return buf_[front_]; }
  const T& front() const { return buf_[front_]; }

  /// Each of the three buffers, for accounting of what they hold (any thread, only
  /// while neither side writes, or for an estimate).
  const T& buffer(int i) const { return buf_[i]; }

 private:
  static constexpr std::uint8_t kIndex = 3, kFresh = 4;
  T buf_[3]{};
  std::atomic<std::uint8_t> middle_{1};  // the middle buffer's index, kFresh when unread
  std::uint8_t back_ = 0;                // (writer) its buffer
  std::uint8_t front_ = 2;               // (reader) its buffer
};

}  // namespace palpsim
