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
#include "runtime/session_table.h"
#include "net/zap_handler.h"
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

TEST_CASE("a key of the wrong half, a pair that does not match and a secret key on an allow-list are refused",
          "[net][security]") {
  const std::string dir = temp_dir();
  const net::CurveKeyPair pair = net::make_curve_keypair(), other = net::make_curve_keypair();
  net::write_key_pair(pair, dir, "server", false);
  const std::string pub = dir + "/server.key", sec = dir + "/server.key_secret";
  // each half where the other is asked for: refused, the file named and how it was told
  CHECK_THROWS_WITH(net::read_secret_key_file(pub), Catch::Contains(pub + ": a public key (palpsim-keys marked it so"));
  CHECK_THROWS_WITH(net::read_public_key_file(sec), Catch::Contains(sec + ": a secret key (palpsim-keys marked it so"));
  CHECK(net::read_public_key_file(pub) == pair.public_key);
  CHECK(net::read_secret_key_file(sec).public_key == pair.public_key);  // server.key beside it matches
  // without palpsim-keys' comment the name tells; a name that tells nothing is taken as asked
  CHECK_THROWS_WITH(net::read_secret_key_file(write(dir, "bare.key", pair.public_key + "\n")),
                    Catch::Contains("bare.key: a public key (its name ends in .key)"));
  CHECK_THROWS_WITH(net::read_public_key_file(write(dir, "bare.key_secret", pair.secret_key + "\n")),
                    Catch::Contains("bare.key_secret: a secret key (its name ends in .key_secret)"));
  CHECK(net::read_secret_key_file(write(dir, "mounted", pair.secret_key + "\n")).public_key == pair.public_key);
  // a comment outweighs the name
  CHECK_THROWS_WITH(net::read_secret_key_file(write(dir, "renamed", "# palpsim CURVE public key 'x'\n" +
                                                                       pair.public_key + "\n")),
                    Catch::Contains("renamed: a public key (palpsim-keys marked it so on line 1)"));
  // NAME.key beside NAME.key_secret replaced by another key: not a pair, both named
  write(dir, "server.key", "# palpsim CURVE public key 'server'\n" + other.public_key + "\n");
  CHECK_THROWS_WITH(net::read_secret_key_file(sec),
                    Catch::Contains(sec + " and " + pub + " are not a pair") && Catch::Contains(other.public_key));
  // a public file named explicitly: checked whatever lies beside
  const std::string given = write(dir, "given.key", pair.public_key + "\n");
  CHECK_THROWS_WITH(net::read_secret_key_file(sec, pub), Catch::Contains("are not a pair"));
  write(dir, "server.key", pair.public_key + "\n");
  CHECK(net::read_secret_key_file(sec, given).secret_key == pair.secret_key);
  CHECK_THROWS_WITH(net::read_secret_key_file(sec, dir + "/missing.key"), Catch::Contains("missing.key: cannot read"));
  // an allow-list: never a secret key file, never a key palpsim-keys marked secret
  CHECK_THROWS_WITH(net::read_allow_list(sec), Catch::Contains(sec + ": a secret key file"));
  net::write_key_pair(other, dir, "bob", false);
  std::ifstream a(pub), b(dir + "/bob.key_secret");
  const std::string list = std::string(std::istreambuf_iterator<char>(a), {}) +
                           std::string(std::istreambuf_iterator<char>(b), {});
  CHECK_THROWS_WITH(net::read_allow_list(write(dir, "allowed", list)),
                    Catch::Contains("allowed:3: a secret key (palpsim-keys marked it so on line 2)"));
}

TEST_CASE("refused handshakes: a line at once, then one summary per period at most", "[net][security]") {
  net::RefusalLog log(5.0, 2);
  const std::string k1(40, 'a'), k2(40, 'b'), k3(40, 'c');
  // the first: at once, with address, key and why
  const std::string first = log.refused("10.0.0.7", k1, "not on the allow-list", 100.0);
  CHECK(first.find("10.0.0.7") != std::string::npos);
  CHECK(first.find("client key " + k1) != std::string::npos);
  CHECK(first.find("not on the allow-list") != std::string::npos);
  // a flood within the period: counted, no line
  for (int i = 0; i < 1000; ++i) {
    CHECK(log.refused("10.0.0.7", k1, "not on the allow-list", 100.0 + i * 0.004).empty());
    CHECK(log.refused("10.0.0.8", k2, "not on the allow-list", 100.0 + i * 0.004).empty());
    CHECK(log.refused("10.0.0.9", k3, "not on the allow-list", 100.0 + i * 0.004).empty());
  }
  CHECK(log.flush(104.9).empty());
  // the period over: one summary, the first two peers named with their counts, the third counted
  const std::string summary = log.flush(105.0);
  INFO(summary);
  CHECK(summary.find("refused 3000 more connections") != std::string::npos);
  CHECK(summary.find("10.0.0.7 key " + k1 + " x1000") != std::string::npos);
  CHECK(summary.find("10.0.0.8 key " + k2 + " x1000") != std::string::npos);
  CHECK(summary.find("1000 from other peers") != std::string::npos);
  CHECK(summary.find(k3) == std::string::npos);
  CHECK(summary.size() < 400);
  CHECK(log.flush(200.0).empty());  // nothing new
  // quiet for a period: the next one at once again; one without a key says so
  CHECK(log.refused("10.0.0.9", "", "malformed ZAP request", 200.0).find("10.0.0.9, no client key") !=
        std::string::npos);
  // counted ones are told at once when forced (the handler stopping)
  CHECK(log.refused("10.0.0.9", k3, "not on the allow-list", 201.0).empty());
  CHECK(log.flush(201.0, true).find("refused 1 more connection in") != std::string::npos);
}

TEST_CASE("a session slot's haptics parameters start as HapticsSettings' defaults", "[net]") {
  const HapticsSettings p = runtime::SessionSlot{}.params(), d;
  CHECK(p.stiffness_n_per_mm == d.stiffness_n_per_mm);
  CHECK(p.friction == d.friction);
  CHECK(p.max_force_n == d.max_force_n);
  CHECK(p.max_force_rate_n_per_s == d.max_force_rate_n_per_s);
  CHECK(p.min_gradient_norm == d.min_gradient_norm);
}

TEST_CASE("a session's key check: any sender without CURVE, only the opener's key with it", "[net][security]") {
  runtime::SessionSlot slot;
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
