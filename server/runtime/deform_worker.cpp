#include "runtime/deform_worker.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>

#ifdef __linux__
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#include "core/error.h"
#include "deform/approach.h"
#include "deform/press_cap.h"
#include "deform/relax_multigrid.h"
#include "runtime/deform_worker_state.h"

namespace palpsim::runtime {
namespace {

// at most this many engines of closed sessions are kept for the next sessions
constexpr std::size_t kMaxSpares = 2;
// how long the worker sleeps when no session had anything new (s): well below a haptic period
constexpr double kIdleSleepS = 0.5e-3;
// how long it sleeps while the scene asks for no deformation or no session is open (s)
constexpr double kDisabledSleepS = 20e-3;
// A session whose tip is out of the body has its multigrid unit response solved where the
// tip is expected to touch (DeformEngine::prime), so that its first contact starts warm
// (half the steps of a solve from zero or fewer). At most once per this interval per
// session (s): a re-prime starts warm too, so a hovering session takes a small share of
// the GPU; and at most a kPrimeShare of the worker's time, for the "cpu" backend, whose
// primes take a core for tens of ms (the interval then grows to 10 times the last prime's
// time).
constexpr double kPrimeIntervalS = 20e-3;
constexpr double kPrimeShare = 0.1;
// Why the server runs the worker at nice 19 (ServerOptions::deform_nice): on a machine
// with few cores the scheduler should prefer answering poses to deforming. On the shared
// 2-core VM, lumbar phantom at VOI 64 on the CPU (~100 ms steps) with palpsim-haptic
// pressing at 1 kHz: nice 0 gave round-trip p99 1.3-2.3 ms and 90-146 missed deadlines of
// 6000; nice 19 p99 0.19-1.8 ms and 25-36; haptics alone p99 0.26-0.27 ms and 8-10. The
// worker then runs fewer steps on a busy machine, which is what the deformation path is for.
// SCHED_IDLE on top of nice 19 (ServerOptions::background_idle) halved p99 again:
// core/thread.h has the figures.

void add_times(DeformTimes& a, const DeformTimes& b) {
  a.reset_ms += b.reset_ms;
  a.chainmail_ms += b.chainmail_ms;
  a.relax_ms += b.relax_ms;
  a.untangle_ms += b.untangle_ms;
  a.invert_ms += b.invert_ms;
  a.upload_ms += b.upload_ms;
  a.total_ms += b.total_ms;
}

bool finite(const DeformStats& st) {
  const DeformTimes& t = st.times;
  const Vec3f& u = st.chainmail.grabbed_u_vox;
  return std::isfinite(u.x) && std::isfinite(u.y) && std::isfinite(u.z) && std::isfinite(st.invert_residual_vox) &&
         std::isfinite(t.total_ms);
}

}  // namespace

DeformWorker::DeformWorker(ServerShared& shared, std::chrono::steady_clock::time_point start, int nice, bool idle,
                           int concurrency, int batch)
    : sh_(shared),
      start_(start),
      nice_(nice),
      idle_(idle),
      thread_(shared.world, shared.deform_seen_generation),
      max_inflight_(std::max(1, concurrency)),
      max_batch_(std::max(1, batch)) {}

DeformWorker::~DeformWorker() { stop(); }

double DeformWorker::now_s() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
}

void DeformWorker::start() { thread_.start("palpsim-deform", nice_, idle_, [this] { run(); }); }

void DeformWorker::stop() { thread_.stop(); }

void DeformWorker::run() {
  while (!thread_.stopping()) {
    // a new scene: new engines (or none)
    if (!thread_.follow_world(generation_, [this] { set_up_world(); })) break;
    if (request_pending_.load(std::memory_order_acquire)) answer_request();
    if (!built_) {
      std::this_thread::sleep_for(std::chrono::duration<double>(kDisabledSleepS));
      continue;
    }
    // one pass over the sessions: at most one step each, on its newest contact; up to
    // max_inflight_ steps are enqueued before the worker waits for them, each on its
    // session's stream with 1/k of the GPU, so that they run side by side
    bool worked = false, any_open = false;
    const int used = sh_.slots_used.load(std::memory_order_acquire);
    int open = 0;
    for (int i = 0; i < used; ++i) open += sh_.slots[i].id.load(std::memory_order_relaxed) != 0;
    gpu_share_ = std::max(1, std::min(max_inflight_, open));
    for (int i = 0; i < used && !thread_.stopping(); ++i) {
      worked = serve(i) || worked;
      any_open = any_open || sessions_[i].id != 0;
      if (request_pending_.load(std::memory_order_acquire)) {
        begin_ready();
        complete_inflight();
        answer_request();
      }
    }
    begin_ready();
    complete_inflight();
    // nothing new: a short nap while sessions are open, a longer one while none is
    if (!worked) {
      const auto t0 = std::chrono::steady_clock::now();
      std::this_thread::sleep_for(std::chrono::duration<double>(any_open ? kIdleSleepS : kDisabledSleepS));
      sleep_s_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      // the worker's times in stats stay current while no step publishes them (a stats
      // request between two loads, as palpsim-bench server makes, reads the nap so far)
      std::lock_guard<std::mutex> lock(report_mu_);
      publish_worker_times();
    }
  }
  // every engine is destroyed on this thread (cuda: its stream and buffers too)
  for (Session& s : sessions_) s.engine.reset();
  spares_.clear();
  thread_.setup().open();
}

void DeformWorker::set_up_world() {
  // copy what the worker needs; then the control thread may free the world once it is old
  const World* w = sh_.world.load(std::memory_order_acquire);
  generation_ = w->generation;
  const Scene scene = w->scene;
  patient_ = w->patient;
  thread_.picked_up(generation_);
  config_ = DeformConfig::from_scene(scene, patient_.get());
  // priming needs multigrid relaxation that reuses and starts warm (DeformBackend::prime)
  const DeformSettings& ds = config_.settings;
  prime_ = scene.effects.chainmail && config_.primes();
  if (prime_) body_centroid_vox_ = deform::body_centroid_vox(*patient_);
  const Vec3i& gs = patient_->grid.size;
  grid_centre_mm_ = patient_->grid.to_physical(Vec3(0.5 * (gs.x - 1), 0.5 * (gs.y - 1), 0.5 * (gs.z - 1)));
  prime_radius_vox_ = ds.whole_volume ? 0 : ds.voi_edge / 2;
  min_watched_step_s_ = scene.effects.frames && scene.render.max_fps > 0 ? 1.0 / scene.render.max_fps : 0.0;
  world_start_ = std::chrono::steady_clock::now();
  step_s_ = sleep_s_ = 0;
  batch_share_ = 0;
  batched_steps_ = 0;
  // engines of the previous world are bound to its patient and settings
  std::vector<Session>().swap(sessions_);
  spares_.clear();
  built_ = scene.effects.chainmail;
  DeformServerReport rep;
  rep.built = built_;
  if (built_) {
    // one engine now: chooses and logs the backend and validates the settings; it is the
    // first session's engine later
    try {
      auto engine = std::make_unique<DeformEngine>(patient_, config_);
      rep.backend = engine->backend_name();
      rep.backend_note = engine->backend_note();
      rep.relax = config_.relax;
      rep.invert = config_.invert;
      spdlog::info("deformation for scene '{}': {}; ChainMail{}{}, VOI {}, one worker thread for all sessions, "
                   "batches of up to {}",
                   scene.name, engine->backend_note(), config_.relax ? " + relaxation" : "",
                   config_.invert ? " + inversion" : "",
                   config_.settings.whole_volume ? std::string("whole volume")
                                                 : "edge " + std::to_string(config_.settings.voi_edge),
                   max_batch_);
      spares_.push_back(std::move(engine));
    } catch (const std::exception& e) {
      built_ = false;
      rep.built = false;
      const std::string why = std::string("scene '") + scene.name + "': deformation cannot be served: " + e.what();
      // the first scene: start() throws it; a scene loaded later is served with haptics only
      if (!thread_.setup().is_open())
        thread_.setup().fail(why);
      else
        spdlog::error("{}; its sessions get haptics only", why);
    }
  } else if (scene.effects.relaxation || scene.effects.inversion) {
    spdlog::warn("scene '{}' asks for relaxation or inversion without chainmail; no deformation is built",
                 scene.name);
  }
  // per-slot bookkeeping only while deformation is built: a scene without it holds nothing
  if (built_) sessions_.resize(kMaxSlots);
  std::lock_guard<std::mutex> lock(report_mu_);
  std::vector<DeformSessionReport>(built_ ? kMaxSlots : 0).swap(reports_);
  slot_bytes_ = sessions_.capacity() * sizeof(Session) + reports_.capacity() * sizeof(DeformSessionReport);
  server_ = rep;
  for (const auto& e : spares_) {
    add_memory(server_.memory, e->memory());
    ++server_.engines;
  }
}

std::unique_ptr<DeformEngine> DeformWorker::take_engine() {
  if (!spares_.empty()) {
    auto e = std::move(spares_.back());
    spares_.pop_back();
    return e;
  }
  return std::make_unique<DeformEngine>(patient_, config_);
}

void DeformWorker::give_back(std::unique_ptr<DeformEngine> engine) {
  if (!engine) return;
  if (spares_.size() < kMaxSpares) {
    engine->reset();
    spares_.push_back(std::move(engine));
  }
}

bool DeformWorker::serve(int index) {
  const Parts p = parts_.at(index);
  const std::size_t before = inflight_.size() + ready_.size();
  const bool worked = serve_deformation(p);
  // a session whose step is readied or in flight exports when it completes (complete_inflight)
  if (inflight_.size() + ready_.size() == before) export_watched(p);
  // at most gpu_share_ steps in flight: their grids are sized to fit together
  if (inflight_.size() >= std::size_t(gpu_share_)) complete_inflight();
  // a full batch is begun and finished at once; a smaller one at the end of the pass
  if (ready_.size() >= std::size_t(max_batch_)) {
    begin_ready();
    complete_inflight();
  }
  return worked;
}

bool DeformWorker::serve_deformation(const Parts& p) {
  SessionSlot& slot = p.table;
  Session& s = p.own;
  const std::uint64_t id = slot.id.load(std::memory_order_acquire);
  // a closed session, or a new one in this slot
  if (id != s.id) {
    const bool had = s.id != 0;
    give_back(std::move(s.engine));
    s = Session{};
    if (id != 0) {
      s.id = id;
      s.resets_seen = slot.reset_requests.load(std::memory_order_acquire);
      s.pose_resets_seen = slot.pose_resets.load(std::memory_order_acquire);
      s.report.session_id = id;
      s.report.elastic.built = config_.relax && config_.settings.relax_method == RelaxMethod::kElastic;
    }
    if (had || id != 0) publish(p);
  }
  if (id == 0) return false;
  // the newest contact first, then the reset counters: a reset ordered before this
  // contact on the pose path is visible once the contact is
  Contact c;
  const std::uint64_t version = slot.latest.read(c);
  const std::uint32_t resets = slot.reset_requests.load(std::memory_order_acquire);
  const std::uint32_t pose_resets = slot.pose_resets.load(std::memory_order_acquire);
  bool worked = false;
  const bool control_reset = resets != s.resets_seen;
  if (control_reset || pose_resets != s.pose_resets_seen) {
    s.report.resets += (resets - s.resets_seen) + (pose_resets - s.pose_resets_seen);
    s.resets_seen = resets;
    s.pose_resets_seen = pose_resets;
    reset(p);
    // a ResetSession undoes what came before it, and the contact read above may: the
    // next pose deforms again. (A reset flag travels with its pose, whose contact is
    // newer than the reset and is stepped on below.)
    if (control_reset && c.session_id == id) {
      s.last_version = version;
      return true;
    }
    worked = true;
  }
  // nothing new, or a contact of the slot's previous session
  if (version == s.last_version || c.session_id != id) {
    // a session before its first pose primes at the body voxel nearest the grid's centre:
    // any unit response is a far better start than zero (a press has one shape wherever
    // it is: 2 warm steps from 22 voxels away land 0.24-0.35% from the steady state, the
    // torso test), so that even a first pose already in the body starts warm
    Vec3i held;
    const bool holds = s.engine && s.engine->unit_response(held);
    if (prime_ && c.session_id != id && !holds && prime(p, grid_centre_mm_)) worked = true;
    return worked;
  }
  // contacts written since the last one taken were stale before the worker got to them
  std::uint64_t dropped = 0;
  if (s.last_version != 0 && version > s.last_version + 1) dropped = version - s.last_version - 1;
  s.last_version = version;
  if (dropped) {
    s.report.contacts_dropped += dropped;
    std::lock_guard<std::mutex> lock(report_mu_);
    server_.contacts_dropped += dropped;
  }
  if (!c.contact) {
    // out of the body: the tissue is undeformed again
    if (s.report.deformed) {
      ++s.report.releases;
      reset(p);
      worked = true;
    } else if (dropped) {
      publish(p);
    }
    // and the next contact's unit response is made ready where the tip is expected to touch
    if (prime_ && prime(p, c.tip_mm)) worked = true;
    return worked;
  }
  // the tip as the step presses it (the elastic model's held short of bone), so that a
  // device tip going on into bone asks for no step, and the force model's x0 is it
  const Vec3 device_tip_mm = c.tip_mm;
  c.tip_mm = deform::capped_press(*patient_, config_, DeformContact{c.skin_point_mm, c.tip_mm}).tip_mm;
  // the same contact as the step in place (a held tip, or one pressing on past where bone
  // holds the press: those tips differ by rounding, hence 1e-9 mm): the same J, nothing to
  // step; the report says which contact J now stands for (published even when no contact
  // was dropped: a client waiting for its last pose's seq would otherwise wait for ever)
  auto same = [](const Vec3& a, const Vec3& b) { return norm(a - b) <= 1e-9; };
  if (s.report.deformed && s.engine && same(c.tip_mm, s.last_tip_mm) && c.skin_point_mm == s.last_skin_mm) {
    s.report.last_contact_seq = c.seq;
    ++s.report.contacts_current;
    // J now stands for a pose at another device tip (a press going on past the hold): the
    // watched hand-overs say so, or a frame drawn at the new tip would name the pose before it
    if (!(device_tip_mm == s.last_device_tip_mm)) {
      s.last_device_tip_mm = device_tip_mm;
      s.last_contact_time_s = c.server_time_s;
      s.last_proxy_mm = c.proxy_mm;
      ++s.state_version;
    }
    publish(p);
    return worked;
  }
  // a session whose frames are watched steps at most once per frame: its viewer sees
  // only the newest J at each frame, and steps beyond that only take the GPU from the
  // frames (watched sessions get fewer frames a second when stepped more often than
  // their frames); the contact stays, the next pass takes the newest
  if (min_watched_step_s_ > 0) {
    if (p.stream && p.stream->frames_for.load(std::memory_order_acquire) == id &&
        now_s() - s.last_step_begun_s < min_watched_step_s_) {
      s.last_version = version - 1;  // not taken: the next pass counts no drop for it
      if (dropped) publish(p);
      return worked;
    }
  }
  s.last_step_begun_s = now_s();
  s.last_device_tip_mm = device_tip_mm;
  step(p, c);
  return true;
}

void DeformWorker::reset(const Parts& p) {
  Session& s = p.own;
  ++s.state_version;
  try {
    if (s.engine) s.engine->reset();
  } catch (const std::exception& e) {
    // a backend that cannot even reset is dropped; the next contact makes a new one
    s.engine.reset();
    ++s.report.failures;
    s.report.last_error = std::string("reset: ") + e.what();
  }
  s.report.deformed = false;
  s.report.max_change_hu = 0;
  // the tissue at rest presses nothing: the haptic thread's elastic force falls to zero
  if (s.report.elastic.built) {
    ElasticModel none;
    none.pose_server_time_s = now_s();
    publish_elastic(p, none);
  }
  publish(p);
}

bool DeformWorker::prime(const Parts& p, const Vec3& tip_mm) {
  Session& s = p.own;
  const double now = now_s();
  if (now - s.last_prime_s < std::max(kPrimeIntervalS, s.last_prime_cost_s / kPrimeShare)) return false;
  Vec3i v;
  bool near = false;
  if (!deform::expected_skin_voxel(*patient_, tip_mm, prime_radius_vox_, body_centroid_vox_, v, &near)) return false;
  // a session holding a unit response primes again only near the body, where the expected
  // voxel moved farther than a warm start's near move from the one held
  Vec3i held;
  if (s.engine && s.engine->unit_response(held)) {
    bool moved = false;
    for (int a = 0; a < 3; ++a) moved = moved || std::abs(v[a] - held[a]) > deform::kMultigridNearMove;
    if (!near || !moved) return false;
  }
  const auto t0 = std::chrono::steady_clock::now();
  s.last_prime_s = now;
  try {
    if (!s.engine) s.engine = take_engine();
    s.report.backend = s.engine->backend_name();
    s.engine->backend().set_gpu_share(gpu_share_);
    const Vec3 X = patient_->grid.to_physical(Vec3(v.x, v.y, v.z));
    const DeformPrime pr = s.engine->prime(DeformContact{X, X});
    if (pr.solved) ++s.report.multigrid_primes;
    // published either way: the engine just taken holds memory the stats must show
    publish(p);
  } catch (const std::exception& e) {
    // a prime only prepares: its failure costs the next contact a solve from zero
    s.report.last_error = std::string("prime: ") + e.what();
    publish(p);
  }
  s.last_prime_cost_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  step_s_ += s.last_prime_cost_s;
  return true;
}

void DeformWorker::step(const Parts& p, const Contact& c) {
  Session& s = p.own;
  const auto t0 = std::chrono::steady_clock::now();
  DeformSessionReport& r = s.report;
  ++s.state_version;
  s.last_contact_time_s = c.server_time_s;
  s.last_tip_mm = c.tip_mm;
  s.last_skin_mm = c.skin_point_mm;
  s.last_proxy_mm = c.proxy_mm;
  try {
    if (!s.engine) s.engine = take_engine();
    r.backend = s.engine->backend_name();
    if (max_batch_ > 1) {
      // begun with the pass's other ready sessions (begin_ready)
      ready_.push_back({p.index, c});
    } else {
      // enqueued now, finished in complete() after the pass's other sessions are enqueued
      s.engine->backend().set_gpu_share(gpu_share_);
      s.engine->begin_step(DeformContact{c.skin_point_mm, c.tip_mm});
      inflight_.push_back({p.index, c});
    }
  } catch (const std::exception& e) {
    fail(p, c, e);
    publish(p);
  }
  // enqueueing (cuda) or the whole step (cpu); complete_inflight() adds the wait
  step_s_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void DeformWorker::begin_ready() {
  if (ready_.empty()) return;
  const auto t0 = std::chrono::steady_clock::now();
  // the sessions ready in this pass, in slot order, stepped by shared launches where the
  // backend can (cuda with one configuration: one launch per stage for all of them)
  std::vector<DeformEngine*>& engines = batch_engines_;
  std::vector<DeformContact>& contacts = batch_contacts_;
  engines.clear();
  contacts.clear();
  // a batch fills the device whatever the share; steps its backend begins alone (scenes
  // the batched kernels do not cover) are all in flight at once, so each takes 1/n of
  // the device: a cooperative grid needs all its blocks resident, and n grids of 1/n fit
  const int share = std::max(gpu_share_, int(ready_.size()));
  for (const Inflight& f : ready_) {
    engines.push_back(sessions_[f.index].engine.get());
    engines.back()->backend().set_gpu_share(share);
    contacts.push_back(DeformContact{f.contact.skin_point_mm, f.contact.tip_mm});
  }
  const std::vector<std::exception_ptr> errors = DeformEngine::begin_steps(engines, contacts);
  for (std::size_t i = 0; i < ready_.size(); ++i) {
    const Inflight& f = ready_[i];
    if (!errors[i]) {
      inflight_.push_back(f);
      continue;
    }
    // a step that could not be begun: counted and reset, as a step that threw
    const Parts p = parts_.at(f.index);
    try {
      std::rethrow_exception(errors[i]);
    } catch (const std::exception& e) {
      fail(p, f.contact, e);
    } catch (...) {
      fail(p, f.contact, Error("unknown error"));
    }
    publish(p);
  }
  ready_.clear();
  step_s_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

void DeformWorker::complete_inflight() {
  // in the order they were begun: the first enqueued is the first to finish
  for (const Inflight& f : inflight_) {
    const Parts p = parts_.at(f.index);
    const auto t0 = std::chrono::steady_clock::now();
    complete(p, f.contact);
    // the wait for this step (the others' steps overlap it on the GPU, so the worker's
    // step time counts waits, not the sum of the steps)
    step_s_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    publish(p);
    export_watched(p);
  }
  inflight_.clear();
}

void DeformWorker::complete(const Parts& p, const Contact& c) {
  Session& s = p.own;
  DeformSessionReport& r = s.report;
  try {
    const DeformStats st = s.engine->end_step();
    // each of a batch's steps counts 1/batch of it
    if (st.batch > 1) {
      ++batched_steps_;
      batch_share_ += 1.0 / st.batch;
    }
    // J must be finite, and how far it moved from I says how much the image changed: the
    // inversion counts both as it writes J (on the GPU for cuda), so the worker does not
    // read J again (a scan of J on the host costs more than the step's own GPU work)
    double change = 0;
    bool ok = finite(st);
    if (s.engine->has_deformed_brick()) {
      ok = ok && st.invert_nonfinite == 0 && std::isfinite(st.invert_max_change);
      change = st.invert_max_change;
    } else {
      // no J (the scene asks for no inversion): the displacement itself must be finite
      for (const Vec3f& u : s.engine->backend().displacement())
        if (!std::isfinite(u.x) || !std::isfinite(u.y) || !std::isfinite(u.z)) {
          ok = false;
          break;
        }
    }
    if (!ok) throw Error("the step produced a non-finite value (NaN or Inf in the displacement or J)");
    ++r.steps;
    r.last = st.times;
    add_times(r.sum, st.times);
    r.moved = st.chainmail.moved;
    r.sweeps = st.chainmail.sweeps;
    r.chainmail_skipped = st.chainmail.skipped;
    r.multigrid_solves += st.relax_solves > 0;
    r.multigrid_warm += st.relax_warm;
    r.elastic_superposed += st.elastic.superposed;
    r.converged = st.chainmail.converged;
    r.invert_residual_vox = st.invert_residual_vox;
    r.invert_unresolved = st.invert_unresolved;
    r.invert_searched = st.invert_searched;
    r.max_change_hu = change;
    r.deformed = true;
    r.last_contact_seq = c.seq;
    r.voi = st.chainmail.voi;
    r.last_step_server_time_s = now_s();
    // the elastic step's force as a local linear model at the tip it solved for
    if (r.elastic.built) {
      const deform::ElasticRun& e = st.elastic;
      ElasticModel m = make_elastic_model(patient_->grid, c.tip_mm, e.contact && e.contact_nodes > 0, e.force_n,
                                          e.normal, e.stiffness_n_per_mm, e.depth_mm, e.contact_nodes);
      m.pose_seq = c.seq;
      m.pose_server_time_s = c.server_time_s;
      r.elastic.iterations = e.iterations;
      r.elastic.stiffness_iterations = e.stiffness_iterations;
      r.elastic.converged = e.converged;
      publish_elastic(p, m);
    }
    if (!st.chainmail.converged) {
      ++r.non_converged;
      r.last_error = "ChainMail did not converge within deform.max_sweeps = " +
                     std::to_string(config_.settings.max_sweeps) + " sweeps (contact seq " + std::to_string(c.seq) +
                     ", " + std::to_string(st.chainmail.moved) + " elements moved); the state is kept";
      if (r.non_converged == 1) spdlog::warn("session {}: {} (counted in stats)", hex_id(s.id), r.last_error);
    }
    std::lock_guard<std::mutex> lock(report_mu_);
    ++server_.steps;
    add_times(server_.sum, st.times);
    if (!st.chainmail.converged) ++server_.non_converged;
  } catch (const std::exception& e) {
    fail(p, c, e);
  }
}

void DeformWorker::fail(const Parts& p, const Contact& c, const std::exception& e) {
  // a failed step poisons nothing: the session's deformation starts again from undeformed
  Session& s = p.own;
  DeformSessionReport& r = s.report;
  ++r.failures;
  r.last_error = "contact seq " + std::to_string(c.seq) + ": " + e.what() + "; the session's deformation was reset";
  if (r.failures == 1) spdlog::warn("session {}: deformation step failed: {} (counted in stats)", hex_id(s.id), r.last_error);
  try {
    if (s.engine) s.engine->reset();
  } catch (const std::exception&) {
    s.engine.reset();
  }
  r.deformed = false;
  r.max_change_hu = 0;
  if (r.elastic.built) {
    ElasticModel none;
    none.pose_seq = c.seq;
    none.pose_server_time_s = c.server_time_s;
    publish_elastic(p, none);
  }
  std::lock_guard<std::mutex> lock(report_mu_);
  ++server_.failures;
}

}  // namespace palpsim::runtime
