// ZeroMQ CURVE key files (palpsim-keys writes them; the server and the clients read
// them): NAME.key holds a z85 public key, NAME.key_secret the matching z85 secret key
// (mode 0600), and an allow-list holds the public keys of the clients a server admits.
// ZeroMQ only: the thin haptic client links this module without the server's libraries.
#pragma once

#include <string>
#include <vector>
#include <zmq.hpp>

namespace palpsim::net {

/// Characters of a z85-encoded CURVE key (32 bytes).
constexpr std::size_t kZ85KeyLength = 40;

/// A key pair, both halves z85.
struct CurveKeyPair {
  std::string public_key;
  std::string secret_key;
};

/// True when this libzmq was built with CURVE (zmq_has("curve")).
bool curve_available();

/// "" when `key` is a z85 CURVE key (40 characters of the z85 alphabet), else why not.
std::string check_z85_key(const std::string& key);

/// A fresh key pair (zmq_curve_keypair); throws palpsim::Error without CURVE.
CurveKeyPair make_curve_keypair();

/// The public key of a z85 secret key (zmq_curve_public); throws palpsim::Error for a bad key.
std::string curve_public_of(const std::string& secret_z85);

/// Which half of a pair a key is. Nothing in a z85 key tells: any 32 bytes are a secret
/// key whose public half is another 32 bytes. So it is told by the comment palpsim-keys
/// writes above each key ("# palpsim CURVE public key 'NAME'" or "... secret key ..."),
/// else by the file's name (NAME.key public, NAME.key_secret secret), else not at all.
enum class KeyKind { unknown, public_key, secret_key };

/// The comment palpsim-keys writes above a key of `kind` made for `name` (one line, no newline).
std::string key_comment(KeyKind kind, const std::string& name);

/// Reads a key file: blank lines, comments ('#' then a blank, at a line's start or after
/// the key: z85 itself uses '#') and exactly one z85 key, of either half.
/// Throws palpsim::Error naming the file (and line) and what is wrong.
std::string read_key_file(const std::string& path);

/// Reads a public key file (the server's NAME.key, for a client's --server-key): as
/// read_key_file, and refuses a key marked or named secret, naming the file.
std::string read_public_key_file(const std::string& path);

/// Reads a secret key file (NAME.key_secret) into a pair, its public half derived from
/// the secret. Refuses a key marked or named public (a client's --client-key or the
/// server's --curve-secret given NAME.key runs with another key, and is met with
/// silence), and a pair that does not match: the public key file `public_path`, or
/// without one NAME.key beside NAME.key_secret when there is one, must hold the public
/// half of this secret. Throws palpsim::Error naming the file(s).
CurveKeyPair read_secret_key_file(const std::string& path, const std::string& public_path = "");

/// Reads an allow-list: one z85 public key per line, comments and blank lines as in a
/// key file, so `cat a.key b.key > allowed` makes one. Refuses a file named
/// NAME.key_secret and a key marked secret (a secret key on a list is no longer secret,
/// and no client presents it). Throws palpsim::Error naming the file and line of the
/// first bad entry, or an empty list.
std::vector<std::string> read_allow_list(const std::string& path);

/// Writes DIR/NAME.key (public, mode 0644) and DIR/NAME.key_secret (secret, mode 0600,
/// created with that mode, never readable by others in between). Refuses to replace
/// either file unless `force`; throws palpsim::Error naming the file. Returns the paths.
std::vector<std::string> write_key_pair(const CurveKeyPair& pair, const std::string& dir, const std::string& name,
                                        bool force);

/// Makes `socket` a CURVE client of the server whose z85 public key is `server_public`,
/// speaking as `client`; before connect.
void make_curve_client(zmq::socket_t& socket, const std::string& server_public, const CurveKeyPair& client);

/// What a client adds when a server does not answer, by whether the client speaks CURVE:
/// the likely causes, since a refused handshake is silent on the client's side.
constexpr const char* kCurveSilenceHint =
    " (with CURVE a server also stays silent when --server-key is not its public key, when this client's key is "
    "not on its allow-list, or when it runs without keys)";
constexpr const char* kPlainSilenceHint =
    " (a server with keys also stays silent to a client without them: give --server-key and --client-key)";

}  // namespace palpsim::net
