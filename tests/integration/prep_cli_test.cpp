// palpsim-prep as a user runs it: outputs on success; on bad input a non-zero exit,
// a message naming the file or field, and no output folder.
#include <catch2/catch.hpp>

#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>

#include <png.h>

#include "unit/prep_files.h"

using namespace palpsim::test;
namespace fs = std::filesystem;

namespace {

struct Run {
  int code;
  std::string output;
};

// runs palpsim-prep with `args`, capturing stdout and stderr
Run prep(const std::string& args) {
  const std::string cmd = std::string(PALPSIM_BINARY_DIR) + "/palpsim-prep " + args + " 2>&1";
  FILE* p = popen(cmd.c_str(), "r");
  std::string out;
  char buf[4096];
  std::size_t n;
  while ((n = fread(buf, 1, sizeof buf, p)) > 0) out.append(buf, n);
  const int status = pclose(p);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

// the longest vertical run of pixels of exactly `rgb` in each column of the histogram strip
// of palpsim-prep's preview: the rows from the first that holds its bars' background
// (40, 40, 64) down (empty when the file cannot be read)
std::vector<int> histogram_runs(const std::string& path, const std::uint8_t (&rgb)[3]) {
  png_image im{};
  im.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_file(&im, path.c_str())) return {};
  im.format = PNG_FORMAT_RGB;
  std::vector<std::uint8_t> px(PNG_IMAGE_SIZE(im));
  if (!png_image_finish_read(&im, nullptr, px.data(), 0, nullptr)) return {};
  const int w = int(im.width), h = int(im.height);
  const auto is = [&](int x, int y, const std::uint8_t (&c)[3]) {
    const std::uint8_t* p = &px[(std::size_t(y) * w + x) * 3];
    return p[0] == c[0] && p[1] == c[1] && p[2] == c[2];
  };
  const std::uint8_t bar_background[3] = {40, 40, 64};
  int strip = h;
  for (int y = 0; y < h && strip == h; ++y)
    for (int x = 0; x < w; ++x)
      if (is(x, y, bar_background)) {
        strip = y;
        break;
      }
  std::vector<int> best(std::size_t(w), 0);
  for (int x = 0; x < w; ++x)
    for (int y = strip, run = 0; y < h; ++y) {
      run = is(x, y, rgb) ? run + 1 : 0;
      best[std::size_t(x)] = std::max(best[std::size_t(x)], run);
    }
  return best;
}

// the first column whose run is at least `min_run` pixels (-1: none)
int first_column(const std::vector<int>& runs, int min_run) {
  for (std::size_t x = 0; x < runs.size(); ++x)
    if (runs[x] >= min_run) return int(x);
  return -1;
}

}  // namespace

TEST_CASE("palpsim-prep writes every output for a CT file") {
  TempDir d;
  write_volume_nrrd(d / "torso.nrrd", synthetic_torso({70, 50, 16}, {1.5, 1.5, 2.5}));
  const Run r = prep("'" + (d / "torso.nrrd") + "' --no-cache --out '" + (d / "out") + "'");
  INFO(r.output);
  REQUIRE(r.code == 0);
  for (const char* f : {"F.nrrd", "body.nrrd", "bone.nrrd", "dist_bone.nrrd", "dist_skin.nrrd", "preview.png", "prep.json"})
    CHECK(fs::file_size(d.path / "out" / f) > 0);
  std::ifstream j(d / "out/prep.json");
  const std::string json((std::istreambuf_iterator<char>(j)), {});
  CHECK_THAT(json, Catch::Contains("\"body_ml\"") && Catch::Contains("\"bone_ml\"") &&
                       Catch::Contains("\"stages_s\"") && Catch::Contains("\"value_range\"") &&
                       Catch::Contains("\"spacing_mm\": [1.5, 1.5, 2.5]"));
  // the bone section: automatic thresholds and why, volume per region, the column and
  // warnings (the torso's bone tube lies behind its centre, on the midline, but has
  // neither vertebrae between discs nor a canal: no spine, warned); the thresholds and
  // the verdict are printed too
  CHECK_THAT(json, Catch::Contains("\"bone\": {\"thresholds\": {\"automatic\": true") &&
                       Catch::Contains("\"reason\": \"automatic from the body's histogram") &&
                       Catch::Contains("\"regions_ml\": {\"spine\": ") && Catch::Contains("\"spine_found\": false") &&
                       Catch::Contains("\"spine\": {\"found\": false") && Catch::Contains("\"segments\": 1") &&
                       Catch::Contains("\"warnings\": [\"no spine found: "));
  CHECK_THAT(r.output, Catch::Contains("bone auto: ") && Catch::Contains("no spine: "));
  // the settings say the bone threshold was automatic, not the unused default of 200 HU
  CHECK_THAT(json, Catch::Contains("\"bone_threshold\": \"auto\""));
  CHECK_THAT(json, !Catch::Contains("\"bone_threshold\": 200"));
}

TEST_CASE("palpsim-prep on bad input exits non-zero, names the problem and writes nothing") {
  TempDir d;
  // a missing CT
  Run r = prep("'" + (d / "missing.nii.gz") + "' --out '" + (d / "out") + "'");
  CHECK(r.code != 0);
  CHECK_THAT(r.output, Catch::Contains("missing.nii.gz"));
  CHECK_FALSE(fs::exists(d.path / "out"));
  // a scene with an unknown field, and one with an out-of-range value
  std::ofstream(d / "unknown.textproto") << "phantom {}\nprep { colour: 3 }\n";
  r = prep("--scene '" + (d / "unknown.textproto") + "' --out '" + (d / "out") + "'");
  CHECK(r.code != 0);
  CHECK_THAT(r.output, Catch::Contains("unknown.textproto:2"));
  std::ofstream(d / "range.textproto") << "phantom {}\nprep {\n  spacing_mm: 99\n}\n";
  r = prep("--scene '" + (d / "range.textproto") + "' --out '" + (d / "out") + "'");
  CHECK(r.code != 0);
  CHECK_THAT(r.output, Catch::Contains("range.textproto:3") && Catch::Contains("spacing_mm"));
  CHECK_FALSE(fs::exists(d.path / "out"));
  // nothing half-written beside it either
  for (const auto& e : fs::directory_iterator(d.path)) CHECK_FALSE(e.is_directory());
  // usage errors
  CHECK(prep("").code == 2);
}

TEST_CASE("palpsim-prep --scene-doc lists the prep fields") {
  const Run r = prep("--scene-doc");
  CHECK(r.code == 0);
  CHECK_THAT(r.output, Catch::Contains("air_threshold") && Catch::Contains("bone_min_volume_ml"));
}

TEST_CASE("palpsim-prep refuses a NaN spacing and a data file outside the CT's folder in one line, never aborting") {
  TempDir d, other;
  // a NIfTI with pixdim[2] NaN: ITK's reader would abort in VNL (exit status 134)
  const double sp[3] = {1, std::numeric_limits<double>::quiet_NaN(), 1};
  write_nifti_int16(d / "nan.nii", 16, 16, 16, sp, std::vector<std::int16_t>(16 * 16 * 16, 40));
  Run r = prep("'" + (d / "nan.nii") + "' --no-cache --out '" + (d / "out") + "'");
  CHECK(r.code == 1);
  CHECK_THAT(r.output, Catch::Contains("nan.nii") && Catch::Contains("pixdim[2]"));
  CHECK(std::count(r.output.begin(), r.output.end(), '\n') == 1);
  // a detached header whose voxels are another folder's file (a secret, say)
  std::ofstream(other / "secret") << std::string(16 * 16 * 16, 'S');
  std::ofstream(d / "steal.nhdr") << "NRRD0004\ntype: uchar\ndimension: 3\nsizes: 16 16 16\nspacings: 1 1 1\n"
                                     "encoding: raw\ndata file: " << (other / "secret") << "\n";
  r = prep("'" + (d / "steal.nhdr") + "' --no-cache --out '" + (d / "out") + "'");
  CHECK(r.code == 1);
  CHECK_THAT(r.output, Catch::Contains("steal.nhdr") && Catch::Contains("outside the CT's folder"));
  CHECK(std::count(r.output.begin(), r.output.end(), '\n') == 1);
  CHECK_FALSE(fs::exists(d.path / "out"));
}

TEST_CASE("palpsim-prep --air-threshold and --bone-threshold process an 8-bit image, naming image units, not HU") {
  TempDir d;
  // the synthetic torso as an 8-bit image mapping -1000..1000 HU onto 0..255: air 0,
  // soft tissue 133, marrow 147, cortex 242
  const palpsim::Volume<float> hu = synthetic_torso({70, 50, 16}, {1.5, 1.5, 2.5});
  std::vector<std::uint8_t> u8(hu.data.size());
  for (std::size_t i = 0; i < u8.size(); ++i)
    u8[i] = std::uint8_t(std::lround(std::clamp((hu.data[i] + 1000.0) / 2000.0 * 255.0, 0.0, 255.0)));
  write_nrrd_file(d / "chest8.nrrd", "uchar", {70, 50, 16}, {1.5, 1.5, 2.5}, u8.data(), u8.size());
  const std::string io = "'" + (d / "chest8.nrrd") + "' --no-cache --out '" + (d / "out") + "'";

  // without the flags: refused in one line that names them and where the defaults would fall
  Run r = prep(io);
  CHECK(r.code == 1);
  CHECK_THAT(r.output, Catch::Contains("--air-threshold V --bone-threshold V") &&
                           Catch::Contains("the default -400 and 200 HU are about"));
  // a bad value: one line naming the flag and the value
  r = prep(io + " --air-threshold 7x --bone-threshold 166");
  CHECK(r.code == 2);
  CHECK(r.output == "palpsim-prep: --air-threshold '7x' is not a number in -1e6..1e6 (a threshold in the image's "
                    "units)\n");
  CHECK(prep(io + " --air-threshold 76 --bone-threshold inf").code == 2);
  CHECK_FALSE(fs::exists(d.path / "out"));

  // with both: prepared; the thresholds used and the units are recorded, and nothing says HU
  r = prep(io + " --air-threshold 76 --bone-threshold 166");
  INFO(r.output);
  REQUIRE(r.code == 0);
  std::ifstream j(d / "out/prep.json");
  const std::string json((std::istreambuf_iterator<char>(j)), {});
  CHECK_THAT(json, Catch::Contains("\"air_threshold\": 76, \"bone_threshold\": 166") &&
                       Catch::Contains("\"units\": \"image units\", \"low\": 166") &&
                       Catch::Contains("\"min\": 0, \"max\": 242, \"units\": \"image units\"") &&
                       !Catch::Contains("_hu\""));   // no key names HU for values in image units
  CHECK_THAT(r.output, Catch::Contains("bone threshold 166 image units") && !Catch::Contains(" HU"));
  // the preview's histogram marks both thresholds as vertical lines at least 40 pixels
  // high (its bars' least height): air (76, cyan) left of bone (166, yellow), where the
  // user sees how the chosen values fall between the image's peaks
  const std::uint8_t cyan[3] = {0, 220, 255}, yellow[3] = {255, 210, 0};
  const int air_x = first_column(histogram_runs(d / "out/preview.png", cyan), 40);
  const int bone_x = first_column(histogram_runs(d / "out/preview.png", yellow), 40);
  CHECK(air_x >= 0);
  CHECK(bone_x > air_x);
  // the scene is named with its file and its CT (the default scene's name is the phantom's)
  CHECK_THAT(r.output, Catch::Contains("(built-in, CT " + (d / "chest8.nrrd") + ")"));
}


TEST_CASE("palpsim-prep prints each landmark with a press that starts outside its skin point and reaches its bone") {
  TempDir d;
  // the phantom at 3 mm (its six spinous processes T12-L5 and both iliac crests stand out)
  std::ofstream(d / "phantom3.textproto") << "phantom {\n  voxel_mm: 3\n}\nprep {\n  spacing_mm: 3\n}\n";
  const Run r = prep("--scene '" + (d / "phantom3.textproto") + "' --no-cache --out '" + (d / "out") + "'");
  INFO(r.output);
  REQUIRE(r.code == 0);
  int marks = 0, crests = 0;
  std::istringstream lines(r.output);
  for (std::string line; std::getline(lines, line);) {
    double sx, sy, sz, depth, px, py, pz, travel;
    const std::size_t at = line.find(" skin (");
    if (at == std::string::npos || line.find("press:") == std::string::npos) continue;
    REQUIRE(std::sscanf(line.c_str() + at, " skin (%lf, %lf, %lf) mm, bone %lf mm under it", &sx, &sy, &sz, &depth) == 4);
    REQUIRE(std::sscanf(line.c_str() + line.find("press:"), "press:%lf,%lf,%lf,%lf", &px, &py, &pz, &travel) == 4);
    ++marks;
    crests += line.find("iliac crest") != std::string::npos;
    // printed to 0.1 mm: the start 10 mm above the skin point along +y, the travel to the
    // bone point (depth under the skin) and 5 mm past it
    CHECK(px == Approx(sx).margin(0.05));
    CHECK(pz == Approx(sz).margin(0.05));
    CHECK(py - sy == Approx(10).margin(0.1));
    CHECK(travel - depth == Approx(15).margin(0.1));
  }
  CHECK(marks >= 8);
  CHECK(crests == 2);
}
