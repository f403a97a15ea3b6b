// The control thread's dispatcher (net/control.h): its sockets, the request loop, the
// refusals, ServerInfo, the workers it starts and housekeeping.
#include "net/control.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <limits>

#include "core/error.h"
#include "core/thread.h"
#include "net/client_text.h"
#include "net/pose_service.h"
#include "net/wire_convert.h"
#include "net/wire_limits.h"

namespace palpsim::net {
namespace {

// a refusal's message is cut to this many characters (client strings in it to kClientTextChars)
constexpr std::size_t kMaxErrorChars = 2048;

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

}  // namespace

void fill_params(v1::HapticsParams* out, const HapticsSettings& s) {
  out->set_stiffness_n_per_mm(s.stiffness_n_per_mm);
  out->set_friction(s.friction);
  out->set_max_force_n(s.max_force_n);
  out->set_max_force_rate_n_per_s(s.max_force_rate_n_per_s);
  out->set_min_gradient_norm(s.min_gradient_norm);
}

Server::Control::Control(ServerShared& sh, const Scene& scene, PatientPtr patient, PatientLoader loader,
                         const ServerOptions& o)
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

void Server::Control::start_deform() {
  if (current_->scene.effects.chainmail && !deform_) {
    auto w = std::make_unique<DeformWorker>(sh_, start_, opt_.deform_nice, opt_.background_idle,
                                            opt_.deform_concurrency, opt_.deform_batch);
    w->start();
    deform_ = std::move(w);
    deform_ptr_.store(deform_.get(), std::memory_order_release);
  }
}

void Server::Control::stop_deform() {
  if (deform_) deform_->stop();
}

void Server::Control::sync_stream() {
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

void Server::Control::stop_stream() {
  if (render_) render_->stop();
  render_.reset();
  if (publisher_) publisher_->stop();
  publisher_.reset();
  std::lock_guard<std::mutex> lock(stream_endpoint_mu_);
  stream_endpoint_.clear();
}

bool Server::Control::frames_served() const {
  if (!render_ || !stream_) return false;
  std::lock_guard<std::mutex> lock(stream_->info_mu);
  return !stream_->info.jpeg_encoder.empty();
}

void Server::Control::close() {
  end_load();
  control_.close();
  pose_.close();
  load_done_rx_.close();
  load_done_tx_.close();
}

void Server::Control::run() {
  zmq::pollitem_t items[] = {{control_.handle(), 0, ZMQ_POLLIN, 0}, {load_done_rx_.handle(), 0, ZMQ_POLLIN, 0}};
  last_log_ = Clock::now();
  while (!sh_.stop.load()) {
    zmq::poll(items, 2, std::chrono::milliseconds(opt_.housekeeping_ms));
    if (items[1].revents & ZMQ_POLLIN) finish_load();
    if (items[0].revents & ZMQ_POLLIN) drain();
    housekeeping();
  }
}

std::string Server::Control::bind(zmq::socket_t& s, const std::string& addr, const char* option) {
  try {
    s.bind(addr);
  } catch (const zmq::error_t& e) {
    throw Error(std::string(option) + " " + addr + ": cannot bind: " + e.what());
  }
  return s.get(zmq::sockopt::last_endpoint);
}

void Server::Control::drain() {
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

void Server::Control::send_reply(const zmq::message_t& routing_id, bool req_envelope) {
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

std::string Server::Control::identity(const zmq::message_t& routing_id, const std::string& user) {
  requester_key_.clear();
  if (sh_.curve) {
    requester_key_ = user;
    return "key " + requester_key_;
  }
  if (!req_.client_token().empty()) return "token " + req_.client_token();
  return "connection " + routing_id.to_string();
}

bool Server::Control::owned(const SessionSlot& s, std::uint64_t id, const std::string& field) {
  if (s.owner == requester_) return true;
  refuse(v1::ERROR_NOT_OWNER, sh_.counters.not_owner,
         field + ": " + hex_id(id) + " belongs to another client; only " +
             (sh_.curve ? "the key that opened it" : "the client token or control connection that opened it") +
             " may act on it or watch it");
  return false;
}

void Server::Control::refuse(v1::ErrorCode code, std::atomic<std::uint64_t>& counter, const std::string& message) {
  // the message may embed client strings from deeper down (a scene's ct_path in a prep
  // error): escaped and cut once more as a whole
  const std::string safe = client_text(message, kMaxErrorChars);
  rep_.clear_body();
  rep_.mutable_error()->set_code(code);
  rep_.mutable_error()->set_message(safe);
  counter.fetch_add(1);
  spdlog::warn("control: {} ({})", safe, v1::ErrorCode_Name(code));
}

void Server::Control::handle() {
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

SessionSlot* Server::Control::session_or_refuse(std::uint64_t id, const char* field, bool use) {
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

void Server::Control::fill_info(v1::ServerInfo* info) {
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

const char* Server::Control::requester_kind() const {
  return sh_.curve ? "CURVE key" : requester_.rfind("token ", 0) == 0 ? "client token" : "control connection";
}

void Server::Control::warn_quota() const {
  const int most = current_->scene.server.max_sessions;
  if (most > 1 && opt_.max_sessions_per_client >= most)
    spdlog::warn("--max-sessions-per-client {} is not below scene '{}''s server.max_sessions {}: one client can "
                 "hold every session",
                 opt_.max_sessions_per_client, current_->scene.name, most);
}

void Server::Control::housekeeping() {
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
  const std::size_t retired = retired_.size();
  retired_.erase(std::remove_if(retired_.begin(), retired_.end(),
                                [seen](const std::unique_ptr<World>& w) { return w->generation < seen; }),
                 retired_.end());
  // an old scene's patient is gone: its memory back to the system at the trimmer's next look
  if (retired_.size() != retired) sh_.heap_trim_requested.store(true, std::memory_order_release);
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

}  // namespace palpsim::net
