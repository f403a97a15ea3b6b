// The server's render thread (server/render/README.md): owns the EGL context and every
// GL object, renders each watched session's frame when its J, tip or view changed
// (at most render.max_fps per session), encodes it and hands it to the publisher.
// Built only for scenes that ask for frames; the pose thread shares nothing with it.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "runtime/session_state.h"
#include "runtime/session_table.h"
#include "runtime/worker_thread.h"
#include "runtime/stream_state.h"

#include "render/frame_encoder.h"
#include "render/frame_renderer.h"
#include "render/overlay_writer.h"

namespace palpsim::render {
class EglContext;
}  // namespace palpsim::render

namespace palpsim::runtime {

/// Renders frames of the watched sessions on one thread.
///
/// Why one thread: a GL context is current on one thread at a time, and the GPU
/// serialises the frames anyway; one thread that round-robins the watched sessions
/// (each at most render.max_fps) shares the GPU fairly and, on a CPU-only machine
/// (Mesa's llvmpipe), runs below the haptic thread like the deformation worker.
///
/// Why batches: with the cuda deformation running, every hand-over between the GL
/// context (ray cast) and CUDA (J into the overlay, nvJPEG) waits for the GPU's time
/// slice, which with many sessions costs more than the frame's own work. So
/// the sessions due in one pass are served render.max_batch at a time: all their J in
/// one write, all frames drawn, then all encoded: two hand-overs per batch.
class RenderWorker {
 public:
  /// `nice`, `idle`: the thread's nice value and SCHED_IDLE (Linux), as the deformation worker's.
  RenderWorker(ServerShared& shared, StreamState& stream, std::chrono::steady_clock::time_point start, int nice,
               bool idle);
  ~RenderWorker();
  RenderWorker(const RenderWorker&) = delete;
  RenderWorker& operator=(const RenderWorker&) = delete;

  /// Starts the thread and waits until it has an OpenGL 4.5 context, a renderer of the
  /// current patient and its encoders; throws palpsim::Error saying why frames cannot
  /// be served (no EGL/GL 4.5, a patient too large for a 3D texture, an encoder).
  void start();
  /// Stops and joins the thread; GL objects and the context are destroyed on it.
  void stop();

 private:
  struct View;
  using Parts = SessionState<View>;  // a session's parts, this thread's own included
  void run();
  void set_up_world();
  bool look(int index, double now_s);
  bool read_pose(const Parts& p);
  void draw_batch(const int* index, int n);
  void fail_frame(int index, double now_s, const std::string& what);
  void release_view(View& v);
  void report_bytes();
  double now_s() const;

  ServerShared& sh_;
  StreamState& st_;
  std::chrono::steady_clock::time_point start_;
  int nice_ = 19;
  bool idle_ = true;
  WorkerThread thread_;  // keeps the world-pinning rule (ServerShared::render_seen_generation)

  // (render thread) the context, the world it draws and per-slot views
  std::unique_ptr<render::EglContext> ctx_;
  std::unique_ptr<render::FrameRenderer> renderer_;
  std::unique_ptr<render::FrameEncoder> encoder_;
  std::unique_ptr<render::OverlayWriter> writer_;
  std::uint64_t generation_ = 0;
  PatientPtr patient_;
  RenderSettings settings_;
  render::RenderQuality quality_;  // the renderer's
  Vec3i max_voi_{0, 0, 0};
  std::vector<View> views_;  // by slot index
  SessionStates<View> parts_{sh_, st_, views_};  // each slot's parts: the table's, the stream's, views_'
  // one pass's sessions due for a frame and one batch's work, kept to reuse their memory
  std::vector<int> due_;
  std::vector<render::OverlayWrite> writes_;
  std::vector<int> written_;  // the slot of each write
  std::vector<render::EncodeJob> jobs_;
  std::size_t reported_bytes_ = 0;  // the renderer's bytes as the stats have them
  bool drew_since_release_ = false;  // frames were encoded since the encoder's buffers were last freed
};

}  // namespace palpsim::runtime
