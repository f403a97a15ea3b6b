// palpsim-bench passivity: the energy a closed press exchanges with the force field on every
// case of the stability catalogue's passivity checks (bench/passivity_cases.h: the shipped
// scenes, the phantom, the shared CTs and a cropped CT through its cut faces), eq. 2 alone
// and as the server's pose path serves it with its passivity controller (haptics.passivity,
// bench/press_energy.h). Energies in mJ (N x mm), what the hand put into the field: a
// negative figure is energy the field gave the hand. Writes one JSON file with the date,
// the machine and the commit (bench/results/passivity-*.json).
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "bench/deform_runs.h"
#include "bench/passivity_cases.h"
#include "bench/registry.h"
#include "bench/stats.h"

namespace palpsim::bench {
namespace {

// one press as a JSON row
std::string press_row(const std::string& name, const Vec3& dir, const PressPath& path, const PressEnergy& e) {
  const auto run = [](const PressRun& r) {
    std::ostringstream j;
    j << "{\"energy_mj\": " << json_number(r.energy_mj) << ", \"min_running_mj\": " << json_number(r.min_running_mj)
      << ", \"limited_poses\": " << r.limited << ", \"removed_mj\": " << json_number(r.removed_mj)
      << ", \"peak_force_n\": " << json_number(r.peak_force_n) << ", \"contact_poses\": " << r.contact_poses << "}";
    return j.str();
  };
  std::ostringstream j;
  j << "    {\"case\": " << json_str(name) << ", \"dir\": " << json_vec3(dir) << ", \"from_mm\": "
    << json_vec3(path.from_mm) << ", \"travel_mm\": " << json_number(path.travel_mm)
    << ", \"eq2\": " << run(e.model) << ", \"served\": " << run(e.served) << "}";
  return j.str();
}

}  // namespace
}  // namespace palpsim::bench

PALPSIM_BENCH(passivity, "energy of a closed press, eq. 2 alone and served with the passivity controller "
                         "[--json FILE] [--commit C]") {
  using namespace palpsim;
  using namespace palpsim::bench;
  std::string json, commit = "unknown";
  for (int a = 1; a < argc; ++a) {
    const std::string s = argv[a];
    if (s == "--json" && a + 1 < argc) json = argv[++a];
    else if (s == "--commit" && a + 1 < argc) commit = argv[++a];
    else {
      std::fprintf(stderr, "usage: palpsim-bench passivity [--json FILE] [--commit C]\n");
      return 2;
    }
  }
  // the press: 20 mm past where the line enters the body, depth on a cosine over 2 s at 1 kHz
  constexpr double kDepthMm = 20;
  std::vector<std::string> rows;
  for (const auto& group : {shipped_scene_cases, phantom_cases, shared_ct_cases, cropped_ct_cases})
    for (const PassivityCase& c : group())
      for (const Vec3& dir : c.dirs) {
        const PressPath path = press_through_middle(*c.patient, dir, kDepthMm);
        if (!path.valid) continue;
        const PressEnergy e = press_energy(*c.patient, c.haptics, path);
        print_press(c.name, dir, path, e);
        rows.push_back(press_row(c.name, dir, path, e));
      }
  if (json.empty()) return 0;
  std::ofstream o(json);
  if (!o) {
    std::fprintf(stderr, "passivity: cannot write %s\n", json.c_str());
    return 1;
  }
  o << json_run_header("passivity", "cpu (the pose path's code)", commit, false) << "\n  \"units\": \"mJ (N x mm): energy the hand put into the "
    << "field, -sum f_n . (x_{n+1} - x_n); negative: the field gave the hand energy\",\n  \"press\": \"from 10 mm "
    << "outside the grid through the body box's middle, " << kDepthMm << " mm past the body's entry, and back; depth "
    << "on a cosine over 2 s at 1 kHz\",\n  \"rows\": [\n";
  for (std::size_t i = 0; i < rows.size(); ++i) o << rows[i] << (i + 1 < rows.size() ? ",\n" : "\n");
  o << "  ]\n}\n";
  std::printf("wrote %s\n", json.c_str());
  return 0;
}
