// The deformation worker's own state of a session slot and of a deformed_volume()
// request, shared by its units: deform_worker.cpp (the loop and the steps) and
// deform_worker_reports.cpp (what it hands out). Private to server/runtime.
#pragma once

#include <cstdint>
#include <memory>

#include "deform/engine.h"
#include "runtime/deform_worker.h"

namespace palpsim::runtime {

// the worker's own state of one session slot (one of a session's parts: session_state.h)
struct DeformWorker::Session {
  std::uint64_t id = 0;                 // 0: no session
  std::unique_ptr<DeformEngine> engine; // made at the first contact
  std::uint64_t last_version = 0;       // contact slot version last taken (0: none yet)
  std::uint32_t resets_seen = 0;        // SessionSlot::reset_requests applied
  std::uint32_t pose_resets_seen = 0;   // SessionSlot::pose_resets applied
  DeformSessionReport report;
  double last_contact_time_s = 0;       // server time of the pose the latest step ran on
  double last_step_begun_s = -1e9;      // server time the latest step began (pacing of watched sessions)
  Vec3 last_tip_mm{0, 0, 0};            // and its tip, skin point and proxy
  Vec3 last_skin_mm{0, 0, 0};
  Vec3 last_proxy_mm{0, 0, 0};
  Vec3 last_device_tip_mm{0, 0, 0};     // the device tip of the newest pose J stands for (the step's, or a
                                        // later one pressing on past the elastic hold to the same J)
  double last_prime_s = -1e9;           // server time of the latest prime (pacing) ...
  double last_prime_cost_s = 0;         // ... and the worker's time it took (s)
  // the stream's hand-overs (stream_state.h): the state's version, and what was exported
  std::uint64_t state_version = 1;      // grows with every step, reset and failure, and when J comes to
                                        // stand for a pose at another device tip (the snapshot says which)
  std::uint64_t render_exported = 0;    // state_version last handed to the render thread
  std::uint64_t bricks_exported = 0;    // ... and to the publisher
  bool render_watched = false;          // frames were wanted at the last pass
  bool bricks_watched = false;          // bricks were wanted at the last pass
};

// one deformed_volume() request
struct DeformWorker::Request {
  std::uint64_t session_id = 0;
  Volume<float>* out = nullptr;
  bool done = false;
  bool found = false;
};

/// Adds one engine's memory to a sum: its own stages, and the patient copy and solver
/// scratch that every engine of a world shares, counted once.
void add_memory(DeformMemory& a, const DeformMemory& b);

}  // namespace palpsim::runtime
