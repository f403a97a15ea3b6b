// The elastic force model (haptics.force_model "elastic"): the deformation worker's elastic
// step reports the tissue's reaction on the fingertip, and the haptic thread renders it at
// every pose from a local linear model, f = f0 + K (x - x0), without waiting for a solve.
// Here: the model (built from a step's results), the per-pose renderer with its bound on
// the force jump at a model update, its energy bound (passivity), and its clamps. No
// allocation, no locks, no logging: the renderer runs once per pose at haptic rate.
#pragma once

#include <array>
#include <cstdint>

#include "core/grid.h"
#include "core/scene.h"
#include "core/vec3.h"

namespace palpsim {

/// One elastic step's force as a local linear model in physical space (LPS; mm, N):
/// f(x) = f0 + K (x - x0), with K = -k n n^T. Along n the force on the finger falls as the
/// tip goes in (k is the step's unit-press stiffness); across n K is zero: the finger slides
/// on the skin without friction, as the solve's contact does (only u.n of a contact node is
/// prescribed, so the tissue exerts no tangential force), and a symmetric K makes the model
/// a conservative field, so that no closed path within one model gains energy. The tissue
/// never pulls: the part of f along n is at most 0 (elastic_model_force).
struct ElasticModel {
  std::uint64_t session_id = 0;   // the session it belongs to (a reused slot's reader skips others' models)
  std::uint64_t generation = 0;   // the world (scene) it was solved in
  std::uint64_t pose_seq = 0;     // the pose whose contact the step solved
  double pose_server_time_s = 0;  // when that pose was answered (server clock, s)
  bool contact = false;           // the fingertip pressed the skin; false: no force (no contact, a release,
                                  // a reset, a failed step)
  Vec3 x0_mm{0, 0, 0};            // the tip the step solved for
  Vec3 f0_n{0, 0, 0};             // the tissue's force on the finger there (N)
  Vec3 normal{0, 0, 0};           // n: the press direction, unit, into the body
  double stiffness_n_per_mm = 0;  // k: d(force along -n) / d(tip depth along n) (N/mm)
  std::array<double, 9> k_n_per_mm{};  // K = -k n n^T, row-major (N/mm)
  double depth_mm = 0;            // the tip's depth along n below the skin point (mm)
  int contact_nodes = 0;          // skin nodes held on the fingertip sphere
};

/// Builds the model of one elastic step (DeformStats::elastic) whose force and normal are
/// given along the grid axes of `grid`: rotated into physical space (Grid::axes_to_physical).
/// A step that pressed nothing, or one with a non-finite value, gives a model without contact.
/// `tip_mm` is the tip the step solved for; ids and times are the caller's to set.
ElasticModel make_elastic_model(const Grid& grid, const Vec3& tip_mm, bool contact, const Vec3& force_axes_n,
                                const Vec3& normal_axes, double stiffness_n_per_mm, double depth_mm,
                                int contact_nodes);

/// The model's force on the finger at tip `x_mm` (N): f0 + K (x - x0), less any part along
/// n that would pull the finger into the body; zero for a model without contact.
Vec3 elastic_model_force(const ElasticModel& m, const Vec3& x_mm);

/// A session's elastic rendering between poses. Value-initialise it (`ElasticRenderState{}`)
/// for a fresh session or a reset, then set left_s to the time of the reset.
struct ElasticRenderState {
  ElasticModel model;          // the model rendered (contact false: none yet since the tip entered)
  Vec3 offset_n{0, 0, 0};      // what is left of the last updates' jumps, rendered on top of the model
                               // and stepped towards 0 by elastic_max_jump_n a pose (N)
  Vec3 force_n{0, 0, 0};       // the force sent for the previous pose (N)
  Vec3 tip_mm{0, 0, 0};        // the previous pose's tip (mm)
  Vec3 step_mm{0, 0, 0};       // the tip's recent step per pose, smoothed (mm): the next step's guess
  double stored_mj = 0;        // the work the hand did on the rendered tissue since the tip entered,
                               // less what the tissue gave back (N mm = mJ; the passivity bound's store)
  double left_s = -1;          // server time (s) the tip was last outside the body (or reset): models of
                               // poses answered before it belong to an earlier press and are not taken
  bool in_contact = false;     // the previous pose was inside the body
  bool has_previous = false;   // a previous pose exists (else dt is one haptic period)
};

/// What the renderer did at one pose.
struct ElasticRenderStep {
  Vec3 force_n{0, 0, 0};           // the force to send (N): exactly zero outside the body
  bool updated = false;            // a new model was taken at this pose
  double jump_n = 0;               // that update's jump: |f_new(x) - f_rendered_before(x)| (N)
  bool jump_bounded = false;       // the jump was over elastic_max_jump_n and is taken in steps
  bool clamped = false;            // the magnitude or rate clamp changed the force
  bool passivity_limited = false;  // the energy bound lowered the force
  bool reset = false;              // a non-finite value reset the state (corrupt model)
};

/// Renders the elastic force for device tip `tip_mm` at server time `now_s` and advances
/// `state`. `fresh`: a model published since the last pose, or nullptr; it is taken when it
/// belongs to the current press (a pose answered after state.left_s). `contact`: the tip is
/// inside the body (the haptic path's test, ForceSample::contact). `dt_s` as compute_force's.
///
/// Per pose, in order: outside the body exactly zero (the model is dropped: the next press
/// waits for its own); a new model's jump at x is taken at most params.elastic_max_jump_n a
/// pose; the model's force plus what is left of the jumps, never pulling; the magnitude and
/// rate clamps (max_force_n, max_force_rate_n_per_s); then the energy bound: over the guessed
/// next step g_n (state.step_mm, the recent steps' smoothed mean) the force may give back at
/// most the energy the hand stored in the tissue since the tip entered (each force acts until
/// the next pose, a zero-order hold: the hand feels f_{n-1} . (x_n - x_{n-1})). So over any
/// path from outside the body to outside again the hand gains at most
/// sum |f_n| |(x_{n+1} - x_n) - g_n|, the guesses' misses (small for smooth motion), whatever
/// models come and however they jump (tests/unit/haptics_elastic_force_test.cpp checks it).
/// The bound may lower the force faster than the rate clamp allows, towards zero only.
ElasticRenderStep render_elastic(ElasticRenderState& state, const ElasticModel* fresh, const HapticsSettings& params,
                                 const Vec3& tip_mm, bool contact, double dt_s, double now_s);

}  // namespace palpsim
