// The local force model end to end (proto/PROTOCOL.md, "Local force model"): the real
// palpsim-server and real palpsim-haptic clients on loopback, the pose path of some of
// them through a delay line (tests/support/delay_line.h). A far client switches to local
// mode and renders the server's force for the same press without the link's lag and
// without generating energy; the same link in remote mode lags; a near client never asks
// for patches.
#include <catch2/catch.hpp>

#include <cstdio>
#include <regex>
#include <string>

#include "integration/server_process.h"
#include "support/delay_line.h"

using namespace palpsim;
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

// one press cycle: 10 mm to the skin, 30 mm in at 20 mm/s, hold 0.5 s, out; off the skin at 4.0 s
constexpr const char* kOneCycleS = "4.8";

}  // namespace

TEST_CASE("a far client renders the server's force locally, and a near one asks for nothing", "[integration][local]") {
  const std::string scene = test::temp_file("scene", test::fast_scene_text("local-model", 30.0));
  ServerProcess server(scene);
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

  // the near client: remote throughout, never asked for a patch
  CHECK(n.mode_at_exit == "remote");
  CHECK(n.switches == 0);
  CHECK(n.patches == 0);
  CHECK(server.stop() == 0);
  std::remove(scene.c_str());
}
