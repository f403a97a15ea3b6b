// WatchSession (a session's frames and bricks, and the view they are rendered with) and
// PickRequest (the skin point under a pixel of a session's frame).
#include "net/control.h"

#include <cmath>
#include <cstdio>

#include "core/setting_names.h"
#include "net/client_text.h"
#include "net/pose_service.h"
#include "net/wire_convert.h"
#include "render/camera.h"
#include "render/view.h"

namespace palpsim::net {

using runtime::brick_topic;
using runtime::default_view;
using runtime::frame_topic;
using runtime::StreamSlot;
using runtime::WatchSettings;

namespace {

// applies the fields a WatchSession sets to `v`; "" or the first bad field and why
std::string apply_view(const v1::ViewSettings& in, render::ViewSettings& v) {
  if (in.has_width()) v.width = int(std::min<std::uint32_t>(in.width(), 1u << 30));
  if (in.has_height()) v.height = int(std::min<std::uint32_t>(in.height(), 1u << 30));
  if (in.has_preset() && !parse_setting(in.preset(), &v.preset))
    return "preset '" + client_text(in.preset()) + "' is not one of " + setting_names_listed<render::Preset>();
  if (in.has_azimuth_deg()) v.azimuth_deg = in.azimuth_deg();
  if (in.has_elevation_deg()) v.elevation_deg = in.elevation_deg();
  if (in.has_zoom()) v.zoom = in.zoom();
  if (in.has_look_at_tip()) v.look_at_tip = in.look_at_tip();
  if (in.has_center_mm()) {
    v.center_mm = {in.center_mm().x(), in.center_mm().y(), in.center_mm().z()};
    v.center_set = true;
  }
  if (in.has_jpeg_quality()) v.jpeg_quality = int(std::min<std::uint32_t>(in.jpeg_quality(), 1u << 30));
  if (in.has_show_tip()) v.show_tip = in.show_tip();
  if (in.has_show_proxy()) v.show_proxy = in.show_proxy();
  if (in.has_slice_fov_mm()) v.slice_fov_mm = in.slice_fov_mm();
  return render::check_view(v);
}

}  // namespace

void Server::Control::watch() {
  const auto& r = req_.watch();
  const Scene& sc = world().scene;
  const auto not_built = [this](const std::string& m) {
    refuse(v1::ERROR_NOT_BUILT, sh_.counters.not_built, m);
  };
  if (!sc.effects.frames && !sc.effects.bricks)
    return not_built("WatchSession: scene '" + sc.name +
                     "' asks for neither frames nor bricks (effects.frames, effects.bricks): nothing is streamed");
  if (!r.frames() && !r.bricks())
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                  "WatchSession: ask for frames, bricks or both (WatchSession.frames, WatchSession.bricks)");
  if (r.frames() && !frames_served()) {
    std::string why = "scene '" + sc.name + "' asks for no frames (effects.frames)";
    if (sc.effects.frames && stream_) {
      std::lock_guard<std::mutex> lock(stream_->info_mu);
      why = stream_->info.render_note.empty() ? "the render thread is not running" : stream_->info.render_note;
    }
    return not_built("WatchSession.frames: " + why);
  }
  if (r.bricks() && !bricks_served())
    return not_built("WatchSession.bricks: scene '" + sc.name + "' asks for no bricks (effects.bricks)");
  if (r.has_hold_s() && (!std::isfinite(r.hold_s()) || r.hold_s() < 0 || r.hold_s() > 3600)) {
    char b[160];
    std::snprintf(b, sizeof b, "WatchSession.hold_s: %g is outside [0, 3600] s", r.hold_s());
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, b);
  }
  // the session: the one named, or the requester's newest open one
  std::uint64_t id = r.session_id();
  if (id == 0) {
    std::uint64_t newest = 0;
    for (int i = 0; i < sh_.slots_used.load(std::memory_order_acquire); ++i) {
      const std::uint64_t sid = sh_.slots[i].id.load(std::memory_order_acquire);
      if (sid != 0 && opened_order_[i] > newest && sh_.slots[i].owner == requester_) {
        newest = opened_order_[i];
        id = sid;
      }
    }
    if (id == 0)
      return refuse(v1::ERROR_NO_SESSION_OPEN, sh_.counters.unknown_session,
                    std::string("WatchSession.session_id: 0 (any session of this client) but none of this "
                                "client's sessions is open; this client is known by its ") +
                        requester_kind() +
                        (sh_.curve ? ": watch with the haptic client's keys"
                         : requester_.rfind("token ", 0) == 0
                             ? ": give the haptic client the same client token"
                             : ", which opened no session: give the haptic client and this viewer the same "
                               "--client-token (ControlRequest.client_token), or name the session"));
  }
  // a watch acts on the session (its idle clock), but is no message naming it for the
  // scene's session_timeout_s: only the session's poses and requests naming it are
  SessionSlot* watched = find(id);
  if (!watched)
    return refuse(v1::ERROR_UNKNOWN_SESSION, sh_.counters.unknown_session,
                  "WatchSession.session_id: " + hex_id(id) +
                      " is not an open session (never opened, closed, or timed out)");
  if (!owned(*watched, id, "WatchSession.session_id")) return;
  watched->last_used_ns.store(ns_since(start_));
  // the view: the session's current one with the fields this request sets
  StreamSlot& ss = stream_->slot(id);
  std::lock_guard<std::mutex> lock(ss.mu);
  if (ss.watch.session_id != id) {
    ss.watch = WatchSettings{};
    ss.watch.session_id = id;
    ss.watch.view = default_view(sc.render);
  }
  render::ViewSettings v = ss.watch.view;
  if (r.has_view()) {
    const std::string bad = apply_view(r.view(), v);
    if (!bad.empty())
      return refuse(v1::ERROR_BAD_VIEW, sh_.counters.bad_view, "WatchSession.view: " + bad);
  }
  if (r.brick_encoding() != v1::BRICK_INT16 && r.brick_encoding() != v1::BRICK_FLOAT32)
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                  "WatchSession.brick_encoding: " + std::to_string(r.brick_encoding()) +
                      " is not BRICK_INT16 (0) or BRICK_FLOAT32 (1)");
  if (r.brick_compression() != v1::COMPRESSION_NONE && r.brick_compression() != v1::COMPRESSION_ZSTD)
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                  "WatchSession.brick_compression: " + std::to_string(r.brick_compression()) +
                      " is not COMPRESSION_NONE (0) or COMPRESSION_ZSTD (1)");
  ss.watch.view = v;
  ++ss.watch.view_version;
  const double now = ns_since(start_) * 1e-9;
  // a hold is set (or ended with 0) only by a request that names one
  if (r.has_hold_s() && r.frames()) ss.watch.frames_hold_until_s = now + r.hold_s();
  if (r.has_hold_s() && r.bricks()) ss.watch.bricks_hold_until_s = now + r.hold_s();
  if (r.bricks()) {
    ss.watch.brick_float32 = r.brick_encoding() == v1::BRICK_FLOAT32;
    ss.watch.brick_zstd = r.brick_compression() == v1::COMPRESSION_ZSTD;
  }
  auto* o = rep_.mutable_watch();
  o->set_session_id(id);
  o->set_stream_endpoint(publisher_->endpoint());
  if (r.frames()) o->set_frame_topic(frame_topic(id));
  if (r.bricks()) o->set_brick_topic(brick_topic(id));
  fill_view(o->mutable_view(), v);
  o->set_brick_encoding(ss.watch.brick_float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16);
  o->set_brick_compression(ss.watch.brick_zstd ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE);
}

void Server::Control::pick() {
  const auto& r = req_.pick();
  SessionSlot* s = session_or_refuse(r.session_id(), "PickRequest.session_id");
  if (!s) return;
  const World& w = world();
  const std::uint64_t id = r.session_id();
  // the view its frames are rendered with: the watched one, else the scene's
  render::ViewSettings v = default_view(w.scene.render);
  if (stream_) {
    StreamSlot& ss = stream_->slot(id);
    std::lock_guard<std::mutex> lock(ss.mu);
    if (ss.watch.session_id == id) v = ss.watch.view;
  }
  const render::Camera cam = [&] {
    Contact c;
    s->latest.read(c);
    const bool has_tip = c.session_id == id && c.seq != 0;
    return render::orbit_camera(w.patient->grid, v, render::frame_target(v, has_tip, c.tip_mm, w.body_center_mm));
  }();
  const auto dir = render::pixel_ray(cam, r.x_px(), r.y_px());
  if (!dir) {
    char b[320];
    std::snprintf(b, sizeof b,
                  "PickRequest.x_px, y_px: (%g, %g) is outside the frame's 3D view, pixels 0..%d x 0..%d of a "
                  "%d x %d frame (the slice column starts at x = %d)",
                  r.x_px(), r.y_px(), cam.view_w, v.height, v.width, v.height, cam.view_w);
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, b);
  }
  auto* o = rep_.mutable_pick();
  o->set_session_id(id);
  set_vec(o->mutable_ray_origin_mm(), cam.eye);
  set_vec(o->mutable_ray_direction(), *dir);
  fill_view(o->mutable_view(), v);
  if (const auto hit = render::first_body_hit(*w.patient, cam.eye, *dir)) {
    o->set_hit(true);
    set_vec(o->mutable_point_mm(), *hit);
    o->set_distance_mm(norm(*hit - cam.eye));
  }
}

}  // namespace palpsim::net
