// What every case of the stability catalogue shares: its name, the backend it runs on
// and the seed of its random choices. A failure inside a case prints all three and the
// command that reproduces it (Catch2 INFO), e.g.
//   stability case "tip inside bone" on cpu, seed 20240801
//   (reproduce: PALPSIM_STABILITY_SEED=20240801 palpsim-test-deform-stability "*tip inside bone*")
#pragma once

#include <cstdint>
#include <cstdlib>
#include <random>
#include <sstream>
#include <string>

namespace palpsim::test::stability {

/// The catalogue's seed: $PALPSIM_STABILITY_SEED when set (to rerun a failure or to
/// explore other draws), else a fixed value so CI runs are repeatable.
inline std::uint64_t base_seed() {
  if (const char* s = std::getenv("PALPSIM_STABILITY_SEED"))
    if (*s) return std::strtoull(s, nullptr, 10);
  return 20240801;
}

/// One case on one backend, with its own random stream (the base seed mixed with the
/// case's name, so adding a case does not change the draws of the others).
struct Case {
  std::string name;
  std::string backend;     // "cpu" or "cuda"
  std::string executable;  // the test executable, for the reproduce line
  std::uint64_t seed;
  std::mt19937_64 rng;

  Case(std::string name_, std::string backend_, std::string executable_)
      : name(std::move(name_)), backend(std::move(backend_)), executable(std::move(executable_)), seed(base_seed()),
        rng(seed ^ fnv1a(name)) {}

  /// The line every failure of this case prints.
  std::string describe() const {
    std::ostringstream s;
    s << "stability case \"" << name << "\" on " << backend << ", seed " << seed
      << " (reproduce: PALPSIM_STABILITY_SEED=" << seed << " " << executable << " \"*" << name << "*\")";
    return s.str();
  }

  /// A uniform draw in [lo, hi).
  double uniform(double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng); }
  /// A uniform integer in [lo, hi].
  int integer(int lo, int hi) { return std::uniform_int_distribution<int>(lo, hi)(rng); }

 private:
  static std::uint64_t fnv1a(const std::string& s) {
    std::uint64_t h = 1469598103934665603ull;
    for (unsigned char ch : s) h = (h ^ ch) * 1099511628211ull;
    return h;
  }
};

}  // namespace palpsim::test::stability
