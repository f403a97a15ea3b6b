// The stages that turn a CT volume into a patient: isotropic resampling, body
// mask C, bone mask, distance maps, force image F and its gradient. Plain C++ on
// the project's own types (no ITK), so benchmarks and tests can run each stage.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>
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

/// The thresholds the bone mask used and why (reported in prep.json). With an
/// explicit prep.bone_threshold, low = high = that value (a plain threshold, as
/// before); without one they are chosen from the body's intensity histogram
/// (choose_bone_thresholds).
struct BoneThresholds {
  bool automatic = false;        // chosen from the image (the scene set no prep.bone_threshold)
  double low = 200;              // HU: voxels at or above it are bone when joined to a seed
  double high = 200;             // HU: seeds; voxels at or above it start bone
  double cancellous = 80;        // HU: a cavity enclosed in 3D, or in a coronal or sagittal slice, with
                                 // at least this mean is filled
  double cancellous_axial = 80;  // HU: the same for a cavity enclosed in an axial slice (no disc is)
  double thin_seed = 200;        // HU: voxels at or above it in thin ridges apart from contrast start bone
                                 // too (a rib's cortex blurred by partial volume); = high when unused
  double grow_mm = 0;            // the low threshold reaches this far (mm) from a seed; 0 = unlimited
  double soft_tissue_hu = 0;     // automatic: the soft-tissue peak of the body's histogram (HU)
  double soft_tissue_sigma_hu = 0;  // automatic: its spread (HU), from the upper half width at half height
  double disc_lo = 0, disc_hi = 0;  // HU: soft tissue [disc_lo, disc_hi) that a cavity enclosed only in
                                    // axial slices leaves open voxel by voxel (a disc; none when lo >= hi)
  std::string reason;            // one sentence: where the values come from
};

/// Bounds (HU) on the automatic thresholds: the low one stays within
/// [kAutoBoneLowMinHu, kAutoBoneLowMaxHu] (above discs, muscle and enhanced
/// organs; at or below the 140-160 HU of a thick-slice vertebral body), the seeds
/// at or above kAutoBoneSeedMinHu (cortical bone, above most contrast in vessels).
constexpr double kAutoBoneLowMinHu = 110;
constexpr double kAutoBoneLowMaxHu = 180;
constexpr double kAutoBoneSeedMinHu = 300;
/// Lower seeds: a rib's cortex on thick slices or 3 mm voxels is blurred by partial
/// volume to 170-290 HU, below the cortical seeds. A voxel at or above
/// BoneThresholds::thin_seed, mu + kThinSeedSpan (low - mu) (half as far again above
/// soft tissue as the low threshold), seeds bone too where those voxels form a thin
/// ridge: not within kThinSeedHalfWidthMm (and a voxel) of one of them farther than
/// kThinSeedHalfWidthMm from any darker voxel (a vessel's lumen that bright is thick),
/// and not within kThinSeedClearMm of a contrast-filled region (contrast.h's
/// find_contrast_regions, run before the mask: large, smooth and without cortex), whose
/// noise reaches the level here and there.
constexpr double kThinSeedSpan = 1.5;
constexpr double kThinSeedHalfWidthMm = 3;
constexpr double kThinSeedClearMm = 3;
/// A bone component smaller than prep.bone_min_volume_ml is kept when it lies within
/// this distance (mm) of a larger one: the end of a rib that partial volume on thick
/// slices cuts off from the rest (vessels with contrast, calcifications and noise
/// apart from bone still go).
constexpr double kBonePieceGapMm = 10;
/// How far (mm) the automatic low threshold grows from a seed: half a lumbar
/// vertebral body's width, so its cancellous bone is reached from the cortex on
/// either side; a vessel or organ at or above the low threshold that touches bone
/// is taken no deeper than that.
constexpr double kAutoBoneGrowMm = 15;
/// Bounds (HU) on the automatic cancellous level: cavities of intervertebral discs
/// (70-90 HU in the shared scans) stay open, the darker centres of thick-slice
/// vertebral bodies (100-160 HU) are filled. Axial slices, where a disc is never
/// enclosed by bone but the spinal canal (CSF, 0-40 HU) is, use a level
/// kAxialCancellousDropHu lower.
constexpr double kAutoCancellousMinHu = 100;
constexpr double kAutoCancellousMaxHu = 120;
constexpr double kAxialCancellousDropHu = 40;
/// The soft-tissue band a cavity enclosed only in axial slices leaves open, voxel by
/// voxel: mu - kDiscBandBelow sigma .. mu + kDiscBandAbove sigma. On thin slices
/// (the shared DICOM series at 2 mm) the closing joins two vertebral bodies' rims
/// across their disc, so the disc's axial slices are enclosed, and with the end plates'
/// partial volume their mean passes any cancellous level; the disc's own voxels lie
/// at soft tissue (70-110 HU), a vertebral body's cancellous bone above it and its
/// fatty marrow below it, so the band takes out the disc and little of the bone.
constexpr double kDiscBandBelow = 2;
constexpr double kDiscBandAbove = 1;

/// Chooses the bone thresholds for `image` inside `body`: prep.bone_threshold when
/// the scene set it, else from the histogram of the body's voxels: the soft-tissue
/// peak mu (the mode between -50 and 150 HU) and its spread sigma (upper half width
/// at half height / 1.18); low = mu + max(100, 3 sigma) clamped to
/// [kAutoBoneLowMinHu, kAutoBoneLowMaxHu], high = max(kAutoBoneSeedMinHu,
/// mu + 2 (low - mu)), thin_seed = min(high, mu + kThinSeedSpan (low - mu)),
/// cancellous = mu + 0.5 (low - mu) clamped to [kAutoCancellousMinHu,
/// kAutoCancellousMaxHu], cancellous_axial = cancellous - kAxialCancellousDropHu,
/// grow_mm = kAutoBoneGrowMm, the disc band from kDiscBandBelow and kDiscBandAbove.
/// Throws palpsim::Error for an empty body.
BoneThresholds choose_bone_thresholds(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                      const PrepSettings& prep);

/// Bone mask with hysteresis: seeds (body voxels >= t.high, and those >= t.thin_seed
/// in thin ridges apart from contrast-filled regions, see kThinSeedSpan) grown into the
/// 6-connected body voxels >= t.low that lie within t.grow_mm of a seed, closed
/// with a ball of prep.bone_closing_mm, cavities enclosed by bone filled
/// (prep.bone_fill_holes: the cancellous interior of a vertebral body is rigid
/// too), and components smaller than prep.bone_min_volume_ml removed. A cavity is
/// filled when it is enclosed in 3D, or when, after a wider closing of
/// `fill_closing_mm` (a cortex blurred by thick slices has gaps; build_patient
/// passes twice the input's coarsest spacing), it is enclosed within an axial,
/// coronal or sagittal slice, covers at most kMaxBoneHoleMm2 there, and its mean
/// value reaches t.cancellous (t.cancellous_axial in an axial slice, whose voxels in
/// [t.disc_lo, t.disc_hi) stay open, as they do where only the closing's 3D fill
/// after the slices would enclose them). That fills vertebral bodies but not the
/// spinal canal (CSF), the discs, the pelvis or the thorax.
constexpr double kMaxBoneHoleMm2 = 2500;
Volume<std::uint8_t> bone_mask(const Volume<float>& image, const Volume<std::uint8_t>& body,
                               const BoneThresholds& t, const PrepSettings& prep, double fill_closing_mm = 0,
                               int threads = 0);

/// Same, with the thresholds of choose_bone_thresholds(image, body, prep).
Volume<std::uint8_t> bone_mask(const Volume<float>& image, const Volume<std::uint8_t>& body,
                               const PrepSettings& prep, double fill_closing_mm = 0, int threads = 0);

/// The mean value above which a cavity enclosed by bone counts as cancellous bone
/// with an explicit prep.bone_threshold: 80% of the way from prep.air_threshold to
/// prep.bone_threshold (80 HU with -400 and 200 HU: above CSF, fat and muscle,
/// below the cortex).
double cancellous_level(const PrepSettings& prep);

/// The vertebral column as prep finds it in a bone mask: bone in the spine region
/// (see BoneSummary) of consecutive axial slices, joined slice to slice across gaps
/// no longer than a disc (kMaxDiscGapMm) where its centroid moves left or right less
/// than kMaxColumnShiftMm; of those chains the longest. It is a spine when it crosses at
/// least half the body's axial slices, its bone encloses a spinal canal (an unfilled
/// hole of kCanalMinMm2..kCanalMaxMm2) in at least kCanalMinFraction of its slices and
/// two of them, and it shows vertebrae: at least two segments (runs of kMinSegmentMm or
/// more between disc levels, slices whose bone area falls below kSegmentLevel of the
/// largest within kMaxDiscGapMm on both sides), unless it is shorter than
/// kTwoVertebraeMm. A contrast-filled heart or aorta is a column without canal.
struct SpineColumn {
  bool found = false;       // a spine: long enough, with a canal and segments
  int slices = 0;           // axial slices from its first to its last (gaps included)
  int bone_slices = 0;      // of those, slices holding at least kSpineMinAreaMm2 of its bone
  int segments = 0;         // vertebra-like segments
  int canal_slices = 0;     // slices where its bone encloses a canal-sized hole
  double from_mm = 0, to_mm = 0;  // its ends along the superior axis (mm, physical z of the first and last slice)
  double length_mm = 0;     // to_mm - from_mm
  Vec3 centroid_mm;         // centroid of its bone (LPS, mm)
  std::string reason;       // one sentence: why it is, or is not, a spine
};
/// Gap (mm) between slices of bone that a column bridges: a lumbar disc with the
/// end plates' partial volume.
constexpr double kMaxDiscGapMm = 20;
/// Left-right shift (mm) of the spine region's bone centroid between joined slices:
/// more is another structure (antero-posterior shifts are allowed: a sloping
/// spinous process alone meets the next vertebral body).
constexpr double kMaxColumnShiftMm = 20;
/// A slice is at a disc's level when its bone area falls below this fraction of the
/// largest within kMaxDiscGapMm above and below: a disc's level holds only the posterior
/// elements (0.4-0.7 of a vertebral body's level in the shared abdomen).
constexpr double kSegmentLevel = 0.75;
/// A column shorter than this (mm) may show a single vertebra and no disc.
constexpr double kTwoVertebraeMm = 60;
/// A segment is at least this long (mm): a vertebral body is 20-30 mm tall.
constexpr double kMinSegmentMm = 10;
/// Spinal canal size (mm^2) in an axial slice: a lumbar canal is 150-300 mm^2, a
/// thoracic one 100-200 mm^2.
constexpr double kCanalMinMm2 = 40, kCanalMaxMm2 = 700;
/// Fraction of the column's slices that must show the canal (at pedicle levels,
/// a third to half of a vertebra's height; 0.36-0.49 in the shared scans).
constexpr double kCanalMinFraction = 0.15;

/// What a user needs to judge a bone mask at a glance: bone volume per region and
/// warnings where it looks implausible. Regions, per axial slice, relative to the
/// body in that slice: "spine" (within kSpineHalfWidthMm of the body's left-right
/// centre and posterior of its antero-posterior centre less kSpineAnteriorMm),
/// "left" and "right" (beyond kSpineHalfWidthMm on the patient's left, +x, or
/// right: ribs, pelvis, arms), "anterior" (the rest: sternum, pubis). Whether
/// there is a spine is the column's (SpineColumn), not the region's.
struct BoneSummary {
  double body_ml = 0;            // volume of the body mask (ml)
  double bone_ml = 0;            // volume of the bone mask (ml)
  double spine_ml = 0, left_ml = 0, right_ml = 0, anterior_ml = 0;  // bone per region (ml)
  int body_slices = 0;           // axial slices holding body
  int spine_slices = 0;          // of those, slices with at least kSpineMinAreaMm2 of bone in the spine region
  SpineColumn column;            // the vertebral column found in the spine region
  bool spine_found = false;      // column.found
  double bone_fraction = 0;      // bone_ml / body_ml
  std::vector<std::string> warnings;  // one sentence each; empty when the mask looks plausible
};
/// Half width (mm) of the spine region: a lumbar vertebra with its transverse
/// processes; ribs and iliac wings lie beyond.
constexpr double kSpineHalfWidthMm = 40;
/// How far (mm) in front of the body's antero-posterior centre the spine region
/// reaches (the front of the lumbar vertebral bodies lies about at that centre in
/// the shared abdomen; thoracic ones lie further back).
constexpr double kSpineAnteriorMm = 20;
/// Bone area (mm^2) in the spine region that counts an axial slice as showing the
/// spine: a lamina or a spinous process at a disc's level is more.
constexpr double kSpineMinAreaMm2 = 50;
/// Bone above this fraction of the body is implausible (an adult's skeleton is
/// about 10-15% of the body's volume, less in a trunk scan).
constexpr double kMaxBoneFraction = 0.25;

/// Measures `bone` against `body` (same grid) as BoneSummary describes.
BoneSummary summarize_bone(const Volume<std::uint8_t>& body, const Volume<std::uint8_t>& bone);

/// Labels 6-connected components of `mask` and clears those smaller than
/// `min_voxels`; returns the number of components kept.
int remove_small_components(Volume<std::uint8_t>& mask, std::size_t min_voxels);

/// The 6-connected components of `mask`'s non-zero voxels: `labels` gets 1..n for
/// them (0 elsewhere); returns n.
std::uint32_t component_labels(const Volume<std::uint8_t>& mask, std::vector<std::uint32_t>& labels);

/// The voxel counts of the 6-connected components of `mask`, largest first.
std::vector<std::size_t> component_sizes(const Volume<std::uint8_t>& mask);

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
