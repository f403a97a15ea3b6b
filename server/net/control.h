// The control thread of palpsim-server (Server::Control): its sockets, the world it
// serves, the workers it starts, and the control requests. One dispatcher (control.cpp:
// sockets, the request loop, refusals, ServerInfo, housekeeping) hands each request to
// its concern's unit: sessions (control_sessions.cpp: open, close, reset, set parameter),
// watch (control_watch.cpp: WatchSession, PickRequest), stats (control_stats.cpp) and
// scene loading (control_load.cpp). Private to server/net; protobuf stays behind it.
#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "core/path_policy.h"
#include "net/curve_keys.h"
#include "net/server.h"
#include "net/stream_publisher.h"
#include "net/zap_handler.h"
#include "palpsim/wire.pb.h"
#include "runtime/deform_worker.h"
#include "runtime/render_worker.h"
#include "runtime/session_table.h"
#include "runtime/stream_state.h"

namespace palpsim::net {

namespace v1 = ::palpsim::v1;
using Clock = std::chrono::steady_clock;
using runtime::DeformServerReport;
using runtime::DeformSessionReport;
using runtime::DeformWorker;
using runtime::hex_id;
using runtime::kMaxSlots;
using runtime::kSlotBits;
using runtime::make_world;
using runtime::RenderWorker;
using runtime::ServerShared;
using runtime::SessionSlot;
using runtime::StreamState;
using runtime::World;

/// Copies haptics parameters into their wire message.
void fill_params(v1::HapticsParams* out, const HapticsSettings& s);

/// The control thread: sockets, world ownership, control requests, housekeeping.
class Server::Control {
 public:
  Control(ServerShared& sh, const Scene& scene, PatientPtr patient, PatientLoader loader, const ServerOptions& o);
  ~Control() { end_load(); }
  Clock::time_point start() const { return start_; }

  // starts the deformation worker when the scene being served asks for chainmail
  // (throws the worker's set-up error); with none asked for, nothing is built
  void start_deform();
  // stops it (its engines are destroyed on its own thread)
  void stop_deform();

  // the publisher and the render thread as the scene being served asks: started for
  // frames or bricks (the render thread for frames only), stopped for a scene without
  // them. Throws when they cannot be started (the start of the server refuses the scene).
  void sync_stream();
  // stops both (GL objects are destroyed on the render thread)
  void stop_stream();
  // true while the render thread serves frames (its encoder is set up)
  bool frames_served() const;
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

  // closes the sockets after the threads have ended
  void close();

  // waits for a running LoadScene's loader thread (after the control thread has ended);
  // its reply is not sent
  void end_load();

  // the control thread's loop: requests, finished loads and housekeeping until stop
  void run();

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

  // --- the dispatcher (control.cpp)
  std::string bind(zmq::socket_t& s, const std::string& addr, const char* option);
  const World& world() const { return *current_; }
  // the slot of an open session, or nullptr
  SessionSlot* find(std::uint64_t id) {
    if (id == 0) return nullptr;
    SessionSlot& s = sh_.slots[runtime::slot_index(id)];
    return s.id.load(std::memory_order_acquire) == id ? &s : nullptr;
  }
  // reads every waiting control request, checks its frames and answers it
  void drain();
  // sends rep_ to `routing_id` (after an empty delimiter for a REQ); never blocks
  void send_reply(const zmq::message_t& routing_id, bool req_envelope);
  // who sent the request being handled: its CURVE key (the ZAP handler's user id), else
  // its client token, else its control connection (the ROUTER's routing id)
  std::string identity(const zmq::message_t& routing_id, const std::string& user);
  // true when the requester opened session `s`; else refuses with ERROR_NOT_OWNER
  bool owned(const SessionSlot& s, std::uint64_t id, const std::string& field);
  // makes rep_ an error reply with `code` and `message` (made safe), counts and logs it
  void refuse(v1::ErrorCode code, std::atomic<std::uint64_t>& counter, const std::string& message);
  // checks the request's envelope fields and hands it to its concern's handler
  void handle();
  // the slot of an open session the requester owns, or nullptr after refusing; its last
  // message time is updated, and with `use` (a request acting on it, not Stats) its idle clock
  SessionSlot* session_or_refuse(std::uint64_t id, const char* field, bool use = true);
  // the ServerInfo of the world being served
  void fill_info(v1::ServerInfo* info);
  // how the requester is known, for messages (its key, token or connection is not echoed)
  const char* requester_kind() const;
  // says so when one client may hold every session of the scene being served
  void warn_quota() const;
  // frees timed-out sessions and retired worlds, and logs a summary of new bad input
  void housekeeping();

  // --- sessions (control_sessions.cpp)
  int open_count() const;
  void open();
  void free_session(SessionSlot& s) { s.id.store(0, std::memory_order_release); }
  // "; deformation: ..." for a session's close or timeout log line ("" without deformation)
  std::string deform_summary(std::uint64_t id) const;
  void close_session();
  void reset();
  void set_parameter();

  // --- watch (control_watch.cpp)
  // WatchSession: a session's frames or bricks, with its view
  void watch();
  // the skin point under a pixel of a session's frame: its view's ray, first body hit
  void pick();

  // --- stats (control_stats.cpp)
  void stats();
  void fill_deform(v1::DeformSessionStats* o, const DeformSessionReport& r);
  // frames and bricks in the stats: server-wide, and one session's
  void fill_stream(v1::ServerStats* s, google::protobuf::RepeatedPtrField<v1::StageInfo>* stages);
  void fill_session_stream(v1::SessionStats* out, std::uint64_t id);

  // --- scene loading (control_load.cpp)
  // LoadScene: refused at once while another runs; else the scene is read, checked and its
  // patient prepared on a loader thread (prepare_world) and the request answered when that
  // ends (finish_load), so that every other control request is answered meanwhile
  void load_scene();
  // (loader thread) the world of a LoadScene's scene, or why it is refused, into `l`; then
  // wakes the control thread. Reads only what no other thread writes (options, folders, loader).
  void prepare_world(Load& l, const std::string& path, const std::string& text);
  // answers the LoadScene whose loader thread has ended: its world is served from now on,
  // or the refusal is sent and the old one kept
  void finish_load();
};

}  // namespace palpsim::net
