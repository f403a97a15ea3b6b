// One session's state: what its parts are, where each lives and which thread owns it.
//
// A session lives in the slot that the low kSlotBits bits of its id name (slot_index(),
// session_table.h). Its state is split by thread, one array of kMaxSlots parts per owner,
// all indexed by that slot, so that no thread waits on another (the pose thread never does):
//
// - SessionSlot (session_table.h), in ServerShared::slots: what every thread may read,
//   through atomics and newest-wins hand-overs, never a lock. The control thread writes
//   the session's id, haptics parameters and owner; the pose thread its proxy, newest
//   contact and counters; the deformation worker its elastic model; the patch worker its
//   patch channel.
// - StreamSlot (stream_state.h), in StreamState::slots, made once a scene asks for frames
//   or bricks; the pose thread never touches it. The publisher writes who is watched, the
//   deformation worker J, the render thread frames; the control thread the watch settings
//   and the publisher and render thread the stream's report, under StreamSlot::mu.
// - DeformWorker::Session (deform_worker_state.h), in DeformWorker::sessions_ while the
//   scene deforms: the deformation worker's alone (its engine, the contacts taken, pacing,
//   what it exported); stats read a copy of its report (DeformWorker::reports_, under
//   DeformWorker::report_mu_).
// - RenderWorker::View (render_worker.cpp), in RenderWorker::views_: the render thread's
//   alone (its overlay and framebuffer, view and frame cadence).
//
// Beside them the publisher keeps its PubSlot per slot (net/stream_publisher.cpp), and the
// control thread each slot's last id and opening order (net/control.h).
//
// SessionStates joins a thread's own array with the two shared ones by slot index: the
// workers and the publisher reach a session's parts through it instead of indexing the
// arrays by hand. It hands out references and takes no lock: each part keeps its owner and
// the rules above.
#pragma once

#include <atomic>
#include <cstddef>
#include <vector>

#include "runtime/session_table.h"
#include "runtime/stream_state.h"

namespace palpsim::runtime {

/// One session slot's parts as one thread reaches them: the two that threads share, and the
/// calling thread's own part `Own` (DeformWorker::Session, RenderWorker::View, the
/// publisher's PubSlot). Made per use on the stack; it copies nothing and takes no lock.
template <class Own>
struct SessionState {
  int index;           // the slot index
  SessionSlot& table;  // ServerShared::slots[index]
  StreamSlot* stream;  // StreamState::slots[index]; nullptr while no scene has asked for frames or bricks
  Own& own;            // the calling thread's part of the slot
};

/// Every session slot as one thread reaches it: the session table, the stream state and the
/// thread's own array of parts, joined by slot index, so that a thread names a session's
/// parts in one place rather than indexing three arrays by hand.
template <class Own>
class SessionStates {
 public:
  /// For a thread that may outlive the making of the stream state (the deformation worker):
  /// each at() reads ServerShared::stream as it is then. `own` holds kMaxSlots parts
  /// whenever at() is called.
  SessionStates(ServerShared& shared, std::vector<Own>& own) : sh_(shared), own_(own) {}
  /// For a thread made with the stream state, which outlives it (the render thread, the
  /// publisher): every at() hands out `stream`'s slot.
  SessionStates(ServerShared& shared, StreamState& stream, std::vector<Own>& own)
      : sh_(shared), fixed_stream_(&stream), own_(own) {}

  /// The parts of slot `index` (0 <= index < kMaxSlots).
  SessionState<Own> at(int index) const {
    StreamState* st = fixed_stream_ ? fixed_stream_ : sh_.stream.load(std::memory_order_acquire);
    const std::size_t i = std::size_t(index);
    return {index, sh_.slots[i], st ? &st->slots[i] : nullptr, own_[i]};
  }

 private:
  ServerShared& sh_;
  StreamState* fixed_stream_ = nullptr;
  std::vector<Own>& own_;
};

}  // namespace palpsim::runtime
