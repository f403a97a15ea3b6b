// What the render frame tests share (render_frame_test.cpp, render_output_test.cpp): the
// 2 mm phantom and one renderer of it, small frames, the renderer's camera as a
// projector, pixel comparisons, and a press over L3 with its markers.
#pragma once

#include <sys/resource.h>

#include <catch2/catch.hpp>

#include <cmath>
#include <cstdint>
#include <utility>
#include <vector>

#include "core/setting_names.h"
#include "deform/engine.h"
#include "render/frame_renderer.h"
#include "support/render_support.h"

namespace palpsim::test::render_frames {

using namespace palpsim::render;

using Rgb = std::vector<std::uint8_t>;

// the 2 mm phantom, prepared once for the whole executable
inline const PatientPtr& phantom_2mm() {
  static const PatientPtr p = test::prepared_phantom(2.0);
  return p;
}

// one renderer of the 2 mm phantom (made after the context)
inline FrameRenderer& renderer_2mm() {
  test::render_context();
  static FrameRenderer r(phantom_2mm());
  return r;
}

// a small frame of `r`'s overlay `id` (RGB8, rows top-down)
inline Rgb frame(FrameRenderer& r, FrameRenderer::OverlayId id, const ViewSettings& v, const FrameMarks& m) {
  FrameTimes t;
  r.render(id, v, m, t);
  Rgb rgb;
  r.read_rgb(rgb, t);
  return rgb;
}

// a 320 x 180 view of preset `p`
inline ViewSettings small_view(Preset p) {
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
inline long differing(const Rgb& a, const Rgb& b, int width, int x0, int y0, int x1, int y1, int tol = 0) {
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
inline DeformContact l3_press(const Patient& p, double depth_mm) {
  const Vec3 x = test::l3_skin_mm(p);
  return {x, x - Vec3{0, depth_mm, 0}};
}

// the CPU deformation with a VOI of 32 voxels (64 mm on the 2 mm phantom)
inline DeformConfig cpu_voi32() {
  DeformConfig dc;
  dc.settings.backend = DeformBackendChoice::kCpu;
  dc.settings.voi_edge = 32;
  return dc;
}

// the real CPU deformation of the 2 mm phantom under a 10 mm press over L3 (VOI of 32
// voxels, 64 mm), stepped once: J on its VOI for an overlay
struct PressedL3 {
  PressedL3() : engine(phantom_2mm(), cpu_voi32()), press(l3_press(*phantom_2mm(), 10)) {
    engine.step(press);
    REQUIRE(engine.deformed_brick() != nullptr);
  }
  DeformEngine engine;
  const DeformContact press;
};

// the markers of a contact: tip, proxy (the skin point), in contact
inline FrameMarks marks_of(const DeformContact& c) {
  FrameMarks m;
  m.has_tip = true;
  m.tip_mm = c.tip_mm;
  m.proxy_mm = c.skin_point_mm;
  m.contact = true;
  return m;
}

// the process's CPU time so far, user and system (s)
inline double cpu_s() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

}  // namespace palpsim::test::render_frames
