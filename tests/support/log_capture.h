// Every line spdlog's default logger writes while a LogCapture lives (the logger that
// palpsim-server and palpsim-prep log through), for tests that check what a user is told.
#pragma once

#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

namespace palpsim::test {

/// Adds a sink to the default logger for its lifetime; lines() gives what it took.
struct LogCapture {
  std::ostringstream out;
  std::shared_ptr<spdlog::sinks::ostream_sink_mt> sink = std::make_shared<spdlog::sinks::ostream_sink_mt>(out);
  LogCapture() { spdlog::default_logger()->sinks().push_back(sink); }
  ~LogCapture() {
    auto& s = spdlog::default_logger()->sinks();
    s.erase(std::remove(s.begin(), s.end(), sink), s.end());
  }
  std::vector<std::string> lines() {
    spdlog::default_logger()->flush();
    std::vector<std::string> v;
    std::istringstream in(out.str());
    for (std::string l; std::getline(in, l);) v.push_back(l);
    return v;
  }
  /// The lines that hold `text`.
  std::vector<std::string> lines_with(const std::string& text) {
    std::vector<std::string> v;
    for (const std::string& l : lines())
      if (l.find(text) != std::string::npos) v.push_back(l);
    return v;
  }
};

}  // namespace palpsim::test
