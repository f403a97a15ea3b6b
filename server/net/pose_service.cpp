#include "net/pose_service.h"

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "haptics/patch_cut.h"
#include "net/curve_keys.h"
#include "net/input_budget.h"
#include "net/wire_convert.h"
#include "net/wire_limits.h"
#include "palpsim/wire.pb.h"

namespace palpsim::net {

using runtime::PatchBytes;
using runtime::PatchChannel;
using runtime::PatchRequest;
using runtime::ServerShared;
using runtime::SessionSlot;
using runtime::World;

namespace {

namespace v1 = ::palpsim::v1;

// distance (mm) from a point to an axis-aligned box; 0 inside
double box_distance_mm(const Vec3& p, const Vec3& lo, const Vec3& hi) {
  const double dx = std::max({lo.x - p.x, 0.0, p.x - hi.x});
  const double dy = std::max({lo.y - p.y, 0.0, p.y - hi.y});
  const double dz = std::max({lo.z - p.z, 0.0, p.z - hi.z});
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

// one pose socket, its reused buffers and messages
class PoseService {
 public:
  PoseService(zmq::socket_t& s, ServerShared& sh, std::chrono::steady_clock::time_point start)
      : sock_(s), sh_(sh), start_(start), out_(kMaxPoseReplyBytes), budget_(random_seed()) {}

  void run(int idle_poll_ms) {
    zmq::pollitem_t items[] = {{sock_.handle(), 0, ZMQ_POLLIN, 0}};
    while (!sh_.stop.load(std::memory_order_relaxed)) {
      pick_up_world();
      zmq::poll(items, 1, std::chrono::milliseconds(idle_poll_ms));
      if (items[0].revents & ZMQ_POLLIN) drain();
    }
  }

 private:
  zmq::socket_t& sock_;
  ServerShared& sh_;
  std::chrono::steady_clock::time_point start_;
  const World* world_ = nullptr;
  v1::PoseRequest req_;
  v1::PoseReply rep_;
  const std::string* patch_ = nullptr;       // a serialized LocalForceModel to append to rep_, or none
  char id_[256];
  std::size_t id_len_ = 0;
  zmq::message_t msg_;                       // with CURVE: a payload frame with its properties
  char user_[kZ85KeyLength];                 // with CURVE: the sender's key (the ZAP user id)
  bool has_user_ = false;
  char frame_[2][kMaxPoseBytes + 1];
  std::size_t frame_len_[2] = {0, 0};        // bytes kept (at most kMaxPoseBytes + 1)
  std::size_t frame_full_len_[2] = {0, 0};   // bytes sent by the client
  char scrap_[64];
  std::vector<char> out_;                    // a serialized reply (room for the largest patch)
  std::int64_t t_recv_ = 0;                  // when the message being answered came (ns since start_)
  BadInputBudget budget_;                    // error replies each connection may still get

  static std::uint64_t random_seed() {
    std::random_device r;
    return (std::uint64_t(r()) << 32) | r();
  }

  // picks up the current world (one atomic load and store): a scene loaded before a pose
  // arrived serves that pose. Once its generation is published the control thread may
  // free older worlds, so no older pointer is used after this call.
  void pick_up_world() {
    world_ = sh_.world.load(std::memory_order_acquire);
    sh_.seen_generation.store(world_ ? world_->generation : 0, std::memory_order_release);
  }

  // answers every message waiting on the socket
  void drain() {
    for (;;) {
      const auto r = sock_.recv(zmq::mutable_buffer(id_, sizeof id_), zmq::recv_flags::dontwait);
      if (!r) return;
      const std::int64_t t_recv = ns_since(start_);
      t_recv_ = t_recv;
      pick_up_world();
      id_len_ = std::min(r->size, sizeof id_);
      has_user_ = false;
      // the frames after the routing id: [payload] (DEALER) or [empty, payload] (REQ)
      int frames = 0;
      while (sock_.get(zmq::sockopt::rcvmore)) {
        if (frames < 2 && sh_.curve) {
          recv_named(frames);
        } else if (frames < 2) {
          const auto f = sock_.recv(zmq::mutable_buffer(frame_[frames], sizeof frame_[frames]));
          frame_len_[frames] = f ? std::min(f->size, sizeof frame_[frames]) : 0;
          frame_full_len_[frames] = f ? f->untruncated_size : 0;
        } else {
          (void)sock_.recv(zmq::mutable_buffer(scrap_, sizeof scrap_));
        }
        ++frames;
      }
      // a REQ's envelope is an empty frame with more after it; the reply echoes it, and any
      // other request, malformed ones included, gets exactly one frame (a lone empty frame too)
      const bool req_envelope = frames >= 2 && frame_full_len_[0] == 0;
      if (frames == 1 && frame_full_len_[0] > 0) {
        handle(frame_[0], frame_len_[0], frame_full_len_[0], t_recv, false);
      } else if (frames == 2 && req_envelope) {
        handle(frame_[1], frame_len_[1], frame_full_len_[1], t_recv, true);
      } else {
        rep_.Clear();
        refuse(v1::ERROR_MALFORMED, sh_.counters.malformed,
               "PoseRequest: expected one frame (DEALER) or an empty delimiter and one frame (REQ)", nullptr);
        send(req_envelope);
      }
    }
  }

  // with CURVE: receives frame `i` as a message, whose "User-Id" property is the key the
  // ZAP handler admitted the connection with (libzmq attaches it to payload frames, not
  // to the ROUTER's routing id frame), and copies it into frame_[i]. The message is
  // reused; decrypting has already made its bytes, so this adds a copy, no allocation.
  void recv_named(int i) {
    (void)sock_.recv(msg_);
    frame_full_len_[i] = msg_.size();
    frame_len_[i] = std::min(msg_.size(), sizeof frame_[i]);
    std::memcpy(frame_[i], msg_.data(), frame_len_[i]);
    const char* user = zmq_msg_gets(msg_.handle(), "User-Id");
    has_user_ = user && std::strlen(user) == kZ85KeyLength;
    if (has_user_) std::memcpy(user_, user, kZ85KeyLength);
  }

  // fills rep_ with an error and counts it (and against the session when known)
  void refuse(v1::ErrorCode code, std::atomic<std::uint64_t>& counter, const char* message, SessionSlot* slot) {
    rep_.set_schema_version(v1::VERSION_CURRENT);
    rep_.mutable_error()->set_code(code);
    rep_.mutable_error()->set_message(message);
    rep_.set_server_time_s(ns_since(start_) * 1e-9);
    counter.fetch_add(1, std::memory_order_relaxed);
    if (slot) slot->errors.fetch_add(1, std::memory_order_relaxed);
  }

  // one PoseRequest: checked, its force computed, answered and handed to the deformation path
  void handle(const char* data, std::size_t len, std::size_t full_len, std::int64_t t_recv, bool req_envelope) {
    rep_.Clear();
    patch_ = nullptr;
    SessionSlot* slot = parse_request(data, len, full_len) ? open_session() : nullptr;
    if (!slot) return send(req_envelope);
    slot->last_seen_ns.store(t_recv, std::memory_order_relaxed);
    slot->last_used_ns.store(t_recv, std::memory_order_relaxed);
    if (!check_pose(*slot)) return send(req_envelope);
    const Vec3 tip{req_.tip_mm().x(), req_.tip_mm().y(), req_.tip_mm().z()};
    refresh_state(*slot, t_recv);
    const double now_s = t_recv * 1e-9;
    const double dt = pose_dt(*slot, now_s);
    const ForceSample f = force(*slot, tip, dt, now_s);
    reply(*slot, tip, f, t_recv);
    send(req_envelope);
  }

  // size, parse, version; false: refused (rep_ says why)
  bool parse_request(const char* data, std::size_t len, std::size_t full_len) {
    char msg[256];
    // size, parse, version
    if (full_len > kMaxPoseBytes) {
      std::snprintf(msg, sizeof msg, "PoseRequest: %zu bytes, over the pose path's limit of %zu bytes", full_len,
                    kMaxPoseBytes);
      refuse(v1::ERROR_OVERSIZED, sh_.counters.oversized, msg, nullptr);
      return false;
    }
    if (!req_.ParseFromArray(data, int(len))) {
      std::snprintf(msg, sizeof msg, "PoseRequest: %zu bytes do not parse (truncated, or not a PoseRequest)", len);
      refuse(v1::ERROR_MALFORMED, sh_.counters.malformed, msg, nullptr);
      return false;
    }
    rep_.set_seq(req_.seq());
    rep_.set_session_id(req_.session_id());
    rep_.set_client_time_s(req_.client_time_s());
    if (req_.schema_version() != v1::VERSION_CURRENT) {
      std::snprintf(msg, sizeof msg, "PoseRequest.schema_version: got %u, this server speaks %d", req_.schema_version(),
                    int(v1::VERSION_CURRENT));
      refuse(v1::ERROR_WRONG_SCHEMA_VERSION, sh_.counters.wrong_schema_version, msg, nullptr);
      return false;
    }
    if (!req_.has_tip_mm()) {
      refuse(v1::ERROR_MALFORMED, sh_.counters.malformed, "PoseRequest.tip_mm: missing", nullptr);
      return false;
    }
    return true;
  }

  // the session of req_ when it is open and this client's; nullptr: refused
  SessionSlot* open_session() {
    char msg[256];
    // the session: its slot index is in the id's low bits, and the slot must hold this id
    const std::uint64_t id = req_.session_id();
    SessionSlot* slot = &sh_.slots[runtime::slot_index(id)];
    if (id == 0 || slot->id.load(std::memory_order_acquire) != id || !world_) {
      std::snprintf(msg, sizeof msg,
                    "PoseRequest.session_id: %016" PRIx64 " is not an open session (never opened, closed, or timed out)",
                    id);
      refuse(v1::ERROR_UNKNOWN_SESSION, sh_.counters.unknown_session, msg, nullptr);
      return nullptr;
    }
    // with CURVE only the key that opened the session may pose for it
    if (!slot->key_may_act(has_user_ ? user_ : nullptr)) {
      std::snprintf(msg, sizeof msg, "PoseRequest.session_id: %016" PRIx64 " belongs to another client's key", id);
      refuse(v1::ERROR_NOT_OWNER, sh_.counters.not_owner, msg, nullptr);
      return nullptr;
    }
    return slot;
  }

  // the pose itself and its patch request; false: refused
  bool check_pose(SessionSlot& slot) {
    char msg[256];
    const Vec3 tip{req_.tip_mm().x(), req_.tip_mm().y(), req_.tip_mm().z()};
    if (!is_finite(tip)) {
      std::snprintf(msg, sizeof msg, "PoseRequest.tip_mm: (%g, %g, %g) is not finite", tip.x, tip.y, tip.z);
      refuse(v1::ERROR_BAD_POSE, sh_.counters.bad_pose, msg, &slot);
      return false;
    }
    const double away_mm = box_distance_mm(tip, world_->bounds_min_mm, world_->bounds_max_mm);
    if (away_mm > sh_.max_pose_distance_mm) {
      std::snprintf(msg, sizeof msg,
                    "PoseRequest.tip_mm: (%g, %g, %g) is %.0f mm from the patient, over the limit of %.0f mm", tip.x,
                    tip.y, tip.z, away_mm, sh_.max_pose_distance_mm);
      refuse(v1::ERROR_ABSURD_POSE, sh_.counters.absurd_pose, msg, &slot);
      return false;
    }
    // a request for patches names a size and a period within their ranges
    const std::uint32_t edge = req_.local_model_edge();
    const double period = req_.local_model_period_s();
    if (edge != 0 && (edge < kMinPatchEdge || edge > kMaxPatchEdge)) {
      std::snprintf(msg, sizeof msg, "PoseRequest.local_model_edge: %u voxels, outside %d..%d (0: no patches)", edge,
                    kMinPatchEdge, kMaxPatchEdge);
      refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, msg, &slot);
      return false;
    }
    if (edge != 0 && !(period >= kMinPatchPeriodS && period <= kMaxPatchPeriodS)) {
      std::snprintf(msg, sizeof msg, "PoseRequest.local_model_period_s: %g s, outside %g..%g s", period,
                    kMinPatchPeriodS, kMaxPatchPeriodS);
      refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, msg, &slot);
      return false;
    }
    return true;
  }

  // a new session in this slot, a reset, or a new world: a fresh proxy state
  void refresh_state(SessionSlot& slot, std::int64_t t_recv) {
    const std::uint64_t id = req_.session_id();
    const std::uint32_t resets = slot.reset_requests.load(std::memory_order_acquire);
    if (slot.state_id != id || slot.resets_seen != resets || slot.state_generation != world_->generation ||
        req_.reset_proxy()) {
      if (slot.state_id != id) {
        slot.latest.clear();
        slot.patch_version = 0;
      }
      slot.patch_sent_s = -1;  // a fresh state gets a fresh patch with its next pose
      slot.state_id = id;
      slot.resets_seen = resets;
      slot.state_generation = world_->generation;
      slot.proxy = ProxyState{};
      slot.elastic = ElasticRenderState{};
      slot.elastic.left_s = t_recv * 1e-9;  // models of poses before the reset are not taken
      slot.passivity = PassivityObserver{};
      slot.last_client_time_s = 0;
      slot.last_server_time_s = 0;
      // the deformation worker resets the session's deformation too
      if (req_.reset_proxy()) slot.pose_resets.fetch_add(1, std::memory_order_release);
    }
  }

  // dt from the client's clock when it grows, else from the server's (s)
  double pose_dt(SessionSlot& slot, double now_s) {
    const double tc = req_.client_time_s();
    double dt = 0;
    if (tc > 0 && slot.last_client_time_s > 0 && tc > slot.last_client_time_s)
      dt = tc - slot.last_client_time_s;
    else if (slot.last_server_time_s > 0)
      dt = now_s - slot.last_server_time_s;
    slot.last_client_time_s = tc;
    slot.last_server_time_s = now_s;
    return dt;
  }

  // the force on the hand, the passivity observer and the patches asked for
  ForceSample force(SessionSlot& slot, const Vec3& tip, double dt, double now_s) {
    const double tc = req_.client_time_s();
    const std::uint32_t edge = req_.local_model_edge();
    const double period = req_.local_model_period_s();
    HapticsSettings params = slot.params();
    params.skin_point = world_->scene.haptics.skin_point;  // scene-wide, not a session parameter
    ForceSample f = compute_force(*world_->patient, params, tip, dt, slot.proxy);
    const bool elastic = world_->scene.haptics.force_model == ForceModel::kElastic;
    if (elastic) render_elastic_force(slot, params, tip, dt, now_s, f);
    observe_passivity(slot, tip, elastic, f);
    if (edge != 0) serve_patches(slot, params, tip, edge, period, now_s, tc);
    slot.renders_locally.store(req_.renders_locally(), std::memory_order_relaxed);
    if (req_.renders_locally()) slot.local_poses.fetch_add(1, std::memory_order_relaxed);
    return f;
  }

  // the reply, statistics and the hand-over to the deformation path
  void reply(SessionSlot& slot, const Vec3& tip, const ForceSample& f, std::int64_t t_recv) {
    const std::uint64_t id = req_.session_id();
    rep_.set_schema_version(v1::VERSION_CURRENT);
    set_vec(rep_.mutable_force_n(), f.force_n);
    set_vec(rep_.mutable_proxy_mm(), f.proxy_mm);
    set_vec(rep_.mutable_skin_point_mm(), f.skin_point_mm);
    rep_.set_contact(f.contact);
    rep_.set_depth_mm(f.depth_mm);
    const std::int64_t t_done = ns_since(start_);
    rep_.set_server_time_s(t_done * 1e-9);
    const double service_us = (t_done - t_recv) * 1e-3;
    rep_.set_service_time_us(service_us);
    // statistics and the hand-over to the deformation path
    slot.poses.fetch_add(1, std::memory_order_relaxed);
    slot.last_seq.store(req_.seq(), std::memory_order_relaxed);
    slot.contact.store(f.contact, std::memory_order_relaxed);
    slot.depth_mm.store(f.depth_mm, std::memory_order_relaxed);
    if (f.clamped) slot.clamps.fetch_add(1, std::memory_order_relaxed);
    if (f.reset) sh_.counters.internal_errors.fetch_add(1, std::memory_order_relaxed);
    Contact c;
    c.tip_mm = tip;
    c.skin_point_mm = f.skin_point_mm;
    c.proxy_mm = f.proxy_mm;
    c.depth_mm = f.depth_mm;
    c.contact = f.contact;
    c.seq = req_.seq();
    c.session_id = id;
    c.server_time_s = t_done * 1e-9;
    slot.latest.write(c);
    sh_.counters.poses.fetch_add(1, std::memory_order_relaxed);
    sh_.pose_service.add(service_us);
  }

  // haptics.force_model "elastic": eq. 2's pass above gave contact, X and depth; the force is
  // the elastic model's, from the newest local linear model the deformation worker published
  // for this session and world (taken without waiting; a value copied once per model)
  void render_elastic_force(SessionSlot& slot, const HapticsSettings& params, const Vec3& tip, double dt,
                            double now_s, ForceSample& f) {
    const ElasticModel* fresh = nullptr;
    if (slot.elastic_model.take()) {
      const ElasticModel& m = slot.elastic_model.front();
      if (m.session_id == slot.state_id && m.generation == world_->generation) fresh = &m;
    }
    HapticsSettings p = params;
    p.elastic_max_jump_n = world_->scene.haptics.elastic_max_jump_n;  // scene-wide
    const ElasticRenderStep e = render_elastic(slot.elastic, fresh, p, tip, f.contact, dt, now_s);
    slot.elastic_counters.add(e);
    f.force_n = e.force_n;
    f.clamped = e.clamped;
    f.reset = f.reset || e.reset;
  }

  // the passivity observer follows the energy of the force sent; with haptics.passivity its
  // controller lowers a force that would give back more than the press put in, and the
  // force model's state then holds the force sent (its rate clamp starts from it)
  void observe_passivity(SessionSlot& slot, const Vec3& tip, bool elastic, ForceSample& f) {
    const PassivityStep p = slot.passivity.pose(tip, f.contact, f.force_n, world_->scene.haptics.passivity,
                                                elastic ? &slot.elastic.force_n : &slot.proxy.force_n);
    slot.passivity_counters.add(slot.passivity, p);
  }

  // a patch is due once per period, and sooner (a quarter period) when the tip comes within
  // kPatchMarginVox voxels of the last box's inner faces, where the client would soon miss
  bool patch_due(const SessionSlot& slot, const Vec3& tip, double now_s, double period_s) const {
    if (slot.patch_sent_s < 0 || now_s - slot.patch_sent_s >= period_s) return true;
    if (now_s - slot.patch_sent_s < 0.25 * period_s) return false;
    const Grid& g = world_->patient->grid;
    const Vec3 ijk = g.to_index(tip);
    for (int a = 0; a < 3; ++a) {
      const double lo = slot.patch_lo[a], hi = slot.patch_lo[a] + slot.patch_size[a] - 1;
      if ((ijk[a] < lo + kPatchMarginVox && lo > 0) || (ijk[a] > hi - kPatchMarginVox && hi < g.size[a] - 1))
        return true;
    }
    return false;
  }

  // the centre of the next patch's box: the tip, led by its velocity since the last patch
  // (on the client's clock: after a TCP stall poses arrive in a burst) times kPatchLeadS, at
  // most edge / 2 - kPatchMarginVox - 1 voxels (the tip stays inside with the margin); the
  // tip itself for a session's first patch, after a pause, or without client times
  Vec3 patch_center(const SessionSlot& slot, const Vec3& tip, int edge, double client_time_s) const {
    const double since_s = client_time_s - slot.patch_client_time_s;
    if (slot.patch_sent_s < 0 || slot.patch_version == 0 || !(since_s > 0) || since_s > 1.0) return tip;
    const Vec3 lead = (tip - slot.patch_tip_mm) * (kPatchLeadS / since_s);
    const Vec3& sp = world_->patient->grid.spacing_mm;
    const double max_mm = std::max(0.0, 0.5 * edge - kPatchMarginVox - 1) * std::min(sp.x, std::min(sp.y, sp.z));
    const double n = norm(lead);
    if (!(n > 0) || !std::isfinite(n)) return tip;
    return n > max_mm ? tip + lead * (max_mm / n) : tip + lead;
  }

  // a session that asks for patches: the first time, the patch worker is told to make the
  // slot's channel; then a request when a patch is due, and the newest patch the worker
  // has cut for this session and world goes with this reply (patch_worker.h)
  void serve_patches(SessionSlot& slot, const HapticsSettings& params, const Vec3& tip, std::uint32_t edge,
                     double period_s, double now_s, double client_time_s) {
    if (!slot.patch_asked.load(std::memory_order_relaxed)) {
      slot.patch_asked.store(true, std::memory_order_release);
      sh_.patches_asked.store(true, std::memory_order_release);
    }
    PatchChannel* ch = slot.patch_channel.load(std::memory_order_acquire);
    if (!ch) return;
    if (patch_due(slot, tip, now_s, period_s)) {
      const Vec3 center = patch_center(slot, tip, int(edge), client_time_s);
      PatchRequest& q = ch->request.back();
      q.session_id = slot.state_id;
      q.generation = world_->generation;
      q.version = ++slot.patch_version;
      q.tip_mm = center;
      q.edge = int(edge);
      q.params = params;
      q.server_time_s = now_s;
      ch->request.publish();
      slot.patch_sent_s = now_s;
      slot.patch_tip_mm = tip;
      slot.patch_client_time_s = client_time_s;
      slot.patch_lo = patch_box(world_->patient->grid, center, int(edge), slot.patch_size);
    }
    if (ch->patch.take()) {
      const PatchBytes& b = ch->patch.front();
      if (b.session_id == slot.state_id && b.generation == world_->generation) {
        patch_ = &b.bytes;
        slot.local_models_sent.fetch_add(1, std::memory_order_relaxed);
      }
    }
  }

  // appends field 13 (tag, length, bytes) holding *patch_ to the n bytes in out_; the new
  // length, or 0 when it does not fit
  std::size_t append_patch(std::size_t n) {
    const std::size_t len = patch_->size();
    if (n + 1 + 10 + len > out_.size()) return 0;
    out_[n++] = char((13 << 3) | 2);  // field 13, length-delimited
    for (std::size_t v = len;; v >>= 7) {
      out_[n++] = char(v < 0x80 ? v : (v & 0x7f) | 0x80);
      if (v < 0x80) break;
    }
    std::memcpy(out_.data() + n, patch_->data(), len);
    return n + len;
  }

  // sends rep_ to the current routing id; never blocks (a vanished or slow client's reply is
  // dropped); an error past its connection's allowance is not sent at all
  void send(bool req_envelope) {
    if (rep_.has_error() && !budget_.answer(id_, id_len_, t_recv_)) {
      sh_.counters.bad_input_unanswered.fetch_add(1, std::memory_order_relaxed);
      patch_ = nullptr;
      return;
    }
    std::size_t n = rep_.ByteSizeLong();
    if (n > out_.size() || !rep_.SerializeToArray(out_.data(), int(n))) return;
    // a patch goes after the reply's other fields as field 13 (PoseReply.local_model):
    // protobuf parses fields in any order, so these bytes are a PoseReply with local_model set
    // (kMaxPoseReplyBytes leaves room for the largest patch; should one not fit, the
    // force still goes out, without it)
    if (patch_) {
      if (const std::size_t with_patch = append_patch(n)) n = with_patch;
      patch_ = nullptr;
    }
    try {
      if (!sock_.send(zmq::const_buffer(id_, id_len_), zmq::send_flags::sndmore | zmq::send_flags::dontwait)) return;
      if (req_envelope) sock_.send(zmq::const_buffer(nullptr, 0), zmq::send_flags::sndmore | zmq::send_flags::dontwait);
      sock_.send(zmq::const_buffer(out_.data(), n), zmq::send_flags::dontwait);
    } catch (const zmq::error_t&) {
      // EHOSTUNREACH and the like: the client is gone; nothing to do
    }
  }
};

}  // namespace

void run_pose_service(zmq::socket_t& socket, ServerShared& shared, std::chrono::steady_clock::time_point start,
                      int idle_poll_ms) {
  // the service object holds ~4 KiB of buffers and the largest patch's: on the heap, once
  auto service = std::make_unique<PoseService>(socket, shared, start);
  service->run(idle_poll_ms);
}

}  // namespace palpsim::net
