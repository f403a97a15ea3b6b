#include "net/curve_keys.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zmq.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <sstream>

#include "core/error.h"

namespace palpsim::net {
namespace {

// the z85 alphabet (ZeroMQ RFC 32)
constexpr const char* kZ85Chars =
    "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#";

// the key of a line, "" for a blank or comment line, or the line itself when it is
// neither (the caller says why). z85 uses '#', so a comment is '#' followed by a blank
// or the line's end, at its start or after the key (a key holds no blanks).
std::string key_of(const std::string& line) {
  const auto b = line.find_first_not_of(" \t\r");
  if (b == std::string::npos) return "";
  const auto e = line.find_first_of(" \t\r", b);
  const std::string first = line.substr(b, e == std::string::npos ? std::string::npos : e - b);
  if (first == "#") return "";
  if (e == std::string::npos) return first;
  const auto rest = line.find_first_not_of(" \t\r", e);
  if (rest == std::string::npos || (line[rest] == '#' && (rest + 1 == line.size() || std::strchr(" \t\r", line[rest + 1]))))
    return first;
  return line.substr(b);
}

// the key lines of a file with their line numbers
std::vector<std::pair<int, std::string>> key_lines(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(path + ": cannot read: " + std::strerror(errno));
  std::vector<std::pair<int, std::string>> out;
  std::string line;
  for (int n = 1; std::getline(in, line); ++n)
    if (const std::string s = key_of(line); !s.empty()) out.emplace_back(n, s);
  return out;
}

// writes `text` to a new file of mode `mode`; O_EXCL unless `force` (then replaced)
void write_file(const std::string& path, const std::string& text, mode_t mode, bool force) {
  if (force) ::unlink(path.c_str());
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL, mode);
  if (fd < 0) {
    if (errno == EEXIST) throw Error(path + ": exists; palpsim-keys replaces key files only with --force");
    throw Error(path + ": cannot create: " + std::strerror(errno));
  }
  // the umask may have narrowed the mode; set it exactly (never wider than asked)
  const bool ok = ::fchmod(fd, mode) == 0 && ::write(fd, text.data(), text.size()) == ssize_t(text.size());
  const int err = errno;
  ::close(fd);
  if (!ok) throw Error(path + ": cannot write: " + std::strerror(err));
}

}  // namespace

bool curve_available() { return zmq_has("curve") != 0; }

std::string check_z85_key(const std::string& key) {
  if (key.size() != kZ85KeyLength)
    return std::to_string(key.size()) + " characters, a z85 CURVE key has " + std::to_string(kZ85KeyLength);
  for (char c : key)
    if (c == 0 || !std::strchr(kZ85Chars, c)) return std::string("character '") + c + "' is not z85";
  return "";
}

CurveKeyPair make_curve_keypair() {
  char pub[kZ85KeyLength + 1], sec[kZ85KeyLength + 1];
  if (!curve_available() || zmq_curve_keypair(pub, sec) != 0)
    throw Error("this libzmq has no CURVE (zmq_has(\"curve\") is false): rebuild it with libsodium");
  return {pub, sec};
}

std::string curve_public_of(const std::string& secret_z85) {
  const std::string why = check_z85_key(secret_z85);
  if (!why.empty()) throw Error("secret key: " + why);
  char pub[kZ85KeyLength + 1];
  if (zmq_curve_public(pub, secret_z85.c_str()) != 0)
    throw Error("secret key: zmq_curve_public failed: " + std::string(zmq_strerror(zmq_errno())));
  return pub;
}

std::string read_key_file(const std::string& path) {
  const auto lines = key_lines(path);
  if (lines.empty()) throw Error(path + ": no key (expected one z85 key of 40 characters)");
  if (lines.size() > 1)
    throw Error(path + ":" + std::to_string(lines[1].first) + ": a second key; a key file holds one");
  const std::string why = check_z85_key(lines[0].second);
  if (!why.empty()) throw Error(path + ":" + std::to_string(lines[0].first) + ": not a key: " + why);
  return lines[0].second;
}

CurveKeyPair read_secret_key_file(const std::string& path) {
  CurveKeyPair p;
  p.secret_key = read_key_file(path);
  try {
    p.public_key = curve_public_of(p.secret_key);
  } catch (const Error& e) {
    throw Error(path + ": " + e.what());
  }
  return p;
}

std::vector<std::string> read_allow_list(const std::string& path) {
  std::vector<std::string> keys;
  for (const auto& [n, s] : key_lines(path)) {
    const std::string why = check_z85_key(s);
    if (!why.empty()) throw Error(path + ":" + std::to_string(n) + ": not a client public key: " + why);
    keys.push_back(s);
  }
  if (keys.empty()) throw Error(path + ": no keys (one z85 client public key per line); no client could connect");
  return keys;
}

std::vector<std::string> write_key_pair(const CurveKeyPair& pair, const std::string& dir, const std::string& name,
                                        bool force) {
  const std::string base = (dir.empty() ? std::string(".") : dir) + "/" + name;
  const std::string pub = base + ".key", sec = base + ".key_secret";
  // both refused before either is written, so a refusal leaves no half pair
  if (!force)
    for (const std::string& p : {pub, sec})
      if (::access(p.c_str(), F_OK) == 0)
        throw Error(p + ": exists; palpsim-keys replaces key files only with --force");
  write_file(sec, "# palpsim CURVE secret key '" + name + "': keep it private (mode 0600)\n" + pair.secret_key + "\n",
             0600, force);
  write_file(pub, "# palpsim CURVE public key '" + name + "'\n" + pair.public_key + "\n", 0644, force);
  return {pub, sec};
}

void make_curve_client(zmq::socket_t& s, const std::string& server_public, const CurveKeyPair& client) {
  s.set(zmq::sockopt::curve_serverkey, server_public);
  s.set(zmq::sockopt::curve_publickey, client.public_key);
  s.set(zmq::sockopt::curve_secretkey, client.secret_key);
}

}  // namespace palpsim::net
