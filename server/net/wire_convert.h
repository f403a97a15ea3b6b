// The project's own types as wire messages (protobuf stays in server/net/): points and
// view settings, shared by the control thread, the pose thread and the stream publisher.
#pragma once

#include "core/vec3.h"
#include "palpsim/wire.pb.h"
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
  o->set_preset(render::preset_name(v.preset));
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

}  // namespace palpsim::net
