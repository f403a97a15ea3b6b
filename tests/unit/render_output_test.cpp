// What becomes of the render module's frames on whatever OpenGL EGL gives (llvmpipe in
// CI): several targets drawn, encoded and written in batches equal to one at a time, the
// last frame let go with no viewer left, JPEG, the encoder and writer factories, and
// snapshot PNGs of the 1 mm phantom for people. Without any EGL the tests fail with EGL's
// message (CI machines have Mesa).
#define GL_GLEXT_PROTOTYPES
#include <GL/glcorearb.h>
#include <catch2/catch.hpp>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "core/error.h"
#include "core/setting_names.h"
#include "deform/engine.h"
#include "prep/phantom.h"
#include "render/camera.h"
#include "render/egl_context.h"
#include "render/frame_encoder.h"
#include "render/frame_renderer.h"
#include "render/overlay_writer.h"
#include "support/render_frames.h"
#include "support/render_support.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
using namespace palpsim::render;
using namespace palpsim::test::render_frames;

TEST_CASE("frames drawn into several targets, then encoded and written in batches, equal one at a time",
          "[render][frame][batch]") {
  FrameRenderer& r = renderer_2mm();
  // two sessions: one pressed (a real CPU deformation over L3), one undeformed
  const PressedL3 l3;
  const DeformContact& press = l3.press;
  const auto pressed = r.add_overlay({32, 32, 32}), plain = r.add_overlay({32, 32, 32});
  const FrameMarks m = marks_of(press);
  ViewSettings va = small_view(Preset::kSkin), vb = small_view(Preset::kBone);
  vb.width = 256;
  vb.height = 144;
  vb.azimuth_deg = -60;

  // the reference: each frame alone, its overlay written alone, in target 0
  auto writer = make_overlay_writer(OverlayWriterChoice::kUpload, test::render_context());
  OverlaySource src;
  src.voi = l3.engine.voi();
  src.host_j = l3.engine.deformed_brick();
  writer->write(r, pressed, src);
  writer->write(r, plain, OverlaySource{});
  const Rgb ref_a = frame(r, pressed, va, m), ref_b = frame(r, plain, vb, FrameMarks{});
  auto enc = make_frame_encoder(JpegEncoderChoice::kCpu, test::render_context());
  std::vector<std::uint8_t> jpeg_a, jpeg_b;
  FrameTimes t;
  r.render(pressed, va, m, t);
  enc->encode(r, 80, jpeg_a, t);
  r.render(plain, vb, FrameMarks{}, t);
  enc->encode(r, 60, jpeg_b, t);

  // the batch: both overlays cleared, then written in one call (the pressed one twice:
  // the last write wins), both frames drawn into their own targets, then encoded at once
  r.clear_overlay(pressed);
  writer->write_batch(r, {OverlayWrite{pressed, OverlaySource{}}, OverlayWrite{plain, OverlaySource{}},
                          OverlayWrite{pressed, src}});
  const auto ta = r.add_target(), tb = r.add_target();
  CHECK(ta != tb);
  CHECK(ta != 0);
  r.draw(pressed, ta, va, m);
  r.draw(plain, tb, vb, FrameMarks{});
  CHECK(r.width(ta) == 320);
  CHECK(r.height(tb) == 144);
  CHECK(r.color_texture(ta) != r.color_texture(tb));
  FrameTimes fa, fb;
  Rgb a, b;
  r.read_rgb(ta, a, fa);
  r.read_rgb(tb, b, fb);
  CHECK(a == ref_a);
  CHECK(b == ref_b);
  std::vector<std::uint8_t> out_a, out_b;
  enc->encode_batch(r, {EncodeJob{ta, 80, &out_a, &fa}, EncodeJob{tb, 60, &out_b, &fb}});
  CHECK(out_a == jpeg_a);
  CHECK(out_b == jpeg_b);
  CHECK(fa.encode_ms > 0);
  // stage times come once per drawn frame
  r.draw_times(ta, fa);
  CHECK(fa.raycast_ms > 0);
  const double once = fa.raycast_ms;
  r.draw_times(ta, fa);
  CHECK(fa.raycast_ms == once);
  // the bytes count every framebuffer; a removed target is gone, target 0 stays
  const std::size_t with = r.bytes();
  r.remove_target(tb);
  CHECK(r.bytes() == with - std::size_t(256 * 144 * 4));
  CHECK_THROWS_AS(r.color_texture(tb), Error);
  CHECK_THROWS_AS(r.draw(plain, tb, vb, FrameMarks{}), Error);
  CHECK_THROWS_AS(r.remove_target(0), Error);
  CHECK_THROWS_AS(enc->encode_batch(r, {EncodeJob{ta, 80, nullptr, &fa}}), Error);
  r.remove_target(ta);
  r.remove_overlay(pressed);
  r.remove_overlay(plain);
}

TEST_CASE("with no viewer left the renderer and encoder let go of the last frame; the next one is the same",
          "[render][frame]") {
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({8, 8, 8});
  const Rgb before = frame(r, id, small_view(Preset::kBone), FrameMarks{});
  // a 3840x2160 frame drawn into a target of its own and encoded, the target then removed
  ViewSettings big = small_view(Preset::kBone);
  big.width = 3840;
  big.height = 2160;
  big.zoom = 0.25;
  auto enc = make_frame_encoder(JpegEncoderChoice::kCpu, test::render_context());
  const auto t = r.add_target();
  r.draw(id, t, big, FrameMarks{});
  std::vector<std::uint8_t> jpeg;
  FrameTimes times;
  enc->encode_batch(r, {EncodeJob{t, 80, &jpeg, &times}});
  REQUIRE_FALSE(jpeg.empty());
  r.remove_target(t);
  // resident memory (bytes) of this process
  auto resident = [] {
    unsigned long long size = 0, pages = 0;
    std::FILE* f = std::fopen("/proc/self/statm", "r");
    REQUIRE(f);
    const int n = std::fscanf(f, "%llu %llu", &size, &pages);
    std::fclose(f);
    REQUIRE(n == 2);
    return double(pages) * double(sysconf(_SC_PAGESIZE));
  };
  const double held = resident();
  r.release_frame_state();
  const double released = resident();
  enc->release_buffers();
  // llvmpipe keeps the last framebuffer's texture (3840 x 2160 x 4 bytes, 33 MB, a block
  // mapped for itself, so given back the moment it is freed) until the next draw; a GPU
  // keeps it in its own memory
  if (test::render_context().renderer().find("llvmpipe") != std::string::npos) {
    INFO("resident " << held / 1048576 << " MB before, " << released / 1048576 << " MB after");
    CHECK(held - released >= 30.0 * 1048576);
  }
  // the next frames are drawn as before, the encoder makes its buffers again
  CHECK(frame(r, id, small_view(Preset::kBone), FrameMarks{}) == before);
  std::vector<std::uint8_t> again;
  enc->encode(r, 80, again, times);
  CHECK_FALSE(again.empty());
  r.remove_overlay(id);
}

TEST_CASE("frame stage times are measured", "[render][frame]") {
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({8, 8, 8});
  FrameTimes t;
  r.render(id, small_view(Preset::kBone), FrameMarks{}, t);
  CHECK(t.raycast_ms > 0);
  CHECK(t.slices_ms > 0);
  CHECK(t.composite_ms > 0);
  CHECK(t.readback_ms == 0);
  Rgb rgb;
  r.read_rgb(rgb, t);
  CHECK(t.readback_ms > 0);
  r.remove_overlay(id);
}

// --- JPEG, encoders and writers -----------------------------------------------------

TEST_CASE("JPEG encode and decode round-trip a frame", "[render][jpeg]") {
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({8, 8, 8});
  const Rgb rgb = frame(r, id, small_view(Preset::kBone), FrameMarks{});
  std::vector<std::uint8_t> jpeg;
  encode_jpeg_rgb(rgb.data(), 320, 180, 90, jpeg);
  REQUIRE(jpeg.size() > 100);
  CHECK(jpeg[0] == 0xFF);
  CHECK(jpeg[1] == 0xD8);
  Rgb back;
  int w = 0, h = 0;
  REQUIRE(decode_jpeg_rgb(jpeg.data(), jpeg.size(), back, w, h));
  CHECK(w == 320);
  CHECK(h == 180);
  REQUIRE(back.size() == rgb.size());
  double err = 0;
  for (std::size_t n = 0; n < rgb.size(); ++n) err += std::abs(int(rgb[n]) - int(back[n]));
  err /= double(rgb.size());
  INFO("mean absolute error " << err << " grey levels");
  // quality 90 with 4:2:0 chroma: about 1-2 levels on average; the coloured one-pixel
  // frame lines and cut lines lose most (chroma at half resolution), hence 4
  CHECK(err < 4.0);
  // not a JPEG
  const std::uint8_t junk[16] = {1, 2, 3};
  CHECK_FALSE(decode_jpeg_rgb(junk, sizeof junk, back, w, h));
  CHECK_FALSE(decode_jpeg_rgb(jpeg.data(), 0, back, w, h));

  // the CPU encoder: readback and TurboJPEG, the same bytes as encoding the readback
  std::string note;
  auto enc = make_frame_encoder(JpegEncoderChoice::kCpu, test::render_context(), &note);
  CHECK(std::string(enc->name()) == "turbojpeg");
  CHECK_FALSE(note.empty());
  FrameTimes t;
  std::vector<std::uint8_t> out;
  enc->encode(r, 90, out, t);
  CHECK(out == jpeg);
  CHECK(t.readback_ms > 0);
  CHECK(t.encode_ms > 0);
  CHECK_THROWS_AS(enc->encode(r, 0, out, t), Error);
  r.remove_overlay(id);
}

TEST_CASE("encoder and writer factories: names, auto, and what this machine lacks", "[render][jpeg][overlay]") {
  EglContext& ctx = test::render_context();
  std::string note;
  CHECK_THROWS_AS(make_frame_encoder(static_cast<JpegEncoderChoice>(7), ctx), Error);
  CHECK_THROWS_AS(make_overlay_writer(static_cast<OverlayWriterChoice>(7), ctx), Error);
  CHECK(std::string(make_frame_encoder(JpegEncoderChoice::kCpu, ctx)->name()) == "turbojpeg");
  CHECK(std::string(make_overlay_writer(OverlayWriterChoice::kUpload, ctx, &note)->name()) == "upload");
  if (!ctx.nvidia()) {
    // no NVIDIA GL device (or no CUDA in this build): auto takes the CPU paths, and the
    // GPU ones are refused with the reason
    CHECK(std::string(make_frame_encoder(JpegEncoderChoice::kAuto, ctx, &note)->name()) == "turbojpeg");
    CHECK(note.find("auto") != std::string::npos);
    CHECK(std::string(make_overlay_writer(OverlayWriterChoice::kAuto, ctx, &note)->name()) == "upload");
    try {
      make_frame_encoder(JpegEncoderChoice::kNvjpeg, ctx);
      FAIL("nvjpeg without an NVIDIA GPU");
    } catch (const Error& e) {
      CHECK(std::string(e.what()).find("not available") != std::string::npos);
    }
    try {
      make_overlay_writer(OverlayWriterChoice::kCudaGl, ctx);
      FAIL("cuda-gl without an NVIDIA GPU");
    } catch (const Error& e) {
      CHECK(std::string(e.what()).find("not available") != std::string::npos);
    }
  }
  // the upload writer needs J in host memory for a deformed VOI
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({8, 8, 8});
  auto w = make_overlay_writer(OverlayWriterChoice::kUpload, ctx);
  OverlaySource src;
  src.voi = Voi{{10, 10, 10}, {8, 8, 8}};
  CHECK_THROWS_AS(w->write(r, id, src), Error);
  r.remove_overlay(id);
}

// --- snapshots for people -----------------------------------------------------------

// Writes PNGs of the 1 mm phantom at 1280x720 (bone and skin presets, the tip on the
// back's skin over L3) and prints the stage times: palpsim-test-render "[.snapshot]".
// $PALPSIM_RENDER_OUT picks the folder (default /tmp).
TEST_CASE("snapshot PNGs of the 1 mm phantom", "[.snapshot]") {
  EglContext& ctx = test::render_context();
  std::printf("GL: %s\n", ctx.describe().c_str());
  const PatientPtr p = test::prepared_phantom(1.0);
  const double c0 = cpu_s();
  FrameRenderer r(p);
  std::printf("renderer set up in %.0f ms CPU, %.0f MB of textures\n", (cpu_s() - c0) * 1e3, r.bytes() / 1e6);
  const auto id = r.add_overlay({64, 64, 64});
  FrameMarks marks;
  marks.has_tip = true;
  marks.tip_mm = test::l3_skin_mm(*p);
  marks.proxy_mm = marks.tip_mm;
  std::printf("tip at (%.1f, %.1f, %.1f) mm\n", marks.tip_mm.x, marks.tip_mm.y, marks.tip_mm.z);
  const char* dir = std::getenv("PALPSIM_RENDER_OUT");
  const std::string out = dir && *dir ? dir : "/tmp";
  auto shoot = [&](const ViewSettings& v, const std::string& name) {
    // the fastest of three frames (the machine may be shared), after one to warm up
    FrameTimes warm, t;
    r.render(id, v, marks, warm);
    const double cpu0 = cpu_s();
    for (int n = 0; n < 3; ++n) {
      FrameTimes f;
      r.render(id, v, marks, f);
      if (n == 0 || f.raycast_ms < t.raycast_ms) t = f;
    }
    const double cpu_ms = (cpu_s() - cpu0) / 3 * 1e3;
    Rgb rgb;
    r.read_rgb(rgb, t);
    std::vector<std::uint8_t> jpeg;
    FrameTimes e;
    auto enc = make_frame_encoder(JpegEncoderChoice::kCpu, ctx);
    enc->encode(r, v.jpeg_quality, jpeg, e);
    t.encode_ms = e.encode_ms;
    std::printf("%-44s %4dx%-4d raycast %7.1f  slices %5.1f  composite %5.1f  readback %5.1f  encode %5.1f ms"
                "  (CPU %.0f ms a frame)\n",
                name.c_str(), v.width, v.height, t.raycast_ms, t.slices_ms, t.composite_ms, t.readback_ms, t.encode_ms,
                cpu_ms);
    if (!name.empty()) test::write_png(out + "/" + name, rgb, v.width, v.height);
  };
  for (Preset preset : {Preset::kBone, Preset::kSkin, Preset::kSoftTissue}) {
    ViewSettings v;
    v.preset = preset;
    if (const char* z = std::getenv("PALPSIM_RENDER_ZOOM")) v.zoom = std::atof(z);
    v.width = 320;
    v.height = 180;
    shoot(v, std::string("render_phantom_") + setting_name(preset) + "_small.png");
    v.width = 1280;
    v.height = 720;
    shoot(v, std::string("render_phantom_") + setting_name(preset) + ".png");
  }
  // a 10 mm press over L3 with the CPU deformation (VOI 64), skin and bone
  DeformConfig dc;
  dc.settings.backend = DeformBackendChoice::kCpu;
  DeformEngine engine(p, dc);
  const DeformContact press = l3_press(*p, 10);
  engine.step(press);
  r.upload_overlay(id, engine.voi(), engine.deformed_brick());
  marks.tip_mm = press.tip_mm;
  marks.proxy_mm = press.skin_point_mm;
  marks.contact = true;
  for (Preset preset : {Preset::kSkin, Preset::kBone}) {
    ViewSettings v;
    v.preset = preset;
    v.zoom = 3;
    v.show_proxy = true;
    shoot(v, std::string("render_phantom_pressed_") + setting_name(preset) + ".png");
  }
}
