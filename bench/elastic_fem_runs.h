#pragma once
// The elastic study's FEM references (palpsim-bench accuracy --elastic): the press exported
// to bench/accuracy_fem.py and solved there (reference (i)), Hertz's block by the same FEM in
// axisymmetric form (reference (iii)), each reused from the work folder when its input is
// unchanged. Included by bench/elastic_accuracy_bench.cpp.
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "bench/deform_runs.h"
#include "bench/elastic_refs.h"
#include "core/error.h"
#include "core/patient.h"

namespace palpsim::bench {

// the FEM of Hertz's block (accuracy_fem.py hertz_case, axisymmetric): cells of kHertzFemH0 mm at the
// contact (converged: 0.05 mm moves the force by 1e-4), doubling out to kHertzFemExtent mm, where
// its faces are held; and cells of the voxels' 1 mm, where the fully integrated element shows locking
constexpr double kHertzFemH0 = 0.1, kHertzFemVoxelH0 = 1.0, kHertzFemExtent = 1000;

// whether two files hold the same bytes (false when either cannot be read)
inline bool same_bytes(const std::string& a, const std::string& b) {
  std::ifstream fa(a, std::ios::binary), fb(b, std::ios::binary);
  if (!fa || !fb) return false;
  std::stringstream sa, sb;
  sa << fa.rdbuf();
  sb << fb.rdbuf();
  return sa.str() == sb.str();
}

// whether a file exists
inline bool exists(const std::string& path) { return access(path.c_str(), F_OK) == 0; }

// writes the values as raw bytes (the FEM script's inputs)
template <typename T>
inline void write_raw(const std::string& path, const std::vector<T>& v) {
  std::ofstream f(path, std::ios::binary);
  f.write(reinterpret_cast<const char*>(v.data()), std::streamsize(v.size() * sizeof(T)));
  if (!f) throw Error("elastic accuracy: cannot write " + path);
}

// reference (i): the FEM of the elastic model's problem on `voi` (bench/accuracy_fem.py contact)
struct Fem {
  bool ok = false;
  std::vector<Vec3> u;  // mm on the VOI
  Vec3 force_n{0, 0, 0};
  std::string stats = "null";  // the script's statistics (JSON)
};

// exports the press on `voi` to work/name.*, solves it (unless the same input was solved
// there before) and reads the FEM's field
inline Fem solve_fem_contact(const std::string& python, const std::string& work, const std::string& name, const Patient& p,
                      const Voi& voi, const DeformConfig& cfg, const DeformContact& contact) {
  const deform::ElasticParams prm = cfg.elastic_params();
  const Grid& g = p.grid;
  const Vec3 h = g.spacing_mm;
  const Vec3 X = g.to_index(contact.skin_point_mm), x = g.to_index(contact.tip_mm);
  const Vec3 d_mm{(x.x - X.x) * h.x, (x.y - X.y) * h.y, (x.z - X.z) * h.z};
  const Vec3 n = d_mm * (1.0 / norm(d_mm));
  const Vec3 tip_local{(x.x - voi.lo.x) * h.x, (x.y - voi.lo.y) * h.y, (x.z - voi.lo.z) * h.z};
  const std::string base = work + "/" + name, in = base + ".in";
  {
    std::ostringstream j;
    j << "{\"size\": [" << voi.size.x << ", " << voi.size.y << ", " << voi.size.z << "], \"spacing_mm\": " << json_vec3(h)
      << ", \"nu\": " << json_number(prm.poisson) << ", \"material\": {\"table_hu\": [";
    for (int i = 0; i < prm.material.table.n; ++i) j << (i ? ", " : "") << json_number(prm.material.table.hu[i]);
    j << "], \"table_e_kpa\": [";
    for (int i = 0; i < prm.material.table.n; ++i) j << (i ? ", " : "") << json_number(prm.material.table.e_kpa[i]);
    j << "], \"skin_e_kpa\": " << json_number(prm.material.skin_e_kpa) << ", \"skin_mm\": "
      << json_number(prm.material.skin_mm) << ", \"air_e_kpa\": " << json_number(prm.material.air_e_kpa)
      << "}, \"tip_mm\": " << json_vec3(tip_local) << ", \"normal\": " << json_vec3(n)
      << ", \"radius_mm\": " << json_number(prm.finger_radius_mm) << ", \"element\": [";
    const auto k = deform::elastic_element(h, prm.poisson);
    for (std::size_t i = 0; i < k.size(); ++i) j << (i ? ", " : "") << json_number(k[i]);
    j << "]}\n";
    std::ofstream(in + ".json") << j.str();
  }
  // the VOI's intensity, B, bone, and body with one node more on every side (0 beyond the grid)
  const std::size_t count = std::size_t(voi.count());
  std::vector<float> hu(count), depth(count);
  std::vector<std::uint8_t> bone(count), body(std::size_t(voi.size.x + 2) * (voi.size.y + 2) * (voi.size.z + 2));
  for (int k = 0; k < voi.size.z; ++k)
    for (int jj = 0; jj < voi.size.y; ++jj)
      for (int i = 0; i < voi.size.x; ++i) {
        const std::size_t gi = g.index(voi.lo.x + i, voi.lo.y + jj, voi.lo.z + k), e = std::size_t(voi.index(i, jj, k));
        hu[e] = p.intensity.data[gi];
        depth[e] = p.dist_skin_mm.data[gi];
        bone[e] = p.bone.data[gi] ? 1 : 0;
      }
  for (int k = -1; k <= voi.size.z; ++k)
    for (int jj = -1; jj <= voi.size.y; ++jj)
      for (int i = -1; i <= voi.size.x; ++i) {
        const int a = voi.lo.x + i, b = voi.lo.y + jj, c = voi.lo.z + k;
        body[(std::size_t(k + 1) * (voi.size.y + 2) + std::size_t(jj + 1)) * (voi.size.x + 2) + std::size_t(i + 1)] =
            g.contains(a, b, c) && p.body.data[g.index(a, b, c)] ? 1 : 0;
      }
  write_raw(in + ".hu.f32", hu);
  write_raw(in + ".depth.f32", depth);
  write_raw(in + ".bone.u8", bone);
  write_raw(in + ".body.u8", body);
  const char* parts[] = {".json", ".hu.f32", ".depth.f32", ".bone.u8", ".body.u8"};
  bool same = exists(base + ".u_fem.f32") && exists(base + ".fem.json");
  for (const char* s : parts) same = same && same_bytes(in + s, base + s);
  if (same) {
    std::printf("  FEM %s: the same input was solved in %s; reusing it\n", name.c_str(), work.c_str());
  } else {
    for (const char* s : parts)
      if (std::rename((in + s).c_str(), (base + s).c_str()) != 0) throw Error("elastic accuracy: cannot write " + base + s);
    const std::string script = std::string(PALPSIM_SOURCE_DIR) + "/bench/accuracy_fem.py";
    if (!run_command(sh_quote(python) + " " + sh_quote(script) + " contact " + sh_quote(base)))
      throw Error("elastic accuracy: " + script + " contact " + base + " failed");
  }
  Fem f;
  std::ifstream uf(base + ".u_fem.f32", std::ios::binary);
  std::vector<float> raw(count * 3);
  uf.read(reinterpret_cast<char*>(raw.data()), std::streamsize(raw.size() * sizeof(float)));
  if (!uf) throw Error("elastic accuracy: cannot read " + base + ".u_fem.f32");
  f.u.resize(count);
  for (std::size_t e = 0; e < count; ++e) f.u[e] = {raw[3 * e], raw[3 * e + 1], raw[3 * e + 2]};
  std::stringstream ss;
  ss << std::ifstream(base + ".fem.json").rdbuf();
  f.stats = ss.str();
  // the force from the statistics: "force_n": [x, y, z]
  const auto at = f.stats.find("\"force_n\": [");
  if (at == std::string::npos) throw Error("elastic accuracy: " + base + ".fem.json has no force_n");
  std::istringstream fs(f.stats.substr(at + 12));
  char comma = 0;
  fs >> f.force_n.x >> comma >> f.force_n.y >> comma >> f.force_n.z;
  while (!f.stats.empty() && (f.stats.back() == '\n' || f.stats.back() == ' ')) f.stats.pop_back();
  f.ok = true;
  return f;
}

// Hertz's block by the FEM (accuracy_fem.py hertz: axisymmetric, graded from cells of h0 mm); its
// statistics (JSON), reused from the work folder when present
inline std::string solve_fem_hertz(const std::string& python, const std::string& work, double r, double d, double nu,
                            double e_kpa, double h0, bool full) {
  char name[240];
  std::snprintf(name, sizeof name, "%s/hertz-R%g-d%g-nu%g-E%g-h%g-L%g%s.json", work.c_str(), r, d, nu, e_kpa, h0,
                kHertzFemExtent, full ? "-full" : "");
  if (!exists(name)) {
    char args[240];
    std::snprintf(args, sizeof args, " --radius %.17g --depth %.17g --nu %.17g --e-kpa %.17g --h0 %.17g --extent %.17g%s", r,
                  d, nu, e_kpa, h0, kHertzFemExtent, full ? " --full" : "");
    const std::string script = std::string(PALPSIM_SOURCE_DIR) + "/bench/accuracy_fem.py";
    if (!run_command(sh_quote(python) + " " + sh_quote(script) + " hertz " + sh_quote(std::string(name) + ".tmp") + args))
      throw Error("elastic accuracy: " + script + " hertz failed");
    std::rename((std::string(name) + ".tmp").c_str(), name);
  } else {
    std::printf("  FEM %s: reusing it\n", name);
  }
  std::stringstream ss;
  ss << std::ifstream(name).rdbuf();
  std::string s = ss.str();
  while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
  return s;
}

}  // namespace palpsim::bench
