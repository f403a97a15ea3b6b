// palpsim-haptic: the thin haptic client. Opens a session on a palpsim-server, runs a
// fixed-rate loop (1 kHz, up to 4 kHz) that reads the device, sends the newest pose,
// applies the newest force that has come back, and never waits on the network; a
// watchdog ramps the force to zero when replies stop. Logs every step to CSV and prints
// round-trip percentiles and missed deadlines at exit. Protocol: proto/PROTOCOL.md.
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <poll.h>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "device.h"
#include "net/curve_keys.h"
#include "palpsim/wire.pb.h"

namespace v1 = palpsim::v1;
using palpsim::haptic::V3;
using Clock = std::chrono::steady_clock;

namespace {

const char* kUsage =
    "usage: palpsim-haptic --connect ADDR [--device press|press:X,Y,Z|csv:FILE|replay:FILE] [--rate HZ]\n"
    "                      [--seconds S] [--log FILE] [--name NAME] [--server-key FILE --client-key FILE]\n"
    "                      [--client-token TEXT]\n"
    "  --connect ADDR  the server's control address (its 'ready on ADDR' line)\n"
    "  --device SPEC   the built-in press path (default), a CSV of t,x,y,z (s, mm), or a palpsim-haptic log to replay\n"
    "  --rate HZ       loop rate, 100 to 4000 (default 1000)\n"
    "  --seconds S     stop after S seconds (default: when the device's path ends)\n"
    "  --log FILE      CSV of every step (time, pose, force, round trip)\n"
    "  --server-key FILE  the server's public key (its NAME.key from palpsim-keys): speak CURVE\n"
    "  --client-key FILE  this client's secret key (NAME.key_secret), whose public key the server allows\n"
    "  --client-token TEXT without CURVE: the session belongs to this token (palpsim-view --client-token\n"
    "                  TEXT may then watch it); else to this client's control connection alone\n";

// the watchdog: full force while replies are younger than this, then a linear ramp to zero
constexpr double kWatchdogGraceS = 0.002;
constexpr double kWatchdogRampS = 0.008;  // grace + ramp = 10 ms from the last reply to zero force

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

double seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return std::nan("");
  const std::size_t k = std::min(v.size() - 1, std::size_t(q * double(v.size())));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

// one control request on a REQ socket, with a timeout; throws std::runtime_error naming what failed
v1::ControlReply control(zmq::socket_t& s, const v1::ControlRequest& req, const std::string& addr, int timeout_ms,
                         bool curve) {
  std::string out;
  req.SerializeToString(&out);
  s.send(zmq::buffer(out), zmq::send_flags::none);
  zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}};
  zmq::poll(items, 1, std::chrono::milliseconds(timeout_ms));
  if (!(items[0].revents & ZMQ_POLLIN))
    throw std::runtime_error("no reply from a palpsim-server at " + addr + " within " + std::to_string(timeout_ms) +
                             " ms" + (curve ? palpsim::net::kCurveSilenceHint : palpsim::net::kPlainSilenceHint));
  zmq::message_t m;
  (void)s.recv(m);
  v1::ControlReply rep;
  if (!rep.ParseFromArray(m.data(), int(m.size()))) throw std::runtime_error(addr + ": a control reply that does not parse");
  if (rep.has_error() && rep.error().code() != v1::ERROR_NONE)
    throw std::runtime_error(addr + ": " + v1::ErrorCode_Name(rep.error().code()) + ": " + rep.error().message());
  return rep;
}

}  // namespace

int main(int argc, char** argv) {
  std::string addr, device_spec = "press", log_path, name = "palpsim-haptic", server_key_file, client_key_file,
              client_token;
  double rate_hz = 1000, max_seconds = 0;
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
  if (!(max_seconds >= 0)) {
    std::fprintf(stderr, "palpsim-haptic: --seconds %g: must be >= 0\n", max_seconds);
    return 2;
  }
  // log lines go to stderr; stdout carries only the summary
  spdlog::set_default_logger(spdlog::stderr_color_mt("palpsim-haptic"));
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);

  zmq::context_t ctx(1);
  zmq::socket_t ctl(ctx, zmq::socket_type::req), pose(ctx, zmq::socket_type::dealer);
  ctl.set(zmq::sockopt::linger, 0);
  pose.set(zmq::sockopt::linger, 0);
  std::uint64_t session = 0;
  std::unique_ptr<palpsim::haptic::Device> device;
  std::FILE* log = nullptr;
  const bool curve = !server_key_file.empty();
  try {
    // CURVE on both sockets when keys are given (the files are checked before anything is sent)
    if (curve) {
      const std::string server_key = palpsim::net::read_key_file(server_key_file);
      const auto client_key = palpsim::net::read_secret_key_file(client_key_file);
      for (zmq::socket_t* s : {&ctl, &pose}) palpsim::net::make_curve_client(*s, server_key, client_key);
    }
    // open the session; the reply names the pose address and the patient's bounds
    ctl.connect(addr);
    v1::ControlRequest open;
    open.set_schema_version(v1::VERSION_CURRENT);
    open.set_request_id(1);
    open.set_client_token(client_token);
    open.mutable_open()->set_client_name(name);
    const v1::ControlReply opened = control(ctl, open, addr, 5000, curve);
    session = opened.open().session_id();
    const auto& pi = opened.open().server().patient();
    palpsim::haptic::PatientBox box;
    box.body_min_mm = {pi.body_min_mm().x(), pi.body_min_mm().y(), pi.body_min_mm().z()};
    box.body_max_mm = {pi.body_max_mm().x(), pi.body_max_mm().y(), pi.body_max_mm().z()};
    device = palpsim::haptic::make_device(device_spec, box);
    pose.connect(opened.open().pose_endpoint());
    spdlog::info("session {:016x} on {} (poses {}), device: {}, {} Hz", session, addr, opened.open().pose_endpoint(),
                 device->describe(), rate_hz);
    if (!log_path.empty()) {
      log = std::fopen(log_path.c_str(), "w");
      if (!log) throw std::runtime_error(log_path + ": cannot write the log");
      std::setvbuf(log, nullptr, _IOFBF, 1 << 20);
      std::fprintf(log,
                   "step,time_s,tip_x_mm,tip_y_mm,tip_z_mm,force_x_n,force_y_n,force_z_n,rtt_us,reply_seq,contact,"
                   "depth_mm,watchdog_scale\n");
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-haptic: error: %s\n", e.what());
    return 1;
  }

  // ring of send times by sequence number (replies older than the ring are counted late)
  const std::size_t ring = 1 << 14;
  std::vector<double> sent_at(ring, -1.0);
  std::vector<double> rtts_us;
  rtts_us.reserve(std::size_t(rate_hz * (max_seconds > 0 ? max_seconds : 60)) + 1024);
  v1::PoseRequest req;
  req.set_schema_version(v1::VERSION_CURRENT);
  req.set_session_id(session);
  v1::PoseReply rep;
  std::string out;
  zmq::message_t in;

  const double period_s = 1.0 / rate_hz;
  const Clock::time_point t0 = Clock::now();
  V3 force{0, 0, 0};               // the newest force from the server
  std::uint64_t newest_seq = 0;    // the seq that force belongs to
  double last_reply_t = 0;         // loop time of the newest reply
  bool watchdog_on = false, contact = false;
  double depth = 0;
  std::uint64_t steps = 0, missed = 0, replies = 0, errors = 0, late = 0, watchdog_trips = 0;
  std::string first_error;

  double rtt_step = std::nan("");  // the newest round trip measured since the previous step
  std::uint64_t n = 0;              // the step being run (its pose's seq)
  double last_watchdog_log_t = -1;

  // takes every reply that has come back, timestamped on arrival: round trips and the newest force
  auto take_replies = [&]() {
    while (pose.recv(in, zmq::recv_flags::dontwait)) {
      const double now = seconds(Clock::now() - t0);
      if (!rep.ParseFromArray(in.data(), int(in.size()))) {
        ++errors;
        continue;
      }
      if (rep.has_error() && rep.error().code() != v1::ERROR_NONE) {
        if (first_error.empty()) first_error = v1::ErrorCode_Name(rep.error().code()) + ": " + rep.error().message();
        ++errors;
        continue;
      }
      ++replies;
      const std::uint64_t s = rep.seq();
      if (s + ring > n && sent_at[s % ring] >= 0) {
        rtt_step = (now - sent_at[s % ring]) * 1e6;
        rtts_us.push_back(rtt_step);
      } else {
        ++late;
      }
      if (s > newest_seq) {
        newest_seq = s;
        force = {rep.force_n().x(), rep.force_n().y(), rep.force_n().z()};
        contact = rep.contact();
        depth = rep.depth_mm();
        last_reply_t = now;
      }
    }
  };
  const int pose_fd = pose.get(zmq::sockopt::fd);

  for (n = 1; !g_stop; ++n) {
    const Clock::time_point deadline = t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(n * period_s));
    const double t = seconds(Clock::now() - t0);
    if (max_seconds > 0 && t >= max_seconds) break;
    V3 tip;
    if (!device->read_tip(t, tip)) break;
    take_replies();

    // send the newest pose; a full queue drops it rather than waiting
    req.set_seq(n);
    req.set_client_time_s(t);
    auto* tm = req.mutable_tip_mm();
    tm->set_x(tip.x);
    tm->set_y(tip.y);
    tm->set_z(tip.z);
    req.SerializeToString(&out);
    sent_at[n % ring] = seconds(Clock::now() - t0);
    (void)pose.send(zmq::buffer(out), zmq::send_flags::dontwait);

    // watchdog: without replies the force ramps to zero within 10 ms of the last one
    const double age = t - (newest_seq ? last_reply_t : 0);
    double scale = 1.0;
    if (newest_seq == 0 || age > kWatchdogGraceS) scale = newest_seq == 0 ? 0.0 : std::max(0.0, 1.0 - (age - kWatchdogGraceS) / kWatchdogRampS);
    if (newest_seq && age > kWatchdogGraceS && !watchdog_on) {
      // says so at most once a second (every trip is counted and reported at exit)
      watchdog_on = true;
      ++watchdog_trips;
      if (last_watchdog_log_t < 0 || t - last_watchdog_log_t >= 1.0) {
        spdlog::warn("watchdog: no reply for {:.1f} ms at t = {:.3f} s; ramping the force to zero within {:.0f} ms "
                     "({} trips so far)",
                     age * 1e3, t, (kWatchdogGraceS + kWatchdogRampS) * 1e3, watchdog_trips);
        last_watchdog_log_t = t;
      }
    } else if (watchdog_on && age <= kWatchdogGraceS) {
      watchdog_on = false;
    }
    const V3 applied{force.x * scale, force.y * scale, force.z * scale};
    device->apply_force(applied);

    if (log)
      std::fprintf(log, "%llu,%.6f,%.4f,%.4f,%.4f,%.6f,%.6f,%.6f,%.1f,%llu,%d,%.4f,%.3f\n", (unsigned long long)n, t,
                   tip.x, tip.y, tip.z, applied.x, applied.y, applied.z, rtt_step, (unsigned long long)newest_seq,
                   int(contact), depth, scale);
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
  zmq::pollitem_t items[] = {{pose.handle(), 0, ZMQ_POLLIN, 0}};
  while (replies + errors < steps && Clock::now() < drain_end) {
    zmq::poll(items, 1, std::chrono::milliseconds(10));
    while (pose.recv(in, zmq::recv_flags::dontwait)) {
      const double now = seconds(Clock::now() - t0);
      if (!rep.ParseFromArray(in.data(), int(in.size())) || (rep.has_error() && rep.error().code() != v1::ERROR_NONE)) {
        ++errors;
        continue;
      }
      ++replies;
      if (sent_at[rep.seq() % ring] >= 0) rtts_us.push_back((now - sent_at[rep.seq() % ring]) * 1e6);
    }
  }
  if (log) std::fclose(log);
  try {
    v1::ControlRequest close;
    close.set_schema_version(v1::VERSION_CURRENT);
    close.set_request_id(2);
    close.set_client_token(client_token);
    close.mutable_close()->set_session_id(session);
    control(ctl, close, addr, 2000, curve);
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
  return errors == 0 && lost == 0 ? 0 : 3;
}
