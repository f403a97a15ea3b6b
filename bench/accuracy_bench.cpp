// palpsim-bench accuracy: one command, one report (issue 8 sections 1-2). Runs every
// knob of the deformation (relaxation method and iterations, inversion iterations, VOI
// edge, ChainMail preset) and the force model's sampling against references (a)-(d)
// (deform_accuracy.h, deform_accuracy_bench.cpp), then writes bench/results/accuracy.md
// and its plots through bench/accuracy_report.py, merging a GPU machine's JSON.
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "bench/deform_accuracy.h"
#include "bench/registry.h"
#include "core/error.h"

namespace {

// the Python that runs the FEM and the report: PALPSIM_PYTHON, else the repository's .venv
std::string find_python() {
  if (const char* p = std::getenv("PALPSIM_PYTHON"); p && *p) return p;
  return std::string(PALPSIM_SOURCE_DIR) + "/.venv/bin/python";
}

}  // namespace

PALPSIM_BENCH(accuracy, "every deformation and force knob against references (a)-(d), the elastic model against "
                        "elasticity (--elastic), the two force models (--forces) -> bench/results/accuracy.md [--gpu-json GPU.json] [--elastic-json E.json] "
                        "[--out-dir DIR] [--quick] [--commit C]; --from-json CPU.json: the report only; on a GPU machine: "
                        "--json-only FILE") {
  palpsim::bench::ReportOptions o;
  palpsim::bench::ElasticStudyOptions e;
  o.out_dir = std::string(PALPSIM_SOURCE_DIR) + "/bench/results";
  bool elastic = false, forces = false, halfspace = false;
  std::string from_json;
  for (int a = 1; a < argc; ++a) {
    const std::string s = argv[a];
    if (s == "--json-only" && a + 1 < argc) o.json_only = argv[++a];
    else if (s == "--gpu-json" && a + 1 < argc) o.gpu_json = argv[++a];
    else if (s == "--elastic-json" && a + 1 < argc) o.elastic_json = argv[++a];
    else if (s == "--elastic-gpu-json" && a + 1 < argc) o.elastic_gpu_json = argv[++a];
    else if (s == "--forces-json" && a + 1 < argc) o.forces_json = argv[++a];
    else if (s == "--halfspace-json" && a + 1 < argc) o.halfspace_json = argv[++a];
    else if (s == "--from-json" && a + 1 < argc) from_json = argv[++a];
    else if (s == "--out-dir" && a + 1 < argc) o.out_dir = argv[++a];
    else if (s == "--commit" && a + 1 < argc) o.commit = argv[++a];
    else if (s == "--quick") o.quick = true;
    else if (s == "--backend" && a + 1 < argc) o.backend = argv[++a];
    else if (s == "--elastic") elastic = true;
    else if (s == "--forces") forces = true;
    else if (s == "--halfspace") halfspace = true;
    else if (s == "--work" && a + 1 < argc) e.work_dir = argv[++a];
    else if (s == "--json" && a + 1 < argc) e.json = argv[++a];
    else {
      std::fprintf(stderr,
                   "palpsim-bench accuracy: unknown argument '%s'\n"
                   "usage: palpsim-bench accuracy [--gpu-json FILE] [--elastic-json FILE] [--elastic-gpu-json FILE] "
                   "[--out-dir DIR] [--quick] [--commit C] [--backend cpu|cuda]\n"
                   "       palpsim-bench accuracy --from-json CPU.json [--gpu-json FILE] [--elastic-json FILE] "
                   "[--elastic-gpu-json FILE] [--forces-json FILE] [--halfspace-json FILE] [--out-dir DIR]   (the report from "
                   "recorded runs)\n"
                   "       palpsim-bench accuracy --elastic [--json FILE | --json-only FILE] [--work DIR] [--quick] "
                   "[--commit C] [--backend cpu|cuda]   (the elastic study; --json-only: times only, no Python)\n"
                   "       palpsim-bench accuracy --forces [--json FILE] [--commit C] [--backend cpu|cuda]   "
                   "(eq. 2's force and the elastic model's for the same presses)\n"
                   "       palpsim-bench accuracy --halfspace [--json FILE] [--commit C] [--quick]   (Hertz's blocks with "
                   "their faces on the half-space)\n"
                   "       palpsim-bench accuracy --json-only FILE [--quick] [--commit C] [--backend cuda]   "
                   "(GPU machine: the study's JSON only, no Python)\n",
                   s.c_str());
      return 2;
    }
  }
  if (int(elastic) + int(forces) + int(halfspace) + int(!from_json.empty()) > 1) {
    std::fprintf(stderr,
                 "palpsim-bench accuracy: --elastic, --forces and --halfspace run a study each and --from-json reports "
                 "recorded ones; give one\n");
    return 2;
  }
  // the FEM references and the report need Python with their packages: checked before minutes of work
  const bool needs_python =
      (forces || halfspace) ? false : elastic ? o.json_only.empty() : (o.json_only.empty() || !from_json.empty());
  if (needs_python) {
    o.python = find_python();
    const std::string probe = "'" + o.python + "' -c 'import numpy, scipy, skfem, pyamg, matplotlib' 2>/dev/null";
    if (access(o.python.c_str(), X_OK) != 0 || std::system(probe.c_str()) != 0) {
      std::fprintf(stderr,
                   "palpsim-bench accuracy: no usable Python at %s (needs numpy, scipy, scikit-fem, pyamg, matplotlib: "
                   "scripts/setup.sh installs them into .venv); set PALPSIM_PYTHON, or use --json-only FILE\n",
                   o.python.c_str());
      return 2;
    }
  }
  try {
    if (!from_json.empty()) return palpsim::bench::write_accuracy_report(o, from_json);
    if (forces) {
      palpsim::bench::ForceModelsOptions f;
      f.json = !e.json.empty() ? e.json : !o.json_only.empty() ? o.json_only : o.out_dir + "/accuracy-forces-cpu.json";
      f.commit = o.commit;
      f.backend = o.backend;
      return palpsim::bench::run_force_models(f);
    }
    if (halfspace) {
      palpsim::bench::HalfspaceOptions h;
      h.json = !e.json.empty() ? e.json : o.out_dir + "/accuracy-halfspace-cpu.json";
      h.commit = o.commit;
      h.quick = o.quick;
      return palpsim::bench::run_hertz_halfspace(h);
    }
    if (elastic) {
      if (!o.json_only.empty()) e.json = o.json_only;
      if (e.json.empty()) e.json = o.out_dir + "/accuracy-elastic-cpu.json";
      e.python = o.python;
      e.commit = o.commit;
      e.backend = o.backend;
      e.quick = o.quick;
      e.references = o.json_only.empty();
      return palpsim::bench::run_elastic_accuracy(e);
    }
    return palpsim::bench::run_accuracy_report(o);
  } catch (const palpsim::Error& err) {
    std::fprintf(stderr, "palpsim-bench accuracy: %s\n", err.what());
    return 1;
  }
}
