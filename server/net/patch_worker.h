// The patch worker: cuts local force model patches (PROTOCOL.md, "Local force model") off
// the pose thread. The pose thread decides that a session's patch is due and hands the
// worker a request (the tip, the box size, the parameters) through the session's
// PatchChannel, newest-wins; the worker copies C, F and grad F into a serialized
// LocalForceModel and hands it back the same way; the pose thread appends those bytes to
// the session's next reply. Neither waits for the other. A channel is made by the worker
// the first time a session's poses ask for patches, so sessions that never ask cost nothing.
#pragma once

#include <cstdint>
#include <string>

#include "core/latest.h"
#include "core/scene.h"
#include "core/vec3.h"

namespace palpsim::net {

struct ServerShared;

/// What the pose thread asks of the worker: one patch around a tip.
struct PatchRequest {
  std::uint64_t session_id = 0;   // the session it is for
  std::uint64_t generation = 0;   // the world (scene generation) whose patient to cut
  std::uint64_t version = 0;      // LocalForceModel.version
  Vec3 tip_mm{0, 0, 0};           // the box's centre
  int edge = 0;                   // voxels per axis
  HapticsSettings params;         // the session's parameters now
  double server_time_s = 0;       // when the pose thread asked
};

/// A serialized LocalForceModel and whom it is for.
struct PatchBytes {
  std::string bytes;              // LocalForceModel, serialized (without the PoseReply field's tag)
  std::uint64_t session_id = 0;
  std::uint64_t generation = 0;
};

/// One session slot's pair of hand-overs: requests to the worker, patches back.
struct PatchChannel {
  Latest<PatchRequest> request;   // pose thread writes, worker reads
  Latest<PatchBytes> patch;       // worker writes, pose thread reads
};

/// Runs the worker until shared.stop is set: every millisecond while some session asks for
/// patches (every 20 ms while none ever did), makes the channels asked for and answers
/// every fresh request.
void run_patch_worker(ServerShared& shared);

}  // namespace palpsim::net
