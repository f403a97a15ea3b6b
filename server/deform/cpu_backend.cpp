// The "cpu" backend: buffers, reset and the timed step around the reference kernels.
#include "deform/cpu_backend.h"

#include <algorithm>
#include <chrono>

namespace palpsim {

namespace {
double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}
}  // namespace

void CpuDeformBackend::bind_impl() {
  const std::size_t n = std::size_t(max_voi_count());
  s_.u.assign(n, Vec3f{0, 0, 0});
  s_.moved_at.assign(n, -1);
  s_.visited_at.assign(n, -1);
  // relaxation's and inversion's buffers only when the scene asks for them (stage-by-stage
  // callers that run a stage the configuration leaves out get them on first use)
  std::vector<Vec3f>().swap(s_.u_next);
  std::vector<float>().swap(s_.weight);
  std::vector<float>().swap(s_.j);
  for (auto* v : {&s_.mg_g, &s_.mg_g_last, &s_.mg_r, &s_.mg_z, &s_.mg_p, &s_.mg_q, &s_.mg_res, &s_.mg_cx, &s_.mg_cf,
                  &s_.mg_cres}) std::vector<float>().swap(*v);
  s_.mg_cache = deform::MultigridCache{};
  std::vector<std::uint8_t>().swap(s_.mg_held);
  std::vector<std::uint8_t>().swap(s_.mg_held_coarse);
  std::vector<std::uint8_t>().swap(s_.cell_folded);
  std::vector<std::uint8_t>().swap(s_.untangle_flags);
  s_.elastic = deform::ElasticCpu{};
  // explicit relaxation's buffers (untangling keeps the relaxed field in u_next too)
  if (config_.relax && (config_.settings.relax_method == RelaxMethod::kExplicit || config_.settings.untangle)) grow_relax_buffers();
  if (config_.relax && config_.settings.untangle) grow_untangle_buffers();
  if (config_.invert) s_.j.assign(n, 0.0f);
  dirty_ = Voi{};
  s_.reach = 0;
}

void CpuDeformBackend::grow_relax_buffers() {
  const std::size_t n = std::size_t(max_voi_count());
  if (s_.u_next.size() < n) s_.u_next.assign(n, Vec3f{0, 0, 0});
  if (s_.weight.size() < n) s_.weight.assign(n, 0.0f);
}

void CpuDeformBackend::grow_untangle_buffers() {
  const std::size_t n = std::size_t(max_voi_count());
  if (s_.cell_folded.size() < n) s_.cell_folded.assign(n, 0);
  if (s_.untangle_flags.size() < n) s_.untangle_flags.assign(n, 0);
}

DeformMemory CpuDeformBackend::memory_impl() const {
  // capacities, not sizes: what the vectors hold on the heap
  auto bytes = [](const auto& v) { return v.capacity() * sizeof(v[0]); };
  DeformMemory m;
  m.chainmail_bytes = bytes(s_.u) + bytes(s_.moved_at) + bytes(s_.visited_at) + bytes(s_.movers) +
                      bytes(s_.candidates) + bytes(s_.changes);
  m.relax_bytes = bytes(s_.u_next) + bytes(s_.weight) + bytes(s_.mg_held) + bytes(s_.mg_g) + bytes(s_.mg_g_last) + bytes(s_.mg_r) +
                  bytes(s_.mg_z) + bytes(s_.mg_p) + bytes(s_.mg_q) + bytes(s_.mg_res) + bytes(s_.mg_cx) + bytes(s_.mg_cf) + bytes(s_.mg_cres) +
                  bytes(s_.mg_held_coarse) + bytes(s_.cell_folded) + bytes(s_.untangle_flags) +
                  deform::elastic_cpu_bytes(s_.elastic);
  m.invert_bytes = bytes(s_.j);
  return m;
}

void CpuDeformBackend::reset_impl() {
  // only the part of the buffers the last VOI used holds anything
  const std::size_t n = std::size_t(dirty_.count());
  std::fill_n(s_.u.begin(), n, Vec3f{0, 0, 0});
  std::fill_n(s_.moved_at.begin(), n, -1);
  std::fill_n(s_.visited_at.begin(), n, -1);
  dirty_ = Voi{};
  s_.reach = 0;
}

void CpuDeformBackend::forget_impl() {
  s_.elastic.have_u = false;
  s_.elastic.have_unit = false;
}

void CpuDeformBackend::chainmail_impl(ChainMailStats& st) {
  dirty_ = st.voi;
  if (st.skipped) {
    deform::chainmail_grab_cpu(st, s_);
    s_.reach = 0;
    return;
  }
  deform::chainmail_cpu(*patient_, limits_, config_.settings.max_sweeps, st, s_);
  s_.reach = st.grabbed_in_bone ? 0 : st.sweeps;  // its wave moved one neighbour a sweep
}

void CpuDeformBackend::relax_impl() {
  const DeformSettings& d = config_.settings;
  if (d.relax_method == RelaxMethod::kElastic) {
    // its buffers grow on first use; it writes every element of the VOI
    elastic_run_ = deform::relax_elastic_cpu(*patient_, setup_.voi, setup_.skin_vox, setup_.tip_vox,
                                             config_.elastic_params(), s_.elastic, s_.u.data());
    s_.reach = -1;
    return;
  }
  if (d.relax_method == RelaxMethod::kMultigrid) {
    // its buffers grow on first use
    relax_run_ = deform::relax_multigrid_cpu(*patient_, setup_, d.relax_cycles, d.relax_warm_cycles,
                                             float(config_.bone_threshold), float(d.material_width),
                                             finger_r2_, config_.relax_reuse, s_);
    s_.reach = -1;  // the steady state is nonzero wherever the grabbed element is felt
    return;
  }
  grow_relax_buffers();
  deform::relax_cpu(*patient_, setup_, d.relax_iterations, float(d.relax_step), float(config_.bone_threshold),
                    float(d.material_width), s_);
}

UntangleStats CpuDeformBackend::untangle_impl() {
  grow_relax_buffers();  // u_next keeps the relaxed field
  grow_untangle_buffers();
  s_.reach = -1;
  return deform::untangle_cpu(*patient_, setup_, s_);
}

InvertStats CpuDeformBackend::invert_impl() {
  if (s_.j.size() < std::size_t(max_voi_count())) s_.j.assign(std::size_t(max_voi_count()), 0.0f);
  return deform::invert_cpu(*patient_, voi_, config_.settings.invert_iterations, config_.settings.invert_search, s_);
}

DeformPrime CpuDeformBackend::prime_impl(const ChainMailStats& expected) {
  const DeformSettings& d = config_.settings;
  if (d.relax_method != RelaxMethod::kMultigrid) return DeformPrime{};
  const deform::MultigridRun r =
      deform::prime_multigrid_cpu(*patient_, expected.voi, expected.grabbed_vox, d.relax_cycles, d.relax_warm_cycles,
                                  float(config_.bone_threshold), float(d.material_width), finger_r2_, s_);
  DeformPrime out;
  out.solved = r.solves > 0;
  out.warm = r.warm;
  out.steps = r.solves == 0 ? 0 : (r.warm ? r.warm_steps : d.relax_cycles);
  return out;
}

std::vector<Vec3f> CpuDeformBackend::displacement_impl() const {
  return std::vector<Vec3f>(s_.u.begin(), s_.u.begin() + voi_.count());
}

void CpuDeformBackend::set_displacement_impl(const std::vector<Vec3f>& u) {
  s_.reach = -1;  // any field
  std::copy(u.begin(), u.end(), s_.u.begin());
}

DeformStats CpuDeformBackend::step_impl(const ChainMailStats& setup) {
  using clock = std::chrono::steady_clock;
  DeformStats out;
  const auto t_start = clock::now();
  // reset: the previous step's displacement back to zero
  auto t0 = clock::now();
  reset_impl();
  out.times.reset_ms = ms_since(t0);
  // chainmail
  t0 = clock::now();
  out.chainmail = setup;
  chainmail_impl(out.chainmail);
  out.times.chainmail_ms = ms_since(t0);
  // relaxation, when the scene asks for it
  if (config_.relax) {
    t0 = clock::now();
    relax_impl();
    set_relax_counts(out);
    if (config_.settings.relax_method == RelaxMethod::kMultigrid) set_multigrid_counts(out, relax_run_.solves, relax_run_.warm, relax_run_.warm_steps);
    if (config_.settings.relax_method == RelaxMethod::kElastic) out.elastic = elastic_run_;
    out.times.relax_ms = ms_since(t0);
    // untangling, with relaxation when the configuration asks for it
    if (config_.settings.untangle) {
      t0 = clock::now();
      out.untangle = untangle_impl();
      out.times.untangle_ms = ms_since(t0);
    }
  }
  // inversion and upload, when the scene asks for J
  if (config_.invert) {
    t0 = clock::now();
    const InvertStats inv = invert_impl();
    out.take_inversion(inv);
    out.times.invert_ms = ms_since(t0);
    t0 = clock::now();
    upload_impl();
    out.times.upload_ms = ms_since(t0);
  }
  out.times.total_ms = ms_since(t_start);
  return out;
}

}  // namespace palpsim
