// Where tests find ../shared/data (the real CT), and a way to skip with a reason.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

namespace palpsim::test {

/// The shared data folder: $PALPSIM_DATA, else ../shared/data beside the project;
/// "" when neither exists.
inline std::string shared_data_dir() {
  if (const char* env = std::getenv("PALPSIM_DATA"); env && *env && std::filesystem::is_directory(env)) return env;
  if (std::filesystem::is_directory(PALPSIM_SHARED_DATA)) return PALPSIM_SHARED_DATA;
  return "";
}

/// Full path of `rel` under the shared data folder, or "" (after printing why) when absent.
inline std::string shared_data_file(const std::string& rel) {
  const std::string dir = shared_data_dir();
  const std::string path = dir.empty() ? "" : dir + "/" + rel;
  if (dir.empty() || !std::filesystem::exists(path)) {
    std::printf("SKIPPED: %s not found (no ../shared/data beside the project and no PALPSIM_DATA)\n", rel.c_str());
    return "";
  }
  return path;
}

}  // namespace palpsim::test
