// The CUDA side of rendering, behind plain C++ types (no CUDA header here): nvJPEG
// encoding of a rendered frame straight from its GL colour texture, and writing a
// session's J from device memory into its overlay texture, both through CUDA-GL
// interop on the render thread. Built only with PALPSIM_CUDA (cuda/render_interop.cu);
// register_render_backends() (cuda/register_backends.h) puts it in server/render's
// registries, which make_frame_encoder(kNvjpeg) and make_overlay_writer(kCudaGl) look up.
#pragma once

#include <memory>
#include <string>

#include "render/frame_encoder.h"
#include "render/overlay_writer.h"

namespace palpsim::cuda {

/// The nvJPEG frame encoder: maps FrameRenderer::color_texture() into CUDA, converts
/// RGBA8 to interleaved RGB on the device and encodes with nvJPEG (4:2:0, as the CPU
/// encoder); only the JPEG bytes cross to the host. Throws palpsim::Error when nvJPEG
/// or the interop cannot be set up (the message says which call failed).
std::unique_ptr<render::FrameEncoder> make_nvjpeg_frame_encoder();

/// The overlay writer that copies J from device memory (OverlaySource::device_j, made
/// by the cuda deformation backend) into FrameRenderer::overlay_texture() through
/// CUDA-GL interop; falls back to the host copy when the source has no device J.
std::unique_ptr<render::OverlayWriter> make_cuda_overlay_writer();

/// True when a CUDA device is usable from the render thread; otherwise `why` says why.
bool cuda_render_available(std::string* why);

}  // namespace palpsim::cuda
