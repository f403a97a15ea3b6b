// palpsim-keys: makes ZeroMQ CURVE key pairs for palpsim-server (--curve-secret) and its
// clients (--client-key), and lists the public key of a secret key file.
#include <cstdio>
#include <string>

#include "core/error.h"
#include "net/curve_keys.h"

namespace {

const char* kUsage =
    "usage: palpsim-keys NAME [--dir DIR] [--force]\n"
    "       palpsim-keys --public FILE.key_secret\n"
    "  NAME          writes DIR/NAME.key (the z85 public key: give it to the other side) and\n"
    "                DIR/NAME.key_secret (the z85 secret key, mode 0600: keep it where it is)\n"
    "  --dir DIR     folder for the two files (default: the current folder)\n"
    "  --force       replace existing files of that name (default: refuse)\n"
    "  --public FILE print the public key of a secret key file\n"
    "A server's allow-list (palpsim-server --allow) is its clients' .key files put together:\n"
    "  cat alice.key bob.key > allowed_clients\n";

}  // namespace

int main(int argc, char** argv) {
  // command line
  std::string name, dir, public_of;
  bool force = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--help" || a == "-h") {
      std::fputs(kUsage, stdout);
      return 0;
    } else if (a == "--force") {
      force = true;
    } else if ((a == "--dir" || a == "--public") && i + 1 < argc) {
      (a == "--dir" ? dir : public_of) = argv[++i];
    } else if (!a.empty() && a[0] != '-' && name.empty()) {
      name = a;
    } else {
      std::fprintf(stderr, "palpsim-keys: unexpected argument '%s'\n%s", a.c_str(), kUsage);
      return 2;
    }
  }
  if (name.empty() == public_of.empty()) {
    std::fprintf(stderr, "palpsim-keys: give a NAME or --public FILE\n%s", kUsage);
    return 2;
  }
  if (name.find('/') != std::string::npos) {
    std::fprintf(stderr, "palpsim-keys: NAME '%s' holds a '/': name the folder with --dir\n", name.c_str());
    return 2;
  }

  // the work: print a public key, or make and write a pair
  try {
    if (!public_of.empty()) {
      std::printf("%s\n", palpsim::net::read_secret_key_file(public_of).public_key.c_str());
      return 0;
    }
    const auto pair = palpsim::net::make_curve_keypair();
    for (const std::string& p : palpsim::net::write_key_pair(pair, dir, name, force))
      std::printf("palpsim-keys: wrote %s\n", p.c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-keys: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
