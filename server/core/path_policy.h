// The one resolver for every file opened on someone else's behalf: LoadScene's scene file,
// the CT its scene names, the data files a CT header names, the files of a DICOM folder and
// render.record_dir. The operator names the folders (palpsim-server --scene-dir; for
// palpsim-prep, the CT's own folder); a path is judged after its links are resolved, and a
// file is opened without blocking and read only when it is a regular file.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace palpsim {

/// What a resolved path must be.
enum class PathKind {
  kFile,          // a regular file (not a folder, FIFO, socket or device)
  kFolder,        // a folder
  kFileOrFolder,  // either (a CT: an image file or a DICOM folder)
};

/// The folders files may be opened in, resolved once (symbolic links and ".." followed),
/// so that a path is judged by where it really leads.
class PathPolicy {
 public:
  /// No folder: no path is allowed.
  PathPolicy() = default;
  /// These folders; `label` names them in messages ("the folders this server allows").
  /// Throws palpsim::Error naming `option` and a folder that does not exist or is not one.
  explicit PathPolicy(const std::vector<std::string>& dirs, const std::string& option = "--scene-dir",
                      const std::string& label = "the folders this server allows");

  /// The folders, resolved.
  const std::vector<std::string>& dirs() const { return dirs_; }

  /// "" when `path` (resolved as far as it exists; it need not exist) lies inside one of
  /// the folders; else a sentence naming `what`, the path and the folders allowed. An
  /// empty path or one holding a NUL character is refused too.
  std::string check(const std::string& path, const std::string& what) const;

  /// The resolved path of `path`, which must exist, be of `kind` and lie inside one of the
  /// folders after its links are resolved. Throws palpsim::Error naming `what` and the path
  /// for an empty path, a NUL character, a missing path, the wrong kind (a folder where a
  /// file is wanted, a FIFO, a device) and a path outside the folders.
  std::string resolve(const std::string& path, const std::string& what, PathKind kind = PathKind::kFile) const;

 private:
  bool inside(const std::string& resolved) const;
  std::string outside(const std::string& path, const std::string& what) const;

  std::vector<std::string> dirs_;
  std::string label_;
};

/// Throws palpsim::Error naming `what` for a path that cannot name a file: empty, or
/// holding a NUL character (the C library would open the part before it).
void check_path_text(const std::string& path, const std::string& what);

/// Opens `path` for reading without blocking (O_NONBLOCK: a FIFO cannot stall the caller)
/// and checks with fstat that it is a regular file; returns the descriptor, which the
/// caller closes. Throws palpsim::Error naming `what` and the path when it cannot.
int open_regular_file(const std::string& path, const std::string& what);

/// The first `max_bytes` bytes of the regular file `path` (all of it when shorter), read
/// through open_regular_file. Throws palpsim::Error naming `what` when it cannot.
std::string read_file_head(const std::string& path, std::size_t max_bytes, const std::string& what);

}  // namespace palpsim
