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
#include "core/thread.h"
#include "net/curve_keys.h"
#include "palpsim/wire.pb.h"

namespace v1 = palpsim::v1;
using palpsim::Vec3;
using palpsim::haptic::RenderMode;
using palpsim::haptic::V3;
using Clock = std::chrono::steady_clock;

namespace {

const char* kUsage =
    "usage: palpsim-haptic --connect ADDR [--device press|press:X,Y,Z|csv:FILE|replay:FILE] [--rate HZ]\n"
    "                      [--seconds S] [--log FILE] [--name NAME] [--server-key FILE --client-key FILE]\n"
    "                      [--client-token TEXT] [--mode auto|local|remote] [--patch-edge N] [--patch-period S]\n"
    "                      [--pose-via ADDR] [--warmup S] [--priority N]\n"
    "  --connect ADDR  the server's control address (its 'ready on ADDR' line)\n"
    "  --device SPEC   the built-in press path (default), a CSV of t,x,y,z (s, mm), or a palpsim-haptic log to replay\n"
    "  --rate HZ       loop rate, 100 to 4000 (default 1000)\n"
    "  --seconds S     stop S seconds after the device's path starts (default: when it ends)\n"
    "  --log FILE      CSV of every step (time, pose, force, round trip)\n"
    "  --server-key FILE  the server's public key (its NAME.key from palpsim-keys): speak CURVE\n"
    "  --client-key FILE  this client's secret key (NAME.key_secret), whose public key the server allows\n"
    "  --client-token TEXT without CURVE: the session belongs to this token (palpsim-view --client-token\n"
    "                  TEXT may then watch it); else to this client's control connection alone\n"
    "  --mode M        auto (default: local when the round trip is over 8 ms, remote under 4 ms), local or remote\n"
    "  --patch-edge N  voxels per axis of the patches of F asked for in local mode, 4..16 (default 12)\n"
    "  --patch-period S  at most one patch per S seconds, 0.01..1 (default 0.05)\n"
    "  --pose-via ADDR send poses to ADDR instead of the server's pose endpoint (a tunnel or relay to it)\n"
    "  --warmup S      hold the device's path at its start until the link is up (the first reply; far:\n"
    "                  local mode), at most S seconds (0..10, default 0); the comparison starts with the path\n"
    "  --priority N    the loop and its network thread under SCHED_FIFO at priority N (1..99, default 10)\n"
    "                  where allowed (root or CAP_SYS_NICE), so that other programs cannot delay it; 0: the\n"
    "                  normal policy\n";

// the largest patch the client asks for (PoseRequest.local_model_edge's range is 4..16)
constexpr int kMaxPatchEdge = 16;

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

}  // namespace

int main(int argc, char** argv) {
  std::string addr, device_spec = "press", log_path, name = "palpsim-haptic", server_key_file, client_key_file,
              client_token, mode_name = "auto", pose_via;
  double rate_hz = 1000, max_seconds = 0, patch_period_s = 0.05, warmup_s = 0;
  int patch_edge = 12, priority = 10;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "palpsim-haptic: %s needs a value\n%s", a.c_str(), kUsage);
        std::exit(2);
      }
      return argv[++i];
    };
    try {
      if (a == "--help" || a == "-h") {
        std::fputs(kUsage, stdout);
        return 0;
      } else if (a == "--connect") addr = value();
      else if (a == "--device") device_spec = value();
      else if (a == "--rate") rate_hz = std::stod(value());
      else if (a == "--seconds") max_seconds = std::stod(value());
      else if (a == "--log") log_path = value();
      else if (a == "--name") name = value();
      else if (a == "--server-key") server_key_file = value();
      else if (a == "--client-key") client_key_file = value();
      else if (a == "--client-token") client_token = value();
      else if (a == "--mode") mode_name = value();
      else if (a == "--patch-edge") patch_edge = std::stoi(value());
      else if (a == "--patch-period") patch_period_s = std::stod(value());
      else if (a == "--pose-via") pose_via = value();
      else if (a == "--warmup") warmup_s = std::stod(value());
      else if (a == "--priority") priority = std::stoi(value());
      else {
        std::fprintf(stderr, "palpsim-haptic: unknown argument '%s'\n%s", a.c_str(), kUsage);
        return 2;
      }
    } catch (const std::exception&) {
      std::fprintf(stderr, "palpsim-haptic: %s: '%s' is not a number\n", a.c_str(), argv[i]);
      return 2;
    }
  }
  if (addr.empty()) {
    std::fprintf(stderr, "palpsim-haptic: --connect ADDR is required\n%s", kUsage);
    return 2;
  }
  if (server_key_file.empty() != client_key_file.empty()) {
    std::fprintf(stderr, "palpsim-haptic: --server-key and --client-key go together (CURVE needs both)\n");
    return 2;
  }
  if (!(rate_hz >= 100 && rate_hz <= 4000)) {
    std::fprintf(stderr, "palpsim-haptic: --rate %g: must be within 100..4000 Hz\n", rate_hz);
    return 2;
  }
  if (mode_name != "auto" && mode_name != "local" && mode_name != "remote") {
    std::fprintf(stderr, "palpsim-haptic: --mode %s: expected auto, local or remote\n", mode_name.c_str());
    return 2;
  }
  if (patch_edge < 4 || patch_edge > kMaxPatchEdge) {
    std::fprintf(stderr, "palpsim-haptic: --patch-edge %d: must be within 4..16 voxels\n", patch_edge);
    return 2;
  }
  if (!(patch_period_s >= 0.01 && patch_period_s <= 1)) {
    std::fprintf(stderr, "palpsim-haptic: --patch-period %g: must be within 0.01..1 s\n", patch_period_s);
    return 2;
  }
  if (!(warmup_s >= 0 && warmup_s <= 10)) {
    std::fprintf(stderr, "palpsim-haptic: --warmup %g: must be within 0..10 s\n", warmup_s);
    return 2;
  }
  if (priority < 0 || priority > 99) {
    std::fprintf(stderr, "palpsim-haptic: --priority %d: must be within 0..99 (0: the normal policy)\n", priority);
    return 2;
  }
  if (!(max_seconds >= 0)) {
    std::fprintf(stderr, "palpsim-haptic: --seconds %g: must be >= 0\n", max_seconds);
    return 2;
  }
  // log lines go to stderr; stdout carries only the summary
  spdlog::set_default_logger(spdlog::stderr_color_mt("palpsim-haptic"));
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);

  // the loop under SCHED_FIFO where allowed; ZeroMQ's I/O thread, started with the first
  // socket, inherits the policy
  if (priority > 0) {
    if (palpsim::raise_this_thread(priority))
      spdlog::info("the loop and its network thread under SCHED_FIFO, priority {}", priority);
    else
      spdlog::info("the loop under the normal policy: SCHED_FIFO is not allowed here (root or CAP_SYS_NICE needed; "
                   "--priority 0 asks for the normal policy)");
  }

  zmq::context_t ctx(1);
  std::function<void(zmq::socket_t&)> setup;  // every socket's CURVE keys (none without)
  std::unique_ptr<palpsim::haptic::ControlLink> link;
  std::unique_ptr<zmq::socket_t> pose;        // the session's pose socket (a fresh one per session)
  std::string pose_addr;
  // a DEALER to `endpoint` for a session's poses
  auto make_pose_socket = [&](const std::string& endpoint) {
    auto s = std::make_unique<zmq::socket_t>(ctx, zmq::socket_type::dealer);
    s->set(zmq::sockopt::linger, 0);
    if (setup) setup(*s);
    s->connect(endpoint);
    return s;
  };
  v1::ControlRequest open;  // the OpenSession request, sent again to reopen the session
  std::uint64_t request_id = 0;
  std::uint64_t session = 0;
  std::unique_ptr<palpsim::haptic::Device> device;
  std::FILE* log = nullptr;
  palpsim::HapticsSettings params;
  const bool curve = !server_key_file.empty();
  try {
    // CURVE on both sockets when keys are given (the files are checked before anything is sent)
    if (curve) {
      const std::string server_key = palpsim::net::read_public_key_file(server_key_file);
      const auto client_key = palpsim::net::read_secret_key_file(client_key_file);
      setup = [server_key, client_key](zmq::socket_t& s) { palpsim::net::make_curve_client(s, server_key, client_key); };
    }
    // open the session; the reply names the pose address and the patient's bounds
    link = std::make_unique<palpsim::haptic::ControlLink>(ctx, addr, setup, curve);
    open.set_schema_version(v1::VERSION_CURRENT);
    open.set_request_id(++request_id);
    open.set_client_token(client_token);
    open.mutable_open()->set_client_name(name);
    const v1::ControlReply opened = link->call(open, 5000);
    session = opened.open().session_id();
    const auto& pi = opened.open().server().patient();
    palpsim::haptic::PatientBox box;
    box.body_min_mm = {pi.body_min_mm().x(), pi.body_min_mm().y(), pi.body_min_mm().z()};
    box.body_max_mm = {pi.body_max_mm().x(), pi.body_max_mm().y(), pi.body_max_mm().z()};
    device = palpsim::haptic::make_device(device_spec, box);
    const auto& op = opened.open().params();
    params.stiffness_n_per_mm = op.stiffness_n_per_mm();
    params.friction = op.friction();
    params.max_force_n = op.max_force_n();
    params.max_force_rate_n_per_s = op.max_force_rate_n_per_s();
    params.min_gradient_norm = op.min_gradient_norm();
    pose_addr = pose_via.empty() ? palpsim::haptic::resolve_endpoint(opened.open().pose_endpoint(), addr) : pose_via;
    pose = make_pose_socket(pose_addr);
    spdlog::info("session {:016x} on {} (poses {}), device: {}, {} Hz", session, addr, pose_addr,
                 device->describe(), rate_hz);
    if (!log_path.empty()) {
      log = std::fopen(log_path.c_str(), "w");
      if (!log) throw std::runtime_error(log_path + ": cannot write the log");
      std::setvbuf(log, nullptr, _IOFBF, 1 << 20);
      std::fprintf(log,
                   "step,time_s,tip_x_mm,tip_y_mm,tip_z_mm,force_x_n,force_y_n,force_z_n,rtt_us,reply_seq,contact,"
                   "depth_mm,watchdog_scale,mode,local_weight,patch_version,energy_mj,server_force_x_n,server_force_y_n,"
                   "server_force_z_n\n");
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-haptic: error: %s\n", e.what());
    return 1;
  }

  // rings by sequence number (replies older than the ring are counted late): send times,
  // tips sent and forces rendered, and the server's force for each pose
  const std::size_t ring = 1 << 14;
  std::vector<double> sent_at(ring, -1.0);
  std::vector<Vec3> tip_at(ring), rendered_at(ring), server_at(ring);
  std::vector<std::uint64_t> server_seq(ring, 0);  // the seq server_at holds (0: none)
  std::vector<double> rtts_us;
  rtts_us.reserve(std::size_t(rate_hz * (warmup_s + (max_seconds > 0 ? max_seconds : 60))) + 1024);
  v1::PoseRequest req;
  req.set_schema_version(v1::VERSION_CURRENT);
  req.set_session_id(session);
  v1::PoseReply rep;
  std::string out;
  zmq::message_t in;

  // local rendering: the renderer and the mode selector (local_model.h)
  palpsim::haptic::LocalRenderer renderer(params, kMaxPatchEdge);
  palpsim::haptic::ModeSelector selector;
  if (mode_name != "auto") selector.force(mode_name == "local" ? RenderMode::kLocal : RenderMode::kRemote);
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
  palpsim::haptic::EnergyMeter server_energy;

  const double period_s = 1.0 / rate_hz;
  const Clock::time_point t0 = Clock::now();
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

  // takes every reply that has come back, timestamped on arrival: round trips, the newest
  // force, patches, and the server's force to compare with what was rendered for that pose
  auto take_replies = [&]() {
    while (pose->recv(in, zmq::recv_flags::dontwait)) {
      const double now = seconds(Clock::now() - t0);
      last_heard_t = now;
      if (!rep.ParseFromArray(in.data(), int(in.size()))) {
        ++errors;
        continue;
      }
      if (rep.has_error() && rep.error().code() != v1::ERROR_NONE) {
        if (first_error.empty()) first_error = v1::ErrorCode_Name(rep.error().code()) + ": " + rep.error().message();
        if (rep.error().code() == v1::ERROR_UNKNOWN_SESSION && rep.session_id() == session) session_unknown = true;
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
  };
  // the server's forces along the path, pose by pose in order (a pose whose reply is lost
  // keeps the force before it; one older than a second is taken as lost)
  auto advance_server_energy = [&](std::uint64_t upto, bool final) {
    while (energy_cursor + 1 < upto) {
      const std::uint64_t s = energy_cursor + 1;
      const bool have = server_seq[s % ring] == s;
      if (!have && !final && s + std::uint64_t(rate_hz) > upto) break;
      if (s > 1) server_energy.move(tip_at[s % ring] - tip_at[(s - 1) % ring]);
      if (have) server_energy.set_force(server_at[s % ring], server_at[s % ring] != Vec3{0, 0, 0});
      energy_cursor = s;
    }
  };
  int pose_fd = pose->get(zmq::sockopt::fd);
  // the session, reopened when the server no longer knows it (it restarted, or the session
  // timed out) or nothing came back on the pose socket for kReopenAfterS: the open request
  // goes out and its reply is picked up step by step while the loop goes on (the watchdog
  // has taken the force to zero); poses then go to the new session on a fresh socket
  auto keep_session = [&](double t) {
    v1::ControlReply r;
    bool parsed = false;
    if (link->waiting() && link->take(r, &parsed)) {
      if (parsed && r.has_open() && r.open().session_id() != 0) {
        const std::uint64_t old = session;
        session = r.open().session_id();
        req.set_session_id(session);
        pose_addr = pose_via.empty() ? palpsim::haptic::resolve_endpoint(r.open().pose_endpoint(), addr) : pose_via;
        pose = make_pose_socket(pose_addr);
        pose_fd = pose->get(zmq::sockopt::fd);
        renderer.reset_proxy();
        ++reopens;
        if (first_reopen_t < 0) first_reopen_t = t;
        spdlog::info("session {:016x} reopened at t = {:.3f} s (poses {}), after {:016x} {}", session, t, pose_addr, old,
                     session_unknown ? "was no longer known to the server" : "went unanswered");
        // a server that was only slow still holds the old session: it is closed (the reply is not awaited)
        if (!session_unknown) {
          v1::ControlRequest close;
          close.set_schema_version(v1::VERSION_CURRENT);
          close.set_request_id(++request_id);
          close.set_client_token(client_token);
          close.mutable_close()->set_session_id(old);
          link->start(close);
        }
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
      open.set_request_id(++request_id);
      link->start(open);
      reopen_sent_t = t;
    }
  };

  for (n = 1; !g_stop; ++n) {
    const Clock::time_point deadline = t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(n * period_s));
    const double t = seconds(Clock::now() - t0);
    // the device's time: held at 0 through the warm-up, which ends when the link is up (a
    // reply came, and the client renders locally or the round trip does not ask it to) or
    // after warmup_s
    const bool link_up = newest_seq != 0 && (selector.mode() == RenderMode::kLocal ||
                                             selector.round_trip_s() <= palpsim::haptic::ModeSelector::kLocalAboveS);
    if (!path_seq && (t >= warmup_s || link_up)) {
      path_seq = n;
      path_t0 = t;
      warmup_trips = watchdog_trips;
    }
    const double t_dev = path_seq ? t - path_t0 : 0.0;
    if (max_seconds > 0 && t_dev >= max_seconds) break;
    V3 tip;
    if (!device->read_tip(t_dev, tip)) break;
    take_replies();
    keep_session(t);
    const RenderMode mode = selector.mode();

    // send the newest pose; a full queue drops it rather than waiting. Patches are asked
    // for only while the round trip says they may be needed (else the fields stay unset)
    req.set_seq(n);
    req.set_client_time_s(t);
    auto* tm = req.mutable_tip_mm();
    tm->set_x(tip.x);
    tm->set_y(tip.y);
    tm->set_z(tip.z);
    const bool want = selector.wants_patches();
    req.set_local_model_edge(want ? std::uint32_t(patch_edge) : 0);
    req.set_local_model_period_s(want ? patch_period_s : 0);
    req.set_renders_locally(mode == RenderMode::kLocal);
    req.SerializeToString(&out);
    sent_at[n % ring] = seconds(Clock::now() - t0);
    tip_at[n % ring] = to_vec(tip);
    (void)pose->send(zmq::buffer(out), zmq::send_flags::dontwait);

    // watchdog: without replies the force ramps to zero (local_model.h says how fast per mode)
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

    // the force: the server's, or eq. 2 on the newest patch, blended, bounded and passive
    const auto r = renderer.step(t, n == 1 ? 0.0 : t - prev_t, to_vec(tip), force, mode, scale);
    prev_t = t;
    if (r.patch_miss) ++patch_misses;
    if (r.rate_limited) ++rate_limited;
    if (mode == RenderMode::kLocal) ++local_steps;
    rendered_at[n % ring] = r.force_n;
    const V3 applied{r.force_n.x, r.force_n.y, r.force_n.z};
    device->apply_force(applied);
    advance_server_energy(n, false);

    // server_force_*: the server's force for pose reply_seq (compare with force_* of step reply_seq)
    if (log) {
      const Vec3 fs = newest_seq && server_seq[newest_seq % ring] == newest_seq ? server_at[newest_seq % ring] : Vec3{};
      std::fprintf(log, "%llu,%.6f,%.4f,%.4f,%.4f,%.6f,%.6f,%.6f,%.1f,%llu,%d,%.4f,%.3f,%d,%.3f,%llu,%.4f,%.6f,%.6f,%.6f\n",
                   (unsigned long long)n, t, tip.x, tip.y, tip.z, applied.x, applied.y, applied.z, rtt_step,
                   (unsigned long long)newest_seq, int(contact), depth, scale, int(mode), r.local_weight,
                   (unsigned long long)(renderer.has_patch() ? renderer.current().version : 0),
                   renderer.energy().energy_mj(), fs.x, fs.y, fs.z);
    }
    rtt_step = std::nan("");
    ++steps;
    // a step whose work ended after its deadline missed it
    if (Clock::now() > deadline) ++missed;
    // wait for the next step, taking replies as they arrive (ZMQ_FD is edge-triggered:
    // the socket is drained before every wait)
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

  // collect the replies still in flight (up to 1 s: a loaded machine may hold some back), then close the session
  const Clock::time_point drain_end = Clock::now() + std::chrono::milliseconds(1000);
  zmq::pollitem_t items[] = {{pose->handle(), 0, ZMQ_POLLIN, 0}};
  while (replies + errors < steps && Clock::now() < drain_end) {
    zmq::poll(items, 1, std::chrono::milliseconds(10));
    take_replies();
  }
  advance_server_energy(steps + 1, true);
  if (log) std::fclose(log);
  try {
    v1::ControlRequest close;
    close.set_schema_version(v1::VERSION_CURRENT);
    close.set_client_token(client_token);
    close.set_request_id(++request_id);
    close.mutable_close()->set_session_id(session);
    link->call(close, 2000);
  } catch (const std::exception& e) {
    spdlog::warn("closing the session: {}", e.what());
  }

  const std::uint64_t lost = steps > replies + errors ? steps - replies - errors : 0;
  std::printf(
      "palpsim-haptic: %llu steps at %.0f Hz, %llu replies, %llu errors, %llu lost, %llu watchdog trips\n"
      "round trip p50 %.1f us, p99 %.1f us, p99.9 %.1f us; missed deadlines %llu of %llu\n",
      (unsigned long long)steps, rate_hz, (unsigned long long)replies, (unsigned long long)errors,
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
