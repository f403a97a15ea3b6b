// palpsim-haptic: the thin haptic client. Opens a session on a palpsim-server, runs a
// fixed-rate loop (1 kHz, up to 4 kHz) that reads the device, sends the newest pose,
// applies the newest force that has come back, and never waits on the network; a
// watchdog ramps the force to zero when replies stop. Far from the server (a round trip
// over 8 ms) it renders eq. 2 itself from patches of F the server sends (local_model.h).
// Logs every step to CSV and prints round-trip percentiles, missed deadlines and the
// rendered force against the server's at exit. A session the server no longer knows (it
// restarted) or a server silent for 2 s gets the session reopened, without stopping the
// loop. Protocol: proto/PROTOCOL.md.
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <poll.h>
#include <cstdio>
#include <cstring>
#include <memory>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "control_link.h"
#include "device.h"
#include "endpoint.h"
#include "local_model.h"
#include "options.h"
#include "core/thread.h"
#include "net/curve_keys.h"
#include "palpsim/wire.pb.h"

namespace v1 = palpsim::v1;
using palpsim::Vec3;
using palpsim::haptic::kMaxPatchEdge;
using palpsim::haptic::Options;
using palpsim::haptic::parse_options;
using palpsim::haptic::RenderMode;
using palpsim::haptic::V3;
using Clock = std::chrono::steady_clock;

namespace {

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

double seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return std::nan("");
  const std::size_t k = std::min(v.size() - 1, std::size_t(q * double(v.size())));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

// a pose reply or none this long (s) and the session is reopened: far above any round trip
// the client works with (local mode starts at 8 ms; a cold link's first reply takes about 4
// round trips), so only a server that is gone, or serves poses elsewhere now, is left
constexpr double kReopenAfterS = 2.0;
// a reopen request without a reply is sent again, on a fresh connection, after this long (s)
constexpr double kReopenRetryS = 1.0;

// decodes a LocalForceModel into `out` (vectors resized within their reserved room);
// false with `why` set for a patch that does not hold together
bool decode_patch(const v1::LocalForceModel& m, palpsim::ForcePatch& out, const char*& why) {
  const palpsim::Vec3i size{int(m.size_i()), int(m.size_j()), int(m.size_k())};
  const std::size_t n = std::size_t(m.size_i()) * m.size_j() * m.size_k();
  why = nullptr;
  if (m.size_i() == 0 || m.size_i() > kMaxPatchEdge || m.size_j() == 0 || m.size_j() > kMaxPatchEdge ||
      m.size_k() == 0 || m.size_k() > kMaxPatchEdge)
    why = "LocalForceModel.size_*: outside 1..16";
  else if (m.body().size() != n || m.force().size() != n * sizeof(float) || m.grad_force().size() != n * 3 * sizeof(float))
    why = "LocalForceModel.body/force/grad_force: lengths do not match size_i*size_j*size_k";
  else if (m.direction_size() != 9 || !(m.spacing_mm() > 0) || m.version() == 0)
    why = "LocalForceModel.direction/spacing_mm/version: missing or not positive";
  if (why) return false;
  palpsim::Grid& g = out.grid;
  g.size = size;
  g.spacing_mm = {m.spacing_mm(), m.spacing_mm(), m.spacing_mm()};
  g.origin_mm = {m.origin_mm().x(), m.origin_mm().y(), m.origin_mm().z()};
  for (int i = 0; i < 9; ++i) g.direction[std::size_t(i)] = m.direction(i);
  out.lo = {int(m.lo_i()), int(m.lo_j()), int(m.lo_k())};
  out.patient_size = {int(m.grid_size_i()), int(m.grid_size_j()), int(m.grid_size_k())};
  // little-endian float32 on the wire, as on the hosts palpsim builds for
  out.body.resize(n);
  out.force_mm.resize(n);
  out.grad_force.resize(n);
  std::memcpy(out.body.data(), m.body().data(), n);
  std::memcpy(out.force_mm.data(), m.force().data(), n * sizeof(float));
  std::memcpy(out.grad_force.data(), m.grad_force().data(), n * sizeof(palpsim::Vec3f));
  out.params.stiffness_n_per_mm = m.stiffness_n_per_mm();
  out.params.friction = m.friction();
  out.params.max_force_n = m.max_force_n();
  out.params.max_force_rate_n_per_s = m.max_force_rate_n_per_s();
  out.params.min_gradient_norm = m.min_gradient_norm();
  out.version = m.version();
  out.generation = m.scene_generation();
  out.center_mm = {m.center_mm().x(), m.center_mm().y(), m.center_mm().z()};
  return true;
}

Vec3 to_vec(const V3& v) { return {v.x, v.y, v.z}; }

// puts the loop under SCHED_FIFO at `priority` where allowed (0: the normal policy); ZeroMQ's
// I/O thread, started with the first socket, inherits the policy
void raise_priority(int priority) {
  if (priority <= 0) return;
  if (palpsim::raise_this_thread(priority))
    spdlog::info("the loop and its network thread under SCHED_FIFO, priority {}", priority);
  else
    spdlog::info("the loop under the normal policy: SCHED_FIFO is not allowed here (root or CAP_SYS_NICE needed; "
                 "--priority 0 asks for the normal policy)");
}

// the connection to the server: the control link, the session and its pose socket
struct Connection {
  zmq::context_t ctx{1};
  std::function<void(zmq::socket_t&)> setup;  // every socket's CURVE keys (none without)
  std::unique_ptr<palpsim::haptic::ControlLink> link;
  std::unique_ptr<zmq::socket_t> pose;        // the session's pose socket (a fresh one per session)
  std::string pose_addr;
  v1::ControlRequest open;  // the OpenSession request, sent again to reopen the session
  std::uint64_t request_id = 0;
  std::uint64_t session = 0;

  // a DEALER to `endpoint` for a session's poses
  std::unique_ptr<zmq::socket_t> make_pose_socket(const std::string& endpoint) {
    auto s = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
    s->set(zmq::sockopt::linger, 0);
    if (setup) setup(*s);
    s->connect(endpoint);
    return s;
  }
  // the pose socket of the session `opened` names (or of --pose-via)
  void connect_poses(const v1::OpenReply& opened, const Options& o) {
    pose_addr = o.pose_via.empty() ? palpsim::haptic::resolve_endpoint(opened.pose_endpoint(), o.addr) : o.pose_via;
    pose = make_pose_socket(pose_addr);
  }
  // the request that closes session `id`, with the next request id
  v1::ControlRequest close_request(std::uint64_t id, const std::string& client_token) {
    v1::ControlRequest close;
    close.set_schema_version(v1::VERSION_CURRENT);
    close.set_request_id(++request_id);
    close.set_client_token(client_token);
    close.mutable_close()->set_session_id(id);
    return close;
  }
};

// opens the session (CURVE on both sockets when keys are given, the files checked before
// anything is sent), makes the device within the patient's bounds, takes the session's
// haptics settings and opens the step log; false, with one line on stderr, when one fails
bool open_session(const Options& o, Connection& c, std::unique_ptr<palpsim::haptic::Device>& device, std::FILE*& log,
                  palpsim::HapticsSettings& params) {
  const bool curve = !o.server_key_file.empty();
  try {
    if (curve) {
      const std::string server_key = palpsim::net::read_public_key_file(o.server_key_file);
      const auto client_key = palpsim::net::read_secret_key_file(o.client_key_file);
      c.setup = [server_key, client_key](zmq::socket_t& s) {
        palpsim::net::make_curve_client(s, server_key, client_key);
      };
    }
    // open the session; the reply names the pose address and the patient's bounds
    c.link = std::make_unique<palpsim::haptic::ControlLink>(c.ctx, o.addr, c.setup, curve);
    c.open.set_schema_version(v1::VERSION_CURRENT);
    c.open.set_request_id(++c.request_id);
    c.open.set_client_token(o.client_token);
    c.open.mutable_open()->set_client_name(o.name);
    const v1::ControlReply opened = c.link->call(c.open, 5000);
    c.session = opened.open().session_id();
    const auto& pi = opened.open().server().patient();
    palpsim::haptic::PatientBox box;
    box.body_min_mm = {pi.body_min_mm().x(), pi.body_min_mm().y(), pi.body_min_mm().z()};
    box.body_max_mm = {pi.body_max_mm().x(), pi.body_max_mm().y(), pi.body_max_mm().z()};
    device = palpsim::haptic::make_device(o.device_spec, box);
    const auto& op = opened.open().params();
    params.stiffness_n_per_mm = op.stiffness_n_per_mm();
    params.friction = op.friction();
    params.max_force_n = op.max_force_n();
    params.max_force_rate_n_per_s = op.max_force_rate_n_per_s();
    params.min_gradient_norm = op.min_gradient_norm();
    c.connect_poses(opened.open(), o);
    spdlog::info("session {:016x} on {} (poses {}), device: {}, {} Hz", c.session, o.addr, c.pose_addr,
                 device->describe(), o.rate_hz);
    if (!o.log_path.empty()) {
      log = std::fopen(o.log_path.c_str(), "w");
      if (!log) throw std::runtime_error(o.log_path + ": cannot write the log");
      std::setvbuf(log, nullptr, _IOFBF, 1 << 20);
      std::fprintf(log,
                   "step,time_s,tip_x_mm,tip_y_mm,tip_z_mm,force_x_n,force_y_n,force_z_n,rtt_us,reply_seq,contact,"
                   "depth_mm,watchdog_scale,mode,local_weight,patch_version,energy_mj,server_force_x_n,server_force_y_n,"
                   "server_force_z_n\n");
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-haptic: error: %s\n", e.what());
    return false;
  }
  return true;
}

// the fixed-rate loop on an open session and everything it counts for the summary: it reads
// the device, sends the newest pose, renders the newest force and never waits on the network
struct Loop {
  Loop(const Options& o, Connection& c, palpsim::haptic::Device& device, std::FILE* log,
       const palpsim::HapticsSettings& params);

  // runs steps until the device's path ends, --seconds have passed or a signal came
  void run();
  // collects the replies still in flight (up to 1 s), closes the log and the session
  void drain_and_close();
  // prints the summary on stdout; the exit code: 0 when every pose was answered without error, else 3
  int print_summary() const;

  // the device's tip at loop time t (s): held at the path's start through the warm-up;
  // false when the path has ended or --seconds have passed
  bool device_tip(double t, V3& tip);
  // takes every reply that has come back, timestamped on arrival: round trips, the newest
  // force, patches, and the server's force to compare with what was rendered for that pose
  void take_replies();
  // the server's forces along the path, pose by pose in order (a pose whose reply is lost
  // keeps the force before it; one older than a second is taken as lost)
  void advance_server_energy(std::uint64_t upto, bool final);
  // reopens the session when the server no longer knows it or has gone silent
  void keep_session(double t);
  // sends step n's pose, never waiting
  void send_pose(double t, const V3& tip, RenderMode mode);
  // the watchdog's scale of the force at loop time t (s); trips are counted and logged
  double watchdog(double t, RenderMode mode);
  // one CSV line of step n
  void write_log(double t, const V3& tip, const V3& applied, double scale, RenderMode mode,
                 const palpsim::haptic::RenderStep& r);
  // waits for `deadline`, taking replies as they arrive
  void wait_until(Clock::time_point deadline);

  const Options& o;
  Connection& c;
  palpsim::haptic::Device& device;
  std::FILE* log;

  // rings by sequence number (replies older than the ring are counted late): send times,
  // tips sent and forces rendered, and the server's force for each pose
  static constexpr std::size_t ring = 1 << 14;
  std::vector<double> sent_at = std::vector<double>(ring, -1.0);
  std::vector<Vec3> tip_at = std::vector<Vec3>(ring), rendered_at = std::vector<Vec3>(ring),
                    server_at = std::vector<Vec3>(ring);
  std::vector<std::uint64_t> server_seq = std::vector<std::uint64_t>(ring, 0);  // the seq server_at holds (0: none)
  std::vector<double> rtts_us;
  v1::PoseRequest req;
  v1::PoseReply rep;
  std::string out;
  zmq::message_t in;

  // local rendering: the renderer and the mode selector (local_model.h)
  palpsim::haptic::LocalRenderer renderer;
  palpsim::haptic::ModeSelector selector;
  std::uint64_t patches = 0, bad_patches = 0, patch_misses = 0, mode_switches = 0, local_steps = 0,
                rate_limited = 0;
  std::string first_bad_patch;
  // the rendered force against the server's for the same pose, and the server's energy
  double err_sq = 0, err_max = 0, server_peak = 0;
  std::uint64_t compared = 0, energy_cursor = 0;
  // the warm-up: the first pose of the device's path (the comparison starts there), when the
  // first reply and the first patch arrived (s), and the watchdog trips before the path
  std::uint64_t path_seq = 0, warmup_trips = 0;
  double first_reply_s = -1, first_patch_s = -1, path_t0 = 0;
  palpsim::EnergyMeter server_energy;

  double period_s;
  Clock::time_point t0;
  Vec3 force{0, 0, 0};             // the newest force from the server
  std::uint64_t newest_seq = 0;    // the seq that force belongs to
  double last_reply_t = 0;         // loop time of the newest reply
  bool watchdog_on = false, contact = false;
  double depth = 0;
  std::uint64_t steps = 0, missed = 0, replies = 0, errors = 0, late = 0, watchdog_trips = 0;
  std::string first_error;

  double rtt_step = std::nan("");  // the newest round trip measured since the previous step
  std::uint64_t n = 0;              // the step being run (its pose's seq)
  double last_watchdog_log_t = -1, prev_t = 0;
  // reopening the session: the server said it no longer knows it, when anything was last heard
  // on the pose socket (loop time, s), when the open request went out (< 0: none), how often
  bool session_unknown = false;
  double last_heard_t = 0, reopen_sent_t = -1, first_reopen_t = -1, last_reopen_log_t = -1;
  std::uint64_t reopens = 0;
  int pose_fd;
};

Loop::Loop(const Options& o, Connection& c, palpsim::haptic::Device& device, std::FILE* log,
           const palpsim::HapticsSettings& params)
    : o(o), c(c), device(device), log(log), renderer(params, kMaxPatchEdge), period_s(1.0 / o.rate_hz) {
  rtts_us.reserve(std::size_t(o.rate_hz * (o.warmup_s + (o.max_seconds > 0 ? o.max_seconds : 60))) + 1024);
  req.set_schema_version(v1::VERSION_CURRENT);
  req.set_session_id(c.session);
  if (o.mode_name != "auto") selector.force(o.mode_name == "local" ? RenderMode::kLocal : RenderMode::kRemote);
  pose_fd = c.pose->get(zmq::sockopt::fd);
}

void Loop::take_replies() {
  while (c.pose->recv(in, zmq::recv_flags::dontwait)) {
    const double now = seconds(Clock::now() - t0);
    last_heard_t = now;
    if (!rep.ParseFromArray(in.data(), int(in.size()))) {
      ++errors;
      continue;
    }
    if (rep.has_error() && rep.error().code() != v1::ERROR_NONE) {
      if (first_error.empty()) first_error = v1::ErrorCode_Name(rep.error().code()) + ": " + rep.error().message();
      if (rep.error().code() == v1::ERROR_UNKNOWN_SESSION && rep.session_id() == c.session) session_unknown = true;
      ++errors;
      continue;
    }
    ++replies;
    if (first_reply_s < 0) first_reply_s = now;
    const std::uint64_t s = rep.seq();
    const Vec3 fs{rep.force_n().x(), rep.force_n().y(), rep.force_n().z()};
    // the patch first, so that the round trip of the reply that brings the first one can switch to local
    if (rep.has_local_model()) {
      const char* why = nullptr;
      if (decode_patch(rep.local_model(), renderer.incoming(), why)) {
        if (renderer.accept_incoming(now)) ++patches;
        if (first_patch_s < 0) first_patch_s = now;
        selector.set_patch_available(true);
      } else {
        if (first_bad_patch.empty()) first_bad_patch = why;
        ++bad_patches;
      }
    }
    if (s + ring > n && s <= n && sent_at[s % ring] >= 0) {
      rtt_step = (now - sent_at[s % ring]) * 1e6;
      rtts_us.push_back(rtt_step);
      if (selector.add_round_trip(rtt_step * 1e-6, now)) {
        ++mode_switches;
        std::printf("palpsim-haptic: mode %s at t = %.3f s (round trip %.1f ms)\n",
                    selector.mode() == RenderMode::kLocal ? "local" : "remote", now, selector.round_trip_s() * 1e3);
      }
      // what was rendered at step s against the server's force for pose s (from the path's start)
      if (path_seq && s >= path_seq) {
        const Vec3 d = rendered_at[s % ring] - fs;
        err_sq += palpsim::dot(d, d);
        err_max = std::max(err_max, palpsim::norm(d));
        server_peak = std::max(server_peak, palpsim::norm(fs));
        ++compared;
      }
      server_at[s % ring] = fs;
      server_seq[s % ring] = s;
    } else {
      ++late;
    }
    if (s > newest_seq) {
      newest_seq = s;
      force = fs;
      contact = rep.contact();
      depth = rep.depth_mm();
      last_reply_t = now;
    }
  }
}

void Loop::advance_server_energy(std::uint64_t upto, bool final) {
  while (energy_cursor + 1 < upto) {
    const std::uint64_t s = energy_cursor + 1;
    const bool have = server_seq[s % ring] == s;
    if (!have && !final && s + std::uint64_t(o.rate_hz) > upto) break;
    if (s > 1) server_energy.move(tip_at[s % ring] - tip_at[(s - 1) % ring]);
    if (have) server_energy.set_force(server_at[s % ring], server_at[s % ring] != Vec3{0, 0, 0});
    energy_cursor = s;
  }
}

// the session, reopened when the server no longer knows it (it restarted, or the session
// timed out) or nothing came back on the pose socket for kReopenAfterS: the open request
// goes out and its reply is picked up step by step while the loop goes on (the watchdog
// has taken the force to zero); poses then go to the new session on a fresh socket
void Loop::keep_session(double t) {
  v1::ControlReply r;
  bool parsed = false;
  if (c.link->waiting() && c.link->take(r, &parsed)) {
    if (parsed && r.has_open() && r.open().session_id() != 0) {
      const std::uint64_t old = c.session;
      c.session = r.open().session_id();
      req.set_session_id(c.session);
      c.connect_poses(r.open(), o);
      pose_fd = c.pose->get(zmq::sockopt::fd);
      renderer.reset_proxy();
      ++reopens;
      if (first_reopen_t < 0) first_reopen_t = t;
      spdlog::info("session {:016x} reopened at t = {:.3f} s (poses {}), after {:016x} {}", c.session, t, c.pose_addr,
                   old, session_unknown ? "was no longer known to the server" : "went unanswered");
      // a server that was only slow still holds the old session: it is closed (the reply is not awaited)
      if (!session_unknown) c.link->start(c.close_request(old, o.client_token));
      session_unknown = false;
      last_heard_t = t;
      reopen_sent_t = -1;
      return;
    }
    if (reopen_sent_t >= 0 && (last_reopen_log_t < 0 || t - last_reopen_log_t >= 1.0)) {
      spdlog::warn("reopening the session: {}",
                   !parsed ? std::string("a reply that does not parse")
                           : r.has_error() ? v1::ErrorCode_Name(r.error().code()) + ": " + r.error().message()
                                           : std::string("a reply without a session"));
      last_reopen_log_t = t;
    }
  }
  const bool due = session_unknown || t - last_heard_t > kReopenAfterS;
  if (due && (reopen_sent_t < 0 || t - reopen_sent_t >= kReopenRetryS)) {
    c.open.set_request_id(++c.request_id);
    c.link->start(c.open);
    reopen_sent_t = t;
  }
}

bool Loop::device_tip(double t, V3& tip) {
  // the device's time: held at 0 through the warm-up, which ends when the link is up (a
  // reply came, and the client renders locally or the round trip does not ask it to) or
  // after warmup_s
  const bool link_up = newest_seq != 0 && (selector.mode() == RenderMode::kLocal ||
                                           selector.round_trip_s() <= palpsim::haptic::ModeSelector::kLocalAboveS);
  if (!path_seq && (t >= o.warmup_s || link_up)) {
    path_seq = n;
    path_t0 = t;
    warmup_trips = watchdog_trips;
  }
  const double t_dev = path_seq ? t - path_t0 : 0.0;
  if (o.max_seconds > 0 && t_dev >= o.max_seconds) return false;
  return device.read_tip(t_dev, tip);
}

// a full queue drops the pose rather than waiting. Patches are asked for only while the
// round trip says they may be needed (else the fields stay unset)
void Loop::send_pose(double t, const V3& tip, RenderMode mode) {
  req.set_seq(n);
  req.set_client_time_s(t);
  auto* tm = req.mutable_tip_mm();
  tm->set_x(tip.x);
  tm->set_y(tip.y);
  tm->set_z(tip.z);
  const bool want = selector.wants_patches();
  req.set_local_model_edge(want ? std::uint32_t(o.patch_edge) : 0);
  req.set_local_model_period_s(want ? o.patch_period_s : 0);
  req.set_renders_locally(mode == RenderMode::kLocal);
  req.SerializeToString(&out);
  sent_at[n % ring] = seconds(Clock::now() - t0);
  tip_at[n % ring] = to_vec(tip);
  (void)c.pose->send(zmq::buffer(out), zmq::send_flags::dontwait);
}

// without replies the force ramps to zero (local_model.h says how fast per mode)
double Loop::watchdog(double t, RenderMode mode) {
  const double age = t - (newest_seq ? last_reply_t : 0);
  const double scale = newest_seq == 0 ? 0.0 : palpsim::haptic::watchdog_scale(age, mode, selector.round_trip_s());
  const double grace = palpsim::haptic::watchdog_grace_s(mode, selector.round_trip_s());
  if (newest_seq && age > grace && !watchdog_on) {
    // says so at most once a second (every trip is counted and reported at exit)
    watchdog_on = true;
    ++watchdog_trips;
    if (last_watchdog_log_t < 0 || t - last_watchdog_log_t >= 1.0) {
      spdlog::warn("watchdog: no reply for {:.1f} ms at t = {:.3f} s ({} mode); ramping the force to zero "
                   "({} trips so far)",
                   age * 1e3, t, mode == RenderMode::kLocal ? "local" : "remote", watchdog_trips);
      last_watchdog_log_t = t;
    }
  } else if (watchdog_on && age <= grace) {
    watchdog_on = false;
  }
  return scale;
}

// server_force_*: the server's force for pose reply_seq (compare with force_* of step reply_seq)
void Loop::write_log(double t, const V3& tip, const V3& applied, double scale, RenderMode mode,
                     const palpsim::haptic::RenderStep& r) {
  const Vec3 fs = newest_seq && server_seq[newest_seq % ring] == newest_seq ? server_at[newest_seq % ring] : Vec3{};
  std::fprintf(log, "%llu,%.6f,%.4f,%.4f,%.4f,%.6f,%.6f,%.6f,%.1f,%llu,%d,%.4f,%.3f,%d,%.3f,%llu,%.4f,%.6f,%.6f,%.6f\n",
               (unsigned long long)n, t, tip.x, tip.y, tip.z, applied.x, applied.y, applied.z, rtt_step,
               (unsigned long long)newest_seq, int(contact), depth, scale, int(mode), r.local_weight,
               (unsigned long long)(renderer.has_patch() ? renderer.current().version : 0),
               renderer.energy().energy_mj(), fs.x, fs.y, fs.z);
}

// ZMQ_FD is edge-triggered: the socket is drained before every wait
void Loop::wait_until(Clock::time_point deadline) {
  for (;;) {
    take_replies();
    const auto left = deadline - Clock::now();
    if (left <= Clock::duration::zero()) break;
    const auto ns = std::chrono::duration_cast<std::chrono::nanoseconds>(left).count();
    timespec ts{time_t(ns / 1000000000), long(ns % 1000000000)};
    pollfd pfd{pose_fd, POLLIN, 0};
    ppoll(&pfd, 1, &ts, nullptr);
  }
}

void Loop::run() {
  t0 = Clock::now();
  for (n = 1; !g_stop; ++n) {
    const Clock::time_point deadline = t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(n * period_s));
    const double t = seconds(Clock::now() - t0);
    V3 tip;
    if (!device_tip(t, tip)) break;
    take_replies();
    keep_session(t);
    const RenderMode mode = selector.mode();
    send_pose(t, tip, mode);
    const double scale = watchdog(t, mode);

    // the force: the server's, or eq. 2 on the newest patch, blended, bounded and passive
    const auto r = renderer.step(t, n == 1 ? 0.0 : t - prev_t, to_vec(tip), force, mode, scale);
    prev_t = t;
    if (r.patch_miss) ++patch_misses;
    if (r.rate_limited) ++rate_limited;
    if (mode == RenderMode::kLocal) ++local_steps;
    rendered_at[n % ring] = r.force_n;
    const V3 applied{r.force_n.x, r.force_n.y, r.force_n.z};
    device.apply_force(applied);
    advance_server_energy(n, false);

    if (log) write_log(t, tip, applied, scale, mode, r);
    rtt_step = std::nan("");
    ++steps;
    // a step whose work ended after its deadline missed it
    if (Clock::now() > deadline) ++missed;
    wait_until(deadline);
  }
}

void Loop::drain_and_close() {
  // up to 1 s for the replies in flight: a loaded machine may hold some back
  const Clock::time_point drain_end = Clock::now() + std::chrono::milliseconds(1000);
  zmq::pollitem_t items[] = {{c.pose->handle(), 0, ZMQ_POLLIN, 0}};
  while (replies + errors < steps && Clock::now() < drain_end) {
    zmq::poll(items, 1, std::chrono::milliseconds(10));
    take_replies();
  }
  advance_server_energy(steps + 1, true);
  if (log) std::fclose(log);
  try {
    c.link->call(c.close_request(c.session, o.client_token), 2000);
  } catch (const std::exception& e) {
    spdlog::warn("closing the session: {}", e.what());
  }
}

int Loop::print_summary() const {
  const std::uint64_t lost = steps > replies + errors ? steps - replies - errors : 0;
  std::printf(
      "palpsim-haptic: %llu steps at %.0f Hz, %llu replies, %llu errors, %llu lost, %llu watchdog trips\n"
      "round trip p50 %.1f us, p99 %.1f us, p99.9 %.1f us; missed deadlines %llu of %llu\n",
      (unsigned long long)steps, o.rate_hz, (unsigned long long)replies, (unsigned long long)errors,
      (unsigned long long)lost, (unsigned long long)watchdog_trips, percentile(rtts_us, 0.5), percentile(rtts_us, 0.99),
      percentile(rtts_us, 0.999), (unsigned long long)missed, (unsigned long long)steps);
  if (!first_error.empty()) std::printf("palpsim-haptic: first error reply: %s\n", first_error.c_str());
  if (reopens)
    std::printf("palpsim-haptic: session reopened %llu times (the server restarted or stopped answering), the first "
                "at t = %.3f s\n",
                (unsigned long long)reopens, first_reopen_t);
  // the link's start: a cold TCP link takes round trips (handshakes, slow start) before any force
  std::printf("palpsim-haptic: first reply at %.3f s, first patch at %.3f s (-1: none); warm-up %.3f s, "
              "%llu watchdog trips in it\n",
              first_reply_s, first_patch_s, path_t0, (unsigned long long)warmup_trips);
  // local rendering, the rendered force against the server's for the same poses, energies
  const auto& re = renderer.energy();
  const double rms = compared ? std::sqrt(err_sq / double(compared)) : 0.0;
  std::printf(
      "palpsim-haptic: mode %s at exit, local for %llu of %llu steps, %llu switches, median round trip %.1f ms; "
      "patches %llu (bad %llu), patch misses %llu, rate-limited steps %llu, passivity steps %llu\n"
      "palpsim-haptic: rendered vs server force over %llu poses: rms %.4f N, max %.4f N, server peak %.3f N "
      "(rms %.2f %% of peak)\n"
      "palpsim-haptic: energy per press cycle (mJ): rendered last %.3f, min %.3f over %llu cycles, min running %.3f; "
      "server last %.3f, min %.3f over %llu cycles, min running %.3f\n",
      selector.mode() == RenderMode::kLocal ? "local" : "remote", (unsigned long long)local_steps,
      (unsigned long long)steps, (unsigned long long)mode_switches, selector.round_trip_s() * 1e3,
      (unsigned long long)patches, (unsigned long long)bad_patches, (unsigned long long)patch_misses,
      (unsigned long long)rate_limited, (unsigned long long)renderer.passivity_steps(), (unsigned long long)compared,
      rms, err_max, server_peak, server_peak > 0 ? 100.0 * rms / server_peak : 0.0, re.last_cycle_mj(),
      re.min_cycle_mj(), (unsigned long long)re.cycles(), re.min_running_mj(), server_energy.last_cycle_mj(),
      server_energy.min_cycle_mj(), (unsigned long long)server_energy.cycles(), server_energy.min_running_mj());
  if (!first_bad_patch.empty()) std::printf("palpsim-haptic: first bad patch: %s\n", first_bad_patch.c_str());
  return errors == 0 && lost == 0 ? 0 : 3;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  if (const int code = parse_options(argc, argv, o); code >= 0) return code;
  // log lines go to stderr; stdout carries only the summary
  spdlog::set_default_logger(spdlog::stderr_color_mt("palpsim-haptic"));
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  raise_priority(o.priority);

  Connection c;
  std::unique_ptr<palpsim::haptic::Device> device;
  std::FILE* log = nullptr;
  palpsim::HapticsSettings params;
  if (!open_session(o, c, device, log, params)) return 1;
  Loop loop(o, c, *device, log, params);
  loop.run();
  loop.drain_and_close();
  return loop.print_summary();
}
