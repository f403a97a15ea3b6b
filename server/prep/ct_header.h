// CT headers checked before ITK reads them: NIfTI-1 (.nii, .nii.gz), NRRD (.nrrd, .nhdr)
// and MetaImage (.mha, .mhd) parsed from their bytes by plain C++ (no ITK), so a value on
// which ITK would abort (VNL's "matrix has non-finite elements") or compute nonsense is
// refused with one line naming the file and the field. The check never aborts, never
// allocates more than a bounded amount and never hangs, whatever the bytes: a libFuzzer
// target may drive check_ct_header directly. DICOM goes through ITK/GDCM (ct_io.cpp).
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

namespace palpsim {

/// Voxels along one axis of a CT, at most (DICOM's rows and columns are 16-bit).
constexpr std::int64_t kMaxCtAxisVoxels = 65536;
/// Voxels of a CT, at most (2^34: 64 GiB as float); larger ones are refused before
/// anything is allocated, whatever prep.max_memory_mb allows.
constexpr std::int64_t kMaxCtVoxels = std::int64_t(1) << 34;
/// Voxel spacing (mm) a CT may have: from a micrometre to a metre.
constexpr double kMinCtSpacingMm = 1e-3;
constexpr double kMaxCtSpacingMm = 1e3;
/// Extent (mm) of a CT along each axis, at most: 10 m, five times a whole-body scan; it
/// keeps the patient grid's voxel counts far from integer overflow at any prep.spacing_mm.
constexpr double kMaxCtExtentMm = 1e4;
/// |origin| (mm) along each physical axis, at most: 1 km.
constexpr double kMaxCtOriginMm = 1e6;
/// A number in a header's geometry fields (pixdim, quaternion, sform rows, space
/// directions, offsets, matrices) larger than this in magnitude is refused: no CT has it,
/// and ITK's products of such numbers overflow.
constexpr double kMaxHeaderNumber = 1e9;
/// Header bytes read and parsed at most (a NRRD or MetaImage header longer than this, or
/// whose end is not found within it, is refused).
constexpr std::size_t kMaxCtHeaderBytes = 1 << 20;

/// What a CT file's header declares, as far as the checks need it.
struct CtHeader {
  std::string format;                  // "NIfTI", "NRRD" or "MetaImage"
  int dimensions = 0;                  // axes the header declares
  std::vector<std::int64_t> size;      // voxels along each of them
  std::string data_file;               // detached data: the file the header names, as written
                                       // ("" = the voxels follow the header in the same file)
  // NIfTI only: where the voxels start, their type and byte order
  std::int64_t vox_offset = 0;         // bytes from the start of the (decompressed) file
  int datatype = 0;                    // NIfTI datatype code (16 = float32, 64 = float64, ...)
  int bytes_per_voxel = 0;
  bool big_endian = false;
};

/// The format the name's extension says: "NIfTI" (.nii, .nii.gz), "NRRD" (.nrrd, .nhdr),
/// "MetaImage" (.mha, .mhd), or "" for any other name (case is ignored).
std::string ct_format_of_name(const std::string& name);

/// Parses and checks the header at the start of `bytes` (a file's first bytes, at least
/// its header; a .nii.gz file's compressed bytes) of the format ct_format_of_name(name)
/// says, naming `name` in messages. Refuses, with one palpsim::Error line naming the file
/// and the field: a missing or corrupt header; a dimension count other than 3 (or extra
/// axes of one voxel); a size below 1 or above kMaxCtAxisVoxels; more than kMaxCtVoxels
/// voxels; a non-finite or oversized (kMaxHeaderNumber) geometry number; more than one
/// value per voxel; NIfTI-2, Analyze and .hdr/.img pairs; data in several files (NRRD
/// "LIST" or patterns, MetaImage "LIST" or patterns). Never aborts or hangs.
CtHeader check_ct_header(const std::string& name, std::string_view bytes);

/// check_ct_header on the file at `path`: its first kMaxCtHeaderBytes bytes, read only
/// when it is a regular file (opened without blocking).
CtHeader check_ct_header_file(const std::string& path);

}  // namespace palpsim
