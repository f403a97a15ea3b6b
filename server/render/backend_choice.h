// The choice the JPEG encoder and the overlay writer factories share: a name asks for the
// CPU variant, the GPU variant (this build has CUDA and the GL context is on an NVIDIA
// GPU: CUDA-GL interop), or "auto" (the GPU variant where it can be used).
#pragma once

#include <functional>
#include <memory>
#include <string>

#include "core/error.h"
#include "render/egl_context.h"

#ifdef PALPSIM_HAVE_CUDA
#include "cuda/render_interop.h"
#endif

namespace palpsim::render {

/// Names and makers of one choice: `what` ("jpeg encoder"), the names that ask for the
/// CPU variant (the first is the one in messages: "cpu"), the GPU name, the CPU
/// variant's own name ("turbojpeg"), and the makers (`make_gpu` empty in a build
/// without CUDA).
template <class T>
struct BackendChoice {
  const char* what;
  const char* cpu_name;
  const char* cpu_alias;  // a second name for the CPU variant ("" for none)
  const char* gpu_name;
  const char* cpu_label;  // what the CPU variant is called in notes
  std::function<std::unique_ptr<T>()> make_gpu;
  std::function<std::unique_ptr<T>()> make_cpu;
};

/// Makes the variant `name` asks for; throws palpsim::Error for an unknown name or an
/// unusable GPU variant asked for by name; `note` says what was chosen and why.
template <class T>
std::unique_ptr<T> choose_backend(const BackendChoice<T>& c, const std::string& name, const EglContext& ctx,
                                  std::string* note) {
  auto say = [&](const std::string& s) {
    if (note) *note = s;
  };
  const bool cpu = name == c.cpu_name || (*c.cpu_alias && name == c.cpu_alias);
  const bool gpu = name == c.gpu_name, automatic = name == "auto";
  if (!cpu && !gpu && !automatic)
    throw Error(std::string(c.what) + " '" + name + "' is unknown; allowed: auto, " + c.cpu_name + ", " + c.gpu_name);
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
        say(std::string(c.what) + " " + c.gpu_name + " (" + (automatic ? "auto: " : "") + "CUDA-GL interop on " +
            ctx.renderer() + ")");
        return made;
      } catch (const std::exception& e) {
        if (gpu) throw;
        why = e.what();
      }
    }
#endif
  }
  if (gpu) throw Error(std::string(c.what) + " " + c.gpu_name + " is not available: " + why);
  say(std::string(c.what) + " " + c.cpu_label + " (auto: " + c.gpu_name + " not usable: " + why + ")");
  return c.make_cpu();
}

}  // namespace palpsim::render
