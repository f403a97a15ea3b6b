// What the stream's threads share (server/render/README.md): per session slot, which
// session is watched now (the publisher decides; the deformation worker and the render
// thread read), the newest-wins hand-overs of J and of frames, what the session's
// viewers asked for (the control thread writes), and what the stats report. Built only
// for scenes that ask for frames or bricks; the pose thread never touches any of it.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "core/device_bytes.h"
#include "core/latest.h"
#include "core/scene.h"
#include "deform/deform_math.h"
#include "runtime/session_table.h"
#include "render/frame_renderer.h"
#include "render/view.h"

namespace palpsim::runtime {

using deform::Voi;

/// A session's deformation as the render and brick paths get it from the worker.
struct JSnapshot {
  std::uint64_t session_id = 0;
  std::uint64_t step = 0;             // the session's deformation steps when taken (0: never deformed)
  std::uint64_t pose_seq = 0;         // seq of the newest pose J stands for (the step's, or a later one served
                                      // without a step: DeformSessionStats.contacts_current)
  double pose_server_time_s = 0;      // when that pose was answered (server clock)
  Vec3 tip_mm{0, 0, 0};               // that pose's tip x and proxy p (mm)
  Vec3 proxy_mm{0, 0, 0};
  bool deformed = false;              // false: J = I everywhere (voi empty)
  Voi voi;                            // J's box (patient voxel indices)
  std::vector<float> host_j;          // J on voi, i fastest; valid when host_valid
  bool host_valid = false;
  std::unique_ptr<DeviceBytes> device_j;  // J on voi on the GPU (cuda backend); valid when device_valid
  bool device_valid = false;
};

/// One encoded frame, from the render thread to the publisher.
struct EncodedFrame {
  std::uint64_t session_id = 0;
  std::uint64_t frame_seq = 0;        // 1, 2, ... per session
  std::uint64_t pose_seq = 0;         // the pose whose tip it shows (0: no pose yet)
  double pose_server_time_s = 0;      // when that pose was answered
  std::uint64_t deform_step = 0;      // J's step (0: undeformed)
  std::uint64_t deform_pose_seq = 0;  // the newest pose J stands for (JSnapshot::pose_seq)
  bool deformed = false;
  render::FrameMarks marks;           // tip, proxy, contact
  render::ViewSettings view;          // what it was rendered with
  render::FrameTimes times;
  const char* encoder = "";           // "turbojpeg" or "nvjpeg"
  std::vector<std::uint8_t> jpeg;
};

/// What one session's viewers asked for through WatchSession (control thread writes).
struct WatchSettings {
  std::uint64_t session_id = 0;       // the session these belong to (0: none yet: scene defaults)
  render::ViewSettings view;
  std::uint64_t view_version = 0;     // grows with every change of view
  bool brick_float32 = false;         // false: int16 HU
  bool brick_zstd = false;
  double frames_hold_until_s = 0;     // server clock: frames rendered until then without a subscriber
  double bricks_hold_until_s = 0;     // the same for bricks
};

/// Pose-to-frame latencies of a session's latest frames (ms), for p50/p99 in stats.
struct LatencyRing {
  static constexpr int kSize = 1024;
  std::array<float, kSize> ms{};
  std::uint64_t count = 0;
  void add(double v) { ms[count++ % kSize] = float(v); }
  /// The q-quantile (0..1) of the kept values; 0 before the first.
  double quantile(double q) const;
};

/// One session's stream statistics (publisher and render thread write under StreamSlot::mu).
struct SessionStreamReport {
  std::uint64_t session_id = 0;       // the session they count (reset when another takes the slot)
  std::uint64_t frames_rendered = 0, frames_published = 0, frames_replaced = 0;
  std::uint64_t bricks_published = 0, key_bricks_published = 0;
  render::FrameTimes last, sum;
  LatencyRing pose_to_frame;
};

/// One session slot's stream state (index = the session's slot index; one of a session's
/// parts: session_state.h).
struct StreamSlot {
  std::atomic<std::uint64_t> frames_for{0};  // (publisher) the session whose frames are rendered now; 0: none
  std::atomic<std::uint64_t> bricks_for{0};  // (publisher) the session whose bricks are published now; 0: none
  Latest<JSnapshot> j_render;                // deformation worker -> render thread
  Latest<JSnapshot> j_bricks;                // deformation worker -> publisher
  Latest<EncodedFrame> frames;               // render thread -> publisher
  std::atomic<std::size_t> j_render_bytes{0};  // (deformation worker) what j_render's buffers hold
  std::atomic<std::size_t> brick_bytes{0};     // (deformation worker) what j_bricks' buffers hold
  std::atomic<std::size_t> frame_bytes{0};     // (render thread) what frames' buffers hold
  mutable std::mutex mu;                     // guards the two below (never taken on the pose path)
  WatchSettings watch;
  SessionStreamReport report;

  /// The report of session `id`, restarted when it still counts an earlier session of
  /// this slot; call with mu held.
  SessionStreamReport& report_of(std::uint64_t id) {
    if (report.session_id != id) {
      report = SessionStreamReport{};
      report.session_id = id;
    }
    return report;
  }
};

/// Server-wide stream facts and counters.
struct StreamInfo {
  bool publisher_thread = false, render_thread = false, egl_context = false;
  std::string gl_renderer, gl_version, jpeg_encoder, overlay_writer, render_note, last_error;
  std::size_t render_bytes = 0;       // GPU memory the renderer holds (textures, framebuffer)
};

/// Everything the stream's threads share; made when the first scene that asks for
/// frames or bricks is served and kept for the server's life (slots are reused).
struct StreamState {
  StreamState() : slots(new StreamSlot[kMaxSlots]) {}
  std::unique_ptr<StreamSlot[]> slots;
  StreamSlot& slot(std::uint64_t session_id) { return slots[slot_index(session_id)]; }

  std::atomic<bool> render_wants_device{false};  // (render) J for frames as a device copy (cuda-gl writer)
  std::atomic<std::uint64_t> frames_rendered{0}, frames_published{0}, frames_replaced{0}, bricks_published{0},
      key_bricks_published{0}, bytes_published{0}, bad_subscriptions{0}, render_failures{0};
  std::atomic<std::uint32_t> subscriptions{0}, sessions_watched{0};
  mutable std::mutex info_mu;                     // guards info and frame_time_sum
  StreamInfo info;
  render::FrameTimes frame_time_sum;              // (render) summed over all frames
};

/// A session's default view: the scene's render settings.
render::ViewSettings default_view(const RenderSettings& r);

/// The topic of a session's frames ("frame." + 16 hex digits) or bricks ("brick." + ...).
std::string frame_topic(std::uint64_t session_id);
std::string brick_topic(std::uint64_t session_id);

/// Bytes the three buffers of a hand-over hold (for stats). Call it on the writer's
/// thread: only the writer ever resizes them, the reader only reads.
std::size_t held_bytes(const Latest<JSnapshot>& h);
std::size_t held_bytes(const Latest<EncodedFrame>& h);

}  // namespace palpsim::runtime
