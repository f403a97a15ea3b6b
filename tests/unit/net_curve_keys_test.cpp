// CURVE key files and session ownership, in-process: what palpsim-keys writes and the
// server reads (comments, a key that begins with '#', errors naming file and line), the
// pose thread's fixed-size key check, and the server's refusals of half-given keys.
#include <catch2/catch.hpp>

#include <sys/stat.h>
#include <unistd.h>

#include <fstream>
#include <string>

#include "core/error.h"
#include "net/curve_keys.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "net/session_table.h"
#include "support/net_client.h"
#include "support/synthetic_patient.h"

using namespace palpsim;

namespace {

// a fresh folder under /tmp
std::string temp_dir() {
  std::string d = "/tmp/palpsim-unit-keys-XXXXXX";
  REQUIRE(::mkdtemp(d.data()) != nullptr);
  return d;
}

std::string write(const std::string& dir, const std::string& name, const std::string& text) {
  const std::string p = dir + "/" + name;
  std::ofstream(p) << text;
  return p;
}

}  // namespace

TEST_CASE("key files: comments, blanks and one z85 key; errors name the file and line", "[net][security]") {
  REQUIRE(net::curve_available());
  const std::string dir = temp_dir();
  const net::CurveKeyPair pair = net::make_curve_keypair();
  CHECK(net::check_z85_key(pair.public_key).empty());
  CHECK(net::curve_public_of(pair.secret_key) == pair.public_key);
  // z85 has '#': a key that begins with it is a key, "# " starts a comment
  const std::string hash_key = "#" + pair.public_key.substr(1);
  CHECK(net::read_key_file(write(dir, "a.key", "# comment\n\n  " + hash_key + "   # trailing\n")) == hash_key);
  CHECK_THROWS_WITH(net::read_key_file(write(dir, "b.key", "# none here\n")),
                    Catch::Contains("b.key: no key"));
  CHECK_THROWS_WITH(net::read_key_file(write(dir, "c.key", pair.public_key + "\n" + pair.public_key + "\n")),
                    Catch::Contains("c.key:2: a second key"));
  CHECK_THROWS_WITH(net::read_key_file(write(dir, "d.key", "\n" + pair.public_key.substr(0, 39) + "\n")),
                    Catch::Contains("d.key:2: not a key: 39 characters"));
  CHECK_THROWS_WITH(net::read_key_file(write(dir, "e.key", pair.public_key.substr(0, 39) + "\"\n")),
                    Catch::Contains("e.key:1: not a key: character '\"'"));
  CHECK_THROWS_WITH(net::read_key_file(write(dir, "f.key", pair.public_key + " junk\n")),
                    Catch::Contains("f.key:1: not a key"));
  CHECK_THROWS_WITH(net::read_key_file(dir + "/missing.key"), Catch::Contains("missing.key: cannot read"));
  // an allow-list is key files put together; a bad line is named, an empty list refused
  const net::CurveKeyPair other = net::make_curve_keypair();
  const auto keys = net::read_allow_list(
      write(dir, "allowed", "# lab\n" + pair.public_key + "\n\n" + other.public_key + "  # station 2\n"));
  CHECK(keys == std::vector<std::string>{pair.public_key, other.public_key});
  CHECK_THROWS_WITH(net::read_allow_list(write(dir, "bad", pair.public_key + "\n\nnope\n")),
                    Catch::Contains("bad:3: not a client public key"));
  CHECK_THROWS_WITH(net::read_allow_list(write(dir, "empty", "# nobody\n")), Catch::Contains("no keys"));
}

TEST_CASE("a key pair is written 0600 / 0644 and never over an existing file", "[net][security]") {
  const std::string dir = temp_dir();
  const net::CurveKeyPair pair = net::make_curve_keypair();
  const auto paths = net::write_key_pair(pair, dir, "s", false);
  REQUIRE(paths.size() == 2);
  struct stat st {};
  REQUIRE(::stat(paths[1].c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0600);
  CHECK(net::read_secret_key_file(paths[1]).public_key == pair.public_key);
  CHECK(net::read_key_file(paths[0]) == pair.public_key);
  // a secret file alone in the way: refused before either file is written
  write(dir, "t.key_secret", "keep me\n");
  CHECK_THROWS_WITH(net::write_key_pair(pair, dir, "t", false), Catch::Contains("t.key_secret: exists"));
  CHECK(::access((dir + "/t.key").c_str(), F_OK) != 0);
  CHECK_NOTHROW(net::write_key_pair(net::make_curve_keypair(), dir, "s", true));
  CHECK(net::read_key_file(paths[0]) != pair.public_key);
}

TEST_CASE("a session's key check: any sender without CURVE, only the opener's key with it", "[net][security]") {
  net::SessionSlot slot;
  const std::string a = net::make_curve_keypair().public_key, b = net::make_curve_keypair().public_key;
  CHECK(slot.key_may_act(nullptr));
  CHECK(slot.key_may_act(b.c_str()));
  slot.set_owner_key(a.c_str());
  CHECK(slot.key_may_act(a.c_str()));
  CHECK_FALSE(slot.key_may_act(b.c_str()));
  CHECK_FALSE(slot.key_may_act(nullptr));
  // a key differing in its last character only (the last of the five words compared)
  std::string near = a;
  near.back() = near.back() == 'x' ? 'y' : 'x';
  CHECK_FALSE(slot.key_may_act(near.c_str()));
  slot.set_owner_key(nullptr);
  CHECK(slot.key_may_act(b.c_str()));
}

TEST_CASE("keys given by halves stop the server; with keys it binds beyond loopback", "[net][security]") {
  const net::CurveKeyPair server = net::make_curve_keypair(), client = net::make_curve_keypair();
  net::ServerOptions o = test::loopback_options();
  o.curve_allowed_keys = {client.public_key};
  CHECK_THROWS_WITH(net::Server(default_scene(), test::slab_patient(), nullptr, o),
                    Catch::Contains("--allow needs --curve-secret"));
  o.curve_allowed_keys.clear();
  o.curve_secret_key = server.secret_key;
  CHECK_THROWS_WITH(net::Server(default_scene(), test::slab_patient(), nullptr, o), Catch::Contains("--allow"));
  o.curve_allowed_keys = {client.public_key};
  o.control_bind = o.pose_bind = "tcp://0.0.0.0:*";
  net::Server s(default_scene(), test::slab_patient(), nullptr, o);
  CHECK(s.control_endpoint().rfind("tcp://0.0.0.0:", 0) == 0);
}
