// The render module on whatever OpenGL EGL gives (llvmpipe in CI, no GPU): the context,
// frames of the 2 mm phantom (not blank, bone brighter than soft tissue, a deformation
// changing only what is near it, clearing it restoring the exact frame), the overlay
// texture, the framebuffer, JPEG, the encoder and writer factories, and a rotated grid.
// Without any EGL the tests fail with EGL's message (CI machines have Mesa).
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
#include "support/render_support.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
using namespace palpsim::render;

namespace {

using Rgb = std::vector<std::uint8_t>;

// the 2 mm phantom, prepared once for the whole executable
const PatientPtr& phantom_2mm() {
  static const PatientPtr p = test::render_phantom(2.0);
  return p;
}

// one renderer of the 2 mm phantom (made after the context)
FrameRenderer& renderer_2mm() {
  test::render_context();
  static FrameRenderer r(phantom_2mm());
  return r;
}

// a small frame of `r`'s overlay `id` (RGB8, rows top-down)
Rgb frame(FrameRenderer& r, FrameRenderer::OverlayId id, const ViewSettings& v, const FrameMarks& m) {
  FrameTimes t;
  r.render(id, v, m, t);
  Rgb rgb;
  r.read_rgb(rgb, t);
  return rgb;
}

ViewSettings small_view(Preset p) {
  ViewSettings v;
  v.width = 320;
  v.height = 180;
  v.preset = p;
  return v;
}

// The camera of view.h as the renderer builds it: the pixel (x, y) of the 3D view where
// a physical point appears, for a view of `v` looking at `target` (mm).
struct Projector {
  Vec3 eye, fwd, right, up;
  double tan_h = 0, aspect = 0;
  int view_w = 0, h = 0;
  Projector(const Grid& g, const ViewSettings& v, const Vec3& target) {
    const double pi = 3.14159265358979323846, half = 15 * pi / 180;
    const Vec3 ext{g.size.x * g.spacing_mm.x, g.size.y * g.spacing_mm.y, g.size.z * g.spacing_mm.z};
    const double dist = 0.5 * norm(ext) / std::sin(half);
    const double az = v.azimuth_deg * pi / 180, el = v.elevation_deg * pi / 180;
    const Vec3 to_eye{std::sin(az) * std::cos(el), std::cos(az) * std::cos(el), std::sin(el)};
    eye = target + to_eye * dist;
    fwd = -to_eye;
    right = cross(fwd, Vec3{0, 0, 1});
    right = right / norm(right);
    up = cross(right, fwd);
    tan_h = std::tan(half) / v.zoom;
    h = v.height;
    view_w = v.width - v.height / 3;
    aspect = double(view_w) / h;
  }
  // pixel column and row (may lie outside the view)
  std::pair<double, double> operator()(const Vec3& p) const {
    const Vec3 r = p - eye;
    const double z = dot(r, fwd);
    const double nx = dot(r, right) / (z * tan_h * aspect), ny = dot(r, up) / (z * tan_h);
    return {(nx + 1) * 0.5 * view_w, (1 - ny) * 0.5 * h};
  }
};

// pixels whose colours differ at all, within the rectangle [x0, x1) x [y0, y1)
long differing(const Rgb& a, const Rgb& b, int width, int x0, int y0, int x1, int y1, int tol = 0) {
  long n = 0;
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) {
      const std::size_t q = (std::size_t(y) * width + x) * 3;
      for (int c = 0; c < 3; ++c)
        if (std::abs(int(a[q + c]) - int(b[q + c])) > tol) {
          ++n;
          break;
        }
    }
  return n;
}

// the press over L3 on `p`: the skin point X and the tip `depth_mm` under it (anterior, -y)
DeformContact l3_press(const Patient& p, double depth_mm) {
  const Vec3 x = test::l3_skin_mm(p);
  return {x, x - Vec3{0, depth_mm, 0}};
}

// the CPU deformation with a VOI of 32 voxels (64 mm on the 2 mm phantom)
DeformConfig cpu_voi32() {
  DeformConfig dc;
  dc.settings.backend = DeformBackendChoice::kCpu;
  dc.settings.voi_edge = 32;
  return dc;
}

// the markers of a contact: tip, proxy (the skin point), in contact
FrameMarks marks_of(const DeformContact& c) {
  FrameMarks m;
  m.has_tip = true;
  m.tip_mm = c.tip_mm;
  m.proxy_mm = c.skin_point_mm;
  m.contact = true;
  return m;
}

double cpu_s() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

}  // namespace

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
  DeformEngine engine(p, cpu_voi32());
  const DeformContact press = l3_press(*p, 10);
  engine.step(press);
  REQUIRE(engine.deformed_brick() != nullptr);
  const Voi voi = engine.voi();
  const auto id = r.add_overlay({32, 32, 32});

  ViewSettings v = small_view(Preset::kSkin);
  const FrameMarks m = marks_of(press);
  const Rgb before = frame(r, id, v, m);
  auto writer = make_overlay_writer(OverlayWriterChoice::kUpload, test::render_context());
  OverlaySource src;
  src.voi = voi;
  src.host_j = engine.deformed_brick();
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

TEST_CASE("frames drawn into several targets, then encoded and written in batches, equal one at a time",
          "[render][frame][batch]") {
  FrameRenderer& r = renderer_2mm();
  const PatientPtr& p = phantom_2mm();
  // two sessions: one pressed (a real CPU deformation over L3), one undeformed
  DeformEngine engine(p, cpu_voi32());
  const DeformContact press = l3_press(*p, 10);
  engine.step(press);
  REQUIRE(engine.deformed_brick() != nullptr);
  const auto pressed = r.add_overlay({32, 32, 32}), plain = r.add_overlay({32, 32, 32});
  const FrameMarks m = marks_of(press);
  ViewSettings va = small_view(Preset::kSkin), vb = small_view(Preset::kBone);
  vb.width = 256;
  vb.height = 144;
  vb.azimuth_deg = -60;

  // the reference: each frame alone, its overlay written alone, in target 0
  auto writer = make_overlay_writer(OverlayWriterChoice::kUpload, test::render_context());
  OverlaySource src;
  src.voi = engine.voi();
  src.host_j = engine.deformed_brick();
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
  const PatientPtr p = test::render_phantom(1.0);
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
