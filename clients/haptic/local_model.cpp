#include "local_model.h"

#include <algorithm>
#include <cmath>

namespace palpsim::haptic {

bool ModeSelector::add_round_trip(double rtt_s, double t_s) {
  if (!(rtt_s >= 0) || !std::isfinite(rtt_s)) return false;
  // the median of the window (a fixed array: no allocation; about a microsecond)
  window_[count_ % kWindow] = rtt_s;
  ++count_;
  const int n = std::min(count_, kWindow);
  std::copy(window_, window_ + n, scratch_);
  std::nth_element(scratch_, scratch_ + n / 2, scratch_ + n);
  rtt_s_ = scratch_[n / 2];
  if (forced_ || t_s - switched_at_s_ < kMinDwellS) return false;
  // hysteresis: local above the upper threshold (with a patch to render from), remote below the lower
  RenderMode want = mode_;
  if (mode_ == RenderMode::kRemote && rtt_s_ > kLocalAboveS && patch_available_) want = RenderMode::kLocal;
  if (mode_ == RenderMode::kLocal && rtt_s_ < kRemoteBelowS) want = RenderMode::kRemote;
  if (want == mode_) return false;
  mode_ = want;
  switched_at_s_ = t_s;
  return true;
}

LocalRenderer::LocalRenderer(const HapticsSettings& params, int max_edge) : params_(params) {
  // every slot can hold the largest patch, so decoding one never allocates
  const std::size_t n = std::size_t(max_edge) * max_edge * max_edge;
  for (ForcePatch& p : slots_) {
    p.body.reserve(n);
    p.force_mm.reserve(n);
    p.grad_force.reserve(n);
  }
}

bool LocalRenderer::accept_incoming(double t_s) {
  const ForcePatch& in = slots_[incoming_];
  if (!in.valid() || (has_patch() && in.version <= current().version)) return false;
  // a patch of another scene's patient: the server reset its proxy state, so do we
  if (has_patch() && in.generation != current().generation) reset_proxy();
  // the current patch becomes the one blended from; its proxy state goes on in both
  const int old_previous = previous_;
  previous_ = current_;
  current_ = incoming_;
  incoming_ = old_previous;
  state_prev_ = state_cur_;
  blend_start_s_ = t_s;
  return true;
}

bool LocalRenderer::patch_force(const ForcePatch& p, const Vec3& tip_mm, double dt_s, ProxyState& st, Vec3& f) const {
  PatientSample s;
  if (!p.sample(tip_mm, s)) return false;
  f = proxy_step(s, p.params, tip_mm, dt_s, st).force_n;
  return true;
}

RenderStep LocalRenderer::step(double t_s, double dt_s, const Vec3& tip_mm, const Vec3& remote_force_n,
                               RenderMode mode, double watchdog_scale) {
  RenderStep r;
  const double dt = dt_s > 0 ? dt_s : kNominalHapticPeriodS;
  const HapticsSettings& params = has_patch() ? current().params : params_;

  // eq. 2 on the current patch and, while a blend runs, on the previous one; where a patch
  // does not cover the tip the remote force stands in for it
  Vec3 f_cur = remote_force_n, f_prev = remote_force_n;
  const bool covered = has_patch() && patch_force(current(), tip_mm, dt, state_cur_, f_cur);
  Vec3 local = f_cur;
  const double mu = std::clamp((t_s - blend_start_s_) / kBlendS, 0.0, 1.0);
  if (mu < 1 && slots_[previous_].valid()) {
    if (!patch_force(slots_[previous_], tip_mm, dt, state_prev_, f_prev)) f_prev = remote_force_n;
    local = f_prev * (1 - mu) + f_cur * mu;
  }
  r.local_force_n = local;
  r.patch_miss = mode == RenderMode::kLocal && !covered;

  // between remote and local: the weight moves towards the mode's at 1 / kBlendS per second
  const double target_weight = mode == RenderMode::kLocal ? 1.0 : 0.0;
  const double step_weight = dt / kBlendS;
  local_weight_ += std::clamp(target_weight - local_weight_, -step_weight, step_weight);
  r.local_weight = local_weight_;
  Vec3 f = local * local_weight_ + remote_force_n * (1 - local_weight_);
  const bool active = f != Vec3{0, 0, 0};

  // passivity observer: the energy (mJ) the device put in with the previous step's force
  const Vec3 dx = has_last_ ? tip_mm - last_tip_ : Vec3{0, 0, 0};
  energy_.move(dx);
  // passivity controller (haptics/passivity.h): the part of the force along the motion is
  // cut to what the energy allows over a displacement like the last one
  if (limit_to_energy(f, dx, energy_.energy_mj()) > 0) {
    r.passivity = true;
    ++passivity_steps_;
  }

  // the magnitude bound, the watchdog's scale, then the force-rate bound on what is rendered
  const double fn = norm(f);
  if (fn > params.max_force_n) f *= params.max_force_n / fn;
  f *= std::clamp(watchdog_scale, 0.0, 1.0);
  const Vec3 df = f - last_out_;
  const double dfn = norm(df), max_step = params.max_force_rate_n_per_s * dt;
  if (dfn > max_step) {
    f = last_out_ + df * (max_step / dfn);
    r.rate_limited = true;
  }

  energy_.set_force(f, active);
  last_out_ = f;
  last_tip_ = tip_mm;
  has_last_ = true;
  r.force_n = f;
  return r;
}

double watchdog_grace_s(RenderMode mode, double rtt_s) {
  return mode == RenderMode::kLocal ? 0.100 + 2 * std::max(rtt_s, 0.0) : 0.002;
}

double watchdog_scale(double age_s, RenderMode mode, double rtt_s) {
  const double grace = watchdog_grace_s(mode, rtt_s), ramp = mode == RenderMode::kLocal ? 0.100 : 0.008;
  if (!(age_s > grace)) return 1.0;
  return std::max(0.0, 1.0 - (age_s - grace) / ramp);
}

}  // namespace palpsim::haptic
