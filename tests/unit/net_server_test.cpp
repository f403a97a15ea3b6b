// The server's network edge in-process on synthetic patients: what comes over the wire
// is exactly the force model's answer, resets and parameter changes apply from the next
// pose on, the contact hook sees the newest pose, and scene reloads swap the patient or
// are refused with the old one kept, and read or write no file outside the operator's
// folders; beyond loopback the server binds only when told it is insecure.
#include <catch2/catch.hpp>

#include <chrono>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <unistd.h>
#include <zmq.hpp>

#include "core/error.h"
#include "haptics/force_model.h"
#include "haptics/passivity.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "palpsim/wire.pb.h"
#include "support/net_client.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
namespace v1 = palpsim::v1;

namespace Catch {
template <>
struct StringMaker<palpsim::Vec3> {
  static std::string convert(const palpsim::Vec3& v) {
    char b[128];
    std::snprintf(b, sizeof b, "(%.17g, %.17g, %.17g)", v.x, v.y, v.z);
    return b;
  }
};
}  // namespace Catch

namespace {

// a session opened as "unit" (control REQ, pose DEALER)
struct Client : test::NetClient {
  explicit Client(const net::Server& s) : NetClient(s, "unit") {}
};

Vec3 vec(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

// the reply carries exactly the force model's sample (doubles travel bit for bit)
void check_same(const v1::PoseReply& r, const ForceSample& f) {
  REQUIRE(r.error().code() == v1::ERROR_NONE);
  CHECK(vec(r.force_n()) == f.force_n);
  CHECK(vec(r.proxy_mm()) == f.proxy_mm);
  CHECK(vec(r.skin_point_mm()) == f.skin_point_mm);
  CHECK(r.contact() == f.contact);
  CHECK(r.depth_mm() == f.depth_mm);
}

}  // namespace

TEST_CASE("the pose address is derived from the control address", "[net]") {
  CHECK(net::derive_pose_endpoint("tcp://127.0.0.1:7420") == "tcp://127.0.0.1:7421");
  CHECK(net::derive_pose_endpoint("tcp://127.0.0.1:*") == "tcp://127.0.0.1:*");
  CHECK(net::derive_pose_endpoint("ipc:///tmp/p") == "ipc:///tmp/p.pose");
  CHECK(net::derive_pose_endpoint("inproc://x") == "inproc://x-pose");
  CHECK_THROWS_AS(net::derive_pose_endpoint("tcp://127.0.0.1:http"), Error);
  // the stream (frames and bricks) two ports up, or its own ipc/inproc name
  CHECK(net::derive_stream_endpoint("tcp://127.0.0.1:7420") == "tcp://127.0.0.1:7422");
  CHECK(net::derive_stream_endpoint("tcp://127.0.0.1:*") == "tcp://127.0.0.1:*");
  CHECK(net::derive_stream_endpoint("ipc:///tmp/p") == "ipc:///tmp/p.stream");
  CHECK(net::derive_stream_endpoint("inproc://x") == "inproc://x-stream");
  CHECK_THROWS_AS(net::derive_stream_endpoint("tcp://127.0.0.1:65534"), Error);  // 65536 is no port
  CHECK_THROWS_AS(net::derive_pose_endpoint("udp://127.0.0.1:5"), Error);
}

TEST_CASE("a bind that fails names the address", "[net]") {
  const Scene scene = default_scene();
  net::Server a(scene, test::slab_patient(), nullptr, test::loopback_options());
  net::ServerOptions same = test::loopback_options();
  same.control_bind = a.control_endpoint();  // already taken
  try {
    net::Server b(scene, test::slab_patient(), nullptr, same);
    FAIL("the second bind succeeded");
  } catch (const Error& e) {
    CHECK(std::string(e.what()).find(a.control_endpoint()) != std::string::npos);
  }
}

TEST_CASE("over the wire a session gets exactly the force model's answers", "[net]") {
  Scene scene = default_scene();
  // under either rule for the skin point X (the scene's, which the session's parameters do not carry)
  scene.haptics.skin_point = GENERATE(SkinPointRule::kNormal, SkinPointRule::kLine);
  const auto patient = test::slab_patient();
  net::Server server(scene, patient, nullptr, test::loopback_options());
  server.start();
  Client c(server);
  HapticsSettings params = scene.haptics;
  ProxyState st{};
  PassivityObserver passivity;  // the session's controller (haptics.passivity, on by default) acts on the replies
  // the force model's answer as the pose path serves it: compute_force, then the controller
  auto served = [&](const Vec3& x, double dt) {
    ForceSample f = compute_force(*patient, params, x, dt, st);
    passivity.pose(x, f.contact, f.force_n, scene.haptics.passivity, &st.force_n);
    return f;
  };

  // a press into the slab beside the bone block and out again, at 1 ms of client time per
  // pose (the server takes dt from the client's clock, so the rate clamp is reproducible)
  std::uint64_t seq = 0;
  double t_prev = 0;  // client time of the previous pose; the server's dt is the same difference
  auto step = [&](const Vec3& x) {
    ++seq;
    const double t = 1.0 + seq * 1e-3;
    const v1::PoseReply r = c.send_pose(seq, x, t);
    INFO("pose " << seq);
    CHECK(r.seq() == seq);
    check_same(r, served(x, t - t_prev));
    t_prev = t;
  };
  for (int n = 0; n < 300; ++n) step({27, 30, test::kSlabSkinZ + 2 - 0.1 * n});
  for (int n = 0; n < 100; ++n) step({27 + 0.05 * n, 30, test::kSlabSkinZ - 28});
  // and beside the bone block, where the two rules put X apart (so the server must apply the scene's)
  HapticsSettings other = params;
  other.skin_point = params.skin_point == SkinPointRule::kLine ? SkinPointRule::kNormal : SkinPointRule::kLine;
  ProxyState st_other = st;
  int apart = 0;
  for (int n = 0; n < 100; ++n) {
    const Vec3 x{37.2, 30, test::kSlabSkinZ - 0.1 * n};
    const double dt = 1.0 + (seq + 1) * 1e-3 - t_prev;
    if (norm(compute_force(*patient, other, x, dt, st_other).skin_point_mm -
             [&] { ProxyState s2 = st; return compute_force(*patient, params, x, dt, s2); }().skin_point_mm) > 0.5)
      ++apart;
    step(x);
  }
  CHECK(apart > 10);

  SECTION("a reset applies from the next pose on") {
    v1::ControlRequest q;
    q.mutable_reset()->set_session_id(c.id);
    REQUIRE(c.call(q).has_reset());
    st = ProxyState{};
    passivity = PassivityObserver{};
    step({30, 30, 20});
    step({30.5, 30, 20});
    // and the reset flag of a pose does the same, ordered with the poses
    st = ProxyState{};
    passivity = PassivityObserver{};
    ++seq;
    check_same(c.send_pose(seq, {31, 30, 21}, 1.0 + seq * 1e-3, true), served({31, 30, 21}, 0));
  }
  SECTION("a parameter change applies from the next pose on") {
    v1::ControlRequest q;
    q.mutable_set_parameter()->set_session_id(c.id);
    q.mutable_set_parameter()->set_name("stiffness_n_per_mm");
    q.mutable_set_parameter()->set_value(0.05);
    const auto r = c.call(q);
    REQUIRE(r.has_set_parameter());
    CHECK(r.set_parameter().params().stiffness_n_per_mm() == 0.05);
    params.stiffness_n_per_mm = 0.05;
    for (int n = 0; n < 20; ++n) step({28, 31, 20 + 0.2 * n});
  }
  SECTION("the deformation hook sees the newest contact") {
    const ContactSlot* slot = server.contact_slot(c.id);
    REQUIRE(slot != nullptr);
    Contact k;
    CHECK(slot->read(k) > 0);
    CHECK(k.seq == seq);
    CHECK(k.tip_mm == Vec3{37.2, 30, test::kSlabSkinZ - 0.1 * 99});  // the last pose of the press beside the block
    CHECK(k.contact);
    CHECK(server.contact_slot(c.id ^ 1) == nullptr);
    const auto open = server.open_sessions();
    CHECK(std::find(open.begin(), open.end(), c.id) != open.end());
    // closed: the hook lets go
    v1::ControlRequest q;
    q.mutable_close()->set_session_id(c.id);
    const auto r = c.call(q);
    CHECK(r.close().poses() == seq);
    CHECK(server.contact_slot(c.id) == nullptr);
  }
  server.stop();
}

TEST_CASE("a scene reload swaps the patient, or is refused and the old one kept", "[net]") {
  const auto slab = test::slab_patient();
  const auto sphere = test::sphere_patient();
  // the loader: "sphere" gives the sphere, anything else fails as a CT that cannot be read would
  auto loader = [&](const Scene& s) -> PatientPtr {
    if (s.name == "sphere") return sphere;
    throw Error("ct.nii: cannot read (test loader)");
  };
  net::Server server(default_scene(), slab, loader, test::loopback_options());
  server.start();
  Client c(server);
  const Vec3 p{32, 32, 50};  // inside the sphere, above the slab's skin
  CHECK_FALSE(c.send_pose(1, p, 0).contact());

  v1::ControlRequest q;
  q.mutable_load_scene()->set_text("name: \"broken\"\nphantom { voxel_mm: 2 }\n");
  auto r = c.call(q);
  CHECK(r.error().code() == v1::ERROR_SCENE_LOAD_FAILED);
  CHECK(std::string(r.error().message()).find("ct.nii") != std::string::npos);
  CHECK_FALSE(c.send_pose(2, p, 0).contact());

  q.mutable_load_scene()->set_text("name: \"sphere\"\nphantom { voxel_mm: 2 }\n");
  r = c.call(q);
  REQUIRE(r.error().code() == v1::ERROR_NONE);
  CHECK(r.load_scene().server().scene_generation() == 2);
  // the open session continues on the new patient with a fresh proxy state
  ProxyState st{};
  check_same(c.send_pose(3, p, 0), compute_force(*sphere, default_scene().haptics, p, 0, st));
  server.stop();
}

TEST_CASE("sessions beyond the scene's max_sessions are refused and counted", "[net]") {
  Scene scene = default_scene();
  scene.server.max_sessions = 2;
  net::Server server(scene, test::slab_patient(), nullptr, test::loopback_options());
  server.start();
  Client a(server), b(server);
  v1::ControlRequest q;
  q.mutable_open();
  auto r = a.call(q);
  CHECK(r.error().code() == v1::ERROR_TOO_MANY_SESSIONS);
  CHECK(std::string(r.error().message()).find("max_sessions") != std::string::npos);
  // closing one makes room again, with a new id
  v1::ControlRequest cl;
  cl.mutable_close()->set_session_id(a.id);
  REQUIRE(a.call(cl).has_close());
  r = a.call(q);
  REQUIRE(r.has_open());
  CHECK(r.open().session_id() != a.id);
  v1::ControlRequest st;
  st.mutable_stats();
  r = a.call(st);
  CHECK(r.stats().server().too_many_sessions() == 1);
  CHECK(r.stats().server().sessions_open() == 2);
  server.stop();
}

TEST_CASE("a REQ socket works on the pose path too (empty delimiter mirrored)", "[net]") {
  net::Server server(default_scene(), test::slab_patient(), nullptr, test::loopback_options());
  server.start();
  Client c(server);
  zmq::socket_t req(c.ctx, zmq::socket_type::req);
  req.set(zmq::sockopt::linger, 0);
  req.connect(server.pose_endpoint());
  for (std::uint64_t seq = 1; seq <= 3; ++seq) {
    const auto r = test::exchange<v1::PoseReply>(req, test::pose_request(c.id, seq, {30, 30, 30}, 0));
    CHECK(r.seq() == seq);
    CHECK(r.contact());
  }
  server.stop();
}

TEST_CASE("LoadScene touches no file outside the operator's folders (--scene-dir)", "[net][security]") {
  namespace fs = std::filesystem;
  // a scratch tree: allowed/ holds a scene, other/ one too, allowed/out a link to other/
  const fs::path root = fs::temp_directory_path() / ("palpsim-scene-dir-" + std::to_string(::getpid()));
  fs::remove_all(root);
  fs::create_directories(root / "allowed");
  fs::create_directories(root / "other");
  const std::string scene_text = "name: \"sphere\"\nphantom { voxel_mm: 2 }\n";
  for (const char* d : {"allowed", "other"}) std::ofstream(root / d / "s.textproto") << scene_text;
  fs::create_directory_symlink(root / "other", root / "allowed" / "out");
  // the loader would make any scene; only the policy may refuse
  const auto sphere = test::sphere_patient();
  auto loader = [&](const Scene&) -> PatientPtr { return sphere; };

  SECTION("without folders no path is read") {
    net::Server server(default_scene(), test::slab_patient(), loader, test::loopback_options());
    server.start();
    Client c(server);
    v1::ControlRequest q;
    q.mutable_load_scene()->set_path((root / "allowed" / "s.textproto").string());
    const auto r = c.call(q);
    CHECK(r.error().code() == v1::ERROR_SCENE_LOAD_FAILED);
    CHECK_THAT(r.error().message(), Catch::Contains("--scene-dir"));
    // a text scene of the phantom names no file: still served
    v1::ControlRequest t;
    t.mutable_load_scene()->set_text(scene_text);
    CHECK(c.call(t).error().code() == v1::ERROR_NONE);
    server.stop();
  }
  SECTION("with a folder: inside it is read; outside, '..' and links out are refused, naming the path") {
    net::ServerOptions o = test::loopback_options();
    o.scene_dirs = {(root / "allowed").string()};
    net::Server server(default_scene(), test::slab_patient(), loader, o);
    server.start();
    Client c(server);
    auto load_path = [&](const fs::path& p) {
      v1::ControlRequest q;
      q.mutable_load_scene()->set_path(p.string());
      return c.call(q);
    };
    CHECK(load_path(root / "allowed" / "s.textproto").error().code() == v1::ERROR_NONE);
    for (const fs::path& bad : {root / "other" / "s.textproto", root / "allowed" / ".." / "other" / "s.textproto",
                                root / "allowed" / "out" / "s.textproto", fs::path("/etc/passwd")}) {
      INFO(bad);
      const auto r = load_path(bad);
      CHECK(r.error().code() == v1::ERROR_SCENE_LOAD_FAILED);
      CHECK_THAT(r.error().message(), Catch::Contains("outside the folders"));
      CHECK_THAT(r.error().message(), Catch::Contains(bad.string()));
    }
    // a text scene may not name a CT or a recording folder outside them either
    for (const std::string& text : {std::string("name: \"ct\"\nct_path: \"") + (root / "other" / "ct.nrrd").string() + "\"\n",
                                    scene_text + "render { record_dir: \"" + (root / "other" / "rec").string() + "\" }\n"}) {
      INFO(text);
      v1::ControlRequest q;
      q.mutable_load_scene()->set_text(text);
      const auto r = c.call(q);
      CHECK(r.error().code() == v1::ERROR_SCENE_LOAD_FAILED);
      CHECK_THAT(r.error().message(), Catch::Contains("outside the folders"));
    }
    CHECK_FALSE(fs::exists(root / "other" / "rec"));
    // the server kept serving the scene it had
    CHECK(c.send_pose(1, {32, 32, 50}, 0).error().code() == v1::ERROR_NONE);
    server.stop();
  }
  SECTION("a folder that does not exist is refused at start, named") {
    net::ServerOptions o = test::loopback_options();
    o.scene_dirs = {(root / "missing").string()};
    CHECK_THROWS_WITH(net::Server(default_scene(), test::slab_patient(), loader, o),
                      Catch::Contains((root / "missing").string()));
  }
  fs::remove_all(root);
}

TEST_CASE("beyond loopback the server binds only with --insecure, naming the address", "[net][security]") {
  for (const char* e : {"tcp://127.0.0.1:7420", "tcp://127.0.0.1:*", "tcp://localhost:7", "tcp://[::1]:7", "tcp://lo:7",
                        "ipc:///tmp/x", "inproc://x"})
    CHECK(net::is_loopback_endpoint(e));
  for (const char* e : {"tcp://0.0.0.0:7420", "tcp://*:7420", "tcp://192.168.1.5:7420", "tcp://eth0:7420",
                        "tcp://127example.org:7", "tcp://localhost.evil.org:7"})
    CHECK_FALSE(net::is_loopback_endpoint(e));
  // the control address, or a pose or stream address given apart from it
  for (int which = 0; which < 3; ++which) {
    net::ServerOptions o = test::loopback_options();
    std::string& addr = which == 0 ? o.control_bind : which == 1 ? o.pose_bind : o.stream_bind;
    if (which == 0) o.pose_bind = o.stream_bind = "tcp://127.0.0.1:*";
    addr = "tcp://0.0.0.0:*";
    INFO("address " << which);
    CHECK_THROWS_WITH(net::Server(default_scene(), test::slab_patient(), nullptr, o),
                      Catch::Contains("tcp://0.0.0.0:*") && Catch::Contains("--insecure"));
    o.insecure = true;
    net::Server server(default_scene(), test::slab_patient(), nullptr, o);
    server.start();
    Client c(server);
    CHECK(c.send_pose(1, {32, 32, 50}, 0).error().code() == v1::ERROR_NONE);
    server.stop();
  }
}
