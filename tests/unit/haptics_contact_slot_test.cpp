// The seqlock slot that hands the newest contact to the deformation path: a reader
// running beside a writer never sees a contact mixed from two writes.
#include <catch2/catch.hpp>

#include <atomic>
#include <thread>

#include "haptics/contact_slot.h"

using namespace palpsim;

namespace {
// every field derived from the sequence number, so a torn read shows as a mismatch
Contact contact_for(std::uint64_t n) {
  const double v = double(n);
  Contact c;
  c.tip_mm = {v, v + 1, v + 2};
  c.skin_point_mm = {v + 3, v + 4, v + 5};
  c.proxy_mm = {v + 6, v + 7, v + 8};
  c.depth_mm = v + 9;
  c.contact = (n % 2) == 1;
  c.seq = n;
  c.server_time_s = v + 10;
  return c;
}
}  // namespace

TEST_CASE("the contact slot never returns a torn contact", "[haptics]") {
  ContactSlot slot;
  Contact c;
  CHECK(slot.read(c) == 0);  // nothing written yet
  std::atomic<bool> done{false};
  std::uint64_t reads = 0, torn = 0, went_back = 0;
  std::thread reader([&] {
    std::uint64_t last_seq = 0;
    while (!done.load()) {
      Contact r;
      slot.read(r);
      ++reads;
      if (!(r.seq == 0 || (r.tip_mm == contact_for(r.seq).tip_mm && r.skin_point_mm == contact_for(r.seq).skin_point_mm &&
                           r.proxy_mm == contact_for(r.seq).proxy_mm && r.depth_mm == r.seq + 9.0 &&
                           r.contact == ((r.seq % 2) == 1) && r.server_time_s == r.seq + 10.0)))
        ++torn;
      if (r.seq < last_seq) ++went_back;
      last_seq = r.seq;
    }
  });
  for (std::uint64_t n = 1; n <= 2000000; ++n) slot.write(contact_for(n));
  done = true;
  reader.join();
  CHECK(torn == 0);
  CHECK(went_back == 0);
  CHECK(reads > 0);
  // the last write is what a reader sees afterwards, with its version
  CHECK(slot.read(c) == 2000000);
  CHECK(c.seq == 2000000);
}
