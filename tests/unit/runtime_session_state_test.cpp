// SessionStates (runtime/session_state.h) hands out one session's parts: the session
// table's slot, the stream's slot and the calling thread's own part, all of the slot that
// the id's low bits name; the stream's only once a scene has made the stream state.
#include <catch2/catch.hpp>

#include <cstdint>
#include <memory>
#include <vector>

#include "runtime/session_state.h"

using namespace palpsim;

TEST_CASE("a session's parts are the same slot of every array, the stream's once it is made", "[runtime]") {
  auto sh = std::make_unique<runtime::ServerShared>();
  std::vector<int> own(runtime::kMaxSlots);
  const runtime::SessionStates<int> states(*sh, own);
  // an id of slot 37, with high bits set, and the highest slot
  const std::uint64_t id = (std::uint64_t(0xabcdef) << runtime::kSlotBits) | 37;
  REQUIRE(runtime::slot_index(id) == 37);
  CHECK(runtime::slot_index(~std::uint64_t(0)) == runtime::kMaxSlots - 1);

  const runtime::SessionState<int> before = states.at(runtime::slot_index(id));
  CHECK(before.index == 37);
  CHECK(&before.table == &sh->slots[37]);
  CHECK(&before.own == &own[37]);
  CHECK(before.stream == nullptr);  // no scene has asked for frames or bricks

  // the deformation worker's kind: the stream state as ServerShared has it at each at()
  runtime::StreamState stream;
  sh->stream.store(&stream);
  const runtime::SessionState<int> after = states.at(runtime::slot_index(id));
  CHECK(after.stream == &stream.slots[37]);
  CHECK(after.stream == &stream.slot(id));

  // the render thread's and the publisher's kind: the stream state they were made with
  runtime::StreamState theirs;
  const runtime::SessionStates<int> fixed(*sh, theirs, own);
  CHECK(fixed.at(runtime::kMaxSlots - 1).stream == &theirs.slots[runtime::kMaxSlots - 1]);
  CHECK(&fixed.at(runtime::kMaxSlots - 1).own == &own.back());
}
