// palpsim-haptic's command line: the options read and their ranges checked.
#include "options.h"

#include <cstdio>
#include <cstdlib>
#include <exception>

namespace palpsim::haptic {

namespace {

const char* kUsage =
    "usage: palpsim-haptic --connect ADDR [--device press|press:X,Y,Z[,TRAVEL]|csv:FILE|replay:FILE] [--rate HZ]\n"
    "                      [--seconds S] [--log FILE] [--name NAME] [--server-key FILE --client-key FILE]\n"
    "                      [--client-token TEXT] [--mode auto|local|remote] [--patch-edge N] [--patch-period S]\n"
    "                      [--pose-via ADDR] [--warmup S] [--priority N]\n"
    "  --connect ADDR  the server's control address (its 'ready on ADDR' line)\n"
    "  --device SPEC   the built-in press path (default; from X,Y,Z, TRAVEL mm along -y, 40 unless given), a CSV of t,x,y,z (s, mm), or a palpsim-haptic log to replay\n"
    "  --rate HZ       loop rate, 100 to 4000 (default 1000)\n"
    "  --seconds S     stop S seconds after the device's path starts (default: when it ends)\n"
    "  --log FILE      CSV of every step (time, pose, force, round trip)\n"
    "  --server-key FILE  the server's public key (its NAME.key from palpsim-keys): speak CURVE\n"
    "  --client-key FILE  this client's secret key (NAME.key_secret), whose public key the server allows\n"
    "  --client-token TEXT without CURVE: the session belongs to this token (palpsim-view --client-token\n"
    "                  TEXT may then watch it); else to this client's control connection alone\n"
    "  --mode M        auto (default: local when the round trip is over 8 ms, remote under 4 ms), local or remote\n"
    "  --patch-edge N  voxels per axis of the patches of F asked for in local mode, 4..16 (default 12)\n"
    "  --patch-period S  at most one patch per S seconds, 0.01..1 (default 0.05)\n"
    "  --pose-via ADDR send poses to ADDR instead of the server's pose endpoint (a tunnel or relay to it)\n"
    "  --warmup S      hold the device's path at its start until the link is up (the first reply; far:\n"
    "                  local mode), at most S seconds (0..10, default 0); the comparison starts with the path\n"
    "  --priority N    the loop and its network thread under SCHED_FIFO at priority N (1..99, default 10)\n"
    "                  where allowed (root or CAP_SYS_NICE), so that other programs cannot delay it; 0: the\n"
    "                  normal policy\n";

// checks the settings' ranges and pairs; false, with one line on stderr, for the first one
// that is wrong
bool check_options(const Options& o) {
  if (o.addr.empty()) {
    std::fprintf(stderr, "palpsim-haptic: --connect ADDR is required\n%s", kUsage);
    return false;
  }
  if (o.server_key_file.empty() != o.client_key_file.empty()) {
    std::fprintf(stderr, "palpsim-haptic: --server-key and --client-key go together (CURVE needs both)\n");
    return false;
  }
  if (!(o.rate_hz >= 100 && o.rate_hz <= 4000)) {
    std::fprintf(stderr, "palpsim-haptic: --rate %g: must be within 100..4000 Hz\n", o.rate_hz);
    return false;
  }
  if (o.mode_name != "auto" && o.mode_name != "local" && o.mode_name != "remote") {
    std::fprintf(stderr, "palpsim-haptic: --mode %s: expected auto, local or remote\n", o.mode_name.c_str());
    return false;
  }
  if (o.patch_edge < 4 || o.patch_edge > kMaxPatchEdge) {
    std::fprintf(stderr, "palpsim-haptic: --patch-edge %d: must be within 4..16 voxels\n", o.patch_edge);
    return false;
  }
  if (!(o.patch_period_s >= 0.01 && o.patch_period_s <= 1)) {
    std::fprintf(stderr, "palpsim-haptic: --patch-period %g: must be within 0.01..1 s\n", o.patch_period_s);
    return false;
  }
  if (!(o.warmup_s >= 0 && o.warmup_s <= 10)) {
    std::fprintf(stderr, "palpsim-haptic: --warmup %g: must be within 0..10 s\n", o.warmup_s);
    return false;
  }
  if (o.priority < 0 || o.priority > 99) {
    std::fprintf(stderr, "palpsim-haptic: --priority %d: must be within 0..99 (0: the normal policy)\n", o.priority);
    return false;
  }
  if (!(o.max_seconds >= 0)) {
    std::fprintf(stderr, "palpsim-haptic: --seconds %g: must be >= 0\n", o.max_seconds);
    return false;
  }
  return true;
}

}  // namespace

int parse_options(int argc, char** argv, Options& o) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "palpsim-haptic: %s needs a value\n%s", a.c_str(), kUsage);
        std::exit(2);
      }
      return argv[++i];
    };
    try {
      if (a == "--help" || a == "-h") {
        std::fputs(kUsage, stdout);
        return 0;
      } else if (a == "--connect") o.addr = value();
      else if (a == "--device") o.device_spec = value();
      else if (a == "--rate") o.rate_hz = std::stod(value());
      else if (a == "--seconds") o.max_seconds = std::stod(value());
      else if (a == "--log") o.log_path = value();
      else if (a == "--name") o.name = value();
      else if (a == "--server-key") o.server_key_file = value();
      else if (a == "--client-key") o.client_key_file = value();
      else if (a == "--client-token") o.client_token = value();
      else if (a == "--mode") o.mode_name = value();
      else if (a == "--patch-edge") o.patch_edge = std::stoi(value());
      else if (a == "--patch-period") o.patch_period_s = std::stod(value());
      else if (a == "--pose-via") o.pose_via = value();
      else if (a == "--warmup") o.warmup_s = std::stod(value());
      else if (a == "--priority") o.priority = std::stoi(value());
      else {
        std::fprintf(stderr, "palpsim-haptic: unknown argument '%s'\n%s", a.c_str(), kUsage);
        return 2;
      }
    } catch (const std::exception&) {
      std::fprintf(stderr, "palpsim-haptic: %s: '%s' is not a number\n", a.c_str(), argv[i]);
      return 2;
    }
  }
  return check_options(o) ? -1 : 2;
}

}  // namespace palpsim::haptic
