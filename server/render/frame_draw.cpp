// FrameRenderer's drawing (frame_renderer.h): one frame's 3D view, slices and composite,
// each a step on the frame's shared layout and camera (FrameRenderer::Impl::Frame).
#include <algorithm>
#include <cmath>
#include <string>

#include "core/error.h"
#include "render/camera.h"
#include "render/frame_renderer_impl.h"
#include "render/transfer_function.h"

namespace palpsim::render {
namespace {

constexpr float kFaintTauPerMm = 0.004f;  // extinction below which space is faint enough to skip

// the highest intensity (HU) below which a preset's extinction stays under kFaintTauPerMm
float faint_below_hu(Preset p) {
  const TransferFunction tf = make_transfer_function(p);
  for (int n = 0; n < kTfSize; ++n)
    if (tf.tau[n] >= kFaintTauPerMm) return n > 0 ? TransferFunction::hu_of(n - 1) : kTfMinHu - 1;
  return kTfMaxHu;
}

// viewport uniform and GL viewport of a rectangle whose top row is image row y0
void set_viewport(Program& p, int x0, int y0, int w, int h) {
  glViewport(x0, y0, w, h);
  p.set("u_viewport", float(x0), float(y0), float(w), float(h));
}

// How one slice lies on the screen: the grid axis it holds fixed, and the grid axes
// (with signs) that run right and down on the screen.
struct SliceAxes {
  int fixed = 2;
  int right_axis = 0, down_axis = 1;
  double right_sign = 1, down_sign = 1;
};

// Radiological orientation, chosen per grid by the closest grid axis: axial (k plane)
// seen from the feet with anterior up (screen right = patient's left +x, down =
// posterior +y); coronal (j plane) seen from the front with superior up (right = +x,
// down = -z); sagittal (i plane) seen from the patient's left with anterior on the
// left (right = posterior +y, down = -z).
SliceAxes slice_axes(const Grid& g, int fixed, const Vec3& want_right, const Vec3& want_down) {
  SliceAxes s;
  s.fixed = fixed;
  const int a = (fixed + 1) % 3, b = (fixed + 2) % 3;
  auto axis = [&](int n) {
    Vec3 e{0, 0, 0};
    e[n] = 1;
    return g.axes_to_physical(e);
  };
  const double ra = dot(axis(a), want_right), rb = dot(axis(b), want_right);
  s.right_axis = std::fabs(ra) >= std::fabs(rb) ? a : b;
  s.down_axis = s.right_axis == a ? b : a;
  s.right_sign = dot(axis(s.right_axis), want_right) < 0 ? -1 : 1;
  s.down_sign = dot(axis(s.down_axis), want_down) < 0 ? -1 : 1;
  return s;
}

// the frame colours of the slices (axial red, coronal green, sagittal yellow, as 3D Slicer)
const Vec3 kSliceColor[3] = {{0.90, 0.28, 0.22}, {0.35, 0.80, 0.35}, {0.95, 0.82, 0.25}};
// marker colours: tip out of contact, tip in contact, proxy
const Vec3 kTipColor{0.25, 0.95, 0.35}, kTipContactColor{1.0, 0.55, 0.10}, kProxyColor{0.30, 0.55, 1.0};

// which slice (0 axial, 1 coronal, 2 sagittal) holds grid axis n fixed
int slice_of_axis(int n) { return 2 - n; }

// The pixels of a w x h view (row 0 at the top) where a VOI box grown by `margin_vox`
// voxels can appear, for a camera at `eye` looking along `fwd` whose frame edges lie at
// fwd + right and fwd + up (mm): x, y (top row), width, height, 2 pixels to spare.
// False when it covers nothing; the whole view when the camera is in or near the box.
bool voi_rect(const Grid& g, const Voi& voi, double margin_vox, const Vec3& eye, const Vec3& fwd, const Vec3& right,
              const Vec3& up, int w, int h, int rect[4]) {
  double x0 = 1e30, y0 = 1e30, x1 = -1e30, y1 = -1e30;
  const double r2 = dot(right, right), u2 = dot(up, up);
  for (int c = 0; c < 8; ++c) {
    const Vec3 ijk{(c & 1) ? voi.lo.x + voi.size.x - 0.5 + margin_vox : voi.lo.x - 0.5 - margin_vox,
                   (c & 2) ? voi.lo.y + voi.size.y - 0.5 + margin_vox : voi.lo.y - 0.5 - margin_vox,
                   (c & 4) ? voi.lo.z + voi.size.z - 0.5 + margin_vox : voi.lo.z - 0.5 - margin_vox};
    const Vec3 q = g.to_physical(ijk) - eye;
    const double z = dot(q, fwd);
    if (z < 1e-3) {
      // a corner beside or behind the camera: any pixel may see the box
      x0 = y0 = 0;
      x1 = w;
      y1 = h;
      break;
    }
    const double nx = dot(q, right) / (r2 * z), ny = dot(q, up) / (u2 * z);  // -1..1 across the view
    const double px = (nx + 1) * 0.5 * w, py = (1 - ny) * 0.5 * h;
    x0 = std::min(x0, px);
    x1 = std::max(x1, px);
    y0 = std::min(y0, py);
    y1 = std::max(y1, py);
  }
  const int ix0 = std::max(0, int(std::floor(x0)) - 2), iy0 = std::max(0, int(std::floor(y0)) - 2);
  const int ix1 = std::min(w, int(std::ceil(x1)) + 2), iy1 = std::min(h, int(std::ceil(y1)) + 2);
  if (ix1 <= ix0 || iy1 <= iy0) return false;
  rect[0] = ix0;
  rect[1] = iy0;
  rect[2] = ix1 - ix0;
  rect[3] = iy1 - iy0;
  return true;
}

}  // namespace

// what the steps of one frame share: the view, its layout, its camera and the slice axes
struct FrameRenderer::Impl::Frame {
  const ViewSettings& view;
  const FrameMarks& marks;
  const Overlay& ov;
  Target& tg;
  const Grid& g;
  // layout: the 3D view on the left, slices of edge s stacked on the right
  int W = 0, H = 0, view_w = 0, s = 0;
  Vec3 target;  // the look-at point and slice centre (mm)
  Camera cam;
  double mm_per_px = 0;  // in the 3D view at the target's distance
  // the slices: axial (k), coronal (j), sagittal (i) through the target, top to bottom
  SliceAxes axes[3];
  double slice_mm_per_px = 0;
  Vec3 center_idx;

  Frame(const ViewSettings& v, const FrameMarks& mk, const Overlay& o, Target& t, const Grid& grid,
        const Vec3& body_center_mm)
      : view(v), marks(mk), ov(o), tg(t), g(grid) {
    W = view.width, H = view.height, view_w = view_width(W, H), s = W - view_w;
    target = frame_target(view, marks.has_tip, marks.tip_mm, body_center_mm);
    cam = orbit_camera(g, view, target);
    mm_per_px = 2 * cam.dist_mm * cam.tan_h / H;
    axes[0] = slice_axes(g, 2, {1, 0, 0}, {0, 1, 0});
    axes[1] = slice_axes(g, 1, {1, 0, 0}, {0, 0, -1});
    axes[2] = slice_axes(g, 0, {0, 1, 0}, {0, 0, -1});
    slice_mm_per_px = view.slice_fov_mm / std::max(s, 1);
    center_idx = g.to_index(target);
  }
  // index-space image of a physical direction (voxel per mm)
  Vec3 to_idx_dir(const Vec3& v) const {
    const Vec3 a = g.physical_to_axes(v);
    return Vec3{a.x / g.spacing_mm.x, a.y / g.spacing_mm.y, a.z / g.spacing_mm.z};
  }
};

void FrameRenderer::render(OverlayId id, const ViewSettings& view, const FrameMarks& marks, FrameTimes& times) {
  draw(id, 0, view, marks);
  draw_times(0, times);
}

void FrameRenderer::draw_times(TargetId t, FrameTimes& times) {
  Impl::Target& tg = impl_->target(t);
  if (!tg.timed) return;
  double ms[3];
  impl_->stage_ms(tg, ms);
  tg.timed = false;
  times.raycast_ms += ms[0];
  times.slices_ms += ms[1];
  times.composite_ms += ms[2];
}

void FrameRenderer::draw(OverlayId id, TargetId t, const ViewSettings& view, const FrameMarks& marks) {
  Impl& m = *impl_;
  const std::string bad = check_view(view);
  if (!bad.empty()) throw Error("frame renderer: " + bad);
  const Impl::Overlay& ov = m.overlay(id);
  Impl::Target& tg = m.target(t);
  tg.timed = false;
  m.resize(tg, view.width, view.height);
  const Impl::Frame f(view, marks, ov, tg, m.patient->grid, m.body_center_mm);

  glBindFramebuffer(GL_FRAMEBUFFER, tg.fbo);
  glBindVertexArray(m.vao);
  glDisable(GL_DEPTH_TEST);
  glDisable(GL_BLEND);
  glDisable(GL_SCISSOR_TEST);
  glViewport(0, 0, f.W, f.H);
  glClearColor(0, 0, 0, 1);
  glClear(GL_COLOR_BUFFER_BIT);

  // 1. the 3D view: camera on its orbit about the target (view.h), zoom narrows the field
  m.mark(tg, 0);
  if (f.view_w > 0) m.cast_rays(f);
  m.mark(tg, 1);

  // 2. the slices through the target
  if (f.s > 0) m.draw_slices(f);
  m.mark(tg, 2);

  // 3. composite: slice frames, cut lines and marker dots; the orientation triad
  glEnable(GL_BLEND);
  glBlendFunc(GL_ONE, GL_ONE_MINUS_SRC_ALPHA);
  if (f.s > 0) m.draw_slice_marks(f);
  if (f.view_w > 0) m.draw_triad(f);
  glDisable(GL_BLEND);
  m.mark(tg, 3);
  tg.timed = true;
  check_gl("rendering a frame");
}

// the ray caster's uniforms, the same for both programs
void FrameRenderer::Impl::set_up_ray(Program& p, const Frame& f) {
  const Grid& g = f.g;
  const Camera& cam = f.cam;
  const Vec3 &eye = cam.eye, &fwd = cam.fwd, &right = cam.right, &up = cam.up;
  const double tan_h = cam.tan_h, aspect = cam.aspect;
  const Vec3 light = normalized(-fwd + up * 0.45 - right * 0.35);
  glUseProgram(p.id);
  set_viewport(p, 0, 0, f.view_w, f.H);
  bind_volume(p, f.ov);
  glBindTextureUnit(kUnitTf, tf_tex[int(f.view.preset)]);
  p.set("u_eye", g.to_index(eye));
  p.set("u_fwd", f.to_idx_dir(fwd));
  p.set("u_right", f.to_idx_dir(right * (tan_h * aspect)));
  p.set("u_up", f.to_idx_dir(up * tan_h));
  p.set("u_box_lo", box_lo);
  p.set("u_box_hi", box_hi);
  p.set("u_spacing", g.spacing_mm);
  p.set("u_light", g.physical_to_axes(light));
  p.set("u_step", float(quality.ray_step_vox));
  glUniform1i(p["u_max_steps"], int(2 * norm(box_hi - box_lo) / quality.ray_step_vox) + 64);
  // HU to the table's texel centres
  const double tf_scale = (kTfSize - 1) / double(kTfMaxHu - kTfMinHu) / kTfSize;
  p.set("u_tf_map", float(tf_scale), float(-kTfMinHu * tf_scale + 0.5 / kTfSize));
  p.set("u_grad_ramp", 15.f, 80.f);
  p.set("u_surface_hu", surface_hu(f.view.preset));
  // steps to shade: surfaces, and interfaces the ray crosses (fat and muscle, say);
  // homogeneous tissue stays flat (its gradient is noise)
  p.set("u_shade_alpha", 0.1f);
  p.set("u_interface_hu", 60.f);
  // faint blocks (every voxel of the block and one around below the preset's faint
  // intensity) are crossed in one step
  glBindTextureUnit(kUnitBlock, block_tex);
  p.set("u_block_vox", float(kBlockVox));
  p.set("u_block_count", Vec3(block_count));
  p.set("u_faint_hu", faint_below_hu(f.view.preset));
  // markers: spheres of about 6 pixels' radius at the target's distance, 1.5..8 mm
  const FrameMarks& marks = f.marks;
  const double r_mm = std::clamp(6 * f.mm_per_px, 1.5, 8.0);
  const bool tip = marks.has_tip && f.view.show_tip, proxy = marks.has_tip && f.view.show_proxy;
  const Vec3 ti = g.to_index(marks.tip_mm), pi_ = g.to_index(marks.proxy_mm);
  const float mk[8] = {float(ti.x), float(ti.y), float(ti.z), float(tip ? r_mm : 0),
                       float(pi_.x), float(pi_.y), float(pi_.z), float(proxy ? r_mm : 0)};
  glUniform4fv(p["u_marker[0]"], 2, mk);
  const Vec3 tc = marks.contact ? kTipContactColor : kTipColor;
  const float mc[6] = {float(tc.x), float(tc.y), float(tc.z),
                       float(kProxyColor.x), float(kProxyColor.y), float(kProxyColor.z)};
  glUniform3fv(p["u_marker_color[0]"], 2, mc);
  p.set("u_bg_top", Vec3{0.16, 0.17, 0.21});
  p.set("u_bg_bottom", Vec3{0.03, 0.03, 0.04});
}

// every ray without the overlay; then, for a deformed session, the rays that may pass
// through its VOI box (or near enough to change how faint space is skipped) again with
// it, within the box's bounding rectangle on the screen
void FrameRenderer::Impl::cast_rays(const Frame& f) {
  // the rays of a rectangle (x0, y0 of its top row, width, height): a compute dispatch
  // of 8x8 work groups on a GPU, a scissored full-view triangle on a software rasteriser
  auto cast = [&](Program& p, int x0, int y0, int w, int h) {
    if (!software) {
      glUniform4i(p["u_rect"], x0, y0, w, h);
      glDispatchCompute(GLuint((w + 7) / 8), GLuint((h + 7) / 8), 1);
      return;
    }
    glEnable(GL_SCISSOR_TEST);
    glScissor(x0, y0, w, h);
    glDrawArrays(GL_TRIANGLES, 0, 3);
    glDisable(GL_SCISSOR_TEST);
  };
  const Camera& cam = f.cam;
  if (!software) glBindImageTexture(0, f.tg.color_tex, 0, GL_FALSE, 0, GL_WRITE_ONLY, GL_RGBA8);
  set_up_ray(ray[0], f);
  cast(ray[0], 0, 0, f.view_w, f.H);
  int rect[4];
  if (f.ov.active && voi_rect(f.g, f.ov.box, kBlockVox + 1.0, cam.eye, cam.fwd, cam.right * (cam.tan_h * cam.aspect),
                              cam.up * cam.tan_h, f.view_w, f.H, rect)) {
    glMemoryBarrier(GL_SHADER_IMAGE_ACCESS_BARRIER_BIT);  // its pixels are written again, after the first pass
    set_up_ray(ray[1], f);
    cast(ray[1], rect[0], rect[1], rect[2], rect[3]);
  }
  // the image stores are seen by the passes that blend over them, the readback and CUDA
  glMemoryBarrier(GL_ALL_BARRIER_BITS);
}

// the three slices, stacked on the right
void FrameRenderer::Impl::draw_slices(const Frame& f) {
  const Grid& g = f.g;
  const int s = f.s;
  Program& p = slice[f.ov.active ? 1 : 0];
  glUseProgram(p.id);
  bind_volume(p, f.ov);
  const Window win = slice_window(f.view.preset);
  p.set("u_window", float(win.level_hu - 0.5 * win.width_hu), float(1.0 / win.width_hu));
  p.set("u_center", f.center_idx);
  for (int n = 0; n < 3; ++n) {
    const SliceAxes& a = f.axes[n];
    Vec3 r{0, 0, 0}, d{0, 0, 0};
    r[a.right_axis] = a.right_sign * f.slice_mm_per_px / g.spacing_mm[a.right_axis];
    d[a.down_axis] = a.down_sign * f.slice_mm_per_px / g.spacing_mm[a.down_axis];
    p.set("u_right", r);
    p.set("u_down", d);
    set_viewport(p, f.view_w, n * s, s, s);
    glDrawArrays(GL_TRIANGLES, 0, 3);
  }
}

// slice frames, cut lines and marker dots over the slices
void FrameRenderer::Impl::draw_slice_marks(const Frame& f) {
  const Grid& g = f.g;
  const int s = f.s;
  Program& p = composite;
  glUseProgram(p.id);
  set_viewport(p, f.view_w, 0, s, 3 * s);
  p.set("u_edge", float(s));
  float frame[9], vline[9], hline[9], cut[6], dots[24];
  const double dot_px = std::max(3.0, s / 45.0);
  for (int n = 0; n < 3; ++n) {
    const SliceAxes& a = f.axes[n];
    for (int c = 0; c < 3; ++c) {
      frame[3 * n + c] = float(kSliceColor[n][c]);
      vline[3 * n + c] = float(kSliceColor[slice_of_axis(a.right_axis)][c]);
      hline[3 * n + c] = float(kSliceColor[slice_of_axis(a.down_axis)][c]);
    }
    // the other planes pass through the centre: lines on the pixel column and row there
    cut[2 * n] = cut[2 * n + 1] = float(s / 2) + 0.5f;
    // a marker's pixel in this slice: its offset from the centre along the screen axes
    auto dot_at = [&](const Vec3& mm, bool show, float* out) {
      const Vec3 di = g.to_index(mm) - f.center_idx;
      const double u = a.right_sign * di[a.right_axis] * g.spacing_mm[a.right_axis] / f.slice_mm_per_px;
      const double v = a.down_sign * di[a.down_axis] * g.spacing_mm[a.down_axis] / f.slice_mm_per_px;
      out[0] = float(0.5 * s + u);
      out[1] = float(0.5 * s + v);
      out[2] = show ? float(dot_px) : 0.f;
      out[3] = 0;
    };
    dot_at(f.marks.tip_mm, f.marks.has_tip && f.view.show_tip, &dots[8 * n]);
    dot_at(f.marks.proxy_mm, f.marks.has_tip && f.view.show_proxy, &dots[8 * n + 4]);
  }
  glUniform3fv(p["u_frame_color[0]"], 3, frame);
  glUniform3fv(p["u_vline_color[0]"], 3, vline);
  glUniform3fv(p["u_hline_color[0]"], 3, hline);
  glUniform2fv(p["u_cut[0]"], 3, cut);
  glUniform4fv(p["u_dot[0]"], 6, dots);
  const Vec3 tc = f.marks.contact ? kTipContactColor : kTipColor;
  const float dc[6] = {float(tc.x), float(tc.y), float(tc.z),
                       float(kProxyColor.x), float(kProxyColor.y), float(kProxyColor.z)};
  glUniform3fv(p["u_dot_color[0]"], 2, dc);
  glDrawArrays(GL_TRIANGLES, 0, 3);
}

// L (red), P (green), S (blue) as the camera sees them, in the 3D view's bottom left
void FrameRenderer::Impl::draw_triad(const Frame& f) {
  Program& p = triad;
  glUseProgram(p.id);
  const int e = std::clamp(f.H / 7, 32, 110);
  if (e + 8 > f.view_w) return;
  set_viewport(p, 6, f.H - e - 6, e, e);
  float ax[9];
  const float col[9] = {0.95f, 0.3f, 0.3f, 0.3f, 0.9f, 0.3f, 0.35f, 0.55f, 1.0f};
  for (int n = 0; n < 3; ++n) {
    Vec3 a{0, 0, 0};
    a[n] = 1;
    ax[3 * n + 0] = float(0.42 * e * dot(a, f.cam.right));
    ax[3 * n + 1] = float(-0.42 * e * dot(a, f.cam.up));
    ax[3 * n + 2] = float(dot(a, -f.cam.fwd));
  }
  glUniform3fv(p["u_axis[0]"], 3, ax);
  glUniform3fv(p["u_axis_color[0]"], 3, col);
  glDrawArrays(GL_TRIANGLES, 0, 3);
}

}  // namespace palpsim::render
