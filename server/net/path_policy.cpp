#include "net/path_policy.h"

#include <filesystem>
#include <system_error>

#include "core/error.h"

namespace palpsim::net {

namespace fs = std::filesystem;

PathPolicy::PathPolicy(const std::vector<std::string>& dirs) {
  for (const std::string& d : dirs) {
    std::error_code ec;
    const fs::path c = fs::canonical(d, ec);
    if (ec || !fs::is_directory(c))
      throw Error("--scene-dir " + d + ": " + (ec ? ec.message() : std::string("not a folder")));
    dirs_.push_back(c.string());
  }
}

std::string PathPolicy::check(const std::string& path, const std::string& what) const {
  if (dirs_.empty())
    return what + " '" + path + "': this server reads and writes no file for network requests (start it with --scene-dir)";
  // resolved as far as it exists: a link inside an allowed folder that leads out of it is out
  std::error_code ec;
  fs::path p = fs::absolute(path, ec);
  if (!ec) p = fs::weakly_canonical(p, ec);
  if (!ec) {
    const std::string s = p.string();
    for (const std::string& d : dirs_)
      if (s == d || (s.size() > d.size() && s.compare(0, d.size(), d) == 0 && (d.back() == '/' || s[d.size()] == '/')))
        return "";
  }
  std::string list;
  for (const std::string& d : dirs_) list += (list.empty() ? "" : ", ") + d;
  return what + " '" + path + "' lies outside the folders this server allows (" + list + ")";
}

}  // namespace palpsim::net
