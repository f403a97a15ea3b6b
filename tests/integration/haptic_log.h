// Reading palpsim-haptic's --log CSV in integration tests (clients/haptic/README.md names
// the columns): the rows as numbers, and the longest stretch without a new reply.
#pragma once

#include <cmath>
#include <cstddef>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace palpsim::test {

/// One step of the client's log.
struct HapticLogRow {
  double t = 0;                     // time_s
  double fx = 0, fy = 0, fz = 0;    // force applied (N)
  unsigned long long reply_seq = 0; // the newest reply's seq
  double scale = 0;                 // watchdog_scale
  int mode = 0;                     // 0 remote, 1 local
  /// The applied force's magnitude (N).
  double force() const { return std::sqrt(fx * fx + fy * fy + fz * fz); }
};

/// The rows of a log (the header skipped; rows with fewer than 13 cells too).
inline std::vector<HapticLogRow> read_haptic_log(const std::string& path) {
  std::vector<HapticLogRow> rows;
  std::ifstream in(path);
  std::string line;
  std::getline(in, line);
  while (std::getline(in, line)) {
    std::vector<std::string> c;
    std::stringstream ss(line);
    std::string cell;
    while (std::getline(ss, cell, ',')) c.push_back(cell);
    if (c.size() < 13) continue;
    HapticLogRow r;
    r.t = std::stod(c[1]);
    r.fx = std::stod(c[5]);
    r.fy = std::stod(c[6]);
    r.fz = std::stod(c[7]);
    r.reply_seq = std::stoull(c[9]);
    r.scale = std::stod(c[12]);
    r.mode = c.size() > 13 ? std::stoi(c[13]) : 0;
    rows.push_back(r);
  }
  return rows;
}

/// The longest stretch of rows in which no new reply arrived: its first row (the newest
/// reply arrived at or before it) and its length in rows.
inline void longest_reply_gap(const std::vector<HapticLogRow>& rows, std::size_t& first, std::size_t& length) {
  first = 0;
  length = 0;
  for (std::size_t i = 1, start = 0; i < rows.size(); ++i) {
    if (rows[i].reply_seq != rows[start].reply_seq) start = i;
    if (i - start > length) {
      length = i - start;
      first = start;
    }
  }
}

/// The watchdog over a stretch without new replies, rows[first .. first + length] (the
/// newest reply arrived at or before rows[first]): whether a force was applied within a
/// step of that reply, and the first row `zero_after_s` or more after it whose force or
/// watchdog scale is not zero (npos: none).
struct WatchdogOverGap {
  bool force_at_reply = false;
  std::size_t not_zero = std::string::npos;
};

inline WatchdogOverGap watchdog_over_gap(const std::vector<HapticLogRow>& rows, std::size_t first, std::size_t length,
                                         double zero_after_s = 0.010) {
  WatchdogOverGap w;
  const double t_reply = rows[first].t;
  for (std::size_t i = first; i <= first + length && i < rows.size(); ++i) {
    if (rows[i].t - t_reply < 0.001 && rows[i].force() > 0) w.force_at_reply = true;
    if (rows[i].t - t_reply >= zero_after_s && (rows[i].force() != 0.0 || rows[i].scale != 0.0) &&
        w.not_zero == std::string::npos)
      w.not_zero = i;
  }
  return w;
}

}  // namespace palpsim::test
