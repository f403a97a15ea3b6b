#include "prep/ct_header.h"

#include <zlib.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <sstream>

#include "core/error.h"
#include "core/path_policy.h"

namespace palpsim {
namespace {

// a NIfTI-1 header's size and where its voxels start at the earliest
constexpr std::size_t kNifti1Bytes = 348;
constexpr std::int64_t kNifti1MinVoxOffset = 352;
// a MetaImage string value is copied into 255-byte buffers by ITK's MetaIO
constexpr std::size_t kMaxMetaStringChars = 254;
// a MetaImage header line, at most (its numbers: a 7x7 matrix at 17 digits is ~1300 characters)
constexpr std::size_t kMaxMetaLineChars = 4096;
// axes a header may declare (NIfTI-1 allows 7, NRRD 16, MetaIO 10)
constexpr std::int64_t kMaxHeaderAxes = 16;
// lines of a NRRD or MetaImage header, at most (a diffusion NRRD's key/value pairs are a few hundred)
constexpr int kMaxHeaderLines = 10000;

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  return s;
}

bool ends_with(const std::string& s, const std::string& tail) {
  return s.size() >= tail.size() && s.compare(s.size() - tail.size(), tail.size(), tail) == 0;
}

// a header value as it may be quoted in a message: control characters escaped, cut at 64
std::string shown(std::string_view v) {
  std::string o;
  for (unsigned char c : v.substr(0, 64)) {
    if (c < 0x20 || c >= 0x7f) {
      char b[8];
      std::snprintf(b, sizeof b, "\\x%02x", c);
      o += b;
    } else {
      o += char(c);
    }
  }
  if (v.size() > 64) o += "...";
  return o;
}

std::string num(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

std::string_view trim(std::string_view s) {
  const auto b = s.find_first_not_of(" \t\r");
  if (b == std::string_view::npos) return {};
  const auto e = s.find_last_not_of(" \t\r");
  return s.substr(b, e - b + 1);
}

std::vector<std::string_view> tokens(std::string_view s) {
  std::vector<std::string_view> out;
  std::size_t i = 0;
  while (i < s.size()) {
    while (i < s.size() && (s[i] == ' ' || s[i] == '\t' || s[i] == '\r')) ++i;
    const std::size_t b = i;
    while (i < s.size() && s[i] != ' ' && s[i] != '\t' && s[i] != '\r') ++i;
    if (i > b) out.push_back(s.substr(b, i - b));
  }
  return out;
}

// a whole token as a number (nan and inf parse, and are judged by the caller)
bool parse_double(std::string_view t, double& v) {
  if (t.empty() || t.size() > 64) return false;
  const std::string s(t);
  char* end = nullptr;
  errno = 0;
  v = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size()) return false;
  if (errno == ERANGE && std::abs(v) > 1) v = std::copysign(HUGE_VAL, v);  // overflow reads as infinite
  return true;
}

bool parse_int(std::string_view t, std::int64_t& v) {
  if (t.empty() || t.size() > 32) return false;
  const std::string s(t);
  char* end = nullptr;
  errno = 0;
  const long long r = std::strtoll(s.c_str(), &end, 10);
  if (end != s.c_str() + s.size() || errno == ERANGE) return false;
  v = r;
  return true;
}

// the checks' one message shape: the file, then what is wrong
[[noreturn]] void fail(const std::string& name, const std::string& what) {
  throw Error("CT file '" + name + "': " + what);
}

// a geometry number: finite and at most kMaxHeaderNumber in magnitude
void check_number(const std::string& name, const std::string& field, double v) {
  if (!std::isfinite(v) || std::abs(v) > kMaxHeaderNumber)
    fail(name, field + " is " + num(v) + "; it must be a finite number of magnitude at most " + num(kMaxHeaderNumber));
}

// the axes a CT may have: 3, or more of one voxel each; 2 to kMaxCtAxisVoxels voxels along
// each of the first 3; at most kMaxCtVoxels in all
void check_axes(const std::string& name, const std::string& field, const std::vector<std::int64_t>& size) {
  const std::size_t dims = size.size();
  for (std::size_t a = 0; a < dims; ++a)
    if (size[a] < 1 || size[a] > kMaxCtAxisVoxels)
      fail(name, field + ": axis " + std::to_string(a) + " has " + std::to_string(size[a]) +
                     " voxels; every size must be a whole number from 1 to " + std::to_string(kMaxCtAxisVoxels));
  if (dims < 3) fail(name, "a " + std::to_string(dims) + "D image; a CT volume has 3 dimensions");
  for (std::size_t a = 3; a < dims; ++a)
    if (size[a] > 1)
      fail(name, "a " + std::to_string(dims) + "D image (" + std::to_string(size[a]) + " volumes along axis " +
                     std::to_string(a) + "); a CT volume has 3 dimensions");
  if (size[0] < 2 || size[1] < 2 || size[2] < 2)
    fail(name, "a 2D image (" + std::to_string(size[0]) + " x " + std::to_string(size[1]) + " x " +
                   std::to_string(size[2]) + " voxels); a CT volume needs at least 2 voxels along each of its 3 axes");
  const std::int64_t voxels = size[0] * size[1] * size[2];  // each at most 2^16: no overflow
  if (voxels > kMaxCtVoxels)
    fail(name, std::to_string(voxels) + " voxels (" + std::to_string(size[0]) + " x " + std::to_string(size[1]) +
                   " x " + std::to_string(size[2]) + "); a CT may have at most " + std::to_string(kMaxCtVoxels));
}

// a sizes field: `dims` whole numbers (`dims_field` names where the count comes from),
// checked as a CT's axes (check_axes)
std::vector<std::int64_t> axis_sizes(const std::string& name, const std::string& field, std::string_view value,
                                     std::int64_t dims, const std::string& dims_field) {
  const auto t = tokens(value);
  if (t.size() != std::size_t(dims))
    fail(name, field + " has " + std::to_string(t.size()) + " values; " + dims_field + " is " + std::to_string(dims));
  std::vector<std::int64_t> size;
  for (std::size_t a = 0; a < t.size(); ++a) {
    std::int64_t v = 0;
    if (!parse_int(t[a], v))
      fail(name, field + ": axis " + std::to_string(a) + " is '" + shown(t[a]) + "', not a whole number");
    size.push_back(v);
  }
  check_axes(name, field, size);
  return size;
}

// a data file name a header gives: one file (several, as a list or a pattern, are refused)
std::string single_data_file(const std::string& name, const std::string& field, std::string_view value) {
  const std::string v(trim(value));
  if (v.empty()) fail(name, field + " is empty");
  if (lower(v).rfind("list", 0) == 0 || v.find('%') != std::string::npos)
    fail(name, field + " '" + shown(v) +
                   "' spreads the voxels over several files (a list or a pattern); join them into one file");
  if (v.find('\0') != std::string::npos) fail(name, field + " '" + shown(v) + "' holds a NUL character");
  return v;
}

// ---- NIfTI-1 ----

// the first `want` bytes of a gzip stream (or fewer when it ends); bounded by the input
std::string gunzip_head(const std::string& name, std::string_view gz, std::size_t want) {
  z_stream zs{};
  if (inflateInit2(&zs, 15 + 32) != Z_OK) fail(name, "cannot start decompressing it");
  std::string out(want, '\0');
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(gz.data()));
  zs.avail_in = uInt(std::min<std::size_t>(gz.size(), 1u << 30));
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = uInt(want);
  int rc = Z_OK;
  while (zs.avail_out > 0 && zs.avail_in > 0 && rc == Z_OK) rc = inflate(&zs, Z_NO_FLUSH);
  const std::size_t got = want - zs.avail_out;
  inflateEnd(&zs);
  if (rc != Z_OK && rc != Z_STREAM_END && rc != Z_BUF_ERROR)
    fail(name, "corrupt compressed data (not a gzip stream, or damaged)");
  out.resize(got);
  return out;
}

struct NiftiReader {
  std::string_view h;
  bool swap = false;
  template <typename T>
  T get(std::size_t off) const {
    T v;
    std::memcpy(&v, h.data() + off, sizeof v);
    if (swap) {
      unsigned char b[sizeof v];
      std::memcpy(b, &v, sizeof v);
      std::reverse(b, b + sizeof v);
      std::memcpy(&v, b, sizeof v);
    }
    return v;
  }
};

// bytes per voxel of a NIfTI-1 datatype with one real value per voxel; 0 for others
int nifti_scalar_bytes(int datatype) {
  switch (datatype) {
    case 2: case 256: return 1;     // uint8, int8
    case 4: case 512: return 2;     // int16, uint16
    case 8: case 768: case 16: return 4;  // int32, uint32, float32
    case 64: case 1024: case 1280: return 8;  // float64, int64, uint64
    default: return 0;
  }
}

CtHeader check_nifti(const std::string& name, std::string_view bytes) {
  const bool gz = ends_with(lower(name), ".gz");
  const std::string inflated = gz ? gunzip_head(name, bytes, kNifti1Bytes) : std::string();
  const std::string_view head = gz ? std::string_view(inflated) : bytes.substr(0, kNifti1Bytes);
  if (head.size() < 4) fail(name, "too short for a NIfTI header (" + std::to_string(head.size()) + " bytes)");
  NiftiReader r{head, false};
  const std::int32_t sizeof_hdr = r.get<std::int32_t>(0);
  r.swap = sizeof_hdr != 348;
  const std::int32_t swapped = r.get<std::int32_t>(0);
  if (sizeof_hdr == 540 || (r.swap && swapped == 540))
    fail(name, "a NIfTI-2 header; this build reads NIfTI-1 only (save the CT as NIfTI-1, NRRD or MetaImage)");
  if (r.swap && swapped != 348)
    fail(name, "not a NIfTI-1 header (sizeof_hdr is " + std::to_string(sizeof_hdr) + ", not 348)");
  if (head.size() < kNifti1Bytes)
    fail(name, "truncated header (" + std::to_string(head.size()) + " of 348 bytes)");
  const std::string_view magic = head.substr(344, 4);
  if (magic == std::string_view("ni1\0", 4))
    fail(name, "a NIfTI header of a .hdr/.img pair; only single-file NIfTI (.nii, .nii.gz) is read");
  if (magic != std::string_view("n+1\0", 4))
    fail(name, "no NIfTI-1 magic 'n+1' at byte 344 (an Analyze 7.5 or damaged header)");

  CtHeader out;
  out.format = "NIfTI";
  const std::uint16_t one = 1;
  const bool host_big = *reinterpret_cast<const unsigned char*>(&one) == 0;
  out.big_endian = r.swap != host_big;
  const std::int16_t dim0 = r.get<std::int16_t>(40);
  if (dim0 < 1 || dim0 > 7) fail(name, "dim[0] is " + std::to_string(dim0) + "; it must be 1 to 7");
  out.dimensions = dim0;
  for (int d = 1; d <= dim0; ++d) out.size.push_back(r.get<std::int16_t>(40 + 2 * d));
  check_axes(name, "dim", out.size);
  out.datatype = r.get<std::int16_t>(70);
  out.bytes_per_voxel = nifti_scalar_bytes(out.datatype);
  if (out.bytes_per_voxel == 0) {
    const int t = out.datatype;
    if (t == 32 || t == 128 || t == 1792 || t == 2048 || t == 2304)
      fail(name, "datatype " + std::to_string(t) +
                     " (complex or RGB) has more than one value per voxel; a CT has one value per voxel");
    fail(name, "datatype " + std::to_string(t) + " is not a NIfTI-1 type this reader takes");
  }
  // every number ITK turns into a matrix (pixdim, quaternion, offsets, sform rows), the
  // voxel offset and the scaling: finite and bounded
  for (int d = 0; d <= dim0; ++d)
    check_number(name, "pixdim[" + std::to_string(d) + "]" + (d ? " (spacing along axis " + std::to_string(d - 1) + ")" : " (qfac)"),
                 r.get<float>(76 + 4 * d));
  const float vox_offset = r.get<float>(108);
  if (!std::isfinite(vox_offset) || vox_offset < 0 || vox_offset > 1e12f)
    fail(name, "vox_offset is " + num(vox_offset) + "; it must be a finite byte offset");
  out.vox_offset = std::max<std::int64_t>(kNifti1MinVoxOffset, std::int64_t(vox_offset));
  check_number(name, "scl_slope", r.get<float>(112));
  check_number(name, "scl_inter", r.get<float>(116));
  static const char* const kQ[] = {"quatern_b", "quatern_c", "quatern_d", "qoffset_x", "qoffset_y", "qoffset_z"};
  for (int i = 0; i < 6; ++i) check_number(name, kQ[i], r.get<float>(256 + 4 * i));
  static const char* const kRow[] = {"srow_x", "srow_y", "srow_z"};
  for (int row = 0; row < 3; ++row)
    for (int c = 0; c < 4; ++c)
      check_number(name, std::string(kRow[row]) + "[" + std::to_string(c) + "]", r.get<float>(280 + 16 * row + 4 * c));
  return out;
}

// ---- NRRD ----

// the NRRD field name of a header line, lowercase without spaces ("spacedirections")
std::string nrrd_field(std::string_view key) {
  std::string k;
  for (char c : key)
    if (c != ' ' && c != '\t') k += char(std::tolower(static_cast<unsigned char>(c)));
  return k;
}

// "(x,y,z)" vectors and "none" of a space directions / origin / measurement frame field
struct NrrdVector {
  bool none = false;
  std::vector<double> v;
};
std::vector<NrrdVector> nrrd_vectors(const std::string& name, const std::string& field, std::string_view s) {
  std::vector<NrrdVector> out;
  std::size_t i = 0;
  while (i < s.size()) {
    while (i < s.size() && (s[i] == ' ' || s[i] == '\t')) ++i;
    if (i >= s.size()) break;
    if (out.size() >= std::size_t(kMaxHeaderAxes)) fail(name, field + " holds more than " + std::to_string(kMaxHeaderAxes) + " entries");
    NrrdVector e;
    if (s.substr(i, 4) == "none") {
      e.none = true;
      i += 4;
    } else if (s[i] == '(') {
      const std::size_t close = s.find(')', i);
      if (close == std::string_view::npos) fail(name, field + ": a '(' without its ')'");
      std::string_view inner = s.substr(i + 1, close - i - 1);
      std::size_t b = 0;
      while (b <= inner.size()) {
        const std::size_t c = std::min(inner.find(',', b), inner.size());
        double v = 0;
        if (!parse_double(trim(inner.substr(b, c - b)), v))
          fail(name, field + ": '" + shown(inner.substr(b, c - b)) + "' is not a number");
        if (e.v.size() >= std::size_t(kMaxHeaderAxes)) fail(name, field + ": a vector of more than " + std::to_string(kMaxHeaderAxes) + " numbers");
        e.v.push_back(v);
        b = c + 1;
      }
      i = close + 1;
    } else {
      fail(name, field + ": '" + shown(s.substr(i, 16)) + "' is neither a vector '(x,y,z)' nor 'none'");
    }
    out.push_back(std::move(e));
  }
  return out;
}

CtHeader check_nrrd(const std::string& name, std::string_view bytes) {
  CtHeader out;
  out.format = "NRRD";
  std::size_t pos = 0;
  auto next_line = [&](std::string_view& line) {
    if (pos >= bytes.size()) return false;
    std::size_t e = bytes.find('\n', pos);
    if (e == std::string_view::npos) e = bytes.size();
    line = bytes.substr(pos, e - pos);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    pos = e + 1;
    return true;
  };
  std::string_view line;
  if (!next_line(line) || line.size() != 8 || line.substr(0, 7) != "NRRD000" || line[7] < '1' || line[7] > '5')
    fail(name, "not a NRRD file (its first line is not NRRD0001 to NRRD0005)");
  bool ended = false, has_type = false, has_encoding = false;
  std::int64_t dimension = -1, space_dim = -1;
  std::string_view sizes, spacings, directions, origin, frame;
  std::vector<std::pair<std::string, std::string_view>> per_axis;  // thicknesses, axis mins and maxs
  int line_no = 1;
  while (next_line(line)) {
    if (++line_no > kMaxHeaderLines) fail(name, "a NRRD header of more than " + std::to_string(kMaxHeaderLines) + " lines");
    if (line.empty()) {
      ended = true;  // the blank line that ends the header
      break;
    }
    if (line[0] == '#') continue;
    const std::size_t colon = line.find(':');
    if (colon == std::string_view::npos) continue;  // left to ITK, which names the line
    if (colon + 1 < line.size() && line[colon + 1] == '=') continue;  // a key:=value pair
    const std::string f = nrrd_field(line.substr(0, colon));
    const std::string_view value = trim(line.substr(colon + 1));
    const std::string field = "NRRD field '" + std::string(trim(line.substr(0, colon))) + "' (line " + std::to_string(line_no) + ")";
    if (f == "dimension") {
      if (!parse_int(value, dimension) || dimension < 1 || dimension > kMaxHeaderAxes)
        fail(name, field + " is '" + shown(value) + "'; it must be a whole number from 1 to " + std::to_string(kMaxHeaderAxes));
    } else if (f == "type") {
      has_type = true;
    } else if (f == "encoding") {
      has_encoding = true;
    } else if (std::string_view* kept = f == "sizes"              ? &sizes
                                        : f == "spacings"         ? &spacings
                                        : f == "spacedirections"  ? &directions
                                        : f == "spaceorigin"      ? &origin
                                        : f == "measurementframe" ? &frame
                                                                  : nullptr) {
      *kept = value;  // judged once the dimension is known
    } else if (f == "thicknesses" || f == "axismins" || f == "axismaxs") {
      per_axis.emplace_back(field, value);
    } else if (f == "space") {
      const std::string s = lower(std::string(value));
      space_dim = ends_with(s, "-time") ? 4 : 3;
    } else if (f == "spacedimension") {
      if (!parse_int(value, space_dim) || space_dim < 1 || space_dim > kMaxHeaderAxes)
        fail(name, field + " is '" + shown(value) + "'; it must be a whole number from 1 to " + std::to_string(kMaxHeaderAxes));
    } else if (f == "lineskip" || f == "byteskip") {
      std::int64_t v = 0;
      if (!parse_int(value, v) || v < (f == "byteskip" ? -1 : 0) || v > (std::int64_t(1) << 40))
        fail(name, field + " is '" + shown(value) + "'; it must be a whole number of " + (f == "byteskip" ? "bytes (or -1)" : "lines"));
    } else if (f == "datafile") {
      out.data_file = single_data_file(name, field, value);
    }
  }
  if (!ended && out.data_file.empty())
    fail(name, bytes.size() >= kMaxCtHeaderBytes
                   ? "no end of the NRRD header within its first " + std::to_string(kMaxCtHeaderBytes) + " bytes"
                   : "no blank line ends the NRRD header, and no 'data file' field names where the voxels are");
  if (dimension < 0) fail(name, "no NRRD 'dimension' field");
  if (sizes.empty()) fail(name, "no NRRD 'sizes' field");
  if (!has_type) fail(name, "no NRRD 'type' field");
  if (!has_encoding) fail(name, "no NRRD 'encoding' field");
  out.dimensions = int(dimension);

  out.size = axis_sizes(name, "NRRD field 'sizes'", sizes, dimension, "'dimension'");

  // spacings and other per-axis numbers: finite on the 3 spatial axes; "nan" (unknown) beyond them
  auto per_axis_numbers = [&](const std::string& field, std::string_view value) {
    const auto t = tokens(value);
    if (t.size() != std::size_t(dimension))
      fail(name, field + " has " + std::to_string(t.size()) + " values; 'dimension' is " + std::to_string(dimension));
    for (std::size_t a = 0; a < t.size(); ++a) {
      double v = 0;
      if (!parse_double(t[a], v)) fail(name, field + ": axis " + std::to_string(a) + " is '" + shown(t[a]) + "', not a number");
      if (a >= 3 && std::isnan(v)) continue;
      check_number(name, field + " on axis " + std::to_string(a), v);
    }
  };
  if (!spacings.empty()) per_axis_numbers("NRRD field 'spacings'", spacings);
  for (const auto& [field, value] : per_axis) per_axis_numbers(field, value);

  // the space: 3D, with a finite direction for each spatial axis and a finite origin
  if (space_dim > 0 && space_dim != 3)
    fail(name, "a " + std::to_string(space_dim) + "D NRRD space; a CT lies in 3D space");
  if (!directions.empty()) {
    const auto dirs = nrrd_vectors(name, "NRRD field 'space directions'", directions);
    if (dirs.size() != std::size_t(dimension))
      fail(name, "NRRD field 'space directions' has " + std::to_string(dirs.size()) + " entries; 'dimension' is " +
                     std::to_string(dimension));
    for (std::size_t a = 0; a < dirs.size(); ++a) {
      const std::string field = "NRRD field 'space directions' on axis " + std::to_string(a);
      if (dirs[a].none) {
        if (a < 3) fail(name, field + " is 'none'; each of a CT's 3 axes needs a direction");
        continue;
      }
      if (dirs[a].v.size() != 3) fail(name, field + " has " + std::to_string(dirs[a].v.size()) + " components; a CT lies in 3D space");
      for (double v : dirs[a].v) check_number(name, field, v);
    }
  }
  if (!origin.empty()) {
    const auto o = nrrd_vectors(name, "NRRD field 'space origin'", origin);
    if (o.size() != 1 || o[0].none || o[0].v.size() != 3) fail(name, "NRRD field 'space origin' is not one vector (x,y,z)");
    for (double v : o[0].v) check_number(name, "NRRD field 'space origin'", v);
  }
  if (!frame.empty())
    for (const NrrdVector& e : nrrd_vectors(name, "NRRD field 'measurement frame'", frame))
      for (double v : e.v) check_number(name, "NRRD field 'measurement frame'", v);
  return out;
}

// ---- MetaImage ----

CtHeader check_meta(const std::string& name, std::string_view bytes) {
  CtHeader out;
  out.format = "MetaImage";
  std::int64_t ndims = -1;
  bool ended = false;
  std::vector<std::pair<std::string, std::string_view>> fields;  // key (lowercase) and value, in order
  std::size_t pos = 0;
  int line_no = 0;
  while (pos < bytes.size()) {
    std::size_t e = bytes.find('\n', pos);
    if (e == std::string_view::npos) e = bytes.size();
    std::string_view line = bytes.substr(pos, e - pos);
    pos = e + 1;
    if (++line_no > kMaxHeaderLines)
      fail(name, "a MetaImage header of more than " + std::to_string(kMaxHeaderLines) + " lines");
    if (line.size() > kMaxMetaLineChars)
      fail(name, "MetaImage header line " + std::to_string(line_no) + " is longer than " +
                     std::to_string(kMaxMetaLineChars) + " characters");
    const std::size_t eq = line.find('=');
    if (eq == std::string_view::npos) {
      if (trim(line).empty()) continue;
      fail(name, "MetaImage header line " + std::to_string(line_no) + " '" + shown(trim(line)) + "' is not 'Key = Value'");
    }
    const std::string key = lower(std::string(trim(line.substr(0, eq))));
    const std::string_view value = trim(line.substr(eq + 1));
    fields.emplace_back(key, value);
    if (key == "elementdatafile") {
      ended = true;  // the last field: the voxels (or the data file's name) follow
      break;
    }
  }
  if (!ended)
    fail(name, bytes.size() >= kMaxCtHeaderBytes
                   ? "no ElementDataFile field within the first " + std::to_string(kMaxCtHeaderBytes) + " bytes"
                   : "no ElementDataFile field (it ends a MetaImage header and says where the voxels are)");
  for (const auto& [key, value] : fields)
    if (key == "ndims" && (!parse_int(value, ndims) || ndims < 1 || ndims > 10))
      fail(name, "MetaImage field NDims is '" + shown(value) + "'; it must be a whole number from 1 to 10");
  if (ndims < 0) fail(name, "no MetaImage NDims field");
  out.dimensions = int(ndims);

  // numbers per field: DimSize whole numbers; spacing, origin and matrices finite
  auto numbers = [&](const std::string& key, std::string_view value, std::size_t want) {
    const auto t = tokens(value);
    if (t.size() != want)
      fail(name, "MetaImage field " + key + " has " + std::to_string(t.size()) + " values; NDims " +
                     std::to_string(ndims) + " needs " + std::to_string(want));
    std::vector<double> v(t.size());
    for (std::size_t i = 0; i < t.size(); ++i)
      if (!parse_double(t[i], v[i])) fail(name, "MetaImage field " + key + ": '" + shown(t[i]) + "' is not a number");
    return v;
  };
  bool has_size = false;
  for (const auto& [key, value] : fields) {
    if (key == "dimsize") {
      has_size = true;
      out.size = axis_sizes(name, "MetaImage field DimSize", value, ndims, "NDims");
    } else if (key == "elementspacing" || key == "elementsize" || key == "offset" || key == "position" ||
               key == "origin" || key == "centerofrotation") {
      const auto v = numbers(key, value, std::size_t(ndims));
      for (std::size_t a = 0; a < v.size(); ++a) check_number(name, "MetaImage field " + key + " on axis " + std::to_string(a), v[a]);
    } else if (key == "transformmatrix" || key == "rotation" || key == "orientation") {
      for (double x : numbers(key, value, std::size_t(ndims * ndims))) check_number(name, "MetaImage field " + key, x);
    } else if (key == "elementnumberofchannels") {
      std::int64_t c = 0;
      if (!parse_int(value, c) || c < 1) fail(name, "MetaImage field ElementNumberOfChannels is '" + shown(value) + "'");
      if (c != 1)
        fail(name, std::to_string(c) + " components per voxel (a vector or colour image); a CT has one value per voxel");
    } else if (key == "headersize" || key == "compresseddatasize") {
      std::int64_t v = 0;
      if (!parse_int(value, v) || v < (key == "headersize" ? -1 : 0))
        fail(name, "MetaImage field " + key + " is '" + shown(value) + "', not a byte count");
    } else if (key == "elementdatafile") {
      const std::string f = single_data_file(name, "MetaImage field ElementDataFile", value);
      if (f.size() > kMaxMetaStringChars)
        fail(name, "MetaImage field ElementDataFile is longer than " + std::to_string(kMaxMetaStringChars) + " characters");
      if (lower(f) != "local") out.data_file = f;
    } else if (value.size() > kMaxMetaStringChars) {
      fail(name, "MetaImage field '" + shown(key) + "' is longer than " + std::to_string(kMaxMetaStringChars) + " characters");
    }
  }
  if (!has_size) fail(name, "no MetaImage DimSize field");
  return out;
}

}  // namespace

std::string ct_format_of_name(const std::string& name) {
  const std::string l = lower(name);
  if (ends_with(l, ".nii") || ends_with(l, ".nii.gz")) return "NIfTI";
  if (ends_with(l, ".nrrd") || ends_with(l, ".nhdr")) return "NRRD";
  if (ends_with(l, ".mha") || ends_with(l, ".mhd")) return "MetaImage";
  return "";
}

CtHeader check_ct_header(const std::string& name, std::string_view bytes) {
  const std::string format = ct_format_of_name(name);
  if (format == "NIfTI") return check_nifti(name, bytes);
  if (format == "NRRD") return check_nrrd(name, bytes.substr(0, kMaxCtHeaderBytes));
  if (format == "MetaImage") return check_meta(name, bytes.substr(0, kMaxCtHeaderBytes));
  fail(name, "not a NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr) or MetaImage (.mha, .mhd) file name");
}

CtHeader check_ct_header_file(const std::string& path) {
  return check_ct_header(path, read_file_head(path, kMaxCtHeaderBytes, "CT file"));
}

}  // namespace palpsim
