// palpsim-haptic's command line: its settings, read and checked.
#pragma once

#include <string>

namespace palpsim::haptic {

/// The largest patch the client asks for, in voxels per axis (PoseRequest.local_model_edge's
/// range is 4..16).
constexpr int kMaxPatchEdge = 16;

/// palpsim-haptic's settings from its command line (its --help says what each one means).
struct Options {
  std::string addr, device_spec = "press", log_path, name = "palpsim-haptic", server_key_file, client_key_file,
              client_token, mode_name = "auto", pose_via;
  double rate_hz = 1000, max_seconds = 0, patch_period_s = 0.05, warmup_s = 0;
  int patch_edge = 12, priority = 10;
};

/// Reads the command line into `o` and checks every setting's range: the exit code when the
/// program ends here (--help: 0 with the usage on stdout; a bad option: 2 with one line on
/// stderr naming it), else -1.
int parse_options(int argc, char** argv, Options& o);

}  // namespace palpsim::haptic
