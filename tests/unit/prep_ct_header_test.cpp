// CT headers checked before ITK reads them (prep/ct_header.h): every field on which ITK
// would abort or compute nonsense is refused with one line naming the file and the field,
// on the header's bytes alone; no prefix or mutation of a header makes the check do
// anything but accept it within bounds or throw palpsim::Error. And with the server's
// folders (core/path_policy.h) a CT's files must lie inside them.
#include <catch2/catch.hpp>

#include <zlib.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>

#include "core/error.h"
#include "core/path_policy.h"
#include "prep/ct_header.h"
#include "prep/prepare.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;
namespace fs = std::filesystem;

namespace {

const double kOne[3] = {1, 1, 1};
const float kNan = std::numeric_limits<float>::quiet_NaN();

std::string check_error(const std::string& name, const std::string& bytes) {
  return error_message([&] { check_ct_header(name, bytes); });
}

// a NIfTI-1 header of 16^3 int16 voxels with `value` written at byte `offset`
template <typename T>
std::string nifti_with(int offset, T value) {
  std::string h = nifti_header(16, 16, 16, kOne, 4, 16);
  std::memcpy(&h[offset], &value, sizeof value);
  return h;
}

// the same header in big-endian byte order (every field the header sets swapped)
std::string big_endian(std::string h) {
  auto swap = [&](int off, int n) { std::reverse(h.begin() + off, h.begin() + off + n); };
  swap(0, 4);
  for (int off = 40; off <= 54; off += 2) swap(off, 2);
  swap(70, 2), swap(72, 2);
  for (int off = 76; off <= 116; off += 4) swap(off, 4);
  swap(252, 2), swap(254, 2);
  for (int off = 256; off <= 340; off += 4) swap(off, 4);
  return h;
}

// gzip-compressed bytes
std::string gzip(const std::string& raw) {
  z_stream zs{};
  REQUIRE(deflateInit2(&zs, 6, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) == Z_OK);
  std::string out(deflateBound(&zs, uLong(raw.size())) + 64, '\0');
  zs.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(raw.data()));
  zs.avail_in = uInt(raw.size());
  zs.next_out = reinterpret_cast<Bytef*>(out.data());
  zs.avail_out = uInt(out.size());
  REQUIRE(deflate(&zs, Z_FINISH) == Z_STREAM_END);
  out.resize(zs.total_out);
  deflateEnd(&zs);
  return out;
}

const std::string kNrrd =
    "NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: 16 16 16\n"
    "space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (0,0,0)\nendian: little\nencoding: raw\n";
const std::string kMhd =
    "ObjectType = Image\nNDims = 3\nDimSize = 16 16 16\nElementSpacing = 1 1 1\nOffset = 0 0 0\n"
    "TransformMatrix = 1 0 0 0 1 0 0 0 1\nElementType = MET_SHORT\n";

// `text` with its first `from` replaced by `to`
std::string replaced(std::string text, const std::string& from, const std::string& to) {
  const auto at = text.find(from);
  REQUIRE(at != std::string::npos);
  return text.replace(at, from.size(), to);
}

}  // namespace

TEST_CASE("well-formed headers of each format pass, with their sizes and data files") {
  const std::string nii = nifti_header(16, 12, 8, kOne, 4, 16);
  for (const auto& [name, bytes] : std::vector<std::pair<std::string, std::string>>{
           {"a.nii", nii}, {"a.nii.gz", gzip(nii + std::string(16 * 12 * 8 * 2, '\0'))}, {"b.nii", big_endian(nii)}}) {
    INFO(name);
    const CtHeader h = check_ct_header(name, bytes);
    CHECK(h.format == "NIfTI");
    CHECK(h.size == std::vector<std::int64_t>{16, 12, 8});
    CHECK(h.vox_offset == 352);
    CHECK(h.bytes_per_voxel == 2);
    CHECK(h.big_endian == (name == "b.nii"));
  }
  CHECK(check_ct_header("a.nrrd", kNrrd + "\n").data_file.empty());
  CHECK(check_ct_header("a.nhdr", kNrrd + "data file: a.raw\n").data_file == "a.raw");
  CHECK(check_ct_header("a.mha", kMhd + "ElementDataFile = LOCAL\n").data_file.empty());
  const CtHeader m = check_ct_header("a.mhd", kMhd + "ElementDataFile = a.raw\n");
  CHECK(m.format == "MetaImage");
  CHECK(m.data_file == "a.raw");
  CHECK(m.size == std::vector<std::int64_t>{16, 16, 16});
}

TEST_CASE("a NIfTI header's non-finite or oversized geometry is refused, naming the field") {
  const std::vector<std::pair<int, std::string>> fields = {
      {76, "pixdim[0]"},   {80, "pixdim[1]"},   {84, "pixdim[2]"},   {88, "pixdim[3]"},  {112, "scl_slope"},
      {116, "scl_inter"},  {256, "quatern_b"},  {264, "quatern_d"},  {276, "qoffset_z"}, {280, "srow_x[0]"},
      {292, "srow_x[3]"},  {300, "srow_y[1]"},  {324, "srow_z[3]"}};
  for (const auto& [offset, field] : fields)
    for (float bad : {kNan, std::numeric_limits<float>::infinity(), 1e30f}) {
      INFO(field << " = " << bad);
      const std::string e = check_error("ct.nii", nifti_with(offset, bad));
      CHECK_THAT(e, Catch::StartsWith("CT file 'ct.nii': " + field));
      // big-endian and compressed files alike
      CHECK_THAT(check_error("ct.nii", big_endian(nifti_with(offset, bad))), Catch::Contains(field));
      CHECK_THAT(check_error("ct.nii.gz", gzip(nifti_with(offset, bad))), Catch::Contains(field));
    }
  CHECK_THAT(check_error("ct.nii", nifti_with(108, kNan)), Catch::Contains("vox_offset"));
}

TEST_CASE("a NIfTI header that is no 3D NIfTI-1 CT is refused, saying what it is") {
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int16_t>(44, -16)), Catch::Contains("axis 1 has -16 voxels"));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int16_t>(40, 8)), Catch::Contains("dim[0] is 8"));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int16_t>(40, 2)), Catch::Contains("2D image"));
  std::string four = nifti_with<std::int16_t>(40, 4);
  const std::int16_t three = 3;
  std::memcpy(&four[48], &three, 2);
  CHECK_THAT(check_error("ct.nii", four), Catch::Contains("4D image (3 volumes along axis 3)"));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int16_t>(46, 1)), Catch::Contains("2D image"));
  std::string huge = nifti_header(32767, 32767, 32767, kOne, 4, 16);
  CHECK_THAT(check_error("ct.nii", huge), Catch::Contains("at most " + std::to_string(kMaxCtVoxels)));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int16_t>(70, 128)), Catch::Contains("RGB"));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int16_t>(70, 3)), Catch::Contains("datatype 3"));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int32_t>(0, 540)), Catch::Contains("NIfTI-2"));
  CHECK_THAT(check_error("ct.nii", nifti_with<std::int32_t>(0, 12)), Catch::Contains("not a NIfTI-1 header"));
  CHECK_THAT(check_error("ct.nii", nifti_with(344, std::array<char, 4>{'n', 'i', '1', '\0'})), Catch::Contains(".hdr/.img"));
  CHECK_THAT(check_error("ct.nii", nifti_with(344, std::array<char, 4>{0, 0, 0, 0})), Catch::Contains("magic"));
  CHECK_THAT(check_error("ct.nii", nifti_header(16, 16, 16, kOne, 4, 16).substr(0, 200)), Catch::Contains("truncated"));
  CHECK_THAT(check_error("ct.nii.gz", "not gzip at all"), Catch::Contains("corrupt compressed data"));
}

TEST_CASE("a NRRD header's bad fields are refused, naming the field") {
  const auto with = [](const std::string& from, const std::string& to) { return replaced(kNrrd, from, to) + "\n"; };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {with("sizes: 16 16 16", "sizes: 16 -16 16"), "axis 1 has -16 voxels"},
      {with("sizes: 16 16 16", "sizes: 16 16"), "'sizes' has 2 values"},
      {with("sizes: 16 16 16", "sizes: 16 16 1e3"), "axis 2 is '1e3'"},
      {with("sizes: 16 16 16", "sizes: 65537 16 16"), "axis 0 has 65537 voxels"},
      {with("space directions: (1,0,0) (0,1,0) (0,0,1)", "space directions: (1,0,0) (0,nan,0) (0,0,1)"),
       "'space directions' on axis 1 is nan"},
      {with("space directions: (1,0,0) (0,1,0) (0,0,1)", "space directions: none (0,1,0) (0,0,1)"), "'none'"},
      {with("space directions: (1,0,0) (0,1,0) (0,0,1)", "space directions: (1,0) (0,1,0) (0,0,1)"), "2 components"},
      {with("space directions: (1,0,0) (0,1,0) (0,0,1)", "space directions: (1,0,0) (0,1,0) (0,0,1e300)"), "1e+300"},
      {with("space origin: (0,0,0)", "space origin: (inf,0,0)"), "'space origin' is inf"},
      {with("space origin: (0,0,0)", "space origin: (0,0,0"), "without its ')'"},
      {with("space: left-posterior-superior", "space: left-posterior-superior-time"), "4D NRRD space"},
      {with("space directions: (1,0,0) (0,1,0) (0,0,1)", "spacings: 1 nan 1"), "'spacings' on axis 1 is nan"},
      {with("dimension: 3", "dimension: 0"), "'dimension' (line 3) is '0'"},
      {with("type: short\n", ""), "no NRRD 'type'"},
      {with("encoding: raw", ""), "no NRRD 'encoding'"},
      {kNrrd + "data file: LIST\n", "several files"},
      {kNrrd + "data file: slice%03d.raw 1 10 1\n", "several files"},
      {kNrrd + "line skip: -3\n\n", "'line skip'"},
      {kNrrd, "no blank line ends the NRRD header"},
      {"NRRD0009\n" + kNrrd.substr(9) + "\n", "not a NRRD file"},
  };
  for (const auto& [bytes, says] : cases) {
    INFO(bytes);
    const std::string e = check_error("ct.nhdr", bytes);
    CHECK_THAT(e, Catch::StartsWith("CT file 'ct.nhdr': ") && Catch::Contains(says));
    CHECK(e.find('\n') == std::string::npos);
  }
  // axes beyond the 3 spatial ones may say "nan" (unknown) and "none"
  const std::string four = "NRRD0004\ntype: short\ndimension: 4\nsizes: 16 16 16 1\nspacings: 1 1 1 nan\n"
                           "endian: little\nencoding: raw\n\n";
  CHECK(check_ct_header("ct.nrrd", four).dimensions == 4);
}

TEST_CASE("a MetaImage header's bad fields are refused, naming the field") {
  const auto with = [](const std::string& from, const std::string& to) {
    return replaced(kMhd, from, to) + "ElementDataFile = ct.raw\n";
  };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {with("ElementSpacing = 1 1 1", "ElementSpacing = 1 nan 1"), "elementspacing on axis 1 is nan"},
      {with("Offset = 0 0 0", "Offset = 0 0 1e999"), "offset on axis 2 is inf"},
      {with("TransformMatrix = 1 0 0 0 1 0 0 0 1", "TransformMatrix = 1 0 0 0 nan 0 0 0 1"), "transformmatrix is nan"},
      {with("TransformMatrix = 1 0 0 0 1 0 0 0 1", "TransformMatrix = 1 0 0"), "has 3 values; NDims 3 needs 9"},
      {with("DimSize = 16 16 16", "DimSize = 16 -1 16"), "axis 1 has -1 voxels"},
      {with("NDims = 3", "NDims = 11"), "NDims is '11'"},
      {with("NDims = 3", "NDims = 2"), "DimSize has 3 values; NDims is 2"},
      {with("ElementType = MET_SHORT", "ElementType = MET_SHORT\nElementNumberOfChannels = 3"), "3 components per voxel"},
      {with("ObjectType = Image", "Name = " + std::string(300, 'n')), "longer than 254"},
      {with("ObjectType = Image", "no equals sign here"), "not 'Key = Value'"},
      {kMhd + "ElementDataFile = LIST\n", "several files"},
      {kMhd + "ElementDataFile = slice%03d.raw 1 10 1\n", "several files"},
      {kMhd, "no ElementDataFile"},
  };
  for (const auto& [bytes, says] : cases) {
    INFO(bytes);
    const std::string e = check_error("ct.mhd", bytes);
    CHECK_THAT(e, Catch::StartsWith("CT file 'ct.mhd': ") && Catch::Contains(says, Catch::CaseSensitive::No));
    CHECK(e.find('\n') == std::string::npos);
  }
  CHECK_THAT(check_error("ct.hdr", kMhd), Catch::Contains("file name"));
}

TEST_CASE("no prefix or mutation of a header makes the check crash or pass what no CT has") {
  const std::string nii = nifti_header(16, 12, 8, kOne, 4, 16);
  const std::vector<std::pair<std::string, std::string>> seeds = {
      {"s.nii", nii},
      {"s.nii.gz", gzip(nii)},
      {"s.nhdr", kNrrd + "spacings: 1 1 1\ndata file: s.raw\n"},
      {"s.nrrd", kNrrd + "\n"},
      {"s.mhd", kMhd + "ElementDataFile = s.raw\n"}};
  // whatever passes must hold sizes a CT may have (what later code relies on)
  const auto judge = [](const std::string& name, const std::string& bytes) {
    try {
      const CtHeader h = check_ct_header(name, bytes);
      REQUIRE(h.size.size() >= 3);
      for (std::size_t a = 0; a < h.size.size(); ++a) {
        CHECK(h.size[a] >= (a < 3 ? 2 : 1));
        CHECK(h.size[a] <= (a < 3 ? kMaxCtAxisVoxels : 1));
      }
      CHECK(h.size[0] * h.size[1] * h.size[2] <= kMaxCtVoxels);
      CHECK(h.data_file.find('\0') == std::string::npos);
    } catch (const Error&) {
      // refused with a message: fine
    }
  };
  std::mt19937 rng(26);  // fixed: the same mutations every run
  const std::string tokens[] = {"nan", "inf", "-1", "0", "1e308", "\n", "\n\n", "(", ")", ",", "=", ":", " ", "%", "LIST", "\0"};
  for (const auto& [name, seed] : seeds) {
    for (std::size_t n = 0; n <= seed.size(); ++n) judge(name, seed.substr(0, n));
    for (int i = 0; i < 2000; ++i) {
      std::string m = seed;
      const int edits = 1 + int(rng() % 4);
      for (int e = 0; e < edits && !m.empty(); ++e) {
        const std::size_t at = rng() % m.size();
        switch (rng() % 3) {
          case 0: m[at] = char(rng()); break;
          case 1: m.insert(at, tokens[rng() % std::size(tokens)]); break;
          default: m.erase(at, 1 + rng() % 8); break;
        }
      }
      judge(name, m);
    }
  }
}

TEST_CASE("with the server's folders, a CT and the files it consists of must lie inside them") {
  TempDir scenes, other;
  const PathPolicy files({scenes.path.string()});
  const Volume<float> torso = synthetic_torso({40, 32, 12}, {2, 2, 3});
  const auto detached = [&](const std::string& header, const std::string& data_text, const std::string& data_path) {
    const Grid& g = torso.grid;
    std::ofstream(header) << "NRRD0004\ntype: float\ndimension: 3\nsizes: " << g.size.x << " " << g.size.y << " "
                          << g.size.z << "\nspacings: 2 2 3\nendian: little\nencoding: raw\ndata file: " << data_text << "\n";
    std::ofstream(data_path, std::ios::binary)
        .write(reinterpret_cast<const char*>(torso.data.data()), std::streamsize(torso.bytes()));
  };
  const auto prep_error = [&](const std::string& ct) {
    return error_message([&] { prepare_patient(ct_scene(ct, ""), nullptr, &files); });
  };
  // inside, in a sibling folder of the header: the server's folders, not the header's, decide
  fs::create_directories(scenes.path / "ct");
  fs::create_directories(scenes.path / "raw");
  detached(scenes / "ct/in.nhdr", "../raw/in.raw", scenes / "raw/in.raw");
  CHECK(prep_error(scenes / "ct/in.nhdr").empty());
  // outside: the data file, the CT itself, a DICOM folder's file (a link out)
  detached(scenes / "ct/out.nhdr", other / "out.raw", other / "out.raw");
  CHECK_THAT(prep_error(scenes / "ct/out.nhdr"),
             Catch::Contains("its data file") && Catch::Contains("outside the folders this server allows"));
  write_volume_nrrd(other / "ct.nrrd", torso);
  CHECK_THAT(prep_error(other / "ct.nrrd"), Catch::Contains("outside the folders this server allows"));
  fs::create_directories(scenes.path / "dicom");
  fs::create_symlink(other.path / "ct.nrrd", scenes.path / "dicom" / "slice.dcm");
  CHECK_THAT(prep_error(scenes / "dicom"), Catch::Contains("slice.dcm") && Catch::Contains("outside"));
}

TEST_CASE("a NIfTI's NaN voxels are found in either byte order, also across the scan's 1 MiB reads") {
  TempDir d;
  // 70^3 float32 voxels (1.37 MB) from byte 354: voxel 262055 spans bytes 1048574..1048577,
  // across the first 1 MiB read
  const int n = 70;
  std::vector<float> v(std::size_t(n) * n * n, -1000.0f);
  v[262055] = kNan;
  for (bool big : {false, true}) {
    INFO((big ? "big" : "little") << "-endian");
    std::string h = nifti_header(n, n, n, kOne, 16, 32);
    const float offset = 354;
    std::memcpy(&h[108], &offset, 4);
    std::string data(reinterpret_cast<const char*>(v.data()), v.size() * 4);
    if (big) {
      h = big_endian(h);
      for (std::size_t i = 0; i < data.size(); i += 4) std::reverse(data.begin() + long(i), data.begin() + long(i) + 4);
    }
    {
      std::ofstream o(d / "ct.nii", std::ios::binary);
      o << h;
      o.write("\0\0", 2);
      o << data;
    }
    CHECK_THAT(error_message([&] { prepare_patient(ct_scene(d / "ct.nii", "")); }),
               Catch::Contains("1 voxel(s) are NaN or Inf (the first at index (45, 33, 53))"));
  }
}
