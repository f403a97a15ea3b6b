// palpsim-bench: one driver, one subcommand per area (prep, haptic, deform).
// Each area's benchmark lives in bench/<area>_bench.cpp and defines bench_<area>().
#include <cstdio>
#include <cstring>
#include <string>

#include "bench/registry.h"
#include "core/linked_backends.h"

int main(int argc, char** argv) {
  // line by line, so that a log cut short (a crash, a timeout on the GPU machine) keeps what was measured
  std::setvbuf(stdout, nullptr, _IOLBF, 0);
  // cuda's deformation backend, nvJPEG encoder and overlay writer, in a CUDA build
  palpsim::register_linked_backends();
  const auto& entries = palpsim::bench::registry();
  if (argc < 2 || std::strcmp(argv[1], "--help") == 0 || std::strcmp(argv[1], "-h") == 0) {
    std::printf("usage: palpsim-bench AREA [--json FILE] [options]\nareas:\n");
    for (const auto& e : entries) std::printf("  %-8s %s\n", e.name.c_str(), e.help.c_str());
    return argc < 2 ? 2 : 0;
  }
  for (const auto& e : entries)
    if (e.name == argv[1]) return e.run(argc - 1, argv + 1);
  std::fprintf(stderr, "palpsim-bench: unknown area '%s' (try --help)\n", argv[1]);
  return 2;
}
