// The choice the JPEG encoder and the overlay writer factories share: the setting
// (render.jpeg_encoder, render.overlay_writer) asks for the CPU variant, the GPU variant
// (this build has CUDA and the GL context is on an NVIDIA GPU: CUDA-GL interop), or
// auto (the GPU variant where it can be used).
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "core/error.h"
#include "core/setting_names.h"
#include "render/egl_context.h"

#ifdef PALPSIM_HAVE_CUDA
#include "cuda/render_interop.h"
#endif

namespace palpsim::render {

/// Values and makers of one choice, a setting's enum E with kAuto (core/scene.h): `what`
/// ("jpeg encoder"), the values that ask for the CPU and the GPU variant, the CPU
/// variant's own name ("turbojpeg"), and the makers (`make_gpu` empty in a build without
/// CUDA).
template <class T, class E>
struct BackendChoice {
  const char* what;
  E cpu;
  E gpu;
  const char* cpu_label;  // what the CPU variant is called in notes
  std::function<std::unique_ptr<T>()> make_gpu;
  std::function<std::unique_ptr<T>()> make_cpu;
};

/// Makes the variant `asked` asks for; throws palpsim::Error for a value outside the
/// setting's table (a cast) or an unusable GPU variant asked for by name; `note` says
/// what was chosen and why.
template <class T, class E>
std::unique_ptr<T> choose_backend(const BackendChoice<T, E>& c, E asked, const EglContext& ctx, std::string* note) {
  auto say = [&](const std::string& s) {
    if (note) *note = s;
  };
  const std::string name = setting_name(asked);
  const char* gpu_name = setting_name(c.gpu);
  const bool cpu = asked == c.cpu, gpu = asked == c.gpu, automatic = asked == E::kAuto;
  if (!cpu && !gpu && !automatic)
    throw Error(std::string(c.what) + " " + std::to_string(int(asked)) + " is unknown; allowed: " +
                setting_names_listed<E>());
  if (cpu) {
    say(std::string(c.what) + " " + c.cpu_label + " (asked for " + name + ")");
    return c.make_cpu();
  }
  // why the GPU variant cannot be used here ("" when it can)
  std::string why;
  if (!c.make_gpu) {
    why = "this build has no CUDA";
  } else if (!ctx.nvidia()) {
    why = "the OpenGL device is not an NVIDIA GPU (" + ctx.renderer() + ")";
  } else {
#ifdef PALPSIM_HAVE_CUDA
    if (cuda::cuda_render_available(&why)) {
      try {
        auto made = c.make_gpu();
        say(std::string(c.what) + " " + gpu_name + " (" + (automatic ? "auto: " : "") + "CUDA-GL interop on " +
            ctx.renderer() + ")");
        return made;
      } catch (const std::exception& e) {
        if (gpu) throw;
        why = e.what();
      }
    }
#endif
  }
  if (gpu) throw Error(std::string(c.what) + " " + gpu_name + " is not available: " + why);
  say(std::string(c.what) + " " + c.cpu_label + " (auto: " + gpu_name + " not usable: " + why + ")");
  return c.make_cpu();
}

}  // namespace palpsim::render
