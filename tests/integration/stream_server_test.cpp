// The real palpsim-server with frames and bricks, the real thin haptic client and a
// viewer that subscribes but never reads, on loopback: the haptic round trip is measured
// without the viewer and with it, twice each in one run, and the server renders meanwhile.
#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <zmq.hpp>

#include "palpsim/wire.pb.h"
#include "server_process.h"
#include "support/zmq_exchange.h"

using namespace palpsim;
namespace v1 = palpsim::v1;

namespace {

// the 2 mm phantom with the shipped lumbar scene's effects: deformation on the CPU
// reference, frames and bricks (small frames: on 2 cores llvmpipe's work is the machine's
// load, not the point; what is tested is that nothing of the pose path waits for a viewer)
std::string stream_scene_text() {
  return "name: \"stream integration\"\n"
         "phantom { voxel_mm: 2.0 }\n"
         "deform { backend: \"cpu\" voi_edge: 32 }\n"
         "effects { haptics: true chainmail: true relaxation: true inversion: true frames: true bricks: true }\n"
         "render { width: 320 height: 180 max_fps: 15 jpeg_encoder: \"cpu\" }\n"
         "server { session_timeout_s: 5 }\n";
}

// one control request on a REQ socket
v1::ControlReply control(zmq::socket_t& s, v1::ControlRequest q) {
  q.set_schema_version(1);
  return test::exchange<v1::ControlReply>(s, q);
}

// palpsim-haptic's p99 round trip (us) from its summary line; -1 when absent
double p99_us(const std::string& out) {
  const auto at = out.find("p99 ");
  if (at == std::string::npos) return -1;
  return std::stod(out.substr(at + 4));
}

// runs palpsim-haptic's press for `seconds` against the server; returns its stdout
std::string run_haptic(const test::ServerProcess& server, double seconds) {
  test::Child c({test::build_exe("palpsim-haptic"), "--connect", server.control(), "--device", "press", "--seconds",
                 std::to_string(seconds)});
  const int rc = c.wait(seconds + 60);
  INFO("palpsim-haptic stdout:\n" << c.out() << "\nstderr:\n" << c.err());
  REQUIRE(rc == 0);
  return c.out();
}

}  // namespace

TEST_CASE("a viewer that never reads leaves the haptic round trip as it was", "[integration][stream]") {
  const std::string scene = test::temp_file("stream-scene", stream_scene_text());
  test::ServerProcess server(scene, {"--stream-bind", "tcp://127.0.0.1:*"});
  const bool ready = server.wait_ready(300);
  INFO("server stderr:\n" << server.child().err());
  REQUIRE(ready);
  zmq::context_t ctx(1);
  zmq::socket_t ctl(ctx, zmq::socket_type::req);
  ctl.set(zmq::sockopt::linger, 0);
  ctl.connect(server.control());
  v1::ControlRequest info;
  info.mutable_info();
  const std::string stream = control(ctl, info).info().stream_endpoint();
  REQUIRE_FALSE(stream.empty());

  // without a viewer, then with a viewer of every session that never reads a message
  // (its queue fills at once), twice: a one-off scheduling hiccup of this shared machine
  // then shows as the difference between the two runs of one kind, not between kinds
  double p99_alone = 0, p99_watched = 1e30;
  std::string alone, watched;
  for (int round = 0; round < 2; ++round) {
    const std::string a = run_haptic(server, 3);
    REQUIRE(p99_us(a) > 0);
    p99_alone = std::max(p99_alone, p99_us(a));
    alone += a;
    zmq::socket_t viewer(ctx, zmq::socket_type::sub);
    viewer.set(zmq::sockopt::linger, 0);
    viewer.set(zmq::sockopt::rcvhwm, 1);
    viewer.connect(stream);
    viewer.set(zmq::sockopt::subscribe, "frame.");
    viewer.set(zmq::sockopt::subscribe, "brick.");
    const std::string w = run_haptic(server, 3);
    REQUIRE(p99_us(w) > 0);
    p99_watched = std::min(p99_watched, p99_us(w));
    watched += w;
  }

  // the server did render and publish meanwhile
  v1::ControlRequest stats;
  stats.mutable_stats();
  const v1::ServerStats st = control(ctl, stats).stats().server();
  INFO(st.stream().DebugString());
  CHECK(st.stream().frames_rendered() > 0);
  CHECK(st.stream().frames_published() > 0);
  CHECK(st.stream().key_bricks_published() > 0);
  CHECK(st.stream().render_failures() == 0);

  // The same round trip within a tolerance: on this 2-core machine the haptic client, the
  // server's pose thread, the deformation worker and (with the viewer) the render thread
  // with llvmpipe's rasteriser threads share two cores; the worker and the renderer run
  // under SCHED_IDLE, so the haptic threads take a core at once, but caches and memory
  // bandwidth are shared, and identical runs here differ in p99 by 2-5x (0.3-1.7 ms with
  // the deformation alone, core/thread.h). So the better of the two runs with the viewer
  // is held to twice the worse of the two without plus 1 ms (0.5 ms failed once by
  // 20 us while ctest ran the security and local-model suites beside it): a pose path
  // that waited for rendering or publishing (a frame takes 30-50 ms here, every 67 ms)
  // would still fail it in both runs.
  std::printf("haptic round trip p99: %.0f us without a viewer (the worse of 2 runs), %.0f us with a viewer "
              "that never reads (the better of 2)\n",
              p99_alone, p99_watched);
  INFO("without viewer:\n" << alone << "with viewer:\n" << watched);
  CHECK(p99_watched <= 2 * p99_alone + 1000);
  CHECK(server.stop() == 0);
}
