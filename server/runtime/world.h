// The world a server serves: a scene, its prepared patient and the bounds the pose and
// render paths use, published whole to the other threads and never changed after.
#pragma once

#include <cstdint>
#include <memory>

#include "core/patient.h"
#include "core/scene.h"
#include "core/vec3.h"

namespace palpsim::runtime {

/// A scene with its prepared patient and its place in the load history. Immutable once
/// published; the pose thread reads it through a raw pointer that the control thread
/// keeps alive until the pose thread has moved on (ServerShared::seen_generation).
struct World {
  Scene scene;
  PatientPtr patient;
  std::uint64_t generation = 0;  // 1 for the scene loaded at start, +1 per successful load
  Vec3 bounds_min_mm{0, 0, 0};   // physical bounding box of the patient grid
  Vec3 bounds_max_mm{0, 0, 0};
  Vec3 body_min_mm{0, 0, 0};     // bounding box of the body mask's voxel centres
  Vec3 body_max_mm{0, 0, 0};
  Vec3 body_center_mm{0, 0, 0};  // the body's centre as frames take it (render/camera.h's body_center)
};

/// Builds a World (bounds included) from a scene and its patient.
std::unique_ptr<World> make_world(const Scene& scene, PatientPtr patient, std::uint64_t generation);

}  // namespace palpsim::runtime
