#include "prep/ct_io.h"

#include <algorithm>
#include <cstring>
#include <cmath>
#include <filesystem>
#include <sstream>

#include <unistd.h>

#include <zlib.h>

#include "core/error.h"
#include "core/path_policy.h"
#include "gdcmTrace.h"
#include "itkGDCMImageIO.h"
#include "itkGDCMSeriesFileNames.h"
#include "itkImage.h"
#include "itkImageFileReader.h"
#include "itkImageIOFactory.h"
#include "itkImageSeriesReader.h"
#include "itkMetaImageIO.h"
#include "itkNiftiImageIO.h"
#include "itkNrrdImageIO.h"
#include "itkObject.h"
#include "prep/ct_header.h"
#include "prep/pipeline.h"

namespace palpsim {
namespace {

namespace fs = std::filesystem;
using FloatImage = itk::Image<float, 3>;

std::string in_quotes(const std::string& s) { return "'" + s + "'"; }

// short name of an ITK component type ("uint8", "int16", "float", ...)
std::string component_name(itk::ImageIOBase::IOComponentType t) {
  using IO = itk::ImageIOBase;
  switch (t) {
    case IO::IOComponentEnum::UCHAR: return "uint8";
    case IO::IOComponentEnum::CHAR: return "int8";
    case IO::IOComponentEnum::USHORT: return "uint16";
    case IO::IOComponentEnum::SHORT: return "int16";
    case IO::IOComponentEnum::UINT: return "uint32";
    case IO::IOComponentEnum::INT: return "int32";
    case IO::IOComponentEnum::ULONG:
    case IO::IOComponentEnum::ULONGLONG: return "uint64";
    case IO::IOComponentEnum::LONG:
    case IO::IOComponentEnum::LONGLONG: return "int64";
    case IO::IOComponentEnum::FLOAT: return "float";
    case IO::IOComponentEnum::DOUBLE: return "double";
    default: return "unknown";
  }
}

// the project's format name from the ImageIO class
std::string format_name(const itk::ImageIOBase* io) {
  const std::string n = io->GetNameOfClass();
  if (n == "GDCMImageIO") return "DICOM";
  if (n == "NiftiImageIO") return "NIfTI";
  if (n == "NrrdImageIO") return "NRRD";
  if (n == "MetaImageIO") return "MetaImage";
  return n;
}

// the most specific line of an ITK (or teem, GDCM) error: its last non-empty line without
// the "itk::ERROR: Class(0x...): " and "[nrrd] function: " prefixes, cut at 200 characters
std::string itk_reason(const itk::ExceptionObject& e) {
  const std::string d = e.GetDescription() ? e.GetDescription() : "";
  std::string line;
  std::istringstream in(d);
  for (std::string l; std::getline(in, l);) {
    l.erase(0, l.find_first_not_of(" \t"));
    l.erase(l.find_last_not_of(" \t\r") + 1);
    if (!l.empty()) line = l;
  }
  if (line.rfind("itk::ERROR: ", 0) == 0 && line.find("): ") != std::string::npos) line.erase(0, line.find("): ") + 3);
  if (!line.empty() && line[0] == '[' && line.find("] ") != std::string::npos) {
    line.erase(0, line.find("] ") + 2);
    if (const auto c = line.find(": "); c != std::string::npos && line.find(' ') > c) line.erase(0, c + 2);
  }
  for (char& c : line)
    if (static_cast<unsigned char>(c) < 0x20) c = ' ';
  if (line.size() > 200) line = line.substr(0, 200) + "...";
  return line.empty() ? std::string("no reason given") : line;
}

// the geometry an ITK reader reports, as a Grid
template <typename Reader>
Grid grid_of(Reader* reader) {
  const FloatImage* img = reader->GetOutput();
  const auto size = img->GetLargestPossibleRegion().GetSize();
  Grid g;
  g.size = {int(size[0]), int(size[1]), int(size[2])};
  g.spacing_mm = {img->GetSpacing()[0], img->GetSpacing()[1], img->GetSpacing()[2]};
  g.origin_mm = {img->GetOrigin()[0], img->GetOrigin()[1], img->GetOrigin()[2]};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) g.direction[r * 3 + c] = img->GetDirection()[r][c];
  return g;
}

// refuses spacing, origin and direction no CT can have: each value finite, spacing from
// kMinCtSpacingMm to kMaxCtSpacingMm, origin within kMaxCtOriginMm, an orthonormal direction;
// `what` names the file
void check_grid_numbers(const Grid& g, const std::string& what) {
  const double sp[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z};
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(sp[a]) || sp[a] < kMinCtSpacingMm || sp[a] > kMaxCtSpacingMm) {
      std::ostringstream s;
      s << what << ": spacing along axis " << a << " is " << sp[a] << " mm; every voxel spacing must be a positive "
        << "finite length from " << kMinCtSpacingMm << " to " << kMaxCtSpacingMm << " mm";
      throw Error(s.str());
    }
  const double o[3] = {g.origin_mm.x, g.origin_mm.y, g.origin_mm.z};
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(o[a]) || std::abs(o[a]) > kMaxCtOriginMm) {
      std::ostringstream s;
      s << what << ": origin along axis " << a << " is " << o[a] << " mm; it must be finite and within "
        << kMaxCtOriginMm << " mm";
      throw Error(s.str());
    }
  // the direction must be orthonormal (the patient grid inverts it by transposing)
  const auto& d = g.direction;
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) {
      const double dot = d[a] * d[b] + d[3 + a] * d[3 + b] + d[6 + a] * d[6 + b];
      if (!std::isfinite(dot) || std::abs(dot - (a == b ? 1.0 : 0.0)) > 1e-3)
        throw Error(what + ": the direction (orientation) matrix is not orthonormal");
    }
}

// refuses spacing, origin, direction and size that no 3D CT can have (before ITK builds an
// image from them: VNL aborts on a non-finite matrix)
void check_geometry(const Grid& g, const std::string& path) {
  check_grid_numbers(g, "CT " + in_quotes(path));
  if (g.size.z <= 1 || g.size.y <= 1 || g.size.x <= 1) {
    std::ostringstream s;
    s << "CT " << in_quotes(path) << ": a 2D image (" << g.size.x << " x " << g.size.y << " x " << g.size.z
      << " voxels); a CT volume needs at least 2 voxels along each of its 3 axes";
    throw Error(s.str());
  }
  const Vec3i n = g.size;
  if (n.x > kMaxCtAxisVoxels || n.y > kMaxCtAxisVoxels || n.z > kMaxCtAxisVoxels ||
      double(n.x) * n.y * n.z > double(kMaxCtVoxels)) {
    std::ostringstream s;
    s << "CT " << in_quotes(path) << ": " << n.x << " x " << n.y << " x " << n.z << " voxels; a CT may have at most "
      << kMaxCtAxisVoxels << " along an axis and " << kMaxCtVoxels << " in all";
    throw Error(s.str());
  }
  const double extent[3] = {(n.x - 1) * g.spacing_mm.x, (n.y - 1) * g.spacing_mm.y, (n.z - 1) * g.spacing_mm.z};
  for (int a = 0; a < 3; ++a)
    if (extent[a] > kMaxCtExtentMm) {
      std::ostringstream s;
      s << "CT " << in_quotes(path) << ": " << extent[a] << " mm long along axis " << a << "; a CT spans at most "
        << kMaxCtExtentMm << " mm";
      throw Error(s.str());
    }
}

// the geometry an ImageIO read from a header, as a Grid (axes it lacks: 1 voxel of 1 mm);
// sizes beyond an int are clamped, for check_geometry to refuse
Grid io_grid(const itk::ImageIOBase* io) {
  Grid g;
  const unsigned dims = std::min(io->GetNumberOfDimensions(), 3u);
  int size[3] = {1, 1, 1};
  double sp[3] = {1, 1, 1}, o[3] = {0, 0, 0};
  for (unsigned a = 0; a < dims; ++a) {
    size[a] = int(std::min<std::size_t>(io->GetDimensions(a), std::size_t(kMaxCtAxisVoxels) + 1));
    sp[a] = io->GetSpacing(a);
    o[a] = io->GetOrigin(a);
    const std::vector<double> col = io->GetDirection(a);
    for (unsigned r = 0; r < 3; ++r) g.direction[r * 3 + a] = r < col.size() ? col[r] : (r == a ? 1.0 : 0.0);
  }
  g.size = {size[0], size[1], size[2]};
  g.spacing_mm = {sp[0], sp[1], sp[2]};
  g.origin_mm = {o[0], o[1], o[2]};
  return g;
}

// the message for a CT with `bad` of its `voxels` values NaN or Inf, the first at linear
// index `first` of a grid of `size`
std::string nonfinite_message(const std::string& path, std::uint64_t bad, std::uint64_t first, std::uint64_t voxels,
                              const Vec3i& size) {
  std::ostringstream s;
  s << "CT " << in_quotes(path) << ": ";
  if (bad == voxels) {
    s << "holds no finite value (all " << voxels << " voxels are NaN or Inf)";
  } else {
    const std::uint64_t nx = std::uint64_t(size.x), ny = std::uint64_t(size.y);
    s << bad << " voxel(s) are NaN or Inf (the first at index (" << first % nx << ", " << (first / nx) % ny << ", "
      << first / (nx * ny) << ")); a CT needs a finite value in every voxel";
  }
  return s.str();
}

// refuses a patient that would not fit in prep.max_memory_mb, before reading voxels
void check_memory(const Grid& input, const PrepSettings& prep, const std::string& path) {
  const Grid out = isotropic_grid(input, patient_spacing_mm(input, prep.spacing_mm));
  const double mb = double(estimate_prep_bytes(input, out)) / (1024.0 * 1024.0);
  if (mb > prep.max_memory_mb) {
    std::ostringstream s;
    s.precision(0);
    s << std::fixed << "CT " << in_quotes(path) << ": preparing it would need about " << mb << " MiB ("
      << input.size.x << " x " << input.size.y << " x " << input.size.z << " input voxels, " << out.size.x << " x "
      << out.size.y << " x " << out.size.z << " patient voxels of " << out.spacing_mm.x
      << " mm), above the scene's prep.max_memory_mb = " << prep.max_memory_mb
      << "; raise prep.max_memory_mb or coarsen prep.spacing_mm";
    throw Error(s.str());
  }
}

// the readers' state between read_ct_info and read_ct
struct Opened {
  CtInfo info;
  FloatImage::Pointer image;  // filled by read_voxels
  itk::ImageFileReader<FloatImage>::Pointer file_reader;
  itk::ImageSeriesReader<FloatImage>::Pointer series_reader;
};

// every entry of a DICOM folder that GDCM will open (all but subfolders): a regular file
// inside the allowed folders once its links are resolved; a FIFO, a device or a link out of
// the folders refuses the whole folder before GDCM opens anything
void check_dicom_folder(const std::string& path, const PathPolicy& files) {
  std::error_code ec;
  fs::directory_iterator it(path, ec), end;
  if (ec) throw Error("CT folder " + in_quotes(path) + ": cannot list it: " + ec.message());
  for (; it != end; it.increment(ec)) {
    if (ec) throw Error("CT folder " + in_quotes(path) + ": cannot list it: " + ec.message());
    std::error_code e2;
    if (fs::is_directory(it->path(), e2)) continue;  // not scanned (non-recursive)
    files.resolve(it->path().string(), "CT folder " + in_quotes(path) + ": file", PathKind::kFile);
  }
}

// lists the series of a DICOM folder and opens the chosen one
void open_dicom(const std::string& path, const PrepSettings& prep, const PathPolicy& files, Opened& o) {
  check_dicom_folder(path, files);
  auto names = itk::GDCMSeriesFileNames::New();
  // series identifiers: the SeriesInstanceUID extended with series details (ITK's
  // default), so volumes sharing a UID are still told apart
  names->SetUseSeriesDetails(true);
  names->SetRecursive(false);
  std::vector<std::string> uids;
  try {
    names->SetDirectory(path);
    uids = names->GetSeriesUIDs();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT folder " + in_quotes(path) + ": cannot scan for DICOM files: " + itk_reason(e));
  }
  if (uids.empty())
    throw Error("CT folder " + in_quotes(path) +
                ": no readable DICOM series in this folder (no DICOM files, or all of them are corrupt)");
  std::string uid = prep.dicom_series_uid;
  const auto listing = [&] {
    std::ostringstream s;
    for (const auto& u : uids) s << "\n  " << u << " (" << names->GetFileNames(u).size() << " slices)";
    return s.str();
  };
  if (uid.empty()) {
    if (uids.size() > 1)
      throw Error("CT folder " + in_quotes(path) + " holds " + std::to_string(uids.size()) +
                  " DICOM series; choose one with the scene field prep.dicom_series_uid:" + listing());
    uid = uids.front();
  } else {
    // an identifier as listed, or a SeriesInstanceUID that starts exactly one of them
    std::vector<std::string> match;
    for (const auto& u : uids)
      if (u == uid) match = {u};
    if (match.empty())
      for (const auto& u : uids)
        if (u.size() > uid.size() && u.compare(0, uid.size(), uid) == 0 && u[uid.size()] == '.') match.push_back(u);
    if (match.size() != 1)
      throw Error("CT folder " + in_quotes(path) + ": " + (match.empty() ? "no" : "more than one") +
                  " DICOM series with prep.dicom_series_uid = " + in_quotes(uid) + "; the folder holds:" + listing());
    uid = match.front();
  }
  o.info.files = names->GetFileNames(uid);
  o.info.series_uid = uid;
  if (o.info.files.size() < 2)
    throw Error("CT folder " + in_quotes(path) + ": DICOM series " + uid +
                " has a single slice (a 2D image); a CT volume needs at least 2 slices");
  // the series reader builds its geometry from the first and the last slice: their
  // spacing, origin and direction are checked before it does (VNL aborts on NaN)
  for (const std::string& f : {o.info.files.front(), o.info.files.back()}) {
    auto slice = itk::GDCMImageIO::New();
    slice->SetFileName(f);
    try {
      slice->ReadImageInformation();
    } catch (const itk::ExceptionObject& e) {
      throw Error("CT folder " + in_quotes(path) + ": cannot read the DICOM file " + in_quotes(f) +
                  " (corrupt or truncated?): " + itk_reason(e));
    }
    Grid g = io_grid(slice.GetPointer());
    g.spacing_mm.z = 1;  // a slice's own thickness is not the series' spacing
    check_grid_numbers(g, "CT folder " + in_quotes(path) + ": DICOM file " + in_quotes(f));
  }
  auto io = itk::GDCMImageIO::New();
  o.series_reader = itk::ImageSeriesReader<FloatImage>::New();
  o.series_reader->SetImageIO(io);
  o.series_reader->SetFileNames(o.info.files);
  try {
    o.series_reader->UpdateOutputInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT folder " + in_quotes(path) + ": cannot read the DICOM series " + uid +
                " (corrupt or truncated file?): " + itk_reason(e));
  }
  o.info.format = "DICOM";
  o.info.pixel_type = component_name(io->GetComponentType());
  o.info.stored_pixel_type = component_name(io->GetInternalComponentType());
  o.info.grid = grid_of(o.series_reader.GetPointer());
}

// NIfTI-1, read through once before ITK reads it: ITK reads a cut-short file without
// complaint, so the length of the (decompressed) file is checked against vox_offset + the
// header's voxel bytes; and ITK's NIfTI library turns NaN and Inf voxels into 0, so a float
// image's values are checked here
void scan_nifti_data(const std::string& path, const std::string& real, const CtHeader& h) {
  const int fd = open_regular_file(real, "CT file");
  gzFile f = gzdopen(fd, "rb");  // reads plain files too
  if (!f) {
    ::close(fd);
    throw Error("CT file " + in_quotes(path) + ": cannot open it");
  }
  const std::uint64_t voxels = std::uint64_t(h.size[0]) * std::uint64_t(h.size[1]) * std::uint64_t(h.size[2]);
  const std::uint64_t start = std::uint64_t(h.vox_offset), bpv = std::uint64_t(h.bytes_per_voxel);
  const std::uint64_t need = start + voxels * bpv;
  const bool is_float = h.datatype == 16 || h.datatype == 64;
  // non-finite values, counted element by element (one element may span two reads)
  std::uint64_t bad = 0, first_bad = 0, element = 0;
  unsigned char part[8];
  std::size_t part_n = 0;
  const auto judge = [&](const unsigned char* e) {
    unsigned char b[8];
    std::memcpy(b, e, bpv);
    if (h.big_endian) std::reverse(b, b + bpv);
    double v;
    if (bpv == 4) {
      float x;
      std::memcpy(&x, b, 4);
      v = x;
    } else {
      std::memcpy(&v, b, 8);
    }
    if (!std::isfinite(v) && bad++ == 0) first_bad = element;
    ++element;
  };
  const auto take = [&](const unsigned char* p, std::size_t n) {
    // the rest of an element the last read began
    if (part_n > 0) {
      const std::size_t k = std::min<std::size_t>(sizeof part - part_n, std::min<std::size_t>(bpv - part_n, n));
      std::memcpy(part + part_n, p, k);
      part_n += k, p += k, n -= k;
      if (part_n == bpv) judge(part), part_n = 0;
    }
    for (; n >= bpv; p += bpv, n -= bpv) judge(p);
    if (n > 0) std::memcpy(part, p, n), part_n = n;  // n < bpv, and no element was begun
  };
  // count the bytes (the whole stream, so a cut gzip stream errors)
  std::uint64_t have = 0;
  std::vector<unsigned char> buf(1 << 20);
  int n;
  while ((n = gzread(f, buf.data(), unsigned(buf.size()))) > 0) {
    const std::uint64_t from = have, to = have + std::uint64_t(n);
    if (is_float && to > start && from < need) {
      const std::uint64_t b = std::max(from, start), e = std::min(to, need);
      take(buf.data() + (b - from), std::size_t(e - b));
    }
    have = to;
  }
  int err = Z_OK;
  const char* msg = gzerror(f, &err);
  const std::string zmsg = msg ? msg : "";
  gzclose(f);
  if (n < 0 || (err != Z_OK && err != Z_STREAM_END))
    throw Error("CT file " + in_quotes(path) + ": corrupt or truncated compressed data (" + zmsg + ")");
  if (have < need) {
    std::ostringstream s;
    s << "CT file " << in_quotes(path) << ": truncated: its header declares " << need << " bytes of header and voxels, "
      << "the file holds " << have;
    throw Error(s.str());
  }
  if (bad) throw Error(nonfinite_message(path, bad, first_bad, voxels, Vec3i{int(h.size[0]), int(h.size[1]), int(h.size[2])}));
}

// the ImageIO of a format ct_header.h checks, made directly (not by ITK's factory, which
// would open the file to guess)
itk::ImageIOBase::Pointer make_io(const std::string& format) {
  if (format == "NIfTI") return itk::NiftiImageIO::New().GetPointer();
  if (format == "NRRD") return itk::NrrdImageIO::New().GetPointer();
  return itk::MetaImageIO::New().GetPointer();
}

// opens an image file: its header checked (ct_header.h, or ITK/GDCM for DICOM), the data
// file it names resolved, its dimension, pixel type and geometry checked before ITK builds
// an image from them; `real` is the file itself after the resolver
void open_file(const std::string& path, const std::string& real, const PathPolicy& files, Opened& o) {
  const std::string format = ct_format_of_name(path);
  itk::ImageIOBase::Pointer io;
  CtHeader header;
  o.info.files = {real};
  if (format.empty()) {
    // a single DICOM file, through ITK's factory as before; any other format is refused
    io = itk::ImageIOFactory::CreateImageIO(real.c_str(), itk::ImageIOFactory::IOFileModeEnum::ReadMode);
    if (!io || format_name(io) != "DICOM")
      throw Error("CT file " + in_quotes(path) +
                  ": not a readable image (unknown format, or a corrupt or truncated header); "
                  "supported: DICOM folders, .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd");
  } else {
    header = check_ct_header_file(path);
    if (!header.data_file.empty()) {
      // relative to the header's folder, as ITK's NRRD and MetaImage readers take it
      const fs::path named(header.data_file);
      const fs::path data = named.is_absolute() ? named : fs::path(path).parent_path() / named;
      o.info.files.push_back(
          files.resolve(data.string(), "CT file " + in_quotes(path) + ": its data file", PathKind::kFile));
    }
    io = make_io(format);
  }
  io->SetFileName(path);
  try {
    io->ReadImageInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT file " + in_quotes(path) + ": cannot read its header (corrupt or truncated?): " + itk_reason(e));
  }
  o.info.format = format_name(io);
  const unsigned dims = io->GetNumberOfDimensions();
  if (dims < 3) {
    std::ostringstream s;
    s << "CT file " << in_quotes(path) << ": a " << dims << "D image; a CT volume has 3 dimensions";
    throw Error(s.str());
  }
  for (unsigned d = 3; d < dims; ++d)
    if (io->GetDimensions(d) > 1) {
      std::ostringstream s;
      s << "CT file " << in_quotes(path) << ": a " << dims << "D image (" << io->GetDimensions(d)
        << " volumes along axis " << d << "); a CT volume has 3 dimensions";
      throw Error(s.str());
    }
  if (io->GetNumberOfComponents() != 1) {
    std::ostringstream s;
    s << "CT file " << in_quotes(path) << ": " << io->GetNumberOfComponents()
      << " components per voxel (a vector or colour image); a CT has one value per voxel";
    throw Error(s.str());
  }
  check_geometry(io_grid(io), path);
  if (o.info.format == "NIfTI") scan_nifti_data(path, real, header);
  o.info.pixel_type = o.info.stored_pixel_type = component_name(io->GetComponentType());
  o.file_reader = itk::ImageFileReader<FloatImage>::New();
  o.file_reader->SetImageIO(io);
  o.file_reader->SetFileName(path);
  try {
    o.file_reader->UpdateOutputInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT file " + in_quotes(path) + ": cannot read its header (corrupt or truncated?): " + itk_reason(e));
  }
  o.info.grid = grid_of(o.file_reader.GetPointer());
}

// ITK and GDCM print their own warnings and errors to stderr ("Cannot find DICOM type.
// Giving up."); every failure reaches the user as a palpsim::Error naming the file, so
// their chatter is switched off once
void quiet_libraries() {
  static const bool once = [] {
    itk::Object::GlobalWarningDisplayOff();
    gdcm::Trace::SetWarning(false);
    gdcm::Trace::SetError(false);
    gdcm::Trace::SetDebug(false);
    return true;
  }();
  (void)once;
}

Opened open_ct(const std::string& path, const PrepSettings& prep, const PathPolicy* files) {
  quiet_libraries();
  Opened o;
  o.info.path = path;
  if (path.empty()) throw Error("CT path is empty; name a file or a DICOM folder");
  check_path_text(path, "CT path");
  if (path.rfind("data:", 0) == 0)
    throw Error("CT " + in_quotes(path) +
                ": no data folder found (set PALPSIM_DATA, or place shared/data above the scene file)");
  // without the caller's folders (palpsim-prep on the operator's CT), the CT's own folder:
  // the data files its header names and the files of a DICOM folder must lie in it
  PathPolicy own;
  if (!files) {
    std::error_code ec;
    if (!fs::exists(path, ec)) throw Error("CT " + in_quotes(path) + ": no such file or folder");
    const fs::path given = fs::absolute(path, ec), real = fs::canonical(path, ec);
    const bool folder = fs::is_directory(real, ec);
    std::vector<std::string> dirs = {(folder ? given : given.parent_path()).string(),
                                     (folder ? real : real.parent_path()).string()};
    own = PathPolicy(dirs, "CT", "the CT's folder");
    files = &own;
  }
  const std::string real = files->resolve(path, "CT", PathKind::kFileOrFolder);
  std::error_code ec;
  if (fs::is_directory(real, ec)) {
    open_dicom(path, prep, *files, o);
  } else {
    open_file(path, real, *files, o);
  }
  check_geometry(o.info.grid, path);
  return o;
}

}  // namespace

CtInfo read_ct_info(const std::string& path, const PrepSettings& prep, const PathPolicy* files) {
  Opened o = open_ct(path, prep, files);
  check_memory(o.info.grid, prep, path);
  return o.info;
}

CtImage read_ct(const std::string& path, const PrepSettings& prep, const PathPolicy* files) {
  Opened o = open_ct(path, prep, files);
  check_memory(o.info.grid, prep, path);

  // read the voxels
  try {
    if (o.series_reader) {
      o.series_reader->Update();
      o.image = o.series_reader->GetOutput();
    } else {
      o.file_reader->Update();
      o.image = o.file_reader->GetOutput();
    }
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT " + in_quotes(path) + ": cannot read the voxel data (truncated or corrupt file?): " +
                itk_reason(e));
  } catch (const std::exception& e) {
    throw Error("CT " + in_quotes(path) + ": cannot read the voxel data (truncated or corrupt file?): " + e.what());
  }

  // copy into a Volume, refusing NaN and Inf, and find the value range
  CtImage ct;
  ct.info = o.info;
  ct.image = Volume<float>(o.info.grid);
  const float* src = o.image->GetBufferPointer();
  const std::size_t n = o.info.grid.count();
  if (o.image->GetPixelContainer()->Size() < n)
    throw Error("CT " + in_quotes(path) + ": the reader returned fewer voxels than the header declares (truncated file?)");
  std::copy(src, src + n, ct.image.data.begin());
  o.image = nullptr;  // free ITK's copy early
  std::size_t bad = 0, first_bad = 0;
  float lo = std::numeric_limits<float>::infinity(), hi = -lo;
  for (std::size_t i = 0; i < n; ++i) {
    const float v = ct.image.data[i];
    if (!std::isfinite(v)) {
      if (bad++ == 0) first_bad = i;
      continue;
    }
    lo = std::min(lo, v);
    hi = std::max(hi, v);
  }
  if (bad) throw Error(nonfinite_message(path, bad, first_bad, n, o.info.grid.size));
  ct.info.min_value = lo;
  ct.info.max_value = hi;
  return ct;
}

}  // namespace palpsim
