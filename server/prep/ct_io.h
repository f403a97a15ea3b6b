// Reading CT images (DICOM series, NIfTI, NRRD, MetaImage) into the project's own
// types. ITK is used only in ct_io.cpp; nothing of it shows here.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/path_policy.h"
#include "core/scene.h"
#include "core/volume.h"

namespace palpsim {

/// What a CT file holds, read from its header (and, after reading, its values).
struct CtInfo {
  std::string path;              // the file or DICOM folder as given
  std::string format;            // "DICOM", "NIfTI", "NRRD", "MetaImage" or the ITK reader's name
  std::string pixel_type;        // the voxels' component type as read: "uint8", "int16", "float", ...
                                 // (DICOM: after the rescale slope and intercept)
  std::string stored_pixel_type; // the component type in the file (DICOM: before rescaling)
  std::string series_uid;        // DICOM only: the SeriesInstanceUID read
  std::vector<std::string> files;  // every file the image consists of (for hashing)
  Grid grid;                     // input geometry: size, spacing (mm), origin (mm), direction (LPS)
  double min_value = 0;          // smallest voxel value (HU for a CT)
  double max_value = 0;          // largest voxel value
};

/// A CT read into float voxels on its own (possibly anisotropic) grid.
struct CtImage {
  Volume<float> image;
  CtInfo info;
};

/// Reads the header of the CT at `path` (a file, or a folder holding a DICOM
/// series; prep.dicom_series_uid picks one of several series) without reading
/// the voxels. Every file it opens goes through `files` (core/path_policy.h): the CT,
/// the data file a detached header names, every file of a DICOM folder; each must be a
/// regular file inside its folders after links are resolved. Without `files` (nullptr:
/// the operator's own CT), the CT's own folder is the one allowed. NIfTI, NRRD and
/// MetaImage headers are checked by check_ct_header (ct_header.h) before ITK reads them,
/// and every CT's size, spacing, origin and direction before ITK builds an image from
/// them. Throws palpsim::Error, one line naming the path and the field, for a missing
/// path, a folder without DICOM, an unreadable or corrupt header, a 2D or 4D image, a
/// vector image, a size, spacing, origin or direction no CT has (ct_header.h's bounds),
/// a file outside the folders, a FIFO or device, and one whose prepared patient would
/// need more than prep.max_memory_mb (estimated from the header's geometry, so a too
/// large CT is refused before its data are hashed, looked up in the cache or read).
CtInfo read_ct_info(const std::string& path, const PrepSettings& prep, const PathPolicy* files = nullptr);

/// Reads the CT's voxels as float after read_ct_info's checks (the memory estimate
/// included), and refuses (palpsim::Error naming the path) when the data are truncated
/// or corrupt, and when a voxel is NaN or Inf (saying so when none is finite).
CtImage read_ct(const std::string& path, const PrepSettings& prep, const PathPolicy* files = nullptr);

}  // namespace palpsim
