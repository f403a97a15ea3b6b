// The 3D view's camera of a frame (view.h's orbit) and the ray through one of its
// pixels, without GL: the frame renderer draws with it, and the control thread answers
// PickRequest with it (the first body voxel under a pixel), so a click on a frame and
// the frame itself agree on what each pixel shows.
#pragma once

#include <optional>

#include "core/grid.h"
#include "core/patient.h"
#include "render/view.h"

namespace palpsim::render {

/// `v` scaled to unit length (a zero vector stays zero).
Vec3 normalized(const Vec3& v);

/// Half the vertical field of view of the 3D view at zoom 1 (degrees).
constexpr double kHalfFovDeg = 15;

/// A frame's 3D view: where the camera is and how its pixels spread (mm, LPS).
struct Camera {
  Vec3 eye{0, 0, 0};     // camera position
  Vec3 fwd{0, 0, 0};     // unit view direction
  Vec3 right{0, 0, 0};   // unit screen right
  Vec3 up{0, 0, 0};      // unit screen up
  double tan_h = 0;      // tangent of half the vertical field of view
  double aspect = 1;     // the 3D view's width / height
  double dist_mm = 0;    // eye to the look-at point
  int view_w = 0;        // the 3D view's width (pixels): the frame's left part
  int height = 0;        // the frame's height (pixels)
};

/// The frame layout's 3D view width for a W x H frame (pixels): W minus the slice
/// column of edge min(H / 3, W).
int view_width(int width, int height);

/// The camera of `view` on grid `g` looking at `target_mm` (the tip, center_mm or the
/// body's centre: frame_target): on its orbit at a distance that frames the grid's
/// bounding sphere at zoom 1.
Camera orbit_camera(const Grid& g, const ViewSettings& view, const Vec3& target_mm);

/// The point a frame looks at: the tip when following it and there is one, else
/// center_mm when set, else the body's centre `body_center_mm`.
Vec3 frame_target(const ViewSettings& view, bool has_tip, const Vec3& tip_mm, const Vec3& body_center_mm);

/// The body's centre as the renderer takes it: the middle of the body mask's voxel
/// index box (the whole grid's when the mask is empty), in physical space (mm).
Vec3 body_center(const Grid& g, const Vec3i& body_lo, const Vec3i& body_hi);

/// body_center of a patient's body mask (scans the mask: once per patient, not per frame).
Vec3 body_center(const Patient& p);

/// The unit direction of the ray through pixel (x_px, y_px) of the frame (x from the
/// left edge, y from the top, pixel centres at .5), as the ray caster casts it; nullopt
/// for a point outside the 3D view (the slice column, or outside the frame).
std::optional<Vec3> pixel_ray(const Camera& c, double x_px, double y_px);

/// The first point along the ray from `origin_mm` in unit direction `dir` that lies in
/// the body mask C (nearest voxel), located to 0.01 voxel; nullopt when the ray misses
/// the body within the grid.
std::optional<Vec3> first_body_hit(const Patient& p, const Vec3& origin_mm, const Vec3& dir);

}  // namespace palpsim::render
