// palpsim-server's network side: a control ROUTER (open, close, reset, set parameter,
// stats, info, load scene) on its own thread, and a pose ROUTER answered by the haptic
// thread (net/pose_service.h). Protocol: proto/PROTOCOL.md. Protobuf stays behind
// this header.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "core/patient.h"
#include "core/scene.h"
#include "core/volume.h"
#include "haptics/contact_slot.h"

namespace palpsim::runtime {
struct ServerShared;
class HeapTrimmer;
}  // namespace palpsim::runtime

namespace palpsim::net {

/// Prepares the patient of a scene (palpsim::prepare_patient in the real server; tests
/// may pass a synthetic one). Throws palpsim::Error for a scene that cannot be served.
using PatientLoader = std::function<PatientPtr(const Scene&)>;

/// Where and how the server listens.
struct ServerOptions {
  std::string control_bind = "tcp://127.0.0.1:7420";  // the control ROUTER's address
  std::string pose_bind;                                // "" = derived (derive_pose_endpoint)
  double max_pose_distance_mm = 1000;                   // poses farther from the patient grid are refused
  int housekeeping_ms = 100;                            // control thread: timeouts, freeing old worlds
  // sessions one client (CURVE key, else client token, else control connection) may hold
  // open at once: below the scene's max_sessions (64 by default), one client cannot take
  // every session
  int max_sessions_per_client = 16;
  // a session without a pose or a control request acting on it (Stats does not) for this
  // long is freed (s; 0 = never), beside the scene's server.session_timeout_s for silence
  double idle_timeout_s = 60;
  double bad_input_log_period_s = 5;                    // log a summary of new bad input at most this often
  // the pose thread and the I/O thread of the pose socket (a ZeroMQ context of its own) run
  // under SCHED_FIFO at this priority (1..99) where the process may (root or CAP_SYS_NICE),
  // so that the haptic path keeps a core when clients, floods or other programs load the
  // machine; 0, or where it may not, under the normal policy (the log says which)
  int pose_priority = 10;
  int deform_nice = 19;                                 // the deformation and render threads' nice value (Linux; 0..19)
  bool background_idle = true;                          // and SCHED_IDLE for them (Linux; core/thread.h says why)
  // sessions' deformation steps in flight on the GPU at once, for steps that are not
  // batched (deform_batch 1, or scenes with multigrid relaxation or untangling). 1 by
  // default: more lets sessions step more often but takes GPU time from watched
  // sessions' frames (bench/results/render-2026-11-23-h100-deform-concurrency4.json); a
  // server without viewers (batch studies) may raise it
  int deform_concurrency = 1;
  // sessions stepped together by one batched launch per stage at most (DeformWorker; cuda
  // with the same settings: cuda/batch.cu); 1 steps one session at a time, as before
  int deform_batch = 64;
  std::string stream_bind;                              // the stream publisher's XPUB address; "" = derived (derive_stream_endpoint)
  std::vector<std::string> scene_dirs;                  // folders LoadScene may read (scene file, CT) and write
                                                        // (render.record_dir) in; none: LoadScene names no file
  bool insecure = false;                                // allow addresses beyond loopback (plain text on the network)
  std::string curve_secret_key;                         // z85 server secret key: every socket is a CURVE server
                                                        // ("" = plain text, loopback unless insecure)
  std::vector<std::string> curve_allowed_keys;          // z85 client public keys admitted with CURVE (at least one)
};

/// True for addresses only this machine can reach: tcp on 127.x.x.x, localhost, [::1]
/// or the lo interface, ipc:// and inproc://. The server binds anything else only with
/// CURVE keys (ServerOptions::curve_secret_key) or ServerOptions::insecure.
bool is_loopback_endpoint(const std::string& endpoint);

/// The default pose address for a control address: tcp port + 1 ("*" stays "*"),
/// ipc://P -> ipc://P.pose, inproc://N -> inproc://N-pose.
std::string derive_pose_endpoint(const std::string& control);

/// The default stream (frames and bricks) address for a control address: tcp port + 2
/// ("*" stays "*"), ipc://P -> ipc://P.stream, inproc://N -> inproc://N-stream.
std::string derive_stream_endpoint(const std::string& control);

/// The server: binds both sockets in the constructor (throws palpsim::Error naming the
/// address when it cannot), serves from start() until stop() or destruction.
class Server {
 public:
  Server(const Scene& scene, PatientPtr patient, PatientLoader loader, const ServerOptions& options);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  /// Starts the control and haptic threads, the deformation worker when the scene asks
  /// for chainmail, the stream publisher for frames or bricks and the render thread for
  /// frames; throws palpsim::Error when the scene's deformation or frames cannot be
  /// served (an unavailable backend, a refused setting, no OpenGL 4.5 context).
  void start();
  /// Stops both threads and closes the sockets (idempotent).
  void stop();

  /// The bound control address (with the real port when bound to "*").
  const std::string& control_endpoint() const { return control_endpoint_; }
  /// The bound pose address.
  const std::string& pose_endpoint() const { return pose_endpoint_; }
  /// The bound stream (frames and bricks) address; "" while the scene asks for neither.
  std::string stream_endpoint() const;

  /// Hook for the deformation path: the newest contact slot of an open session, or
  /// nullptr. The slot lives as long as the server; a reader polls it at its own rate.
  const ContactSlot* contact_slot(std::uint64_t session_id) const;
  /// Ids of the sessions open now (a snapshot).
  std::vector<std::uint64_t> open_sessions() const;

  /// True while a deformation worker runs (a scene with effects.chainmail was served).
  bool deformation_running() const;
  /// The session's whole deformed image as the deformation worker holds it now (J in
  /// its VOI, I elsewhere). False when no worker runs, the session is unknown, or the
  /// worker did not answer within `timeout_s`. For tests and tools: the copy is made on
  /// the worker's thread between two steps, never on the haptic path.
  bool deformed_volume(std::uint64_t session_id, Volume<float>& out, double timeout_s = 10) const;

 private:
  class Control;
  std::unique_ptr<runtime::ServerShared> shared_;
  std::unique_ptr<Control> control_;
  std::string control_endpoint_, pose_endpoint_;
  std::thread pose_thread_, control_thread_, patch_thread_;
  std::unique_ptr<runtime::HeapTrimmer> heap_trimmer_;  // gives freed memory back to the system while serving
  bool started_ = false;
};

}  // namespace palpsim::net
