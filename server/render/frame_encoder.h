// JPEG encoding of rendered frames: libjpeg-turbo on the CPU (glReadPixels, then
// TurboJPEG), nvJPEG on the GPU (registered by cuda/render_interop.cu: the frame's colour
// texture through CUDA-GL interop, no pixel readback). Chosen by name at run time.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/backend_registry.h"
#include "core/scene.h"
#include "render/egl_context.h"
#include "render/frame_renderer.h"

namespace palpsim::render {

/// One frame to encode: the renderer's target holding it, the quality and where the
/// JPEG and the readback and encode times go.
struct EncodeJob {
  FrameRenderer::TargetId target = 0;
  int quality = 90;                            // 1..100
  std::vector<std::uint8_t>* out = nullptr;    // the JPEG (replaced)
  FrameTimes* times = nullptr;                 // readback_ms and encode_ms are added
};

/// Encodes rendered frames as JPEG.
class FrameEncoder {
 public:
  virtual ~FrameEncoder() = default;
  /// "turbojpeg" or "nvjpeg".
  virtual const char* name() const = 0;
  /// Encodes the frames of several targets of `r` in one go (nvjpeg: one mapping of all
  /// their textures into CUDA, then every encode queued before the first wait); each
  /// job's times get an equal share of the batch's readback and encode time. Throws
  /// palpsim::Error on failure; then no job's output is to be trusted.
  virtual void encode_batch(FrameRenderer& r, const std::vector<EncodeJob>& jobs) = 0;
  /// Frees the host buffers kept from frame to frame (turbojpeg: the readback and the
  /// JPEG output, 50 MB at 3840x2160), for the render thread to call when no session is
  /// watched any more; the next frame makes them again. nvjpeg keeps its device buffers.
  virtual void release_buffers() {}
  /// Encodes target 0's last frame at `quality` (1..100) into `out` (replaced); adds
  /// the readback and encode times to `times`.
  void encode(FrameRenderer& r, int quality, std::vector<std::uint8_t>& out, FrameTimes& times) {
    encode_batch(r, {EncodeJob{0, quality, &out, &times}});
  }
};

/// The encoders outside server/render, by the render.jpeg_encoder value that asks for
/// them: cuda/ registers nvjpeg (register_linked_backends(), core/linked_backends.h).
using FrameEncoderRegistry = BackendRegistry<FrameEncoder, JpegEncoderChoice>;

/// The one registry make_frame_encoder() looks nvjpeg up in.
FrameEncoderRegistry& frame_encoders();

/// Makes the encoder render.jpeg_encoder asks for: cpu (libjpeg-turbo), nvjpeg (registered
/// by a CUDA build and the context is on an NVIDIA GPU) or auto (nvjpeg where it can be
/// used, else cpu). Throws palpsim::Error for an unusable nvjpeg; `note`, when given,
/// says what was chosen and why.
std::unique_ptr<FrameEncoder> make_frame_encoder(JpegEncoderChoice choice, const EglContext& ctx,
                                                 std::string* note = nullptr);

/// Encodes an RGB8 image (rows top-down) with libjpeg-turbo at `quality` (1..100).
void encode_jpeg_rgb(const std::uint8_t* rgb, int width, int height, int quality, std::vector<std::uint8_t>& out);
/// Decodes a JPEG into RGB8 rows top-down; false when the bytes are not a JPEG.
bool decode_jpeg_rgb(const std::uint8_t* jpeg, std::size_t size, std::vector<std::uint8_t>& rgb, int& width,
                     int& height);

}  // namespace palpsim::render
