#include "core/path_policy.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <system_error>

#include "core/error.h"

namespace palpsim {

namespace fs = std::filesystem;

namespace {

std::string quoted(const std::string& s) { return "'" + s + "'"; }

// what a file of this mode is, for messages
const char* kind_name(mode_t m) {
  if (S_ISDIR(m)) return "a folder";
  if (S_ISFIFO(m)) return "a FIFO (named pipe)";
  if (S_ISSOCK(m)) return "a socket";
  if (S_ISCHR(m) || S_ISBLK(m)) return "a device";
  if (S_ISREG(m)) return "a regular file";
  return "not a regular file";
}

}  // namespace

void check_path_text(const std::string& path, const std::string& what) {
  if (path.empty()) throw Error(what + " is empty");
  if (path.find('\0') != std::string::npos)
    throw Error(what + " " + quoted(path.substr(0, path.find('\0'))) +
                "... holds a NUL character; a path cannot");
}

PathPolicy::PathPolicy(const std::vector<std::string>& dirs, const std::string& option, const std::string& label)
    : label_(label) {
  for (const std::string& d : dirs) {
    std::error_code ec;
    if (d.empty() || d.find('\0') != std::string::npos) throw Error(option + " " + quoted(d) + ": not a folder name");
    const fs::path c = fs::canonical(d, ec);
    if (ec || !fs::is_directory(c))
      throw Error(option + " " + d + ": " + (ec ? ec.message() : std::string("not a folder")));
    if (std::find(dirs_.begin(), dirs_.end(), c.string()) == dirs_.end()) dirs_.push_back(c.string());
  }
}

bool PathPolicy::inside(const std::string& resolved) const {
  for (const std::string& d : dirs_)
    if (resolved == d || (resolved.size() > d.size() && resolved.compare(0, d.size(), d) == 0 &&
                          (d.back() == '/' || resolved[d.size()] == '/')))
      return true;
  return false;
}

std::string PathPolicy::outside(const std::string& path, const std::string& what) const {
  if (dirs_.empty())
    return what + " " + quoted(path) +
           ": this server reads and writes no file for network requests (start it with --scene-dir)";
  std::string list;
  for (const std::string& d : dirs_) list += (list.empty() ? "" : ", ") + d;
  // a path that only its links lead out
  std::error_code ec;
  const bool link = inside(fs::absolute(path, ec).lexically_normal().string());
  return what + " " + quoted(path) + " lies outside " + label_ + " (" + list + ")" +
         (link ? " once its links are followed" : "");
}

std::string PathPolicy::check(const std::string& path, const std::string& what) const {
  try {
    check_path_text(path, what);
  } catch (const Error& e) {
    return e.what();
  }
  // resolved as far as it exists: a link inside an allowed folder that leads out of it is out
  std::error_code ec;
  fs::path p = fs::absolute(path, ec);
  if (!ec) p = fs::weakly_canonical(p, ec);
  return !ec && inside(p.string()) ? "" : outside(path, what);
}

std::string PathPolicy::resolve(const std::string& path, const std::string& what, PathKind kind) const {
  check_path_text(path, what);
  // the folders first (resolved as far as the path exists), so nothing is said about a
  // path outside them, not even whether it exists
  if (!check(path, what).empty()) throw Error(outside(path, what));
  std::error_code ec;
  const fs::path c = fs::canonical(path, ec);
  if (ec) {
    if (ec == std::errc::no_such_file_or_directory) throw Error(what + " " + quoted(path) + ": no such file or folder");
    throw Error(what + " " + quoted(path) + ": " + ec.message());
  }
  if (!inside(c.string())) throw Error(outside(path, what));
  struct stat st {};
  if (::stat(c.c_str(), &st) != 0) throw Error(what + " " + quoted(path) + ": " + std::strerror(errno));
  const bool file = S_ISREG(st.st_mode), folder = S_ISDIR(st.st_mode);
  if (kind == PathKind::kFile && !file)
    throw Error(what + " " + quoted(path) + " is " + kind_name(st.st_mode) + ", not a regular file");
  if (kind == PathKind::kFolder && !folder)
    throw Error(what + " " + quoted(path) + " is " + kind_name(st.st_mode) + ", not a folder");
  if (kind == PathKind::kFileOrFolder && !file && !folder)
    throw Error(what + " " + quoted(path) + " is " + kind_name(st.st_mode) + ", neither a regular file nor a folder");
  return c.string();
}

int open_regular_file(const std::string& path, const std::string& what) {
  check_path_text(path, what);
  const int fd = ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC | O_NOCTTY);
  if (fd < 0) {
    const int err = errno;
    if (err == ENOENT) throw Error(what + " " + quoted(path) + ": no such file");
    throw Error(what + " " + quoted(path) + ": cannot open it: " + std::strerror(err));
  }
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    const mode_t m = st.st_mode;
    ::close(fd);
    throw Error(what + " " + quoted(path) + " is " + kind_name(m) + ", not a regular file");
  }
  return fd;
}

std::string read_file_head(const std::string& path, std::size_t max_bytes, const std::string& what) {
  const int fd = open_regular_file(path, what);
  std::string out;
  char buf[1 << 16];
  while (out.size() < max_bytes) {
    const ssize_t n = ::read(fd, buf, std::min(sizeof buf, max_bytes - out.size()));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      const int err = errno;
      ::close(fd);
      throw Error(what + " " + quoted(path) + ": cannot read it: " + std::strerror(err));
    }
    if (n == 0) break;
    out.append(buf, std::size_t(n));
  }
  ::close(fd);
  return out;
}

}  // namespace palpsim
