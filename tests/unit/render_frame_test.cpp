// The render module on whatever OpenGL EGL gives (llvmpipe in CI, no GPU): the context,
// frames of the 2 mm phantom (not blank, bone brighter than soft tissue, a deformation
// changing only what is near it, clearing it restoring the exact frame), the overlay
// texture, the framebuffer and a rotated grid. Targets, encoders and writers are in
// render_output_test.cpp. Without any EGL the tests fail with EGL's message (CI machines have Mesa).
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

// --- the context --------------------------------------------------------------------

TEST_CASE("the EGL context is OpenGL 4.5 core and names its renderer", "[render][egl]") {
  EglContext& ctx = test::render_context();
  INFO(ctx.describe());
  CHECK_FALSE(ctx.renderer().empty());
  CHECK_FALSE(ctx.vendor().empty());
  CHECK(ctx.version().find("4.") != std::string::npos);
  CHECK((ctx.platform() == "surfaceless" || ctx.platform().rfind("device ", 0) == 0));
  CHECK(ctx.describe().find(ctx.renderer()) != std::string::npos);
  GLint major = 0, minor = 0, profile = 0;
  glGetIntegerv(GL_MAJOR_VERSION, &major);
  glGetIntegerv(GL_MINOR_VERSION, &minor);
  glGetIntegerv(GL_CONTEXT_PROFILE_MASK, &profile);
  CHECK(major * 10 + minor >= 45);
  CHECK((profile & GL_CONTEXT_CORE_PROFILE_BIT) != 0);
  // llvmpipe, softpipe and swrast are software; NVIDIA only by its vendor string
  const bool sw = ctx.renderer().find("llvmpipe") != std::string::npos ||
                  ctx.renderer().find("softpipe") != std::string::npos;
  if (sw) CHECK(ctx.software());
  CHECK(ctx.nvidia() == (ctx.vendor().find("NVIDIA") != std::string::npos));
  // released and made current again, on the same thread
  ctx.release_current();
  CHECK(glGetString(GL_VERSION) == nullptr);
  ctx.make_current();
  CHECK(glGetString(GL_VERSION) != nullptr);
}

TEST_CASE("PALPSIM_EGL_DEVICE naming no device is refused with the range", "[render][egl]") {
  test::render_context();  // the test context stays current on this thread
  setenv("PALPSIM_EGL_DEVICE", "999", 1);
  std::string msg;
  try {
    EglContext::create();
  } catch (const Error& e) {
    msg = e.what();
  }
  unsetenv("PALPSIM_EGL_DEVICE");
  test::render_context().make_current();
  // "PALPSIM_EGL_DEVICE = '999' does not name one of the N EGL devices", or, where EGL
  // has no device platform, the list of what was tried
  CHECK_FALSE(msg.empty());
}

// --- frames of the phantom ----------------------------------------------------------

TEST_CASE("a phantom frame is not blank: body in the 3D view, tissue in the slices", "[render][frame]") {
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({32, 32, 32});
  for (Preset preset : {Preset::kSkin, Preset::kBone, Preset::kSoftTissue}) {
    const ViewSettings v = small_view(preset);
    const Rgb rgb = frame(r, id, v, FrameMarks{});
    REQUIRE(rgb.size() == std::size_t(320 * 180 * 3));
    const int vw = 320 - 60;
    // the body covers the middle of the 3D view (about 30 % of it at zoom 1): the
    // background is a dark grey gradient, so count pixels far brighter than it
    long lit = 0;
    for (int y = 0; y < 180; ++y)
      for (int x = 0; x < vw; ++x)
        if (test::mean_luma(rgb, 320, x, y, x + 1, y + 1) > 70) ++lit;
    INFO(setting_name(preset) << ": " << lit << " bright pixels in the 3D view");
    CHECK(lit > vw * 180 / 20);
    // each slice shows tissue (grey, not black) somewhere
    for (int s = 0; s < 3; ++s) CHECK(test::mean_luma(rgb, 320, vw + 2, s * 60 + 2, 318, s * 60 + 58) > 20);
  }
  r.remove_overlay(id);
}

TEST_CASE("a pixel's pick ray hits the body exactly where the frame shows it", "[render][frame][pick]") {
  // PickRequest's camera (render/camera.h) against the drawn frame: off-centre pixels of
  // an oblique view, so a mirrored or shifted pixel mapping lands on the wrong side of
  // the silhouette somewhere
  FrameRenderer& r = renderer_2mm();
  const Patient& p = *phantom_2mm();
  const auto id = r.add_overlay({32, 32, 32});
  ViewSettings v = small_view(Preset::kSkin);
  v.azimuth_deg = 35;
  v.elevation_deg = 25;
  v.zoom = 1.6;
  const Rgb rgb = frame(r, id, v, FrameMarks{});
  r.remove_overlay(id);
  const Vec3 lo = p.grid.to_physical({0, 0, 0});
  const Camera cam = orbit_camera(p.grid, v, frame_target(v, false, lo, body_center(p)));
  auto hits = [&](double x, double y) { return bool(first_body_hit(p, cam.eye, *pixel_ray(cam, x, y))); };
  // pixels 3 px or more inside or outside the silhouette on both axes (the skin is drawn
  // from the CT's partial-volume shell around the mask, which may reach a voxel, about
  // 1.5 px here, beyond it); the background is a grey gradient below luma 55
  long inside = 0, outside = 0, lit_inside = 0, dark_outside = 0;
  for (int y = 4; y < v.height - 4; y += 2)
    for (int x = 4; x < cam.view_w - 4; x += 2) {
      const double cx = x + 0.5, cy = y + 0.5;
      const bool h = hits(cx, cy);
      if (hits(cx - 3, cy) != h || hits(cx + 3, cy) != h || hits(cx, cy - 3) != h || hits(cx, cy + 3) != h) continue;
      // the orientation triad in the bottom left corner (6 px from the edges, edge H/7 but at least 32 px)
      if (x < 6 + 32 + 2 && y > v.height - 6 - 32 - 2) continue;
      const double luma = test::mean_luma(rgb, v.width, x, y, x + 1, y + 1);
      if (h) {
        ++inside;
        lit_inside += luma > 60;
      } else {
        ++outside;
        dark_outside += luma < 60;
      }
    }
  INFO(inside << " pixels inside (" << lit_inside << " lit), " << outside << " outside (" << dark_outside << " dark)");
  REQUIRE(inside > 200);
  REQUIRE(outside > 200);
  // every pixel the pick calls background is background; of the body's, all but a few
  // in the skin's own shadow (the light comes from above right) are lit
  CHECK(dark_outside == outside);
  CHECK(lit_inside >= inside * 95 / 100);
}

TEST_CASE("bone preset: the spine is brighter than the soft tissue beside it", "[render][frame]") {
  FrameRenderer& r = renderer_2mm();
  const Patient& p = *phantom_2mm();
  const auto id = r.add_overlay({32, 32, 32});
  const PhantomGeometry geo;
  // from straight behind (posterior), centred in the spinous process of L3
  ViewSettings v = small_view(Preset::kBone);
  v.azimuth_deg = 0;
  v.elevation_deg = 0;
  v.zoom = 2;
  v.look_at_tip = false;
  v.center_set = true;
  v.center_mm = geo.landmark("spinous_tip_L3") - Vec3{0, 6, 0};
  const Rgb rgb = frame(r, id, v, FrameMarks{});
  const Projector proj(p.grid, v, v.center_mm);
  // 3D view: the spine at the centre column against the back 60 mm to either side
  // (soft tissue only at the L3 level: the ribs are above, the iliac crests below)
  const auto [cx, cy] = proj(v.center_mm);
  const auto [lx, ly] = proj(v.center_mm + Vec3{60, 0, 0});
  const auto [rx, ry] = proj(v.center_mm - Vec3{60, 0, 0});
  auto patch = [&](double x, double y) { return test::mean_luma(rgb, 320, int(x) - 3, int(y) - 3, int(x) + 4, int(y) + 4); };
  const double spine = patch(cx, cy), left = patch(lx, ly), right = patch(rx, ry);
  INFO("3D view: spine " << spine << ", 60 mm left " << left << ", right " << right);
  // ivory bone against a faint haze: a margin of 40 grey levels is far from both
  CHECK(spine > left + 40);
  CHECK(spine > right + 40);
  // axial slice (top right, edge 60 px over 120 mm: 2 mm a pixel, screen right = +x):
  // the process at its centre against muscle 40 mm lateral; bone window W1500/L300
  // puts cancellous bone (300 HU) at ~128 and muscle (50 HU) at ~85
  const int s = 60, x0 = 320 - s;
  const double bone_px = test::mean_luma(rgb, 320, x0 + 29, 29, x0 + 32, 32);
  const double muscle_px = test::mean_luma(rgb, 320, x0 + 29 + 20, 29, x0 + 32 + 20, 32);
  INFO("axial slice: process " << bone_px << ", muscle " << muscle_px);
  CHECK(bone_px > muscle_px + 20);
  r.remove_overlay(id);
}

TEST_CASE("a deformed overlay changes the frame near the tip only; clearing it restores it", "[render][frame][overlay]") {
  FrameRenderer& r = renderer_2mm();
  const PatientPtr& p = phantom_2mm();
  // the real CPU deformation: a 10 mm press over L3, VOI of 32 voxels (64 mm)
  const PressedL3 l3;
  const DeformContact& press = l3.press;
  const Voi voi = l3.engine.voi();
  const auto id = r.add_overlay({32, 32, 32});

  ViewSettings v = small_view(Preset::kSkin);
  const FrameMarks m = marks_of(press);
  const Rgb before = frame(r, id, v, m);
  auto writer = make_overlay_writer(OverlayWriterChoice::kUpload, test::render_context());
  OverlaySource src;
  src.voi = voi;
  src.host_j = l3.engine.deformed_brick();
  writer->write(r, id, src);
  const Rgb after = frame(r, id, v, m);

  // the tip is the look-at point: the centre of the 3D view (260 x 180). The VOI box
  // (64 mm, plus the 16 mm where faint space is no longer skipped near it) spans about
  // 40 pixels there (2.8 mm a pixel at zoom 1): 60 pixels away nothing may change
  const int vw = 260, cx = vw / 2, cy = 90;
  const long near = differing(before, after, 320, cx - 30, cy - 30, cx + 30, cy + 30, 8);
  INFO("pixels near the tip that changed by more than 8 levels: " << near);
  CHECK(near >= 20);  // the dent in the skin
  long far = differing(before, after, 320, 0, 0, cx - 60, 180) + differing(before, after, 320, cx + 60, 0, vw, 180) +
             differing(before, after, 320, cx - 60, 0, cx + 60, cy - 60) +
             differing(before, after, 320, cx - 60, cy + 60, cx + 60, 180);
  CHECK(far == 0);
  // slices: the dent shows around the tip; columns whose sample points lie a voxel or
  // more outside the VOI are untouched (60 px slices of 120 mm: 2 mm a pixel, 1 voxel;
  // screen right is +x, i, on the axial and coronal slices and +y, j, on the sagittal)
  const int s = 60, x0 = 320 - s;
  long slice_near = 0;
  for (int k = 0; k < 3; ++k) slice_near += differing(before, after, 320, x0 + 14, k * s + 14, x0 + 46, k * s + 46);
  CHECK(slice_near > 20);
  const Vec3 c = p->grid.to_index(press.tip_mm);
  for (int k = 0; k < 3; ++k) {
    const int axis = k == 2 ? 1 : 0;
    long untouched_columns = 0;
    for (int u = 0; u < s; ++u) {
      const double idx = c[axis] + (u + 0.5 - 0.5 * s);
      if (idx > voi.lo[axis] - 1.5 && idx < voi.lo[axis] + voi.size[axis] + 0.5) continue;
      ++untouched_columns;
      CHECK(differing(before, after, 320, x0 + u, k * s, x0 + u + 1, k * s + s) == 0);
    }
    CHECK(untouched_columns >= 10);
  }

  // cleared: bit for bit the undeformed frame; an empty VOI through the writer too
  r.clear_overlay(id);
  CHECK(frame(r, id, v, m) == before);
  writer->write(r, id, src);
  CHECK(frame(r, id, v, m) != before);
  writer->write(r, id, OverlaySource{});
  CHECK(frame(r, id, v, m) == before);
  // set_overlay_box shows what the texture holds (as after a CUDA-GL write)
  r.set_overlay_box(id, voi);
  CHECK(frame(r, id, v, m) == after);
  r.remove_overlay(id);
}

TEST_CASE("the overlay texture holds what was uploaded", "[render][overlay]") {
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({24, 20, 16});
  const Voi voi{{40, 50, 30}, {21, 17, 13}};
  std::vector<float> j(std::size_t(voi.count()));
  for (std::size_t n = 0; n < j.size(); ++n) j[n] = float(n % 997) - 500.f + 0.25f;
  r.upload_overlay(id, voi, j.data());
  const GLuint tex = r.overlay_texture(id);
  REQUIRE(tex != 0);
  GLint w = 0, h = 0, d = 0, fmt = 0;
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_WIDTH, &w);
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_HEIGHT, &h);
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_DEPTH, &d);
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_INTERNAL_FORMAT, &fmt);
  CHECK(w == 24);
  CHECK(h == 20);
  CHECK(d == 16);
  CHECK(fmt == GL_R32F);
  // VOI voxel (i, j, k) at texel (i, j, k): exactly the floats uploaded
  std::vector<float> back(j.size(), 0.f);
  glPixelStorei(GL_PACK_ALIGNMENT, 4);
  glGetTextureSubImage(tex, 0, 0, 0, 0, voi.size.x, voi.size.y, voi.size.z, GL_RED, GL_FLOAT,
                       GLsizei(back.size() * sizeof(float)), back.data());
  CHECK(glGetError() == GL_NO_ERROR);
  CHECK(std::memcmp(back.data(), j.data(), j.size() * sizeof(float)) == 0);
  // a VOI larger than the overlay, or leaving the grid, is refused
  CHECK_THROWS_AS(r.upload_overlay(id, Voi{{0, 0, 0}, {25, 20, 16}}, j.data()), Error);
  const Vec3i g = r.patient().grid.size;
  CHECK_THROWS_AS(r.set_overlay_box(id, Voi{{g.x - 10, 0, 0}, {24, 20, 16}}), Error);
  CHECK_THROWS_AS(r.overlay_texture(id + 1000), Error);
  CHECK(r.bytes() >= std::size_t(24 * 20 * 16 * 4));
  r.remove_overlay(id);
  CHECK_THROWS_AS(r.overlay_texture(id), Error);
}

TEST_CASE("the framebuffer follows the frame size; bad views are refused", "[render][frame]") {
  FrameRenderer& r = renderer_2mm();
  const auto id = r.add_overlay({8, 8, 8});
  ViewSettings v = small_view(Preset::kBone);
  Rgb a = frame(r, id, v, FrameMarks{});
  CHECK(r.width() == 320);
  CHECK(r.height() == 180);
  const unsigned tex = r.color_texture();
  CHECK(tex != 0);
  // the same size again keeps the texture; a new size gets a new one
  frame(r, id, v, FrameMarks{});
  CHECK(r.color_texture() == tex);
  v.width = 200;
  v.height = 96;
  a = frame(r, id, v, FrameMarks{});
  CHECK(a.size() == std::size_t(200 * 96 * 3));
  CHECK(r.width() == 200);
  CHECK(r.height() == 96);
  // a view check_view refuses never reaches GL
  v.width = 0;
  CHECK_THROWS_AS(frame(r, id, v, FrameMarks{}), Error);
  v.width = 200;
  v.zoom = std::nan("");
  CHECK_THROWS_AS(frame(r, id, v, FrameMarks{}), Error);
  r.remove_overlay(id);
}

// --- a grid with a rotated direction matrix -----------------------------------------

TEST_CASE("a rotated patient grid renders the same 3D view as an axis-aligned one", "[render][frame]") {
  test::render_context();
  // a ball of tissue with an off-centre bone ball, on a 48^3 grid at 2 mm
  const int n = 48;
  const Vec3 c{47, 47, 47}, b{60, 40, 50};
  auto skin = [c](const Vec3& x) { return norm(x - c) - 40.0; };
  auto bone = [b](const Vec3& x) { return norm(x - b) - 12.0; };
  auto straight = test::make_patient(n, 2.0, skin, bone);
  // the same voxels on a grid whose axes are rotated: i along -y, j along +x, k along +z
  // (an orthonormal direction matrix), with the origin put where voxel (0,0,0) now lies
  auto turned = std::make_shared<Patient>(*straight);
  Grid& g = turned->grid;
  g.direction = {0, 1, 0, -1, 0, 0, 0, 0, 1};
  g.origin_mm = {0, 2.0 * (n - 1), 0};
  for (auto* vol : {&turned->intensity.grid, &turned->body.grid}) *vol = g;
  for (int k = 0; k < n; ++k)
    for (int j = 0; j < n; ++j)
      for (int i = 0; i < n; ++i) {
        // physical point of the turned voxel (i, j, k) is straight's voxel (j, n-1-i, k)
        turned->intensity.at(i, j, k) = straight->intensity.at(j, n - 1 - i, k);
        turned->body.at(i, j, k) = straight->body.at(j, n - 1 - i, k);
      }
  REQUIRE(norm(turned->grid.to_physical({3, 5, 7}) - straight->grid.to_physical({5, double(n - 1 - 3), 7})) < 1e-9);
  FrameRenderer ra(straight), rb(turned);
  const auto ia = ra.add_overlay({4, 4, 4}), ib = rb.add_overlay({4, 4, 4});
  for (Preset preset : {Preset::kSkin, Preset::kBone}) {
    ViewSettings v = small_view(preset);
    v.azimuth_deg = 50;
    v.elevation_deg = 20;
    v.look_at_tip = false;
    v.center_set = true;
    v.center_mm = c;
    const Rgb a = frame(ra, ia, v, FrameMarks{}), bb = frame(rb, ib, v, FrameMarks{});
    // the same physical samples along the same rays: equal up to float rounding in the
    // index-space ray set-up (a few grey levels on a handful of silhouette pixels)
    const long off = differing(a, bb, 320, 0, 0, 260, 180, 3);
    INFO(setting_name(preset) << ": " << off << " of 46800 pixels differ by more than 3 levels");
    CHECK(off < 100);
    // and the view is not empty (the skin-coloured ball is there)
    if (preset == Preset::kSkin) CHECK(test::mean_luma(a, 320, 100, 60, 160, 120) > 60);
  }
}

TEST_CASE("a grid larger than GL_MAX_3D_TEXTURE_SIZE is refused by name", "[render][frame]") {
  test::render_context();
  GLint max3d = 0;
  glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max3d);
  REQUIRE(max3d > 0);
  auto p = std::make_shared<Patient>();
  p->grid.size = {2, 2, max3d + 1};
  p->intensity = Volume<float>(p->grid, 0.f);
  p->body = Volume<std::uint8_t>(p->grid, 1);
  try {
    FrameRenderer r(p);
    FAIL("no error for a grid of " << max3d + 1 << " slices");
  } catch (const Error& e) {
    CHECK(std::string(e.what()).find("GL_MAX_3D_TEXTURE_SIZE") != std::string::npos);
  }
}
