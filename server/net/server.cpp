#include "net/server.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <random>
#include <utility>
#include <zmq.hpp>

#include "core/error.h"
#include "core/path_policy.h"
#include "core/setting_names.h"
#include "core/thread.h"
#include "deform/backend.h"
#include "net/client_text.h"
#include "net/curve_keys.h"
#include "net/deform_worker.h"
#include "net/heap_trimmer.h"
#include "net/pose_service.h"
#include "net/render_worker.h"
#include "net/scene_io.h"
#include "net/session_table.h"
#include "net/stream_publisher.h"
#include "net/stream_state.h"
#include "net/wire_convert.h"
#include "net/zap_handler.h"
#include "render/camera.h"
#include "render/view.h"
#include "palpsim/options.pb.h"
#include "palpsim/scene.pb.h"
#include "palpsim/wire.pb.h"

namespace palpsim::net {
namespace {

namespace v1 = ::palpsim::v1;
using Clock = std::chrono::steady_clock;

// a refusal's message is cut to this many characters (client strings in it to kClientTextChars)
constexpr std::size_t kMaxErrorChars = 2048;

std::string hex_id(std::uint64_t id) {
  char b[32];
  std::snprintf(b, sizeof b, "%016" PRIx64, id);
  return b;
}

void fill_params(v1::HapticsParams* out, const HapticsSettings& s) {
  out->set_stiffness_n_per_mm(s.stiffness_n_per_mm);
  out->set_friction(s.friction);
  out->set_max_force_n(s.max_force_n);
  out->set_max_force_rate_n_per_s(s.max_force_rate_n_per_s);
  out->set_min_gradient_norm(s.min_gradient_norm);
}

// the stages built for a scene: the deformation stages a report says were built, and
// frames and bricks while their threads serve them
std::vector<std::string> stages_of(const Scene& s, const DeformServerReport* d, bool frames, bool bricks) {
  std::vector<std::string> out;
  if (s.effects.haptics) out.push_back("haptics");
  if (d && d->built) {
    out.push_back("chainmail");
    if (d->relax) out.push_back("relaxation");
    if (d->invert) out.push_back("inversion");
  }
  if (frames) out.push_back("frames");
  if (bricks) out.push_back("bricks");
  return out;
}

// applies the fields a WatchSession sets to `v`; "" or the first bad field and why
std::string apply_view(const v1::ViewSettings& in, render::ViewSettings& v) {
  if (in.has_width()) v.width = int(std::min<std::uint32_t>(in.width(), 1u << 30));
  if (in.has_height()) v.height = int(std::min<std::uint32_t>(in.height(), 1u << 30));
  if (in.has_preset() && !parse_setting(in.preset(), &v.preset))
    return "preset '" + client_text(in.preset()) + "' is not one of " + setting_names_listed<render::Preset>();
  if (in.has_azimuth_deg()) v.azimuth_deg = in.azimuth_deg();
  if (in.has_elevation_deg()) v.elevation_deg = in.elevation_deg();
  if (in.has_zoom()) v.zoom = in.zoom();
  if (in.has_look_at_tip()) v.look_at_tip = in.look_at_tip();
  if (in.has_center_mm()) {
    v.center_mm = {in.center_mm().x(), in.center_mm().y(), in.center_mm().z()};
    v.center_set = true;
  }
  if (in.has_jpeg_quality()) v.jpeg_quality = int(std::min<std::uint32_t>(in.jpeg_quality(), 1u << 30));
  if (in.has_show_tip()) v.show_tip = in.show_tip();
  if (in.has_show_proxy()) v.show_proxy = in.show_proxy();
  if (in.has_slice_fov_mm()) v.slice_fov_mm = in.slice_fov_mm();
  return render::check_view(v);
}

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

std::unique_ptr<World> make_world(const Scene& scene, PatientPtr patient, std::uint64_t generation) {
  auto w = std::make_unique<World>();
  w->scene = scene;
  w->patient = std::move(patient);
  w->generation = generation;
  const Grid& g = w->patient->grid;
  // grid bounds: the eight corners of the voxel box
  Vec3 lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  auto grow = [](Vec3& a, Vec3& b, const Vec3& p) {
    a = {std::min(a.x, p.x), std::min(a.y, p.y), std::min(a.z, p.z)};
    b = {std::max(b.x, p.x), std::max(b.y, p.y), std::max(b.z, p.z)};
  };
  for (int c = 0; c < 8; ++c) {
    const Vec3 ijk{(c & 1) ? g.size.x - 0.5 : -0.5, (c & 2) ? g.size.y - 0.5 : -0.5, (c & 4) ? g.size.z - 0.5 : -0.5};
    grow(lo, hi, g.to_physical(ijk));
  }
  w->bounds_min_mm = lo;
  w->bounds_max_mm = hi;
  // body bounds: index box of the body voxels, then its corners in physical space
  const IndexBox box = mask_box(w->patient->body);
  const Vec3i bl = box.lo, bh = box.hi;
  if (!box.empty()) {
    Vec3 a{1e300, 1e300, 1e300}, b{-1e300, -1e300, -1e300};
    for (int c = 0; c < 8; ++c)
      grow(a, b, g.to_physical(Vec3{double((c & 1) ? bh.x : bl.x), double((c & 2) ? bh.y : bl.y),
                                    double((c & 4) ? bh.z : bl.z)}));
    w->body_min_mm = a;
    w->body_max_mm = b;
  }
  w->body_center_mm = render::body_center(g, bl, bh);
  return w;
}

namespace {
// the address `offset` ports above a tcp control address ("*" stays "*"), or the control
// path with `suffix` for ipc:// and inproc:// ("." or "-" joined)
std::string derive_endpoint(const std::string& control, int offset, const std::string& suffix) {
  if (control.rfind("tcp://", 0) == 0) {
    const auto colon = control.rfind(':');
    if (colon == std::string::npos || colon < 6) throw Error("--bind " + control + ": a tcp address needs :PORT");
    const std::string port = control.substr(colon + 1);
    if (port == "*") return control;
    try {
      std::size_t used = 0;
      const int p = std::stoi(port, &used);
      if (used != port.size() || p <= 0 || p + offset > 65535) throw std::invalid_argument(port);
      return control.substr(0, colon + 1) + std::to_string(p + offset);
    } catch (const std::exception&) {
      throw Error("--bind " + control + ": port '" + port + "' is not a number in 1.." +
                  std::to_string(65535 - offset) + " or *");
    }
  }
  if (control.rfind("ipc://", 0) == 0) return control + "." + suffix;
  if (control.rfind("inproc://", 0) == 0) return control + "-" + suffix;
  throw Error("--bind " + control + ": expected tcp://HOST:PORT, ipc://PATH or inproc://NAME");
}
}  // namespace

std::string derive_pose_endpoint(const std::string& control) { return derive_endpoint(control, 1, "pose"); }
std::string derive_stream_endpoint(const std::string& control) { return derive_endpoint(control, 2, "stream"); }

bool is_loopback_endpoint(const std::string& e) {
  auto starts = [&](const char* p) { return e.rfind(p, 0) == 0; };
  return starts("ipc://") || starts("inproc://") || starts("tcp://127.") || starts("tcp://localhost:") ||
         starts("tcp://[::1]:") || starts("tcp://lo:");
}

// the pose socket's context, with one I/O thread under SCHED_FIFO at `priority` where this
// process may (probed first: libzmq aborts when it cannot apply the policy it was given);
// `fifo` is set to the priority given, or 0 when the threads keep the normal policy
zmq::context_t pose_context(int priority, int& fifo) {
  zmq::context_t c(1);
  fifo = priority > 0 && priority <= 99 && may_raise_threads(priority) ? priority : 0;
  if (fifo) {
    c.set(zmq::ctxopt::thread_sched_policy, SCHED_FIFO);
    c.set(zmq::ctxopt::thread_priority, fifo);
  }
  return c;
}

// the control thread: sockets, world ownership, control requests, housekeeping
class Server::Control {
 public:
  Control(ServerShared& sh, const Scene& scene, PatientPtr patient, PatientLoader loader, const ServerOptions& o)
      : sh_(sh), loader_(std::move(loader)), opt_(o), paths_(o.scene_dirs), ctx_(1),
        pose_ctx_(pose_context(o.pose_priority, pose_fifo_)), control_(ctx_, zmq::socket_type::router),
        pose_(pose_ctx_, zmq::socket_type::router), load_done_rx_(ctx_, zmq::socket_type::pair),
        load_done_tx_(ctx_, zmq::socket_type::pair), in_(kMaxControlBytes + 1) {
    start_ = Clock::now();
    sh_.max_pose_distance_mm = o.max_pose_distance_mm;
    if (o.pose_priority < 0 || o.pose_priority > 99)
      throw Error("--pose-priority " + std::to_string(o.pose_priority) + ": expected 0 (the normal policy) to 99");
    if (pose_fifo_)
      spdlog::info("poses: the pose thread and its I/O thread under SCHED_FIFO, priority {}", pose_fifo_);
    else if (o.pose_priority > 0)
      spdlog::info("poses: the pose thread under the normal policy: this process may not use SCHED_FIFO (it needs "
                   "root or CAP_SYS_NICE; --pose-priority 0 asks for the normal policy)");
    if (o.max_sessions_per_client < 1 || o.max_sessions_per_client > kMaxSlots)
      throw Error("--max-sessions-per-client " + std::to_string(o.max_sessions_per_client) + ": expected 1.." +
                  std::to_string(kMaxSlots));
    if (!(o.idle_timeout_s >= 0 && o.idle_timeout_s <= 1e6))
      throw Error("--idle-timeout-s " + std::to_string(o.idle_timeout_s) + ": expected 0 (never) to 1e6 s");
    // the loader thread's word that a LoadScene has finished, on the control thread's poll
    for (zmq::socket_t* s : {&load_done_rx_, &load_done_tx_}) s->set(zmq::sockopt::linger, 0);
    const std::string done = "inproc://palpsim-load-done-" + hex_id(std::uint64_t(reinterpret_cast<std::uintptr_t>(this)));
    load_done_rx_.bind(done);
    load_done_tx_.connect(done);
    // CURVE: the ZAP handler binds first, so no connection is ever admitted without it
    if (!o.curve_secret_key.empty()) {
      if (o.curve_allowed_keys.empty())
        throw Error("--allow: no client keys; with --curve-secret the server admits only the keys it lists");
      curve_.secret_key = o.curve_secret_key;
      curve_.allowed = std::make_shared<const AllowList>(o.curve_allowed_keys.begin(), o.curve_allowed_keys.end());
      zap_ = std::make_unique<ZapHandler>(ctx_, curve_.allowed, sh_.counters.curve_refused, sh_.counters.curve_admitted);
      pose_zap_ = std::make_unique<ZapHandler>(pose_ctx_, curve_.allowed, sh_.counters.curve_refused,
                                               sh_.counters.curve_admitted);
      for (zmq::socket_t* s : {&control_, &pose_}) make_curve_server(*s, o.curve_secret_key);
      sh_.curve = true;
    } else if (!o.curve_allowed_keys.empty()) {
      throw Error("--allow needs --curve-secret: without a server key nothing is encrypted or checked");
    }
    current_ = make_world(scene, std::move(patient), 1);
    sh_.world.store(current_.get(), std::memory_order_release);
    warn_quota();
    for (zmq::socket_t* s : {&control_, &pose_}) {
      s->set(zmq::sockopt::linger, 0);
      s->set(zmq::sockopt::maxmsgsize, kMaxFrameBytes);
      s->set(zmq::sockopt::sndhwm, 10000);
      s->set(zmq::sockopt::rcvhwm, 10000);
    }
    // plain text beyond this machine only when the operator says so
    if (!o.insecure && !sh_.curve) {
      const std::pair<std::string, const char*> addrs[] = {
          {o.control_bind, "--bind"},
          {o.pose_bind.empty() ? derive_pose_endpoint(o.control_bind) : o.pose_bind, "--pose-bind"},
          {o.stream_bind.empty() ? derive_stream_endpoint(o.control_bind) : o.stream_bind, "--stream-bind"}};
      for (const auto& [addr, option] : addrs)
        if (!is_loopback_endpoint(addr))
          throw Error(std::string(option) + " " + addr +
                      ": not a loopback address; without keys this server speaks without encryption or "
                      "authentication, so it binds beyond this machine only with --curve-secret and --allow "
                      "(README, \"Security\") or with --insecure (for a trusted network)");
    }
    control_endpoint_ = bind(control_, o.control_bind, "--bind");
    pose_endpoint_ = bind(pose_, o.pose_bind.empty() ? derive_pose_endpoint(o.control_bind) : o.pose_bind,
                          "--pose-bind");
  }

  ~Control() { end_load(); }

  Clock::time_point start() const { return start_; }

  // starts the deformation worker when the scene being served asks for chainmail
  // (throws the worker's set-up error); with none asked for, nothing is built
  void start_deform() {
    if (current_->scene.effects.chainmail && !deform_) {
      auto w = std::make_unique<DeformWorker>(sh_, start_, opt_.deform_nice, opt_.background_idle,
                                              opt_.deform_concurrency, opt_.deform_batch);
      w->start();
      deform_ = std::move(w);
      deform_ptr_.store(deform_.get(), std::memory_order_release);
    }
  }
  // stops it (its engines are destroyed on its own thread)
  void stop_deform() {
    if (deform_) deform_->stop();
  }

  // the publisher and the render thread as the scene being served asks: started for
  // frames or bricks (the render thread for frames only), stopped for a scene without
  // them. Throws when they cannot be started (the start of the server refuses the scene).
  void sync_stream() {
    const Scene& sc = current_->scene;
    if (!sc.effects.frames && render_) {
      render_->stop();
      render_.reset();
    }
    if (!sc.effects.frames && !sc.effects.bricks) {
      stop_stream();
      return;
    }
    if (!stream_) {
      stream_ = std::make_unique<StreamState>();
      sh_.stream.store(stream_.get(), std::memory_order_release);
    }
    if (!publisher_) {
      auto p = std::make_unique<StreamPublisher>(
          sh_, *stream_, opt_.stream_bind.empty() ? derive_stream_endpoint(opt_.control_bind) : opt_.stream_bind, start_,
          curve_);
      p->start();
      publisher_ = std::move(p);
      std::lock_guard<std::mutex> lock(stream_endpoint_mu_);
      stream_endpoint_ = publisher_->endpoint();
      spdlog::info("frames and bricks are published on {}", publisher_->endpoint());
    }
    if (sc.effects.frames && !render_) {
      auto r = std::make_unique<RenderWorker>(sh_, *stream_, start_, opt_.deform_nice, opt_.background_idle);
      r->start();
      render_ = std::move(r);
    }
  }
  // stops both (GL objects are destroyed on the render thread)
  void stop_stream() {
    if (render_) render_->stop();
    render_.reset();
    if (publisher_) publisher_->stop();
    publisher_.reset();
    std::lock_guard<std::mutex> lock(stream_endpoint_mu_);
    stream_endpoint_.clear();
  }
  bool frames_served() const {
    if (!render_ || !stream_) return false;
    std::lock_guard<std::mutex> lock(stream_->info_mu);
    return !stream_->info.jpeg_encoder.empty();
  }
  bool bricks_served() const { return publisher_ && current_->scene.effects.bricks; }
  DeformWorker* deform() const { return deform_ptr_.load(std::memory_order_acquire); }
  // the publisher's address ("" without one); read by other threads after start()
  std::string stream_endpoint() const {
    std::lock_guard<std::mutex> lock(stream_endpoint_mu_);
    return stream_endpoint_;
  }
  zmq::socket_t& pose_socket() { return pose_; }
  // the SCHED_FIFO priority the pose thread is to take (0: the normal policy)
  int pose_fifo() const { return pose_fifo_; }
  const std::string& control_endpoint() const { return control_endpoint_; }
  const std::string& pose_endpoint() const { return pose_endpoint_; }

  void close() {
    end_load();
    control_.close();
    pose_.close();
    load_done_rx_.close();
    load_done_tx_.close();
  }

  // waits for a running LoadScene's loader thread (after the control thread has ended);
  // its reply is not sent
  void end_load() {
    if (load_ && load_->thread.joinable()) load_->thread.join();
    load_.reset();
  }

  void run() {
    zmq::pollitem_t items[] = {{control_.handle(), 0, ZMQ_POLLIN, 0}, {load_done_rx_.handle(), 0, ZMQ_POLLIN, 0}};
    last_log_ = Clock::now();
    while (!sh_.stop.load()) {
      zmq::poll(items, 2, std::chrono::milliseconds(opt_.housekeeping_ms));
      if (items[1].revents & ZMQ_POLLIN) finish_load();
      if (items[0].revents & ZMQ_POLLIN) drain();
      housekeeping();
    }
  }

 private:
  ServerShared& sh_;
  PatientLoader loader_;
  ServerOptions opt_;
  PathPolicy paths_;  // the folders LoadScene may touch
  int pose_fifo_ = 0;  // SCHED_FIFO priority of the pose path's threads (0: the normal policy)
  zmq::context_t ctx_;
  zmq::context_t pose_ctx_;  // the pose socket's alone: its I/O thread serves poses only
  zmq::socket_t control_, pose_;
  zmq::socket_t load_done_rx_, load_done_tx_;  // inproc PAIR: the loader thread (tx) wakes the control thread (rx)
  CurveServer curve_;                 // the server key and the allow-list ("" key: plain text)
  std::unique_ptr<ZapHandler> zap_;   // admits connections to ctx_'s sockets (CURVE only)
  std::unique_ptr<ZapHandler> pose_zap_;  // and to pose_ctx_'s
  std::string requester_;             // who sent the control request being handled (see identity())
  zmq::message_t* requester_id_ = nullptr;  // its routing id, and whether it came in a REQ's envelope
  bool requester_req_ = false;
  bool deferred_ = false;             // the request being handled is answered later (a LoadScene that started)
  std::string requester_key_;         // its z85 CURVE key ("" without CURVE)
  std::string control_endpoint_, pose_endpoint_;
  Clock::time_point start_;
  std::uint64_t id_counter_opened_ = 0;
  std::random_device random_;                   // session ids (getrandom on Linux)
  std::array<std::uint64_t, kMaxSlots> last_id_{};  // each slot's latest session id
  std::unique_ptr<World> current_;
  std::vector<std::unique_ptr<World>> retired_;  // old worlds the pose thread may still read
  std::vector<char> in_;
  v1::ControlRequest req_;
  v1::ControlReply rep_;
  std::string out_;
  Clock::time_point last_log_;
  std::uint64_t logged_bad_ = 0;
  std::unique_ptr<DeformWorker> deform_;           // (control) the deformation worker, once a scene asked for it
  std::atomic<DeformWorker*> deform_ptr_{nullptr}; // the same, for readers on other threads
  // frames and bricks: the shared state (kept once made), the publisher and the render thread
  std::unique_ptr<StreamState> stream_;
  std::unique_ptr<StreamPublisher> publisher_;
  std::unique_ptr<RenderWorker> render_;
  mutable std::mutex stream_endpoint_mu_;          // guards stream_endpoint_ (control writes, anyone reads)
  std::string stream_endpoint_;
  std::vector<std::uint64_t> opened_order_ = std::vector<std::uint64_t>(kMaxSlots);  // per slot: when opened
  // a LoadScene being prepared on its loader thread; its request is answered when it ends
  struct Load {
    std::thread thread;
    zmq::message_t routing_id;      // whom to answer, and how (a REQ's envelope or not)
    bool req_envelope = false;
    std::uint64_t request_id = 0;
    std::string what;               // the path asked for, or "scene text" (made safe for logs)
    Clock::time_point started;
    std::unique_ptr<World> world;   // (loader) the world made, its generation not yet set; or
    std::string error;              // (loader) why the scene was refused
  };
  std::unique_ptr<Load> load_;      // (control) the running load, or none

  std::string bind(zmq::socket_t& s, const std::string& addr, const char* option) {
    try {
      s.bind(addr);
    } catch (const zmq::error_t& e) {
      throw Error(std::string(option) + " " + addr + ": cannot bind: " + e.what());
    }
    return s.get(zmq::sockopt::last_endpoint);
  }

  const World& world() const { return *current_; }

  // the slot of an open session, or nullptr
  SessionSlot* find(std::uint64_t id) {
    if (id == 0) return nullptr;
    SessionSlot& s = sh_.slots[id & (kMaxSlots - 1)];
    return s.id.load(std::memory_order_acquire) == id ? &s : nullptr;
  }

  void drain() {
    for (;;) {
      zmq::message_t id;
      if (!control_.recv(id, zmq::recv_flags::dontwait)) return;
      // frames after the routing id: [payload] (DEALER) or [empty, payload] (REQ)
      std::vector<std::size_t> sizes;
      std::size_t kept = 0;
      std::string user;  // with CURVE: the sender's key, a property of its payload frames
      while (control_.get(zmq::sockopt::rcvmore)) {
        zmq::message_t part;
        (void)control_.recv(part);
        sizes.push_back(part.size());
        kept = std::min(part.size(), in_.size());
        std::memcpy(in_.data(), part.data(), kept);
        const char* u = sh_.curve ? zmq_msg_gets(part.handle(), "User-Id") : nullptr;
        if (u) user = u;
      }
      // a REQ's envelope is an empty frame with more after it; the reply echoes it, and any
      // other request, malformed ones included, gets exactly one frame (a lone empty frame too)
      const bool req_envelope = sizes.size() >= 2 && sizes[0] == 0;
      rep_.Clear();
      deferred_ = false;
      rep_.set_schema_version(v1::VERSION_CURRENT);
      sh_.counters.control_requests.fetch_add(1);
      if (!((sizes.size() == 1 && sizes[0] > 0) || (sizes.size() == 2 && req_envelope))) {
        refuse(v1::ERROR_MALFORMED, sh_.counters.malformed,
               "ControlRequest: expected one frame (DEALER) or an empty delimiter and one frame (REQ)");
      } else if (sizes.back() > kMaxControlBytes) {
        refuse(v1::ERROR_OVERSIZED, sh_.counters.oversized,
               "ControlRequest: " + std::to_string(sizes.back()) + " bytes, over the control path's limit of " +
                   std::to_string(kMaxControlBytes) + " bytes");
      } else if (!req_.ParseFromArray(in_.data(), int(kept))) {
        refuse(v1::ERROR_MALFORMED, sh_.counters.malformed,
               "ControlRequest: " + std::to_string(kept) + " bytes do not parse (truncated, or not a ControlRequest)");
      } else if (sh_.curve && user.size() != kZ85KeyLength) {
        // cannot happen with the ZAP handler in place; refused rather than served as nobody
        refuse(v1::ERROR_INTERNAL, sh_.counters.internal_errors,
               "ControlRequest: a CURVE connection without the key its ZAP handler names");
      } else {
        requester_ = identity(id, user);
        requester_id_ = &id;
        requester_req_ = req_envelope;
        handle();
        requester_id_ = nullptr;
      }
      if (!deferred_) send_reply(id, req_envelope);
    }
  }

  // sends rep_ to `routing_id` (after an empty delimiter for a REQ); never blocks
  void send_reply(const zmq::message_t& routing_id, bool req_envelope) {
    rep_.SerializeToString(&out_);
    try {
      control_.send(zmq::const_buffer(routing_id.data(), routing_id.size()),
                    zmq::send_flags::sndmore | zmq::send_flags::dontwait);
      if (req_envelope) control_.send(zmq::const_buffer(nullptr, 0), zmq::send_flags::sndmore | zmq::send_flags::dontwait);
      control_.send(zmq::const_buffer(out_.data(), out_.size()), zmq::send_flags::dontwait);
    } catch (const zmq::error_t&) {
      // the client is gone
    }
  }

  // who sent the request being handled: its CURVE key (the ZAP handler's user id), else
  // its client token, else its control connection (the ROUTER's routing id)
  std::string identity(const zmq::message_t& routing_id, const std::string& user) {
    requester_key_.clear();
    if (sh_.curve) {
      requester_key_ = user;
      return "key " + requester_key_;
    }
    if (!req_.client_token().empty()) return "token " + req_.client_token();
    return "connection " + routing_id.to_string();
  }

  // true when the requester opened session `s`; else refuses with ERROR_NOT_OWNER
  bool owned(const SessionSlot& s, std::uint64_t id, const std::string& field) {
    if (s.owner == requester_) return true;
    refuse(v1::ERROR_NOT_OWNER, sh_.counters.not_owner,
           field + ": " + hex_id(id) + " belongs to another client; only " +
               (sh_.curve ? "the key that opened it" : "the client token or control connection that opened it") +
               " may act on it or watch it");
    return false;
  }

  void refuse(v1::ErrorCode code, std::atomic<std::uint64_t>& counter, const std::string& message) {
    // the message may embed client strings from deeper down (a scene's ct_path in a prep
    // error): escaped and cut once more as a whole
    const std::string safe = client_text(message, kMaxErrorChars);
    rep_.clear_body();
    rep_.mutable_error()->set_code(code);
    rep_.mutable_error()->set_message(safe);
    counter.fetch_add(1);
    spdlog::warn("control: {} ({})", safe, v1::ErrorCode_Name(code));
  }

  void handle() {
    rep_.set_request_id(req_.request_id());
    if (req_.schema_version() != v1::VERSION_CURRENT)
      return refuse(v1::ERROR_WRONG_SCHEMA_VERSION, sh_.counters.wrong_schema_version,
                    "ControlRequest.schema_version: got " + std::to_string(req_.schema_version()) +
                        ", this server speaks " + std::to_string(int(v1::VERSION_CURRENT)));
    if (req_.client_token().size() > kMaxClientTokenBytes)
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                    "ControlRequest.client_token: " + std::to_string(req_.client_token().size()) +
                        " bytes, at most " + std::to_string(kMaxClientTokenBytes));
    try {
      switch (req_.body_case()) {
        case v1::ControlRequest::kOpen: return open();
        case v1::ControlRequest::kClose: return close_session();
        case v1::ControlRequest::kReset: return reset();
        case v1::ControlRequest::kSetParameter: return set_parameter();
        case v1::ControlRequest::kStats: return stats();
        case v1::ControlRequest::kLoadScene: return load_scene();
        case v1::ControlRequest::kInfo: return fill_info(rep_.mutable_info());
        case v1::ControlRequest::kWatch: return watch();
        case v1::ControlRequest::kPick: return pick();
        case v1::ControlRequest::BODY_NOT_SET:
          return refuse(v1::ERROR_EMPTY_REQUEST, sh_.counters.empty_request,
                        "ControlRequest: no body set (open, close, reset, set_parameter, stats, load_scene, info, watch "
                        "or pick)");
      }
    } catch (const std::exception& e) {
      return refuse(v1::ERROR_INTERNAL, sh_.counters.internal_errors, std::string("ControlRequest: ") + e.what());
    }
  }

  // the slot of an open session the requester owns, or nullptr after refusing; its last
  // message time is updated, and with `use` (a request acting on it, not Stats) its idle clock
  SessionSlot* session_or_refuse(std::uint64_t id, const char* field, bool use = true) {
    SessionSlot* s = find(id);
    if (!s) {
      refuse(v1::ERROR_UNKNOWN_SESSION, sh_.counters.unknown_session,
             std::string(field) + ": " + hex_id(id) + " is not an open session (never opened, closed, or timed out)");
      return nullptr;
    }
    if (!owned(*s, id, field)) return nullptr;
    const std::int64_t now = ns_since(start_);
    s->last_seen_ns.store(now);
    if (use) s->last_used_ns.store(now);
    return s;
  }

  void fill_info(v1::ServerInfo* info) {
    const World& w = world();
    const Patient& p = *w.patient;
    info->set_scene_name(w.scene.name);
    info->set_scene_file(client_text(w.scene.file, kMaxErrorChars));
    info->set_scene_generation(w.generation);
    auto* pi = info->mutable_patient();
    pi->set_source(p.source);
    pi->set_size_i(p.grid.size.x);
    pi->set_size_j(p.grid.size.y);
    pi->set_size_k(p.grid.size.z);
    pi->set_spacing_mm(p.grid.spacing_mm.x);
    set_vec(pi->mutable_origin_mm(), p.grid.origin_mm);
    set_vec(pi->mutable_bounds_min_mm(), w.bounds_min_mm);
    set_vec(pi->mutable_bounds_max_mm(), w.bounds_max_mm);
    set_vec(pi->mutable_body_min_mm(), w.body_min_mm);
    set_vec(pi->mutable_body_max_mm(), w.body_max_mm);
    pi->set_has_bone(p.has_bone);
    info->set_control_endpoint(control_endpoint_);
    info->set_pose_endpoint(pose_endpoint_);
    info->set_session_timeout_s(w.scene.server.session_timeout_s);
    info->set_max_sessions(w.scene.server.max_sessions);
    info->set_max_pose_distance_mm(sh_.max_pose_distance_mm);
    info->set_max_pose_bytes(kMaxPoseBytes);
    info->set_max_control_bytes(kMaxControlBytes);
    DeformServerReport d;
    if (deform_) d = deform_->server_report();
    for (const auto& s : stages_of(w.scene, deform_ ? &d : nullptr, frames_served(), bricks_served()))
      info->add_stages(s);
    info->set_stream_endpoint(publisher_ ? publisher_->endpoint() : "");
    info->set_curve(sh_.curve);
    info->set_max_sessions_per_client(std::uint32_t(opt_.max_sessions_per_client));
    info->set_idle_timeout_s(opt_.idle_timeout_s);
    info->set_scene_loading(load_ ? load_->what : "");
  }

  int open_count() const {
    int n = 0;
    for (const auto& s : sh_.slots) n += s.id.load(std::memory_order_relaxed) != 0;
    return n;
  }

  // how the requester is known, for messages (its key, token or connection is not echoed)
  const char* requester_kind() const {
    return sh_.curve ? "CURVE key" : requester_.rfind("token ", 0) == 0 ? "client token" : "control connection";
  }

  void open() {
    // one client holds at most its quota, so that it cannot take every session
    int mine = 0;
    for (int i = 0; i < sh_.slots_used.load(std::memory_order_relaxed); ++i)
      mine += sh_.slots[i].id.load(std::memory_order_relaxed) != 0 && sh_.slots[i].owner == requester_;
    if (mine >= opt_.max_sessions_per_client)
      return refuse(v1::ERROR_SESSION_QUOTA, sh_.counters.session_quota,
                    "OpenSession: this client (its " + std::string(requester_kind()) + ") already holds " +
                        std::to_string(mine) + " sessions, the most one client may hold open at once "
                        "(palpsim-server --max-sessions-per-client); close one first");
    const int limit = std::min(world().scene.server.max_sessions, kMaxSlots);
    SessionSlot* free_slot = nullptr;
    int index = 0;
    for (int i = 0; i < kMaxSlots && !free_slot; ++i)
      if (sh_.slots[i].id.load(std::memory_order_relaxed) == 0) {
        free_slot = &sh_.slots[i];
        index = i;
      }
    if (!free_slot || open_count() >= limit)
      return refuse(v1::ERROR_TOO_MANY_SESSIONS, sh_.counters.too_many_sessions,
                    "OpenSession: all " + std::to_string(limit) + " sessions (scene server.max_sessions) are open");
    // a fresh id: high bits from the OS's random source, so that a client that knows
    // its own ids learns nothing of anyone else's (a counter through a fixed mix could
    // be inverted and stepped); the slot index in the low bits; never 0, and never the
    // id this slot had last (a late message of that session cannot reach the new one)
    std::uint64_t id = 0;
    while (id == 0 || id == last_id_[std::size_t(index)])
      id = (((std::uint64_t(random_()) << 32) | random_()) << kSlotBits) | std::uint64_t(index);
    last_id_[std::size_t(index)] = id;
    SessionSlot& s = *free_slot;
    s.set_params(world().scene.haptics);
    s.poses = 0;
    s.errors = 0;
    s.last_seq = 0;
    s.clamps = 0;
    s.local_models_sent = 0;
    s.local_poses = 0;
    s.elastic_counters.clear();
    s.passivity_counters.clear();
    s.renders_locally = false;
    s.contact = false;
    s.depth_mm = 0;
    s.client_name = client_text(req_.open().client_name());
    s.owner = requester_;
    s.set_owner_key(requester_key_.empty() ? nullptr : requester_key_.c_str());
    const std::int64_t now = ns_since(start_);
    s.last_seen_ns.store(now);
    s.last_used_ns.store(now);
    opened_order_[index] = ++id_counter_opened_;
    if (index >= sh_.slots_used.load(std::memory_order_relaxed))
      sh_.slots_used.store(index + 1, std::memory_order_release);
    s.id.store(id, std::memory_order_release);  // publishes the slot to the pose thread
    sh_.counters.sessions_opened.fetch_add(1);
    auto* o = rep_.mutable_open();
    o->set_session_id(id);
    o->set_pose_endpoint(pose_endpoint_);
    fill_params(o->mutable_params(), world().scene.haptics);
    fill_info(o->mutable_server());
    spdlog::info("session {} opened ({}), {} open", hex_id(id), s.client_name.empty() ? "unnamed" : s.client_name,
                 open_count());
  }

  void free_session(SessionSlot& s) { s.id.store(0, std::memory_order_release); }

  // "; deformation: ..." for a session's close or timeout log line ("" without deformation)
  std::string deform_summary(std::uint64_t id) const {
    DeformSessionReport r;
    if (!deform_ || !deform_->session_report(id, r)) return "";
    const double k = r.steps ? 1.0 / double(r.steps) : 0.0;
    char b[320];
    std::snprintf(b, sizeof b,
                  "; deformation (%s): %llu steps, mean %.2f ms (chainmail %.2f, relax %.2f, invert %.2f), %llu "
                  "contacts dropped, %llu non-converged, %llu failures",
                  r.backend.empty() ? "no contact" : r.backend.c_str(), (unsigned long long)r.steps, r.sum.total_ms * k,
                  r.sum.chainmail_ms * k, r.sum.relax_ms * k, r.sum.invert_ms * k,
                  (unsigned long long)r.contacts_dropped, (unsigned long long)r.non_converged,
                  (unsigned long long)r.failures);
    return b;
  }

  void close_session() {
    const std::uint64_t id = req_.close().session_id();
    SessionSlot* s = session_or_refuse(id, "CloseSession.session_id");
    if (!s) return;
    const std::string deformation = deform_summary(id);
    free_session(*s);
    sh_.counters.sessions_closed.fetch_add(1);
    auto* c = rep_.mutable_close();
    c->set_session_id(id);
    c->set_poses(s->poses.load());
    spdlog::info("session {} closed after {} poses{}", hex_id(id), s->poses.load(), deformation);
  }

  void reset() {
    const std::uint64_t id = req_.reset().session_id();
    SessionSlot* s = session_or_refuse(id, "ResetSession.session_id");
    if (!s) return;
    s->reset_requests.fetch_add(1, std::memory_order_release);
    rep_.mutable_reset()->set_session_id(id);
  }

  void set_parameter() {
    const auto& r = req_.set_parameter();
    SessionSlot* s = session_or_refuse(r.session_id(), "SetParameter.session_id");
    if (!s) return;
    // names and ranges come from the scene schema's Haptics message
    const auto* field = v1::Haptics::descriptor()->FindFieldByName(r.name());
    if (!field || field->cpp_type() != google::protobuf::FieldDescriptor::CPPTYPE_DOUBLE)
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                    "SetParameter.name: '" + client_text(r.name()) +
                        "' is not a haptics parameter (stiffness_n_per_mm, friction, max_force_n, "
                        "max_force_rate_n_per_s, min_gradient_norm)");
    const auto& o = field->options();
    const double lo = o.GetExtension(v1::min), hi = o.GetExtension(v1::max), v = r.value();
    if (!std::isfinite(v) || v < lo || v > hi) {
      char b[256];
      std::snprintf(b, sizeof b, "SetParameter.value: %s = %g is outside [%g, %g] %s", field->name().c_str(), v, lo, hi,
                    o.GetExtension(v1::unit).c_str());
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, b);
    }
    HapticsSettings p = s->params();
    if (r.name() == "stiffness_n_per_mm") p.stiffness_n_per_mm = v;
    else if (r.name() == "friction") p.friction = v;
    else if (r.name() == "max_force_n") p.max_force_n = v;
    else if (r.name() == "max_force_rate_n_per_s") p.max_force_rate_n_per_s = v;
    else if (r.name() == "min_gradient_norm") p.min_gradient_norm = v;
    s->set_params(p);
    auto* out = rep_.mutable_set_parameter();
    out->set_session_id(r.session_id());
    fill_params(out->mutable_params(), p);
  }

  void stats() {
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

  void fill_deform(v1::DeformSessionStats* o, const DeformSessionReport& r) {
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

  void watch() {
    const auto& r = req_.watch();
    const Scene& sc = world().scene;
    const auto not_built = [this](const std::string& m) {
      refuse(v1::ERROR_NOT_BUILT, sh_.counters.not_built, m);
    };
    if (!sc.effects.frames && !sc.effects.bricks)
      return not_built("WatchSession: scene '" + sc.name +
                       "' asks for neither frames nor bricks (effects.frames, effects.bricks): nothing is streamed");
    if (!r.frames() && !r.bricks())
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                    "WatchSession: ask for frames, bricks or both (WatchSession.frames, WatchSession.bricks)");
    if (r.frames() && !frames_served()) {
      std::string why = "scene '" + sc.name + "' asks for no frames (effects.frames)";
      if (sc.effects.frames && stream_) {
        std::lock_guard<std::mutex> lock(stream_->info_mu);
        why = stream_->info.render_note.empty() ? "the render thread is not running" : stream_->info.render_note;
      }
      return not_built("WatchSession.frames: " + why);
    }
    if (r.bricks() && !bricks_served())
      return not_built("WatchSession.bricks: scene '" + sc.name + "' asks for no bricks (effects.bricks)");
    if (r.has_hold_s() && (!std::isfinite(r.hold_s()) || r.hold_s() < 0 || r.hold_s() > 3600)) {
      char b[160];
      std::snprintf(b, sizeof b, "WatchSession.hold_s: %g is outside [0, 3600] s", r.hold_s());
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, b);
    }
    // the session: the one named, or the requester's newest open one
    std::uint64_t id = r.session_id();
    if (id == 0) {
      std::uint64_t newest = 0;
      for (int i = 0; i < sh_.slots_used.load(std::memory_order_acquire); ++i) {
        const std::uint64_t sid = sh_.slots[i].id.load(std::memory_order_acquire);
        if (sid != 0 && opened_order_[i] > newest && sh_.slots[i].owner == requester_) {
          newest = opened_order_[i];
          id = sid;
        }
      }
      if (id == 0)
        return refuse(v1::ERROR_NO_SESSION_OPEN, sh_.counters.unknown_session,
                      std::string("WatchSession.session_id: 0 (any session of this client) but none of this "
                                  "client's sessions is open; this client is known by its ") +
                          requester_kind() +
                          (sh_.curve ? ": watch with the haptic client's keys"
                           : requester_.rfind("token ", 0) == 0
                               ? ": give the haptic client the same client token"
                               : ", which opened no session: give the haptic client and this viewer the same "
                                 "--client-token (ControlRequest.client_token), or name the session"));
    }
    // a watch acts on the session (its idle clock), but is no message naming it for the
    // scene's session_timeout_s: only the session's poses and requests naming it are
    SessionSlot* watched = find(id);
    if (!watched)
      return refuse(v1::ERROR_UNKNOWN_SESSION, sh_.counters.unknown_session,
                    "WatchSession.session_id: " + hex_id(id) +
                        " is not an open session (never opened, closed, or timed out)");
    if (!owned(*watched, id, "WatchSession.session_id")) return;
    watched->last_used_ns.store(ns_since(start_));
    // the view: the session's current one with the fields this request sets
    StreamSlot& ss = stream_->slot(id);
    std::lock_guard<std::mutex> lock(ss.mu);
    if (ss.watch.session_id != id) {
      ss.watch = WatchSettings{};
      ss.watch.session_id = id;
      ss.watch.view = default_view(sc.render);
    }
    render::ViewSettings v = ss.watch.view;
    if (r.has_view()) {
      const std::string bad = apply_view(r.view(), v);
      if (!bad.empty())
        return refuse(v1::ERROR_BAD_VIEW, sh_.counters.bad_view, "WatchSession.view: " + bad);
    }
    if (r.brick_encoding() != v1::BRICK_INT16 && r.brick_encoding() != v1::BRICK_FLOAT32)
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                    "WatchSession.brick_encoding: " + std::to_string(r.brick_encoding()) +
                        " is not BRICK_INT16 (0) or BRICK_FLOAT32 (1)");
    if (r.brick_compression() != v1::COMPRESSION_NONE && r.brick_compression() != v1::COMPRESSION_ZSTD)
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                    "WatchSession.brick_compression: " + std::to_string(r.brick_compression()) +
                        " is not COMPRESSION_NONE (0) or COMPRESSION_ZSTD (1)");
    ss.watch.view = v;
    ++ss.watch.view_version;
    const double now = ns_since(start_) * 1e-9;
    // a hold is set (or ended with 0) only by a request that names one
    if (r.has_hold_s() && r.frames()) ss.watch.frames_hold_until_s = now + r.hold_s();
    if (r.has_hold_s() && r.bricks()) ss.watch.bricks_hold_until_s = now + r.hold_s();
    if (r.bricks()) {
      ss.watch.brick_float32 = r.brick_encoding() == v1::BRICK_FLOAT32;
      ss.watch.brick_zstd = r.brick_compression() == v1::COMPRESSION_ZSTD;
    }
    auto* o = rep_.mutable_watch();
    o->set_session_id(id);
    o->set_stream_endpoint(publisher_->endpoint());
    if (r.frames()) o->set_frame_topic(frame_topic(id));
    if (r.bricks()) o->set_brick_topic(brick_topic(id));
    fill_view(o->mutable_view(), v);
    o->set_brick_encoding(ss.watch.brick_float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16);
    o->set_brick_compression(ss.watch.brick_zstd ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE);
  }

  // the skin point under a pixel of a session's frame: its view's ray, first body hit
  void pick() {
    const auto& r = req_.pick();
    SessionSlot* s = session_or_refuse(r.session_id(), "PickRequest.session_id");
    if (!s) return;
    const World& w = world();
    const std::uint64_t id = r.session_id();
    // the view its frames are rendered with: the watched one, else the scene's
    render::ViewSettings v = default_view(w.scene.render);
    if (stream_) {
      StreamSlot& ss = stream_->slot(id);
      std::lock_guard<std::mutex> lock(ss.mu);
      if (ss.watch.session_id == id) v = ss.watch.view;
    }
    const render::Camera cam = [&] {
      Contact c;
      s->latest.read(c);
      const bool has_tip = c.session_id == id && c.seq != 0;
      return render::orbit_camera(w.patient->grid, v, render::frame_target(v, has_tip, c.tip_mm, w.body_center_mm));
    }();
    const auto dir = render::pixel_ray(cam, r.x_px(), r.y_px());
    if (!dir) {
      char b[320];
      std::snprintf(b, sizeof b,
                    "PickRequest.x_px, y_px: (%g, %g) is outside the frame's 3D view, pixels 0..%d x 0..%d of a "
                    "%d x %d frame (the slice column starts at x = %d)",
                    r.x_px(), r.y_px(), cam.view_w, v.height, v.width, v.height, cam.view_w);
      return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, b);
    }
    auto* o = rep_.mutable_pick();
    o->set_session_id(id);
    set_vec(o->mutable_ray_origin_mm(), cam.eye);
    set_vec(o->mutable_ray_direction(), *dir);
    fill_view(o->mutable_view(), v);
    if (const auto hit = render::first_body_hit(*w.patient, cam.eye, *dir)) {
      o->set_hit(true);
      set_vec(o->mutable_point_mm(), *hit);
      o->set_distance_mm(norm(*hit - cam.eye));
    }
  }

  // frames and bricks in the stats: server-wide, and one session's
  void fill_stream(v1::ServerStats* s, google::protobuf::RepeatedPtrField<v1::StageInfo>* stages) {
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

  void fill_session_stream(v1::SessionStats* out, std::uint64_t id) {
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

  // LoadScene: refused at once while another runs; else the scene is read, checked and its
  // patient prepared on a loader thread (prepare_world) and the request answered when that
  // ends (finish_load), so that every other control request is answered meanwhile
  void load_scene() {
    const auto& r = req_.load_scene();
    if (load_) {
      char b[64];
      std::snprintf(b, sizeof b, "%.1f", std::chrono::duration<double>(Clock::now() - load_->started).count());
      return refuse(v1::ERROR_LOAD_RUNNING, sh_.counters.load_running,
                    "LoadScene: refused: another LoadScene is running (" + load_->what + ", for " + b +
                        " s); send it again when ServerInfo.scene_loading is empty");
    }
    auto l = std::make_unique<Load>();
    l->routing_id.copy(*requester_id_);
    l->req_envelope = requester_req_;
    l->request_id = req_.request_id();
    l->what = r.path().empty() ? std::string("scene text") : client_text(r.path());
    l->started = Clock::now();
    Load* job = l.get();
    l->thread = std::thread([this, job, path = r.path(), text = r.text()] { prepare_world(*job, path, text); });
    load_ = std::move(l);
    deferred_ = true;
  }

  // (loader thread) the world of a LoadScene's scene, or why it is refused, into `l`; then
  // wakes the control thread. Reads only what no other thread writes (options, folders, loader).
  void prepare_world(Load& l, const std::string& path, const std::string& text) {
    // at the control thread's own priority: a background (SCHED_IDLE or nice 19) loader
    // would starve on a busy host, and a scene load is an operator's request that must end
    name_this_thread("palpsim-load");
    const std::string& what = l.what;
    try {
      if (path.empty() == text.empty())
        throw Error("LoadScene: set exactly one of path or text");
      // no file outside the operator's folders is read or written for a client
      auto allowed = [&](const std::string& p, const std::string& field) {
        const std::string why = paths_.check(p, "LoadScene: " + field);
        if (!why.empty()) throw Error(why);
      };
      // the scene file: a regular file inside them, judged after its links are resolved
      Scene scene = path.empty() ? parse_scene_text(text, "") : load_scene_file(paths_.resolve(path, "LoadScene: path"));
      // its name is the client's string, shown in logs, replies and frames
      scene.name = client_text(scene.name);
      if (!scene.use_phantom) allowed(scene.ct_path, what + ": ct_path");
      if (!scene.prep.cache_dir.empty())
        throw Error("LoadScene: " + what + ": prep.cache_dir is the operator's setting (palpsim-server --cache-dir, "
                    "PALPSIM_CACHE); a client's scene cannot choose the cache folder");
      if (!scene.render.record_dir.empty()) allowed(scene.render.record_dir, what + ": render.record_dir");
      // deformation settings no backend can serve refuse the scene before its patient is made
      if (scene.effects.chainmail) {
        check_deform_config(DeformConfig::from_scene(scene), "LoadScene: " + what);
        std::string why;
        if (scene.deform.backend == DeformBackendChoice::kCuda && !cuda_deform_available(&why))
          throw Error("LoadScene: " + what + ": deform.backend = \"cuda\" is not available here: " + why);
      }
      spdlog::info("loading scene '{}' from {} (poses and control requests keep being served on the old one)",
                   scene.name, what);
      PatientPtr patient = loader_(scene);
      if (!patient) throw Error("LoadScene: " + what + ": the loader returned no patient");
      l.world = make_world(scene, std::move(patient), 0);
    } catch (const std::exception& e) {
      l.error = e.what();
    } catch (...) {
      l.error = "LoadScene: " + what + ": an unknown error";
    }
    (void)load_done_tx_.send(zmq::const_buffer(nullptr, 0), zmq::send_flags::dontwait);
  }

  // answers the LoadScene whose loader thread has ended: its world is served from now on,
  // or the refusal is sent and the old one kept
  void finish_load() {
    zmq::message_t done;
    (void)load_done_rx_.recv(done, zmq::recv_flags::dontwait);
    if (!load_) return;
    const std::unique_ptr<Load> l = std::move(load_);
    l->thread.join();
    rep_.Clear();
    rep_.set_schema_version(v1::VERSION_CURRENT);
    rep_.set_request_id(l->request_id);
    if (!l->world) {
      refuse(v1::ERROR_SCENE_LOAD_FAILED, sh_.counters.scene_load_failures,
             std::string("LoadScene: refused, still serving '") + current_->scene.name + "': " + l->error);
      return send_reply(l->routing_id, l->req_envelope);
    }
    std::unique_ptr<World> next = std::move(l->world);
    next->generation = current_->generation + 1;
    sh_.world.store(next.get(), std::memory_order_release);
    retired_.push_back(std::move(current_));
    current_ = std::move(next);
    sh_.counters.scene_loads.fetch_add(1);
    spdlog::info("now serving scene {} (generation {})", scene_label(current_->scene), current_->generation);
    warn_quota();
    // a running worker picks the new scene up itself; the first scene that asks for
    // deformation starts one (settings were checked above; a failure past them, such as
    // a device out of memory, leaves the scene served with haptics only)
    try {
      start_deform();
    } catch (const std::exception& e) {
      spdlog::error("scene {}: {}; serving haptics only", scene_label(current_->scene), e.what());
    }
    // frames and bricks likewise: a render thread that cannot start leaves the scene without frames
    try {
      sync_stream();
    } catch (const std::exception& e) {
      spdlog::error("scene {}: {}; no frames are served", scene_label(current_->scene), e.what());
    }
    fill_info(rep_.mutable_load_scene()->mutable_server());
    send_reply(l->routing_id, l->req_envelope);
  }

  // says so when one client may hold every session of the scene being served
  void warn_quota() const {
    const int most = current_->scene.server.max_sessions;
    if (most > 1 && opt_.max_sessions_per_client >= most)
      spdlog::warn("--max-sessions-per-client {} is not below scene '{}''s server.max_sessions {}: one client can "
                   "hold every session",
                   opt_.max_sessions_per_client, current_->scene.name, most);
  }

  void housekeeping() {
    const std::int64_t now = ns_since(start_);
    // sessions silent for longer than the scene's timeout, or idle (no pose, no control
    // request acting on them: Stats does not count) for longer than the server's, are freed
    const auto timeout_ns = std::int64_t(world().scene.server.session_timeout_s * 1e9);
    const std::int64_t idle_ns =
        opt_.idle_timeout_s > 0 ? std::int64_t(opt_.idle_timeout_s * 1e9) : std::numeric_limits<std::int64_t>::max();
    for (auto& s : sh_.slots) {
      const std::uint64_t id = s.id.load(std::memory_order_relaxed);
      if (id == 0) continue;
      const bool silent = now - s.last_seen_ns.load(std::memory_order_relaxed) > timeout_ns;
      if (!silent && now - s.last_used_ns.load(std::memory_order_relaxed) <= idle_ns) continue;
      const std::string deformation = deform_summary(id);
      free_session(s);
      if (silent) {
        sh_.counters.sessions_timed_out.fetch_add(1);
        spdlog::warn("session {} timed out after {:.2f} s without a message; freed{}", hex_id(id),
                     world().scene.server.session_timeout_s, deformation);
      } else {
        sh_.counters.sessions_idle_timed_out.fetch_add(1);
        spdlog::warn("session {} ({}) freed after {:g} s without a pose or a control request acting on it "
                     "(--idle-timeout-s; Stats does not count){}",
                     hex_id(id), s.client_name, opt_.idle_timeout_s, deformation);
      }
    }
    // worlds older than the ones the pose thread and the deformation worker have picked up are no longer read
    const std::uint64_t seen = std::min({sh_.seen_generation.load(std::memory_order_acquire),
                                         sh_.deform_seen_generation.load(std::memory_order_acquire),
                                         sh_.render_seen_generation.load(std::memory_order_acquire),
                                         sh_.publish_seen_generation.load(std::memory_order_acquire),
                                         sh_.patch_seen_generation.load(std::memory_order_acquire)});
    retired_.erase(std::remove_if(retired_.begin(), retired_.end(),
                                  [seen](const std::unique_ptr<World>& w) { return w->generation < seen; }),
                   retired_.end());
    // a summary of new bad pose input (the pose thread does not log)
    if (std::chrono::duration<double>(Clock::now() - last_log_).count() >= opt_.bad_input_log_period_s) {
      last_log_ = Clock::now();
      const auto& c = sh_.counters;
      const std::uint64_t bad = c.malformed + c.wrong_schema_version + c.unknown_session + c.bad_pose + c.absurd_pose +
                                c.oversized + c.not_owner + c.curve_refused;
      if (bad != logged_bad_) {
        spdlog::warn(
            "bad input so far: {} malformed, {} wrong schema version, {} unknown session, {} NaN/Inf poses, {} absurd "
            "poses, {} oversized, {} for another client's session, {} connections refused by key ({} new; {} pose "
            "messages left unanswered past their connection's allowance of error replies)",
            c.malformed.load(), c.wrong_schema_version.load(), c.unknown_session.load(), c.bad_pose.load(),
            c.absurd_pose.load(), c.oversized.load(), c.not_owner.load(), c.curve_refused.load(), bad - logged_bad_,
            c.bad_input_unanswered.load());
        logged_bad_ = bad;
      }
    }
  }
};

Server::Server(const Scene& scene, PatientPtr patient, PatientLoader loader, const ServerOptions& options)
    : shared_(std::make_unique<ServerShared>()) {
  if (!patient) throw Error("Server: no patient for scene '" + scene.name + "'");
  control_ = std::make_unique<Control>(*shared_, scene, std::move(patient), std::move(loader), options);
  control_endpoint_ = control_->control_endpoint();
  pose_endpoint_ = control_->pose_endpoint();
}

Server::~Server() { stop(); }

void Server::start() {
  if (started_) return;
  started_ = true;
  const auto t0 = control_->start();
  control_->start_deform();
  try {
    control_->sync_stream();
  } catch (...) {
    control_->stop_deform();
    throw;
  }
  pose_thread_ = std::thread([this, t0] {
    name_this_thread("palpsim-pose");
    if (const int p = control_->pose_fifo()) raise_this_thread(p);
    run_pose_service(control_->pose_socket(), *shared_, t0);
  });
  control_thread_ = std::thread([this] {
    name_this_thread("palpsim-control");
    control_->run();
  });
  // local force model patches, cut off the pose thread (it naps while no session asks)
  patch_thread_ = std::thread([this] {
    name_this_thread("palpsim-patch");
    run_patch_worker(*shared_);
  });
  heap_trimmer_ = std::make_unique<HeapTrimmer>();
}

void Server::stop() {
  shared_->stop.store(true);
  if (pose_thread_.joinable()) pose_thread_.join();
  if (control_thread_.joinable()) control_thread_.join();
  if (patch_thread_.joinable()) patch_thread_.join();
  heap_trimmer_.reset();
  if (control_) {
    control_->stop_stream();
    control_->stop_deform();
    control_->close();
  }
}

const ContactSlot* Server::contact_slot(std::uint64_t session_id) const {
  if (session_id == 0) return nullptr;
  const SessionSlot& s = shared_->slots[session_id & (kMaxSlots - 1)];
  return s.id.load(std::memory_order_acquire) == session_id ? &s.latest : nullptr;
}

bool Server::deformation_running() const { return control_->deform() != nullptr; }

std::string Server::stream_endpoint() const { return control_->stream_endpoint(); }

bool Server::deformed_volume(std::uint64_t session_id, Volume<float>& out, double timeout_s) const {
  DeformWorker* w = control_->deform();
  return w && w->deformed_volume(session_id, out, timeout_s);
}

std::vector<std::uint64_t> Server::open_sessions() const {
  std::vector<std::uint64_t> ids;
  for (const auto& s : shared_->slots)
    if (const std::uint64_t id = s.id.load(std::memory_order_acquire)) ids.push_back(id);
  return ids;
}

}  // namespace palpsim::net
