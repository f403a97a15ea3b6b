// Shared state between the control thread and the haptic (pose) thread, all atomics:
// the session table, the current world (scene + patient), counters and the pose
// latency histogram. No locks: the pose thread never waits on the control thread.
#pragma once

#include <array>
#include <cinttypes>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <memory>
#include <string>

#include "core/patient.h"
#include "core/scene.h"
#include "core/latest.h"
#include "haptics/contact_slot.h"
#include "haptics/elastic_force.h"
#include "haptics/force_model.h"
#include "haptics/passivity.h"
#include "runtime/patch_channel.h"
#include "runtime/world.h"

namespace palpsim::runtime {

/// A session id as 16 hex digits, for logs and messages.
inline std::string hex_id(std::uint64_t id) {
  char b[32];
  std::snprintf(b, sizeof b, "%016" PRIx64, id);
  return b;
}

/// The largest number of sessions any scene may ask for (scene.proto's server.max_sessions max).
constexpr int kMaxSlots = 4096;
/// Low bits of a session id that hold its slot index.
constexpr int kSlotBits = 12;
static_assert(kMaxSlots == 1 << kSlotBits, "a slot index fills the id's low kSlotBits bits");

/// The slot of session `id`: the index of each of its parts in every per-slot array (session_state.h).
constexpr int slot_index(std::uint64_t id) { return int(id & (kMaxSlots - 1)); }

/// What the haptic thread's elastic renderer did for a session (haptics.force_model
/// "elastic"; ElasticForceStats in wire.proto): the pose thread adds, anyone reads, the
/// control thread clears when a session opens.
struct ElasticRenderCounters {
  std::atomic<std::uint64_t> models_taken{0};       // models the renderer started rendering
  std::atomic<std::uint64_t> jumps_bounded{0};      // updates whose jump was over elastic_max_jump_n
  std::atomic<std::uint64_t> passivity_limited{0};  // poses whose force the energy bound lowered
  std::atomic<double> largest_jump_n{0};            // the largest update jump (N)

  /// Adds one pose's step (pose thread only: one writer).
  void add(const ElasticRenderStep& e) {
    if (e.updated) models_taken.fetch_add(1, std::memory_order_relaxed);
    if (e.jump_bounded) jumps_bounded.fetch_add(1, std::memory_order_relaxed);
    if (e.passivity_limited) passivity_limited.fetch_add(1, std::memory_order_relaxed);
    if (e.jump_n > largest_jump_n.load(std::memory_order_relaxed))
      largest_jump_n.store(e.jump_n, std::memory_order_relaxed);
  }
  /// Zeroes them (control thread, before the session's id is published).
  void clear() {
    models_taken = 0;
    jumps_bounded = 0;
    passivity_limited = 0;
    largest_jump_n = 0;
  }
};

/// What the pose path's passivity observer saw and did for a session (haptics.passivity;
/// PassivityStats in wire.proto): energies in mJ (N mm), the energy the hand put into the
/// force field, so that a negative value is energy the field gave the hand. The pose thread
/// writes, anyone reads, the control thread clears when a session opens.
struct PassivityCounters {
  std::atomic<double> energy_mj{0};       // the current press's energy so far (0 between presses)
  std::atomic<double> last_press_mj{0};   // the last completed press's
  std::atomic<double> min_energy_mj{0};   // the lowest running energy any press reached
  std::atomic<double> dissipated_mj{0};   // energy the controller took out (over its guessed steps)
  std::atomic<std::uint64_t> limited_poses{0};  // poses whose force the controller lowered
  std::atomic<std::uint64_t> presses{0};        // completed presses (contact to release)

  /// Adds one pose (pose thread only: one writer).
  void add(const PassivityObserver& o, const PassivityStep& p) {
    const EnergyMeter& m = o.meter();
    energy_mj.store(m.energy_mj(), std::memory_order_relaxed);
    if (m.energy_mj() < min_energy_mj.load(std::memory_order_relaxed))
      min_energy_mj.store(m.energy_mj(), std::memory_order_relaxed);
    if (p.limited) {
      limited_poses.fetch_add(1, std::memory_order_relaxed);
      dissipated_mj.store(dissipated_mj.load(std::memory_order_relaxed) + p.removed_mj, std::memory_order_relaxed);
    }
    if (p.released) {
      last_press_mj.store(m.last_cycle_mj(), std::memory_order_relaxed);
      presses.fetch_add(1, std::memory_order_relaxed);
    }
  }
  /// Zeroes them (control thread, before the session's id is published).
  void clear() {
    energy_mj = 0;
    last_press_mj = 0;
    min_energy_mj = 0;
    dissipated_mj = 0;
    limited_poses = 0;
    presses = 0;
  }
};

/// One session's slot in the table the threads share (the first of a session's parts:
/// session_state.h lists them all). Fields marked (control) are written by the control
/// thread only, (pose) by the pose thread only; atomics may be read by either.
struct SessionSlot {
  std::atomic<std::uint64_t> id{0};             // (control) 0 = free; else the open session's id
  std::atomic<std::int64_t> last_seen_ns{0};    // (both) server clock of the last message naming it (Stats too)
  std::atomic<std::int64_t> last_used_ns{0};    // (both) and of the last pose or control request acting on it
                                                // (not Stats): the idle timeout's clock
  std::atomic<std::uint32_t> reset_requests{0}; // (control) grows by one per ResetSession
  std::atomic<std::uint32_t> pose_resets{0};    // (pose) grows by one per PoseRequest.reset_proxy, for the deformation worker
  // haptics parameters (control), read by the pose thread at every pose; HapticsSettings'
  // defaults (core/scene.h) until a session opens with the scene's
  std::atomic<double> stiffness_n_per_mm{HapticsSettings{}.stiffness_n_per_mm}, friction{HapticsSettings{}.friction},
      max_force_n{HapticsSettings{}.max_force_n}, max_force_rate_n_per_s{HapticsSettings{}.max_force_rate_n_per_s},
      min_gradient_norm{HapticsSettings{}.min_gradient_norm};
  // statistics (pose)
  std::atomic<std::uint64_t> poses{0}, errors{0}, last_seq{0}, clamps{0};
  std::atomic<bool> contact{false};
  std::atomic<double> depth_mm{0};
  std::atomic<std::uint64_t> local_models_sent{0}, local_poses{0};  // patches sent; poses rendered locally
  std::atomic<bool> renders_locally{false};                          // the last pose said so
  // the newest contact, for the deformation path (pose writes, anyone reads)
  ContactSlot latest;
  // the elastic force (haptics.force_model "elastic"): the deformation worker publishes each
  // step's local linear model (worker writes, pose reads: newest wins, neither waits), the
  // pose thread renders it (its state and counters)
  Latest<ElasticModel> elastic_model;
  ElasticRenderState elastic;          // (pose)
  ElasticRenderCounters elastic_counters;
  // the passivity observer and controller of the replies' force (haptics.passivity)
  PassivityObserver passivity;         // (pose)
  PassivityCounters passivity_counters;
  // (pose) the proxy state and what it belongs to
  std::uint64_t state_id = 0;          // the session id the state below belongs to
  std::uint32_t resets_seen = 0;       // reset_requests already applied
  std::uint64_t state_generation = 0;  // the world the proxy state was computed in
  ProxyState proxy{};
  double last_client_time_s = 0;       // of the previous pose
  double last_server_time_s = 0;       // of the previous pose
  // (pose) the session's local force model patches (PROTOCOL.md, "Local force model")
  std::uint64_t patch_version = 0;     // of the last patch asked for (0: none since the session opened)
  double patch_sent_s = 0;             // server clock when it was asked for (< 0: due now)
  Vec3 patch_tip_mm{0, 0, 0};          // the tip then (its velocity since leads the next box)
  double patch_client_time_s = 0;      // and the client's time of that pose (s)
  Vec3i patch_lo{0, 0, 0};             // its box on the patient grid
  Vec3i patch_size{0, 0, 0};
  // the slot's hand-over to the patch worker: the pose thread says that patches were asked
  // for, the worker makes the channel (kept for the slot's later sessions) and publishes it
  std::atomic<bool> patch_asked{false};
  std::unique_ptr<PatchChannel> patch_storage;     // (patch worker) owns the channel
  std::atomic<PatchChannel*> patch_channel{nullptr};
  // (control) name shown in stats
  std::string client_name;
  // who opened the session: (control) the identity its control requests must carry, and
  // with CURVE (control writes before publishing `id`, pose reads) the opener's z85 key
  // as 5 words, all 0 without CURVE: a pose is checked with five loads and compares
  std::string owner;
  std::array<std::atomic<std::uint64_t>, 5> owner_key{};

  /// Sets owner_key from a z85 key of 40 characters, or clears it for nullptr (control thread).
  void set_owner_key(const char* z85) {
    for (std::size_t i = 0; i < owner_key.size(); ++i) {
      std::uint64_t w = 0;
      if (z85) std::memcpy(&w, z85 + 8 * i, 8);
      owner_key[i].store(w, std::memory_order_relaxed);
    }
  }
  /// True when owner_key is unset (no CURVE) or equals the z85 key of 40 characters `z85`
  /// (nullptr: the sender has no key). No allocation: the pose thread calls it per pose.
  bool key_may_act(const char* z85) const {
    if (owner_key[0].load(std::memory_order_relaxed) == 0) return true;
    if (!z85) return false;
    for (std::size_t i = 0; i < owner_key.size(); ++i) {
      std::uint64_t w;
      std::memcpy(&w, z85 + 8 * i, 8);
      if (owner_key[i].load(std::memory_order_relaxed) != w) return false;
    }
    return true;
  }

  /// The parameters as HapticsSettings (pose thread, per pose).
  HapticsSettings params() const {
    HapticsSettings s;
    s.stiffness_n_per_mm = stiffness_n_per_mm.load(std::memory_order_relaxed);
    s.friction = friction.load(std::memory_order_relaxed);
    s.max_force_n = max_force_n.load(std::memory_order_relaxed);
    s.max_force_rate_n_per_s = max_force_rate_n_per_s.load(std::memory_order_relaxed);
    s.min_gradient_norm = min_gradient_norm.load(std::memory_order_relaxed);
    return s;
  }
  /// Sets all parameters (control thread).
  void set_params(const HapticsSettings& s) {
    stiffness_n_per_mm.store(s.stiffness_n_per_mm, std::memory_order_relaxed);
    friction.store(s.friction, std::memory_order_relaxed);
    max_force_n.store(s.max_force_n, std::memory_order_relaxed);
    max_force_rate_n_per_s.store(s.max_force_rate_n_per_s, std::memory_order_relaxed);
    min_gradient_norm.store(s.min_gradient_norm, std::memory_order_relaxed);
  }
};

/// Server-wide counters; every kind of bad input has one (ServerStats in wire.proto).
struct Counters {
  std::atomic<std::uint64_t> sessions_opened{0}, sessions_closed{0}, sessions_timed_out{0}, poses{0}, malformed{0},
      wrong_schema_version{0}, unknown_session{0}, bad_pose{0}, absurd_pose{0}, oversized{0}, too_many_sessions{0},
      bad_parameter{0}, scene_loads{0}, scene_load_failures{0}, control_requests{0}, empty_request{0},
      internal_errors{0}, bad_view{0}, not_built{0}, not_owner{0}, curve_refused{0}, curve_admitted{0},
      sessions_idle_timed_out{0}, session_quota{0}, load_running{0}, bad_input_unanswered{0};
};

/// A log-binned histogram of service times that one thread fills (relaxed atomics, no
/// allocation) and another reads: 8 bins per octave from 0.125 us to ~1 s.
class LatencyHistogram {
 public:
  static constexpr int kBins = 8 * 23;
  /// Adds one sample (us).
  void add(double us) {
    int b = 0;
    if (us > 0.125) b = std::min(kBins - 1, int(std::log2(us / 0.125) * 8));
    bins_[b].fetch_add(1, std::memory_order_relaxed);
    count_.fetch_add(1, std::memory_order_relaxed);
    sum_us_.store(sum_us_.load(std::memory_order_relaxed) + us, std::memory_order_relaxed);  // one writer
    if (us > max_us_.load(std::memory_order_relaxed)) max_us_.store(us, std::memory_order_relaxed);
  }
  /// The q-quantile (0..1) in us: the upper edge of the bin that holds it (9 % resolution).
  double quantile(double q) const {
    const std::uint64_t n = count_.load(std::memory_order_relaxed);
    if (n == 0) return 0;
    const double target = q * double(n);
    std::uint64_t acc = 0;
    for (int b = 0; b < kBins; ++b) {
      acc += bins_[b].load(std::memory_order_relaxed);
      if (double(acc) >= target) return 0.125 * std::exp2((b + 1) / 8.0);
    }
    return max_us();
  }
  std::uint64_t count() const { return count_.load(std::memory_order_relaxed); }
  double max_us() const { return max_us_.load(std::memory_order_relaxed); }
  /// The mean sample (us); 0 before the first.
  double mean_us() const {
    const std::uint64_t n = count();
    return n ? sum_us_.load(std::memory_order_relaxed) / double(n) : 0.0;
  }

 private:
  std::array<std::atomic<std::uint64_t>, kBins> bins_{};
  std::atomic<std::uint64_t> count_{0};
  std::atomic<double> max_us_{0};
  std::atomic<double> sum_us_{0};
};

struct StreamState;

/// Everything the two threads share.
struct ServerShared {
  std::array<SessionSlot, kMaxSlots> slots;
  std::atomic<const World*> world{nullptr};          // (control) the world being served
  std::atomic<std::uint64_t> seen_generation{0};     // (pose) the newest world generation it has picked up
  std::atomic<std::uint64_t> deform_seen_generation{~std::uint64_t(0)};  // (deformation worker) the same; max: no worker
  std::atomic<std::uint64_t> render_seen_generation{~std::uint64_t(0)};   // (render thread) the same; max: none
  std::atomic<std::uint64_t> publish_seen_generation{~std::uint64_t(0)};  // (stream publisher) the same; max: none
  std::atomic<std::uint64_t> patch_seen_generation{~std::uint64_t(0)};   // (patch worker) the same; max: none
  std::atomic<bool> patches_asked{false};            // (pose) some session's poses asked for patches
  Counters counters;
  LatencyHistogram pose_service;                     // (pose) receive-to-send times of answered poses
  std::atomic<bool> stop{false};
  double max_pose_distance_mm = 1000;                // poses farther than this from the grid are absurd
  bool curve = false;                                // every socket is a CURVE server (set before the threads start)
  std::atomic<StreamState*> stream{nullptr};         // (control) frames and bricks, once a scene asked for them
  std::atomic<int> slots_used{0};                    // (control) one past the highest slot index ever opened:
                                                     // the workers' passes over the sessions stop there
  std::atomic<bool> heap_trim_requested{false};      // (control) an old world was freed: the heap trimmer's
                                                     // next look trims (runtime/heap_trimmer.h)
};

}  // namespace palpsim::runtime
