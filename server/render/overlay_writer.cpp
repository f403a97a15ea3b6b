#include "render/overlay_writer.h"

#include <string>

#include "core/error.h"
#include "render/backend_choice.h"

#ifdef PALPSIM_HAVE_CUDA
#include "cuda/render_interop.h"
#endif

namespace palpsim::render {
namespace {

// J from host memory by a sub-box upload (glTexSubImage3D).
class UploadWriter final : public OverlayWriter {
 public:
  const char* name() const override { return "upload"; }
  void write_batch(FrameRenderer& r, const std::vector<OverlayWrite>& writes) override {
    for (const OverlayWrite& w : writes) {
      const OverlaySource& src = w.src;
      // an empty VOI: the session is undeformed
      if (src.voi.count() <= 0) {
        r.clear_overlay(w.id);
        continue;
      }
      if (!src.host_j)
        throw Error("overlay writer upload: J of the VOI is not in host memory (the deformation handed over " +
                    std::string(src.device_j ? "only a device copy" : "nothing") + ")");
      r.upload_overlay(w.id, src.voi, src.host_j);
    }
  }
};

}  // namespace

std::unique_ptr<OverlayWriter> make_overlay_writer(OverlayWriterChoice choice, const EglContext& ctx,
                                                   std::string* note) {
  BackendChoice<OverlayWriter, OverlayWriterChoice> c{"overlay writer", OverlayWriterChoice::kUpload,
                                                      OverlayWriterChoice::kCudaGl, "upload", nullptr,
                                                      [] { return std::make_unique<UploadWriter>(); }};
#ifdef PALPSIM_HAVE_CUDA
  c.make_gpu = [] { return cuda::make_cuda_overlay_writer(); };
#endif
  return choose_backend(c, choice, ctx, note);
}

}  // namespace palpsim::render
