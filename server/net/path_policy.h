// Which folders a network request may make the server read or write: LoadScene's scene
// file, the CT its scene names and its render.record_dir. The operator names them
// (palpsim-server --scene-dir); a client can never reach a file outside them.
#pragma once

#include <string>
#include <vector>

namespace palpsim::net {

/// The folders network requests may touch, resolved once (symbolic links and ".."
/// followed), so that a path is judged by where it really leads.
class PathPolicy {
 public:
  /// No folder: a request may name no file at all.
  PathPolicy() = default;
  /// These folders; throws palpsim::Error naming one that does not exist or is not a folder.
  explicit PathPolicy(const std::vector<std::string>& dirs);

  /// "" when `path` (resolved, existing or not) lies inside one of the folders; else a
  /// sentence naming `what`, the path and the folders allowed.
  std::string check(const std::string& path, const std::string& what) const;

 private:
  std::vector<std::string> dirs_;
};

}  // namespace palpsim::net
