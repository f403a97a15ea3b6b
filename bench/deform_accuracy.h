// palpsim-bench deform --accuracy: what accuracy costs in time. For one realistic
// press on the phantom (10 mm into the back over the L3 spinous process) every
// backend this build and machine have is timed for each setting of one knob at a
// time (relaxation iterations, multigrid steps, inversion iterations, VOI edge; the others at the
// scene defaults) and the result is compared with a reference run with generous
// settings of that knob. The implementation lives in deform_accuracy_bench.cpp so
// that bench/CMakeLists.txt's *_bench.cpp glob links it; it registers no area of
// its own: `palpsim-bench deform --accuracy` calls it.
#pragma once

#include <string>
#include <vector>

namespace palpsim::bench {

/// What the accuracy study runs and where it writes.
struct AccuracyOptions {
  std::string json;                  // JSON output file; empty: print only
  std::string commit = "unknown";    // commit of the build, copied into the JSON
  bool quick = false;                // fewer timed repetitions (a smoke run)
  double voxel_mm = 340.0 / 255.0;   // phantom voxel size (mm), as in the deform bench
  int ref_relax_iterations = 400;    // reference of the relaxation study
  int ref_invert_iterations = 64;    // reference of the inversion study
  int ref_voi_edge = 160;            // reference of the VOI study (voxel), above the largest setting
  std::string study;                 // only this knob's study (relax_iterations, relax_cycles, invert_iterations, voi_edge); "" = all
  std::string backend;               // only this backend ("cpu" or "cuda"); "" = every one available
  int ref_multigrid_cycles = 40;     // reference of the multigrid study: converged to float rounding
};

/// The deformation backends this build and machine have ("cpu", and "cuda" where it
/// runs), or only `only` when it is not empty (a --backend option): an unknown name or
/// one this machine lacks throws palpsim::Error starting with `who` and saying why.
/// `device` names the GPU (or "cpu only"). A non-empty `who` prints
/// "<who>: backends ... (why cuda is or is not there)".
std::vector<std::string> deform_backends(std::string& device, const std::string& who, const std::string& only = "");

/// Throws palpsim::Error ("<what> cannot write <path> ...") before minutes of work when
/// `path` cannot be created (its folder missing or read-only).
void check_writable(const std::string& path, const std::string& what);

/// Runs the study, prints one markdown table per backend and knob, writes the JSON
/// when asked; returns the process exit code (throws palpsim::Error on bad input).
int run_deform_accuracy(const AccuracyOptions& options);

}  // namespace palpsim::bench

namespace palpsim::bench {

/// What `palpsim-bench accuracy` runs and where it writes (accuracy_bench.cpp parses
/// the flags): one study of every knob against references (a)-(d), then the report.
struct ReportOptions {
  std::string json_only;          // write the study's JSON here and stop (the GPU machine, no Python)
  std::string gpu_json;           // a GPU machine's --json-only output to merge into the report
  std::string elastic_json;       // the elastic study's JSON (accuracy --elastic) for the report's elastic sections
  std::string elastic_gpu_json;   // a GPU machine's elastic study (accuracy --elastic --json-only) for their GPU column
  std::string forces_json;        // the force models' comparison (accuracy --forces) for the report's force section
  std::string halfspace_json;     // Hertz's blocks on the half-space (accuracy --halfspace) for the report's table
  std::string out_dir;            // report folder: accuracy.md, its PNGs and accuracy-cpu.json
  std::string python;             // interpreter with numpy, scikit-fem, pyamg, matplotlib (empty: not needed)
  std::string commit = "unknown"; // commit of the build, copied into the JSON
  bool quick = false;             // fewer timed repetitions and force samples (a smoke run)
  std::string backend;            // only this deformation backend ("" = every one this build and machine have)
  double voxel_mm = 340.0 / 255.0;  // phantom voxel size (mm) of the deformation press
};

/// Runs the study (every backend this build and machine have), computes reference (c)
/// through bench/accuracy_fem.py when `python` is set, writes the JSON and, unless
/// json_only, bench/accuracy_report.py's report; returns the process exit code.
int run_accuracy_report(const ReportOptions& options);

/// Writes the report (accuracy.md and its plots in options.out_dir) through
/// bench/accuracy_report.py from recorded JSON: `cpu_json` (the study of `palpsim-bench
/// accuracy`) and the options' GPU and elastic JSON; returns the process exit code.
int write_accuracy_report(const ReportOptions& options, const std::string& cpu_json);

/// What `palpsim-bench accuracy --elastic` runs and where it writes (elastic_accuracy_bench.cpp):
/// the elastic model and the ChainMail family on the shipped scene against references a correct
/// elasticity solver can meet, and what each costs.
struct ElasticStudyOptions {
  std::string json;               // the study's JSON
  std::string python;             // interpreter with numpy, scikit-fem and pyamg for the FEM references (empty: none)
  std::string work_dir;           // where the FEM's inputs and results stay, reused while an input is unchanged
                                  // (empty: a temporary folder, removed at the end)
  std::string commit = "unknown"; // commit of the build, copied into the JSON
  std::string backend;            // only this deformation backend ("" = every one this build and machine have)
  bool quick = false;             // fewer settings, repetitions and references (a smoke run)
  bool references = true;         // false: the rows' times only (a GPU machine; the errors come from the CPU run)
};

/// Runs the elastic study and writes its JSON; returns the process exit code (throws
/// palpsim::Error on bad input).
int run_elastic_accuracy(const ElasticStudyOptions& options);

/// What `palpsim-bench accuracy --forces` runs and where it writes (force_models_bench.cpp): eq. 2's
/// force and the elastic model's, as the server reports each, for the same presses of the shipped
/// scene on the elastic study's block (beside Hertz) and on the phantom.
struct ForceModelsOptions {
  std::string json;               // the study's JSON
  std::string commit = "unknown"; // commit of the build, copied into the JSON
  std::string backend;            // the elastic step's backend ("" = cpu)
};

/// Runs the force-model comparison and writes its JSON; returns the process exit code (throws
/// palpsim::Error on bad input).
int run_force_models(const ForceModelsOptions& options);

/// What `palpsim-bench accuracy --halfspace` runs and where it writes (hertz_halfspace_bench.cpp):
/// Hertz's blocks with their faces at rest and on the half-space (Boussinesq's field of the
/// finger's force), on the CPU.
struct HalfspaceOptions {
  std::string json;               // the study's JSON
  std::string commit = "unknown"; // commit of the build, copied into the JSON
  bool quick = false;             // the 64^3 block at R / 5 only
};

/// Runs the half-space study and writes its JSON; returns the process exit code (throws
/// palpsim::Error on bad input).
int run_hertz_halfspace(const HalfspaceOptions& options);

}  // namespace palpsim::bench
