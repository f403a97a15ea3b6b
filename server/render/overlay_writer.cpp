#include "render/overlay_writer.h"

#include <string>

#include "core/error.h"
#include "render/backend_choice.h"

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

OverlayWriterRegistry& overlay_writers() {
  static OverlayWriterRegistry registry;
  return registry;
}

std::unique_ptr<OverlayWriter> make_overlay_writer(OverlayWriterChoice choice, const EglContext& ctx,
                                                   std::string* note) {
  const BackendChoice<OverlayWriter, OverlayWriterChoice> c{
      "overlay writer", OverlayWriterChoice::kUpload, OverlayWriterChoice::kCudaGl, "upload",
      [] { return std::make_unique<UploadWriter>(); }, &overlay_writers()};
  return choose_backend(c, choice, ctx, note);
}

}  // namespace palpsim::render
