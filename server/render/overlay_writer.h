// How a session's deformed VOI (J) reaches its overlay texture: a sub-box upload from
// host memory (the cpu deformation backend), or CUDA-GL interop from device memory (the
// cuda backend; registered by cuda/render_interop.cu), chosen once per render thread.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "core/backend_registry.h"
#include "core/device_bytes.h"
#include "core/scene.h"
#include "render/egl_context.h"
#include "render/frame_renderer.h"

namespace palpsim::render {

/// J of one session's latest deformation step, as the render thread gets it.
struct OverlaySource {
  Voi voi;                            // the step's VOI (patient voxel indices)
  const float* host_j = nullptr;      // J on voi (voi.count() floats, i fastest), or nullptr
  const DeviceBytes* device_j = nullptr;  // the same on the GPU (cuda backend), or nullptr
};

/// One overlay to write: which, and J for it.
struct OverlayWrite {
  FrameRenderer::OverlayId id = -1;
  OverlaySource src;
};

/// Writes J into sessions' overlays.
class OverlayWriter {
 public:
  virtual ~OverlayWriter() = default;
  /// "upload" (host memory, glTexSubImage3D) or "cuda-gl" (device memory, interop).
  virtual const char* name() const = 0;
  /// Makes each overlay show its J (cuda-gl: one mapping of all the textures, one wait
  /// at the end; when an overlay appears twice, the last write wins). On return every
  /// source may be reused. Throws palpsim::Error when a source has neither a host nor
  /// (for this writer) a usable device copy; then the overlays' contents are undefined
  /// until their next write.
  virtual void write_batch(FrameRenderer& r, const std::vector<OverlayWrite>& writes) = 0;
  /// Makes the overlay `id` show J on src.voi.
  void write(FrameRenderer& r, FrameRenderer::OverlayId id, const OverlaySource& src) {
    write_batch(r, {OverlayWrite{id, src}});
  }
};

/// The overlay writers outside server/render, by the render.overlay_writer value that
/// asks for them: cuda/ registers cuda-gl (register_linked_backends(), core/linked_backends.h).
using OverlayWriterRegistry = BackendRegistry<OverlayWriter, OverlayWriterChoice>;

/// The one registry make_overlay_writer() looks cuda-gl up in.
OverlayWriterRegistry& overlay_writers();

/// Makes the writer render.overlay_writer asks for: upload, cuda-gl (registered by a CUDA
/// build, and the context is on an NVIDIA GPU) or auto (cuda-gl where it can be used, else
/// upload). Throws palpsim::Error for an unusable cuda-gl; `note` says what was chosen
/// and why.
std::unique_ptr<OverlayWriter> make_overlay_writer(OverlayWriterChoice choice, const EglContext& ctx,
                                                   std::string* note = nullptr);

}  // namespace palpsim::render
