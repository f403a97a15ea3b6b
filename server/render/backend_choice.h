// The choice the JPEG encoder and the overlay writer factories share: the setting
// (render.jpeg_encoder, render.overlay_writer) asks for the CPU variant, the GPU variant
// (registered by cuda/ in a CUDA build, and the GL context is on an NVIDIA GPU: CUDA-GL
// interop), or auto (the GPU variant where it can be used).
#pragma once

#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "core/backend_registry.h"
#include "core/error.h"
#include "core/setting_names.h"
#include "render/egl_context.h"

namespace palpsim::render {

/// Values and makers of one choice, a setting's enum E with kAuto (core/scene.h): `what`
/// ("jpeg encoder"), the values that ask for the CPU and the GPU variant, the CPU
/// variant's own name ("turbojpeg"), its maker, and the registry the GPU variant is
/// looked up in (empty in a build without CUDA).
template <class T, class E>
struct BackendChoice {
  const char* what;
  E cpu;
  E gpu;
  const char* cpu_label;  // what the CPU variant is called in notes
  std::function<std::unique_ptr<T>()> make_cpu;
  const BackendRegistry<T, E>* registry;
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
  const std::optional<typename BackendRegistry<T, E>::Factory> gpu_factory = c.registry->find(c.gpu);
  if (!gpu_factory) {
    why = "this build has no CUDA";
  } else if (!ctx.nvidia()) {
    why = "the OpenGL device is not an NVIDIA GPU (" + ctx.renderer() + ")";
  } else if (gpu_factory->usable(&why)) {
    try {
      auto made = gpu_factory->make();
      say(std::string(c.what) + " " + gpu_name + " (" + (automatic ? "auto: " : "") + "CUDA-GL interop on " +
          ctx.renderer() + ")");
      return made;
    } catch (const std::exception& e) {
      if (gpu) throw;
      why = e.what();
    }
  }
  if (gpu) throw Error(std::string(c.what) + " " + gpu_name + " is not available: " + why);
  say(std::string(c.what) + " " + c.cpu_label + " (auto: " + gpu_name + " not usable: " + why + ")");
  return c.make_cpu();
}

}  // namespace palpsim::render
