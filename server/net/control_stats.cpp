// StatsRequest: the server's counters, pose latency and stages, and one session's.
#include "net/control.h"

#include <algorithm>

#include "net/pose_service.h"
#include "net/wire_convert.h"

namespace palpsim::net {

using runtime::default_view;
using runtime::ElasticForceReport;
using runtime::ElasticRenderCounters;
using runtime::PassivityCounters;
using runtime::SessionStreamReport;
using runtime::StreamInfo;
using runtime::StreamSlot;

namespace {

void fill_times(v1::DeformTimes* out, const DeformTimes& t, double scale) {
  out->set_chainmail_ms(t.chainmail_ms * scale);
  out->set_relax_ms(t.relax_ms * scale);
  out->set_untangle_ms(t.untangle_ms * scale);
  out->set_invert_ms(t.invert_ms * scale);
  out->set_upload_ms(t.upload_ms * scale);
  out->set_reset_ms(t.reset_ms * scale);
  out->set_total_ms(t.total_ms * scale);
}

// the latest elastic step's model (the worker's report) and the haptic thread's rendering of such models
void fill_elastic(v1::ElasticForceStats* out, const ElasticForceReport& r, const ElasticRenderCounters& c) {
  const ElasticModel& m = r.model;
  out->set_contact(m.contact);
  set_vec(out->mutable_force_n(), m.f0_n);
  set_vec(out->mutable_contact_point_mm(), m.x0_mm);
  set_vec(out->mutable_normal(), m.normal);
  out->set_stiffness_n_per_mm(m.stiffness_n_per_mm);
  out->set_depth_mm(m.depth_mm);
  out->set_contact_nodes(std::uint32_t(m.contact_nodes));
  out->set_model_pose_seq(m.pose_seq);
  out->set_model_pose_server_time_s(m.pose_server_time_s);
  out->set_iterations(std::uint32_t(r.iterations));
  out->set_stiffness_iterations(std::uint32_t(r.stiffness_iterations));
  out->set_converged(r.converged);
  out->set_models_published(r.models_published);
  out->set_models_taken(c.models_taken.load(std::memory_order_relaxed));
  out->set_largest_jump_n(c.largest_jump_n.load(std::memory_order_relaxed));
  out->set_jumps_bounded(c.jumps_bounded.load(std::memory_order_relaxed));
  out->set_passivity_limited(c.passivity_limited.load(std::memory_order_relaxed));
}

// the pose path's passivity observer and controller for one session
void fill_passivity(v1::PassivityStats* out, const PassivityCounters& c, bool limiting) {
  out->set_limiting(limiting);
  out->set_energy_mj(c.energy_mj.load(std::memory_order_relaxed));
  out->set_last_press_mj(c.last_press_mj.load(std::memory_order_relaxed));
  out->set_min_energy_mj(c.min_energy_mj.load(std::memory_order_relaxed));
  out->set_dissipated_mj(c.dissipated_mj.load(std::memory_order_relaxed));
  out->set_limited_poses(c.limited_poses.load(std::memory_order_relaxed));
  out->set_presses(c.presses.load(std::memory_order_relaxed));
}

void add_stage(google::protobuf::RepeatedPtrField<v1::StageInfo>* out, const char* name, bool built,
               std::uint64_t bytes, double mean_ms, std::uint64_t runs) {
  auto* st = out->Add();
  st->set_name(name);
  st->set_built(built);
  // what is really held and run, built or not: a stage not built must show 0 by itself
  st->set_bytes_allocated(bytes);
  st->set_mean_ms(mean_ms);
  st->set_runs(runs);
}

// the deformation stages of a report
template <class Report>
void add_deform_stages(google::protobuf::RepeatedPtrField<v1::StageInfo>* out, const Report* r, bool built,
                       bool relax, bool invert) {
  const std::uint64_t n = r ? r->steps : 0;
  const double k = n ? 1.0 / double(n) : 0.0;
  add_stage(out, "chainmail", built, r ? r->memory.chainmail_bytes : 0, r ? r->sum.chainmail_ms * k : 0, n);
  add_stage(out, "relaxation", built && relax, r ? r->memory.relax_bytes : 0, r ? r->sum.relax_ms * k : 0,
            built && relax ? n : 0);
  add_stage(out, "inversion", built && invert, r ? r->memory.invert_bytes : 0, r ? r->sum.invert_ms * k : 0,
            built && invert ? n : 0);
}

}  // namespace

void Server::Control::stats() {
  auto* st = rep_.mutable_stats();
  const auto& c = sh_.counters;
  auto* s = st->mutable_server();
  s->set_uptime_s(ns_since(start_) * 1e-9);
  s->set_sessions_open(open_count());
  s->set_sessions_opened(c.sessions_opened);
  s->set_sessions_closed(c.sessions_closed);
  s->set_sessions_timed_out(c.sessions_timed_out);
  s->set_poses(c.poses);
  s->set_malformed(c.malformed);
  s->set_wrong_schema_version(c.wrong_schema_version);
  s->set_unknown_session(c.unknown_session);
  s->set_bad_pose(c.bad_pose);
  s->set_absurd_pose(c.absurd_pose);
  s->set_oversized(c.oversized);
  s->set_too_many_sessions(c.too_many_sessions);
  s->set_bad_parameter(c.bad_parameter);
  s->set_scene_loads(c.scene_loads);
  s->set_scene_load_failures(c.scene_load_failures);
  s->set_control_requests(c.control_requests);
  s->set_empty_request(c.empty_request);
  s->set_internal_errors(c.internal_errors);
  s->set_bad_view(c.bad_view);
  s->set_not_built(c.not_built);
  s->set_not_owner(c.not_owner);
  s->set_curve_refused(c.curve_refused);
  s->set_curve_admitted(c.curve_admitted);
  s->set_sessions_idle_timed_out(c.sessions_idle_timed_out);
  s->set_session_quota(c.session_quota);
  s->set_load_running(c.load_running);
  s->set_bad_input_unanswered(c.bad_input_unanswered);
  auto* l = s->mutable_pose_service();
  l->set_count(sh_.pose_service.count());
  l->set_p50_us(sh_.pose_service.quantile(0.5));
  l->set_p99_us(sh_.pose_service.quantile(0.99));
  l->set_p999_us(sh_.pose_service.quantile(0.999));
  l->set_max_us(sh_.pose_service.max_us());
  // stages, server-wide: what each holds and costs; deformation only when built
  const World& w = world();
  DeformServerReport d;
  if (deform_) d = deform_->server_report();
  add_stage(s->mutable_stages(), "haptics", w.scene.effects.haptics, sizeof(sh_.slots),
            sh_.pose_service.mean_us() * 1e-3, sh_.pose_service.count());
  add_deform_stages(s->mutable_stages(), deform_ ? &d : nullptr, d.built, d.relax, d.invert);
  fill_stream(s, s->mutable_stages());
  s->set_deform_backend(d.built ? d.backend : "");
  s->set_deform_backend_note(d.built ? d.backend_note : "");
  s->set_deform_steps(d.steps);
  s->set_deform_failures(d.failures);
  s->set_deform_non_converged(d.non_converged);
  s->set_deform_contacts_dropped(d.contacts_dropped);
  s->set_deform_worker_wall_s(d.worker_wall_s);
  s->set_deform_worker_step_s(d.worker_step_s);
  s->set_deform_worker_sleep_s(d.worker_sleep_s);
  s->set_deform_batched_steps(d.batched_steps);
  s->set_deform_batches(d.batches);
  fill_info(st->mutable_info());
  const std::uint64_t id = req_.stats().session_id();
  if (id != 0) {
    // reading a session's stats is not using it: its idle clock runs on
    SessionSlot* slot = session_or_refuse(id, "StatsRequest.session_id", false);
    if (!slot) return;
    auto* ss = st->mutable_session();
    ss->set_session_id(id);
    ss->set_client_name(slot->client_name);
    ss->set_poses(slot->poses);
    ss->set_errors(slot->errors);
    ss->set_last_seq(slot->last_seq);
    ss->set_contact(slot->contact);
    ss->set_depth_mm(slot->depth_mm);
    ss->set_idle_s((ns_since(start_) - slot->last_used_ns.load()) * 1e-9);
    ss->set_silent_s((ns_since(start_) - slot->last_seen_ns.load()) * 1e-9);
    fill_params(ss->mutable_params(), slot->params());
    ss->set_force_clamps(slot->clamps);
    ss->set_local_models_sent(slot->local_models_sent);
    ss->set_local_poses(slot->local_poses);
    ss->set_renders_locally(slot->renders_locally);
    // the session's stages: haptics holds its slot; its pose times are kept server-wide only
    add_stage(ss->mutable_stages(), "haptics", w.scene.effects.haptics, sizeof(SessionSlot), 0, slot->poses);
    DeformSessionReport r;
    const bool has = d.built && deform_->session_report(id, r);
    add_deform_stages(ss->mutable_stages(), has ? &r : nullptr, d.built, d.relax, d.invert);
    fill_session_stream(ss, id);
    if (has) fill_deform(ss->mutable_deform(), r);
    if (has && r.elastic.built) fill_elastic(ss->mutable_deform()->mutable_elastic(), r.elastic, slot->elastic_counters);
    fill_passivity(ss->mutable_passivity(), slot->passivity_counters, w.scene.haptics.passivity);
  }
}

void Server::Control::fill_deform(v1::DeformSessionStats* o, const DeformSessionReport& r) {
  o->set_backend(r.backend);
  o->set_steps(r.steps);
  o->set_contacts_dropped(r.contacts_dropped);
  o->set_non_converged(r.non_converged);
  o->set_failures(r.failures);
  o->set_resets(r.resets);
  o->set_releases(r.releases);
  o->set_last_error(r.last_error);
  fill_times(o->mutable_last(), r.last, 1.0);
  fill_times(o->mutable_mean(), r.sum, r.steps ? 1.0 / double(r.steps) : 0.0);
  o->set_moved(std::uint64_t(r.moved));
  o->set_sweeps(std::uint32_t(r.sweeps));
  o->set_converged(r.converged);
  o->set_chainmail_skipped(r.chainmail_skipped);
  o->set_multigrid_solves(r.multigrid_solves);
  o->set_multigrid_warm(r.multigrid_warm);
  o->set_multigrid_primes(r.multigrid_primes);
  o->set_elastic_superposed(r.elastic_superposed);
  o->set_contacts_current(r.contacts_current);
  o->set_invert_residual_vox(r.invert_residual_vox);
  o->set_invert_unresolved(std::uint64_t(r.invert_unresolved));
  o->set_invert_searched(std::uint64_t(r.invert_searched));
  o->set_max_change_hu(r.max_change_hu);
  o->set_deformed(r.deformed);
  o->set_last_contact_seq(r.last_contact_seq);
  o->set_last_step_server_time_s(r.last_step_server_time_s);
  o->set_voi_lo_i(r.voi.lo.x);
  o->set_voi_lo_j(r.voi.lo.y);
  o->set_voi_lo_k(r.voi.lo.z);
  o->set_voi_size_i(r.voi.size.x);
  o->set_voi_size_j(r.voi.size.y);
  o->set_voi_size_k(r.voi.size.z);
  o->set_bytes_allocated(r.memory.total());
}

void Server::Control::fill_stream(v1::ServerStats* s, google::protobuf::RepeatedPtrField<v1::StageInfo>* stages) {
  const bool frames = frames_served(), bricks = bricks_served();
  StreamInfo info;
  std::size_t frame_bytes = 0, brick_bytes = 0;
  render::FrameTimes sum;
  std::uint64_t frames_n = 0, bricks_n = 0;
  if (stream_) {
    {
      std::lock_guard<std::mutex> lock(stream_->info_mu);
      info = stream_->info;
      sum = stream_->frame_time_sum;
    }
    // the frames path holds its copies of J and its encoded frames, the bricks path its copies of J
    for (int i = 0; i < sh_.slots_used.load(std::memory_order_acquire); ++i) {
      const StreamSlot& ss = stream_->slots[i];
      frame_bytes += ss.j_render_bytes.load(std::memory_order_relaxed) + ss.frame_bytes.load(std::memory_order_relaxed);
      brick_bytes += ss.brick_bytes.load(std::memory_order_relaxed);
    }
    frames_n = stream_->frames_rendered.load();
    bricks_n = stream_->bricks_published.load();
  }
  const double k = frames_n ? 1.0 / double(frames_n) : 0.0;
  add_stage(stages, "frames", frames, frames ? info.render_bytes + frame_bytes : 0, sum.total_ms * k, frames_n);
  add_stage(stages, "bricks", bricks, bricks ? brick_bytes : 0, 0, bricks_n);
  if (!stream_ || (!publisher_ && !render_)) return;
  auto* o = s->mutable_stream();
  o->set_endpoint(publisher_ ? publisher_->endpoint() : "");
  o->set_publisher_thread(info.publisher_thread);
  o->set_render_thread(info.render_thread);
  o->set_egl_context(info.egl_context);
  o->set_gl_renderer(info.gl_renderer);
  o->set_gl_version(info.gl_version);
  o->set_jpeg_encoder(info.jpeg_encoder);
  o->set_overlay_writer(info.overlay_writer);
  o->set_render_note(info.render_note);
  o->set_frames_rendered(stream_->frames_rendered.load());
  o->set_frames_published(stream_->frames_published.load());
  o->set_frames_replaced(stream_->frames_replaced.load());
  o->set_bricks_published(stream_->bricks_published.load());
  o->set_key_bricks_published(stream_->key_bricks_published.load());
  o->set_bytes_published(stream_->bytes_published.load());
  o->set_subscriptions(stream_->subscriptions.load());
  o->set_sessions_watched(stream_->sessions_watched.load());
  o->set_bad_subscriptions(stream_->bad_subscriptions.load());
  o->set_render_failures(stream_->render_failures.load());
  o->set_last_error(info.last_error);
}

void Server::Control::fill_session_stream(v1::SessionStats* out, std::uint64_t id) {
  const bool frames = frames_served(), bricks = bricks_served();
  if (!stream_ || (!frames && !bricks)) {
    add_stage(out->mutable_stages(), "frames", false, 0, 0, 0);
    add_stage(out->mutable_stages(), "bricks", false, 0, 0, 0);
    return;
  }
  StreamSlot& ss = stream_->slot(id);
  auto* o = out->mutable_stream();
  o->set_frames_watched(ss.frames_for.load() == id);
  o->set_bricks_watched(ss.bricks_for.load() == id);
  std::lock_guard<std::mutex> lock(ss.mu);
  const bool mine = ss.report.session_id == id;
  const SessionStreamReport& r = ss.report;
  const std::uint64_t n = mine ? r.frames_rendered : 0;
  if (mine) {
    o->set_frames_rendered(r.frames_rendered);
    o->set_frames_published(r.frames_published);
    o->set_frames_replaced(r.frames_replaced);
    o->set_bricks_published(r.bricks_published);
    o->set_key_bricks_published(r.key_bricks_published);
    fill_frame_times(o->mutable_last(), r.last);
    fill_frame_times(o->mutable_mean(), render::scaled(r.sum, n ? 1.0 / double(n) : 0.0));
    o->set_pose_to_frame_p50_ms(r.pose_to_frame.quantile(0.5));
    o->set_pose_to_frame_p99_ms(r.pose_to_frame.quantile(0.99));
  }
  const bool watched = ss.watch.session_id == id;
  fill_view(o->mutable_view(), watched ? ss.watch.view : default_view(world().scene.render));
  o->set_brick_encoding(watched && ss.watch.brick_float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16);
  o->set_brick_compression(watched && ss.watch.brick_zstd ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE);
  const double now = ns_since(start_) * 1e-9;
  o->set_hold_left_s(watched ? std::max({0.0, ss.watch.frames_hold_until_s - now, ss.watch.bricks_hold_until_s - now}) : 0);
  // the session's stages: its hand-overs (the renderer's textures are counted server-wide only)
  add_stage(out->mutable_stages(), "frames", frames, ss.j_render_bytes.load() + ss.frame_bytes.load(),
            n ? r.sum.total_ms / double(n) : 0, n);
  add_stage(out->mutable_stages(), "bricks", bricks, ss.brick_bytes.load(), 0, mine ? r.bricks_published : 0);
}

}  // namespace palpsim::net
