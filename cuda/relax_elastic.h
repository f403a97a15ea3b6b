// The elastic model on the GPU (deform.relax_method "elastic"): one session's solver state,
// the solver scratch that sessions share, and the step's launches (relax_elastic.cu). The
// CPU reference is server/deform/relax_elastic.cpp; elastic_math.h says what is solved.
#pragma once

#include <cuda_runtime.h>

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>

#include "core/patient.h"
#include "cuda/check.h"
#include "cuda/kernels.h"
#include "cuda/shared_scratch.h"
#include "deform/relax_elastic.h"

namespace palpsim::cuda {

/// The elastic solver's scratch for VOIs of up to `capacity` nodes whose coarse levels hold
/// up to `coarse_capacity` nodes: every level's V-cycle vectors, level 0's CG direction, the
/// set-up's carry of the last contact set and the reductions. Nothing in it outlives a
/// launch, so sessions whose solves run one after another may share one (ScratchTurn);
/// what a session keeps from step to step is in its ElasticBuffers.
struct ElasticScratch {
  using Turn = ScratchTurn<ElasticScratch>;

  ElasticScratch(long long capacity, long long coarse_capacity);
  ~ElasticScratch();
  ElasticScratch(const ElasticScratch&) = delete;
  ElasticScratch& operator=(const ElasticScratch&) = delete;
  /// The scratch shared on the current device for these capacities and `lane` (0: every
  /// session's; 1 and up: the batch lanes' that run solves side by side,
  /// relax_elastic_lanes()): the one alive, or a new one.
  static std::shared_ptr<ElasticScratch> shared(long long capacity, long long coarse_capacity, int lane = 0);
  /// Device bytes held.
  std::size_t bytes() const;

  long long capacity, coarse_capacity;
  int device = 0;
  int lane = 0;  // shared()'s lane
  // every level (capacity + coarse_capacity nodes, component c at c times that): the
  // V-cycle's two corrections (level 0: z), right-hand side (level 0: CG's residual r),
  // residual (level 0: also CG's K p), Chebyshev step; level 0 (capacity, same layout): CG's
  // direction p
  float *x[2] = {nullptr, nullptr}, *f = nullptr, *res = nullptr, *d = nullptr, *p = nullptr;
  std::uint8_t* tmp_flags = nullptr;  // the set-up's carry: the last VOI's contact bits
  double* sums = nullptr;             // the reductions' slots (relax_elastic.cu)
  cudaEvent_t done = nullptr;         // recorded after the last launch that used the scratch
  std::mutex mu;                      // one Turn at a time
};

/// A patient's volumes on the device that the elastic set-up reads (patient grid, i fastest).
struct ElasticPatient {
  const float* intensity = nullptr;        // HU (DevicePatient)
  const std::uint8_t* bone = nullptr;      // nonzero = bone (DevicePatient)
  const std::uint8_t* body = nullptr;      // the body mask C (DeviceBody)
  const float* dist_skin_mm = nullptr;     // B: depth under the skin (mm; DeviceBody)
};

class ElasticTrace;  // PALPSIM_ELASTIC_TRACE: where a solver's steps spend their time (relax_elastic.cu)

/// One session's elastic model on the GPU: its buffers (the field, flags and moduli of
/// every level kept from step to step: the warm start), what the host keeps of it (the
/// VOI it is set up for, whether the field and the unit press may start the next step),
/// and the step's launches. Mirrors relax_elastic_cpu() step for step.
class ElasticSolver {
 public:
  ElasticSolver();
  ~ElasticSolver();
  ElasticSolver(const ElasticSolver&) = delete;
  ElasticSolver& operator=(const ElasticSolver&) = delete;

  /// Allocates the session's buffers for VOIs of up to `most` nodes along each axis (the
  /// unit press's only with params.stiffness) and makes the cell matrix for the patient's
  /// spacing.
  void bind(const Patient& p, const deform::ElasticParams& params, const Vec3i& most);
  /// Frees the device buffers.
  void release();
  /// Forgets the field and the unit press (DeformBackend::reset): the next step starts from rest.
  void forget();

  /// Enqueues one elastic step on `stream` (relax_elastic_cpu()'s, with the patient's
  /// device copies in `patient`): the set-up when the VOI moved (the last field and contact
  /// set carried over), the contact rounds, the force, the unit press when asked, and u in
  /// voxels into `out` (VOI-local, component c at out[c]); the kernels' counts into `result`
  /// (device). `skin_vox`, `tip_vox`: X and x as continuous patient voxel indices.
  void enqueue(const Patient& p, const ElasticPatient& patient, const deform::Voi& voi, const Vec3& skin_vox,
               const Vec3& tip_vox, ElasticScratch& scratch, int blocks, float* const out[3],
               ElasticCounters* result, cudaStream_t stream);
  /// The step's run from the counts `c` read back after the stream finished; keeps what the
  /// next step starts from (as relax_elastic_cpu() does).
  deform::ElasticRun finish(const ElasticCounters& c);

  /// Device bytes the session holds.
  std::size_t bytes() const;
  /// Nodes of the largest VOI and of its coarse levels (the scratch's capacities).
  long long capacity() const { return capacity_; }
  long long coarse_capacity() const { return coarse_capacity_; }
  bool bound() const { return capacity_ > 0; }

 private:
  deform::ElasticParams params_;
  // the cell matrix for E = 1 kPa at level 0 as the kernels take it: corner 0's row block
  // (deform::ElasticCellBase; the rest by its mirror symmetry)
  std::array<float, 72> k_{};
  long long capacity_ = 0, coarse_capacity_ = 0;
  // session's own device buffers: the field and the unit press (mm, component c at c times
  // capacity), every level's flags and cell moduli (level l >= 1 at capacity + its plan
  // offset), every level's largest eigenvalue of D^-1 K, level 0's tiles the gathers take
  float* u_ = nullptr;
  float* u_unit_ = nullptr;
  float* react_ = nullptr;  // the last reactions at the contact nodes (View::react; with the unit press)
  std::uint8_t* flags_ = nullptr;
  float* cell_e_ = nullptr;
  float* lmax_ = nullptr;
  int* tiles_ = nullptr;      // level 0's tiles with a node that is not held (the set-up's list and marks)
  std::size_t tile_ints_ = 0;  // the ints tiles_ holds
  // the host's record (ElasticCpu's): the VOI the buffers are set up for, the field's and
  // the unit press's validity, the unit press's normal
  deform::Voi voi_;
  bool set_up_ = false;
  bool have_u_ = false;
  bool have_unit_ = false;
  Vec3f unit_normal_{0, 0, 0};
  deform::ElasticLastPress last_press_;  // the last step's press, for the warm start's prediction
  deform::ElasticSuperposeState superpose_;  // what a superposed step adds to (ElasticCpu's)
  // what the enqueued step's run has from the host
  deform::ElasticRun pending_;
  Vec3f pending_normal_{0, 0, 0};
  float pending_factor_ = 0;  // the enqueued step's prediction factor (mm along n for kUnit)
  std::unique_ptr<ElasticTrace> trace_;  // only with PALPSIM_ELASTIC_TRACE set (a measurement)
};

/// Cooperative blocks of the elastic kernels that run at once on this device (one per multiprocessor).
int relax_elastic_blocks();

/// How many of a batch's elastic solves run side by side (each on its own stream and lane
/// scratch, with that share of relax_elastic_blocks()): PALPSIM_ELASTIC_LANES (1 to 8),
/// else kElasticLanes. Two lanes overlap one solve's grid barriers and light passes with
/// another's (the phantom scene's server bench on the H100, 16 sessions: 95 steps/s each
/// in one lane, 117 in two or four, 111 in eight;
/// bench/results/elastic-server-probes-2026-12-06-h100-d9e7903.txt), for one more scratch
/// server-wide.
constexpr int kElasticLanes = 2;
int relax_elastic_lanes();

}  // namespace palpsim::cuda
