#include "render/overlay_writer.h"

#include <string>

#include "core/error.h"

#ifdef PALPSIM_HAVE_CUDA
#include "cuda/render_interop.h"
#endif

namespace palpsim::render {
namespace {

// J from host memory by a sub-box upload (glTexSubImage3D).
class UploadWriter final : public OverlayWriter {
 public:
  const char* name() const override { return "upload"; }
  void write(FrameRenderer& r, FrameRenderer::OverlayId id, const OverlaySource& src) override {
    // an empty VOI: the session is undeformed
    if (src.voi.count() <= 0) {
      r.clear_overlay(id);
      return;
    }
    if (!src.host_j)
      throw Error("overlay writer upload: J of the VOI is not in host memory (the deformation handed over " +
                  std::string(src.device_j ? "only a device copy" : "nothing") + ")");
    r.upload_overlay(id, src.voi, src.host_j);
  }
};

}  // namespace

std::unique_ptr<OverlayWriter> make_overlay_writer(const std::string& name, const EglContext& ctx, std::string* note) {
  auto say = [&](const std::string& s) {
    if (note) *note = s;
  };
  if (name != "upload" && name != "cuda-gl" && name != "auto")
    throw Error("overlay writer '" + name + "' is unknown; allowed: auto, upload, cuda-gl");
#ifdef PALPSIM_HAVE_CUDA
  if (name == "cuda-gl" || name == "auto") {
    std::string why;
    if (!ctx.nvidia()) {
      why = "the OpenGL device is not an NVIDIA GPU (" + ctx.renderer() + ")";
    } else if (!cuda::cuda_render_available(&why)) {
      // why says it
    } else {
      try {
        auto w = cuda::make_cuda_overlay_writer();
        say("overlay writer cuda-gl (" + std::string(name == "auto" ? "auto: " : "") + "CUDA-GL interop on " +
            ctx.renderer() + ")");
        return w;
      } catch (const std::exception& ex) {
        if (name == "cuda-gl") throw;
        why = ex.what();
      }
    }
    if (name == "cuda-gl") throw Error("overlay writer cuda-gl is not available: " + why);
    say("overlay writer upload (auto: cuda-gl not usable: " + why + ")");
    return std::make_unique<UploadWriter>();
  }
#else
  if (name == "cuda-gl") throw Error("overlay writer cuda-gl is not available: this build has no CUDA");
  if (name == "auto") {
    say("overlay writer upload (auto: this build has no CUDA)");
    return std::make_unique<UploadWriter>();
  }
#endif
  (void)ctx;
  say("overlay writer upload (asked for upload)");
  return std::make_unique<UploadWriter>();
}

}  // namespace palpsim::render
