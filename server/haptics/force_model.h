// The force model of the paper's section 2.1: a proxy from the force image F and
// its gradient (eq. 2), friction, a spring to the device tip, clamps, and the skin
// point X. Reads only the immutable Patient; each session owns a small ProxyState.
// The per-pose math of eq. 2 is in force_field.h, shared with the haptic client.
// No allocation, no locks, no logging: this runs once per pose at haptic rate.
#pragma once

#include <cstdint>

#include "core/patient.h"
#include "core/scene.h"
#include "core/vec3.h"
#include "haptics/force_field.h"

namespace palpsim {

/// What the model says for one pose.
struct ForceSample {
  Vec3 force_n{0, 0, 0};        // f = k (x - p), clamped; exactly zero outside the body
  Vec3 proxy_mm{0, 0, 0};       // p after friction (the tip itself outside the body)
  Vec3 skin_point_mm{0, 0, 0};  // X: the skin point nearest to the tip, or the skin crossing of the line
                                // through x and p (HapticsSettings::skin_point); the tip outside; in
                                // contact always within the grid's outer faces (the deformation's rule)
  double depth_mm = 0;          // depth of the tip under the skin (0 outside)
  bool contact = false;         // the tip is inside the body
  bool clamped = false;         // the magnitude or the rate clamp changed the force
  bool reset = false;           // a non-finite intermediate value reset the state (corrupt input)
};

/// Computes force, proxy, skin point and depth for device tip `tip_mm` and advances
/// `state`. `dt_s` is the time since the session's previous pose (<= 0 or no previous
/// pose: kNominalHapticPeriodS); it scales the force-rate clamp. `tip_mm` must be
/// finite (the network layer refuses other poses); points outside the patient grid
/// are outside the body.
ForceSample compute_force(const Patient& patient, const HapticsSettings& params, const Vec3& tip_mm,
                          double dt_s, ProxyState& state);

/// The patient's volumes as a FieldView on its grid.
FieldView patient_view(const Patient& patient);

/// Samples C, B, F and grad F trilinearly at a physical point (mm) with one set of
/// weights; outside the grid (beyond half a voxel) everything is zero.
PatientSample sample_patient(const Patient& patient, const Vec3& p_mm);

/// Depth (mm) under the skin from a sample: B minus half a voxel (B is the distance
/// between voxel centres, so the skin, halfway between the last outside and first
/// inside voxel centre, sits at B = spacing / 2), at least 0.
double depth_from_sample(const Patient& patient, const PatientSample& s);

}  // namespace palpsim
