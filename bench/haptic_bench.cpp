// palpsim-bench haptic: the force model's cost per pose on the phantom, and the
// loopback round trip of palpsim-server's pose path paced at 1 kHz for 1, 4 and 16
// clients (p50, p99, p99.9), next to a bare ZeroMQ DEALER/ROUTER ping-pong with the
// same message sizes, pacing and client counts, and next to the same server with CURVE
// on every socket (docs/security.md), in the same run. Goal: palpsim's round trip at
// most 1.3 times the bare one at p50 and p99.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <unistd.h>
#include <vector>
#include <spdlog/spdlog.h>
#include <zmq.hpp>

#include "bench/registry.h"
#include "bench/stats.h"
#include "core/error.h"
#include "haptics/force_model.h"
#include "net/curve_keys.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "palpsim/wire.pb.h"
#include "prep/prepare.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using Clock = std::chrono::steady_clock;

namespace {

using bench::machine;

struct Options {
  std::string json;
  double seconds = 5;  // per configuration and transport
  std::vector<int> clients{1, 4, 16};
  double rate_hz = 1000;
  long model_poses = 200000;
};

struct Quantiles {
  double p50 = 0, p99 = 0, p999 = 0, max = 0, mean = 0;
  std::size_t n = 0;
};

Quantiles quantiles(std::vector<double> v) {
  Quantiles q;
  q.n = v.size();
  if (v.empty()) return q;
  std::sort(v.begin(), v.end());
  auto at = [&](double p) { return v[std::min(v.size() - 1, std::size_t(p * double(v.size())))]; };
  q.p50 = at(0.5);
  q.p99 = at(0.99);
  q.p999 = at(0.999);
  q.max = v.back();
  double s = 0;
  for (double x : v) s += x;
  q.mean = s / double(v.size());
  return q;
}

std::string json_q(const Quantiles& q, const char* unit) {
  std::ostringstream s;
  s << "{\"n\": " << q.n << ", \"p50_" << unit << "\": " << q.p50 << ", \"p99_" << unit << "\": " << q.p99
    << ", \"p999_" << unit << "\": " << q.p999 << ", \"max_" << unit << "\": " << q.max << ", \"mean_" << unit
    << "\": " << q.mean << "}";
  return s.str();
}


// --- force model cost ---------------------------------------------------------------

struct ModelResult {
  Quantiles ns;
  double contact_fraction = 0;
};

// straight strokes of 1000 poses at 50 mm/s (0.05 mm per pose at 1 kHz) through the body's box
ModelResult bench_model(const Patient& p, const HapticsSettings& hs, long poses) {
  Vec3 lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  for (int k = 0; k < p.grid.size.z; k += 2)
    for (int j = 0; j < p.grid.size.y; j += 2)
      for (int i = 0; i < p.grid.size.x; i += 2)
        if (p.body.at(i, j, k)) {
          const Vec3 x = p.grid.to_physical(Vec3{double(i), double(j), double(k)});
          lo = {std::min(lo.x, x.x), std::min(lo.y, x.y), std::min(lo.z, x.z)};
          hi = {std::max(hi.x, x.x), std::max(hi.y, x.y), std::max(hi.z, x.z)};
        }
  std::mt19937_64 rng(12345);
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<double> ns;
  ns.reserve(poses);
  long contacts = 0;
  ProxyState st{};
  Vec3 x, d;
  for (long n = 0; n < poses; ++n) {
    if (n % 1000 == 0) {
      x = {lo.x + u(rng) * (hi.x - lo.x), lo.y + u(rng) * (hi.y - lo.y), lo.z + u(rng) * (hi.z - lo.z)};
      d = {u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5};
      d = d * (0.05 / norm(d));
      st = ProxyState{};
    }
    x += d;
    const auto t0 = Clock::now();
    const ForceSample f = compute_force(p, hs, x, 1e-3, st);
    const auto t1 = Clock::now();
    ns.push_back(std::chrono::duration<double, std::nano>(t1 - t0).count());
    contacts += f.contact;
  }
  return {quantiles(ns), double(contacts) / double(poses)};
}

// --- round trips ----------------------------------------------------------------------

// a bare ROUTER that answers every message with `reply` (the size of a PoseReply), unparsed
class EchoServer {
 public:
  explicit EchoServer(std::string reply) : reply_(std::move(reply)), ctx_(1), s_(ctx_, zmq::socket_type::router) {
    s_.set(zmq::sockopt::linger, 0);
    s_.bind("tcp://127.0.0.1:*");
    endpoint_ = s_.get(zmq::sockopt::last_endpoint);
    thread_ = std::thread([this] { run(); });
  }
  ~EchoServer() {
    stop_ = true;
    thread_.join();
  }
  const std::string& endpoint() const { return endpoint_; }

 private:
  std::string reply_;
  zmq::context_t ctx_;
  zmq::socket_t s_;
  std::string endpoint_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  void run() {
    zmq::pollitem_t items[] = {{s_.handle(), 0, ZMQ_POLLIN, 0}};
    char id[256], payload[2048];
    while (!stop_) {
      zmq::poll(items, 1, std::chrono::milliseconds(50));
      if (!(items[0].revents & ZMQ_POLLIN)) continue;
      while (auto r = s_.recv(zmq::mutable_buffer(id, sizeof id), zmq::recv_flags::dontwait)) {
        const std::size_t idn = r->size;
        while (s_.get(zmq::sockopt::rcvmore)) (void)s_.recv(zmq::mutable_buffer(payload, sizeof payload));
        s_.send(zmq::const_buffer(id, idn), zmq::send_flags::sndmore | zmq::send_flags::dontwait);
        s_.send(zmq::const_buffer(reply_.data(), reply_.size()), zmq::send_flags::dontwait);
      }
    }
  }
};

// a socket's set-up before it connects: CURVE keys, or nothing
using Setup = std::function<void(zmq::socket_t&)>;

// `clients` threads, each paced at rate_hz for `seconds`: send one message, wait for its
// reply, record the round trip (us). `make_request(client, seq)` gives the bytes to send;
// `setup` prepares each client's socket before `open` names the endpoint.
template <class Open, class Request>
std::vector<double> paced_round_trips(int clients, double rate_hz, double seconds, Open open, Request make_request,
                                      const Setup& setup = {}) {
  std::vector<std::vector<double>> per(clients);
  std::vector<std::thread> threads;
  std::atomic<int> failures{0};
  const auto start = Clock::now() + std::chrono::milliseconds(200);
  const double period = 1.0 / rate_hz;
  for (int c = 0; c < clients; ++c)
    threads.emplace_back([&, c] {
      zmq::context_t ctx(1);
      zmq::socket_t s(ctx, zmq::socket_type::dealer);
      s.set(zmq::sockopt::linger, 0);
      if (setup) setup(s);
      const std::string endpoint = open(ctx, c);
      s.connect(endpoint);
      zmq::pollitem_t items[] = {{s.handle(), 0, ZMQ_POLLIN, 0}};
      zmq::message_t m;
      const long steps = long(seconds * rate_hz), warmup = long(0.2 * rate_hz);
      per[c].reserve(steps);
      // clients start spread over one period, as independent devices would
      const auto t0 = start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(period * c / clients));
      for (long n = 0; n < steps + warmup; ++n) {
        std::this_thread::sleep_until(t0 + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(n * period)));
        const std::string req = make_request(c, std::uint64_t(n + 1));
        const auto ts = Clock::now();
        s.send(zmq::buffer(req), zmq::send_flags::none);
        zmq::poll(items, 1, std::chrono::milliseconds(1000));
        if (!(items[0].revents & ZMQ_POLLIN)) {
          ++failures;
          continue;
        }
        (void)s.recv(m);
        const auto tr = Clock::now();
        if (n >= warmup) per[c].push_back(std::chrono::duration<double, std::micro>(tr - ts).count());
      }
    });
  for (auto& t : threads) t.join();
  if (failures) std::fprintf(stderr, "palpsim-bench haptic: %d requests without a reply within 1 s\n", int(failures));
  std::vector<double> all;
  for (auto& v : per) all.insert(all.end(), v.begin(), v.end());
  return all;
}

struct RoundTripRow {
  int clients = 0;
  Quantiles palpsim, bare, curve;  // curve: the same server with CURVE on every socket
};

// one control request on a fresh REQ socket (set up by `setup`) and its reply; every
// request carries one client token, so that without CURVE the sessions one call opens
// are another call's to close (with CURVE the key is the identity and the token is ignored)
v1::ControlReply control_call(const std::string& endpoint, v1::ControlRequest q, const Setup& setup) {
  zmq::context_t ctx(1);
  zmq::socket_t s(ctx, zmq::socket_type::req);
  s.set(zmq::sockopt::linger, 0);
  if (setup) setup(s);
  s.connect(endpoint);
  q.set_schema_version(1);
  q.set_client_token("palpsim-bench");
  s.send(zmq::buffer(q.SerializeAsString()), zmq::send_flags::none);
  zmq::message_t m;
  (void)s.recv(m);
  v1::ControlReply r;
  r.ParseFromArray(m.data(), int(m.size()));
  if (r.error().code() != v1::ERROR_NONE) throw Error("palpsim-bench haptic: " + r.error().message());
  return r;
}

// the server's own receive-to-send time over every pose it answered
Quantiles service_time(const net::Server& server, const Setup& setup) {
  v1::ControlRequest q;
  q.mutable_stats();
  const auto& l = control_call(server.control_endpoint(), q, setup).stats().server().pose_service();
  Quantiles service;
  service.n = l.count();
  service.p50 = l.p50_us();
  service.p99 = l.p99_us();
  service.p999 = l.p999_us();
  service.max = l.max_us();
  return service;
}

// reads the command line into `o`; false after printing the usage (--help)
bool parse_options(int argc, char** argv, Options& o) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw Error("palpsim-bench haptic: " + a + " needs a value");
      return argv[++i];
    };
    if (a == "--json") o.json = value();
    else if (a == "--seconds") o.seconds = std::stod(value());
    else if (a == "--model-poses") o.model_poses = std::stol(value());
    else if (a == "--clients") {
      o.clients.clear();
      std::stringstream ss(value());
      std::string c;
      while (std::getline(ss, c, ',')) o.clients.push_back(std::stoi(c));
    } else if (a == "--help" || a == "-h") {
      std::printf(
          "usage: palpsim-bench haptic [--json FILE] [--seconds S per run (5)] [--clients 1,4,16] [--model-poses N]\n");
      return false;
    } else {
      throw Error("palpsim-bench haptic: unknown argument '" + a + "'");
    }
  }
  return true;
}

// the force model's cost per pose with `haptics`' rule for the skin point and with the
// paper's ("line"), printed
void bench_models(const Patient& patient, const HapticsSettings& haptics, long poses, ModelResult& model,
                  ModelResult& model_line) {
  model = bench_model(patient, haptics, poses);
  HapticsSettings paper = haptics;
  paper.skin_point = SkinPointRule::kLine;
  model_line = bench_model(patient, paper, poses);
  for (const auto& [name, m] : {std::pair<const char*, const ModelResult&>{"skin point \"normal\"", model},
                                {"skin point \"line\"", model_line}})
    std::printf("force model, %s: %zu poses (%.0f %% in contact): p50 %.0f ns, p99 %.0f ns, p99.9 %.0f ns, max %.0f ns, "
                "mean %.0f ns\n",
                name, m.ns.n, 100 * m.contact_fraction, m.ns.p50, m.ns.p99, m.ns.p999, m.ns.max, m.ns.mean);
}

// the servers' own receive-to-send times, plain and with CURVE
void print_service(const Quantiles& service, const Quantiles& curve_service) {
  for (const auto& [name, q] : {std::make_pair("", service), std::make_pair(" with CURVE", curve_service)})
    std::printf("server-side service time%s (receive to send, 9 %% bins): p50 %.2f us, p99 %.2f us, p99.9 %.2f us, "
                "max %.0f us over %zu poses\n",
                name, q.p50, q.p99, q.p999, q.max, q.n);
}

// a pose in contact, for the message sizes and as the template of every client's poses
v1::PoseRequest sample_pose() {
  v1::PoseRequest sample_req;
  sample_req.set_schema_version(1);
  sample_req.set_session_id(0xfedcba9876543210ull);
  sample_req.set_seq(123456);
  sample_req.set_client_time_s(12.345678);
  sample_req.mutable_tip_mm()->set_x(1.25);
  sample_req.mutable_tip_mm()->set_y(95.5);
  sample_req.mutable_tip_mm()->set_z(-3.75);
  return sample_req;
}

// opens a session on `server`, sends one pose 10 mm into the back's middle and closes it:
// the reply's size (bytes); `top` becomes the top of the body's box above its middle (mm)
std::size_t probe_reply(const net::Server& server, const v1::PoseRequest& sample_req, Vec3& top) {
  std::size_t reply_bytes = 0;
  zmq::context_t ctx(1);
  zmq::socket_t c(ctx, zmq::socket_type::req);
  c.connect(server.control_endpoint());
  v1::ControlRequest q;
  q.set_schema_version(1);
  q.mutable_open();
  c.send(zmq::buffer(q.SerializeAsString()), zmq::send_flags::none);
  zmq::message_t m;
  (void)c.recv(m);
  v1::ControlReply r;
  r.ParseFromArray(m.data(), int(m.size()));
  const auto& pi = r.open().server().patient();
  top = {0.5 * (pi.body_min_mm().x() + pi.body_max_mm().x()), pi.body_max_mm().y(),
         0.5 * (pi.body_min_mm().z() + pi.body_max_mm().z())};
  zmq::socket_t p(ctx, zmq::socket_type::dealer);
  p.connect(r.open().pose_endpoint());
  v1::PoseRequest pr = sample_req;
  pr.set_session_id(r.open().session_id());
  pr.mutable_tip_mm()->set_x(top.x);
  pr.mutable_tip_mm()->set_y(top.y - 10);
  pr.mutable_tip_mm()->set_z(top.z);
  p.send(zmq::buffer(pr.SerializeAsString()), zmq::send_flags::none);
  (void)p.recv(m);
  reply_bytes = m.size();
  v1::ControlRequest cl;
  cl.set_schema_version(1);
  cl.mutable_close()->set_session_id(r.open().session_id());
  c.send(zmq::buffer(cl.SerializeAsString()), zmq::send_flags::none);
  (void)c.recv(m);
  return reply_bytes;
}

// one client count's round trips on stdout: palpsim, bare ZeroMQ and CURVE
void print_row(const RoundTripRow& row, const Options& o) {
  const int n = row.clients;
  std::printf(
      "%2d client%s at %.0f Hz: palpsim p50 %.1f us, p99 %.1f us, p99.9 %.1f us | bare ZeroMQ p50 %.1f us, p99 %.1f "
      "us, p99.9 %.1f us | ratio p50 %.2f, p99 %.2f (goal <= 1.3)\n"
      "             with CURVE: p50 %.1f us, p99 %.1f us, p99.9 %.1f us | CURVE / plain p50 %.2f, p99 %.2f\n",
      n, n == 1 ? " " : "s", o.rate_hz, row.palpsim.p50, row.palpsim.p99, row.palpsim.p999, row.bare.p50,
      row.bare.p99, row.bare.p999, row.palpsim.p50 / row.bare.p50, row.palpsim.p99 / row.bare.p99, row.curve.p50,
      row.curve.p99, row.curve.p999, row.curve.p50 / row.palpsim.p50, row.curve.p99 / row.palpsim.p99);
  std::fflush(stdout);
}

// everything measured, as --json
void write_json(const Options& o, const Patient& patient, const ModelResult& model, const ModelResult& model_line,
                std::size_t req_bytes, std::size_t reply_bytes, const Quantiles& service, const Quantiles& curve_service,
                const std::vector<RoundTripRow>& rows) {
  std::ofstream f(o.json);
  if (!f) throw Error("palpsim-bench haptic: cannot write --json " + o.json);
  const std::time_t now = std::time(nullptr);
  char date[32];
  std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
  f << "{\n  \"area\": \"haptic\",\n  \"date\": \"" << date << "\",\n  \"machine\": \"" << machine()
    << "\",\n  \"patient\": {\"source\": \"" << patient.source << "\", \"size\": [" << patient.grid.size.x << ", "
    << patient.grid.size.y << ", " << patient.grid.size.z << "], \"voxel_mm\": " << patient.grid.spacing_mm.x
    << "},\n  \"force_model\": {\"poses\": " << model.ns.n << ", \"contact_fraction\": " << model.contact_fraction
    << ", \"per_pose\": " << json_q(model.ns, "ns")
    << ", \"per_pose_skin_point_line\": " << json_q(model_line.ns, "ns") << "},\n  \"messages\": {\"pose_bytes\": "
    << req_bytes
    << ", \"reply_bytes\": " << reply_bytes << "},\n  \"rate_hz\": " << o.rate_hz << ",\n  \"seconds_per_run\": "
    << o.seconds << ",\n  \"server_service\": {\"n\": " << service.n << ", \"p50_us\": " << service.p50
    << ", \"p99_us\": " << service.p99 << ", \"p999_us\": " << service.p999 << ", \"max_us\": " << service.max
    << "},\n  \"server_service_curve\": {\"n\": " << curve_service.n << ", \"p50_us\": " << curve_service.p50
    << ", \"p99_us\": " << curve_service.p99 << ", \"p999_us\": " << curve_service.p999
    << ", \"max_us\": " << curve_service.max << "},\n  \"round_trip\": [\n";
  for (std::size_t i = 0; i < rows.size(); ++i) {
    const auto& r = rows[i];
    const double r50 = r.palpsim.p50 / r.bare.p50, r99 = r.palpsim.p99 / r.bare.p99;
    f << "    {\"clients\": " << r.clients << ", \"palpsim\": " << json_q(r.palpsim, "us")
      << ", \"bare_zmq\": " << json_q(r.bare, "us") << ", \"palpsim_curve\": " << json_q(r.curve, "us")
      << ", \"curve_over_plain_p50\": " << r.curve.p50 / r.palpsim.p50
      << ", \"curve_over_plain_p99\": " << r.curve.p99 / r.palpsim.p99 << ", \"ratio_p50\": " << r50
      << ", \"ratio_p99\": " << r99
      << ", \"goal_met\": " << ((r50 <= 1.3 && r99 <= 1.3) ? "true" : "false") << "}"
      << (i + 1 < rows.size() ? "," : "") << "\n";
  }
  f << "  ]\n}\n";
  std::printf("wrote %s\n", o.json.c_str());
}

int run(int argc, char** argv) {
  Options o;
  if (!parse_options(argc, argv, o)) return 0;

  // the phantom patient of the default scene
  const Scene scene = default_scene();
  PrepReport report;
  const PatientPtr patient = prepare_patient(scene, &report);
  std::printf("patient: %s, %d x %d x %d at %.2f mm (%s, %.1f s)\nmachine: %s\n", patient->source.c_str(),
              patient->grid.size.x, patient->grid.size.y, patient->grid.size.z, patient->grid.spacing_mm.x,
              report.from_cache ? "cached" : "prepared", report.total_s, machine().c_str());

  // session open/close lines would interleave with the figures
  spdlog::set_level(spdlog::level::warn);

  // force model cost, with the scene's rule for the skin point and with the paper's
  ModelResult model, model_line;
  bench_models(*patient, scene.haptics, o.model_poses, model, model_line);

  // the server, in this process, on loopback tcp like the real one
  net::ServerOptions so;
  so.control_bind = "tcp://127.0.0.1:*";
  so.pose_bind = "tcp://127.0.0.1:*";
  Scene served = scene;
  served.server.max_sessions = 64;
  so.max_sessions_per_client = served.server.max_sessions;  // one bench client opens every session
  net::Server server(served, patient, [](const Scene& s) { return prepare_patient(s); }, so);
  server.start();
  // and beside it the same server with CURVE, admitting one client key
  const net::CurveKeyPair server_keys = net::make_curve_keypair(), client_keys = net::make_curve_keypair();
  net::ServerOptions co = so;
  co.curve_secret_key = server_keys.secret_key;
  co.curve_allowed_keys = {client_keys.public_key};
  net::Server curve_server(served, patient, [](const Scene& s) { return prepare_patient(s); }, co);
  curve_server.start();
  const Setup curve_setup = [&](zmq::socket_t& s) { net::make_curve_client(s, server_keys.public_key, client_keys); };

  // message sizes: a pose in contact and its reply
  const v1::PoseRequest sample_req = sample_pose();
  const std::size_t req_bytes = sample_req.ByteSizeLong();
  // the tip presses in and out at the back's middle, like a palpation
  Vec3 top{0, 0, 0};
  const std::size_t reply_bytes = probe_reply(server, sample_req, top);
  std::printf("messages: pose %zu bytes, reply %zu bytes (the bare ping-pong sends and answers the same sizes)\n",
              req_bytes, reply_bytes);
  EchoServer echo(std::string(reply_bytes, 'r'));

  std::vector<RoundTripRow> rows;
  // the palpsim pose for client c at step seq: in and out of the back, 20 mm deep, once a
  // second; clients side by side. Each client opens its session with its own socket's
  // set-up (with CURVE a session belongs to the key that opened it)
  std::vector<std::uint64_t> ids(64, 0);
  auto opener = [&](const net::Server& srv, const Setup& setup) {
    return [&srv, &ids, setup](zmq::context_t&, int c) {
      v1::ControlRequest q;
      q.mutable_open()->set_client_name("bench " + std::to_string(c));
      const v1::ControlReply r = control_call(srv.control_endpoint(), q, setup);
      ids[c] = r.open().session_id();
      return r.open().pose_endpoint();
    };
  };
  // closes a block's sessions so that they do not linger until their timeout
  auto close_sessions = [&](const net::Server& srv, int n, const Setup& setup) {
    for (int c = 0; c < n; ++c) {
      v1::ControlRequest q;
      q.mutable_close()->set_session_id(ids[c]);
      control_call(srv.control_endpoint(), q, setup);
    }
  };
  auto pose_bytes = [&](int c, std::uint64_t seq) {
    const double t = double(seq) / o.rate_hz;
    v1::PoseRequest q = sample_req;
    q.set_session_id(ids[c]);
    q.set_seq(seq);
    q.set_client_time_s(t);
    q.mutable_tip_mm()->set_x(top.x + 4.0 * (c % 8) - 14);
    q.mutable_tip_mm()->set_y(top.y + 5 - 25 * (0.5 - 0.5 * std::cos(2 * M_PI * t)));
    q.mutable_tip_mm()->set_z(top.z + 6.0 * (c / 8));
    return q.SerializeAsString();
  };
  const std::string bare_req(req_bytes, 'q');
  for (int n : o.clients) {
    RoundTripRow row;
    row.clients = n;
    // bare ZeroMQ, palpsim and palpsim with CURVE alternate in 1 s blocks, so that all
    // see the same background load on a shared machine; same pacing, sizes and client count
    std::vector<double> bare, pal, cur;
    const int blocks = std::max(1, int(std::lround(o.seconds)));
    for (int b = 0; b < blocks; ++b) {
      const double block_s = o.seconds / blocks;
      auto x = paced_round_trips(
          n, o.rate_hz, block_s, [&](zmq::context_t&, int) { return echo.endpoint(); },
          [&](int, std::uint64_t) { return bare_req; });
      bare.insert(bare.end(), x.begin(), x.end());
      auto y = paced_round_trips(n, o.rate_hz, block_s, opener(server, {}), pose_bytes);
      pal.insert(pal.end(), y.begin(), y.end());
      close_sessions(server, n, {});
      auto z = paced_round_trips(n, o.rate_hz, block_s, opener(curve_server, curve_setup), pose_bytes, curve_setup);
      cur.insert(cur.end(), z.begin(), z.end());
      close_sessions(curve_server, n, curve_setup);
    }
    row.bare = quantiles(bare);
    row.palpsim = quantiles(pal);
    row.curve = quantiles(cur);
    print_row(row, o);
    rows.push_back(row);
  }
  // the servers' own receive-to-send times over every pose of the runs (decryption and
  // encryption happen in ZeroMQ's I/O thread, outside this time)
  const Quantiles service = service_time(server, {}), curve_service = service_time(curve_server, curve_setup);
  print_service(service, curve_service);
  server.stop();
  curve_server.stop();

  if (!o.json.empty())
    write_json(o, *patient, model, model_line, req_bytes, reply_bytes, service, curve_service, rows);
  return 0;
}

}  // namespace

PALPSIM_BENCH(haptic,
              "force model cost per pose; pose round trip at 1 kHz for 1/4/16 clients vs bare ZeroMQ and with CURVE") {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
  }
}
