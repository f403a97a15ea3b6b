// The frame renderer on the phantom, through whatever OpenGL EGL gives (llvmpipe in CI).
#include <catch2/catch.hpp>

#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "render/egl_context.h"
#include "render/frame_encoder.h"
#include "render/frame_renderer.h"
#include "support/render_support.h"

using namespace palpsim;
using namespace palpsim::render;

namespace {

void print_times(const char* what, const FrameTimes& t) {
  std::printf("%s: raycast %.1f ms, slices %.1f ms, composite %.1f ms, readback %.1f ms, encode %.1f ms\n", what,
              t.raycast_ms, t.slices_ms, t.composite_ms, t.readback_ms, t.encode_ms);
}

}  // namespace

// Writes PNGs of the 1 mm phantom at 1280x720 (bone and skin presets, the tip on the
// back over L3) for a person to look at: palpsim-test-render "[.snapshot]".
TEST_CASE("snapshot PNGs of the 1 mm phantom", "[.snapshot]") {
  EglContext& ctx = test::render_context();
  std::printf("GL: %s\n", ctx.describe().c_str());
  const PatientPtr p = test::render_phantom(1.0);
  FrameRenderer r(p);
  const auto id = r.add_overlay({64, 64, 64});
  FrameMarks marks;
  marks.has_tip = true;
  marks.tip_mm = test::l3_skin_mm(*p);
  marks.proxy_mm = marks.tip_mm;
  std::printf("tip at (%.1f, %.1f, %.1f) mm\n", marks.tip_mm.x, marks.tip_mm.y, marks.tip_mm.z);
  const char* dir = std::getenv("PALPSIM_RENDER_OUT");
  const std::string out = dir && *dir ? dir : "/tmp";
  for (Preset preset : {Preset::Bone, Preset::Skin, Preset::SoftTissue}) {
    ViewSettings v;
    v.preset = preset;
    if (const char* az = std::getenv("PALPSIM_RENDER_AZ")) v.azimuth_deg = std::atof(az);
    if (const char* el = std::getenv("PALPSIM_RENDER_EL")) v.elevation_deg = std::atof(el);
    if (const char* z = std::getenv("PALPSIM_RENDER_ZOOM")) v.zoom = std::atof(z);
    for (int size = 0; size < 2; ++size) {
      v.width = size ? 1280 : 320;
      v.height = size ? 720 : 180;
      FrameTimes warm, t;
      r.render(id, v, marks, warm);
      r.render(id, v, marks, t);
      std::vector<std::uint8_t> rgb;
      r.read_rgb(rgb, t);
      std::vector<std::uint8_t> jpeg;
      encode_jpeg_rgb(rgb.data(), v.width, v.height, 85, jpeg);
      const std::string name = out + "/render_phantom_" + preset_name(preset) + (size ? "" : "_small") + ".png";
      print_times(name.c_str(), t);
      test::write_png(name, rgb, v.width, v.height);
    }
  }
}
