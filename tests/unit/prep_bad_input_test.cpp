// Bad CT inputs: each is refused with a palpsim::Error naming the file and the
// problem, and leaves nothing in the cache.
#include <catch2/catch.hpp>

#include <sys/stat.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>

#include "core/error.h"
#include "prep/prepare.h"
#include "support/data.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;
namespace fs = std::filesystem;

namespace {

// prepares `ct` with the cache in dir/cache; returns the error message ("" if none)
std::string prep_error(const TempDir& dir, const std::string& ct, const std::function<void(Scene&)>& edit = {}) {
  Scene s = ct_scene(ct, dir / "cache");
  if (edit) edit(s);
  return error_message([&] { prepare_patient(s); });
}

// the cache holds no entry and no temporary folder
bool cache_empty(const TempDir& dir) {
  const fs::path c = dir.path / "cache";
  return !fs::exists(c) || fs::is_empty(c);
}

std::vector<float> cube(int n, float inside, float outside) {
  std::vector<float> v(std::size_t(n) * n * n, outside);
  for (int k = n / 4; k < 3 * n / 4; ++k)
    for (int j = n / 4; j < 3 * n / 4; ++j)
      for (int i = n / 4; i < 3 * n / 4; ++i) v[(std::size_t(k) * n + j) * n + i] = inside;
  return v;
}

}  // namespace

TEST_CASE("a missing path is refused by name") {
  TempDir d;
  const std::string e = prep_error(d, d / "nowhere.nii.gz");
  CHECK_THAT(e, Catch::Contains("nowhere.nii.gz") && Catch::Contains("no such file"));
  CHECK(cache_empty(d));
}

TEST_CASE("a data: path with no data folder says how to provide one") {
  TempDir d;
  const std::string e = prep_error(d, "data:ct/abdomen-lumbar-3mm.nii.gz");
  CHECK_THAT(e, Catch::Contains("data:ct/abdomen-lumbar-3mm.nii.gz") && Catch::Contains("PALPSIM_DATA"));
  CHECK(cache_empty(d));
}

TEST_CASE("a folder without DICOM is refused") {
  TempDir d;
  fs::create_directories(d.path / "notes");
  std::ofstream(d / "notes/readme.txt") << "no images here\n";
  const std::string e = prep_error(d, d / "notes");
  CHECK_THAT(e, Catch::Contains("notes") && Catch::Contains("no readable DICOM"));
  CHECK(cache_empty(d));
}

TEST_CASE("corrupt DICOM files are refused") {
  TempDir d;
  fs::create_directories(d.path / "bad");
  for (int n = 0; n < 3; ++n) {
    std::ofstream f(d / ("bad/slice" + std::to_string(n) + ".dcm"), std::ios::binary);
    f << std::string(128, '\0') << "DICM" << std::string(200, '\x7f');
  }
  const std::string e = prep_error(d, d / "bad");
  CHECK_THAT(e, Catch::Contains("bad"));
  CHECK_FALSE(e.empty());
  CHECK(cache_empty(d));
}

TEST_CASE("a truncated DICOM series is refused") {
  const std::string series = shared_data_file("ct/dicom-partial-body");
  if (series.empty()) return;
  TempDir d;
  fs::create_directories(d.path / "cut");
  for (int n = 0; n < 4; ++n) {
    const std::string name = "slice0" + std::to_string(n) + ".dcm";
    fs::copy_file(series + "/" + name, d / ("cut/" + name));
  }
  // cut the last file in the middle of its pixel data
  const std::string victim = d / "cut/slice03.dcm";
  fs::resize_file(victim, fs::file_size(victim) / 2);
  const std::string e = prep_error(d, d / "cut");
  CHECK_THAT(e, Catch::Contains("cut"));
  CHECK_FALSE(e.empty());
  CHECK(cache_empty(d));
}

TEST_CASE("a truncated or corrupt NIfTI is refused") {
  TempDir d;
  const double sp[3] = {1, 1, 2};
  std::vector<std::int16_t> vox(40 * 40 * 20, -1000);
  for (int k = 2; k < 18; ++k)
    for (int j = 5; j < 35; ++j)
      for (int i = 5; i < 35; ++i) vox[(std::size_t(k) * 40 + j) * 40 + i] = 40;  // a 30 x 30 x 32 mm block
  write_nifti_int16(d / "ok.nii", 40, 40, 20, sp, vox);
  REQUIRE(std::system(("gzip -k -f '" + (d / "ok.nii") + "'").c_str()) == 0);
  fs::copy_file(d / "ok.nii.gz", d / "cut.nii.gz");
  fs::resize_file(d / "cut.nii.gz", fs::file_size(d / "cut.nii.gz") * 6 / 10);
  std::string e = prep_error(d, d / "cut.nii.gz");
  CHECK_THAT(e, Catch::Contains("cut.nii.gz"));
  CHECK_FALSE(e.empty());
  // uncompressed and cut short
  fs::copy_file(d / "ok.nii", d / "short.nii");
  fs::resize_file(d / "short.nii", 352 + 1000);
  e = prep_error(d, d / "short.nii");
  CHECK_THAT(e, Catch::Contains("short.nii"));
  CHECK_FALSE(e.empty());
  // header garbage
  std::ofstream(d / "junk.nii", std::ios::binary) << std::string(400, 'x');
  e = prep_error(d, d / "junk.nii");
  CHECK_THAT(e, Catch::Contains("junk.nii"));
  CHECK_FALSE(e.empty());
  CHECK(cache_empty(d));
  // the intact file is read (the test's files are right; only the damage is refused)
  Scene s = ct_scene(d / "ok.nii.gz", "");
  CHECK_NOTHROW(prepare_patient(s));
}

TEST_CASE("2D and 4D images are refused") {
  TempDir d;
  std::vector<float> img(32 * 32, 40), vol4(16 * 16 * 16 * 2, 40);
  write_nrrd_file(d / "slice.nrrd", "float", {32, 32}, {1, 1}, img.data(), img.size() * 4);
  CHECK_THAT(prep_error(d, d / "slice.nrrd"), Catch::Contains("slice.nrrd") && Catch::Contains("2D"));
  write_nrrd_file(d / "one.nrrd", "float", {32, 32, 1}, {1, 1, 1}, img.data(), img.size() * 4);
  CHECK_THAT(prep_error(d, d / "one.nrrd"), Catch::Contains("one.nrrd") && Catch::Contains("2D"));
  write_nrrd_file(d / "time.nrrd", "float", {16, 16, 16, 2}, {1, 1, 1, 1}, vol4.data(), vol4.size() * 4);
  CHECK_THAT(prep_error(d, d / "time.nrrd"), Catch::Contains("time.nrrd") && Catch::Contains("4D"));
  CHECK(cache_empty(d));
}

TEST_CASE("an all-air volume is refused") {
  TempDir d;
  std::vector<float> air(24 * 24 * 24, -1000);
  write_nrrd_file(d / "air.nrrd", "float", {24, 24, 24}, {1, 1, 1}, air.data(), air.size() * 4);
  CHECK_THAT(prep_error(d, d / "air.nrrd"), Catch::Contains("air.nrrd") && Catch::Contains("all-air"));
  CHECK(cache_empty(d));
}

TEST_CASE("zero and negative spacing are refused") {
  TempDir d;
  const auto v = cube(16, 40, -1000);
  write_nrrd_file(d / "zero.nrrd", "float", {16, 16, 16}, {1, 0, 1}, v.data(), v.size() * 4);
  CHECK_THAT(prep_error(d, d / "zero.nrrd"), Catch::Contains("zero.nrrd") && Catch::Contains("spacing"));
  {
    std::ofstream h(d / "neg.mhd");
    h << "ObjectType = Image\nNDims = 3\nDimSize = 16 16 16\nElementSpacing = 1 -2 1\n"
         "ElementType = MET_FLOAT\nElementDataFile = neg.raw\n";
    std::ofstream(d / "neg.raw", std::ios::binary).write(reinterpret_cast<const char*>(v.data()), std::streamsize(v.size() * 4));
  }
  CHECK_THAT(prep_error(d, d / "neg.mhd"), Catch::Contains("neg.mhd") && Catch::Contains("spacing"));
  CHECK(cache_empty(d));
}

TEST_CASE("NaN or Inf voxels in a float image are refused") {
  TempDir d;
  auto v = cube(16, 40, -1000);
  v[5] = std::numeric_limits<float>::quiet_NaN();
  write_nrrd_file(d / "nan.nrrd", "float", {16, 16, 16}, {1, 1, 1}, v.data(), v.size() * 4);
  CHECK_THAT(prep_error(d, d / "nan.nrrd"), Catch::Contains("nan.nrrd") && Catch::Contains("NaN or Inf"));
  v[5] = 0, v[77] = std::numeric_limits<float>::infinity();
  write_nrrd_file(d / "inf.nrrd", "float", {16, 16, 16}, {1, 1, 1}, v.data(), v.size() * 4);
  CHECK_THAT(prep_error(d, d / "inf.nrrd"), Catch::Contains("inf.nrrd") && Catch::Contains("NaN or Inf"));
  CHECK(cache_empty(d));
}

TEST_CASE("an unsigned 8-bit image is not HU unless both thresholds are set") {
  TempDir d;
  std::vector<std::uint8_t> v(32 * 32 * 32, 0);
  for (int k = 8; k < 24; ++k)
    for (int j = 8; j < 24; ++j)
      for (int i = 8; i < 24; ++i) v[(std::size_t(k) * 32 + j) * 32 + i] = (i >= 14 && i < 18 && j >= 14 && j < 18) ? 250 : 100;
  write_nrrd_file(d / "u8.nrrd", "uchar", {32, 32, 32}, {1, 1, 1}, v.data(), v.size());
  const std::string e = prep_error(d, d / "u8.nrrd");
  CHECK_THAT(e, Catch::Contains("u8.nrrd") && Catch::Contains("prep.air_threshold") &&
                    Catch::Contains("prep.bone_threshold") && Catch::Contains("8-bit"));
  // one threshold is not enough
  CHECK_FALSE(prep_error(d, d / "u8.nrrd", [](Scene& s) { s.prep.air_threshold_set = true; }).empty());
  CHECK(cache_empty(d));
  // both set, in the image's units: processed
  Scene s = ct_scene(d / "u8.nrrd", "");
  s.prep.air_threshold = 50, s.prep.air_threshold_set = true;
  s.prep.bone_threshold = 200, s.prep.bone_threshold_set = true;
  s.prep.bone_min_volume_ml = 0;
  PrepReport r;
  const PatientPtr p = prepare_patient(s, &r);
  // the 16 mm cube (4.096 ml), its edges rounded by the body mask's 5 mm opening
  CHECK(r.body_ml <= 4.096);
  CHECK(r.body_ml > 3.5);
  CHECK(p->has_bone);
  CHECK_THAT(r.json, Catch::Contains("\"image units\""));
}

TEST_CASE("a float image whose range no CT has is refused as not HU") {
  TempDir d;
  const auto v = cube(16, 0.8f, 0.0f);  // normalised intensities 0..1
  write_nrrd_file(d / "unit.nrrd", "float", {16, 16, 16}, {1, 1, 1}, v.data(), v.size() * 4);
  CHECK_THAT(prep_error(d, d / "unit.nrrd"), Catch::Contains("unit.nrrd") && Catch::Contains("Hounsfield"));
}

TEST_CASE("a volume above prep.max_memory_mb is refused before its voxels are read") {
  TempDir d;
  // a detached header declaring 2000^3 voxels over a tiny data file: reading it would fail,
  // so the memory error proves the check comes first
  std::ofstream(d / "big.nhdr") << "NRRD0004\ntype: short\ndimension: 3\nsizes: 2000 2000 2000\n"
                                   "spacings: 0.5 0.5 0.5\nendian: little\nencoding: raw\ndata file: big.raw\n\n";
  std::ofstream(d / "big.raw") << "xx";
  const std::string e = prep_error(d, d / "big.nhdr", [](Scene& s) { s.prep.max_memory_mb = 4096; });
  CHECK_THAT(e, Catch::Contains("big.nhdr") && Catch::Contains("prep.max_memory_mb"));
  CHECK(cache_empty(d));
  // a small volume under a tight limit
  const auto v = cube(64, 40, -1000);
  write_nrrd_file(d / "small.nrrd", "float", {64, 64, 64}, {1, 1, 1}, v.data(), v.size() * 4);
  CHECK_THAT(prep_error(d, d / "small.nrrd", [](Scene& s) { s.prep.max_memory_mb = 1; }),
             Catch::Contains("small.nrrd") && Catch::Contains("MiB"));
}

TEST_CASE("the memory estimate refuses a phantom or a CT from its geometry, before anything is built or read") {
  TempDir d;
  // the 0.25 mm phantom (about 13 GiB to prepare): refused by the default limit before a
  // voxel of it is made, so no "phantom" stage ran
  Scene s;
  s.use_phantom = true;
  s.phantom_voxel_mm = 0.25;
  s.prep.cache_dir = (d / "cache");
  PrepReport r;
  CHECK_THAT(error_message([&] { prepare_patient(s, &r); }),
             Catch::Contains("phantom at 0.25 mm") && Catch::Contains("prep.max_memory_mb"));
  for (const auto& [stage, seconds] : r.stage_s) CHECK(stage != "phantom");
  // a CT header declaring 2000^3 voxels: refused from the header, before its data are
  // hashed for the cache (a "hash" stage) or read
  std::ofstream(d / "huge.nhdr") << "NRRD0004\ntype: short\ndimension: 3\nsizes: 2000 2000 2000\n"
                                    "spacings: 0.5 0.5 0.5\nendian: little\nencoding: raw\ndata file: huge.raw\n\n";
  std::ofstream(d / "huge.raw") << "xx";
  const Scene ct = ct_scene(d / "huge.nhdr", d / "cache");
  CHECK_THAT(error_message([&] { prepare_patient(ct, &r); }),
             Catch::Contains("huge.nhdr") && Catch::Contains("prep.max_memory_mb"));
  for (const auto& [stage, seconds] : r.stage_s) CHECK(stage != "hash");
  CHECK(cache_empty(d));
}

TEST_CASE("a DICOM folder with two series is refused with their UIDs unless one is chosen") {
  const std::string series = shared_data_file("ct/dicom-partial-body");
  if (series.empty()) return;
  TempDir d;
  fs::create_directories(d.path / "two");
  for (int n = 0; n < 20; ++n) {
    const std::string name = std::string("slice") + (n < 10 ? "0" : "") + std::to_string(n) + ".dcm";
    fs::copy_file(series + "/" + name, d / ("two/" + name));
  }
  // a second series: the first three slices again with a SeriesInstanceUID (the
  // de-identified files have an empty one); in explicit-VR little endian the
  // top-level element may grow without touching any other length
  std::string uid;
  for (int n = 0; n < 3; ++n) {
    const std::string name = "slice0" + std::to_string(n) + ".dcm";
    std::ifstream in(series + "/" + name, std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(in)), {});
    const std::string empty_uid("\x20\x00\x0e\x00UI\x00\x00", 8);  // (0020,000E) SeriesInstanceUID, length 0
    const std::size_t at = bytes.find(empty_uid);
    REQUIRE(at != std::string::npos);
    bytes.replace(at, 8, std::string("\x20\x00\x0e\x00UI\x08\x00", 8) + "1.2.3.44");
    std::ofstream(d / ("two/b" + name), std::ios::binary) << bytes;
  }
  const std::string e = prep_error(d, d / "two");
  CHECK_THAT(e, Catch::Contains("2 DICOM series") && Catch::Contains("prep.dicom_series_uid") &&
                    Catch::Contains("(20 slices)") && Catch::Contains("(3 slices)"));
  // choose the big series by the identifier the message lists with it
  const std::size_t at20 = e.find(" (20 slices)");
  REQUIRE(at20 != std::string::npos);
  const std::size_t from = e.rfind("\n  ", at20) + 3;
  uid = e.substr(from, at20 - from);
  CHECK_THAT(prep_error(d, d / "two", [](Scene& s) { s.prep.dicom_series_uid = "9.9.9"; }),
             Catch::Contains("no DICOM series with prep.dicom_series_uid"));
  Scene s = ct_scene(d / "two", "");
  s.prep.dicom_series_uid = uid;
  s.prep.spacing_mm = 2.0;
  PrepReport r;
  CHECK_NOTHROW(prepare_patient(s, &r));
  CHECK_THAT(r.json, Catch::Contains("\"files\": 20"));
}

// ---- issue 26: values on which ITK aborts, files outside the CT's folder, FIFOs ----

namespace {

// a float volume as a detached NRRD header `header` whose "data file" line reads
// `data_file_text`, the voxels written to `data_path`
void write_detached_nrrd(const std::string& header, const std::string& data_file_text, const std::string& data_path,
                         const Volume<float>& v) {
  const Grid& g = v.grid;
  std::ofstream(header) << "NRRD0004\ntype: float\ndimension: 3\nsizes: " << g.size.x << " " << g.size.y << " "
                        << g.size.z << "\nspacings: " << g.spacing_mm.x << " " << g.spacing_mm.y << " " << g.spacing_mm.z
                        << "\nendian: little\nencoding: raw\ndata file: " << data_file_text << "\n";
  std::ofstream(data_path, std::ios::binary).write(reinterpret_cast<const char*>(v.data.data()), std::streamsize(v.bytes()));
}

}  // namespace

TEST_CASE("a NaN spacing or sform in a NIfTI header is refused by name, never an abort") {
  TempDir d;
  const auto c = cube(16, 40, -1000);
  const std::vector<std::int16_t> vox(c.begin(), c.end());
  const double nan = std::numeric_limits<double>::quiet_NaN();
  // ITK's NIfTI reader hands pixdim and the sform to VNL, which aborts on NaN
  for (int axis = 0; axis < 3; ++axis) {
    double sp[3] = {1, 1, 1};
    sp[axis] = nan;
    write_nifti_int16(d / "nan.nii", 16, 16, 16, sp, vox);
    INFO("axis " << axis);
    CHECK_THAT(prep_error(d, d / "nan.nii"),
               Catch::Contains("nan.nii") && Catch::Contains("pixdim[" + std::to_string(axis + 1) + "]"));
  }
  // a finite pixdim, a NaN in the sform's second row
  const double one[3] = {1, 1, 1};
  std::string h = nifti_header(16, 16, 16, one, 4, 16);
  const float fnan = std::numeric_limits<float>::quiet_NaN();
  std::memcpy(&h[300], &fnan, 4);  // srow_y[1]
  std::ofstream(d / "sform.nii", std::ios::binary)
      << h << std::string(reinterpret_cast<const char*>(vox.data()), vox.size() * 2);
  CHECK_THAT(prep_error(d, d / "sform.nii"), Catch::Contains("sform.nii") && Catch::Contains("srow_y[1]"));
  CHECK(cache_empty(d));
}

TEST_CASE("a NaN origin or direction in a NRRD header is refused by name, in one line") {
  TempDir d;
  const auto c = cube(16, 40, -1000);
  for (const std::string& line : {std::string("space origin: (nan,0,0)"),
                                  std::string("space directions: (1,0,0) (0,nan,0) (0,0,1)")}) {
    INFO(line);
    std::ofstream o(d / "bad.nrrd", std::ios::binary);
    o << "NRRD0004\ntype: float\ndimension: 3\nspace: left-posterior-superior\nsizes: 16 16 16\n"
      << (line.rfind("space origin", 0) == 0 ? "space directions: (1,0,0) (0,1,0) (0,0,1)\n" : "")
      << line << "\nendian: little\nencoding: raw\n\n";
    o.write(reinterpret_cast<const char*>(c.data()), std::streamsize(c.size() * 4));
    o.close();
    const std::string e = prep_error(d, d / "bad.nrrd");
    CHECK_THAT(e, Catch::Contains("bad.nrrd") && Catch::Contains(line.substr(0, line.find(':'))) && Catch::Contains("nan"));
    CHECK(e.find('\n') == std::string::npos);  // one line, not the NRRD library's trace
  }
  CHECK(cache_empty(d));
}

TEST_CASE("a data file a header names outside the CT's folder is refused (NRRD, MetaImage, a link)") {
  TempDir d, other;
  const Volume<float> torso = synthetic_torso({40, 32, 12}, {2, 2, 3});
  // the voxels lie in another folder: named absolutely, by "..", or through a link
  write_detached_nrrd(d / "abs.nhdr", other / "data.raw", other / "data.raw", torso);
  const std::string up = "../" + other.path.filename().string() + "/data.raw";
  write_detached_nrrd(d / "up.nhdr", up, other / "data.raw", torso);
  fs::create_symlink(other.path / "data.raw", d.path / "link.raw");
  write_detached_nrrd(d / "link.nhdr", "link.raw", other / "data.raw", torso);
  for (const char* name : {"abs.nhdr", "up.nhdr", "link.nhdr"}) {
    INFO(name);
    const std::string e = prep_error(d, d / name);
    CHECK_THAT(e, Catch::Contains(name) && Catch::Contains("data file") && Catch::Contains("outside the CT's folder"));
  }
  std::ofstream(d / "abs.mhd") << "ObjectType = Image\nNDims = 3\nDimSize = 40 32 12\nElementSpacing = 2 2 3\n"
                                  "ElementType = MET_FLOAT\nElementDataFile = " << (other / "data.raw") << "\n";
  CHECK_THAT(prep_error(d, d / "abs.mhd"), Catch::Contains("abs.mhd") && Catch::Contains("outside the CT's folder"));
  CHECK(cache_empty(d));
  // the same voxels beside their header are read
  write_detached_nrrd(d / "near.nhdr", "near.raw", d / "near.raw", torso);
  CHECK(prep_error(d, d / "near.nhdr").empty());
}

TEST_CASE("a FIFO as the CT, as a header's data file or in a DICOM folder is refused without reading it") {
  TempDir d;
  REQUIRE(::mkfifo((d / "pipe.nii").c_str(), 0600) == 0);
  CHECK_THAT(prep_error(d, d / "pipe.nii"), Catch::Contains("pipe.nii") && Catch::Contains("FIFO"));
  REQUIRE(::mkfifo((d / "pipe.raw").c_str(), 0600) == 0);
  std::ofstream(d / "pipe.nhdr") << "NRRD0004\ntype: float\ndimension: 3\nsizes: 16 16 16\nspacings: 1 1 1\n"
                                    "endian: little\nencoding: raw\ndata file: pipe.raw\n";
  CHECK_THAT(prep_error(d, d / "pipe.nhdr"), Catch::Contains("pipe.raw") && Catch::Contains("FIFO"));
  fs::create_directory(d.path / "dicom");
  REQUIRE(::mkfifo((d / "dicom/slice.dcm").c_str(), 0600) == 0);
  CHECK_THAT(prep_error(d, d / "dicom"), Catch::Contains("slice.dcm") && Catch::Contains("FIFO"));
  CHECK(cache_empty(d));
}

TEST_CASE("NaN voxels of a NIfTI are refused, and an all-NaN CT says it holds no finite value") {
  TempDir d;
  const double one[3] = {1, 1, 1};
  // ITK's NIfTI library turns NaN into 0: the values are checked before it reads them
  write_nifti_float(d / "allnan.nii", 16, 16, 16, one, std::vector<float>(16 * 16 * 16, NAN));
  CHECK_THAT(prep_error(d, d / "allnan.nii"), Catch::Contains("allnan.nii") && Catch::Contains("holds no finite value"));
  auto c = cube(16, 40, -1000);
  c[17] = std::numeric_limits<float>::infinity();
  write_nifti_float(d / "inf.nii", 16, 16, 16, one, c);
  CHECK_THAT(prep_error(d, d / "inf.nii"),
             Catch::Contains("inf.nii") && Catch::Contains("1 voxel(s) are NaN or Inf") && Catch::Contains("(1, 1, 0)"));
  // the same for another format
  const std::vector<float> nan(16 * 16 * 16, NAN);
  write_nrrd_file(d / "allnan.nrrd", "float", {16, 16, 16}, {1, 1, 1}, nan.data(), nan.size() * 4);
  CHECK_THAT(prep_error(d, d / "allnan.nrrd"), Catch::Contains("holds no finite value"));
  CHECK(cache_empty(d));
}

TEST_CASE("a negative size and a damaged NRRD header get one line naming the field") {
  TempDir d;
  const auto c = cube(16, 40, -1000);
  write_nrrd_file(d / "neg.nrrd", "float", {16, -16, 16}, {1, 1, 1}, c.data(), c.size() * 4);
  std::ofstream(d / "bad.nhdr") << "NRRD0004\ntype: float\ndimension: 3\nsizes: 16 16 x\nspacings: 1 1 1\n"
                                   "endian: little\nencoding: raw\ndata file: bad.raw\n";
  std::ofstream(d / "bad.raw") << "x";
  const std::vector<std::int16_t> vox(16 * 16 * 16, 40);
  const double one[3] = {1, 1, 1};
  write_nifti_int16(d / "neg.nii", 16, 16, 16, one, vox);
  {
    std::fstream f(d / "neg.nii", std::ios::in | std::ios::out | std::ios::binary);
    const std::int16_t minus = -16;
    f.seekp(44);  // dim[2]
    f.write(reinterpret_cast<const char*>(&minus), 2);
  }
  for (const char* name : {"neg.nrrd", "bad.nhdr", "neg.nii"}) {
    INFO(name);
    const std::string e = prep_error(d, d / name);
    CHECK_THAT(e, Catch::Contains(name) && (Catch::Contains("sizes") || Catch::Contains("dim")));
    CHECK(e.find('\n') == std::string::npos);
  }
}
