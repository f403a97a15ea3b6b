// The frame renderer's state (FrameRenderer::Impl), shared by its set-up and overlays
// (frame_renderer.cpp) and its drawing (frame_draw.cpp); for those two files only.
#pragma once

#include <chrono>
#include <map>

#include "render/frame_renderer.h"
#include "render/gl_program.h"

namespace palpsim::render {

using Clock = std::chrono::steady_clock;

constexpr int kBlockVox = 8;  // edge of the blocks for skipping faint space (voxel)

// texture units of the volume shaders (the binding = N in shaders.h)
enum Unit { kUnitCt = 0, kUnitOverlay = 1, kUnitBody = 2, kUnitTf = 3, kUnitBlock = 4 };

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

  // the steps of one frame (frame_draw.cpp), on what they share
  struct Frame;
  void set_up_ray(Program& p, const Frame& f);
  void cast_rays(const Frame& f);
  void draw_slices(const Frame& f);
  void draw_slice_marks(const Frame& f);
  void draw_triad(const Frame& f);
};

}  // namespace palpsim::render
