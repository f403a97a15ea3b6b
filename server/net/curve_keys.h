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

/// Reads a key file: blank lines, comments ('#' then a blank, at a line's start or after
/// the key: z85 itself uses '#') and exactly one z85 key.
/// Throws palpsim::Error naming the file (and line) and what is wrong.
std::string read_key_file(const std::string& path);

/// Reads a secret key file (NAME.key_secret) into a pair, its public half derived from
/// the secret; throws palpsim::Error naming the file.
CurveKeyPair read_secret_key_file(const std::string& path);

/// Reads an allow-list: one z85 public key per line, comments and blank lines as in a
/// key file, so `cat a.key b.key > allowed` makes one.
/// Throws palpsim::Error naming the file and line of the first bad entry, or an empty list.
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
