// palpsim-bench accuracy --forces: the force each model reports for the same press (issue 25,
// section 2: "the report compares both, and the force the server reports for each"). Eq. 2
// ("proxy", the default) and the elastic model's reaction on the fingertip ("elastic"), both as a
// server serving the shipped scene (config/scenes/lumbar_phantom.textproto) puts them in its pose
// replies (bench/press_forces.h runs the server's own code), on
//   - the homogeneous block of the elastic study (soft tissue, no bone, no skin layer), pressed
//     straight down at its centre, beside Hertz's force for a sphere of the fingertip's radius;
//   - the phantom above L3's spinous tip, pressed towards the bone, where no closed form exists.
// The JSON it writes is what bench/accuracy_report.py turns into the report's force section.
#include <cmath>
#include <limits>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "bench/deform_accuracy.h"
#include "bench/deform_runs.h"
#include "bench/elastic_refs.h"
#include "bench/press_forces.h"
#include "core/error.h"
#include "deform/relax_elastic.h"
#include "net/scene_io.h"
#include "prep/phantom.h"
#include "prep/pipeline.h"
#include "prep/prepare.h"

namespace palpsim::bench {
namespace {

// the press starts this far outside the skin (mm), along the outward normal, and comes in at 1 kHz
constexpr double kApproachMm = 10;
constexpr int kApproachPoses = 100;

// depths (mm) under the skin: on the block in units of the fingertip's radius R (Hertz's range
// is d << R; 0.8 R is past it), on the phantom in mm (towards L3, whose spinous tip lies about
// 15 mm under the skin there)
const double kBlockDepthsR[] = {0.05, 0.1, 0.2, 0.4, 0.8};
const double kPhantomDepthsMm[] = {2, 4, 6, 8, 10};

// the block as prep would finish it: no bone (A = +inf), F and grad F from the scene's eq. 1
PatientPtr block_patient(const Scene& scene) {
  auto p = elastic_block(kBlockSize, 1.0, kBlockSkinJ, kBlockHu);
  p->dist_bone_mm = Volume<float>(p->grid, std::numeric_limits<float>::infinity());
  p->has_bone = false;
  p->force = force_image(*p, scene.force_image);
  p->grad_force = gradient_physical(p->force);
  return p;
}

// one press as a JSON row
std::string row_json(const std::string& where, double depth_mm, const PressForces& f, double hertz_n) {
  std::ostringstream j;
  j << "    {\"where\": " << json_str(where) << ", \"depth_mm\": " << json_number(depth_mm)
    << ", \"contact\": " << (f.contact ? "true" : "false") << ", \"haptic_depth_mm\": " << json_number(f.depth_mm)
    << ", \"proxy_n\": " << json_vec3(f.proxy_n) << ", \"elastic_n\": " << json_vec3(f.elastic_n)
    << ", \"elastic_f0_n\": " << json_vec3(f.model.f0_n) << ", \"stiffness_n_per_mm\": "
    << json_number(f.model.stiffness_n_per_mm) << ", \"contact_nodes\": " << f.model.contact_nodes
    << ", \"cg_steps\": " << f.run.iterations << ", \"converged\": " << (f.run.converged ? "true" : "false")
    << ", \"step_ms\": " << json_number(f.step_ms) << ", \"hertz_n\": " << json_number(hertz_n) << "}";
  return j.str();
}

}  // namespace

int run_force_models(const ForceModelsOptions& o) {
  check_writable(o.json, "accuracy --forces:");
  std::string device;
  deform_backends(device, "accuracy --forces", o.backend.empty() ? "cpu" : o.backend);
  const std::string backend = o.backend.empty() ? "cpu" : o.backend;

  // the shipped scene with the elastic step (its haptics as shipped: eq. 2's k and clamps)
  const std::string scene_file = "config/scenes/lumbar_phantom.textproto";
  Scene scene = load_scene_file(std::string(PALPSIM_SOURCE_DIR) + "/" + scene_file);
  scene.deform.relax_method = RelaxMethod::kElastic;
  const double R = scene.deform.grab_radius_mm, nu = scene.deform.elastic.poisson;
  std::vector<std::string> rows;

  // the block: homogeneous, as the elastic study's Hertz rows (no skin layer)
  {
    Scene bs = scene;
    bs.name = "force models: block";
    bs.deform.elastic.skin_thickness_mm = 0;
    const PatientPtr block = block_patient(bs);
    const double e_kpa = deform::elastic_table_e(DeformConfig::from_scene(bs, block.get()).elastic_params().material.table,
                                                 kBlockHu);
    const Vec3 X = block->grid.to_physical(Vec3(kBlockSize.x / 2, kBlockSkinJ, kBlockSize.z / 2));
    for (const double r : kBlockDepthsR) {
      const double d = r * R;
      // X is the skin node; the haptic path's skin (trilinear C = 1/2) lies half a voxel above it
      const Vec3 tip = X - Vec3{0, d, 0};
      const PressForces f = press_forces(block, bs, X + Vec3{0, kApproachMm, 0}, tip, kApproachPoses, backend);
      const double fh = hertz_force_n(e_kpa, nu, R, d);
      std::printf("block, %.2f mm (%.2f R): eq. 2 %.4f N, elastic %.4f N (f0 %.4f), Hertz %.4f N, %d CG steps, %.0f ms\n",
                  d, r, norm(f.proxy_n), norm(f.elastic_n), norm(f.model.f0_n), fh, f.run.iterations, f.step_ms);
      rows.push_back(row_json("block", d, f, fh));
    }
  }
  // the phantom above L3, pressed anterior (towards the bone)
  {
    const PatientPtr patient = prepare_patient(scene);
    const PhantomGeometry geo;
    const Vec3 X = skin_point_along(*patient, geo.landmark(kPressLandmark), Vec3{0, 1, 0});
    for (const double d : kPhantomDepthsMm) {
      const Vec3 tip = X - Vec3{0, d, 0};
      const PressForces f = press_forces(patient, scene, X + Vec3{0, kApproachMm, 0}, tip, kApproachPoses, backend);
      std::printf("phantom above L3, %.0f mm: eq. 2 %.4f N, elastic %.4f N (f0 %.4f), %d CG steps, %.0f ms\n", d,
                  norm(f.proxy_n), norm(f.elastic_n), norm(f.model.f0_n), f.run.iterations, f.step_ms);
      rows.push_back(row_json("phantom above L3", d, f, NAN));
    }
  }

  // the JSON: the run, the scene's force settings, the presses
  {
    std::ofstream f(o.json + ".tmp");
    const HapticsSettings& h = scene.haptics;
    f << json_run_header("accuracy-forces", device + ", backend " + backend, o.commit, false)
      << "\n  \"scene\": " << json_str(scene_file) << ",\n  \"finger_radius_mm\": " << json_number(R)
      << ",\n  \"poisson\": " << json_number(nu) << ",\n  \"block\": {\"size\": [" << kBlockSize.x << ", "
      << kBlockSize.y << ", " << kBlockSize.z << "], \"hu\": " << json_number(kBlockHu)
      << "},\n  \"haptics\": {\"stiffness_n_per_mm\": " << json_number(h.stiffness_n_per_mm)
      << ", \"max_force_n\": " << json_number(h.max_force_n) << ", \"elastic_max_jump_n\": "
      << json_number(h.elastic_max_jump_n) << "},\n  \"landmark\": " << json_str(kPressLandmark) << ",\n  \"rows\": [\n";
    for (std::size_t i = 0; i < rows.size(); ++i) f << rows[i] << (i + 1 < rows.size() ? ",\n" : "\n");
    f << "  ]\n}\n";
    if (!f) throw Error("accuracy --forces: writing " + o.json + " failed");
  }
  if (std::rename((o.json + ".tmp").c_str(), o.json.c_str()) != 0) throw Error("accuracy --forces: cannot write " + o.json);
  std::printf("wrote %s\n", o.json.c_str());
  return 0;
}

}  // namespace palpsim::bench
