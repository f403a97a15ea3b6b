// The real palpsim-server with deformation on the phantom (4 mm voxels, VOI 32): it logs
// the backend it chose, a press is deformed with stage times in the stats while every
// pose is answered, it stops cleanly; a scene whose deformation cannot be served keeps
// it from starting, with the setting named.
#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <thread>
#include <zmq.hpp>

#include "integration/server_process.h"
#include "palpsim/wire.pb.h"
#include "support/pose_session.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using test::ServerProcess;

namespace {

// how long a test waits for a reply or for the worker (loaded 2-core CI machine)
constexpr int kReplyTimeoutMs = 5000;
constexpr double kWorkerWaitS = 30;
// how long the server may take to prepare the 4 mm phantom and start
constexpr double kStartS = 120;

std::string deform_scene_text(const std::string& extra_deform = "") {
  return "name: \"deform integration\"\nphantom { voxel_mm: 4.0 }\n"
         "deform { voi_edge: 32 relax_iterations: 10 " +
         extra_deform +
         " }\n"
         "effects { haptics: true chainmail: true relaxation: true inversion: true }\n";
}

}  // namespace

// opens a session on `server`, presses into the back (+y) at the middle of the body, 10
// mm deep, at 1 ms of client time per pose (every pose answered without error, some in
// contact), and returns the stats once the worker has stepped the last contact; with
// `hover`, the tip first stays 5 mm out of the body until the stats say the worker primed
// the session's multigrid unit response (DeformEngine::prime), at most kWorkerWaitS
struct Pressed {
  v1::StatsReply stats;
  std::uint64_t last_seq = 0;
};

Pressed press_and_wait(ServerProcess& server, bool hover = false) {
  test::PoseSession session(server.control(), server.pose(), "deform-integration", kReplyTimeoutMs);
  const auto& info = session.open.server();
  CHECK(std::find(info.stages().begin(), info.stages().end(), "chainmail") != info.stages().end());

  const auto& lo = info.patient().body_min_mm();
  const auto& hi = info.patient().body_max_mm();
  const double x = 0.5 * (lo.x() + hi.x()), z = 0.5 * (lo.z() + hi.z());
  // one pose with the tip at height y (mm), answered without error; returns the reply
  auto send = [&](double y) { return session.send({x, y, z}); };
  if (hover) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWorkerWaitS);
    bool primed = false;
    while (!primed && std::chrono::steady_clock::now() < until) {
      REQUIRE_FALSE(send(hi.y() + 5).contact());
      primed = session.stats().session().deform().multigrid_primes() >= 1;
      if (!primed) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    REQUIRE(primed);
  }
  bool touched = false;
  for (int n = 0; n <= 400; ++n) touched = send(hi.y() + 5 - 15.0 * std::min(1.0, n / 300.0)).contact() || touched;
  REQUIRE(touched);

  // the worker ends on the last contact
  Pressed out;
  out.last_seq = session.seq;
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWorkerWaitS);
  do {
    out.stats = session.stats();
    if (out.stats.session().deform().last_contact_seq() == session.seq) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  } while (std::chrono::steady_clock::now() < end);
  return out;
}

TEST_CASE("palpsim-server deforms a press on the phantom, logs its backend and keeps answering poses",
          "[integration][deform]") {
  ServerProcess server(test::temp_file("deform.textproto", deform_scene_text()));
  REQUIRE(server.wait_ready(kStartS));
  INFO(server.child().err());
  CHECK(server.child().err().find("deform backend \"") != std::string::npos);

  // every stage timed
  const Pressed pr = press_and_wait(server);
  const v1::StatsReply& st = pr.stats;
  const v1::DeformSessionStats& d = st.session().deform();
  INFO(d.DebugString());
  REQUIRE(d.last_contact_seq() == pr.last_seq);
  CHECK(d.steps() >= 1);
  CHECK(d.converged());
  CHECK(d.deformed());
  CHECK(d.failures() == 0);
  CHECK(d.moved() > 0);
  CHECK_FALSE(d.chainmail_skipped());  // the explicit relaxation keeps ChainMail's field
  CHECK(d.last().chainmail_ms() > 0);
  CHECK(d.last().relax_ms() > 0);
  CHECK(d.last().invert_ms() > 0);
  CHECK(d.last().total_ms() >= d.last().chainmail_ms() + d.last().relax_ms() + d.last().invert_ms());
  CHECK(!st.server().deform_backend().empty());
  CHECK(server.child().err().find("deform backend \"" + st.server().deform_backend() + "\"") != std::string::npos);
  std::printf("phantom 4 mm, VOI 32, backend %s: %llu steps for %llu poses, mean step %.2f ms (chainmail %.2f, "
              "relax %.2f, invert %.2f)\n",
              st.server().deform_backend().c_str(), (unsigned long long)d.steps(), (unsigned long long)pr.last_seq,
              d.mean().total_ms(), d.mean().chainmail_ms(), d.mean().relax_ms(), d.mean().invert_ms());
  CHECK(server.stop() == 0);
  CHECK(server.child().out().find("palpsim-server: stopped") != std::string::npos);
}

TEST_CASE("palpsim-server's multigrid steps say they left ChainMail out", "[integration][deform]") {
  // the phantom holds nothing outside bone that relaxation would hold, so every multigrid
  // step skips ChainMail (server/deform/README.md) and its stats say so: no sweep, no move
  ServerProcess server(test::temp_file("deform-mg.textproto", deform_scene_text("relax_method: \"multigrid\"")));
  REQUIRE(server.wait_ready(kStartS));
  const Pressed pr = press_and_wait(server);
  const v1::DeformSessionStats& d = pr.stats.session().deform();
  INFO(d.DebugString());
  REQUIRE(d.last_contact_seq() == pr.last_seq);
  CHECK(d.steps() >= 1);
  CHECK(d.chainmail_skipped());
  CHECK(d.sweeps() == 0);
  CHECK(d.moved() == 0);
  CHECK(d.converged());
  CHECK(d.deformed());
  CHECK(d.failures() == 0);
  CHECK(d.max_change_hu() > 0);  // the press still deforms J
  // the first contact solves; a step solves at most once
  CHECK(d.multigrid_solves() >= 1);
  CHECK(d.multigrid_solves() <= d.steps());
  CHECK(d.multigrid_warm() <= d.multigrid_solves());
  CHECK(server.stop() == 0);
}

TEST_CASE("palpsim-server primes a hovering session's unit response, so that its first contact starts warm",
          "[integration][deform]") {
  // the tip 5 mm above the skin until the worker has solved the unit response where it is
  // expected to touch (multigrid_primes), then the press: no step of the session solves
  // from zero (every solve a warm start), where without the prime the first contact's would
  ServerProcess server(test::temp_file("deform-prime.textproto", deform_scene_text("relax_method: \"multigrid\"")));
  REQUIRE(server.wait_ready(kStartS));
  const Pressed pr = press_and_wait(server, true);
  const v1::DeformSessionStats& d = pr.stats.session().deform();
  INFO(d.DebugString());
  REQUIRE(d.last_contact_seq() == pr.last_seq);
  CHECK(d.multigrid_primes() >= 1);
  CHECK(d.failures() == 0);
  CHECK(d.deformed());
  CHECK(d.multigrid_solves() >= 1);
  CHECK(d.multigrid_warm() == d.multigrid_solves());
  std::printf("hovering then pressing: %llu primes, %llu steps, %llu solves, %llu warm\n",
              (unsigned long long)d.multigrid_primes(), (unsigned long long)d.steps(),
              (unsigned long long)d.multigrid_solves(), (unsigned long long)d.multigrid_warm());
  CHECK(server.stop() == 0);
}

TEST_CASE("palpsim-server refuses to start when the scene's deformation cannot be served", "[integration][deform]") {
  ServerProcess server(test::temp_file("deform-bad.textproto", deform_scene_text("relax_step: 0.5")));
  CHECK_FALSE(server.wait_ready(kStartS));
  CHECK(server.child().wait(10) == 1);
  const std::string err = server.child().err();
  INFO(err);
  CHECK(err.find("relax_step") != std::string::npos);
  CHECK(err.find("stable limit") != std::string::npos);
}
