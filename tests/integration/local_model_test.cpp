// The local force model end to end (proto/PROTOCOL.md, "Local force model"): the real
// palpsim-server and real palpsim-haptic clients on loopback, the pose path of some of
// them through a delay line (tests/support/delay_line.h). A far client switches to local
// mode and renders the server's force for the same press without the link's lag and
// without generating energy; the same link in remote mode lags; a near client never asks
// for patches. And the wire: patches on request, bad requests refused by name.
#include <catch2/catch.hpp>

#include <csignal>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <regex>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "integration/haptic_log.h"
#include "integration/server_process.h"
#include "palpsim/wire.pb.h"
#include "support/delay_line.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using test::ServerProcess;

namespace {

// what palpsim-haptic's summary says (its last lines on stdout)
struct Summary {
  double rms_n = -1, max_n = -1, peak_n = -1;
  double rendered_min_cycle_mj = 0, rendered_min_running_mj = 0, server_min_cycle_mj = 0;
  long rendered_cycles = -1, server_cycles = -1, patches = -1, switches = -1, local_steps = -1, steps = -1;
  long missed = -1, watchdog_trips = -1;
  std::string mode_at_exit;
};

Summary parse(const std::string& out) {
  Summary s;
  std::smatch m;
  if (std::regex_search(out, m, std::regex(R"(mode (\w+) at exit, local for (\d+) of (\d+) steps, (\d+) switches)"))) {
    s.mode_at_exit = m[1];
    s.local_steps = std::stol(m[2]);
    s.steps = std::stol(m[3]);
    s.switches = std::stol(m[4]);
  }
  if (std::regex_search(out, m, std::regex(R"(patches (\d+) \(bad)"))) s.patches = std::stol(m[1]);
  if (std::regex_search(out, m, std::regex(R"(rms ([-\d.]+) N, max ([-\d.]+) N, server peak ([-\d.]+) N)"))) {
    s.rms_n = std::stod(m[1]);
    s.max_n = std::stod(m[2]);
    s.peak_n = std::stod(m[3]);
  }
  if (std::regex_search(out, m,
                        std::regex(R"(rendered last [-\d.]+, min ([-\d.]+) over (\d+) cycles, min running ([-\d.]+); )"
                                   R"(server last [-\d.]+, min ([-\d.]+) over (\d+) cycles)"))) {
    s.rendered_min_cycle_mj = std::stod(m[1]);
    s.rendered_cycles = std::stol(m[2]);
    s.rendered_min_running_mj = std::stod(m[3]);
    s.server_min_cycle_mj = std::stod(m[4]);
    s.server_cycles = std::stol(m[5]);
  }
  if (std::regex_search(out, m, std::regex(R"((\d+) watchdog trips)"))) s.watchdog_trips = std::stol(m[1]);
  if (std::regex_search(out, m, std::regex(R"(missed deadlines (\d+) of)"))) s.missed = std::stol(m[1]);
  return s;
}

// a server on the fast test scene; its scene file is removed at the end
struct SceneServer {
  std::string scene;
  ServerProcess server;
  explicit SceneServer(const std::string& name)
      : scene(test::temp_file("scene", test::fast_scene_text(name, 30.0))), server(scene) {}
  ~SceneServer() { std::remove(scene.c_str()); }
};

// one press cycle: 10 mm to the skin, 30 mm in at 20 mm/s, hold 0.5 s, out; off the skin at 4.0 s
constexpr const char* kOneCycleS = "4.8";

}  // namespace

TEST_CASE("a far client renders the server's force locally, and a near one asks for nothing", "[integration][local]") {
  SceneServer run("local-model");
  ServerProcess& server = run.server;
  REQUIRE(server.wait_ready(300));

  // 50 ms each way (100 ms round trip): one client in auto mode, one held in remote mode,
  // and one on the direct link, all at once
  test::DelayLine far_auto(server.pose(), 0.050), far_remote(server.pose(), 0.050);
  test::Child local({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--pose-via",
                     far_auto.endpoint(), "--seconds", kOneCycleS});
  test::Child remote({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--pose-via",
                      far_remote.endpoint(), "--mode", "remote", "--seconds", kOneCycleS});
  test::Child near({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--seconds", kOneCycleS});
  const int rc_local = local.wait(60), rc_remote = remote.wait(60), rc_near = near.wait(60);
  INFO("auto, 100 ms:\n" << local.out() << local.err() << "\nremote, 100 ms:\n" << remote.out() << remote.err()
                         << "\nnear:\n" << near.out() << near.err());
  // 3: a reply came back too late to be counted (a loaded CI machine); the run itself is good
  CHECK((rc_local == 0 || rc_local == 3));
  CHECK((rc_remote == 0 || rc_remote == 3));
  CHECK((rc_near == 0 || rc_near == 3));
  const Summary a = parse(local.out()), r = parse(remote.out()), n = parse(near.out());
  WARN("100 ms round trip, auto: rms " << a.rms_n << " N, max " << a.max_n << " N of peak " << a.peak_n
                                       << " N; energy per cycle " << a.rendered_min_cycle_mj << " mJ (server's "
                                       << a.server_min_cycle_mj << "), min running " << a.rendered_min_running_mj
                                       << " mJ; patches " << a.patches << ", local steps " << a.local_steps << " of "
                                       << a.steps << ", missed " << a.missed << ", watchdog trips "
                                       << a.watchdog_trips);
  WARN("100 ms round trip, remote: rms " << r.rms_n << " N, max " << r.max_n << " N; energy per cycle "
                                         << r.rendered_min_cycle_mj << " mJ, min running "
                                         << r.rendered_min_running_mj << " mJ");

  // the far client went local early (the round trip is known after the first reply, a
  // patch 100 ms later), long before the press reaches the skin at 0.5 s
  CHECK(a.mode_at_exit == "local");
  CHECK(a.switches == 1);
  CHECK(a.local_steps > a.steps * 8 / 10);
  CHECK(a.patches >= 40);  // 20 Hz over ~4.6 s of local mode, and early ones near the box's faces
  // the goal of issue 9: at 100 ms round trip the rendered force is within 5 % (rms) of
  // the peak force of what the server computes for the same poses
  REQUIRE(a.peak_n > 1.0);  // the press really pressed
  CHECK(a.rms_n < 0.05 * a.peak_n);
  // one press cycle completed, and the rendered force gave back no more than it took: the
  // passivity controller keeps each step's energy >= 0 up to its prediction error (the last
  // step's displacement stands for the next one's; under 1e-3 mJ a step at 20 mm/s and
  // 3.3 N), and an episode's running minimum may hold a few such steps
  CHECK(a.rendered_cycles >= 1);
  CHECK(a.rendered_min_cycle_mj > -0.01);
  CHECK(a.rendered_min_running_mj > -0.01);

  // the same link rendering the server's late replies: much further from the server's force
  CHECK(r.mode_at_exit == "remote");
  CHECK(r.patches == 0);
  CHECK(r.rms_n > 2 * a.rms_n);
  CHECK(r.rendered_min_running_mj > -0.01);  // passive all the same

  // the near client: remote (a stall of over 64 ms on a loaded machine is a slow link
  // for that moment, and may ask for patches and go local for the 0.5 s dwell; more than
  // that would be a mode that does not follow the link)
  WARN("loopback: " << n.switches << " switches, " << n.patches << " patches, local steps " << n.local_steps);
  CHECK(n.mode_at_exit == "remote");
  CHECK(n.local_steps <= n.steps / 5);
  CHECK(server.stop() == 0);
}

TEST_CASE("patches are served on request, bad requests are refused by name, and stats count them",
          "[integration][local]") {
  SceneServer run("local-model-wire");
  ServerProcess& server = run.server;
  REQUIRE(server.wait_ready(300));
  zmq::context_t ctx(1);
  zmq::socket_t ctl(ctx, zmq::socket_type::req), pose(ctx, zmq::socket_type::dealer);
  ctl.set(zmq::sockopt::linger, 0);
  pose.set(zmq::sockopt::linger, 0);
  ctl.connect(server.control());
  auto call = [&](v1::ControlRequest q) {
    q.set_schema_version(v1::VERSION_CURRENT);
    ctl.send(zmq::buffer(q.SerializeAsString()));
    zmq::message_t m;
    REQUIRE(ctl.recv(m));
    v1::ControlReply r;
    REQUIRE(r.ParseFromArray(m.data(), int(m.size())));
    return r;
  };
  v1::ControlRequest open;
  open.mutable_open()->set_client_name("wire");
  const v1::ControlReply opened = call(open);
  REQUIRE(opened.has_open());
  const std::uint64_t id = opened.open().session_id();
  pose.connect(opened.open().pose_endpoint());
  const auto& pi = opened.open().server().patient();
  // a tip 10 mm under the middle of the back
  const double x = 0.5 * (pi.body_min_mm().x() + pi.body_max_mm().x()), y = pi.body_max_mm().y() - 10,
               z = 0.5 * (pi.body_min_mm().z() + pi.body_max_mm().z());
  std::uint64_t seq = 0;
  // one pose at the tip moved by dy_mm along y, at client time tc_s (0: none), and its reply
  auto pose_call = [&](std::uint32_t edge, double period, bool local = false, double dy_mm = 0, double tc_s = 0) {
    v1::PoseRequest q;
    q.set_schema_version(v1::VERSION_CURRENT);
    q.set_session_id(id);
    q.set_seq(++seq);
    q.mutable_tip_mm()->set_x(x);
    q.mutable_tip_mm()->set_y(y + dy_mm);
    q.mutable_tip_mm()->set_z(z);
    q.set_client_time_s(tc_s);
    q.set_local_model_edge(edge);
    q.set_local_model_period_s(period);
    q.set_renders_locally(local);
    pose.send(zmq::buffer(q.SerializeAsString()));
    zmq::pollitem_t it[] = {{pose.handle(), 0, ZMQ_POLLIN, 0}};
    zmq::poll(it, 1, std::chrono::milliseconds(5000));
    REQUIRE((it[0].revents & ZMQ_POLLIN));
    zmq::message_t m;
    (void)pose.recv(m);
    v1::PoseReply r;
    REQUIRE(r.ParseFromArray(m.data(), int(m.size())));
    return r;
  };
  // out of range: refused, naming the field and its range
  v1::PoseReply bad = pose_call(17, 0.05);
  CHECK(bad.error().code() == v1::ERROR_BAD_PARAMETER);
  CHECK(bad.error().message().find("PoseRequest.local_model_edge") != std::string::npos);
  CHECK(bad.error().message().find("4..16") != std::string::npos);
  bad = pose_call(8, 0.001);
  CHECK(bad.error().code() == v1::ERROR_BAD_PARAMETER);
  CHECK(bad.error().message().find("PoseRequest.local_model_period_s") != std::string::npos);
  // no request, no patch
  CHECK_FALSE(pose_call(0, 0).has_local_model());
  // asked for: a patch within a few poses (the worker makes the channel, then cuts), one
  // that holds together, and at most one per period afterwards
  v1::LocalForceModel first;
  for (int i = 0; i < 200 && first.version() == 0; ++i) {
    const v1::PoseReply r = pose_call(8, 0.5);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    if (r.has_local_model()) first = r.local_model();
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  REQUIRE(first.version() == 1);
  CHECK(first.size_i() == 8);
  CHECK(first.size_j() == 8);
  CHECK(first.size_k() == 8);
  CHECK(first.body().size() == 512);
  CHECK(first.force().size() == 512 * 4);
  CHECK(first.grad_force().size() == 512 * 12);
  CHECK(first.direction_size() == 9);
  CHECK(first.scene_generation() == 1);
  CHECK(first.stiffness_n_per_mm() == opened.open().params().stiffness_n_per_mm());
  int more = 0;
  for (int i = 0; i < 50; ++i) more += int(pose_call(8, 0.5).has_local_model());
  CHECK(more == 0);  // 50 quick poses of a still tip lie within one 0.5 s period
  // the client says it renders locally: the session's stats say so
  (void)pose_call(8, 0.5, true);
  v1::ControlRequest st;
  st.mutable_stats()->set_session_id(id);
  const v1::ControlReply stats = call(st);
  CHECK(stats.stats().session().local_models_sent() == 1);
  CHECK(stats.stats().session().renders_locally());
  CHECK(stats.stats().session().local_poses() == 1);
  CHECK(stats.stats().server().bad_parameter() == 2);

  // a tip moving at 20 mm/s along +y on the client's clock (a pose a millisecond): each box
  // is centred ahead of it by its velocity times kPatchLeadS (0.25 s: 5 mm), so it covers
  // the tip for longer where it goes (a patch is used a round trip or a TCP stall later)
  int led = 0, moving_patches = 0;
  for (int i = 1; i <= 300; ++i) {
    const double dy = 0.02 * i;
    const v1::PoseReply r = pose_call(12, 0.01, true, dy, 1.0 + 1e-3 * i);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
    if (!r.has_local_model() || i < 50) continue;  // from the second patch on (the first has no velocity)
    ++moving_patches;
    // 5 mm ahead of the pose that asked for it, a pose or a few before this one (0.02 mm
    // each; the worker answers within milliseconds, under 1 mm on a loaded machine)
    const double ahead = r.local_model().center_mm().y() - (y + dy);
    INFO("patch " << r.local_model().version() << ": centre " << ahead << " mm ahead of the tip");
    CHECK(ahead > 4.0);
    CHECK(ahead <= 5.0 + 1e-6);
    led += int(ahead > 4.0);
  }
  CHECK(moving_patches >= 10);  // one per 10 ms (0.01 s period) over 0.25 s at least
  CHECK(led == moving_patches);
  CHECK(server.stop() == 0);
}

TEST_CASE("in local mode the watchdog still takes the force to zero when the server goes silent",
          "[integration][local]") {
  SceneServer run("local-model-watchdog");
  ServerProcess& server = run.server;
  REQUIRE(server.wait_ready(300));
  const std::string log = test::temp_file("local-watchdog-log", "");
  test::DelayLine line(server.pose(), 0.050);
  test::Child client({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--pose-via",
                      line.endpoint(), "--seconds", "3.5", "--log", log});
  // in contact from 0.5 s, local from ~0.2 s; the server stops from 1.5 s to 2.5 s
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  server.child().signal(SIGSTOP);
  std::this_thread::sleep_for(std::chrono::milliseconds(1000));
  server.child().signal(SIGCONT);
  const int rc = client.wait(30);
  INFO("palpsim-haptic:\n" << client.out() << client.err());
  CHECK((rc == 0 || rc == 3));
  const std::vector<test::HapticLogRow> rows = test::read_haptic_log(log);
  REQUIRE(rows.size() > 2000);
  // the longest stretch without a new reply: the stop (the delay line empties in 50 ms)
  std::size_t best_first = 0, best_len = 0;
  test::longest_reply_gap(rows, best_first, best_len);
  const double t_reply = rows[best_first].t;
  REQUIRE(rows[best_first + best_len].t - t_reply > 0.6);
  CHECK(rows[best_first].mode == 1);  // local when the server stopped
  CHECK(rows[best_first].force() > 0.1);  // and pressing, so there was a force to take away
  for (std::size_t i = best_first; i <= best_first + best_len; ++i) {
    const double age = rows[i].t - t_reply;
    INFO("t " << rows[i].t << " s, " << age * 1e3 << " ms after the last reply");
    // local mode: full force for 100 ms plus two median round trips (the patch still
    // holds), then down over 100 ms. The line's round trip measures 100 to 110 ms on a
    // loaded machine, so the grace is 0.30 to 0.32 s and the ramp ends by 0.42 s; 10 ms
    // of slack for the loop's steps around the last reply
    if (age < 0.29) CHECK(rows[i].scale == 1.0);
    if (age > 0.43) {
      CHECK(rows[i].scale == 0.0);
      CHECK(rows[i].force() == 0.0);
    }
  }
  std::remove(log.c_str());
  CHECK(server.stop() == 0);
}

namespace {

// reversals of the rendered force's magnitude along a log (palpsim-haptic --log): the
// magnitude turns from rising to falling or back by more than 0.05 N (3 % of the peak; the
// step of a 2000 N/s rate bound is 2 N, the noise of a blend a few mN). A clean press
// cycle has one (up to the plateau, then down from it); ringing has many.
int force_reversals(const std::string& log_path) {
  int reversals = 0, dir = 1;  // from no force, the magnitude can only rise
  double extreme = 0;
  for (const test::HapticLogRow& row : test::read_haptic_log(log_path)) {
    const double f = row.force();
    if (dir > 0 && f > extreme) extreme = f;
    if (dir < 0 && f < extreme) extreme = f;
    if (dir > 0 && f < extreme - 0.05) {
      ++reversals;
      dir = -1;
      extreme = f;
    } else if (dir < 0 && f > extreme + 0.05) {
      ++reversals;
      dir = 1;
      extreme = f;
    }
  }
  return reversals;
}

}  // namespace

// Issue 9, section 3, on loopback: the cases of scripts/netem_matrix.py through the delay
// line (delay, jitter and TCP-like loss in user space) for machines without tc netem.
// Hidden ("[.matrix]": about 45 s); run: palpsim-test-local-model "[.matrix]".
TEST_CASE("impaired links: the rendered force against the server's, per case", "[.matrix]") {
  SceneServer run("local-model-matrix");
  ServerProcess& server = run.server;
  REQUIRE(server.wait_ready(300));
  struct Case {
    const char* name;
    test::LinkImpairment link;
  };
  const Case cases[] = {{"rtt 0 ms", {0, 0, 0}},           {"rtt 20 ms", {0.010, 0, 0}},
                        {"rtt 50 ms", {0.025, 0, 0}},      {"rtt 100 ms", {0.050, 0, 0}},
                        {"rtt 200 ms", {0.100, 0, 0}},     {"rtt 100 ms, jitter +-10 ms", {0.050, 0.010, 0}},
                        {"rtt 100 ms, loss 1 %", {0.050, 0, 0.01}}};
  std::printf("%-28s %-6s %7s %8s %8s %7s %7s %6s %6s %9s %9s %9s\n", "case", "mode", "local%", "rms N", "max N",
              "rms %pk", "missed", "wdog", "revs", "E rend mJ", "E srv mJ", "E min mJ");
  for (const Case& k : cases) {
    const std::string log = test::temp_file("matrix-log", "");
    test::DelayLine line(server.pose(), k.link, 7);
    test::Child c({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--pose-via", line.endpoint(),
                   "--seconds", kOneCycleS, "--log", log});
    const int rc = c.wait(60);
    INFO(k.name << ":\n" << c.out() << c.err());
    CHECK((rc == 0 || rc == 3));
    const Summary s = parse(c.out());
    std::printf("%-28s %-6s %6.1f%% %8.4f %8.4f %6.2f%% %7ld %6ld %6d %9.3f %9.3f %9.3f\n", k.name,
                s.mode_at_exit.c_str(), s.steps > 0 ? 100.0 * double(s.local_steps) / double(s.steps) : 0.0, s.rms_n,
                s.max_n, s.peak_n > 0 ? 100 * s.rms_n / s.peak_n : 0.0, s.missed, s.watchdog_trips,
                force_reversals(log), s.rendered_min_cycle_mj, s.server_min_cycle_mj, s.rendered_min_running_mj);
    std::fflush(stdout);
    std::remove(log.c_str());
  }
  CHECK(server.stop() == 0);
}
