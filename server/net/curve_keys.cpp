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

// what palpsim-keys writes in front of a key's kind in its comment
constexpr const char* kCommentPrefix = "# palpsim CURVE ";

// one key of a file: its line, and the kind palpsim-keys' comment above it gives (with
// the line of that comment)
struct KeyLine {
  int line = 0;
  std::string key;
  KeyKind kind = KeyKind::unknown;
  int kind_line = 0;
};

// the kind a comment line names, or unknown
KeyKind comment_kind(const std::string& line) {
  const auto b = line.find_first_not_of(" \t\r");
  if (b == std::string::npos || line.compare(b, std::strlen(kCommentPrefix), kCommentPrefix) != 0)
    return KeyKind::unknown;
  const std::string rest = line.substr(b + std::strlen(kCommentPrefix));
  if (rest.rfind("public key", 0) == 0) return KeyKind::public_key;
  if (rest.rfind("secret key", 0) == 0) return KeyKind::secret_key;
  return KeyKind::unknown;
}

// the key lines of a file, each with the kind palpsim-keys' comment right above it
// (blank lines between them allowed) gives
std::vector<KeyLine> key_lines(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(path + ": cannot read: " + std::strerror(errno));
  std::vector<KeyLine> out;
  std::string line;
  KeyKind marked = KeyKind::unknown;
  int marked_line = 0;
  for (int n = 1; std::getline(in, line); ++n) {
    if (const KeyKind k = comment_kind(line); k != KeyKind::unknown) {
      marked = k;
      marked_line = n;
    } else if (const std::string s = key_of(line); !s.empty()) {
      out.push_back({n, s, marked, marked_line});
      marked = KeyKind::unknown;
    }
  }
  return out;
}

bool ends_with(const std::string& s, const std::string& tail) {
  return s.size() >= tail.size() && s.compare(s.size() - tail.size(), tail.size(), tail) == 0;
}

// the kind a file's name gives: NAME.key_secret secret, NAME.key public
KeyKind name_kind(const std::string& path) {
  if (ends_with(path, ".key_secret")) return KeyKind::secret_key;
  if (ends_with(path, ".key")) return KeyKind::public_key;
  return KeyKind::unknown;
}

// the one key of a key file, its kind (the comment's, else the name's) and why that kind
KeyLine read_one_key(const std::string& path, std::string* why_kind) {
  const auto lines = key_lines(path);
  if (lines.empty()) throw Error(path + ": no key (expected one z85 key of 40 characters)");
  if (lines.size() > 1)
    throw Error(path + ":" + std::to_string(lines[1].line) + ": a second key; a key file holds one");
  KeyLine k = lines[0];
  const std::string why = check_z85_key(k.key);
  if (!why.empty()) throw Error(path + ":" + std::to_string(k.line) + ": not a key: " + why);
  if (k.kind != KeyKind::unknown) {
    *why_kind = "palpsim-keys marked it so on line " + std::to_string(k.kind_line);
  } else {
    k.kind = name_kind(path);
    *why_kind = k.kind == KeyKind::secret_key   ? "its name ends in .key_secret"
                : k.kind == KeyKind::public_key ? "its name ends in .key"
                                                : "";
  }
  return k;
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

std::string key_comment(KeyKind kind, const std::string& name) {
  if (kind == KeyKind::secret_key)
    return std::string(kCommentPrefix) + "secret key '" + name + "': keep it private (mode 0600)";
  return std::string(kCommentPrefix) + "public key '" + name + "'";
}

std::string read_key_file(const std::string& path) {
  std::string why;
  return read_one_key(path, &why).key;
}

std::string read_public_key_file(const std::string& path) {
  std::string why;
  const KeyLine k = read_one_key(path, &why);
  if (k.kind == KeyKind::secret_key)
    throw Error(path + ": a secret key (" + why + "), not a public key: give the public half, the NAME.key that " +
                "palpsim-keys wrote beside NAME.key_secret");
  return k.key;
}

CurveKeyPair read_secret_key_file(const std::string& path, const std::string& public_path) {
  std::string why;
  const KeyLine k = read_one_key(path, &why);
  if (k.kind == KeyKind::public_key)
    throw Error(path + ": a public key (" + why + "), not a secret key: give NAME.key_secret, the file " +
                "palpsim-keys wrote beside NAME.key (taken as a secret key it makes another key pair, which the " +
                "other side never answers)");
  CurveKeyPair p;
  p.secret_key = k.key;
  try {
    p.public_key = curve_public_of(p.secret_key);
  } catch (const Error& e) {
    throw Error(path + ": " + e.what());
  }
  // the public half given, or palpsim-keys' NAME.key beside NAME.key_secret, must match
  std::string pub_path = public_path;
  if (pub_path.empty() && ends_with(path, ".key_secret")) {
    const std::string beside = path.substr(0, path.size() - std::strlen("_secret"));
    if (::access(beside.c_str(), F_OK) == 0) pub_path = beside;
  }
  if (!pub_path.empty()) {
    const std::string pub = read_public_key_file(pub_path);
    if (pub != p.public_key)
      throw Error(path + " and " + pub_path + " are not a pair: the public half of " + path + " is " + p.public_key +
                  ", " + pub_path + " holds " + pub + " (one of them was replaced: make a new pair with " +
                  "palpsim-keys NAME --force and hand out the new NAME.key)");
  }
  return p;
}

std::vector<std::string> read_allow_list(const std::string& path) {
  if (name_kind(path) == KeyKind::secret_key)
    throw Error(path + ": a secret key file (its name ends in .key_secret), not an allow-list: an allow-list " +
                "holds the clients' public keys (cat alice.key bob.key > FILE)");
  std::vector<std::string> keys;
  for (const KeyLine& k : key_lines(path)) {
    const std::string where = path + ":" + std::to_string(k.line);
    const std::string why = check_z85_key(k.key);
    if (!why.empty()) throw Error(where + ": not a client public key: " + why);
    if (k.kind == KeyKind::secret_key)
      throw Error(where + ": a secret key (palpsim-keys marked it so on line " + std::to_string(k.kind_line) +
                  "), not a client public key: an allow-list holds the clients' NAME.key files, and this secret " +
                  "key is no longer private (make that client a new pair)");
    keys.push_back(k.key);
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
  write_file(sec, key_comment(KeyKind::secret_key, name) + "\n" + pair.secret_key + "\n", 0600, force);
  write_file(pub, key_comment(KeyKind::public_key, name) + "\n" + pair.public_key + "\n", 0644, force);
  return {pub, sec};
}

void make_curve_client(zmq::socket_t& s, const std::string& server_public, const CurveKeyPair& client) {
  s.set(zmq::sockopt::curve_serverkey, server_public);
  s.set(zmq::sockopt::curve_publickey, client.public_key);
  s.set(zmq::sockopt::curve_secretkey, client.secret_key);
}

}  // namespace palpsim::net
