// How cuda/ plugs into the server: it adds its variants to the registries server/
// defines (core/backend_registry.h), and nothing in server/ names cuda/. The executables
// call palpsim::register_linked_backends() (core/linked_backends.h), which in a CUDA
// build is register_backends() below.
#pragma once

namespace palpsim::cuda {

/// Registers the "cuda" deformation backend in deform_backends() (cuda_backend.cu).
void register_deform_backend();

/// Registers the nvJPEG encoder in render::frame_encoders() and the CUDA-GL overlay
/// writer in render::overlay_writers() (render_interop.cu).
void register_render_backends();

/// Both of the above.
void register_backends();

}  // namespace palpsim::cuda
