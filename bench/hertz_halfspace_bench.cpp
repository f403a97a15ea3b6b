// palpsim-bench accuracy --halfspace: Hertz's rows (iii) and (iv) on a block that stands for a
// piece of the half-space Hertz's formulas describe. accuracy --elastic presses blocks whose
// faces are held at rest, which a half-space's are not: 32 to 48 mm from the finger the surface
// of a half-space still sinks by (1 - nu^2) F / (pi E r), 3 to 5 % of the press's depth at R / 5,
// so held faces make the block stiffer and its surface flatter than Hertz's, and the error they
// add shrinks only slowly as the block grows (the 128^3 rows). Here the faces are held where the
// half-space puts them: Boussinesq's displacement under a point load equal to the finger's
// force (boussinesq_mm; beyond a few contact radii the contact's field is the point load's),
// the force taken from the solve before, starting with the faces at rest, until it moves by
// less than kForceSettled. What is left against Hertz is the model's own error (the voxels,
// the element, the contact in whole nodes), the same quantity the FEM at the voxels' 1 mm
// (accuracy --elastic's "FEM 1 mm" column, on a 1000 mm domain) measures for the same element.
// The JSON it writes is what bench/accuracy_report.py turns into the report's half-space table.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "bench/deform_accuracy.h"
#include "bench/deform_runs.h"
#include "bench/elastic_refs.h"
#include "bench/stats.h"
#include "core/error.h"
#include "deform/relax_elastic.h"
#include "net/scene_io.h"

namespace palpsim::bench {
namespace {

// the faces' point load is settled when the force moves by less than this fraction
constexpr double kForceSettled = 1e-4;
constexpr int kMaxFaceUpdates = 8;

// the blocks (n^3 voxels of 1 mm): 64^3 is the shipped VOI's size, 96^3 accuracy --elastic's
const int kBlocks[] = {64, 96};

// one row: a block, a Poisson ratio and a depth, with the faces at rest and where the half-space puts them
struct Row {
  int n = 0;
  double nu = 0, d = 0, e_kpa = 0, hertz_n = 0;
  double held_n = 0, held_profile = NAN;   // faces at rest (the first solve)
  double half_n = 0, half_profile = NAN;   // faces on the half-space
  int updates = 0;                         // solves with the faces moved
  int iterations = 0, contact_nodes = 0;   // CG steps over all solves; the last contact set
  bool settled = false;
  double seconds = 0;
};

// the block's body nodes on its faces (the VOI's boundary) moved to Boussinesq's displacement
// of a point load of p_n N pressed along -y at the skin node (ci, skin_j, ck); the air's gel
// above the skin stays at rest, as with held faces (its pull is 1e-4 of the tissue's)
void hold_faces_on_halfspace(const Voi& voi, int skin_j, double p_n, double e_kpa, double nu, Vec3f* u) {
  const int ci = voi.size.x / 2, ck = voi.size.z / 2;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j <= skin_j; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        if (!(i == 0 || j == 0 || k == 0 || i + 1 == voi.size.x || k + 1 == voi.size.z)) continue;
        const double dx = i - ci, dz = k - ck, r = std::hypot(dx, dz), depth = skin_j - j;
        const auto [ur, uz] = boussinesq_mm(p_n, e_kpa, nu, r, depth);
        const double cx = r > 0 ? dx / r : 0.0, cz = r > 0 ? dz / r : 0.0;
        u[voi.index(i, j, k)] = Vec3f{float(ur * cx), float(-uz), float(ur * cz)};
      }
}

Row run_row(int n, double nu, double d, const DeformConfig& base) {
  Row row;
  row.n = n;
  row.nu = nu;
  row.d = d;
  const int skin_j = n - kHertzAir;
  const PatientPtr b = elastic_block({n, n, n}, 1.0, skin_j, kBlockHu);
  DeformConfig c = base;
  c.settings.grab_radius_mm = kHertzR;
  c.settings.elastic.poisson = nu;
  c.settings.elastic.tolerance = 1e-6;
  c.settings.elastic.max_iterations = 400;
  c.settings.elastic.contact_rounds = 40;
  const deform::ElasticParams prm = c.elastic_params();
  row.e_kpa = deform::elastic_table_e(prm.material.table, kBlockHu);
  row.hertz_n = hertz_force_n(row.e_kpa, nu, kHertzR, d);
  const Voi voi{{0, 0, 0}, b->grid.size};
  const DeformContact press = block_press(*b, skin_j, d);
  const Vec3 skin = b->grid.to_index(press.skin_point_mm), tip = b->grid.to_index(press.tip_mm);
  deform::ElasticCpu s;
  std::vector<Vec3f> u_vox(std::size_t(voi.count()));
  auto profile = [&]() {
    std::vector<Vec3> u_mm(u_vox.size());
    for (std::size_t e = 0; e < u_vox.size(); ++e) u_mm[e] = Vec3(u_vox[e]);  // 1 mm voxels
    return profile_error(*b, skin_j, voi, u_mm, kHertzR, d);
  };
  const auto t0 = std::chrono::steady_clock::now();
  // the faces at rest, then on the half-space of the last force: each solve starts from the
  // last (the solver keeps held nodes' values and the contact set)
  double f = 0;
  for (int it = 0; it <= kMaxFaceUpdates; ++it) {
    if (it > 0) hold_faces_on_halfspace(voi, skin_j, f, row.e_kpa, nu, s.u.data());
    const deform::ElasticRun run = deform::relax_elastic_cpu(*b, voi, skin, tip, prm, s, u_vox.data());
    if (!run.contact) throw Error("accuracy --halfspace: the block press touched nothing");
    row.iterations += run.iterations;
    row.contact_nodes = run.contact_nodes;
    const double fn = norm(run.force_n);
    if (it == 0) {
      row.held_n = fn;
      row.held_profile = profile();
    } else {
      row.updates = it;
      row.settled = std::fabs(fn - f) <= kForceSettled * f;
    }
    f = fn;
    if (row.settled) break;
  }
  row.half_n = f;
  row.half_profile = profile();
  row.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("halfspace %d^3 nu %g d %g mm: Hertz %.5g N; faces at rest %.4f (profile %.3g %%), on the half-space "
              "%.4f (profile %.3g %%) after %d updates%s; %d CG steps, %.1f s\n",
              n, nu, d, row.hertz_n, row.held_n / row.hertz_n, row.held_profile, row.half_n / row.hertz_n,
              row.half_profile, row.updates, row.settled ? "" : " (not settled)", row.iterations, row.seconds);
  std::fflush(stdout);
  return row;
}

}  // namespace

int run_hertz_halfspace(const HalfspaceOptions& o) {
  check_writable(o.json, "accuracy --halfspace:");
  // the shipped scene's elastic model (its table gives the block's modulus), no skin layer
  const std::string scene_file = "config/scenes/lumbar_phantom.textproto";
  const Scene scene = load_scene_file(std::string(PALPSIM_SOURCE_DIR) + "/" + scene_file);
  DeformConfig base = DeformConfig::from_scene(scene, nullptr);
  base.settings.relax_method = RelaxMethod::kElastic;
  base.settings.elastic.skin_thickness_mm = 0;
  base.settings.whole_volume = true;
  std::vector<Row> rows;
  for (const int n : kBlocks)
    for (const double nu : kHertzNus)
      for (const double d : kHertzDepths) {
        if (o.quick && (n != kBlocks[0] || d != kHertzDepths[2])) continue;
        rows.push_back(run_row(n, nu, d, base));
      }
  std::ofstream f(o.json + ".tmp");
  f << json_run_header("accuracy-halfspace", "cpu", o.commit, o.quick) << "\n  \"scene\": "
    << json_str(scene_file) << ",\n  \"radius_mm\": " << json_number(kHertzR) << ",\n  \"hu\": " << json_number(kBlockHu)
    << ",\n  \"force_settled\": " << json_number(kForceSettled) << ",\n  \"profile_within_radii\": "
    << json_number(kProfileRadii) << ",\n  \"rows\": [\n";
  for (std::size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    f << "    {\"block_n\": " << r.n << ", \"nu\": " << json_number(r.nu) << ", \"depth_mm\": " << json_number(r.d)
      << ", \"e_kpa\": " << json_number(r.e_kpa) << ", \"hertz_n\": " << json_number(r.hertz_n)
      << ", \"held_n\": " << json_number(r.held_n) << ", \"held_ratio\": " << json_number(r.held_n / r.hertz_n)
      << ", \"held_profile_pct\": " << json_number(r.held_profile) << ", \"halfspace_n\": " << json_number(r.half_n)
      << ", \"halfspace_ratio\": " << json_number(r.half_n / r.hertz_n) << ", \"halfspace_profile_pct\": "
      << json_number(r.half_profile) << ", \"face_updates\": " << r.updates << ", \"settled\": "
      << (r.settled ? "true" : "false") << ", \"iterations\": " << r.iterations << ", \"contact_nodes\": "
      << r.contact_nodes << ", \"seconds\": " << json_number(r.seconds) << "}" << (i + 1 < rows.size() ? "," : "")
      << "\n";
  }
  f << "  ]\n}\n";
  if (!f) throw Error("accuracy --halfspace: writing " + o.json + " failed");
  f.close();
  if (std::rename((o.json + ".tmp").c_str(), o.json.c_str()) != 0) throw Error("accuracy --halfspace: cannot write " + o.json);
  std::printf("wrote %s\n", o.json.c_str());
  return 0;
}

}  // namespace palpsim::bench
