#include "render/frame_renderer.h"

#define GL_GLEXT_PROTOTYPES
#include <GL/glcorearb.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <string>
#include <unordered_map>

#include "core/error.h"
#include "render/camera.h"
#include "render/shaders.h"
#include "render/transfer_function.h"

namespace palpsim::render {
namespace {

using Clock = std::chrono::steady_clock;

constexpr float kAirHu = -1024;       // what voxels outside the body mask become
constexpr int kCtSlab = 8;            // k-slices per chunk of the CT upload
constexpr int kBlockVox = 8;          // edge of the blocks for skipping faint space (voxel)
constexpr float kShellMaxHu = -450;   // the shell around the body keeps its CT value up to this
constexpr float kFaintTauPerMm = 0.004f;  // extinction below which space is faint enough to skip

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

// the highest intensity (HU) below which a preset's extinction stays under kFaintTauPerMm
float faint_below_hu(Preset p) {
  const TransferFunction tf = make_transfer_function(p);
  for (int n = 0; n < kTfSize; ++n)
    if (tf.tau[n] >= kFaintTauPerMm) return n > 0 ? TransferFunction::hu_of(n - 1) : kTfMinHu - 1;
  return kTfMaxHu;
}

// texture units of the volume shaders (the binding = N in shaders.h)
enum Unit { kUnitCt = 0, kUnitOverlay = 1, kUnitBody = 2, kUnitTf = 3, kUnitBlock = 4 };

double ms_since(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

// a GL error as text, or "" when there is none (clears the pending errors)
std::string gl_errors() {
  std::string s;
  GLenum e;
  for (int n = 0; n < 8 && (e = glGetError()) != GL_NO_ERROR; ++n) {
    char b[16];
    std::snprintf(b, sizeof b, "0x%04X", unsigned(e));
    s += (s.empty() ? "" : ", ") + std::string(b) + (e == GL_OUT_OF_MEMORY ? " (out of memory)" : "");
  }
  return s;
}

void check_gl(const char* what) {
  const std::string e = gl_errors();
  if (!e.empty()) throw Error(std::string("OpenGL error during ") + what + ": " + e);
}

GLuint compile(GLenum type, const std::string& src, const char* name) {
  const GLuint s = glCreateShader(type);
  const char* p = src.c_str();
  glShaderSource(s, 1, &p, nullptr);
  glCompileShader(s);
  GLint ok = 0;
  glGetShaderiv(s, GL_COMPILE_STATUS, &ok);
  if (!ok) {
    GLint n = 0;
    glGetShaderiv(s, GL_INFO_LOG_LENGTH, &n);
    std::string log(std::size_t(std::max(n, 1)), '\0');
    glGetShaderInfoLog(s, n, nullptr, log.data());
    glDeleteShader(s);
    throw Error(std::string("the ") + name + " shader does not compile: " + log);
  }
  return s;
}

// A linked program with its uniform locations looked up once by name.
struct Program {
  GLuint id = 0;
  std::unordered_map<std::string, GLint> loc;

  // a full-viewport triangle with fragment shader `fs`, or (compute) a compute shader
  void build(const std::string& fs, const char* name, bool compute = false) {
    const GLuint v = compute ? 0 : compile(GL_VERTEX_SHADER, shaders::kFullscreenVs, name);
    const GLuint f = compile(compute ? GL_COMPUTE_SHADER : GL_FRAGMENT_SHADER, fs, name);
    id = glCreateProgram();
    if (v) glAttachShader(id, v);
    glAttachShader(id, f);
    glLinkProgram(id);
    if (v) glDeleteShader(v);
    glDeleteShader(f);
    GLint ok = 0;
    glGetProgramiv(id, GL_LINK_STATUS, &ok);
    if (!ok) {
      GLint n = 0;
      glGetProgramiv(id, GL_INFO_LOG_LENGTH, &n);
      std::string log(std::size_t(std::max(n, 1)), '\0');
      glGetProgramInfoLog(id, n, nullptr, log.data());
      throw Error(std::string("the ") + name + " shader does not link: " + log);
    }
  }
  // location of a uniform (-1, which GL ignores, when the compiler removed it)
  GLint operator[](const std::string& name) {
    auto it = loc.find(name);
    if (it != loc.end()) return it->second;
    return loc[name] = glGetUniformLocation(id, name.c_str());
  }
  void set(const char* n, float a) { glUniform1f((*this)[n], a); }
  void set(const char* n, float a, float b) { glUniform2f((*this)[n], a, b); }
  void set(const char* n, const Vec3& v) { glUniform3f((*this)[n], float(v.x), float(v.y), float(v.z)); }
  void set(const char* n, float a, float b, float c, float d) { glUniform4f((*this)[n], a, b, c, d); }
};

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

struct FrameRenderer::Impl {
  // one session's overlay: J on a VOI box
  struct Overlay {
    GLuint tex = 0;
    Vec3i max_voi{0, 0, 0};
    Voi box;
    bool active = false;
  };

  // one framebuffer: its colour texture, size and the timestamps of its latest frame
  // (before the ray cast, after it, the slices, the composite). On a GPU the stages are
  // timed by GL timestamps, so that no stage waits for the one before; a software
  // rasteriser (llvmpipe) draws at the flush, after its timestamps, so there each stage
  // is finished and timed on the wall clock instead.
  struct Target {
    GLuint fbo = 0, color_tex = 0;
    int width = 0, height = 0;
    GLuint stamps[4] = {0, 0, 0, 0};
    Clock::time_point wall[4];
    bool timed = false;  // a frame was drawn whose times were not read yet
  };

  PatientPtr patient;
  GLuint ct_tex = 0, body_tex = 0, block_tex = 0, vao = 0;
  Vec3i block_count{0, 0, 0};    // blocks of kBlockVox voxels per axis
  GLuint tf_tex[3] = {0, 0, 0};  // per preset (Preset's order)
  Program ray[2], slice[2];      // without and with the overlay (OVERLAY 0 and 1)
  Program composite, triad;
  std::map<int, Target> targets;  // 0: the default
  int next_target = 1;
  Vec3 box_lo, box_hi;           // the body's bounding box (voxel index, voxel edges)
  Vec3 body_center_mm;           // its centre (mm)
  std::map<int, Overlay> overlays;
  int next_id = 1;
  std::size_t ct_bytes = 0, tf_bytes = 0;
  RenderQuality quality;
  bool software = false;
  void mark(Target& t, int n) {
    if (software) {
      glFinish();
      t.wall[n] = Clock::now();
    } else {
      glQueryCounter(t.stamps[n], GL_TIMESTAMP);
    }
  }
  // the ms from mark a to mark b of t's latest frame (waits for its last mark on a GPU)
  void stage_ms(Target& t, double out[3]) {
    if (software) {
      for (int n = 0; n < 3; ++n) out[n] = std::chrono::duration<double, std::milli>(t.wall[n + 1] - t.wall[n]).count();
      return;
    }
    GLuint64 ns[4] = {0, 0, 0, 0};
    for (int n = 0; n < 4; ++n) glGetQueryObjectui64v(t.stamps[n], GL_QUERY_RESULT, &ns[n]);
    for (int n = 0; n < 3; ++n) out[n] = double(ns[n + 1] - ns[n]) * 1e-6;
  }
  Target& target(TargetId id) {
    auto it = targets.find(id);
    if (it == targets.end()) throw Error("frame renderer: no target " + std::to_string(id));
    return it->second;
  }
  const Target& target(TargetId id) const { return const_cast<Impl*>(this)->target(id); }
  // a framebuffer and its timestamp queries (its texture comes with the first frame)
  Target make_target() {
    Target t;
    glCreateFramebuffers(1, &t.fbo);
    glCreateQueries(GL_TIMESTAMP, 4, t.stamps);
    check_gl("a framebuffer's set-up");
    return t;
  }
  static void free_target(Target& t) {
    glDeleteTextures(1, &t.color_tex);
    glDeleteFramebuffers(1, &t.fbo);
    glDeleteQueries(4, t.stamps);
    t = Target{};
  }

  Overlay& overlay(OverlayId id) {
    auto it = overlays.find(id);
    if (it == overlays.end()) throw Error("frame renderer: no overlay " + std::to_string(id));
    return it->second;
  }
  const Overlay& overlay(OverlayId id) const { return const_cast<Impl*>(this)->overlay(id); }

  Impl() = default;
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  // frees every GL object made so far (also when the constructor failed half way)
  ~Impl() {
    for (auto& [id, o] : overlays) glDeleteTextures(1, &o.tex);
    glDeleteTextures(1, &ct_tex);
    glDeleteTextures(1, &body_tex);
    glDeleteTextures(1, &block_tex);
    glDeleteTextures(3, tf_tex);
    for (auto& [id, t] : targets) free_target(t);
    glDeleteVertexArrays(1, &vao);
    for (Program* p : {&ray[0], &ray[1], &slice[0], &slice[1], &composite, &triad})
      if (p->id) glDeleteProgram(p->id);
  }

  void upload_volumes();
  void build_programs();
  void resize(Target& t, int w, int h);
  void check_voi(const Overlay& o, const Voi& voi) const;
  void bind_volume(Program& p, const Overlay& o);
};

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
  const Grid& g = m.patient->grid;
  Impl::Target& tg = m.target(t);
  tg.timed = false;
  m.resize(tg, view.width, view.height);

  // layout: the 3D view on the left, slices of edge s stacked on the right
  const int W = view.width, H = view.height, view_w = view_width(W, H), s = W - view_w;
  // the look-at point and slice centre (mm)
  const Vec3 target = frame_target(view, marks.has_tip, marks.tip_mm, m.body_center_mm);
  // index-space image of a physical direction (voxel per mm)
  auto to_idx_dir = [&](const Vec3& v) {
    const Vec3 a = g.physical_to_axes(v);
    return Vec3{a.x / g.spacing_mm.x, a.y / g.spacing_mm.y, a.z / g.spacing_mm.z};
  };

  glBindFramebuffer(GL_FRAMEBUFFER, tg.fbo);
  glBindVertexArray(m.vao);
  glDisable(GL_DEPTH_TEST);
  glDisable(GL_BLEND);
  glDisable(GL_SCISSOR_TEST);
  glViewport(0, 0, W, H);
  glClearColor(0, 0, 0, 1);
  glClear(GL_COLOR_BUFFER_BIT);

  // 1. the 3D view: camera on its orbit about the target (view.h), zoom narrows the field
  m.mark(tg, 0);
  const Camera cam = orbit_camera(g, view, target);
  const Vec3 &eye = cam.eye, &fwd = cam.fwd, &right = cam.right, &up = cam.up;
  const double dist_mm = cam.dist_mm, tan_h = cam.tan_h, aspect = cam.aspect;
  const Vec3 light = normalized(-fwd + up * 0.45 - right * 0.35);
  const double mm_per_px = 2 * dist_mm * tan_h / H;  // at the target's distance
  // the ray caster's uniforms, the same for both programs
  auto set_up_ray = [&](Program& p) {
    glUseProgram(p.id);
    set_viewport(p, 0, 0, view_w, H);
    m.bind_volume(p, ov);
    glBindTextureUnit(kUnitTf, m.tf_tex[int(view.preset)]);
    p.set("u_eye", g.to_index(eye));
    p.set("u_fwd", to_idx_dir(fwd));
    p.set("u_right", to_idx_dir(right * (tan_h * aspect)));
    p.set("u_up", to_idx_dir(up * tan_h));
    p.set("u_box_lo", m.box_lo);
    p.set("u_box_hi", m.box_hi);
    p.set("u_spacing", g.spacing_mm);
    p.set("u_light", g.physical_to_axes(light));
    p.set("u_step", float(m.quality.ray_step_vox));
    glUniform1i(p["u_max_steps"], int(2 * norm(m.box_hi - m.box_lo) / m.quality.ray_step_vox) + 64);
    // HU to the table's texel centres
    const double tf_scale = (kTfSize - 1) / double(kTfMaxHu - kTfMinHu) / kTfSize;
    p.set("u_tf_map", float(tf_scale), float(-kTfMinHu * tf_scale + 0.5 / kTfSize));
    p.set("u_grad_ramp", 15.f, 80.f);
    p.set("u_surface_hu", surface_hu(view.preset));
    // steps to shade: surfaces, and interfaces the ray crosses (fat and muscle, say);
    // homogeneous tissue stays flat (its gradient is noise)
    p.set("u_shade_alpha", 0.1f);
    p.set("u_interface_hu", 60.f);
    // faint blocks (every voxel of the block and one around below the preset's faint
    // intensity) are crossed in one step
    glBindTextureUnit(kUnitBlock, m.block_tex);
    p.set("u_block_vox", float(kBlockVox));
    p.set("u_block_count", Vec3(m.block_count));
    p.set("u_faint_hu", faint_below_hu(view.preset));
    // markers: spheres of about 6 pixels' radius at the target's distance, 1.5..8 mm
    const double r_mm = std::clamp(6 * mm_per_px, 1.5, 8.0);
    const bool tip = marks.has_tip && view.show_tip, proxy = marks.has_tip && view.show_proxy;
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
  };
  if (view_w > 0) {
    // every ray without the overlay; then, for a deformed session, the rays that may
    // pass through its VOI box (or near enough to change how faint space is skipped)
    // again with it, within the box's bounding rectangle on the screen
    // the rays of a rectangle (x0, y0 of its top row, width, height): a compute dispatch
    // of 8x8 work groups on a GPU, a scissored full-view triangle on a software rasteriser
    auto cast = [&](Program& p, int x0, int y0, int w, int h) {
      if (!m.software) {
        glUniform4i(p["u_rect"], x0, y0, w, h);
        glDispatchCompute(GLuint((w + 7) / 8), GLuint((h + 7) / 8), 1);
        return;
      }
      glEnable(GL_SCISSOR_TEST);
      glScissor(x0, y0, w, h);
      glDrawArrays(GL_TRIANGLES, 0, 3);
      glDisable(GL_SCISSOR_TEST);
    };
    if (!m.software) glBindImageTexture(0, tg.color_tex, 0, GL_FALSE, 0, GL_WRITE_ONLY, GL_RGBA8);
    set_up_ray(m.ray[0]);
    cast(m.ray[0], 0, 0, view_w, H);
    int rect[4];
    if (ov.active && voi_rect(g, ov.box, kBlockVox + 1.0, eye, fwd, right * (tan_h * aspect), up * tan_h, view_w, H,
                              rect)) {
      glMemoryBarrier(GL_SHADER_IMAGE_ACCESS_BARRIER_BIT);  // its pixels are written again, after the first pass
      set_up_ray(m.ray[1]);
      cast(m.ray[1], rect[0], rect[1], rect[2], rect[3]);
    }
    // the image stores are seen by the passes that blend over them, the readback and CUDA
    glMemoryBarrier(GL_ALL_BARRIER_BITS);
  }
  m.mark(tg, 1);

  // 2. the slices: axial (k), coronal (j), sagittal (i) through the target, top to bottom
  const SliceAxes axes[3] = {slice_axes(g, 2, {1, 0, 0}, {0, 1, 0}), slice_axes(g, 1, {1, 0, 0}, {0, 0, -1}),
                             slice_axes(g, 0, {0, 1, 0}, {0, 0, -1})};
  const double slice_mm_per_px = view.slice_fov_mm / std::max(s, 1);
  const Vec3 center_idx = g.to_index(target);
  if (s > 0) {
    Program& p = m.slice[ov.active ? 1 : 0];
    glUseProgram(p.id);
    m.bind_volume(p, ov);
    const Window win = slice_window(view.preset);
    p.set("u_window", float(win.level_hu - 0.5 * win.width_hu), float(1.0 / win.width_hu));
    p.set("u_center", center_idx);
    for (int n = 0; n < 3; ++n) {
      Vec3 r{0, 0, 0}, d{0, 0, 0};
      r[axes[n].right_axis] = axes[n].right_sign * slice_mm_per_px / g.spacing_mm[axes[n].right_axis];
      d[axes[n].down_axis] = axes[n].down_sign * slice_mm_per_px / g.spacing_mm[axes[n].down_axis];
      p.set("u_right", r);
      p.set("u_down", d);
      set_viewport(p, view_w, n * s, s, s);
      glDrawArrays(GL_TRIANGLES, 0, 3);
    }
  }
  m.mark(tg, 2);

  // 3. composite: slice frames, cut lines and marker dots; the orientation triad
  glEnable(GL_BLEND);
  glBlendFunc(GL_ONE, GL_ONE_MINUS_SRC_ALPHA);
  if (s > 0) {
    Program& p = m.composite;
    glUseProgram(p.id);
    set_viewport(p, view_w, 0, s, 3 * s);
    p.set("u_edge", float(s));
    float frame[9], vline[9], hline[9], cut[6], dots[24];
    const double dot_px = std::max(3.0, s / 45.0);
    for (int n = 0; n < 3; ++n) {
      const SliceAxes& a = axes[n];
      for (int c = 0; c < 3; ++c) {
        frame[3 * n + c] = float(kSliceColor[n][c]);
        vline[3 * n + c] = float(kSliceColor[slice_of_axis(a.right_axis)][c]);
        hline[3 * n + c] = float(kSliceColor[slice_of_axis(a.down_axis)][c]);
      }
      // the other planes pass through the centre: lines on the pixel column and row there
      cut[2 * n] = cut[2 * n + 1] = float(s / 2) + 0.5f;
      // a marker's pixel in this slice: its offset from the centre along the screen axes
      auto dot_at = [&](const Vec3& mm, bool show, float* out) {
        const Vec3 di = g.to_index(mm) - center_idx;
        const double u = a.right_sign * di[a.right_axis] * g.spacing_mm[a.right_axis] / slice_mm_per_px;
        const double v = a.down_sign * di[a.down_axis] * g.spacing_mm[a.down_axis] / slice_mm_per_px;
        out[0] = float(0.5 * s + u);
        out[1] = float(0.5 * s + v);
        out[2] = show ? float(dot_px) : 0.f;
        out[3] = 0;
      };
      dot_at(marks.tip_mm, marks.has_tip && view.show_tip, &dots[8 * n]);
      dot_at(marks.proxy_mm, marks.has_tip && view.show_proxy, &dots[8 * n + 4]);
    }
    glUniform3fv(p["u_frame_color[0]"], 3, frame);
    glUniform3fv(p["u_vline_color[0]"], 3, vline);
    glUniform3fv(p["u_hline_color[0]"], 3, hline);
    glUniform2fv(p["u_cut[0]"], 3, cut);
    glUniform4fv(p["u_dot[0]"], 6, dots);
    const Vec3 tc = marks.contact ? kTipContactColor : kTipColor;
    const float dc[6] = {float(tc.x), float(tc.y), float(tc.z),
                         float(kProxyColor.x), float(kProxyColor.y), float(kProxyColor.z)};
    glUniform3fv(p["u_dot_color[0]"], 2, dc);
    glDrawArrays(GL_TRIANGLES, 0, 3);
  }
  if (view_w > 0) {
    // L (red), P (green), S (blue) as the camera sees them, in the 3D view's bottom left
    Program& p = m.triad;
    glUseProgram(p.id);
    const int e = std::clamp(H / 7, 32, 110);
    if (e + 8 <= view_w) {
      set_viewport(p, 6, H - e - 6, e, e);
      float ax[9];
      const float col[9] = {0.95f, 0.3f, 0.3f, 0.3f, 0.9f, 0.3f, 0.35f, 0.55f, 1.0f};
      for (int n = 0; n < 3; ++n) {
        Vec3 a{0, 0, 0};
        a[n] = 1;
        ax[3 * n + 0] = float(0.42 * e * dot(a, right));
        ax[3 * n + 1] = float(-0.42 * e * dot(a, up));
        ax[3 * n + 2] = float(dot(a, -fwd));
      }
      glUniform3fv(p["u_axis[0]"], 3, ax);
      glUniform3fv(p["u_axis_color[0]"], 3, col);
      glDrawArrays(GL_TRIANGLES, 0, 3);
    }
  }
  glDisable(GL_BLEND);
  m.mark(tg, 3);
  tg.timed = true;
  check_gl("rendering a frame");
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
