// Who may connect (issue 9, section 1), with the real palpsim-server, palpsim-keys and
// palpsim-haptic on loopback: CURVE admits only allow-listed keys and counts the others,
// a wrong server key or a plain-text client gets no answer, and a session belongs to the
// client that opened it (its key with CURVE; its token or control connection without).
// Key files of the wrong half stop the server and name the file, and refusals are logged
// with the peer's address and key, rate-limited (issue 26, finding 8).
#include <catch2/catch.hpp>

#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>
#include <zmq.hpp>

#include "net/curve_keys.h"
#include "palpsim/wire.pb.h"
#include "server_process.h"
#include "support/zmq_exchange.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using net::CurveKeyPair;

namespace {

// A healthy server answers in milliseconds; 5 s covers a loaded 2-core CI machine.
constexpr int kReplyMs = 5000;
// A refused handshake never answers. An admitted client's first reply comes within
// ~100 ms of connecting on loopback (handshake included), so 1.5 s of silence means refused.
constexpr int kSilenceMs = 1500;

// bricks make a stream (and WatchSession) without an EGL context: a cheap scene to watch
std::string bricks_scene_text() {
  return "name: \"security\"\nphantom { voxel_mm: 2.0 }\neffects { haptics: true bricks: true }\n"
         "server { session_timeout_s: 10 max_sessions: 32 }\n";
}

// a fresh folder under /tmp
std::string temp_dir(const std::string& stem) {
  std::string d = "/tmp/palpsim-it-" + std::to_string(::getpid()) + "-" + stem + "-XXXXXX";
  REQUIRE(::mkdtemp(d.data()) != nullptr);
  return d;
}

// runs palpsim-keys with `args`; returns its exit status (stderr in `err`, stdout in `out`)
int run_keys(const std::vector<std::string>& args, std::string* err = nullptr, std::string* out = nullptr) {
  std::vector<std::string> a{test::build_exe("palpsim-keys")};
  a.insert(a.end(), args.begin(), args.end());
  test::Child c(a);
  const int rc = c.wait(30);
  if (err) *err = c.err();
  if (out) *out = c.out();
  return rc;
}

// a key pair made by palpsim-keys in `dir`
CurveKeyPair make_keys(const std::string& dir, const std::string& name) {
  REQUIRE(run_keys({name, "--dir", dir}) == 0);
  return net::read_secret_key_file(dir + "/" + name + ".key_secret");
}

std::string slurp(const std::string& path) {
  std::ifstream in(path);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// one client: a DEALER for control requests and one for poses, CURVE when given keys
class Peer {
 public:
  Peer(const std::string& control, const CurveKeyPair* me = nullptr, const std::string& server_key = "",
       const std::string& token = "")
      : ctl_(ctx_, zmq::socket_type::dealer), pose_(ctx_, zmq::socket_type::dealer), token_(token) {
    for (zmq::socket_t* s : {&ctl_, &pose_}) {
      s->set(zmq::sockopt::linger, 0);
      if (me) net::make_curve_client(*s, server_key, *me);
    }
    ctl_.connect(control);
  }
  /// One control request and its reply, or nothing within `wait_ms`.
  std::optional<v1::ControlReply> call(v1::ControlRequest q, int wait_ms = kReplyMs) {
    q.set_schema_version(1);
    q.set_client_token(token_);
    return exchange<v1::ControlReply>(ctl_, q.SerializeAsString(), wait_ms);
  }
  /// Opens a session (the test fails when it is refused) and connects the pose socket.
  v1::OpenReply open(const std::string& name) {
    v1::ControlRequest q;
    q.mutable_open()->set_client_name(name);
    const auto r = call(q);
    REQUIRE(r);
    REQUIRE(r->has_open());
    if (!pose_connected_) pose_.connect(r->open().pose_endpoint());
    pose_connected_ = true;
    return r->open();
  }
  /// One pose for `session` and its reply (the test fails without one).
  v1::PoseReply pose(std::uint64_t session, std::uint64_t seq, double x, double y, double z) {
    v1::PoseRequest q;
    q.set_schema_version(1);
    q.set_session_id(session);
    q.set_seq(seq);
    q.mutable_tip_mm()->set_x(x);
    q.mutable_tip_mm()->set_y(y);
    q.mutable_tip_mm()->set_z(z);
    const auto r = exchange<v1::PoseReply>(pose_, q.SerializeAsString(), kReplyMs);
    REQUIRE(r);
    return *r;
  }
  /// Connects the pose socket without opening a session (to pose for someone else's).
  void connect_poses(const std::string& endpoint) {
    pose_.connect(endpoint);
    pose_connected_ = true;
  }
  /// The server's counters (the test fails without a reply).
  v1::ServerStats stats() {
    v1::ControlRequest q;
    q.mutable_stats();
    const auto r = call(q);
    REQUIRE(r);
    REQUIRE(r->has_stats());
    return r->stats().server();
  }

 private:
  zmq::context_t ctx_{1};
  zmq::socket_t ctl_, pose_;
  std::string token_;
  bool pose_connected_ = false;

  template <class Reply>
  static std::optional<Reply> exchange(zmq::socket_t& s, const std::string& bytes, int wait_ms) {
    s.send(zmq::buffer(bytes), zmq::send_flags::dontwait);
    return test::reply_within<Reply>(s, wait_ms);
  }
};

// the control requests that name a session: close, reset, stats of it, watch
std::vector<v1::ControlRequest> session_requests(std::uint64_t id) {
  std::vector<v1::ControlRequest> out(4);
  out[0].mutable_close()->set_session_id(id);
  out[1].mutable_reset()->set_session_id(id);
  out[2].mutable_stats()->set_session_id(id);
  out[3].mutable_watch()->set_session_id(id);
  out[3].mutable_watch()->set_bricks(true);
  return out;
}

// every request of session_requests(id) from `intruder` is refused with ERROR_NOT_OWNER
void check_refused(Peer& intruder, std::uint64_t id) {
  for (const auto& q : session_requests(id)) {
    const auto r = intruder.call(q);
    REQUIRE(r);
    INFO(q.ShortDebugString() << " -> " << r->ShortDebugString());
    CHECK(r->error().code() == v1::ERROR_NOT_OWNER);
    CHECK(r->error().message().find("belongs to another client") != std::string::npos);
  }
}

// a server on the bricks scene with `extra` arguments, ready
std::unique_ptr<test::ServerProcess> start(const std::string& scene, const std::vector<std::string>& extra) {
  auto s = std::make_unique<test::ServerProcess>(scene, extra);
  const bool ready = s->wait_ready(300);
  INFO("server stderr:\n" << s->child().err());
  REQUIRE(ready);
  return s;
}

// the server on `scene` with `extra` arguments, run until it exits (it is meant to refuse
// to start): its exit status and stderr
std::pair<int, std::string> run_to_exit(const std::string& scene, const std::vector<std::string>& extra) {
  test::ServerProcess s(scene, extra);
  const int rc = s.child().wait(120);
  return std::make_pair(rc, s.child().err());
}

}  // namespace

TEST_CASE("palpsim-keys writes a pair, the secret key 0600, and replaces files only with --force",
          "[integration][security]") {
  const std::string dir = temp_dir("keys");
  const CurveKeyPair pair = make_keys(dir, "station");
  struct stat pub_st {}, sec_st {};
  REQUIRE(::stat((dir + "/station.key").c_str(), &pub_st) == 0);
  REQUIRE(::stat((dir + "/station.key_secret").c_str(), &sec_st) == 0);
  CHECK((sec_st.st_mode & 0777) == 0600);
  CHECK((pub_st.st_mode & 0777) == 0644);
  // the public file holds the public half of the secret file, which --public prints
  CHECK(net::read_key_file(dir + "/station.key") == pair.public_key);
  std::string printed;
  CHECK(run_keys({"--public", dir + "/station.key_secret"}, nullptr, &printed) == 0);
  CHECK(printed == pair.public_key + "\n");
  // a second run refuses, naming the file, and leaves both files as they were
  const std::string before = slurp(dir + "/station.key_secret");
  std::string err;
  CHECK(run_keys({"station", "--dir", dir}, &err) == 1);
  CHECK(err.find("station.key") != std::string::npos);
  CHECK(err.find("--force") != std::string::npos);
  CHECK(slurp(dir + "/station.key_secret") == before);
  // --force makes a new pair
  CHECK(run_keys({"station", "--dir", dir, "--force"}) == 0);
  CHECK(net::read_secret_key_file(dir + "/station.key_secret").secret_key != pair.secret_key);
  REQUIRE(::stat((dir + "/station.key_secret").c_str(), &sec_st) == 0);
  CHECK((sec_st.st_mode & 0777) == 0600);
}

TEST_CASE("CURVE: allowed keys are served, others are refused and counted, sessions belong to their key",
          "[integration][security]") {
  const std::string dir = temp_dir("curve");
  const CurveKeyPair server = make_keys(dir, "server"), alice = make_keys(dir, "alice"), bob = make_keys(dir, "bob"),
                     mallory = make_keys(dir, "mallory");
  const std::string allow = dir + "/allowed";
  std::ofstream(allow) << slurp(dir + "/alice.key") << slurp(dir + "/bob.key");
  const std::string scene = test::temp_file("scene", bricks_scene_text());
  // beyond loopback (every interface) without --insecure: keys make it allowed
  auto srv = start(scene, {"--bind", "tcp://0.0.0.0:*", "--pose-bind", "tcp://0.0.0.0:*", "--stream-bind",
                           "tcp://0.0.0.0:*", "--curve-secret", dir + "/server.key_secret", "--allow", allow});
  const std::string addr = srv->control();

  // alice: a session, and forces from a press into the body
  Peer a(addr, &alice, server.public_key);
  const v1::OpenReply opened = a.open("alice");
  CHECK(opened.server().curve());
  const auto& body = opened.server().patient();
  const double x = 0.5 * (body.body_min_mm().x() + body.body_max_mm().x());
  const double z = 0.5 * (body.body_min_mm().z() + body.body_max_mm().z());
  bool felt = false;
  for (int k = 0; k <= 40 && !felt; ++k) {
    const v1::PoseReply r = a.pose(opened.session_id(), k + 1, x, body.body_max_mm().y() + 5 - k, z);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    felt = r.contact() && std::hypot(r.force_n().x(), r.force_n().y(), r.force_n().z()) > 0;
  }
  CHECK(felt);

  SECTION("an unknown key, a wrong server key and a plain-text client get no answer; refusals are counted") {
    const std::uint64_t refused_before = a.stats().curve_refused();
    v1::ControlRequest info;
    info.mutable_info();
    Peer unknown(addr, &mallory, server.public_key);
    CHECK_FALSE(unknown.call(info, kSilenceMs));
    Peer wrong_server(addr, &alice, bob.public_key);  // alice is allowed, but this is not the server's key
    CHECK_FALSE(wrong_server.call(info, kSilenceMs));
    Peer plain(addr);
    CHECK_FALSE(plain.call(info, kSilenceMs));
    // the ZAP handler saw mallory's key (the other two fail before it is asked)
    CHECK(a.stats().curve_refused() >= refused_before + 1);
    // palpsim-haptic without keys says why it may have heard nothing
    test::Child h({test::build_exe("palpsim-haptic"), "--connect", addr, "--seconds", "0.2"});
    CHECK(h.wait(60) == 1);
    CHECK(h.err().find("--server-key") != std::string::npos);
  }

  SECTION("palpsim-haptic with keys runs its loop") {
    test::Child h({test::build_exe("palpsim-haptic"), "--connect", addr, "--seconds", "0.5", "--server-key",
                   dir + "/server.key", "--client-key", dir + "/alice.key_secret"});
    const int rc = h.wait(60);
    INFO("palpsim-haptic stdout:\n" << h.out() << "\nstderr:\n" << h.err());
    CHECK(rc == 0);
    CHECK(h.out().find(" 0 errors") != std::string::npos);
  }

  SECTION("another allowed key cannot close, reset, read, watch, pose for or subscribe to alice's session") {
    Peer b(addr, &bob, server.public_key);
    const std::uint64_t not_owner_before = b.stats().not_owner();
    check_refused(b, opened.session_id());
    b.connect_poses(opened.pose_endpoint());
    const v1::PoseReply r = b.pose(opened.session_id(), 1, x, body.body_max_mm().y() - 10, z);
    CHECK(r.error().code() == v1::ERROR_NOT_OWNER);
    CHECK(r.force_n().y() == 0);
    // the stream: bob's subscription to alice's brick topic is refused (he gets nothing),
    // alice's own gets the key at once
    v1::ControlRequest w;
    w.mutable_watch()->set_session_id(opened.session_id());
    w.mutable_watch()->set_bricks(true);
    const auto watched = a.call(w);
    REQUIRE(watched);
    REQUIRE(watched->has_watch());
    const std::string topic = watched->watch().brick_topic();
    auto subscriber = [&](zmq::context_t& ctx, const CurveKeyPair& who) {
      zmq::socket_t s(ctx, zmq::socket_type::sub);
      s.set(zmq::sockopt::linger, 0);
      net::make_curve_client(s, server.public_key, who);
      s.connect(watched->watch().stream_endpoint());
      s.set(zmq::sockopt::subscribe, topic);
      return s;
    };
    zmq::context_t ctx(1);
    zmq::socket_t bob_sub = subscriber(ctx, bob);
    zmq::pollitem_t bob_item[] = {{bob_sub.handle(), 0, ZMQ_POLLIN, 0}};
    zmq::poll(bob_item, 1, std::chrono::milliseconds(kSilenceMs));
    CHECK_FALSE((bob_item[0].revents & ZMQ_POLLIN));
    zmq::socket_t alice_sub = subscriber(ctx, alice);
    zmq::pollitem_t alice_item[] = {{alice_sub.handle(), 0, ZMQ_POLLIN, 0}};
    zmq::poll(alice_item, 1, std::chrono::milliseconds(kReplyMs));
    CHECK((alice_item[0].revents & ZMQ_POLLIN));
    zmq::poll(bob_item, 1, std::chrono::milliseconds(0));
    CHECK_FALSE((bob_item[0].revents & ZMQ_POLLIN));
    // four control requests, one pose and one subscription, each counted
    CHECK(b.stats().not_owner() == not_owner_before + 6);
    // alice's session went on through all of it
    CHECK(a.pose(opened.session_id(), 100, x, body.body_max_mm().y() - 10, z).error().code() == v1::ERROR_NONE);
  }
  CHECK(srv->stop() == 0);
  std::remove(scene.c_str());
}

TEST_CASE("without keys a session belongs to its control connection or client token", "[integration][security]") {
  const std::string scene = test::temp_file("scene", bricks_scene_text());
  auto srv = start(scene, {});
  Peer a(srv->control());
  const v1::OpenReply mine = a.open("a");
  CHECK_FALSE(mine.server().curve());

  // another connection, even one that knows the id, is refused and counted
  Peer other(srv->control());
  const std::uint64_t not_owner_before = other.stats().not_owner();
  check_refused(other, mine.session_id());
  CHECK(other.stats().not_owner() == not_owner_before + 4);
  // a watch of "any session" finds none of the other connection's own
  v1::ControlRequest any;
  any.mutable_watch()->set_bricks(true);
  const auto none = other.call(any);
  REQUIRE(none);
  CHECK(none->error().code() == v1::ERROR_NO_SESSION_OPEN);
  // the refusal says how to watch another connection's session: a shared client token
  CHECK_THAT(none->error().message(), Catch::Contains("--client-token"));

  // a session opened with a token: the same token on another connection may act on it
  // (a viewer beside a haptic client), another token may not
  Peer haptic(srv->control(), nullptr, "", "station-7");
  const v1::OpenReply shared = haptic.open("haptic");
  Peer viewer(srv->control(), nullptr, "", "station-7");
  v1::ControlRequest stats_of;
  stats_of.mutable_stats()->set_session_id(shared.session_id());
  const auto seen = viewer.call(stats_of);
  REQUIRE(seen);
  CHECK(seen->error().code() == v1::ERROR_NONE);
  CHECK(seen->stats().session().client_name() == "haptic");
  const auto watched = viewer.call(any);  // "any": the token's newest session
  REQUIRE(watched);
  CHECK(watched->watch().session_id() == shared.session_id());
  Peer stranger(srv->control(), nullptr, "", "station-8");
  check_refused(stranger, shared.session_id());

  // the owner still has its session
  v1::ControlRequest close;
  close.mutable_close()->set_session_id(mine.session_id());
  const auto closed = a.call(close);
  REQUIRE(closed);
  CHECK(closed->error().code() == v1::ERROR_NONE);
  CHECK(srv->stop() == 0);
  std::remove(scene.c_str());
}

TEST_CASE("bad key options stop the server at start, naming the file and line", "[integration][security]") {
  const std::string dir = temp_dir("badkeys");
  make_keys(dir, "server");
  const std::string allow = dir + "/allowed";
  std::ofstream(allow) << "# the lab's stations\n" << slurp(dir + "/server.key") << "not-a-key\n";
  const std::string scene = test::temp_file("scene", bricks_scene_text());
  const auto [rc, err] = run_to_exit(scene, {"--curve-secret", dir + "/server.key_secret", "--allow", allow});
  CHECK(rc == 1);
  CHECK(err.find(allow + ":4") != std::string::npos);  // line 4: the public file's comment and key are lines 2-3
  const auto [rc2, err2] = run_to_exit(scene, {"--curve-secret", dir + "/server.key_secret"});
  CHECK(rc2 == 1);
  CHECK(err2.find("--curve-secret needs --allow") != std::string::npos);
  const auto [rc3, err3] = run_to_exit(scene, {"--bind", "tcp://0.0.0.0:*"});
  CHECK(rc3 == 1);
  CHECK(err3.find("--curve-secret") != std::string::npos);  // the refusal names the way to bind beyond loopback
  std::remove(scene.c_str());
}

TEST_CASE("a key of the wrong half, a pair that does not match or a secret key on the allow-list stop the server",
          "[integration][security]") {
  const std::string dir = temp_dir("halves");
  make_keys(dir, "server");
  make_keys(dir, "alice");
  make_keys(dir, "other");
  const std::string allow = dir + "/allowed";
  std::ofstream(allow) << slurp(dir + "/alice.key");
  const std::string scene = test::temp_file("scene", bricks_scene_text());
  // the public key file as the secret: another key, and every client would get silence
  auto [rc, err] = run_to_exit(scene, {"--curve-secret", dir + "/server.key", "--allow", allow});
  CHECK(rc == 1);
  CHECK(err.find(dir + "/server.key: a public key") != std::string::npos);
  // a secret key file as the allow-list
  std::tie(rc, err) =
      run_to_exit(scene, {"--curve-secret", dir + "/server.key_secret", "--allow", dir + "/alice.key_secret"});
  CHECK(rc == 1);
  CHECK(err.find(dir + "/alice.key_secret: a secret key file") != std::string::npos);
  // a secret key among the public ones (cat of the wrong file)
  const std::string mixed = dir + "/mixed";
  std::ofstream(mixed) << slurp(dir + "/alice.key") << slurp(dir + "/other.key_secret");
  std::tie(rc, err) = run_to_exit(scene, {"--curve-secret", dir + "/server.key_secret", "--allow", mixed});
  CHECK(rc == 1);
  CHECK(err.find(mixed + ":4: a secret key") != std::string::npos);
  // the public key given, or the one beside the secret, of another pair
  std::tie(rc, err) = run_to_exit(scene, {"--curve-secret", dir + "/server.key_secret", "--curve-public",
                                          dir + "/other.key", "--allow", allow});
  CHECK(rc == 1);
  CHECK(err.find("server.key_secret and " + dir + "/other.key are not a pair") != std::string::npos);
  const std::string server_pub = slurp(dir + "/server.key");
  std::ofstream(dir + "/server.key") << slurp(dir + "/other.key");
  std::tie(rc, err) = run_to_exit(scene, {"--curve-secret", dir + "/server.key_secret", "--allow", allow});
  CHECK(rc == 1);
  CHECK(err.find("server.key_secret and " + dir + "/server.key are not a pair") != std::string::npos);
  std::ofstream(dir + "/server.key") << server_pub;
  // palpsim-keys --public and palpsim-haptic say the same of the wrong half
  std::string keys_err;
  CHECK(run_keys({"--public", dir + "/alice.key"}, &keys_err) == 1);
  CHECK(keys_err.find("alice.key: a public key") != std::string::npos);
  test::Child h({test::build_exe("palpsim-haptic"), "--connect", "tcp://127.0.0.1:9", "--seconds", "0.2",
                 "--server-key", dir + "/server.key_secret", "--client-key", dir + "/alice.key_secret"});
  CHECK(h.wait(60) == 1);
  CHECK(h.err().find("server.key_secret: a secret key") != std::string::npos);
  std::remove(scene.c_str());
}

TEST_CASE("refused handshakes are logged with the peer's address and key, a summary per period at most",
          "[integration][security]") {
  const std::string dir = temp_dir("refusals");
  const CurveKeyPair server = make_keys(dir, "server"), mallory = make_keys(dir, "mallory");
  make_keys(dir, "alice");
  const std::string scene = test::temp_file("scene", bricks_scene_text());
  auto srv = start(scene, {"--curve-secret", dir + "/server.key_secret", "--allow", dir + "/alice.key"});
  const auto t0 = std::chrono::steady_clock::now();
  // mallory tries 20 times (and ZeroMQ retries each refused connection by itself)
  v1::ControlRequest info;
  info.mutable_info();
  for (int i = 0; i < 20; ++i) {
    Peer m(srv->control(), &mallory, server.public_key);
    CHECK_FALSE(m.call(info, 200));
  }
  // the summary of those after the first comes within the period (5 s) of the first line
  auto lines = [&] {
    std::vector<std::string> out;
    std::istringstream in(srv->child().err());
    for (std::string l; std::getline(in, l);)
      if (l.find("CURVE: refused") != std::string::npos) out.push_back(l);
    return out;
  };
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (lines().size() < 2 && std::chrono::steady_clock::now() < end) ::usleep(100000);
  const double elapsed_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const auto found = lines();
  INFO("server stderr:\n" << srv->child().err());
  REQUIRE(found.size() >= 2);
  // the first at once: peer address and key; then a count per peer and key
  CHECK(found[0].find("from 127.0.0.1, client key " + mallory.public_key + ": not on the allow-list") !=
        std::string::npos);
  CHECK(found[1].find("more connections in") != std::string::npos);
  CHECK(found[1].find("127.0.0.1 key " + mallory.public_key + " x") != std::string::npos);
  // at most one line per 5 s, however often mallory knocked (>= 20 times)
  CHECK(double(found.size()) <= 1 + elapsed_s / 5 + 1);
  CHECK(srv->stop() == 0);
  std::remove(scene.c_str());
}
