// The project's own types as wire messages (protobuf stays in server/net/): points and
// view settings, shared by the control thread, the pose thread and the stream publisher.
#pragma once

#include "core/setting_names.h"
#include "core/vec3.h"
#include "palpsim/wire.pb.h"
#include "render/frame_renderer.h"
#include "render/view.h"

namespace palpsim::net {

/// A point or vector (mm) into a wire Vec3.
inline void set_vec(::palpsim::v1::Vec3* out, const Vec3& v) {
  out->set_x(v.x);
  out->set_y(v.y);
  out->set_z(v.z);
}

/// A whole view into a wire ViewSettings (every field set).
inline void fill_view(::palpsim::v1::ViewSettings* o, const render::ViewSettings& v) {
  o->set_width(v.width);
  o->set_height(v.height);
  o->set_preset(setting_name(v.preset));
  o->set_azimuth_deg(v.azimuth_deg);
  o->set_elevation_deg(v.elevation_deg);
  o->set_zoom(v.zoom);
  o->set_look_at_tip(v.look_at_tip);
  set_vec(o->mutable_center_mm(), v.center_mm);
  o->set_jpeg_quality(v.jpeg_quality);
  o->set_show_tip(v.show_tip);
  o->set_show_proxy(v.show_proxy);
  o->set_slice_fov_mm(v.slice_fov_mm);
}

/// Stage times (ms) into a wire FrameTimes.
inline void fill_frame_times(::palpsim::v1::FrameTimes* out, const render::FrameTimes& t) {
  out->set_j_to_texture_ms(t.j_to_texture_ms);
  out->set_raycast_ms(t.raycast_ms);
  out->set_slices_ms(t.slices_ms);
  out->set_composite_ms(t.composite_ms);
  out->set_readback_ms(t.readback_ms);
  out->set_encode_ms(t.encode_ms);
  out->set_total_ms(t.total_ms);
}

/// A wire FrameTimes back into stage times (ms).
inline render::FrameTimes frame_times(const ::palpsim::v1::FrameTimes& w) {
  render::FrameTimes t;
  t.j_to_texture_ms = w.j_to_texture_ms();
  t.raycast_ms = w.raycast_ms();
  t.slices_ms = w.slices_ms();
  t.composite_ms = w.composite_ms();
  t.readback_ms = w.readback_ms();
  t.encode_ms = w.encode_ms();
  t.total_ms = w.total_ms();
  return t;
}

}  // namespace palpsim::net
