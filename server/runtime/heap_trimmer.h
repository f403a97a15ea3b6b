// Gives memory the server has freed back to the operating system. glibc's malloc keeps
// what is freed in its arenas (one per thread that allocates: control, deformation,
// render, stream, ZeroMQ's I/O threads, llvmpipe's and ITK's workers) and gives back on
// its own only blocks it mapped for themselves and the top of each heap. Its mmap
// threshold rises to the size of every such block freed (up to 32 MB), so after the
// first reload the volumes of a small patient, 4K readback and JPEG buffers, brick
// payloads and the queues of subscribers that left all come from the arenas, and once
// freed stay resident: RSS grows with reloads and viewers until the arenas hold the
// largest mix of sizes seen (scripts/memory_bench.py prints it). configure_heap() fixes
// the threshold at 4 MB for palpsim-server; a HeapTrimmer thread calls malloc_trim(0),
// which returns every free page of every arena, when enough was freed since its last call.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <mutex>
#include <thread>

namespace palpsim::runtime {

/// Blocks of at least this many bytes get pages of their own, given back when freed.
constexpr std::size_t kHeapMmapThresholdBytes = std::size_t(4) << 20;

/// Sets the process's allocator policy for a long-running server (glibc; nothing
/// elsewhere): blocks of kHeapMmapThresholdBytes and more are mapped for themselves
/// whatever was freed before, instead of glibc's threshold that rises with every such
/// block freed up to 32 MB. Volumes, 4K readback and JPEG buffers, render targets and
/// whole-volume key parts then go back to the system the moment they are freed, and do
/// not scatter through the arenas where a trim can return only whole free pages; the
/// smaller blocks that change hands at frame and brick rates stay in the arenas. Call it
/// first thing in main(), before any thread starts.
void configure_heap();

/// The allocator's own figures (bytes); zeros where the C library is not glibc.
struct HeapFigures {
  std::size_t in_use = 0;  // allocated from the arenas (mallinfo2 uordblks)
  std::size_t free = 0;    // freed into the arenas and kept there, resident or already trimmed (fordblks)
  std::size_t mapped = 0;  // allocated as blocks mapped for themselves (hblkhd), given back when freed
};

/// The allocator's figures now (mallinfo2: takes each arena's lock briefly).
HeapFigures heap_figures();

/// The process's resident memory now (bytes, /proc/self/statm); 0 where unknown.
std::size_t resident_bytes();

/// Gives every free page of every arena back to the system (glibc's malloc_trim(0));
/// returns the drop of resident memory (bytes, 0 when none or unknown).
std::size_t trim_heap();

/// When to trim: once, since the last trim, the arenas' free bytes have grown by a step
/// over the least they held (memory freed after the trim, kept by the arenas), or
/// resident memory has grown by a step over the least it was (memory freed and used
/// again between two looks leaves the free bytes where they were while its pages are
/// back in memory), and the arenas hold at least a step free. The step is 1/32 of
/// resident memory, at least `min_step_bytes`: what is kept beyond use stays within about
/// 3 % of the process. A trim that finds only live memory costs a few milliseconds and
/// moves both baselines up.
class TrimPolicy {
 public:
  /// `min_step_bytes`: the least growth (and free memory) worth a trim.
  explicit TrimPolicy(std::size_t min_step_bytes) : min_step_(min_step_bytes) {}
  /// True when a trim is due, given resident memory and the arenas' free bytes now.
  bool due(std::size_t resident_bytes, std::size_t free_bytes);
  /// Records resident memory and the arenas' free bytes right after a trim: the new baselines.
  void trimmed(std::size_t resident_bytes, std::size_t free_bytes) {
    least_resident_ = resident_bytes;
    least_free_ = free_bytes;
  }

 private:
  std::size_t min_step_;
  std::size_t least_resident_ = ~std::size_t(0);  // since the last trim
  std::size_t least_free_ = ~std::size_t(0);
};

/// A thread that looks at resident memory and the allocator every `period_s` and trims
/// when its TrimPolicy says so. It runs at normal priority: malloc_trim holds each arena's lock while it
/// works (milliseconds), and a thread preempted there would make the control, render and
/// deformation threads wait for it on a busy machine (the pose thread never allocates).
class HeapTrimmer {
 public:
  /// Starts the thread. Why once a second and steps of 4 MB or 1/32: a reload of the
  /// 1 mm phantom frees about 600 MB and a 4K viewer's leaving about 100 MB, while a trim
  /// takes 1-7 ms on the 2-core VM (10-240 MB given back) and a look (/proc/self/statm,
  /// mallinfo2) microseconds.
  /// `requested`, when given: a flag the server sets where it knows that much was just
  /// freed (an old scene's world, its patient and engines, after a LoadScene); the next
  /// look trims whatever the policy says, and clears it. The policy alone missed such a
  /// release: a trim in the middle of a reload records resident memory with both patients
  /// alive as its baseline, and the next reloads' frees, each under a step, added up to
  /// 20 MB of free pages kept resident (8 % of the memory test's server, the 2 mm phantom).
  explicit HeapTrimmer(double period_s = 1.0, std::size_t min_step_bytes = std::size_t(4) << 20,
                       std::atomic<bool>* requested = nullptr);
  /// Stops and joins it.
  ~HeapTrimmer();
  HeapTrimmer(const HeapTrimmer&) = delete;
  HeapTrimmer& operator=(const HeapTrimmer&) = delete;

 private:
  void run();

  double period_s_;
  TrimPolicy policy_;
  std::atomic<bool>* requested_;  // may be null
  std::mutex mu_;
  std::condition_variable wake_;
  bool stop_ = false;  // guarded by mu_
  std::thread thread_;
};

}  // namespace palpsim::runtime
