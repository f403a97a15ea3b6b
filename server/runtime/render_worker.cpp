#include "runtime/render_worker.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>

#ifdef __linux__
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include "core/error.h"
#include "render/egl_context.h"
#include "render/frame_encoder.h"
#include "render/frame_renderer.h"
#include "render/overlay_writer.h"

namespace palpsim::runtime {
namespace {

// how long the thread naps at most when no watched session needs a frame now (s): well
// below a frame interval, so a new pose or J is drawn within about a millisecond; less
// when a session's next frame is due sooner
constexpr double kIdleSleepS = 1e-3;
// and while nobody watches anything (s)
constexpr double kUnwatchedSleepS = 10e-3;

bool same_marks(const render::FrameMarks& a, const render::FrameMarks& b) {
  return a.has_tip == b.has_tip && a.tip_mm == b.tip_mm && a.proxy_mm == b.proxy_mm && a.contact == b.contact;
}

}  // namespace

// the render thread's own state of one session slot
struct RenderWorker::View {
  std::uint64_t session = 0;               // 0: not rendered
  render::FrameRenderer::OverlayId overlay = -1;
  render::FrameRenderer::TargetId target = -1;  // its framebuffer
  std::uint64_t deform_step = 0;           // J in the overlay: its step and pose
  std::uint64_t deform_pose_seq = 0;
  bool deformed = false;
  double pending_j_ms = 0;                 // J-to-texture time not yet counted in a frame
  std::uint64_t view_version = ~std::uint64_t(0);
  render::ViewSettings view;
  render::FrameMarks marks;                // of the latest frame, or the newest pose seen
  std::uint64_t pose_seq = 0;
  double pose_server_time_s = 0;
  std::uint64_t frame_seq = 0;
  double next_frame_s = 0;                 // server clock: not before then (render.max_fps)
  bool dirty = true;                       // something changed since the latest frame
};

RenderWorker::RenderWorker(ServerShared& shared, StreamState& stream, std::chrono::steady_clock::time_point start,
                           int nice, bool idle)
    : sh_(shared),
      st_(stream),
      start_(start),
      nice_(nice),
      idle_(idle),
      thread_(shared.world, shared.render_seen_generation) {}

RenderWorker::~RenderWorker() { stop(); }

double RenderWorker::now_s() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

void RenderWorker::start() {
  try {
    thread_.start("palpsim-render", nice_, idle_, [this] { run(); });
  } catch (const Error&) {
    stop();
    throw;
  }
}

void RenderWorker::stop() {
  thread_.stop();
  st_.render_wants_device.store(false, std::memory_order_release);
  std::lock_guard<std::mutex> lock(st_.info_mu);
  st_.info.render_thread = false;
  st_.info.egl_context = false;
  st_.info.render_bytes = 0;
}

void RenderWorker::run() {
  try {
    ctx_ = render::EglContext::create();
    spdlog::info("render thread: OpenGL {}", ctx_->describe());
    std::lock_guard<std::mutex> lock(st_.info_mu);
    st_.info.render_thread = true;
    st_.info.egl_context = true;
    st_.info.gl_renderer = ctx_->renderer();
    st_.info.gl_version = ctx_->version();
  } catch (const std::exception& e) {
    const World* w = sh_.world.load(std::memory_order_acquire);
    thread_.setup().fail("scene '" + (w ? w->scene.name : std::string()) +
                         "' asks for frames (effects.frames) but no OpenGL 4.5 context could be made: " + e.what());
    thread_.setup().open();
    return;
  }
  views_.assign(kMaxSlots, View{});
  while (!thread_.stopping()) {
    // a new scene: a renderer of its patient (or none)
    if (!thread_.follow_world(generation_, [this] { set_up_world(); })) break;
    // one pass over the watched sessions: each one's news; those due for a frame are
    // drawn render.max_batch at a time (at most one frame each)
    bool any = false;
    double nap = kUnwatchedSleepS;
    due_.clear();
    const int used = sh_.slots_used.load(std::memory_order_acquire);
    for (int i = 0; i < used && !thread_.stopping(); ++i) {
      const double now = now_s();
      if (look(i, now)) due_.push_back(i);
      const View& v = views_[i];
      if (v.session == 0) continue;
      any = true;
      // a changed session waits for its frame time at most; an unchanged one for news
      nap = std::min(nap, v.dirty ? std::max(v.next_frame_s - now, 0.0) : kIdleSleepS);
    }
    const int batch = std::max(1, settings_.max_batch);
    for (std::size_t b = 0; b < due_.size() && !thread_.stopping(); b += std::size_t(batch))
      draw_batch(due_.data() + b, int(std::min(due_.size() - b, std::size_t(batch))));
    // nobody watches any more: the buffers sized for the last viewers' frames go
    if (!any && drew_since_release_) {
      drew_since_release_ = false;
      try {
        if (encoder_) encoder_->release_buffers();
        if (renderer_) renderer_->release_frame_state();
        report_bytes();
      } catch (const std::exception& e) {
        spdlog::warn("render thread: releasing the last frames' buffers: {}", e.what());
      }
    }
    if (due_.empty() && nap > 0)
      std::this_thread::sleep_for(std::chrono::duration<double>(std::min(nap, any ? kIdleSleepS : kUnwatchedSleepS)));
  }
  // every GL object is destroyed on this thread, the context last
  for (View& v : views_) release_view(v);
  writer_.reset();
  encoder_.reset();
  renderer_.reset();
  ctx_.reset();
  thread_.setup().open();
}

void RenderWorker::set_up_world() {
  const World* w = sh_.world.load(std::memory_order_acquire);
  generation_ = w->generation;
  const Scene scene = w->scene;
  const bool same_patient = patient_ == w->patient;
  patient_ = w->patient;
  thread_.picked_up(generation_);
  settings_ = scene.render;
  // overlays hold at most one VOI: deform.voi_edge^3 within the grid, or the whole grid
  const Vec3i g = patient_->grid.size;
  const int e = scene.deform.voi_edge;
  max_voi_ = scene.deform.whole_volume ? g : Vec3i{std::min(e, g.x), std::min(e, g.y), std::min(e, g.z)};
  for (View& v : views_) release_view(v);
  std::string note;
  // the writer and encoder hold CUDA registrations of the renderer's textures: they go first
  writer_.reset();
  encoder_.reset();
  try {
    if (!scene.effects.frames) {
      renderer_.reset();
      note = "scene '" + scene.name + "' asks for no frames";
    } else {
      render::RenderQuality quality;
      quality.ray_step_vox = settings_.ray_step_vox;
      if (!renderer_ || !same_patient || quality_.ray_step_vox != quality.ray_step_vox) {
        renderer_.reset();
        renderer_ = std::make_unique<render::FrameRenderer>(patient_, quality);
        quality_ = quality;
      }
      std::string enc_note, writer_note;
      encoder_ = render::make_frame_encoder(settings_.jpeg_encoder, *ctx_, &enc_note);
      writer_ = render::make_overlay_writer(settings_.overlay_writer, *ctx_, &writer_note);
      note = enc_note + "; " + writer_note;
      spdlog::info("frames for scene '{}': {}; at most {:g} frames/s per watched session", scene.name, note,
                   settings_.max_fps);
    }
  } catch (const std::exception& e) {
    writer_.reset();
    encoder_.reset();
    renderer_.reset();
    note = "scene '" + scene.name + "': frames cannot be served: " + e.what();
    if (!thread_.setup().is_open())
      thread_.setup().fail(note);
    else
      spdlog::error("{}; its sessions get no frames", note);
  }
  // the deformation worker hands J over in device memory when the writer reads it from there
  st_.render_wants_device.store(writer_ && std::string(writer_->name()) == "cuda-gl", std::memory_order_release);
  std::lock_guard<std::mutex> lock(st_.info_mu);
  st_.info.jpeg_encoder = encoder_ ? encoder_->name() : "";
  st_.info.overlay_writer = writer_ ? writer_->name() : "";
  st_.info.render_note = note;
  reported_bytes_ = renderer_ ? renderer_->bytes() : 0;
  st_.info.render_bytes = reported_bytes_;
}

void RenderWorker::release_view(View& v) {
  if ((v.overlay >= 0 || v.target > 0) && renderer_) {
    try {
      if (v.overlay >= 0) renderer_->remove_overlay(v.overlay);
      if (v.target > 0) renderer_->remove_target(v.target);
    } catch (const std::exception&) {
      // a failing GL delete leaves nothing to undo
    }
    report_bytes();
  }
  v = View{};
}

void RenderWorker::report_bytes() {
  // the stats' figure changes only with an overlay or framebuffer made, resized or freed
  const std::size_t b = renderer_ ? renderer_->bytes() : 0;
  if (b == reported_bytes_) return;
  reported_bytes_ = b;
  std::lock_guard<std::mutex> lock(st_.info_mu);
  st_.info.render_bytes = b;
}

bool RenderWorker::look(int index, double now) {
  const Parts p = parts_.at(index);
  View& v = p.own;
  StreamSlot& ss = *p.stream;
  const std::uint64_t id = renderer_ ? ss.frames_for.load(std::memory_order_acquire) : 0;
  // a session no longer watched, or another one in this slot
  if (id != v.session) {
    release_view(v);
    v.session = id;
  }
  if (id == 0) return false;
  try {
    if (v.overlay < 0) {
      v.overlay = renderer_->add_overlay(max_voi_);
      report_bytes();
    }
    if (v.target < 0) v.target = renderer_->add_target();
    // a newer J waits (it is taken when the frame is drawn: only the newest is written)
    if (ss.j_render.fresh()) v.dirty = true;
    // the session's view, as its viewers last set it (the scene's defaults before)
    {
      std::lock_guard<std::mutex> lock(ss.mu);
      const std::uint64_t version = ss.watch.session_id == id ? ss.watch.view_version : 0;
      if (version != v.view_version) {
        v.view = ss.watch.session_id == id ? ss.watch.view : default_view(settings_);
        v.view_version = version;
        v.dirty = true;
      }
    }
    if (read_pose(p)) v.dirty = true;
    if (!v.dirty || now < v.next_frame_s) return false;
    // render.max_fps on the frames' own cadence, so that waiting for other sessions'
    // frames does not stretch the interval; more than an interval behind, from now
    const double interval = 1.0 / settings_.max_fps;
    if (now - v.next_frame_s > interval) v.next_frame_s = now;
    v.next_frame_s += interval;
    v.dirty = false;
    return true;
  } catch (const std::exception& e) {
    fail_frame(index, now, e.what());
    return false;
  }
}

bool RenderWorker::read_pose(const Parts& p) {
  // the newest pose: the tip and proxy markers, the camera and slice centre
  View& v = p.own;
  Contact c;
  p.table.latest.read(c);
  if (c.session_id != v.session || c.seq == 0) return false;
  render::FrameMarks m;
  m.has_tip = true;
  m.tip_mm = c.tip_mm;
  m.proxy_mm = c.proxy_mm;
  m.contact = c.contact;
  const bool changed = !same_marks(m, v.marks);
  v.marks = m;
  v.pose_seq = c.seq;
  v.pose_server_time_s = c.server_time_s;
  return changed;
}

void RenderWorker::fail_frame(int index, double now, const std::string& what) {
  // a failed frame poisons nothing: the session's next change is drawn again
  View& v = views_[index];
  st_.render_failures.fetch_add(1, std::memory_order_relaxed);
  v.dirty = false;
  v.next_frame_s = now + 1.0 / settings_.max_fps;
  v.pending_j_ms = 0;
  const std::string msg = "session " + hex_id(v.session) + ": frame failed: " + what;
  std::lock_guard<std::mutex> lock(st_.info_mu);
  if (st_.info.last_error != msg) spdlog::warn("{} (counted in stats)", msg);
  st_.info.last_error = msg;
}

void RenderWorker::draw_batch(const int* index, int n) {
  try {
    // 1. the newest J of each session into its overlay, in one write
    writes_.clear();
    written_.clear();
    for (int b = 0; b < n; ++b) {
      const Parts p = parts_.at(index[b]);
      View& v = p.own;
      StreamSlot& ss = *p.stream;
      if (!ss.j_render.take()) continue;
      const JSnapshot& j = ss.j_render.front();
      if (j.session_id != v.session) continue;
      render::OverlayWrite w;
      w.id = v.overlay;
      w.src.voi = j.deformed ? j.voi : Voi{};
      w.src.host_j = j.host_valid ? j.host_j.data() : nullptr;
      w.src.device_j = j.device_valid ? j.device_j.get() : nullptr;
      writes_.push_back(w);
      written_.push_back(index[b]);
      v.deform_step = j.step;
      v.deform_pose_seq = j.pose_seq;
      v.deformed = j.deformed;
    }
    if (!writes_.empty()) {
      const auto tj = std::chrono::steady_clock::now();
      writer_->write_batch(*renderer_, writes_);
      const double share =
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - tj).count() / double(writes_.size());
      for (int i : written_) views_[i].pending_j_ms += share;
    }
    // 2. every frame drawn into its session's framebuffer, nothing waited for; each
    // with the pose newest now (the pass looked at it before the batches ahead of this one)
    const auto t1 = std::chrono::steady_clock::now();
    for (int b = 0; b < n; ++b) {
      const Parts p = parts_.at(index[b]);
      read_pose(p);
      const View& v = p.own;
      renderer_->draw(v.overlay, v.target, v.view, v.marks);
    }
    // 3. all encoded together, each into its slot's frame buffer
    jobs_.clear();
    for (int b = 0; b < n; ++b) {
      const Parts p = parts_.at(index[b]);
      const View& v = p.own;
      EncodedFrame& f = p.stream->frames.back();
      f.times = render::FrameTimes{};
      jobs_.push_back(render::EncodeJob{v.target, v.view.jpeg_quality, &f.jpeg, &f.times});
    }
    encoder_->encode_batch(*renderer_, jobs_);
    drew_since_release_ = true;
    // each frame's total: its J and its share of the batch's drawing and encoding
    const double batch_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t1).count() / double(n);

    // 4. the frames handed over (newest wins)
    for (int b = 0; b < n; ++b) {
      const Parts p = parts_.at(index[b]);
      View& v = p.own;
      StreamSlot& ss = *p.stream;
      EncodedFrame& f = ss.frames.back();
      renderer_->draw_times(v.target, f.times);
      f.times.j_to_texture_ms = v.pending_j_ms;
      f.times.total_ms = v.pending_j_ms + batch_ms;
      f.session_id = v.session;
      f.frame_seq = ++v.frame_seq;
      f.pose_seq = v.pose_seq;
      f.pose_server_time_s = v.pose_server_time_s;
      f.deform_step = v.deform_step;
      f.deform_pose_seq = v.deform_pose_seq;
      f.deformed = v.deformed;
      f.marks = v.marks;
      f.view = v.view;
      f.encoder = encoder_->name();
      const bool replaced = ss.frames.publish();
      ss.frame_bytes.store(held_bytes(ss.frames), std::memory_order_relaxed);
      v.pending_j_ms = 0;
      st_.frames_rendered.fetch_add(1, std::memory_order_relaxed);
      if (replaced) st_.frames_replaced.fetch_add(1, std::memory_order_relaxed);
      std::lock_guard<std::mutex> lock(ss.mu);
      SessionStreamReport& r = ss.report_of(v.session);
      ++r.frames_rendered;
      if (replaced) ++r.frames_replaced;
      r.last = f.times;
      render::add_times(r.sum, f.times);
      std::lock_guard<std::mutex> info_lock(st_.info_mu);
      render::add_times(st_.frame_time_sum, f.times);
    }
  } catch (const std::exception& e) {
    // the whole batch failed: each of its sessions counts one failed frame
    const double now = now_s();
    for (int b = 0; b < n; ++b) fail_frame(index[b], now, e.what());
  }
  report_bytes();  // a framebuffer may have been made or resized
}

}  // namespace palpsim::runtime
