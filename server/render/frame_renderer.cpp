#include "render/frame_renderer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <string>

#include "core/error.h"
#include "render/camera.h"
#include "render/frame_renderer_impl.h"
#include "render/shaders.h"
#include "render/transfer_function.h"

namespace palpsim::render {
namespace {

constexpr float kAirHu = -1024;       // what voxels outside the body mask become
constexpr int kCtSlab = 8;            // k-slices per chunk of the CT upload
constexpr float kShellMaxHu = -450;   // the shell around the body keeps its CT value up to this

// Mask classes in the R8 mask texture: the body, the one-voxel shell around it, outside.
// The shell keeps the CT's partial-volume values (capped at kShellMaxHu), so the skin is
// a smooth surface and not the body mask's voxel staircase, while the table and
// blankets (beyond the shell, or capped in it) stay air.
constexpr std::uint8_t kMaskBody = 255, kMaskShell = 128;

// the intensity the renderer shows for a voxel of intensity `hu` and mask class `cls` (HU)
float masked_hu(float hu, std::uint8_t cls) {
  return cls == kMaskBody ? hu : cls == kMaskShell ? std::min(hu, kShellMaxHu) : kAirHu;
}

// marks every non-body voxel touching a body voxel (26-neighbourhood) as shell:
// a separable 3x3x3 dilation
void dilate_shell(std::vector<std::uint8_t>& cls, const Vec3i& size) {
  std::vector<std::uint8_t> a(cls.size()), b(cls.size());
  for (std::size_t n = 0; n < cls.size(); ++n) a[n] = cls[n] == kMaskBody;
  const std::size_t sx = 1, sy = std::size_t(size.x), sz = std::size_t(size.x) * size.y;
  const int ext[3] = {size.x, size.y, size.z};
  const std::size_t stride[3] = {sx, sy, sz};
  for (int axis = 0; axis < 3; ++axis) {
    for (int k = 0; k < size.z; ++k)
      for (int j = 0; j < size.y; ++j)
        for (int i = 0; i < size.x; ++i) {
          const std::size_t n = k * sz + j * sy + i;
          const int c = axis == 0 ? i : axis == 1 ? j : k;
          std::uint8_t v = a[n];
          if (c > 0) v |= a[n - stride[axis]];
          if (c + 1 < ext[axis]) v |= a[n + stride[axis]];
          b[n] = v;
        }
    std::swap(a, b);
  }
  for (std::size_t n = 0; n < cls.size(); ++n)
    if (cls[n] != kMaskBody && a[n]) cls[n] = kMaskShell;
}

double ms_since(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

}  // namespace

// --- construction -------------------------------------------------------------------

void FrameRenderer::Impl::upload_volumes() {
  const Patient& p = *patient;
  const Grid& g = p.grid;
  if (g.size.x < 1 || g.size.y < 1 || g.size.z < 1) throw Error("frame renderer: the patient grid is empty");
  if (p.intensity.data.size() != g.count() || p.body.data.size() != g.count())
    throw Error("frame renderer: the patient's intensity and body mask do not fill its grid");
  GLint max3d = 0;
  glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max3d);
  if (g.size.x > max3d || g.size.y > max3d || g.size.z > max3d)
    throw Error("frame renderer: the patient grid " + std::to_string(g.size.x) + " x " + std::to_string(g.size.y) +
                " x " + std::to_string(g.size.z) + " voxels exceeds GL_MAX_3D_TEXTURE_SIZE = " +
                std::to_string(max3d) + " of this OpenGL device; prepare the patient at a coarser prep.spacing_mm");

  // the mask classes: body, the shell of voxels touching it (26-neighbourhood), outside
  const std::size_t plane = std::size_t(g.size.x) * g.size.y;
  std::vector<std::uint8_t> cls(g.count());
  for (std::size_t n = 0; n < cls.size(); ++n) cls[n] = p.body.data[n] ? kMaskBody : 0;
  dilate_shell(cls, g.size);

  // the CT with the body's surroundings as air, and the mask classes, a slab of k-slices at a time
  auto make3d = [&](GLenum format, GLenum filter, const Vec3i& size) {
    GLuint t = 0;
    glCreateTextures(GL_TEXTURE_3D, 1, &t);
    glTextureStorage3D(t, 1, format, size.x, size.y, size.z);
    glTextureParameteri(t, GL_TEXTURE_MIN_FILTER, filter);
    glTextureParameteri(t, GL_TEXTURE_MAG_FILTER, filter);
    for (GLenum w : {GL_TEXTURE_WRAP_S, GL_TEXTURE_WRAP_T, GL_TEXTURE_WRAP_R})
      glTextureParameteri(t, w, GL_CLAMP_TO_EDGE);
    return t;
  };
  ct_tex = make3d(quality.half_float_ct ? GL_R16F : GL_R32F, GL_LINEAR, g.size);
  body_tex = make3d(GL_R8, GL_LINEAR, g.size);
  check_gl("the CT texture's allocation");
  glPixelStorei(GL_UNPACK_ALIGNMENT, 1);
  std::vector<float> hu(plane * kCtSlab);
  // the largest masked intensity (HU) of each block and the voxels one around it (the
  // trilinear footprint of any point in the block), for skipping faint space
  const Vec3i nb{(g.size.x + kBlockVox - 1) / kBlockVox, (g.size.y + kBlockVox - 1) / kBlockVox,
                 (g.size.z + kBlockVox - 1) / kBlockVox};
  std::vector<float> block(std::size_t(nb.x) * nb.y * nb.z, kAirHu);
  auto block_range = [](int v, int n) {  // the blocks whose footprint holds voxel v
    return std::pair<int, int>{std::max((v - 1) / kBlockVox, 0), std::min((v + 1) / kBlockVox, n - 1)};
  };
  Vec3i lo{g.size.x, g.size.y, g.size.z}, hi{-1, -1, -1};
  for (int k0 = 0; k0 < g.size.z; k0 += kCtSlab) {
    const int nk = std::min(kCtSlab, g.size.z - k0);
    const std::size_t base = plane * std::size_t(k0);
    for (int k = k0; k < k0 + nk; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const std::size_t n = g.index(i, j, k);
          const float v = masked_hu(p.intensity.data[n], cls[n]);
          hu[n - base] = v;
          if (v > kAirHu) {
            const auto [bi0, bi1] = block_range(i, nb.x);
            const auto [bj0, bj1] = block_range(j, nb.y);
            const auto [bk0, bk1] = block_range(k, nb.z);
            for (int bk = bk0; bk <= bk1; ++bk)
              for (int bj = bj0; bj <= bj1; ++bj)
                for (int bi = bi0; bi <= bi1; ++bi) {
                  float& b = block[(std::size_t(bk) * nb.y + bj) * nb.x + bi];
                  b = std::max(b, v);
                }
          }
          if (cls[n] == kMaskBody) {
            // the body's bounding box
            lo = {std::min(lo.x, i), std::min(lo.y, j), std::min(lo.z, k)};
            hi = {std::max(hi.x, i), std::max(hi.y, j), std::max(hi.z, k)};
          }
        }
    glTextureSubImage3D(ct_tex, 0, 0, 0, k0, g.size.x, g.size.y, nk, GL_RED, GL_FLOAT, hu.data());
    glTextureSubImage3D(body_tex, 0, 0, 0, k0, g.size.x, g.size.y, nk, GL_RED, GL_UNSIGNED_BYTE, &cls[base]);
  }
  check_gl("the CT texture's upload");
  block_tex = make3d(GL_R32F, GL_NEAREST, nb);
  glTextureSubImage3D(block_tex, 0, 0, 0, 0, nb.x, nb.y, nb.z, GL_RED, GL_FLOAT, block.data());
  check_gl("the block texture's upload");
  block_count = nb;
  ct_bytes = g.count() * ((quality.half_float_ct ? 2 : sizeof(float)) + 1) + block.size() * sizeof(float);
  if (hi.x < 0) {
    // no body at all: the whole grid
    lo = {0, 0, 0};
    hi = {g.size.x - 1, g.size.y - 1, g.size.z - 1};
  }
  box_lo = Vec3(lo.x - 0.5, lo.y - 0.5, lo.z - 0.5);
  box_hi = Vec3(hi.x + 0.5, hi.y + 0.5, hi.z + 0.5);
  body_center_mm = body_center(g, lo, hi);
  // the pre-integrated transfer functions, for steps of ray_step_vox voxels (mean voxel edge)
  const double voxel_mm = std::cbrt(g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z);
  for (Preset pr : {Preset::kSkin, Preset::kBone, Preset::kSoftTissue}) {
    const std::vector<float> table = preintegrate(make_transfer_function(pr), quality.ray_step_vox * voxel_mm);
    GLuint& t = tf_tex[int(pr)];
    glCreateTextures(GL_TEXTURE_2D, 1, &t);
    glTextureStorage2D(t, 1, GL_RGBA16F, kTfSize, kTfSize);
    glTextureSubImage2D(t, 0, 0, 0, kTfSize, kTfSize, GL_RGBA, GL_FLOAT, table.data());
    glTextureParameteri(t, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
    glTextureParameteri(t, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
    glTextureParameteri(t, GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
    glTextureParameteri(t, GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);
    tf_bytes += std::size_t(kTfSize) * kTfSize * 8;
  }
  check_gl("the transfer functions' upload");
}

void FrameRenderer::Impl::build_programs() {
  // the constants the shaders share with this file
  const std::string head = "#version 450 core\n#define AIR_HU " + std::to_string(kAirHu) + "\n#define SHELL_MAX_HU " +
                           std::to_string(kShellMaxHu) + "\n#define SHELL_MASK " + std::to_string(kMaskShell) +
                           ".0 / 255.0\n";
  for (int overlay = 0; overlay < 2; ++overlay) {
    const std::string volume = head + "#define OVERLAY " + std::to_string(overlay) + "\n" + shaders::kSampleGlsl;
    ray[overlay].build((software ? volume : volume + "#define RAY_COMPUTE 1\n") + shaders::kRaycastFs, "ray casting",
                       !software);
    slice[overlay].build(volume + shaders::kSliceFs, "slice");
  }
  composite.build(head + shaders::kCompositeFs, "composite");
  triad.build(head + shaders::kTriadFs, "orientation triad");
  glCreateVertexArrays(1, &vao);
  check_gl("the shaders' set-up");
  targets[0] = make_target();
}

FrameRenderer::FrameRenderer(PatientPtr patient, const RenderQuality& quality) : impl_(std::make_unique<Impl>()) {
  if (!patient) throw Error("frame renderer: no patient");
  if (!glGetString(GL_VERSION)) throw Error("frame renderer: no OpenGL context is current on this thread");
  if (!(quality.ray_step_vox >= 0.25 && quality.ray_step_vox <= 4))
    throw Error("frame renderer: ray_step_vox = " + std::to_string(quality.ray_step_vox) +
                " is outside 0.25..4 voxels");
  gl_errors();  // start clean
  impl_->patient = std::move(patient);
  impl_->quality = quality;
  const std::string renderer = reinterpret_cast<const char*>(glGetString(GL_RENDERER));
  impl_->software = renderer.find("llvmpipe") != std::string::npos || renderer.find("softpipe") != std::string::npos ||
                    renderer.find("swrast") != std::string::npos;
  // on a throw, ~Impl frees what was made
  impl_->build_programs();
  impl_->upload_volumes();
}

FrameRenderer::~FrameRenderer() = default;

// --- overlays -----------------------------------------------------------------------

FrameRenderer::OverlayId FrameRenderer::add_overlay(const Vec3i& max_voi) {
  if (max_voi.x < 1 || max_voi.y < 1 || max_voi.z < 1)
    throw Error("frame renderer: an overlay of " + std::to_string(max_voi.x) + " x " + std::to_string(max_voi.y) +
                " x " + std::to_string(max_voi.z) + " voxels is empty");
  GLint max3d = 0;
  glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &max3d);
  if (max_voi.x > max3d || max_voi.y > max3d || max_voi.z > max3d)
    throw Error("frame renderer: an overlay of " + std::to_string(max_voi.x) + " x " + std::to_string(max_voi.y) +
                " x " + std::to_string(max_voi.z) + " voxels exceeds GL_MAX_3D_TEXTURE_SIZE = " +
                std::to_string(max3d));
  Impl::Overlay o;
  o.max_voi = max_voi;
  glCreateTextures(GL_TEXTURE_3D, 1, &o.tex);
  glTextureStorage3D(o.tex, 1, GL_R32F, max_voi.x, max_voi.y, max_voi.z);
  glTextureParameteri(o.tex, GL_TEXTURE_MIN_FILTER, GL_LINEAR);
  glTextureParameteri(o.tex, GL_TEXTURE_MAG_FILTER, GL_LINEAR);
  for (GLenum w : {GL_TEXTURE_WRAP_S, GL_TEXTURE_WRAP_T, GL_TEXTURE_WRAP_R}) glTextureParameteri(o.tex, w, GL_CLAMP_TO_EDGE);
  // defined contents (air) until the first upload
  const float air = kAirHu;
  glClearTexImage(o.tex, 0, GL_RED, GL_FLOAT, &air);
  const std::string e = gl_errors();
  if (!e.empty()) {
    glDeleteTextures(1, &o.tex);
    throw Error("frame renderer: an overlay of " + std::to_string(max_voi.x) + " x " + std::to_string(max_voi.y) +
                " x " + std::to_string(max_voi.z) + " voxels cannot be made: OpenGL error " + e);
  }
  const int id = impl_->next_id++;
  impl_->overlays[id] = o;
  return id;
}

void FrameRenderer::remove_overlay(OverlayId id) {
  auto it = impl_->overlays.find(id);
  if (it == impl_->overlays.end()) return;
  glDeleteTextures(1, &it->second.tex);
  impl_->overlays.erase(it);
}

void FrameRenderer::Impl::check_voi(const Overlay& o, const Voi& voi) const {
  const Vec3i& s = voi.size;
  const Vec3i& g = patient->grid.size;
  auto box = [](const Vec3i& lo, const Vec3i& size) {
    return "[" + std::to_string(lo.x) + ", " + std::to_string(lo.y) + ", " + std::to_string(lo.z) + "] + " +
           std::to_string(size.x) + " x " + std::to_string(size.y) + " x " + std::to_string(size.z);
  };
  if (s.x < 0 || s.y < 0 || s.z < 0 || s.x > o.max_voi.x || s.y > o.max_voi.y || s.z > o.max_voi.z)
    throw Error("frame renderer: VOI " + box(voi.lo, s) + " does not fit the overlay of " +
                std::to_string(o.max_voi.x) + " x " + std::to_string(o.max_voi.y) + " x " +
                std::to_string(o.max_voi.z) + " voxels");
  if (voi.lo.x < 0 || voi.lo.y < 0 || voi.lo.z < 0 || voi.lo.x + s.x > g.x || voi.lo.y + s.y > g.y ||
      voi.lo.z + s.z > g.z)
    throw Error("frame renderer: VOI " + box(voi.lo, s) + " leaves the patient grid of " + std::to_string(g.x) +
                " x " + std::to_string(g.y) + " x " + std::to_string(g.z) + " voxels");
}

void FrameRenderer::upload_overlay(OverlayId id, const Voi& voi, const float* j) {
  Impl::Overlay& o = impl_->overlay(id);
  impl_->check_voi(o, voi);
  if (voi.count() == 0) {
    o.active = false;
    return;
  }
  if (!j) throw Error("frame renderer: upload_overlay without J");
  glPixelStorei(GL_UNPACK_ALIGNMENT, 4);
  glTextureSubImage3D(o.tex, 0, 0, 0, 0, voi.size.x, voi.size.y, voi.size.z, GL_RED, GL_FLOAT, j);
  check_gl("the overlay upload");
  o.box = voi;
  o.active = true;
}

void FrameRenderer::set_overlay_box(OverlayId id, const Voi& voi) {
  Impl::Overlay& o = impl_->overlay(id);
  impl_->check_voi(o, voi);
  o.box = voi;
  o.active = voi.count() > 0;
}

void FrameRenderer::clear_overlay(OverlayId id) { impl_->overlay(id).active = false; }

unsigned FrameRenderer::overlay_texture(OverlayId id) const { return impl_->overlay(id).tex; }

// --- rendering ----------------------------------------------------------------------

FrameRenderer::TargetId FrameRenderer::add_target() {
  Impl& m = *impl_;
  const TargetId id = m.next_target++;
  m.targets[id] = m.make_target();
  return id;
}

void FrameRenderer::remove_target(TargetId t) {
  if (t == 0) throw Error("frame renderer: target 0 cannot be removed");
  auto it = impl_->targets.find(t);
  if (it == impl_->targets.end()) return;
  Impl::free_target(it->second);
  impl_->targets.erase(it);
}

void FrameRenderer::release_frame_state() {
  Impl& m = *impl_;
  // a draw's worth of state that references nothing big: a 1 x 1 framebuffer, no textures
  Impl::Target& t = m.target(0);
  m.resize(t, 1, 1);
  for (GLuint unit : {kUnitCt, kUnitOverlay, kUnitBody, kUnitTf, kUnitBlock}) glBindTextureUnit(unit, 0);
  if (!m.software) glBindImageTexture(0, 0, 0, GL_FALSE, 0, GL_WRITE_ONLY, GL_RGBA8);
  glUseProgram(0);
  glBindFramebuffer(GL_FRAMEBUFFER, t.fbo);
  glViewport(0, 0, 1, 1);
  glClear(GL_COLOR_BUFFER_BIT);
  glFinish();
  check_gl("releasing the last frame's state");
}

void FrameRenderer::Impl::resize(Target& t, int w, int h) {
  if (w == t.width && h == t.height && t.color_tex) return;
  // a new texture (immutable storage): interop users see a new name after a resize
  if (t.color_tex) glDeleteTextures(1, &t.color_tex);
  t.color_tex = 0;
  t.width = t.height = 0;
  glCreateTextures(GL_TEXTURE_2D, 1, &t.color_tex);
  glTextureStorage2D(t.color_tex, 1, GL_RGBA8, w, h);
  glTextureParameteri(t.color_tex, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTextureParameteri(t.color_tex, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  glNamedFramebufferTexture(t.fbo, GL_COLOR_ATTACHMENT0, t.color_tex, 0);
  const GLenum status = glCheckNamedFramebufferStatus(t.fbo, GL_FRAMEBUFFER);
  check_gl("the framebuffer's allocation");
  if (status != GL_FRAMEBUFFER_COMPLETE)
    throw Error("frame renderer: the " + std::to_string(w) + " x " + std::to_string(h) +
                " framebuffer is incomplete (status " + std::to_string(status) + ")");
  t.width = w;
  t.height = h;
}

void FrameRenderer::Impl::bind_volume(Program& p, const Overlay& o) {
  const Grid& g = patient->grid;
  glBindTextureUnit(kUnitCt, ct_tex);
  glBindTextureUnit(kUnitOverlay, o.tex);
  glBindTextureUnit(kUnitBody, body_tex);
  p.set("u_grid_size", Vec3(g.size));
  glUniform1i(p["u_overlay_on"], o.active ? 1 : 0);
  p.set("u_voi_lo", Vec3(o.box.lo));
  p.set("u_voi_size", Vec3(o.box.size));
  p.set("u_overlay_tex_size", Vec3(o.max_voi));
}

void FrameRenderer::read_rgb(TargetId t, std::vector<std::uint8_t>& rgb, FrameTimes& times) {
  const auto t0 = Clock::now();
  const Impl::Target& m = impl_->target(t);
  if (!m.color_tex) throw Error("frame renderer: read_rgb before the first frame");
  rgb.resize(std::size_t(m.width) * m.height * 3);
  glBindFramebuffer(GL_READ_FRAMEBUFFER, m.fbo);
  glReadBuffer(GL_COLOR_ATTACHMENT0);
  glPixelStorei(GL_PACK_ALIGNMENT, 1);
  // texel row 0 is the image's top row: glReadPixels' first row is the top
  glReadPixels(0, 0, m.width, m.height, GL_RGB, GL_UNSIGNED_BYTE, rgb.data());
  check_gl("reading the frame back");
  times.readback_ms += ms_since(t0);
}

unsigned FrameRenderer::color_texture(TargetId t) const { return impl_->target(t).color_tex; }
int FrameRenderer::width(TargetId t) const { return impl_->target(t).width; }
int FrameRenderer::height(TargetId t) const { return impl_->target(t).height; }

std::size_t FrameRenderer::bytes() const {
  const Impl& m = *impl_;
  std::size_t b = m.ct_bytes + m.tf_bytes;
  for (const auto& [id, t] : m.targets) b += std::size_t(t.width) * t.height * 4;
  for (const auto& [id, o] : m.overlays) b += std::size_t(o.max_voi.x) * o.max_voi.y * o.max_voi.z * sizeof(float);
  return b;
}

const Patient& FrameRenderer::patient() const { return *impl_->patient; }

}  // namespace palpsim::render
