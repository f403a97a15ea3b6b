#include "net/stream_publisher.h"

#include <spdlog/spdlog.h>
#include <zstd.h>

#include <algorithm>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <unordered_map>
#include <unordered_set>
#include <vector>
#include <zmq.hpp>

#include "core/error.h"
#include "core/thread.h"
#include "net/client_text.h"
#include "net/wire_convert.h"
#include "palpsim/wire.pb.h"
#include "runtime/session_state.h"

namespace palpsim::net {

using deform::Voi;
using runtime::brick_topic;
using runtime::EncodedFrame;
using runtime::frame_topic;
using runtime::hex_id;
using runtime::JSnapshot;
using runtime::kMaxSlots;
using runtime::ServerShared;
using runtime::SessionState;
using runtime::SessionStates;
using runtime::SessionStreamReport;
using runtime::slot_index;
using runtime::StreamSlot;
using runtime::StreamState;
using runtime::World;

namespace {

namespace v1 = ::palpsim::v1;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

// Why 64: ZeroMQ counts every part of a message against the high-water mark, and a
// whole-volume key is at most kMaxKeyParts two-part messages; a slow subscriber's pipe
// then holds at most one key plus a few frames. Beyond it, messages to that subscriber
// are dropped (the XPUB default), never queued and never waited for.
constexpr int kSendHwm = 64;
// the key (undeformed image) goes in slabs along k of about this many voxels, at most
// kMaxKeyParts of them
constexpr std::size_t kKeySlabVoxels = std::size_t(2) << 20;
constexpr int kMaxKeyParts = 16;
// subscription messages longer than this are not topics of this server
constexpr std::int64_t kMaxSubscriptionBytes = 1024;
// the thread polls for subscriptions this long at most between passes (ms)
constexpr int kPollMs = 1;
// a topic's length: "frame." or "brick." and 16 hex digits
constexpr std::size_t kTopicLength = 6 + 16;
// Why messages are sent once more after this long (s): at a full pipe ZeroMQ drops the
// message being sent, not the oldest queued one, so the last frame of a burst (or a
// "closed" notice) may never reach a viewer that was behind. The newest frame of a
// session that went quiet, and every "closed" notice, are sent again once, by when a
// viewer that drains its socket has room again.
constexpr double kResendAfterS = 0.25;


// the session id of a full topic ("frame.<16 hex>"), or 0
std::uint64_t topic_session(const std::string& t) {
  if (t.size() != kTopicLength) return 0;
  std::uint64_t id = 0;
  for (std::size_t i = 6; i < t.size(); ++i) {
    const char c = t[i];
    int d = -1;
    if (c >= '0' && c <= '9') d = c - '0';
    if (c >= 'a' && c <= 'f') d = c - 'a' + 10;
    if (d < 0) return 0;
    id = (id << 4) | std::uint64_t(d);
  }
  return id;
}

}  // namespace


// a session whose frames cannot be recorded logs at most one line per this many seconds
constexpr double kRecordLogPeriodS = 10.0;

// the publisher's own state of one session slot (one of a session's parts: runtime/session_state.h)
struct PubSlot {
  std::uint64_t session = 0;        // the open session in the slot (0: none)
  bool frames = false, bricks = false;  // watched at the last pass
  bool key_pending = false;         // a key is owed to brick subscribers
  std::uint64_t key_id = 0;         // keys sent so far
  std::uint64_t brick_seq = 0;      // bricks sent so far (VOI and key parts)
  std::string last_voi_brick;       // the latest VOI brick's payload, sent again after a key
  double next_brick_s = 0;          // server clock: no VOI brick before then (render.max_fps)
  std::string last_frame;           // the latest frame's payload and when it was sent
  double last_frame_s = 0;
  bool frame_resent = true;         // the latest frame was sent again after the session went quiet
  // recording (render.record_dir): the session's folder and index
  fs::path record_dir;
  std::ofstream record_index;
  // frames that could not be recorded since the last log line about it, and when that line
  // was written (server clock, s): a full disk logs a line per 10 s, not one per frame
  std::uint64_t record_unlogged = 0;
  double record_logged_s = -1e9;
};

struct StreamPublisher::Impl {
  ServerShared& sh;
  StreamState& st;
  Clock::time_point start;
  zmq::context_t ctx{1};
  std::unique_ptr<ZapHandler> zap;  // CURVE only: admits connections to ctx's socket
  zmq::socket_t xpub{ctx, zmq::socket_type::xpub};
  // CURVE only (manual mode): per topic, the subscriptions admitted and refused that are
  // still held; ZeroMQ reports each one's end, but a departing pipe's end carries no key,
  // so such an end is taken from the refused first (a topic may be thought watched a
  // little longer, never one of someone else's sessions delivered)
  bool manual = false;
  std::unordered_map<std::string, std::pair<int, int>> held;
  std::atomic<bool> stop{false};

  // subscriptions: full topics, and shorter prefixes (a prefix of "frame." watches every session)
  std::unordered_set<std::string> exact;
  std::vector<std::string> prefixes;
  std::vector<PubSlot> pub = std::vector<PubSlot>(kMaxSlots);
  SessionStates<PubSlot> sessions{sh, st, pub};  // each slot's parts: the table's, the stream's, pub's

  // the world whose patient the keys are made of
  std::uint64_t generation = 0;
  PatientPtr patient;
  Scene scene;

  // notices sent again once (kResendAfterS)
  struct Late {
    double due_s;
    std::string topic, payload;
  };
  std::vector<Late> late;

  // reused buffers: no allocation per message once they have grown
  v1::StreamMessage msg;
  bool sent_since_release = false;  // a session was watched since the buffers were last freed
  std::string payload;
  std::vector<std::int16_t> i16;
  std::vector<char> packed;
  ZSTD_CCtx* zstd = ZSTD_createCCtx();

  Impl(ServerShared& s, StreamState& t, Clock::time_point t0) : sh(s), st(t), start(t0) {}
  ~Impl() { ZSTD_freeCCtx(zstd); }

  double now_s() const { return std::chrono::duration<double>(Clock::now() - start).count(); }

  // frees the buffers reused from message to message (the next message makes them again)
  void release_buffers() {
    std::string().swap(payload);
    std::vector<std::int16_t>().swap(i16);
    std::vector<char>().swap(packed);
    v1::StreamMessage().Swap(&msg);
    sent_since_release = false;
  }

  void send(const std::string& topic, const std::string& body) {
    try {
      xpub.send(zmq::buffer(topic), zmq::send_flags::sndmore | zmq::send_flags::dontwait);
      xpub.send(zmq::buffer(body), zmq::send_flags::dontwait);
      st.bytes_published.fetch_add(topic.size() + body.size(), std::memory_order_relaxed);
    } catch (const zmq::error_t& e) {
      spdlog::warn("stream: sending on {} failed: {}", topic, e.what());
    }
  }

  void notice(const std::string& topic, std::uint64_t id, const char* event, const std::string& message,
              bool unknown, bool again = false) {
    msg.Clear();
    msg.set_schema_version(v1::VERSION_CURRENT);
    auto* n = msg.mutable_notice();
    n->set_session_id(id);
    n->set_event(event);
    n->set_message(message);
    if (unknown) {
      n->mutable_error()->set_code(v1::ERROR_UNKNOWN_SESSION);
      n->mutable_error()->set_message(message);
    }
    msg.SerializeToString(&payload);
    send(topic, payload);
    if (again) late.push_back({now_s() + kResendAfterS, topic, payload});
  }

  // is a topic watched by some subscription (exact, or a prefix of it)?
  bool watched(const std::string& topic) const {
    if (exact.count(topic)) return true;
    for (const std::string& p : prefixes)
      if (topic.compare(0, p.size(), p) == 0) return true;
    return false;
  }

  bool open(std::uint64_t id) const {
    return id != 0 && sh.slots[slot_index(id)].id.load(std::memory_order_acquire) == id;
  }

  // manual mode (CURVE): admits or refuses one subscription (the sender's key against the
  // session's opener, no prefixes: they would cover other clients' sessions) and keeps
  // the count; false when the subscription is refused or an end leaves the topic watched
  bool admit(const zmq::message_t& m, bool on, const std::string& topic, std::uint64_t id, bool prefix) {
    auto& [admitted, refused] = held[topic];
    const char* key = zmq_msg_gets(m.handle(), "User-Id");
    const bool foreign = id != 0 && open(id) && !sh.slots[slot_index(id)].key_may_act(key);
    if (!on) {
      // an unsubscribe with a key says whose it is; a departing pipe's has none
      const bool was_refused = refused > 0 && (!key || foreign || prefix);
      if (was_refused) --refused;
      else if (admitted > 0) --admitted;
      if (!was_refused) xpub.set(zmq::sockopt::unsubscribe, topic);
      const bool last = admitted == 0;
      if (admitted == 0 && refused == 0) held.erase(topic);
      return last && !was_refused;
    }
    if (foreign || prefix) {
      ++refused;
      (foreign ? sh.counters.not_owner : st.bad_subscriptions).fetch_add(1, std::memory_order_relaxed);
      spdlog::warn("stream: subscription '{}' refused: {}", client_text(topic),
                   foreign ? "the session belongs to another client's key"
                           : "with CURVE a subscription names one session's full topic");
      return false;
    }
    ++admitted;
    xpub.set(zmq::sockopt::subscribe, topic);
    return true;
  }

  // one subscription message: 1 or 0, then the topic
  void subscription(const zmq::message_t& m) {
    if (m.size() == 0) return;
    const bool on = static_cast<const char*>(m.data())[0] == 1;
    const std::string topic(static_cast<const char*>(m.data()) + 1, m.size() - 1);
    const bool is_frame = topic.rfind("frame.", 0) == 0, is_brick = topic.rfind("brick.", 0) == 0;
    // a shorter topic that begins some session's topics ("", "frame.", "brick.00ab", ...)
    const auto begins = [&topic](const char* kind) {
      const std::string k(kind);
      const std::size_t n = std::min(topic.size(), k.size());
      return topic.compare(0, n, k, 0, n) == 0;
    };
    const bool prefix = topic.size() < kTopicLength && (begins("frame.") || begins("brick."));
    const std::uint64_t id = (is_frame || is_brick) ? topic_session(topic) : 0;
    if (manual && !admit(m, on, topic, id, prefix)) return;
    if (!on) {
      exact.erase(topic);
      prefixes.erase(std::remove(prefixes.begin(), prefixes.end(), topic), prefixes.end());
      return;
    }
    if (id != 0) {
      if (!open(id)) {
        st.bad_subscriptions.fetch_add(1, std::memory_order_relaxed);
        notice(topic, id, "unknown_session",
               "subscription " + topic + ": session " + hex_id(id) +
                   " is not open (never opened, closed, or timed out)",
               true);
        return;
      }
      exact.insert(topic);
      // every brick subscriber gets a key, so it can rebuild the whole deformed volume
      if (is_brick) pub[slot_index(id)].key_pending = true;
      return;
    }
    if (prefix) {
      if (std::find(prefixes.begin(), prefixes.end(), topic) == prefixes.end()) prefixes.push_back(topic);
      // brick subscribers of the sessions it covers get a key
      for (PubSlot& p : pub)
        if (p.session != 0 && brick_topic(p.session).compare(0, topic.size(), topic) == 0) p.key_pending = true;
      return;
    }
    st.bad_subscriptions.fetch_add(1, std::memory_order_relaxed);
    notice(topic, 0, "unknown_session",
           "subscription '" + client_text(topic) + "' names no stream: subscribe to frame.<16 hex digits of the session id> or "
                                      "brick.<...> (WatchReply.frame_topic, brick_topic)",
           true);
  }

  // a new scene: its patient for keys; brick subscribers get a new key
  void pick_up_world() {
    const World* w = sh.world.load(std::memory_order_acquire);
    if (!w || w->generation == generation) return;
    const bool changed = generation != 0;
    generation = w->generation;
    patient = w->patient;
    scene = w->scene;
    sh.publish_seen_generation.store(generation, std::memory_order_release);
    if (!changed) return;
    for (PubSlot& p : pub) {
      if (p.session == 0) continue;
      const std::string m = "scene changed to '" + scene.name + "' (generation " + std::to_string(generation) + ")";
      if (p.frames) notice(frame_topic(p.session), p.session, "scene_changed", m, false);
      if (p.bricks) notice(brick_topic(p.session), p.session, "scene_changed", m, false);
      p.key_pending = p.bricks;
      p.last_voi_brick.clear();
    }
  }

  // encodes `n` floats into packed bytes (int16 HU or float32), compressed when asked
  std::uint64_t encode(const float* v, std::size_t n, bool float32, bool zstd_on, std::string* out) {
    const char* raw = nullptr;
    std::size_t raw_bytes = 0;
    if (float32) {
      raw = reinterpret_cast<const char*>(v);
      raw_bytes = n * sizeof(float);
    } else {
      // round to nearest (halves away from zero) and clamp to the int16 range
      i16.resize(n);
      for (std::size_t e = 0; e < n; ++e) {
        const float c = std::min(32767.0f, std::max(-32768.0f, v[e]));
        i16[e] = std::int16_t(std::lround(c));
      }
      raw = reinterpret_cast<const char*>(i16.data());
      raw_bytes = n * sizeof(std::int16_t);
    }
    if (!zstd_on) {
      out->assign(raw, raw_bytes);
      return raw_bytes;
    }
    packed.resize(ZSTD_compressBound(raw_bytes));
    const std::size_t z = ZSTD_compressCCtx(zstd, packed.data(), packed.size(), raw, raw_bytes, 1);
    if (ZSTD_isError(z)) throw Error(std::string("zstd: ") + ZSTD_getErrorName(z));
    out->assign(packed.data(), z);
    return raw_bytes;
  }

  // the brick's geometry: the patient grid and the box
  void geometry(v1::Brick* b, const Voi& box) {
    const Grid& g = patient->grid;
    b->set_lo_i(box.lo.x);
    b->set_lo_j(box.lo.y);
    b->set_lo_k(box.lo.z);
    b->set_size_i(box.size.x);
    b->set_size_j(box.size.y);
    b->set_size_k(box.size.z);
    b->set_grid_size_i(g.size.x);
    b->set_grid_size_j(g.size.y);
    b->set_grid_size_k(g.size.z);
    b->set_spacing_mm(g.spacing_mm.x);
    set_vec(b->mutable_grid_origin_mm(), g.origin_mm);
    for (double d : g.direction) b->add_direction(d);
    set_vec(b->mutable_origin_mm(), g.to_physical(Vec3(box.lo)));
  }

  void send_key(PubSlot& p, StreamSlot& ss, bool float32, bool zstd_on) {
    const Grid& g = patient->grid;
    const std::size_t plane = std::size_t(g.size.x) * g.size.y;
    int slab = int(std::max<std::size_t>(1, kKeySlabVoxels / std::max<std::size_t>(1, plane)));
    slab = std::max(slab, (g.size.z + kMaxKeyParts - 1) / kMaxKeyParts);
    const int parts = (g.size.z + slab - 1) / slab;
    ++p.key_id;
    const std::string topic = brick_topic(p.session);
    // counted before they are sent (as frames)
    st.key_bricks_published.fetch_add(parts, std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(ss.mu);
      ss.report_of(p.session).key_bricks_published += parts;
    }
    for (int part = 0; part < parts; ++part) {
      const int k0 = part * slab, nk = std::min(slab, g.size.z - k0);
      msg.Clear();
      msg.set_schema_version(v1::VERSION_CURRENT);
      auto* b = msg.mutable_brick();
      b->set_session_id(p.session);
      b->set_brick_seq(++p.brick_seq);
      b->set_key(true);
      b->set_key_id(p.key_id);
      b->set_key_part(part);
      b->set_key_parts(parts);
      b->set_deformed(false);
      Voi box;
      box.lo = {0, 0, k0};
      box.size = {g.size.x, g.size.y, nk};
      geometry(b, box);
      b->set_encoding(float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16);
      b->set_compression(zstd_on ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE);
      b->set_raw_bytes(encode(&patient->intensity.data[plane * k0], plane * nk, float32, zstd_on, b->mutable_data()));
      b->set_server_time_s(now_s());
      msg.SerializeToString(&payload);
      send(topic, payload);
    }
    p.key_pending = false;
  }

  void send_voi_brick(PubSlot& p, StreamSlot& ss, const JSnapshot& j, bool float32, bool zstd_on) {
    msg.Clear();
    msg.set_schema_version(v1::VERSION_CURRENT);
    auto* b = msg.mutable_brick();
    b->set_session_id(p.session);
    b->set_brick_seq(++p.brick_seq);
    b->set_pose_seq(j.pose_seq);
    b->set_deform_step(j.step);
    b->set_deformed(j.deformed && j.host_valid);
    const Voi box = b->deformed() ? j.voi : Voi{};
    geometry(b, box);
    b->set_encoding(float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16);
    b->set_compression(zstd_on ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE);
    if (b->deformed()) b->set_raw_bytes(encode(j.host_j.data(), std::size_t(box.count()), float32, zstd_on, b->mutable_data()));
    b->set_server_time_s(now_s());
    set_vec(b->mutable_tip_mm(), j.tip_mm);
    set_vec(b->mutable_proxy_mm(), j.proxy_mm);
    msg.SerializeToString(&p.last_voi_brick);
    // counted before it is sent (as frames)
    st.bricks_published.fetch_add(1, std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(ss.mu);
      ++ss.report_of(p.session).bricks_published;
    }
    send(brick_topic(p.session), p.last_voi_brick);
  }

  void send_frame(PubSlot& p, StreamSlot& ss, const EncodedFrame& f) {
    const double now = now_s();
    msg.Clear();
    msg.set_schema_version(v1::VERSION_CURRENT);
    auto* o = msg.mutable_frame();
    o->set_session_id(f.session_id);
    o->set_frame_seq(f.frame_seq);
    o->set_pose_seq(f.pose_seq);
    o->set_pose_server_time_s(f.pose_server_time_s);
    o->set_deform_step(f.deform_step);
    o->set_deform_pose_seq(f.deform_pose_seq);
    o->set_server_time_s(now);
    const double latency_ms = f.pose_seq ? (now - f.pose_server_time_s) * 1e3 : 0.0;
    o->set_pose_to_frame_ms(latency_ms);
    o->set_width(f.view.width);
    o->set_height(f.view.height);
    o->set_jpeg(f.jpeg.data(), f.jpeg.size());
    o->set_encoder(f.encoder);
    fill_frame_times(o->mutable_times(), f.times);
    set_vec(o->mutable_tip_mm(), f.marks.tip_mm);
    set_vec(o->mutable_proxy_mm(), f.marks.proxy_mm);
    o->set_contact(f.marks.contact);
    fill_view(o->mutable_view(), f.view);
    o->set_deformed(f.deformed);
    msg.SerializeToString(&p.last_frame);
    // counted before it is sent, so that a viewer that got the frame finds it in the stats
    st.frames_published.fetch_add(1, std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(ss.mu);
      SessionStreamReport& r = ss.report_of(p.session);
      ++r.frames_published;
      if (f.pose_seq) r.pose_to_frame.add(latency_ms);
    }
    send(frame_topic(f.session_id), p.last_frame);
    p.last_frame_s = now;
    p.frame_resent = false;
    if (!scene.render.record_dir.empty()) record(p, f, now);
  }

  // render.record_dir: the frame as a JPEG file and a line of the session's index
  void record(PubSlot& p, const EncodedFrame& f, double now) {
    try {
      if (p.record_dir.empty()) {
        p.record_dir = fs::path(scene.render.record_dir) / hex_id(p.session);
        fs::create_directories(p.record_dir);
        p.record_index.open(p.record_dir / "frames.csv");
        p.record_index << "frame_seq,file,pose_seq,pose_server_time_s,server_time_s,deform_step,deformed\n";
      }
      char name[32];
      std::snprintf(name, sizeof name, "frame_%06llu.jpg", (unsigned long long)f.frame_seq);
      std::ofstream out(p.record_dir / name, std::ios::binary);
      out.write(reinterpret_cast<const char*>(f.jpeg.data()), std::streamsize(f.jpeg.size()));
      if (!out) throw Error("cannot write " + (p.record_dir / name).string());
      p.record_index << f.frame_seq << ',' << name << ',' << f.pose_seq << ',' << f.pose_server_time_s << ','
                     << now << ',' << f.deform_step << ',' << (f.deformed ? 1 : 0) << '\n';
      p.record_index.flush();
    } catch (const std::exception& e) {
      std::lock_guard<std::mutex> lock(st.info_mu);
      const std::string m = std::string("recording frames: ") + e.what();
      ++p.record_unlogged;
      if (now - p.record_logged_s >= kRecordLogPeriodS) {
        if (p.record_unlogged > 1)
          spdlog::error("{} ({} frames of this session not recorded since the last line)", m, p.record_unlogged);
        else
          spdlog::error("{}", m);
        p.record_unlogged = 0;
        p.record_logged_s = now;
      }
      st.info.last_error = m;
    }
  }


  // one session slot: watched or not, then its newest frame and brick
  void serve(int index, double now, std::uint32_t& watched_count) {
    const SessionState<PubSlot> parts = sessions.at(index);
    PubSlot& p = parts.own;
    StreamSlot& ss = *parts.stream;
    const std::uint64_t id = parts.table.id.load(std::memory_order_acquire);
    if (id != p.session) {
      // the session closed or timed out: its subscribers are told
      if (p.session != 0) {
        const std::string m = "session " + hex_id(p.session) + " closed (or timed out)";
        if (p.frames || watched(frame_topic(p.session)))
          notice(frame_topic(p.session), p.session, "closed", m, false, true);
        if (p.bricks || watched(brick_topic(p.session)))
          notice(brick_topic(p.session), p.session, "closed", m, false, true);
        exact.erase(frame_topic(p.session));
        exact.erase(brick_topic(p.session));
      }
      p.session = id;
      p.frames = p.bricks = false;
      // a brick subscriber that came before this pass noticed the session is owed a key too
      p.key_pending = id != 0 && watched(brick_topic(id));
      p.key_id = p.brick_seq = 0;
      std::string().swap(p.last_voi_brick);  // freed, not only emptied: a 4K frame is megabytes
      p.next_brick_s = 0;
      std::string().swap(p.last_frame);
      p.frame_resent = true;
      p.record_dir.clear();
      if (p.record_index.is_open()) p.record_index.close();
      p.record_unlogged = 0;
      p.record_logged_s = -1e9;
    }
    if (id == 0) {
      // (stored only on a change: the pass touches as few cache lines as it can)
      if (ss.frames_for.load(std::memory_order_relaxed)) ss.frames_for.store(0, std::memory_order_release);
      if (ss.bricks_for.load(std::memory_order_relaxed)) ss.bricks_for.store(0, std::memory_order_release);
      return;
    }
    bool float32 = false, zstd_on = false, frames_hold = false, bricks_hold = false;
    {
      std::lock_guard<std::mutex> lock(ss.mu);
      if (ss.watch.session_id == id) {
        float32 = ss.watch.brick_float32;
        zstd_on = ss.watch.brick_zstd;
        frames_hold = now < ss.watch.frames_hold_until_s;
        bricks_hold = now < ss.watch.bricks_hold_until_s;
      }
    }
    const bool frames = scene.effects.frames &&
                        (watched(frame_topic(id)) || frames_hold || !scene.render.record_dir.empty());
    const bool bricks = scene.effects.bricks && (watched(brick_topic(id)) || bricks_hold);
    p.frames = frames;
    p.bricks = bricks;
    ss.frames_for.store(frames ? id : 0, std::memory_order_release);
    ss.bricks_for.store(bricks ? id : 0, std::memory_order_release);
    if (frames || bricks) ++watched_count;
    if (frames && ss.frames.take() && ss.frames.front().session_id == id) {
      send_frame(p, ss, ss.frames.front());
    } else if (frames && !p.frame_resent && now - p.last_frame_s >= kResendAfterS) {
      // the session went quiet: its newest frame once more
      send(frame_topic(id), p.last_frame);
      p.frame_resent = true;
    }
    if (!bricks) return;
    if (p.key_pending && patient) {
      send_key(p, ss, float32, zstd_on);
      // the newest VOI brick again, after the key it belongs on
      if (!p.last_voi_brick.empty()) send(brick_topic(id), p.last_voi_brick);
    }
    // VOI bricks at most render.max_fps a second per session, the newest each time
    if (now >= p.next_brick_s && ss.j_bricks.take() && ss.j_bricks.front().session_id == id) {
      send_voi_brick(p, ss, ss.j_bricks.front(), float32, zstd_on);
      p.next_brick_s = now + 1.0 / scene.render.max_fps;
    }
  }

  void run() {
    name_this_thread("palpsim-stream");
    zmq::pollitem_t items[] = {{xpub.handle(), 0, ZMQ_POLLIN, 0}};
    while (!stop.load(std::memory_order_relaxed)) {
      zmq::poll(items, 1, std::chrono::milliseconds(kPollMs));
      // subscriptions first: who watches what
      for (;;) {
        zmq::message_t m;
        if (!xpub.recv(m, zmq::recv_flags::dontwait)) break;
        subscription(m);
      }
      pick_up_world();
      const double now = now_s();
      std::uint32_t count = 0;
      const int used = sh.slots_used.load(std::memory_order_acquire);
      for (int i = 0; i < used && !stop.load(std::memory_order_relaxed); ++i) {
        try {
          serve(i, now, count);
        } catch (const std::exception& e) {
          std::lock_guard<std::mutex> lock(st.info_mu);
          const std::string m = "stream: session " + hex_id(pub[i].session) + ": " + e.what();
          if (st.info.last_error != m) spdlog::error("{}", m);
          st.info.last_error = m;
        }
      }
      // notices due to be sent again
      for (std::size_t i = 0; i < late.size();) {
        if (late[i].due_s > now) {
          ++i;
          continue;
        }
        send(late[i].topic, late[i].payload);
        late[i] = std::move(late.back());
        late.pop_back();
      }
      st.sessions_watched.store(count, std::memory_order_relaxed);
      // nothing watched any more: the buffers sized for the largest key or frame go
      if (count == 0 && sent_since_release) release_buffers();
      sent_since_release = sent_since_release || count > 0;
      st.subscriptions.store(std::uint32_t(exact.size() + prefixes.size()), std::memory_order_relaxed);
    }
    // nobody is watched once the publisher is gone
    for (int i = 0; i < kMaxSlots; ++i) {
      st.slots[i].frames_for.store(0, std::memory_order_release);
      st.slots[i].bricks_for.store(0, std::memory_order_release);
    }
    st.sessions_watched.store(0);
    st.subscriptions.store(0);
  }
};

StreamPublisher::StreamPublisher(ServerShared& shared, StreamState& stream, const std::string& bind,
                                 std::chrono::steady_clock::time_point start, const CurveServer& curve)
    : impl_(std::make_unique<Impl>(shared, stream, start)) {
  zmq::socket_t& s = impl_->xpub;
  s.set(zmq::sockopt::linger, 0);
  s.set(zmq::sockopt::sndhwm, kSendHwm);
  s.set(zmq::sockopt::maxmsgsize, kMaxSubscriptionBytes);
  s.set(zmq::sockopt::xpub_verbose, 1);  // every subscribe (a key per brick subscriber); an unsubscribe when the last leaves
  // CURVE: this context's own ZAP handler first; subscriptions are then admitted one by
  // one (manual mode), each checked against the key that opened its session
  if (!curve.secret_key.empty()) {
    impl_->zap = std::make_unique<ZapHandler>(impl_->ctx, curve.allowed, shared.counters.curve_refused,
                                              shared.counters.curve_admitted);
    make_curve_server(s, curve.secret_key);
    s.set(zmq::sockopt::xpub_manual, 1);
    impl_->manual = true;
  }
  try {
    s.bind(bind);
  } catch (const zmq::error_t& e) {
    throw Error("--stream-bind " + bind + ": cannot bind: " + e.what());
  }
  endpoint_ = s.get(zmq::sockopt::last_endpoint);
}

StreamPublisher::~StreamPublisher() { stop(); }

void StreamPublisher::start() {
  if (thread_.joinable()) return;
  impl_->pick_up_world();
  {
    std::lock_guard<std::mutex> lock(impl_->st.info_mu);
    impl_->st.info.publisher_thread = true;
  }
  thread_ = std::thread([this] { impl_->run(); });
}

void StreamPublisher::stop() {
  impl_->stop.store(true);
  if (thread_.joinable()) thread_.join();
  impl_->sh.publish_seen_generation.store(~std::uint64_t(0), std::memory_order_release);
  std::lock_guard<std::mutex> lock(impl_->st.info_mu);
  impl_->st.info.publisher_thread = false;
}

}  // namespace palpsim::net
