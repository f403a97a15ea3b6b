// The real palpsim-server and real clients on loopback: many sessions at once with every
// reply matching its pose, a scene that fails at start, the pose threads' scheduling and a
// flood of garbage on the pose path. Bad input is in haptics_bad_input_test.cpp, the
// client's watchdog in haptics_watchdog_test.cpp.
#include <catch2/catch.hpp>

#include <dirent.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <sstream>
#include <thread>
#include <zmq.hpp>

#include "core/thread.h"
#include "integration/haptics_clients.h"
#include "integration/server_process.h"
#include "palpsim/wire.pb.h"

using namespace palpsim;
using namespace palpsim::test::haptics;
using test::ServerProcess;

TEST_CASE("several sessions at once: every reply matches its pose and none is lost", "[integration]") {
  Started st = start_server(5.0);
  zmq::context_t ctx(1);
  Control ctl(ctx, st.server->control());
  const v1::OpenReply probe = ctl.open("probe");
  const v1::PatientInfo patient = probe.server().patient();
  ctl.close(probe.session_id());

  // the thin haptic client, three at once, beside the test's own sessions
  std::vector<std::unique_ptr<test::Child>> haptic;
  std::vector<std::string> logs;
  for (int i = 0; i < 3; ++i) {
    logs.push_back(test::temp_file("haptic-log", ""));
    haptic.push_back(std::make_unique<test::Child>(std::vector<std::string>{
        test::build_exe("palpsim-haptic"), "--connect", st.server->control(), "--device", "press", "--seconds", "3",
        "--log", logs.back()}));
  }

  // eight sessions, each 5000 poses with up to 16 in flight
  constexpr int kSessions = 8, kPoses = 5000, kWindow = 16;
  std::atomic<int> mismatches{0}, errors{0}, nonzero_outside{0}, contacts{0};
  std::atomic<long> answered{0};
  std::vector<std::thread> threads;
  for (int lane = 0; lane < kSessions; ++lane)
    threads.emplace_back([&, lane] {
      try {
        Control c(ctx, st.server->control());
        const v1::OpenReply o = c.open("lane " + std::to_string(lane));
        Poses p(ctx, o.pose_endpoint());
        std::uint64_t sent = 0, got = 0;
        while (got < kPoses) {
          while (sent < kPoses && sent - got < kWindow) {
            double x, y, z;
            path_point(patient, double(sent) / kPoses, lane, x, y, z);
            p.send(o.session_id(), ++sent, x, y, z);
          }
          const v1::PoseReply r = p.recv();
          ++got;
          if (r.seq() != got || r.session_id() != o.session_id()) ++mismatches;
          if (r.error().code() != v1::ERROR_NONE) ++errors;
          if (r.contact()) ++contacts;
          if (!r.contact() && (r.force_n().x() != 0 || r.force_n().y() != 0 || r.force_n().z() != 0)) ++nonzero_outside;
          ++answered;
        }
        c.close(o.session_id());
      } catch (const std::exception& e) {
        ++errors;
      }
    });
  for (auto& t : threads) t.join();
  CHECK(mismatches == 0);
  CHECK(errors == 0);
  CHECK(nonzero_outside == 0);
  CHECK(answered == long(kSessions) * kPoses);
  CHECK(contacts > kSessions * kPoses / 4);  // the path spends most of its time inside the body

  // the haptic clients: exit 0 means every pose got its reply and none was an error
  for (int i = 0; i < 3; ++i) {
    const int rc = haptic[i]->wait(30);
    INFO("palpsim-haptic " << i << " stdout:\n" << haptic[i]->out() << "\nstderr:\n" << haptic[i]->err());
    CHECK(rc == 0);
    CHECK(haptic[i]->out().find("round trip p50") != std::string::npos);
    std::ifstream log(logs[i]);
    std::string header, line;
    std::getline(log, header);
    CHECK(header.find("force_x_n,force_y_n,force_z_n") != std::string::npos);
    int rows = 0, in_contact = 0;
    while (std::getline(log, line)) {
      ++rows;
      std::stringstream ss(line);
      std::string cell;
      for (int c = 0; c < 11 && std::getline(ss, cell, ','); ++c)
        if (c == 10 && cell == "1") ++in_contact;
    }
    // 3 s at 1 kHz; a loaded machine may run a few steps short of 3000 but not many
    CHECK(rows > 2500);
    CHECK(in_contact > 0);
    std::remove(logs[i].c_str());
  }

  const v1::ServerStats s = ctl.stats();
  CHECK(s.poses() >= std::uint64_t(kSessions) * kPoses);
  CHECK(s.sessions_open() == 0);
  CHECK(s.malformed() + s.unknown_session() + s.bad_pose() + s.absurd_pose() + s.oversized() == 0);
  CHECK(s.pose_service().count() == s.poses());
  CHECK(st.server->stop() == 0);  // SIGTERM: a clean exit
  CHECK(st.server->child().out().find("stopped") != std::string::npos);
  std::remove(st.scene.c_str());
}

TEST_CASE("a scene that fails to load at start: the server refuses to start and says why", "[integration]") {
  {
    ServerProcess s("/no/such/dir/scene.textproto");
    CHECK_FALSE(s.wait_ready(60));
    CHECK(s.child().wait(10) == 1);
    CHECK(s.child().err().find("/no/such/dir/scene.textproto") != std::string::npos);
  }
  {
    const std::string bad = test::temp_file("bad-scene", "phantom { voxel_mm: 2 }\nhaptics {\n  friction: 7\n}\n");
    ServerProcess s(bad);
    CHECK_FALSE(s.wait_ready(60));
    CHECK(s.child().wait(10) == 1);
    const std::string err = s.child().err();
    INFO(err);
    CHECK(err.find(bad + ":3") != std::string::npos);  // file:line of the out-of-range field
    std::remove(bad.c_str());
  }
}

namespace {

// the scheduling policy (0 normal, 1 SCHED_FIFO, ...) and real-time priority of each thread
// of process `pid` called `name`, from /proc/PID/task/*/stat (fields 41 and 40)
std::vector<std::pair<int, int>> thread_policies(pid_t pid, const std::string& name) {
  std::vector<std::pair<int, int>> out;
  const std::string base = "/proc/" + std::to_string(pid) + "/task";
  DIR* d = opendir(base.c_str());
  if (!d) return out;
  while (dirent* e = readdir(d)) {
    if (e->d_name[0] == '.') continue;
    std::string comm, stat;
    std::getline(std::ifstream(base + "/" + e->d_name + "/comm"), comm);
    std::getline(std::ifstream(base + "/" + e->d_name + "/stat"), stat);
    if (comm != name) continue;
    std::istringstream fields(stat.substr(stat.rfind(')') + 2));
    std::string f;
    int rt_priority = 0, policy = 0;
    for (int k = 3; k <= 41 && fields >> f; ++k) {
      if (k == 40) rt_priority = std::stoi(f);
      if (k == 41) policy = std::stoi(f);
    }
    out.emplace_back(policy, rt_priority);
  }
  closedir(d);
  return out;
}

// thread_policies(pid, name) once `done` accepts it, or its last reading after 10 s: each
// thread names itself and takes its policy as it starts, which on a loaded machine may come
// after the ready line (the first look usually sees it)
template <typename Done>
std::vector<std::pair<int, int>> thread_policies_when(pid_t pid, const std::string& name, Done&& done) {
  auto t = thread_policies(pid, name);
  for (int i = 0; i < 1000 && !done(t); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
    t = thread_policies(pid, name);
  }
  return t;
}

}  // namespace

TEST_CASE("the pose thread and its I/O thread run under SCHED_FIFO where allowed, the rest under the normal policy",
          "[integration]") {
  Started st = start_server(5.0);
  const pid_t pid = st.server->child().pid();
  const bool fifo = may_raise_threads(10);
  const auto pose = thread_policies_when(pid, "palpsim-pose", [&](const auto& t) {
    return t.size() == 1 && (!fifo || t[0].first == 1);
  });
  const auto control = thread_policies_when(pid, "palpsim-control", [](const auto& t) { return t.size() == 1; });
  const auto io = thread_policies(pid, "ZMQbg/IO/0");
  REQUIRE(pose.size() == 1);
  REQUIRE(control.size() == 1);
  CHECK(control[0].first == 0);
  if (fifo) {
    // (root or CAP_SYS_NICE, as in CI) the default --pose-priority 10
    CHECK(pose[0] == std::make_pair(1, 10));
    // the pose socket's own I/O thread too, not the control socket's
    CHECK(std::count(io.begin(), io.end(), std::make_pair(1, 10)) == 1);
    CHECK(std::count(io.begin(), io.end(), std::make_pair(0, 0)) >= 1);
  } else {
    WARN("this process may not use SCHED_FIFO: the server is checked to say so");
    CHECK(pose[0].first == 0);
    CHECK(st.server->child().err().find("may not use SCHED_FIFO") != std::string::npos);
  }
  CHECK(st.server->stop() == 0);
  // --pose-priority 0: the normal policy for every thread
  ServerProcess plain(st.scene, {"--pose-priority", "0"});
  REQUIRE(plain.wait_ready(300));
  const auto plain_pose =
      thread_policies_when(plain.child().pid(), "palpsim-pose", [](const auto& t) { return t.size() == 1; });
  REQUIRE(plain_pose.size() == 1);
  CHECK(plain_pose[0].first == 0);
  for (const auto& t : thread_policies(plain.child().pid(), "ZMQbg/IO/0")) CHECK(t.first == 0);
  CHECK(plain.stop() == 0);
  std::remove(st.scene.c_str());
}

TEST_CASE("garbage flooding the pose path: errors are answered up to the connection's allowance, an honest session "
          "beside it gets every reply",
          "[integration]") {
  Started st = start_server(5.0);
  zmq::context_t ctx(1);
  Control ctl(ctx, st.server->control());
  const v1::OpenReply honest = ctl.open("honest");
  Poses good(ctx, honest.pose_endpoint());
  Poses flood(ctx, honest.pose_endpoint());
  const v1::ServerStats before = ctl.stats();
  // 2000 messages that do not parse, with an honest pose after every 100 of them
  constexpr int kGarbage = 2000;
  const auto t0 = std::chrono::steady_clock::now();
  double x, y, z;
  path_point(honest.server().patient(), 0.5, 0, x, y, z);
  for (int i = 0; i < kGarbage; ++i) {
    flood.send_raw({std::string("\xff\xff\xff\xff not a PoseRequest")});
    if (i % 100 == 99) {
      const std::uint64_t seq = std::uint64_t(i / 100 + 1);
      const v1::PoseReply r = good.call(honest.session_id(), seq, x, y, z);
      CHECK(r.error().code() == v1::ERROR_NONE);
      CHECK(r.seq() == seq);
    }
  }
  // every message counted as malformed, then the replies that came (none comes later: the
  // server has handled them all)
  v1::ServerStats after = ctl.stats();
  for (int i = 0; i < 500 && after.malformed() < before.malformed() + kGarbage; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    after = ctl.stats();
  }
  REQUIRE(after.malformed() == before.malformed() + kGarbage);
  const double elapsed_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  int answered = 0;
  for (v1::PoseReply r; flood.try_recv(r, 200);) {
    CHECK(r.error().code() == v1::ERROR_MALFORMED);
    ++answered;
  }
  // the burst of 100, and at most 100 more for each second the flood took (the allowance
  // refills at 100 a second); without the allowance every one of the 2000 is answered
  INFO(answered << " answered in " << elapsed_s << " s");
  CHECK(answered >= 100);
  CHECK(answered <= 100 + int(100 * elapsed_s) + 1);
  CHECK(after.bad_input_unanswered() - before.bad_input_unanswered() == std::uint64_t(kGarbage - answered));
  CHECK(st.server->stop() == 0);
  std::remove(st.scene.c_str());
}
