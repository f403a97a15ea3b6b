#include "prep/ct_io.h"

#include <algorithm>
#include <cstring>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <zlib.h>

#include "core/error.h"
#include "gdcmTrace.h"
#include "itkGDCMImageIO.h"
#include "itkGDCMSeriesFileNames.h"
#include "itkImage.h"
#include "itkImageFileReader.h"
#include "itkImageIOFactory.h"
#include "itkImageSeriesReader.h"
#include "itkObject.h"
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

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  return s;
}

// the data file a detached header (.nhdr "data file:", .mhd "ElementDataFile =") names
std::string detached_data_file(const std::string& header) {
  const std::string ext = lower(fs::path(header).extension().string());
  const bool nhdr = ext == ".nhdr", mhd = ext == ".mhd";
  if (!nhdr && !mhd) return "";
  std::ifstream in(header);
  std::string line;
  while (std::getline(in, line)) {
    const std::string l = lower(line);
    std::string value;
    if (nhdr && (l.rfind("data file:", 0) == 0 || l.rfind("datafile:", 0) == 0)) {
      value = line.substr(line.find(':') + 1);
    } else if (mhd && l.rfind("elementdatafile", 0) == 0 && line.find('=') != std::string::npos) {
      value = line.substr(line.find('=') + 1);
    } else if (nhdr && line.empty()) {
      break;  // end of the NRRD header
    }
    if (value.empty()) continue;
    value.erase(0, value.find_first_not_of(" \t"));
    value.erase(value.find_last_not_of(" \t\r") + 1);
    if (value == "LOCAL" || value.rfind("LIST", 0) == 0 || value.find('%') != std::string::npos) return "";
    const fs::path p = fs::path(header).parent_path() / value;
    return fs::exists(p) ? p.string() : "";
  }
  return "";
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

// refuses spacing, direction and size that no 3D CT can have
void check_geometry(const Grid& g, const std::string& path) {
  const double sp[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z};
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(sp[a]) || sp[a] <= 0) {
      std::ostringstream s;
      s << "CT " << in_quotes(path) << ": spacing along axis " << a << " is " << sp[a]
        << " mm; every voxel spacing must be a positive finite length";
      throw Error(s.str());
    }
  if (g.size.z <= 1 || g.size.y <= 1 || g.size.x <= 1) {
    std::ostringstream s;
    s << "CT " << in_quotes(path) << ": a 2D image (" << g.size.x << " x " << g.size.y << " x " << g.size.z
      << " voxels); a CT volume needs at least 2 voxels along each of its 3 axes";
    throw Error(s.str());
  }
  // the direction must be orthonormal (the patient grid inverts it by transposing)
  const auto& d = g.direction;
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) {
      const double dot = d[a] * d[b] + d[3 + a] * d[3 + b] + d[6 + a] * d[6 + b];
      if (!std::isfinite(dot) || std::abs(dot - (a == b ? 1.0 : 0.0)) > 1e-3)
        throw Error("CT " + in_quotes(path) + ": the direction (orientation) matrix is not orthonormal");
    }
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

// lists the series of a DICOM folder and opens the chosen one
void open_dicom(const std::string& path, const PrepSettings& prep, Opened& o) {
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
    throw Error("CT folder " + in_quotes(path) + ": cannot scan for DICOM files: " + e.GetDescription());
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
  auto io = itk::GDCMImageIO::New();
  o.series_reader = itk::ImageSeriesReader<FloatImage>::New();
  o.series_reader->SetImageIO(io);
  o.series_reader->SetFileNames(o.info.files);
  try {
    o.series_reader->UpdateOutputInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT folder " + in_quotes(path) + ": cannot read the DICOM series " + uid +
                " (corrupt or truncated file?): " + e.GetDescription());
  }
  o.info.format = "DICOM";
  o.info.pixel_type = component_name(io->GetComponentType());
  o.info.stored_pixel_type = component_name(io->GetInternalComponentType());
  o.info.grid = grid_of(o.series_reader.GetPointer());
}

// NIfTI-1: ITK reads a cut-short file without complaint, so the length of the
// (decompressed) file is checked against vox_offset + the header's voxel bytes
void check_nifti_length(const std::string& path) {
  const std::string l = lower(path);
  const bool gz = l.size() > 7 && l.compare(l.size() - 7, 7, ".nii.gz") == 0;
  if (!gz && !(l.size() > 4 && l.compare(l.size() - 4, 4, ".nii") == 0)) return;
  gzFile f = gzopen(path.c_str(), "rb");  // reads plain files too
  if (!f) throw Error("CT file " + in_quotes(path) + ": cannot open it");
  unsigned char h[348];
  const int got = gzread(f, h, sizeof h);
  std::int32_t sizeof_hdr = 0;
  if (got == int(sizeof h)) std::memcpy(&sizeof_hdr, h, 4);
  if (sizeof_hdr != 348) {  // NIfTI-2 or byte-swapped headers: left to ITK
    gzclose(f);
    return;
  }
  std::int16_t dim[8], bitpix = 0;
  float vox_offset = 0;
  std::memcpy(dim, h + 40, sizeof dim);
  std::memcpy(&bitpix, h + 72, 2);
  std::memcpy(&vox_offset, h + 108, 4);
  std::uint64_t need = std::uint64_t(std::max(352.0f, vox_offset));
  std::uint64_t voxels = 1;
  for (int d = 1; d <= std::min<int>(dim[0], 7); ++d) voxels *= std::uint64_t(std::max<std::int16_t>(dim[d], 1));
  need += voxels * std::uint64_t(std::max<std::int16_t>(bitpix, 8)) / 8;
  // count the bytes that follow (the whole stream, so a cut gzip stream errors)
  std::uint64_t have = std::uint64_t(got);
  std::vector<char> buf(1 << 20);
  int n;
  while ((n = gzread(f, buf.data(), unsigned(buf.size()))) > 0) have += std::uint64_t(n);
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
}

// opens an image file after checking its dimension and pixel type from its header
void open_file(const std::string& path, Opened& o) {
  itk::ImageIOBase::Pointer io =
      itk::ImageIOFactory::CreateImageIO(path.c_str(), itk::ImageIOFactory::IOFileModeEnum::ReadMode);
  if (!io)
    throw Error("CT file " + in_quotes(path) +
                ": not a readable image (unknown format, or a corrupt or truncated header); "
                "supported: DICOM folders, .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd");
  io->SetFileName(path);
  try {
    io->ReadImageInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT file " + in_quotes(path) + ": cannot read its header (corrupt or truncated?): " + e.GetDescription());
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
  for (unsigned d = 0; d < 3; ++d)
    if (!(io->GetSpacing(d) > 0) || !std::isfinite(io->GetSpacing(d))) {
      std::ostringstream s;
      s << "CT file " << in_quotes(path) << ": spacing along axis " << d << " is " << io->GetSpacing(d)
        << " mm; every voxel spacing must be a positive finite length";
      throw Error(s.str());
    }
  if (o.info.format == "NIfTI") check_nifti_length(path);
  o.info.pixel_type = o.info.stored_pixel_type = component_name(io->GetComponentType());
  o.info.files = {path};
  if (const std::string data = detached_data_file(path); !data.empty()) o.info.files.push_back(data);
  o.file_reader = itk::ImageFileReader<FloatImage>::New();
  o.file_reader->SetImageIO(io);
  o.file_reader->SetFileName(path);
  try {
    o.file_reader->UpdateOutputInformation();
  } catch (const itk::ExceptionObject& e) {
    throw Error("CT file " + in_quotes(path) + ": cannot read its header (corrupt or truncated?): " + e.GetDescription());
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

Opened open_ct(const std::string& path, const PrepSettings& prep) {
  quiet_libraries();
  Opened o;
  o.info.path = path;
  std::error_code ec;
  if (path.empty()) throw Error("CT path is empty; name a file or a DICOM folder");
  if (path.rfind("data:", 0) == 0)
    throw Error("CT " + in_quotes(path) +
                ": no data folder found (set PALPSIM_DATA, or place shared/data above the scene file)");
  if (!fs::exists(path, ec)) throw Error("CT " + in_quotes(path) + ": no such file or folder");
  if (fs::is_directory(path, ec)) {
    open_dicom(path, prep, o);
  } else {
    open_file(path, o);
  }
  check_geometry(o.info.grid, path);
  return o;
}

}  // namespace

CtInfo read_ct_info(const std::string& path, const PrepSettings& prep) {
  Opened o = open_ct(path, prep);
  check_memory(o.info.grid, prep, path);
  return o.info;
}

CtImage read_ct(const std::string& path, const PrepSettings& prep) {
  Opened o = open_ct(path, prep);
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
                e.GetDescription());
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
  if (bad) {
    const Grid& g = o.info.grid;
    std::ostringstream s;
    s << "CT " << in_quotes(path) << ": " << bad << " voxel(s) are NaN or Inf (the first at index ("
      << first_bad % g.size.x << ", " << (first_bad / g.size.x) % g.size.y << ", "
      << first_bad / (std::size_t(g.size.x) * g.size.y) << ")); a CT needs a finite value in every voxel";
    throw Error(s.str());
  }
  ct.info.min_value = lo;
  ct.info.max_value = hi;
  return ct;
}

}  // namespace palpsim
