// The one call that plugs the optional backends in: each executable that chooses
// backends (palpsim-server, palpsim-bench, the tests' main) calls it first thing in main.
// The library palpsim_backends defines it: in a CUDA build cuda/register_backends.cpp,
// which registers the "cuda" deformation backend, the nvJPEG encoder and the CUDA-GL
// overlay writer; in a build without CUDA core/linked_backends.cpp, which has none to add.
#pragma once

namespace palpsim {

/// Adds the optional backends this executable was linked with to the registries of
/// core/backend_registry.h (deform_backends(), render::frame_encoders(),
/// render::overlay_writers()), so that the settings that ask for them find them. An
/// explicit call rather than static constructors, which the linker drops from static
/// libraries that nothing references. Call once, before any backend is chosen.
void register_linked_backends();

}  // namespace palpsim
