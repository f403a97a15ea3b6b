// Registration of benchmark areas: a bench/<area>_bench.cpp file adds itself with
// PALPSIM_BENCH(name, help) { ... } and is linked into palpsim-bench.
#pragma once

#include <functional>
#include <string>
#include <vector>

namespace palpsim::bench {

/// One benchmark area: its subcommand name, a line of help, and its entry point
/// (argv[0] is the area name).
struct Entry {
  std::string name;
  std::string help;
  std::function<int(int, char**)> run;
};

/// All registered areas, in registration order.
inline std::vector<Entry>& registry() {
  static std::vector<Entry> entries;
  return entries;
}

/// Adds an area at static-initialisation time.
struct Register {
  Register(const char* name, const char* help, int (*fn)(int, char**)) { registry().push_back({name, help, fn}); }
};

}  // namespace palpsim::bench

#define PALPSIM_BENCH(area, help)                                                  \
  static int bench_##area(int argc, char** argv);                                 \
  static ::palpsim::bench::Register bench_register_##area(#area, help, bench_##area); \
  static int bench_##area(int argc, char** argv)
