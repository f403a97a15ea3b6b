// The server's deformation path: one worker thread that runs every open session's
// DeformEngine (ChainMail, relaxation, inversion; server/deform/engine.h) on the
// session's newest contact, read from the contact slot the haptic thread writes.
// Stale contacts are dropped, never queued; the haptic thread never waits for it.
// Built only when the scene asks for effects.chainmail: without it the server has no
// worker, no engine and no deformation buffer.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "core/volume.h"
#include "deform/engine.h"
#include "runtime/session_state.h"
#include "runtime/session_table.h"
#include "runtime/worker_thread.h"
#include "runtime/stream_state.h"

namespace palpsim::runtime {

/// The latest elastic step's force (deform.relax_method "elastic"; ElasticForceStats).
struct ElasticForceReport {
  bool built = false;                  // the scene's relaxation is the elastic model
  ElasticModel model;                  // the latest step's local linear model (physical; contact false before
                                       // the first step, after a release, reset or failure)
  int iterations = 0;                  // latest step: CG steps over its contact rounds
  int stiffness_iterations = 0;        // ... and of its unit press (0 unless haptics.force_model "elastic")
  bool converged = true;               // ... every round reached deform.elastic.tolerance
  std::uint64_t models_published = 0;  // models handed to the haptic thread (haptics.force_model "elastic")
};

/// One session's deformation as the worker reports it (copied out for the stats reply).
struct DeformSessionReport {
  std::uint64_t session_id = 0;
  std::string backend;                 // "cpu" or "cuda"; "" until the session's engine exists
  std::uint64_t steps = 0;             // deformation steps run
  std::uint64_t contacts_dropped = 0;  // contacts overwritten by newer ones before the worker got to them
  std::uint64_t contacts_current = 0;  // contacts served without a step: J already stood for them
  std::uint64_t non_converged = 0;     // steps that reached deform.max_sweeps (the state is kept)
  std::uint64_t failures = 0;          // steps that threw or produced a non-finite value (the state is reset)
  std::uint64_t resets = 0;            // session resets (ResetSession or PoseRequest.reset_proxy)
  std::uint64_t releases = 0;          // the tip left the body: the tissue returned to undeformed
  std::string last_error;              // the latest non-converged step or failure
  DeformTimes last;                    // stage times of the latest step (ms)
  DeformTimes sum;                     // summed over all steps (ms); mean = sum / steps
  long long moved = 0;                 // latest step: elements ChainMail moved (the first not counted)
  int sweeps = 0;                      // latest step: ChainMail sweeps
  bool converged = true;               // latest step: ChainMail converged within max_sweeps
  bool chainmail_skipped = false;      // latest step: ChainMail left out (ChainMailStats::skipped)
  std::uint64_t multigrid_solves = 0;  // steps whose multigrid relaxation solved (DeformStats::relax_solves > 0)
  std::uint64_t multigrid_warm = 0;    // ... starting from the last unit response
  std::uint64_t elastic_superposed = 0;  // elastic steps that superposed the unit press (ElasticRun::superposed)
  std::uint64_t multigrid_primes = 0;  // unit responses solved while the tip was out of the body, where it was
                                       // expected to touch (DeformEngine::prime)
  double invert_residual_vox = 0;      // latest step: max inversion residual (voxel)
  long long invert_unresolved = 0;     // latest step: voxels with a residual above 0.1 voxel
  long long invert_searched = 0;       // latest step: voxels Newton left to the cell search (deform.invert_search)
  double max_change_hu = 0;            // latest step: max |J - I| over the VOI (0 without inversion)
  bool deformed = false;               // a deformation is in place now
  std::uint64_t last_contact_seq = 0;  // pose seq of the newest contact the deformation reflects (one equal to
                                       // the latest step's contact, a held tip, is not stepped again)
  double last_step_server_time_s = 0;  // server clock when the latest step ended
  Voi voi;                             // latest step's VOI (patient voxel indices)
  DeformMemory memory;                 // what the session's engine holds (bytes)
  ElasticForceReport elastic;          // the elastic model's force
};

/// The whole deformation path of the server (all sessions, spare engines included).
struct DeformServerReport {
  bool built = false;           // the current scene asks for chainmail and the worker serves it
  bool relax = false;           // and relaxation
  bool invert = false;          // and inversion
  std::string backend;          // "cpu" or "cuda"
  std::string backend_note;     // which backend and why (DeformEngine::backend_note)
  std::uint64_t steps = 0;      // all sessions, since the current scene was set up
  std::uint64_t failures = 0;
  std::uint64_t non_converged = 0;
  std::uint64_t contacts_dropped = 0;
  DeformTimes sum;              // summed stage times of those steps (ms)
  DeformMemory memory;          // every engine the worker holds (bytes)
  std::uint64_t engines = 0;    // engines held (sessions' and spares)
  // where the worker thread's time went since the current scene was set up (s): in
  // steps (the engine's step and the worker's checks of J), napping for want of new
  // contacts, and everything else (passes, reports, exports to the stream)
  double worker_wall_s = 0;
  double worker_step_s = 0;
  double worker_sleep_s = 0;
  std::uint64_t batches = 0;        // batched launches (steps of two sessions or more sharing them)
  std::uint64_t batched_steps = 0;  // steps run in them
};

/// Runs deformation for every open session on one thread.
///
/// Why one thread for the server and not one per session: the machine this serves on
/// may have two cores, one of which the haptic thread needs; a thread per session would
/// compete with it and with each other, while one worker that round-robins sessions
/// (one step per session per pass, newest contact only) uses at most one core, shares
/// it fairly, and runs at the lowest priority (nice 19), below the haptic thread. With
/// the cuda backend it also keeps every CUDA call (engine creation, steps, destruction)
/// on one thread, and the sessions a pass finds ready are stepped together by one launch
/// per stage (cuda/batch.cu says why).
class DeformWorker {
 public:
  /// `nice`, `idle`: the thread's nice value and SCHED_IDLE (Linux; core/thread.h says why
  /// the server uses 19 and SCHED_IDLE).
  /// `concurrency`: how many sessions' steps the worker enqueues before it waits for
  /// them (each with 1/concurrency of the GPU; 1: one step at a time, as before).
  /// `batch`: how many sessions ready in one pass are stepped together at most, with one
  /// launch per stage where the backend can (DeformEngine::begin_steps); 1: none is.
  DeformWorker(ServerShared& shared, std::chrono::steady_clock::time_point start, int nice, bool idle,
               int concurrency = 1, int batch = 1);
  ~DeformWorker();
  DeformWorker(const DeformWorker&) = delete;
  DeformWorker& operator=(const DeformWorker&) = delete;

  /// Starts the thread and waits until it has set up the current world (chosen the
  /// backend, logged it, built and validated one engine); throws palpsim::Error with
  /// the engine's message when the scene's deformation cannot be served.
  void start();
  /// Stops and joins the thread; engines are destroyed on it (idempotent).
  void stop();

  /// The deformation of an open session; false when the worker does not know it.
  bool session_report(std::uint64_t session_id, DeformSessionReport& out) const;
  /// The whole deformation path.
  DeformServerReport server_report() const;

  /// Copies the session's whole deformed image (J in its VOI, I elsewhere) as the
  /// worker holds it between two steps; waits up to `timeout_s` for the worker to
  /// answer. False when the session is unknown or the worker did not answer. For tests
  /// and tools: the copy is made on the worker thread, never on the haptic path.
  bool deformed_volume(std::uint64_t session_id, Volume<float>& out, double timeout_s);

 private:
  struct Session;
  struct Request;
  using Parts = SessionState<Session>;  // a session's parts, this worker's own included
  void run();
  void set_up_world();
  bool serve(int index);
  bool serve_deformation(const Parts& p);
  void export_watched(const Parts& p);
  void fill_snapshot(JSnapshot& out, Session& s, bool device);
  void step(const Parts& p, const Contact& c);      // begins the step (in flight) or readies it for a batch
  bool prime(const Parts& p, const Vec3& tip_mm);   // primes the unit response where a tip out of the body will touch; true: it ran
  void begin_ready();                               // begins the readied steps, batched
  void complete_inflight();                         // finishes every step in flight, in order
  void complete(const Parts& p, const Contact& c);  // finishes one: checks, counts, reports
  void fail(const Parts& p, const Contact& c, const std::exception& e);  // a step that threw: reset, counted
  void reset(const Parts& p);
  std::unique_ptr<DeformEngine> take_engine();
  void give_back(std::unique_ptr<DeformEngine> engine);
  void publish(const Parts& p);
  void publish_elastic(const Parts& p, const ElasticModel& m);  // the session's newest model, to stats and the haptic thread
  void publish_worker_times();  // the worker's wall, step and nap times into server_ (report_mu_ held)
  void answer_request();
  double now_s() const;

  ServerShared& sh_;
  std::chrono::steady_clock::time_point start_;
  int nice_ = 19;
  bool idle_ = true;
  WorkerThread thread_;  // keeps the world-pinning rule (ServerShared::deform_seen_generation)

  // (worker) the world being served and its engines
  std::uint64_t generation_ = 0;
  PatientPtr patient_;
  DeformConfig config_;
  bool built_ = false;
  std::vector<Session> sessions_;                       // by slot index
  SessionStates<Session> parts_{sh_, sessions_};       // each slot's parts: the table's, the stream's, sessions_'
  std::vector<std::unique_ptr<DeformEngine>> spares_;  // engines of closed sessions, reused
  // steps begun and not yet finished: the slot and its contact
  struct Inflight {
    int index;
    Contact contact;
  };
  std::vector<Inflight> inflight_;
  std::vector<Inflight> ready_;  // steps readied in this pass, begun together by begin_ready()
  std::vector<DeformEngine*> batch_engines_;    // begin_ready()'s batch, kept to reuse their room
  std::vector<DeformContact> batch_contacts_;
  int max_inflight_ = 1;  // steps in flight at most (ServerOptions::deform_concurrency)
  int max_batch_ = 1;     // sessions begun together at most (ServerOptions::deform_batch)
  bool prime_ = false;    // the scene's relaxation can be primed (multigrid, reuse, warm starts)
  Vec3 body_centroid_vox_{0, 0, 0};  // the patient's body centroid (deform::expected_skin_voxel)
  int prime_radius_vox_ = 0;         // the near search's reach: half a VOI edge (voxels)
  Vec3 grid_centre_mm_{0, 0, 0};     // where a session primes before its first pose (mm)
  int gpu_share_ = 1;     // this pass: min(max_inflight_, open sessions)
  double min_watched_step_s_ = 0;  // least time between steps of a session whose frames are watched (s)
  std::chrono::steady_clock::time_point world_start_;  // when the current scene was set up
  double step_s_ = 0, sleep_s_ = 0;                    // the worker's time in steps and naps since then
  double batch_share_ = 0;                             // batched steps since then, each 1/batch of a batch
  std::uint64_t batched_steps_ = 0;                    // ... counted

  // (worker writes, others read under report_mu_) what stats show
  mutable std::mutex report_mu_;
  std::vector<DeformSessionReport> reports_;  // by slot index; session_id 0: none
  std::size_t slot_bytes_ = 0;                // what sessions_ and reports_ hold (bytes)
  DeformServerReport server_;

  // deformed_volume() requests: one at a time, answered between steps
  std::mutex request_mu_;             // requesters among themselves
  std::mutex mailbox_mu_;             // the mailbox below
  std::condition_variable mailbox_cv_;
  std::atomic<bool> request_pending_{false};
  std::unique_ptr<Request> request_;
};

}  // namespace palpsim::runtime
