// Summaries of benchmark samples shared by the bench areas: percentiles and their JSON,
// and the machine a run was taken on.
#pragma once

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace palpsim::bench {

/// Median and 10th/90th percentiles of a sample (ms).
struct Spread {
  double median = 0, p10 = 0, p90 = 0;
};

/// The spread of `v` (nearest-rank percentiles); all zero for an empty sample.
inline Spread spread(std::vector<double> v) {
  Spread s;
  if (v.empty()) return s;
  std::sort(v.begin(), v.end());
  auto at = [&](double q) { return v[std::size_t(std::lround(q * double(v.size() - 1)))]; };
  s.median = at(0.5);
  s.p10 = at(0.1);
  s.p90 = at(0.9);
  return s;
}

/// The q-quantile (0..1) of `v` by rank (the sample at floor(q n)); 0 for no samples.
inline double quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, std::size_t(q * double(v.size())))];
}

/// A JSON number (null for a non-finite value, which JSON cannot hold).
inline std::string json_number(double v) {
  if (!std::isfinite(v)) return "null";
  std::ostringstream o;
  o.precision(7);
  o << v;
  return o.str();
}

/// A vector (anything with x, y and z) as a JSON array of three numbers.
template <typename V>
std::string json_vec3(const V& v) {
  return "[" + json_number(v.x) + ", " + json_number(v.y) + ", " + json_number(v.z) + "]";
}

/// {"median_ms": ..., "p10_ms": ..., "p90_ms": ...}
inline std::string json_spread(const Spread& s) {
  return "{\"median_ms\": " + json_number(s.median) + ", \"p10_ms\": " + json_number(s.p10) +
         ", \"p90_ms\": " + json_number(s.p90) + "}";
}

/// "host, cpu model, N cores": the machine a benchmark ran on, for its output.
inline std::string machine() {
  std::ifstream in("/proc/cpuinfo");
  std::string line, model = "unknown cpu";
  while (std::getline(in, line))
    if (line.rfind("model name", 0) == 0) {
      model = line.substr(line.find(':') + 2);
      break;
    }
  char host[256] = "unknown";
  gethostname(host, sizeof host - 1);
  return std::string(host) + ", " + model + ", " + std::to_string(std::thread::hardware_concurrency()) + " cores";
}

}  // namespace palpsim::bench
