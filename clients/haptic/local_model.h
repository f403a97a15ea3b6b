// Local force rendering for far stations (proto/PROTOCOL.md, "Local force model"): the
// client runs eq. 2 at its own rate on the newest patch of F the server sent (the same
// force_field.h code as the server), blends to each new patch and between local and
// remote forces, bounds the force rate, keeps the rendered force passive, and picks local
// or remote mode by measured round trip. No protobuf here (main.cpp decodes the patches);
// nothing allocates after construction, so the 1 kHz loop may call everything.
#pragma once

#include <algorithm>
#include <cstdint>

#include "haptics/force_patch.h"
#include "haptics/passivity.h"

namespace palpsim::haptic {

/// Where the rendered force comes from.
enum class RenderMode { kRemote = 0, kLocal = 1 };

/// Picks local or remote mode from the round trip (the median of the last kWindow replies,
/// so that a burst of late replies after a stall of under kWindow / 2 ms on a loaded
/// machine does not count as a slow link), with hysteresis and a minimum dwell.
/// Local above kLocalAboveS: at 8 ms the remote force lags eight 1 kHz steps, which at a
/// palpation speed of 20 mm/s and 0.25 N/mm is 0.04 N behind (over 1% of the 3.3 N peak)
/// and grows with the lag, while a patch renders the same force as the server with no lag.
/// Remote below kRemoteBelowS: half the upper threshold, so that a link whose round trip
/// wanders around one threshold (jitter) does not flip; plus kMinDwellS in a mode.
class ModeSelector {
 public:
  static constexpr double kLocalAboveS = 0.008;   // smoothed round trip (s) above which local mode is chosen
  static constexpr double kRemoteBelowS = 0.004;  // smoothed round trip (s) below which remote mode is chosen
  static constexpr double kMinDwellS = 0.5;       // time (s) in a mode before the next switch
  static constexpr int kWindow = 128;             // round trips the median is taken over (0.128 s at 1 kHz)

  /// Adds a measured round trip (s) at loop time t_s; returns true when the mode changed.
  bool add_round_trip(double rtt_s, double t_s);
  /// The current mode (remote until round trips say otherwise; never local without a patch).
  RenderMode mode() const { return mode_; }
  /// True when patches should be asked for: local mode, or (not held in remote mode) a round
  /// trip above kRemoteBelowS or none measured yet, so that a patch is there when local mode
  /// starts: a far link's first reply then brings one and local mode starts at once, a round
  /// trip earlier than after asking on the first reply; a near link stops asking at its first
  /// reply (a patch or two at most).
  bool wants_patches() const {
    return mode_ == RenderMode::kLocal || (!forced_ && (count_ == 0 || rtt_s_ > kRemoteBelowS));
  }
  /// The median round trip (s) of the window; 0 before the first.
  double round_trip_s() const { return rtt_s_; }
  /// Forces a mode (--mode local|remote); auto selection stops.
  void force(RenderMode m) {
    mode_ = m;
    forced_ = true;
  }
  /// Local mode needs a patch: until one arrived, the selector stays remote (false: none yet).
  void set_patch_available(bool yes) { patch_available_ = yes; }

 private:
  RenderMode mode_ = RenderMode::kRemote;
  double rtt_s_ = 0;
  double window_[kWindow] = {};   // the last round trips (s), a ring
  double scratch_[kWindow] = {};  // the window's copy that the median is found in
  int count_ = 0;                 // round trips seen (the window is full from kWindow on)
  double switched_at_s_ = -1e9;
  bool forced_ = false;
  bool patch_available_ = false;
};

/// What one step of the renderer did (for logs and counters).
struct RenderStep {
  Vec3 force_n{0, 0, 0};     // the force to apply (N), after every bound
  Vec3 local_force_n{0, 0, 0};  // the patch's force (N) before blending (the remote one where no patch covers the tip)
  double local_weight = 0;   // 0: remote force, 1: local force, between: blending
  bool patch_miss = false;   // local mode, but no patch covers the tip: the remote force stood in
  bool passivity = false;    // the passivity controller took energy out of this step's force
  bool rate_limited = false; // the force-rate bound changed this step's force
};

/// The client's force renderer: patches in, one force per loop step out.
class LocalRenderer {
 public:
  /// The time (s) over which the force moves from one patch to the next and between remote
  /// and local forces: 20 ms, long enough that a difference of the whole 3.3 N default
  /// range changes at 165 N/s (far under the default rate bound of 2000 N/s) and short
  /// against a 50 ms patch period, so that a blend ends before the next patch arrives.
  static constexpr double kBlendS = 0.020;

  /// `params` are the session's haptics parameters (OpenReply); each patch brings its own.
  /// Reserves room for patches of up to `max_edge`^3 voxels.
  LocalRenderer(const HapticsSettings& params, int max_edge);

  /// The buffer the next patch is decoded into (its vectors have room for the largest patch).
  ForcePatch& incoming() { return slots_[incoming_]; }
  /// Takes the patch in incoming() (a newer version than the newest) at loop time t_s: a
  /// blend from the current patch starts. Returns false (and ignores it) for an older one.
  bool accept_incoming(double t_s);
  /// True when a patch has been accepted.
  bool has_patch() const { return slots_[current_].valid(); }
  /// The newest accepted patch.
  const ForcePatch& current() const { return slots_[current_]; }

  /// One loop step at time t_s (s), dt_s after the previous one, tip at `tip_mm`: eq. 2 on
  /// the patches (kept running in every mode, so the proxy state is current when local mode
  /// starts), blended with `remote_force_n` by `mode`, then passivity, the magnitude bound,
  /// the watchdog scale (0..1) and the force-rate bound.
  RenderStep step(double t_s, double dt_s, const Vec3& tip_mm, const Vec3& remote_force_n, RenderMode mode,
                  double watchdog_scale);

  /// The rendered force's energy, per contact episode (passivity observer, haptics/passivity.h).
  const EnergyMeter& energy() const { return energy_; }
  /// Steps in which the passivity controller acted.
  std::uint64_t passivity_steps() const { return passivity_steps_; }
  /// Resets the proxy states (the server's state was reset too).
  void reset_proxy() {
    state_cur_ = ProxyState{};
    state_prev_ = ProxyState{};
  }

 private:
  HapticsSettings params_;
  ForcePatch slots_[3];
  int current_ = 0, previous_ = 1, incoming_ = 2;
  ProxyState state_cur_{}, state_prev_{};
  double blend_start_s_ = -1e9;   // when the current patch was accepted
  double local_weight_ = 0;       // 0 remote .. 1 local
  Vec3 last_out_{0, 0, 0};        // the previous step's force (N)
  Vec3 last_tip_{0, 0, 0};        // the previous step's tip (mm)
  bool has_last_ = false;
  EnergyMeter energy_;
  std::uint64_t passivity_steps_ = 0;

  // the force of one patch at the tip (false: the patch does not cover it)
  bool patch_force(const ForcePatch& p, const Vec3& tip_mm, double dt_s, ProxyState& st, Vec3& f) const;
};

/// The watchdog's scale of the force (0..1) when the newest message from the server is
/// `age_s` old: 1 up to the grace, then linearly to 0 over the ramp. Remote mode: 2 ms
/// grace, 8 ms ramp (the force is the server's, and a 2 ms gap at 1 kHz already means
/// lost replies). Local mode: 100 ms plus two round trips (`rtt_s`, the median) of grace,
/// then 100 ms of ramp: the force comes from the patch, and replies only prove that the
/// link lives; one lost TCP segment stalls the stream for about a round trip until it is
/// sent again, which must not cut the force, while a link silent for longer is down.
double watchdog_scale(double age_s, RenderMode mode, double rtt_s);
/// The watchdog's grace (s) in a mode: the age above which it trips.
double watchdog_grace_s(RenderMode mode, double rtt_s);

}  // namespace palpsim::haptic
