// Memory given back (issue 26, finding 5), with the real palpsim-server on loopback: 20
// reloads of its scene and 20 sessions watched at 3840x2160 by subscribers that never
// read, each closed again, leave its resident memory where it settled before them.
#include <catch2/catch.hpp>

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "palpsim/wire.pb.h"
#include "server_process.h"
#include "support/zmq_exchange.h"

using namespace palpsim;
namespace v1 = palpsim::v1;

namespace {

// the 2 mm phantom with every effect: deformation on the CPU reference, frames and
// bricks; the coarsest ray step (with the zoom of watch_cycle, a 3840x2160 frame takes
// llvmpipe well under a second here rather than several)
std::string memory_scene_text() {
  return "name: \"memory integration\"\n"
         "phantom { voxel_mm: 2.0 }\n"
         "deform { backend: \"cpu\" voi_edge: 32 }\n"
         "effects { haptics: true chainmail: true relaxation: true inversion: true frames: true bricks: true }\n"
         "render { width: 320 height: 180 max_fps: 30 ray_step_vox: 4 jpeg_encoder: \"cpu\" }\n"
         "server { session_timeout_s: 30 }\n";
}

// resident memory of process `pid` (MB), from /proc/PID/status
double rss_mb(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  FAIL("no VmRSS in /proc/" << pid << "/status");
  return 0;
}

// the least resident memory of `pid` (MB) seen over `seconds`: what it settles at once
// the threads that free and the heap trimmer (once a second) have had their turn
double settled_rss_mb(pid_t pid, double seconds) {
  double least = 1e30;
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (std::chrono::steady_clock::now() < end) {
    least = std::min(least, rss_mb(pid));
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  return least;
}

// waits up to `seconds` for the resident memory of `pid` to come down to `bound_mb`;
// returns the least seen
double rss_down_to(pid_t pid, double bound_mb, double seconds) {
  double least = 1e30;
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (std::chrono::steady_clock::now() < end && least > bound_mb) {
    least = std::min(least, rss_mb(pid));
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  return least;
}

// one control request on a REQ socket
v1::ControlReply control(zmq::socket_t& s, v1::ControlRequest q) {
  q.set_schema_version(1);
  return test::exchange<v1::ControlReply>(s, q, 60000);
}

// a session watched at 3840x2160 (frames, float32 bricks) by three subscribers that never
// read, pressed until the server has rendered a frame of it, then closed with them
void watch_cycle(zmq::context_t& ctx, zmq::socket_t& ctl, const v1::ServerInfo& info) {
  v1::ControlRequest open;
  open.mutable_open()->set_client_name("memory");
  const v1::ControlReply opened = control(ctl, open);
  REQUIRE(opened.has_open());
  const std::uint64_t id = opened.open().session_id();
  v1::ControlRequest watch;
  auto* w = watch.mutable_watch();
  w->set_session_id(id);
  w->set_frames(true);
  w->set_bricks(true);
  w->set_brick_encoding(v1::BRICK_FLOAT32);
  w->mutable_view()->set_width(3840);
  w->mutable_view()->set_height(2160);
  w->mutable_view()->set_zoom(0.25);  // the body small in the 3D view: a frame costs llvmpipe less
  const v1::ControlReply watched = control(ctl, watch);
  REQUIRE(watched.has_watch());
  std::vector<zmq::socket_t> subs;
  for (int k = 0; k < 3; ++k) {
    subs.emplace_back(ctx, zmq::socket_type::sub);
    zmq::socket_t& s = subs.back();
    s.set(zmq::sockopt::linger, 0);
    s.set(zmq::sockopt::rcvhwm, 1);
    s.set(zmq::sockopt::rcvbuf, 4096);
    s.connect(watched.watch().stream_endpoint());
    s.set(zmq::sockopt::subscribe, watched.watch().frame_topic());
    s.set(zmq::sockopt::subscribe, watched.watch().brick_topic());
  }
  // a press 5 mm into the back (a deformation step, a VOI brick), then a wait for the
  // session's first frame (a newly watched session is drawn at once)
  zmq::socket_t pose(ctx, zmq::socket_type::dealer);
  pose.set(zmq::sockopt::linger, 0);
  pose.connect(opened.open().pose_endpoint());
  const auto& p = info.patient();
  for (int k = 1; k <= 2; ++k) {
    v1::PoseRequest q;
    q.set_schema_version(1);
    q.set_session_id(id);
    q.set_seq(std::uint64_t(k));
    q.mutable_tip_mm()->set_x(0.5 * (p.body_min_mm().x() + p.body_max_mm().x()));
    q.mutable_tip_mm()->set_y(p.body_max_mm().y() + (k == 1 ? 5.0 : -5.0));
    q.mutable_tip_mm()->set_z(0.5 * (p.body_min_mm().z() + p.body_max_mm().z()));
    REQUIRE(test::exchange<v1::PoseReply>(pose, q).error().code() == v1::ERROR_NONE);
  }
  v1::ControlRequest stats;
  stats.mutable_stats()->set_session_id(id);
  // the bound: a 3840x2160 frame by llvmpipe at nice 19 beside other tests on the 2-core
  // CI machine; 60 s ran out once there under extra load, so 180
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(180);
  while (control(ctl, stats).stats().session().stream().frames_rendered() == 0) {
    REQUIRE(std::chrono::steady_clock::now() < end);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  subs.clear();
  v1::ControlRequest close;
  close.mutable_close()->set_session_id(id);
  REQUIRE(control(ctl, close).has_close());
}

}  // namespace

TEST_CASE("reloads and watched sessions give their memory back", "[integration][memory]") {
  const std::string scene = test::temp_file("memory-scene", memory_scene_text());
  // nice rather than SCHED_IDLE for the render thread: on a busy shared machine an idle-
  // class thread may wait many seconds for a core before it frees a viewer's buffers
  test::ServerProcess server(scene, {"--stream-bind", "tcp://127.0.0.1:*", "--background", "nice"});
  const bool ready = server.wait_ready(300);
  INFO("server stderr:\n" << server.child().err());
  REQUIRE(ready);
  const pid_t pid = server.child().pid();
  zmq::context_t ctx(1);
  zmq::socket_t ctl(ctx, zmq::socket_type::req);
  ctl.set(zmq::sockopt::linger, 0);
  ctl.connect(server.control());
  v1::ControlRequest info_q;
  info_q.mutable_info();
  const v1::ServerInfo info = control(ctl, info_q).info();

  // the first plateau: serving the scene, a viewer come and gone (the render thread's
  // shaders and the publisher's socket exist from then on)
  watch_cycle(ctx, ctl, info);
  const double plateau = settled_rss_mb(pid, 3);

  // Why 10 %: the goal. What the server holds beyond its plateau once they are
  // freed is what the arenas' fragments pin and what the heap trimmer leaves (less than
  // its 32 MB step): 1-5 % of this plateau in runs here. Before the fixes the first
  // reload alone kept a second patient (main() held the first one), and the arenas
  // kept every freed volume, 4K readback and JPEG buffer: 317 -> 636 MB after the
  // reloads, 720 MB after the viewers. Each check waits up to 30 s for the memory to
  // come down: the render thread frees a viewer's buffers after the frame it is drawing
  // (seconds at 3840x2160 on a loaded machine), the trimmer looks once a second.
  const double bound = 1.10 * plateau;
  for (int i = 0; i < 20; ++i) {
    v1::ControlRequest load;
    load.mutable_load_scene()->set_path(scene);
    const v1::ControlReply r = control(ctl, load);
    INFO(r.ShortDebugString());
    REQUIRE(r.has_load_scene());
  }
  const double after_reloads = rss_down_to(pid, bound, 30);

  for (int i = 0; i < 20; ++i) watch_cycle(ctx, ctl, info);
  const double after_watches = rss_down_to(pid, bound, 30);
  std::printf("resident memory: plateau %.0f MB, after 20 reloads %.0f MB, after 20 watch/close cycles %.0f MB\n",
              plateau, after_reloads, after_watches);
  CHECK(after_reloads <= bound);
  CHECK(after_watches <= bound);
  CHECK(server.stop() == 0);
  std::remove(scene.c_str());
}
