// What a viewer asks to see of one session: frame size, transfer-function preset,
// camera, slices, markers and JPEG quality. Plain settings, checked against the ranges
// below before the render thread ever sees them (a bad value is refused at the network
// edge with the allowed range, never clamped silently).
#pragma once

#include <string>

#include "core/scene.h"
#include "core/vec3.h"

namespace palpsim::render {

/// Transfer-function presets of the 3D view (and the window of the slices): the scene's
/// render.preset, its names in core/setting_names.h.
using Preset = RenderPreset;

/// Limits of the view settings (checked by check_view).
constexpr int kMinFrameEdge = 64;          // pixels
constexpr int kMaxFrameWidth = 3840;       // pixels
constexpr int kMaxFrameHeight = 2160;      // pixels
constexpr double kMinZoom = 0.1, kMaxZoom = 20;
constexpr double kMinSliceFovMm = 10, kMaxSliceFovMm = 2000;

/// One session's view. The camera orbits a look-at point (the tip, or center_mm) in the
/// patient's physical space (LPS: +x left, +y posterior, +z superior): at azimuth 0 and
/// elevation 0 it looks from posterior (+y) towards anterior with superior (+z) up on
/// the screen; azimuth turns it about the superior axis towards the patient's left (+x),
/// elevation lifts it towards superior.
struct ViewSettings {
  int width = 1280;             // frame width (pixels), kMinFrameEdge..kMaxFrameWidth
  int height = 720;             // frame height (pixels), kMinFrameEdge..kMaxFrameHeight
  Preset preset = Preset::kBone;
  double azimuth_deg = 35;      // any finite value (taken modulo 360)
  double elevation_deg = 25;    // -89..89
  double zoom = 1;              // kMinZoom..kMaxZoom; 1 frames the patient grid's bounding sphere
  bool look_at_tip = true;      // camera and slices centre on the device tip (when a pose exists)
  Vec3 center_mm{0, 0, 0};      // look-at point and slice centre when not following the tip (mm, LPS)
  bool center_set = false;      // false: center_mm is the body's bounding-box centre
  int jpeg_quality = 85;        // 1..100
  bool show_tip = true;         // a marker at the device tip x
  bool show_proxy = false;      // a marker at the proxy p
  double slice_fov_mm = 120;    // edge of the square each slice shows (mm)
};

/// Empty when every setting is in range; otherwise one sentence naming the first bad
/// field, its value and the allowed range (e.g. "width = 0 is outside 64..3840 pixels").
std::string check_view(const ViewSettings& v);

}  // namespace palpsim::render
