// The hand-over of local force model patches between the pose thread and the patch
// worker (net/patch_worker.h): one PatchChannel per session slot, newest-wins both ways,
// so that neither thread waits for the other.
#pragma once

#include <cstdint>
#include <string>

#include "core/latest.h"
#include "core/scene.h"
#include "core/vec3.h"

namespace palpsim::runtime {

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

}  // namespace palpsim::runtime
