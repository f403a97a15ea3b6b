// palpsim-server: loads a scene, prepares its patient and serves haptics sessions
// (proto/PROTOCOL.md) until SIGINT or SIGTERM: on loopback in plain text, or anywhere with
// CURVE keys (--curve-secret, --allow) or --insecure.
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <pthread.h>
#include <cstdlib>
#include <string>
#include <utility>

#include "core/error.h"
#include "core/linked_backends.h"
#include "core/path_policy.h"
#include "net/curve_keys.h"
#include "runtime/heap_trimmer.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "prep/prepare.h"

namespace {

const char* kUsage =
    "usage: palpsim-server [--scene FILE] [--bind ADDR] [--pose-bind ADDR] [--stream-bind ADDR]\n"
    "                      [--max-pose-distance-mm MM] [--pose-priority N] [--background idle|nice]\n"
    "                      [--deform-concurrency K]\n"
    "                      [--deform-batch N] [--max-sessions-per-client N] [--idle-timeout-s S]\n"
    "                      [--scene-dir DIR ...] [--cache-dir DIR]\n"
    "                      [--curve-secret FILE [--curve-public FILE] --allow FILE] [--insecure]\n"
    "                      [--log-level trace|debug|info|warn|error]\n"
    "  --scene FILE       scene (config/scenes/*.textproto); default: the built-in phantom scene\n"
    "  --bind ADDR        control address (default tcp://127.0.0.1:7420; tcp://127.0.0.1:* picks a free port)\n"
    "  --pose-bind ADDR   pose address (default: the control port + 1; * stays *)\n"
    "  --stream-bind ADDR frames and bricks (XPUB) address, for scenes that ask for them\n"
    "                     (default: the control port + 2; * stays *)\n"
    "  --pose-priority N  the pose thread and the pose socket's I/O thread under SCHED_FIFO at priority\n"
    "                     N (default 10; 0: the normal policy), where the process may (root or\n"
    "                     CAP_SYS_NICE; else the normal policy, and the log says so)\n"
    "  --background P     the deformation and render threads: idle (default: SCHED_IDLE and nice 19,\n"
    "                     any pose thread takes a core at once) or nice (nice 19 only)\n"
    "  --deform-concurrency K  sessions' deformation steps on the GPU at once, each with 1/K of it\n"
    "                     (default 1: one at a time; 4 doubles the steps of 16 sessions but costs\n"
    "                     watched sessions frames: for servers without viewers)\n"
    "  --deform-batch N   sessions whose steps share one launch per stage, at most (default 64;\n"
    "                     1: each session steps alone, with --deform-concurrency)\n"
    "  --max-sessions-per-client N  sessions one client (CURVE key, else client token, else control\n"
    "                     connection) may hold open at once (default 16; 1..4096)\n"
    "  --idle-timeout-s S a session without a pose or a control request acting on it (Stats does not\n"
    "                     count) for S seconds is freed (default 60; 0: never)\n"
    "  --scene-dir DIR    a folder LoadScene requests may read scene files and CTs from and record\n"
    "                     frames into (repeatable; default: the folder of --scene, none without it);\n"
    "                     only regular files inside it, links resolved, and the data files their\n"
    "                     headers name and DICOM folders' files likewise\n"
    "  --cache-dir DIR    the folder of prepared patients, for --scene and LoadScene's scenes (default:\n"
    "                     --scene's prep.cache_dir, else $PALPSIM_CACHE, else ~/.cache/palpsim); a\n"
    "                     client's scene that sets prep.cache_dir is refused\n"
    "  --curve-secret FILE the server's secret key (palpsim-keys NAME makes NAME.key_secret): every\n"
    "                     endpoint is CURVE-encrypted, and addresses beyond loopback are allowed;\n"
    "                     a public key file here is refused, and so is a secret key that NAME.key\n"
    "                     beside it does not match\n"
    "  --curve-public FILE the server's public key file the clients were given (default: NAME.key\n"
    "                     beside NAME.key_secret, when there is one): refused unless it matches\n"
    "  --allow FILE       the client public keys admitted with --curve-secret, one z85 key per line\n"
    "                     ('# ' comments; cat alice.key bob.key > FILE makes one); a secret key\n"
    "                     in it is refused\n"
    "                     Refused handshakes are logged with the peer's address and key, a line\n"
    "                     at first and then one summary per 5 s at most\n"
    "  --insecure         allow addresses beyond loopback without keys: poses, frames and control\n"
    "                     travel in plain text, unauthenticated (a trusted network only)\n"
    "Prints 'ready on ADDR poses ADDR [stream ADDR]' when serving; stops cleanly on SIGINT or SIGTERM.\n";

int fail(const std::string& what) {
  std::fprintf(stderr, "palpsim-server: error: %s\n", what.c_str());
  return 1;
}

// what the command line asks for
struct CommandLine {
  std::string scene_file, curve_secret_file, curve_public_file, allow_file, cache_dir;
  palpsim::net::ServerOptions options;
};

// reads the command line into `cl`; -1 to go on, else the exit status (0: --help; 2: a bad
// option, said with the usage)
int parse_command_line(int argc, char** argv, CommandLine& cl) {
  palpsim::net::ServerOptions& options = cl.options;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&](const char* name) -> std::string {
      if (i + 1 >= argc) throw palpsim::Error(std::string(name) + " needs a value");
      return argv[++i];
    };
    // the value of option `name`: a whole number from 1 to `most`
    auto whole = [&](const char* name, long most) -> int {
      const std::string v = value(name);
      char* end = nullptr;
      const long k = std::strtol(v.c_str(), &end, 10);
      if (end == v.c_str() || *end != '\0' || k < 1 || k > most)
        throw palpsim::Error(std::string(name) + " " + v + ": expected a whole number from 1 to " + std::to_string(most));
      return int(k);
    };
    try {
      if (a == "--help" || a == "-h") {
        std::fputs(kUsage, stdout);
        return 0;
      } else if (a == "--scene") {
        cl.scene_file = value("--scene");
      } else if (a == "--curve-secret") {
        cl.curve_secret_file = value("--curve-secret");
      } else if (a == "--curve-public") {
        cl.curve_public_file = value("--curve-public");
      } else if (a == "--allow") {
        cl.allow_file = value("--allow");
      } else if (a == "--insecure") {
        options.insecure = true;
      } else if (a == "--scene-dir") {
        options.scene_dirs.push_back(value("--scene-dir"));
      } else if (a == "--cache-dir") {
        cl.cache_dir = value("--cache-dir");
      } else if (a == "--bind") {
        options.control_bind = value("--bind");
      } else if (a == "--pose-bind") {
        options.pose_bind = value("--pose-bind");
      } else if (a == "--stream-bind") {
        options.stream_bind = value("--stream-bind");
      } else if (a == "--pose-priority") {
        const std::string v = value("--pose-priority");
        char* end = nullptr;
        const long k = std::strtol(v.c_str(), &end, 10);
        if (end == v.c_str() || *end != '\0' || k < 0 || k > 99)
          throw palpsim::Error("--pose-priority " + v + ": expected a whole number from 0 (the normal policy) to 99");
        options.pose_priority = int(k);
      } else if (a == "--background") {
        const std::string p = value("--background");
        if (p != "idle" && p != "nice") throw palpsim::Error("--background " + p + ": expected idle or nice");
        options.background_idle = p == "idle";
      } else if (a == "--deform-concurrency") {
        options.deform_concurrency = whole("--deform-concurrency", 64);
      } else if (a == "--deform-batch") {
        options.deform_batch = whole("--deform-batch", 64);
      } else if (a == "--max-sessions-per-client") {
        options.max_sessions_per_client = whole("--max-sessions-per-client", 4096);
      } else if (a == "--idle-timeout-s") {
        const std::string v = value("--idle-timeout-s");
        char* end = nullptr;
        const double t = std::strtod(v.c_str(), &end);
        if (end == v.c_str() || *end != '\0' || !(t >= 0 && t <= 1e6))
          throw palpsim::Error("--idle-timeout-s " + v + ": expected seconds from 0 (never) to 1e6");
        options.idle_timeout_s = t;
      } else if (a == "--max-pose-distance-mm") {
        options.max_pose_distance_mm = std::stod(value("--max-pose-distance-mm"));
      } else if (a == "--log-level") {
        spdlog::set_level(spdlog::level::from_str(value("--log-level")));
      } else {
        std::fprintf(stderr, "palpsim-server: unknown argument '%s'\n%s", a.c_str(), kUsage);
        return 2;
      }
    } catch (const std::exception& e) {
      std::fprintf(stderr, "palpsim-server: %s\n%s", e.what(), kUsage);
      return 2;
    }
  }
  return -1;
}

// refuses folders that do not exist and bad key files (throws palpsim::Error saying which),
// and takes the CURVE keys into the options
void check_files_and_keys(CommandLine& cl) {
  palpsim::net::ServerOptions& options = cl.options;
  const std::string &curve_secret_file = cl.curve_secret_file, &curve_public_file = cl.curve_public_file,
                    &allow_file = cl.allow_file;
  palpsim::PathPolicy check(options.scene_dirs);
  if (curve_secret_file.empty() != allow_file.empty())
    throw palpsim::Error(curve_secret_file.empty() ? "--allow needs --curve-secret (the server's secret key)"
                                                   : "--curve-secret needs --allow (the client keys admitted)");
  if (!curve_public_file.empty() && curve_secret_file.empty())
    throw palpsim::Error("--curve-public needs --curve-secret (the public key is checked against it)");
  if (!curve_secret_file.empty()) {
    if (!palpsim::net::curve_available())
      throw palpsim::Error("--curve-secret: this libzmq has no CURVE (zmq_has(\"curve\") is false)");
    const auto pair = palpsim::net::read_secret_key_file(curve_secret_file, curve_public_file);
    options.curve_secret_key = pair.secret_key;
    options.curve_allowed_keys = palpsim::net::read_allow_list(allow_file);
    // the server's own secret key on its list: it is no longer secret
    for (const std::string& k : options.curve_allowed_keys)
      if (k == pair.secret_key)
        throw palpsim::Error(allow_file + ": holds the server's own secret key (" + curve_secret_file +
                             "); an allow-list holds the clients' public keys, and this secret key is no longer " +
                             "private: make the server a new pair");
    spdlog::info("CURVE on every endpoint: server public key {}, {} client key(s) allowed from {}", pair.public_key,
                 options.curve_allowed_keys.size(), allow_file);
  }
}

}  // namespace

int main(int argc, char** argv) {
  // big blocks go back to the system when freed (runtime/heap_trimmer.h says why)
  palpsim::runtime::configure_heap();
  // cuda's deformation backend, nvJPEG encoder and overlay writer, in a CUDA build
  palpsim::register_linked_backends();

  // SIGINT and SIGTERM are taken by sigwait below; every thread started later inherits the mask
  sigset_t stop_signals;
  sigemptyset(&stop_signals);
  sigaddset(&stop_signals, SIGINT);
  sigaddset(&stop_signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &stop_signals, nullptr);

  // log lines go to stderr; stdout carries only the 'ready on' and 'stopped' lines for scripts
  spdlog::set_default_logger(spdlog::stderr_color_mt("palpsim-server"));

  // command line
  CommandLine cl;
  if (const int status = parse_command_line(argc, argv, cl); status >= 0) return status;
  palpsim::net::ServerOptions& options = cl.options;
  const std::string& scene_file = cl.scene_file;
  std::string& cache_dir = cl.cache_dir;

  // folders that do not exist and bad key files are refused before the patient is prepared
  try {
    check_files_and_keys(cl);
  } catch (const std::exception& e) {
    return fail(std::string("cannot start: ") + e.what());
  }

  // scene and patient: refuse to start on any error, naming it
  palpsim::Scene scene;
  palpsim::PatientPtr patient;
  try {
    scene = scene_file.empty() ? palpsim::default_scene() : palpsim::load_scene_file(scene_file);
    if (!cache_dir.empty()) scene.prep.cache_dir = cache_dir;
    spdlog::info("scene {}", palpsim::scene_label(scene));
    palpsim::PrepReport report;
    patient = palpsim::prepare_patient(scene, &report);
    spdlog::info("patient {}: {}x{}x{} voxels at {} mm ({} in {:.2f} s)", patient->source, patient->grid.size.x,
                 patient->grid.size.y, patient->grid.size.z, patient->grid.spacing_mm.x,
                 report.from_cache ? "from cache" : "prepared", report.total_s);
  } catch (const std::exception& e) {
    return fail(std::string("cannot start: ") + e.what());
  }
  // deformation, frames and bricks are built by the server (and logged) when the scene asks for them

  // LoadScene's files: the folder of the starting scene unless the operator names folders
  if (options.scene_dirs.empty() && !scene_file.empty())
    options.scene_dirs.push_back(std::filesystem::absolute(scene_file).parent_path().string());
  // and its cache: the operator's (the server refuses a client's scene that names one)
  if (cache_dir.empty()) cache_dir = scene.prep.cache_dir;

  // serve
  try {
    // LoadScene's patients: every CT file through the folders' resolver, the operator's cache;
    // the server holds the only reference to the starting patient, so a LoadScene frees it
    auto loader = [files = palpsim::PathPolicy(options.scene_dirs), cache_dir](const palpsim::Scene& s) {
      palpsim::Scene operators = s;
      operators.prep.cache_dir = cache_dir;
      return palpsim::prepare_patient(operators, nullptr, &files);
    };
    palpsim::net::Server server(scene, std::move(patient), loader, options);
    server.start();
    const std::string stream = server.stream_endpoint();
    std::printf("palpsim-server: ready on %s poses %s%s%s (scene %s)\n", server.control_endpoint().c_str(),
                server.pose_endpoint().c_str(), stream.empty() ? "" : " stream ", stream.c_str(),
                palpsim::scene_label(scene).c_str());
    std::fflush(stdout);
    int sig = 0;
    sigwait(&stop_signals, &sig);
    spdlog::info("stopping on {}", sig == SIGINT ? "SIGINT" : "SIGTERM");
    server.stop();
  } catch (const std::exception& e) {
    return fail(e.what());
  }
  std::printf("palpsim-server: stopped\n");
  return 0;
}
