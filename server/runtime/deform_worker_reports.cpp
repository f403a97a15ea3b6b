// What the deformation worker hands out: elastic models to the haptic thread, J to the
// render thread and the publisher, reports to stats, and whole deformed volumes on request.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <mutex>

#include "runtime/deform_worker.h"
#include "runtime/deform_worker_state.h"

namespace palpsim::runtime {

void add_memory(DeformMemory& a, const DeformMemory& b) {
  a.chainmail_bytes += b.chainmail_bytes;
  a.relax_bytes += b.relax_bytes;
  a.invert_bytes += b.invert_bytes;
  // every engine of a world shares the one device copy of its patient: count it once
  a.shared_patient_bytes = std::max(a.shared_patient_bytes, b.shared_patient_bytes);
  // and the one solver scratch of its multigrid sessions
  a.shared_scratch_bytes = std::max(a.shared_scratch_bytes, b.shared_scratch_bytes);
}

void DeformWorker::publish_elastic(const Parts& p, const ElasticModel& m) {
  Session& s = p.own;
  ElasticForceReport& r = s.report.elastic;
  r.model = m;
  r.model.session_id = s.id;
  r.model.generation = generation_;
  // with haptics.force_model "elastic" the haptic thread renders it (newest wins; never waits)
  if (config_.elastic_force) {
    p.table.elastic_model.back() = r.model;
    p.table.elastic_model.publish();
    ++r.models_published;
  }
}

void DeformWorker::export_watched(const Parts& p) {
  Session& s = p.own;
  if (!p.stream || s.id == 0) return;
  StreamSlot& ss = *p.stream;
  // a session that became watched gets its current state at once; then every change
  const bool frames = ss.frames_for.load(std::memory_order_acquire) == s.id;
  const bool bricks = ss.bricks_for.load(std::memory_order_acquire) == s.id;
  if (frames && (!s.render_watched || s.render_exported != s.state_version)) {
    // the stream state that holds p.stream: made once, kept for the server's life
    const StreamState& st = *sh_.stream.load(std::memory_order_acquire);
    fill_snapshot(ss.j_render.back(), s, st.render_wants_device.load(std::memory_order_acquire));
    ss.j_render.publish();
    ss.j_render_bytes.store(held_bytes(ss.j_render), std::memory_order_relaxed);
    s.render_exported = s.state_version;
  }
  if (bricks && (!s.bricks_watched || s.bricks_exported != s.state_version)) {
    fill_snapshot(ss.j_bricks.back(), s, false);
    ss.j_bricks.publish();
    ss.brick_bytes.store(held_bytes(ss.j_bricks), std::memory_order_relaxed);
    s.bricks_exported = s.state_version;
  }
  s.render_watched = frames;
  s.bricks_watched = bricks;
}

void DeformWorker::fill_snapshot(JSnapshot& o, Session& s, bool device) {
  o.session_id = s.id;
  o.step = s.report.steps;
  o.pose_seq = s.report.last_contact_seq;
  o.pose_server_time_s = s.last_contact_time_s;
  o.tip_mm = s.last_tip_mm;
  o.proxy_mm = s.last_proxy_mm;
  // J exists after a step of a scene with inversion; otherwise the image is undeformed
  const bool has_j = s.report.deformed && s.engine && s.engine->has_deformed_brick();
  o.deformed = has_j;
  o.voi = has_j ? s.engine->voi() : Voi{};
  o.host_valid = false;
  o.device_valid = false;
  if (!has_j) return;
  // the render thread's cuda-gl writer takes a device copy; everyone else the host brick
  if (device) {
    try {
      o.device_valid = s.engine->copy_brick_to_device(o.device_j);
    } catch (const std::exception& e) {
      spdlog::warn("session {}: device copy of J for the renderer failed ({}); sending the host copy", hex_id(s.id),
                   e.what());
    }
  }
  if (!o.device_valid) {
    const float* j = s.engine->deformed_brick();  // cuda: copied to the host now, after a batched step
    o.host_j.assign(j, j + o.voi.count());
    o.host_valid = true;
  }
}

void DeformWorker::publish(const Parts& p) {
  const Session& s = p.own;
  std::lock_guard<std::mutex> lock(report_mu_);
  DeformSessionReport& out = reports_[std::size_t(p.index)];
  out = s.report;
  out.memory = s.engine ? s.engine->memory() : DeformMemory{};
  // server_.memory holds the spare engines; server_report() adds the sessions' own
  publish_worker_times();
  server_.batches = std::uint64_t(std::llround(batch_share_));
  server_.batched_steps = batched_steps_;
  server_.memory = DeformMemory{};
  server_.engines = 0;
  for (const auto& e : spares_) {
    add_memory(server_.memory, e->memory());
    ++server_.engines;
  }
}

void DeformWorker::publish_worker_times() {
  server_.worker_wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - world_start_).count();
  server_.worker_step_s = step_s_;
  server_.worker_sleep_s = sleep_s_;
}

bool DeformWorker::session_report(std::uint64_t session_id, DeformSessionReport& out) const {
  if (session_id == 0) return false;
  std::lock_guard<std::mutex> lock(report_mu_);
  if (reports_.empty()) return false;
  const DeformSessionReport& r = reports_[std::size_t(slot_index(session_id))];
  if (r.session_id != session_id) return false;
  out = r;
  return true;
}

DeformServerReport DeformWorker::server_report() const {
  std::lock_guard<std::mutex> lock(report_mu_);
  DeformServerReport r = server_;
  // the worker's own per-slot bookkeeping serves ChainMail too
  r.memory.chainmail_bytes += slot_bytes_;
  // sessions' engines on top of the spares
  for (const DeformSessionReport& s : reports_)
    if (s.session_id != 0 && s.memory.total() > 0) {
      add_memory(r.memory, s.memory);
      ++r.engines;
    }
  // server-wide, ChainMail's stage holds the patient's shared device copy too (once)
  r.memory.chainmail_bytes += r.memory.shared_patient_bytes;
  r.memory.relax_bytes += r.memory.shared_scratch_bytes;
  return r;
}

bool DeformWorker::deformed_volume(std::uint64_t session_id, Volume<float>& out, double timeout_s) {
  std::lock_guard<std::mutex> one_at_a_time(request_mu_);
  std::unique_lock<std::mutex> lock(mailbox_mu_);
  request_ = std::make_unique<Request>();
  request_->session_id = session_id;
  request_->out = &out;
  request_pending_.store(true, std::memory_order_release);
  const bool answered = mailbox_cv_.wait_for(lock, std::chrono::duration<double>(timeout_s), [this] { return request_->done; });
  const bool found = answered && request_->found;
  request_pending_.store(false, std::memory_order_release);
  request_.reset();
  return found;
}

void DeformWorker::answer_request() {
  std::lock_guard<std::mutex> lock(mailbox_mu_);
  if (!request_ || request_->done) return;
  Request& q = *request_;
  const Session* s = sessions_.empty() ? nullptr : &sessions_[std::size_t(slot_index(q.session_id))];
  if (s && q.session_id != 0 && s->id == q.session_id) {
    q.found = true;
    if (s->engine) {
      *q.out = s->engine->deformed_volume();
    } else {
      // no engine yet: undeformed
      q.out->grid = patient_->grid;
      q.out->data = patient_->intensity.data;
    }
  }
  q.done = true;
  request_pending_.store(false, std::memory_order_release);
  mailbox_cv_.notify_all();
}

}  // namespace palpsim::runtime
