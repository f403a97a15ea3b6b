// Both force models for one press, as palpsim-server reports them: eq. 2 ("proxy", the
// default) and the elastic model's reaction on the fingertip (haptics.force_model
// "elastic"), for the accuracy report that compares them (bench/deform_accuracy_bench.cpp,
// bench/accuracy_*). The same code as the server's pose thread and deformation worker:
// compute_force along the approach, one elastic step on the held tip (DeformEngine, as the
// worker runs it), make_elastic_model and render_elastic until every jump is taken.
#pragma once

#include <string>

#include "core/error.h"
#include "core/setting_names.h"
#include "core/patient.h"
#include "core/scene.h"
#include "deform/backend.h"
#include "deform/engine.h"
#include "haptics/elastic_force.h"
#include "haptics/force_model.h"

namespace palpsim::bench {

/// What each force model gives for one press held at its tip.
struct PressForces {
  bool contact = false;             // the tip is inside the body (the haptic path's test)
  Vec3 skin_point_mm{0, 0, 0};      // X: the haptic path's skin point, where the elastic step presses from
  double depth_mm = 0;              // the tip's depth under the skin (the haptic path's, from B)
  Vec3 proxy_n{0, 0, 0};            // eq. 2: PoseReply.force_n with force_model "proxy" (the scene's haptics,
                                    // friction along the approach, clamps), once the held proxy has settled
  Vec3 elastic_n{0, 0, 0};          // PoseReply.force_n with force_model "elastic" once the worker has stepped
                                    // on the held tip and every jump is taken (the clamps apply)
  ElasticModel model;               // that step's local linear model: ElasticForceStats (force_n = f0, unclamped;
                                    // stiffness, normal, contact nodes), physical axes
  deform::ElasticRun run;           // the step itself (CG steps, residual, contact rounds, depth along n)
  double step_ms = 0;               // its wall time
};

/// Presses `patient` as a client of a server serving `scene` would: poses at 1 kHz along the
/// straight line from `from_mm` (outside the body) to `tip_mm` in `approach_poses` steps, then
/// held at `tip_mm`. Returns eq. 2's force there and the elastic model's, both as the pose
/// replies would carry them, and the elastic step's model as the stats would. The elastic
/// step runs once, on the held tip from rest (a server that stepped on the way in starts warm
/// and converges to the same within deform.elastic.tolerance), on `backend` ("cpu", "cuda"
/// or "auto"; "" keeps the scene's). The scene's deform.relax_method must be "elastic";
/// haptics.force_model may be either (the stiffness is solved here as "elastic" asks).
/// Throws palpsim::Error naming the field for a scene whose elastic step cannot run.
inline PressForces press_forces(const PatientPtr& patient, const Scene& scene, const Vec3& from_mm,
                                const Vec3& tip_mm, int approach_poses = 100, const std::string& backend = "cpu") {
  if (scene.deform.relax_method != RelaxMethod::kElastic)
    throw Error("press_forces: scene '" + scene.name + "': deform.relax_method = \"" +
                setting_name(scene.deform.relax_method) +
                "\"; the elastic force needs \"elastic\"");
  constexpr double kPeriodS = 1e-3;  // 1 kHz, on the client's clock
  // enough held poses for friction's proxy to settle (0.2 of the gap left a pose) and for any
  // jump to be taken (max_force_n / elastic_max_jump_n poses)
  const int hold_poses =
      200 + int(scene.haptics.max_force_n / std::max(scene.haptics.elastic_max_jump_n, 1e-3)) + 2;
  PressForces out;

  // eq. 2 along the approach and held, as the pose thread runs it
  HapticsSettings hs = scene.haptics;
  ProxyState proxy{};
  ForceSample held;
  const int n = std::max(1, approach_poses);
  for (int i = 0; i <= n; ++i) held = compute_force(*patient, hs, from_mm + (tip_mm - from_mm) * (double(i) / n), kPeriodS, proxy);
  for (int i = 0; i < hold_poses; ++i) held = compute_force(*patient, hs, tip_mm, kPeriodS, proxy);
  out.contact = held.contact;
  out.skin_point_mm = held.skin_point_mm;
  out.depth_mm = held.depth_mm;
  out.proxy_n = held.force_n;
  if (!held.contact) return out;

  // the elastic step on the held contact, as the deformation worker runs it
  DeformConfig cfg = DeformConfig::from_scene(scene, patient.get());
  cfg.relax = true;
  cfg.invert = false;  // J does not change the force
  cfg.elastic_stiffness = true;
  if (!backend.empty()) cfg.settings.backend = deform_backend_choice(backend);
  check_deform_config(cfg, "press_forces: scene '" + scene.name + "'");
  DeformEngine engine(patient, cfg);
  const DeformStats st = engine.step(DeformContact{held.skin_point_mm, tip_mm});
  out.run = st.elastic;
  out.step_ms = st.times.total_ms;
  out.model = make_elastic_model(patient->grid, tip_mm, st.elastic.contact && st.elastic.contact_nodes > 0,
                                 st.elastic.force_n, st.elastic.normal, st.elastic.stiffness_n_per_mm,
                                 st.elastic.depth_mm, st.elastic.contact_nodes);

  // the elastic renderer over the same poses: no model on the way in (the server's comes a
  // step later), then this one at the held tip until every jump is taken
  ElasticRenderState rs;
  double t = 0;
  for (int i = 0; i <= n; ++i) {
    const Vec3 x = from_mm + (tip_mm - from_mm) * (double(i) / n);
    ProxyState probe{};
    const bool in = compute_force(*patient, hs, x, kPeriodS, probe).contact;
    render_elastic(rs, nullptr, hs, x, in, kPeriodS, t += kPeriodS);
  }
  out.model.pose_server_time_s = t;
  ElasticRenderStep r = render_elastic(rs, &out.model, hs, tip_mm, true, kPeriodS, t += kPeriodS);
  for (int i = 0; i < hold_poses; ++i) r = render_elastic(rs, nullptr, hs, tip_mm, true, kPeriodS, t += kPeriodS);
  out.elastic_n = r.force_n;
  return out;
}

}  // namespace palpsim::bench
