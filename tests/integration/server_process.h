// Runs the real palpsim-server (and other executables of the build) as child processes
// for integration tests: free ports (tcp://127.0.0.1:*), the "ready on" line parsed,
// clean stop with SIGTERM, and exit status and output collected.
#pragma once

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace palpsim::test {

/// Path of an executable in the build folder.
inline std::string build_exe(const std::string& name) { return std::string(PALPSIM_BINARY_DIR) + "/" + name; }

/// A child process with stdout and stderr captured to files.
class Child {
 public:
  /// Starts argv[0] with argv; stdout and stderr go to files under /tmp.
  explicit Child(const std::vector<std::string>& argv) {
    static int counter = 0;
    const std::string base = "/tmp/palpsim-it-" + std::to_string(::getpid()) + "-" + std::to_string(counter++);
    out_path_ = base + ".out";
    err_path_ = base + ".err";
    pid_ = ::fork();
    if (pid_ < 0) throw std::runtime_error("fork failed");
    if (pid_ == 0) {
      const int o = ::open(out_path_.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      const int e = ::open(err_path_.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      ::dup2(o, 1);
      ::dup2(e, 2);
      std::vector<char*> args;
      for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
      args.push_back(nullptr);
      ::execv(args[0], args.data());
      std::perror("execv");
      ::_exit(127);
    }
  }
  ~Child() {
    if (pid_ > 0 && !exited_) {
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
    }
    std::remove(out_path_.c_str());
    std::remove(err_path_.c_str());
  }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;

  pid_t pid() const { return pid_; }
  std::string out() const { return slurp(out_path_); }
  std::string err() const { return slurp(err_path_); }

  /// Waits up to `timeout_s` for the exit; returns the exit status, or -1 when it is
  /// still running (or died of a signal: 128 + signal).
  int wait(double timeout_s) {
    if (exited_) return status_;
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    for (;;) {
      int st = 0;
      const pid_t r = ::waitpid(pid_, &st, WNOHANG);
      if (r == pid_) {
        exited_ = true;
        status_ = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
        return status_;
      }
      if (std::chrono::steady_clock::now() > end) return -1;
      ::usleep(5000);
    }
  }
  /// Sends a signal.
  void signal(int sig) { ::kill(pid_, sig); }

 private:
  pid_t pid_ = -1;
  bool exited_ = false;
  int status_ = -1;
  std::string out_path_, err_path_;
  static std::string slurp(const std::string& p) {
    std::ifstream in(p);
    return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
};

/// palpsim-server on free loopback ports with a scene file; start() waits for "ready on".
class ServerProcess {
 public:
  /// `exe`: another palpsim-server (an older build, for comparisons); default this build's.
  explicit ServerProcess(const std::string& scene_file, std::vector<std::string> extra = {},
                         const std::string& exe = build_exe("palpsim-server"))
      : child_([&] {
          std::vector<std::string> a{exe, "--bind", "tcp://127.0.0.1:*", "--pose-bind", "tcp://127.0.0.1:*"};
          if (!scene_file.empty()) {
            a.push_back("--scene");
            a.push_back(scene_file);
          }
          a.insert(a.end(), extra.begin(), extra.end());
          return a;
        }()) {}

  /// Waits up to `timeout_s` for the ready line; false when the server exited or timed out.
  bool wait_ready(double timeout_s) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < end) {
      const std::string o = child_.out();
      const auto at = o.find("ready on ");
      if (at != std::string::npos && o.find('\n', at) != std::string::npos) {
        const auto a0 = at + 9, a1 = o.find(' ', a0);
        control_ = o.substr(a0, a1 - a0);
        const auto p0 = o.find("poses ", a1) + 6, p1 = o.find_first_of(" \n", p0);
        pose_ = o.substr(p0, p1 - p0);
        return true;
      }
      if (child_.wait(0) >= 0) return false;
      ::usleep(20000);
    }
    return false;
  }
  /// SIGTERM, then the exit status (-1: it did not exit within `timeout_s`).
  int stop(double timeout_s = 10) {
    child_.signal(SIGTERM);
    return child_.wait(timeout_s);
  }
  Child& child() { return child_; }
  const std::string& control() const { return control_; }
  const std::string& pose() const { return pose_; }

 private:
  Child child_;
  std::string control_, pose_;
};

/// Writes `text` to a fresh file under /tmp and returns its path.
inline std::string temp_file(const std::string& stem, const std::string& text) {
  static int counter = 0;
  const std::string p = "/tmp/palpsim-it-" + std::to_string(::getpid()) + "-" + stem + std::to_string(counter++);
  std::ofstream(p) << text;
  return p;
}

/// A small, fast scene for integration tests: the phantom at 2 mm, short session timeout.
inline std::string fast_scene_text(const std::string& name = "integration", double timeout_s = 0.5) {
  return "name: \"" + name + "\"\nphantom { voxel_mm: 2.0 }\nserver { session_timeout_s: " + std::to_string(timeout_s) +
         " max_sessions: 32 }\n";
}

}  // namespace palpsim::test
