// The frame a training station sees: a GPU ray cast of the whole CT (a 3D texture) with
// the session's deformed VOI (J) drawn over it, beside three orthogonal slices of J
// through the tip (the paper's Fig. 5 layout), composited into one RGB frame.
//
// Layout of a W x H frame: the 3D view fills the left (W - H/3) x H; the right column
// holds three square slices of edge H/3, top to bottom axial (k plane), coronal (j
// plane), sagittal (i plane) of the patient grid, each with a coloured frame and the
// lines where the other two cut it. Voxels outside the body mask C render as air (the CT
// table and blankets are not drawn), in the deformed VOI too (by the undeformed mask).
//
// All methods run on the thread whose EglContext is current (the server's render thread).
#pragma once

#include <cstdint>
#include <initializer_list>
#include <memory>
#include <vector>

#include "core/patient.h"
#include "deform/deform_math.h"
#include "render/view.h"

namespace palpsim::render {

using deform::Voi;

/// Where the markers, camera and slices go in one frame (mm, LPS).
struct FrameMarks {
  bool has_tip = false;       // false before the session's first pose: no markers, view centre only
  Vec3 tip_mm{0, 0, 0};       // device tip x
  Vec3 proxy_mm{0, 0, 0};     // proxy p
  bool contact = false;       // the tip is in the body (the marker turns from green to orange)
};

/// Time of each stage of one frame (ms). On a GPU the GL stages (ray cast, slices,
/// composite) are GPU times from timestamp queries, so no stage waits for the one before;
/// on a software rasteriser, and for the other stages, wall times with the work finished.
struct FrameTimes {
  double j_to_texture_ms = 0;  // J of the VOI into the overlay texture
  double raycast_ms = 0;       // the 3D view
  double slices_ms = 0;        // the three slices
  double composite_ms = 0;     // markers, frames and cut lines over the views
  double readback_ms = 0;      // the frame into host or CUDA memory
  double encode_ms = 0;        // JPEG
  double total_ms = 0;         // all of the above
};

/// Adds every stage of `b` to `a` (sums over frames, for means).
inline void add_times(FrameTimes& a, const FrameTimes& b) {
  a.j_to_texture_ms += b.j_to_texture_ms;
  a.raycast_ms += b.raycast_ms;
  a.slices_ms += b.slices_ms;
  a.composite_ms += b.composite_ms;
  a.readback_ms += b.readback_ms;
  a.encode_ms += b.encode_ms;
  a.total_ms += b.total_ms;
}

/// Every stage of `t` times `k` (a sum over n frames times 1/n is their mean).
inline FrameTimes scaled(FrameTimes t, double k) {
  for (double* v : {&t.j_to_texture_ms, &t.raycast_ms, &t.slices_ms, &t.composite_ms, &t.readback_ms, &t.encode_ms,
                    &t.total_ms})
    *v *= k;
  return t;
}

/// What a frame's 3D view trades between accuracy and time (the scene's render section).
struct RenderQuality {
  double ray_step_vox = 1.0;  // ray step (voxel), 0.25..4; the pre-integrated table is made for it
  bool half_float_ct = false; // the CT texture as 16-bit floats: half the memory and texture
                              // traffic; steps of 0.5 HU at 1000 HU, 1 HU above 2048 HU
};

/// Renders frames of one patient. Owns the CT's 3D texture (shared by all sessions),
/// one overlay per session (a 3D texture holding J on the session's VOI) and the
/// framebuffers (targets) the frames are drawn into: target 0 always exists; more can
/// be added so that several frames are drawn one after another and encoded together
/// (the render thread's batches: each switch between GL and CUDA costs a GPU time slice
/// while the deformation runs, so fewer switches mean more frames).
class FrameRenderer {
 public:
  /// A session's overlay handle.
  using OverlayId = int;
  /// A framebuffer's handle; 0 is the default one.
  using TargetId = int;

  /// Uploads the patient's intensity (voxels outside the body mask as air) into a 3D
  /// texture and builds the shaders and transfer functions. Throws palpsim::Error
  /// naming the limit when the grid exceeds GL_MAX_3D_TEXTURE_SIZE or a shader fails.
  explicit FrameRenderer(PatientPtr patient, const RenderQuality& quality = {});
  ~FrameRenderer();
  FrameRenderer(const FrameRenderer&) = delete;
  FrameRenderer& operator=(const FrameRenderer&) = delete;

  /// A new overlay able to hold a VOI of up to `max_voi` voxels (deform.voi_edge^3, or
  /// the whole grid); it starts empty (J = I).
  OverlayId add_overlay(const Vec3i& max_voi);
  /// Frees an overlay's texture.
  void remove_overlay(OverlayId id);
  /// Writes J on `voi` (voi.count() floats, i fastest, host memory) into the overlay
  /// by a sub-box upload; the frame then shows J there and I elsewhere.
  void upload_overlay(OverlayId id, const Voi& voi, const float* j);
  /// The overlay shows J on `voi`, which the caller has already written into
  /// overlay_texture() at offset 0 (CUDA-GL interop).
  void set_overlay_box(OverlayId id, const Voi& voi);
  /// The overlay shows nothing: the session is undeformed (J = I everywhere).
  void clear_overlay(OverlayId id);
  /// The overlay's GL texture name (GL_TEXTURE_3D, GL_R32F, max_voi voxels; J's voxel
  /// (i, j, k) of the VOI at texel (i, j, k)), for CUDA-GL interop.
  unsigned overlay_texture(OverlayId id) const;

  /// A new framebuffer, sized at its first frame.
  TargetId add_target();
  /// Frees a framebuffer (not target 0).
  void remove_target(TargetId t);
  /// Lets the driver drop what it keeps of the frames drawn so far, for when nothing will
  /// be drawn for a while: target 0 becomes 1 x 1, is cleared and left bound, and no
  /// texture stays bound. Mesa's llvmpipe holds the last framebuffer's texture (33 MB at
  /// 3840 x 2160) and the last textures sampled until the next draw, even once deleted.
  void release_frame_state();

  /// Renders one frame of the session whose overlay is `id` at view.width x view.height
  /// into target 0; `view` must pass check_view. Adds the ray cast, slices and
  /// composite times to `times` (on a GPU, waiting for the frame).
  void render(OverlayId id, const ViewSettings& view, const FrameMarks& marks, FrameTimes& times);
  /// Queues the same frame into target `t` without waiting for the GPU; draw_times()
  /// gives its stage times later.
  void draw(OverlayId id, TargetId t, const ViewSettings& view, const FrameMarks& marks);
  /// Adds the stage times of target t's latest frame to `times` (waits for it on a GPU).
  void draw_times(TargetId t, FrameTimes& times);

  /// Target t's last frame as RGB8, rows top-down (width(t) * height(t) * 3 bytes);
  /// adds the readback time to `times`.
  void read_rgb(std::vector<std::uint8_t>& rgb, FrameTimes& times) { read_rgb(0, rgb, times); }
  void read_rgb(TargetId t, std::vector<std::uint8_t>& rgb, FrameTimes& times);
  /// The GL texture holding target t's last frame (GL_TEXTURE_2D, GL_RGBA8; texel row 0
  /// is the image's top row), for CUDA-GL interop and GPU encoding; 0 before its first.
  unsigned color_texture(TargetId t = 0) const;
  /// Size of target t's last frame (pixels).
  int width(TargetId t = 0) const;
  int height(TargetId t = 0) const;

  /// GPU memory the renderer holds (bytes): CT texture, overlays, framebuffers.
  std::size_t bytes() const;
  /// The patient it draws.
  const Patient& patient() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace palpsim::render
