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

#include "net/session_table.h"
#include "net/setup_gate.h"
#include "net/stream_state.h"

#include "render/frame_renderer.h"

namespace palpsim::render {
class EglContext;
class FrameEncoder;
class OverlayWriter;
}  // namespace palpsim::render

namespace palpsim::net {

/// Renders frames of the watched sessions on one thread.
///
/// Why one thread: a GL context is current on one thread at a time, and the GPU
/// serialises the frames anyway; one thread that round-robins the watched sessions
/// (each at most render.max_fps) shares the GPU fairly and, on a CPU-only machine
/// (Mesa's llvmpipe), runs below the haptic thread like the deformation worker.
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
  void run();
  void set_up_world();
  bool serve(int index, double now_s);
  void release_view(View& v);
  double now_s() const;

  ServerShared& sh_;
  StreamState& st_;
  std::chrono::steady_clock::time_point start_;
  int nice_ = 19;
  bool idle_ = true;
  std::thread thread_;
  std::atomic<bool> stop_{false};

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

  // start() waits for the first set-up
  SetupGate setup_;
};

}  // namespace palpsim::net
