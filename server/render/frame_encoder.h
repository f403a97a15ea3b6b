// JPEG encoding of rendered frames: libjpeg-turbo on the CPU (glReadPixels, then
// TurboJPEG), nvJPEG on the GPU (cuda/frame_encoder_nvjpeg.cu: the frame's colour
// texture through CUDA-GL interop, no pixel readback). Chosen by name at run time.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "render/egl_context.h"
#include "render/frame_renderer.h"

namespace palpsim::render {

/// Encodes the renderer's last frame as JPEG.
class FrameEncoder {
 public:
  virtual ~FrameEncoder() = default;
  /// "turbojpeg" or "nvjpeg".
  virtual const char* name() const = 0;
  /// Encodes the last frame of `r` at `quality` (1..100) into `out` (replaced); adds
  /// the readback and encode times to `times`. Throws palpsim::Error on failure.
  virtual void encode(FrameRenderer& r, int quality, std::vector<std::uint8_t>& out, FrameTimes& times) = 0;
};

/// Makes an encoder by name: "cpu" (libjpeg-turbo), "nvjpeg" (this build has CUDA and
/// the context is on an NVIDIA GPU) or "auto" (nvjpeg where it can be used, else cpu).
/// Throws palpsim::Error for an unknown name or an unusable "nvjpeg"; `note`, when
/// given, says what was chosen and why.
std::unique_ptr<FrameEncoder> make_frame_encoder(const std::string& name, const EglContext& ctx,
                                                 std::string* note = nullptr);

/// Encodes an RGB8 image (rows top-down) with libjpeg-turbo at `quality` (1..100).
void encode_jpeg_rgb(const std::uint8_t* rgb, int width, int height, int quality, std::vector<std::uint8_t>& out);
/// Decodes a JPEG into RGB8 rows top-down; false when the bytes are not a JPEG.
bool decode_jpeg_rgb(const std::uint8_t* jpeg, std::size_t size, std::vector<std::uint8_t>& rgb, int& width,
                     int& height);

}  // namespace palpsim::render
