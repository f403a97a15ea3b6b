// Writing a prepared patient: NRRD volumes with their physical geometry (they open
// in 3D Slicer), the preview PNG (three orthogonal slices of F with the skin
// contour, like the paper's Fig. 1), and the output folder written atomically.
#pragma once

#include <array>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "core/patient.h"
#include "core/volume.h"

namespace palpsim {

/// Writes a float volume as a NRRD file (raw, little-endian, space
/// left-posterior-superior, space directions and origin in mm).
void write_nrrd(const std::string& path, const Volume<float>& v);
/// Writes a 0/1 mask as an unsigned 8-bit NRRD file (same geometry fields).
void write_nrrd(const std::string& path, const Volume<std::uint8_t>& v);

/// Writes `img` (width x height RGB pixels, row by row from the top) as a PNG file, each
/// pixel repeated `scale` times along x and y; throws Error naming the file on failure.
void write_rgb_png(const std::string& path, const std::vector<std::array<std::uint8_t, 3>>& img, int width,
                   int height, int scale);

/// What the preview shows beside F's slices.
struct PreviewOptions {
  std::vector<std::string> caption;  // lines under the slices (PrepReport::summary_lines)
  bool border_is_skin = true;        // prep.cut_faces = "skin": the skin contour follows the image's border
  /// Thresholds drawn on the intensity histogram under the slices (NaN: not drawn), in `units`.
  double air_threshold = std::numeric_limits<double>::quiet_NaN();
  double bone_low = std::numeric_limits<double>::quiet_NaN();
  double bone_high = std::numeric_limits<double>::quiet_NaN();
  std::string units = "HU";          // "HU", or "image units" for an image not in HU
};

/// Writes preview.png: axial, coronal and sagittal slices of F through `centre_mm`
/// (grey: the square root of F over its 99th percentile in the body), skin contour (the border of
/// C) in red, bone contour in yellow; patient's right on the image's left, anterior and
/// superior up; below them the `caption` lines (PrepReport::summary_lines: thresholds,
/// bone per region), those starting with "warning" in orange. Where the image's border
/// cuts the body the skin contour follows the border when `o.border_is_skin`
/// (prep.cut_faces = "skin") and is left open there otherwise. Between slices and
/// caption, when a threshold is set, the histogram of every voxel's value (log counts)
/// with the air threshold in cyan and the bone thresholds in yellow (low) and orange
/// (seeds), so a user of an image not in HU sees where the chosen values fall.
void write_preview_png(const std::string& path, const Patient& p, const Vec3& centre_mm,
                       const PreviewOptions& o = {});

/// A good place for the preview's slices: the centre of the bone mask's bounding
/// box (the spine and pelvis), else the centre of the body.
Vec3 preview_centre_mm(const Patient& p);

/// Writes every output of palpsim-prep (F.nrrd, body.nrrd, bone.nrrd,
/// dist_bone.nrrd, dist_skin.nrrd, preview.png, prep.json) into a temporary
/// sibling folder of `out_dir` and renames it to `out_dir` at the end (an existing
/// `out_dir` is replaced only then); on any error nothing half-written is left.
/// `preview` says what the preview shows beside the slices.
void write_patient_outputs(const std::string& out_dir, const Patient& p, const std::string& prep_json,
                           const PreviewOptions& preview = {});

}  // namespace palpsim
