#include "device.h"

#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <stdexcept>

namespace palpsim::haptic {
namespace {

std::vector<std::string> split(const std::string& line, char sep) {
  std::vector<std::string> out;
  std::string cell;
  std::istringstream s(line);
  while (std::getline(s, cell, sep)) {
    // trim blanks and a trailing CR
    const auto a = cell.find_first_not_of(" \t\r");
    const auto b = cell.find_last_not_of(" \t\r");
    out.push_back(a == std::string::npos ? "" : cell.substr(a, b - a + 1));
  }
  return out;
}

bool parse_double(const std::string& s, double& v) {
  if (s.empty()) return false;
  char* end = nullptr;
  v = std::strtod(s.c_str(), &end);
  return end && *end == '\0' && std::isfinite(v);
}

// reads columns `names` (or the first four columns of a header-less file) as t,x,y,z
ScriptedDevice read_table(const std::string& path, const std::vector<std::string>& names, bool header_required,
                          const std::string& what) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path + ": cannot open");
  std::vector<double> t;
  std::vector<V3> p;
  std::string line;
  int lineno = 0;
  std::vector<int> col{0, 1, 2, 3};
  bool first = true;
  while (std::getline(in, line)) {
    ++lineno;
    if (line.empty() || line[0] == '#') continue;
    const auto cells = split(line, ',');
    if (first) {
      first = false;
      double dummy;
      if (!parse_double(cells.empty() ? "" : cells[0], dummy)) {
        // a header: find the columns by name
        for (std::size_t k = 0; k < names.size(); ++k) {
          col[k] = -1;
          for (std::size_t c = 0; c < cells.size(); ++c)
            if (cells[c] == names[k]) col[k] = int(c);
          if (col[k] < 0) throw std::runtime_error(path + ":" + std::to_string(lineno) + ": no column '" + names[k] + "' in the header");
        }
        continue;
      }
      if (header_required) throw std::runtime_error(path + ":1: expected a header naming " + names[0] + ", " + names[1] + ", ...");
    }
    double v[4];
    for (int k = 0; k < 4; ++k) {
      if (col[k] >= int(cells.size()) || !parse_double(cells[col[k]], v[k]))
        throw std::runtime_error(path + ":" + std::to_string(lineno) + ": column " + std::to_string(col[k] + 1) + " ('" +
                                 names[k] + "') is not a finite number");
    }
    if (!t.empty() && v[0] < t.back())
      throw std::runtime_error(path + ":" + std::to_string(lineno) + ": time goes backwards (" + std::to_string(v[0]) + " s after " +
                               std::to_string(t.back()) + " s)");
    t.push_back(v[0]);
    p.push_back({v[1], v[2], v[3]});
  }
  if (t.empty()) throw std::runtime_error(path + ": no samples");
  return ScriptedDevice(std::move(t), std::move(p), what + " " + path + " (" + std::to_string(lineno) + " lines)");
}

// press:X,Y,Z[,TRAVEL]: the start point and, when given, how far the press goes (mm,
// (0, kMaxPressTravelMm]); `travel` keeps its default otherwise
V3 parse_press(const std::string& s, const std::string& spec, double& travel_mm) {
  const auto c = split(s, ',');
  V3 v;
  if ((c.size() != 3 && c.size() != 4) || !parse_double(c[0], v.x) || !parse_double(c[1], v.y) ||
      !parse_double(c[2], v.z))
    throw std::runtime_error("--device " + spec + ": expected press:X,Y,Z or press:X,Y,Z,TRAVEL in mm");
  if (c.size() == 4 && (!parse_double(c[3], travel_mm) || !(travel_mm > 0) || travel_mm > kMaxPressTravelMm))
    throw std::runtime_error("--device " + spec + ": TRAVEL '" + c[3] + "' must be a length in mm in (0, " +
                             std::to_string(int(kMaxPressTravelMm)) + "]");
  return v;
}

}  // namespace

ScriptedDevice::ScriptedDevice(std::vector<double> t_s, std::vector<V3> tip_mm, std::string what)
    : t_(std::move(t_s)), p_(std::move(tip_mm)), what_(std::move(what)) {}

bool ScriptedDevice::read_tip(double t, V3& tip) {
  if (t_.empty() || t > t_.back()) return false;
  if (t <= t_.front()) {
    tip = p_.front();
    return true;
  }
  while (cursor_ + 1 < t_.size() && t_[cursor_ + 1] < t) ++cursor_;
  const std::size_t a = cursor_, b = std::min(cursor_ + 1, t_.size() - 1);
  const double span = t_[b] - t_[a];
  const double w = span > 0 ? (t - t_[a]) / span : 1.0;
  tip = {p_[a].x + w * (p_[b].x - p_[a].x), p_[a].y + w * (p_[b].y - p_[a].y), p_[a].z + w * (p_[b].z - p_[a].z)};
  return true;
}

std::unique_ptr<Device> make_device(const std::string& spec, const PatientBox& box) {
  if (spec == "press" || spec.rfind("press:", 0) == 0) {
    // start 10 mm behind the middle of the back (or at the given point), press 40 mm (or
    // the given travel) along -y at 20 mm/s, hold 0.5 s, come back; three times
    V3 s{0.5 * (box.body_min_mm.x + box.body_max_mm.x), box.body_max_mm.y + 10,
         0.5 * (box.body_min_mm.z + box.body_max_mm.z)};
    double depth_mm = kDefaultPressTravelMm;
    if (spec.size() > 6) s = parse_press(spec.substr(6), spec, depth_mm);
    const double speed_mm_s = 20, hold_s = 0.5;
    const double t_press = depth_mm / speed_mm_s;
    std::vector<double> t;
    std::vector<V3> p;
    double t0 = 0;
    for (int rep = 0; rep < 3; ++rep) {
      t.push_back(t0);
      p.push_back(s);
      t.push_back(t0 + t_press);
      p.push_back({s.x, s.y - depth_mm, s.z});
      t.push_back(t0 + t_press + hold_s);
      p.push_back({s.x, s.y - depth_mm, s.z});
      t0 += 2 * t_press + hold_s;
    }
    t.push_back(t0);
    p.push_back(s);
    char what[160];
    std::snprintf(what, sizeof what, "press from (%.1f, %.1f, %.1f) mm, %.1f mm along -y at 20 mm/s, 3 times", s.x,
                  s.y, s.z, depth_mm);
    return std::make_unique<ScriptedDevice>(std::move(t), std::move(p), what);
  }
  if (spec.rfind("csv:", 0) == 0)
    return std::make_unique<ScriptedDevice>(read_table(spec.substr(4), {"t", "x", "y", "z"}, false, "csv"));
  if (spec.rfind("replay:", 0) == 0)
    return std::make_unique<ScriptedDevice>(
        read_table(spec.substr(7), {"time_s", "tip_x_mm", "tip_y_mm", "tip_z_mm"}, true, "replay of"));
  throw std::runtime_error("--device " + spec + ": expected press, press:X,Y,Z[,TRAVEL], csv:FILE or replay:FILE");
}

}  // namespace palpsim::haptic
