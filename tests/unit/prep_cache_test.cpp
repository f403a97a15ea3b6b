// The prepared-patient cache: reuse while unchanged, a new entry when the CT or a
// setting changes, corrupt and half-written entries never used.
#include <catch2/catch.hpp>

#include <cmath>

#include <filesystem>
#include <fstream>

#include "prep/cache.h"
#include "prep/ct_io.h"
#include "prep/outputs.h"
#include "prep/prepare.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;
namespace fs = std::filesystem;

namespace {

void write_torso(const std::string& path) { write_volume_nrrd(path, synthetic_torso({70, 50, 16}, {1.5, 1.5, 2.5})); }

bool same_patient(const Patient& a, const Patient& b) {
  return a.grid.same_geometry(b.grid) && a.intensity.data == b.intensity.data && a.body.data == b.body.data &&
         a.bone.data == b.bone.data && a.dist_bone_mm.data == b.dist_bone_mm.data &&
         a.dist_skin_mm.data == b.dist_skin_mm.data && a.force.data == b.force.data && a.has_bone == b.has_bone &&
         a.grad_force.data.size() == b.grad_force.data.size();
}

int entries(const std::string& root) {
  int n = 0;
  for (const auto& e : fs::directory_iterator(root)) n += e.is_directory();
  return n;
}

}  // namespace

TEST_CASE("a prepared patient is reused while the CT and settings are unchanged") {
  TempDir d;
  write_torso(d / "torso.nrrd");
  Scene s = ct_scene(d / "torso.nrrd", d / "cache");
  PrepReport r1, r2;
  const PatientPtr a = prepare_patient(s, &r1);
  CHECK_FALSE(r1.from_cache);
  REQUIRE_FALSE(r1.cache_path.empty());
  CHECK(fs::exists(r1.cache_path + "/patient.bin"));
  const PatientPtr b = prepare_patient(s, &r2);
  CHECK(r2.from_cache);
  CHECK(r2.cache_key == r1.cache_key);
  CHECK(same_patient(*a, *b));
  CHECK_THAT(r2.json, Catch::Contains("\"hit\": true"));
  CHECK(entries(d / "cache") == 1);
  // the bone threshold prep chose (for the deformation's material function): the same
  // from the cache as made fresh
  CHECK(a->bone_threshold_hu == r1.bone_thresholds.low);
  CHECK(b->bone_threshold_hu == a->bone_threshold_hu);
  CHECK(std::isfinite(a->bone_threshold_hu));

  // another setting: another key
  s.prep.bone_threshold = 250;
  s.prep.bone_threshold_set = true;
  PrepReport r3;
  CHECK(prepare_patient(s, &r3)->bone_threshold_hu == 250);  // the scene's explicit one
  CHECK_FALSE(r3.from_cache);
  CHECK(r3.cache_key != r1.cache_key);
  s.prep.bone_threshold = 200;
  s.force_image.gamma = 0.03;
  PrepReport r4;
  prepare_patient(s, &r4);
  CHECK(r4.cache_key != r1.cache_key);
  s.force_image.gamma = ForceImageSettings{}.gamma;

  // other CT bytes under the same name: another key
  auto v = synthetic_torso({70, 50, 16}, {1.5, 1.5, 2.5});
  v.data[100] += 1;
  write_volume_nrrd(d / "torso.nrrd", v);
  PrepReport r5;
  prepare_patient(s, &r5);
  CHECK_FALSE(r5.from_cache);
  CHECK(r5.cache_key != r1.cache_key);
}

TEST_CASE("a corrupt or truncated cache entry is rebuilt, never used") {
  TempDir d;
  write_torso(d / "torso.nrrd");
  const Scene s = ct_scene(d / "torso.nrrd", d / "cache");
  PrepReport r1;
  const PatientPtr a = prepare_patient(s, &r1);
  const std::string bin = r1.cache_path + "/patient.bin";

  // one flipped byte in the voxels
  {
    std::fstream f(bin, std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(std::streamoff(fs::file_size(bin) / 2));
    f.put('\x5a');
  }
  PrepReport r2;
  const PatientPtr b = prepare_patient(s, &r2);
  CHECK_FALSE(r2.from_cache);
  CHECK(same_patient(*a, *b));

  // cut short (as if the writer died without the atomic rename)
  fs::resize_file(bin, fs::file_size(bin) - 100);
  PrepReport r3;
  prepare_patient(s, &r3);
  CHECK_FALSE(r3.from_cache);
  // rebuilt and valid again
  PrepReport r4;
  prepare_patient(s, &r4);
  CHECK(r4.from_cache);

  // an entry without its report
  fs::remove(r4.cache_path + "/prep.json");
  PrepReport r5;
  prepare_patient(s, &r5);
  CHECK_FALSE(r5.from_cache);
}

TEST_CASE("cache writes are atomic: a leftover temporary folder is ignored, entries appear whole") {
  TempDir d;
  write_torso(d / "torso.nrrd");
  const Scene s = ct_scene(d / "torso.nrrd", d / "cache");
  PrepReport r1;
  prepare_patient(s, &r1);
  const std::string key = r1.cache_key;
  // a half-written entry of a crashed writer, under its temporary name
  fs::remove_all(r1.cache_path);
  fs::create_directories(d.path / "cache" / (".tmp-" + key.substr(0, 16) + "-1-2"));
  std::ofstream(d / ("cache/.tmp-" + key.substr(0, 16) + "-1-2/patient.bin")) << "PALPPAT\n half";
  PrepReport r2;
  prepare_patient(s, &r2);
  CHECK_FALSE(r2.from_cache);
  CHECK(fs::exists(r2.cache_path + "/patient.bin"));
  CHECK(fs::exists(r2.cache_path + "/prep.json"));
  // storing again under an existing key keeps the first entry and leaves no temporary folder
  Patient p;
  std::string json;
  REQUIRE(load_cached_patient(r2.cache_path, p, json));
  store_cached_patient(d / "cache", key, p, json);
  int tmp = 0;
  for (const auto& e : fs::directory_iterator(d.path / "cache"))
    tmp += e.path().filename().string().rfind(".tmp-" + key.substr(0, 16) + "-", 0) == 0 &&
           e.path().filename().string() != ".tmp-" + key.substr(0, 16) + "-1-2";
  CHECK(tmp == 0);
  CHECK(load_cached_patient(r2.cache_path, p, json));
}

TEST_CASE("outputs are written whole into the output folder, replacing an older one") {
  TempDir d;
  {
    // an oblique CT (rotated about S) with an origin: the outputs keep both
    auto v = synthetic_torso({70, 50, 16}, {1.5, 1.5, 2.5});
    v.grid.direction = {0.8, -0.6, 0, 0.6, 0.8, 0, 0, 0, 1};
    v.grid.origin_mm = {12.5, -40, 100};
    write_volume_nrrd(d / "torso.nrrd", v);
  }
  const Scene s = ct_scene(d / "torso.nrrd", "");
  PrepReport r;
  const PatientPtr p = prepare_patient(s, &r);
  fs::create_directories(d.path / "out");
  std::ofstream(d / "out/stale.txt") << "old";
  write_patient_outputs(d / "out", *p, r.json);
  for (const char* f : {"F.nrrd", "body.nrrd", "bone.nrrd", "dist_bone.nrrd", "dist_skin.nrrd", "preview.png", "prep.json"})
    CHECK(fs::exists(d.path / "out" / f));
  CHECK_FALSE(fs::exists(d.path / "out/stale.txt"));
  // nothing else beside it (no temporary or old folder left)
  int siblings = 0;
  for (const auto& e : fs::directory_iterator(d.path)) siblings += e.is_directory();
  CHECK(siblings == 1);
  // the NRRD header carries the physical geometry Slicer needs
  std::ifstream h(d / "out/F.nrrd");
  std::string header((std::istreambuf_iterator<char>(h)), {});
  header = header.substr(0, header.find("\n\n"));
  CHECK_THAT(header, Catch::Contains("space: left-posterior-superior") && Catch::Contains("space directions: (1.2") &&
                         Catch::Contains("space origin:") && Catch::Contains("type: float"));
  // ITK reads the NRRD back with the patient's geometry (what 3D Slicer sees);
  // 1e-9 mm: the header prints 17 digits
  const CtImage back = read_ct(d / "out/dist_skin.nrrd", PrepSettings{});
  CHECK(back.image.grid.size == p->grid.size);
  for (int a = 0; a < 3; ++a) {
    CHECK(back.image.grid.spacing_mm[a] == Approx(p->grid.spacing_mm[a]).margin(1e-9));
    CHECK(back.image.grid.origin_mm[a] == Approx(p->grid.origin_mm[a]).margin(1e-9));
  }
  for (int e = 0; e < 9; ++e) CHECK(back.image.grid.direction[e] == Approx(p->grid.direction[e]).margin(1e-12));
  CHECK(back.image.data == p->dist_skin_mm.data);
  // an output path that is a file is refused and left alone
  std::ofstream(d / "afile") << "x";
  CHECK_FALSE(error_message([&] { write_patient_outputs(d / "afile", *p, r.json); }).empty());
}
