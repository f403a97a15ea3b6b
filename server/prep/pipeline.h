// The stages that turn a CT volume into a patient: isotropic resampling, body
// mask C, bone mask, distance maps, force image F and its gradient. Plain C++ on
// the project's own types (no ITK), so benchmarks and tests can run each stage.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <vector>

#include "core/patient.h"
#include "core/scene.h"
#include "core/volume.h"

namespace palpsim {

/// Edge (mm) of the isotropic patient grid: `requested` when > 0, else the
/// smallest input spacing clamped to [0.5, 2] mm.
double patient_spacing_mm(const Grid& input, double requested_mm);

/// The isotropic grid covering the input's voxel centres with edge `spacing_mm`;
/// it keeps the input's origin and direction (the patient stays in the CT's
/// physical space, oblique directions included; nothing is axis-aligned).
Grid isotropic_grid(const Grid& input, double spacing_mm);

/// Bytes the preparation needs at its peak for an input grid and a patient grid
/// (input voxels as float, the patient's volumes, and working buffers); checked
/// against prep.max_memory_mb before anything large is allocated.
std::size_t estimate_prep_bytes(const Grid& input, const Grid& patient);

/// Linear (trilinear) resampling of `in` onto `out`; points outside the input's
/// voxel centres get `outside_value` (air).
Volume<float> resample_linear(const Volume<float>& in, const Grid& out, float outside_value, int threads = 0);

/// The grid axis (0, 1, 2) most parallel to physical axis `physical` (0 = x, L;
/// 1 = y, P; 2 = z, S).
int grid_axis_along(const Grid& g, int physical);

/// The grid axis most parallel to the physical superior axis; axial slices are
/// perpendicular to it.
inline int axial_axis(const Grid& g) { return grid_axis_along(g, 2); }

/// Body mask C: 1 for the patient, 0 for outside air, the CT table and other thin
/// structures outside the body (blankets, cables). Voxels >= air_threshold are
/// tissue candidates; a morphological opening of `opening_mm` (prep.body_opening_mm)
/// cuts thin structures (the table's shell) off the body, components smaller than
/// `min_part_ml` (prep.body_min_part_ml) are dropped except the largest (arms apart
/// from the torso are kept), and air
/// enclosed within each axial slice (bowel gas, lungs, airways cut by the first
/// or last slice) is filled. The body may touch the volume border.
Volume<std::uint8_t> body_mask(const Volume<float>& image, double air_threshold, double opening_mm = 5.0,
                               double min_part_ml = 20.0, int threads = 0);

/// Bone mask: voxels of the body >= prep.bone_threshold, closed with a ball of
/// prep.bone_closing_mm, cavities enclosed by bone filled (prep.bone_fill_holes:
/// the cancellous interior of a vertebral body is rigid too), and components
/// smaller than prep.bone_min_volume_ml removed. A cavity is filled when it is
/// enclosed in 3D, or when, after a wider closing of `fill_closing_mm` (a cortex
/// blurred by thick slices has gaps; build_patient passes twice the input's
/// coarsest spacing), it is enclosed within an axial, coronal or sagittal slice,
/// covers at most kMaxBoneHoleMm2 there, and its mean value reaches
/// cancellous_level(prep). That fills vertebral bodies but not the spinal canal
/// (CSF), the pelvis or the thorax.
constexpr double kMaxBoneHoleMm2 = 2500;
Volume<std::uint8_t> bone_mask(const Volume<float>& image, const Volume<std::uint8_t>& body,
                               const PrepSettings& prep, double fill_closing_mm = 0, int threads = 0);

/// The mean value above which a cavity enclosed by bone counts as cancellous bone:
/// 80% of the way from prep.air_threshold to prep.bone_threshold (80 HU with the
/// defaults: above CSF, fat and muscle, below the cortex).
double cancellous_level(const PrepSettings& prep);

/// Labels 6-connected components of `mask` and clears those smaller than
/// `min_voxels`; returns the number of components kept.
int remove_small_components(Volume<std::uint8_t>& mask, std::size_t min_voxels);

/// Sets to 1 every 0-voxel of `mask` that no 6-connected path of 0-voxels links
/// to the volume's border (fills enclosed cavities in 3D).
void fill_holes_3d(Volume<std::uint8_t>& mask);

/// Same as fill_holes_3d, but within each slice perpendicular to `axis` (2D,
/// 4-connected): air enclosed in a slice is filled even where it reaches the
/// first or last slice. Holes of more than `max_hole_pixels` stay open.
/// `accept`, when set, sees each hole's voxel indices and decides whether it is filled.
using HoleFilter = std::function<bool(const std::vector<std::size_t>&)>;
void fill_holes_per_slice(Volume<std::uint8_t>& mask, int axis, std::size_t max_hole_pixels = SIZE_MAX,
                          const HoleFilter& accept = nullptr);

/// F = alpha*C/(beta+A) + gamma*B (eq. 1) from the patient's body, dist_bone_mm
/// and dist_skin_mm; A = +inf (no bone) gives F = gamma*B.
Volume<float> force_image(const Patient& p, const ForceImageSettings& f, int threads = 0);

/// grad F (mm/mm) in physical axes by central differences (one-sided at the border).
Volume<Vec3f> gradient_physical(const Volume<float>& f, int threads = 0);

/// Number of non-zero voxels.
std::size_t count_nonzero(const Volume<std::uint8_t>& m);

}  // namespace palpsim
