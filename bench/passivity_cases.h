// The patients and presses of the passivity checks (issue 29), shared by the stability
// catalogue (tests/stability/passivity_test.cpp), the server test's crop
// (tests/integration/passivity_server_test.cpp) and palpsim-bench passivity: every shipped
// scene (config/scenes), the phantom, the shared CTs (../shared/data) and a crop of the
// shared abdomen whose body is cut by the grid's faces. A case whose data is absent is left
// out with a printed "SKIPPED:" line. Needs prep (ITK) and the scene reader.
#pragma once

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "bench/press_energy.h"
#include "net/scene_io.h"
#include "prep/ct_io.h"
#include "prep/prepare.h"

namespace palpsim::bench {

/// One patient and the directions (physical, LPS) of the presses through its body's middle.
struct PassivityCase {
  std::string name;
  PatientPtr patient;
  HapticsSettings haptics;
  std::vector<Vec3> dirs;
};

/// The shared data file `rel` ($PALPSIM_DATA, else ../shared/data beside the project), or ""
/// after printing why it is skipped.
inline std::string passivity_data_file(const std::string& rel) {
  std::string dir = PALPSIM_SHARED_DATA;
  if (const char* env = std::getenv("PALPSIM_DATA"); env && *env) dir = env;
  const std::string path = dir + "/" + rel;
  if (std::filesystem::exists(path)) return path;
  std::printf("SKIPPED: %s not found (no ../shared/data beside the project and no PALPSIM_DATA)\n", rel.c_str());
  return "";
}

/// The shared abdomen CT (3 mm) cropped to its middle, 40 of 122 columns from column 41 and
/// 45 of 101 rows from row 28, every slice: the body is cut at four faces of the grid, with
/// no skin there, as a crop around an organ is.
inline Volume<float> crop_abdomen(const Volume<float>& full) {
  const int i0 = 41, j0 = 28;
  Grid g = full.grid;
  g.size = {40, 45, g.size.z};
  g.origin_mm = full.grid.to_physical(Vec3{double(i0), double(j0), 0});
  Volume<float> crop(g, 0.0f);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) crop.at(i, j, k) = full.at(i0 + i, j0 + j, k);
  return crop;
}

/// A scene for a CT file or DICOM folder, prep's defaults, no cache.
inline Scene passivity_ct_scene(const std::string& path) {
  Scene s;
  s.use_phantom = false;
  s.ct_path = path;
  s.prep.use_cache = false;
  return s;
}

/// Every shipped scene (config/scenes), pressed from the back (LPS +y is posterior, as
/// palpsim-haptic's press device does); a scene whose CT is absent is skipped.
inline std::vector<PassivityCase> shipped_scene_cases() {
  std::vector<std::filesystem::path> files;
  for (const auto& f : std::filesystem::directory_iterator(PALPSIM_SOURCE_DIR "/config/scenes"))
    if (f.path().extension() == ".textproto") files.push_back(f.path());
  std::sort(files.begin(), files.end());
  std::vector<PassivityCase> out;
  for (const auto& f : files) {
    Scene s = load_scene_file(f.string());
    if (!s.use_phantom && !std::filesystem::exists(s.ct_path)) {
      std::printf("SKIPPED: %s: its CT %s is absent\n", f.filename().c_str(), s.ct_path.c_str());
      continue;
    }
    s.prep.use_cache = false;
    out.push_back({"scene " + f.filename().string(), prepare_patient(s), s.haptics, {Vec3{0, -1, 0}}});
  }
  return out;
}

/// The built-in default scene's phantom, from the back and from the right.
inline std::vector<PassivityCase> phantom_cases() {
  const Scene s = default_scene();
  return {{"phantom (default scene)", prepare_patient(s), s.haptics, {Vec3{0, -1, 0}, Vec3{1, 0, 0}}}};
}

/// The shared CTs at 2 mm (the abdomen's 3 mm at prep's default): the abdomen and the DICOM series, from the back and
/// through the top slice (where the field of view cuts the body).
inline std::vector<PassivityCase> shared_ct_cases() {
  std::vector<PassivityCase> out;
  const std::vector<Vec3> dirs{Vec3{0, -1, 0}, Vec3{0, 0, -1}};
  if (const std::string ct = passivity_data_file("ct/abdomen-lumbar-3mm.nii.gz"); !ct.empty()) {
    const Scene s = passivity_ct_scene(ct);
    out.push_back({"abdomen CT at 2 mm", prepare_patient(s), s.haptics, dirs});
  }
  if (const std::string dicom = passivity_data_file("ct/dicom-partial-body"); !dicom.empty()) {
    Scene s = passivity_ct_scene(dicom);
    s.prep.spacing_mm = 2.0;  // not its 0.98 mm: the catalogue stays fast
    out.push_back({"DICOM series at 2 mm", prepare_patient(s), s.haptics, dirs});
  }
  return out;
}

/// The cropped abdomen (crop_abdomen), pressed through each of its four cut faces and the top.
inline std::vector<PassivityCase> cropped_ct_cases() {
  const std::string ct = passivity_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  if (ct.empty()) return {};
  const Scene s = passivity_ct_scene(ct);
  const Volume<float> crop = crop_abdomen(read_ct(ct, s.prep).image);
  return {{"abdomen CT cropped (cut faces)", build_patient(crop, s, "abdomen cropped to 40 x 45 columns"), s.haptics,
           {Vec3{1, 0, 0}, Vec3{-1, 0, 0}, Vec3{0, 1, 0}, Vec3{0, -1, 0}, Vec3{0, 0, -1}}}};
}

/// Prints one press's figures (one line).
inline void print_press(const std::string& name, const Vec3& dir, const PressPath& path, const PressEnergy& e) {
  std::printf("passivity %-36s dir (%+.0f %+.0f %+.0f) travel %5.1f mm: eq. 2 %+.4f mJ (lowest %+.4f), served %+.4f mJ "
              "(lowest %+.4f), limited %llu poses, removed %.4f mJ, peak %.2f N\n",
              name.c_str(), dir.x, dir.y, dir.z, path.travel_mm, e.model.energy_mj, e.model.min_running_mj,
              e.served.energy_mj, e.served.min_running_mj, (unsigned long long)e.served.limited, e.served.removed_mj,
              e.served.peak_force_n);
}

}  // namespace palpsim::bench
