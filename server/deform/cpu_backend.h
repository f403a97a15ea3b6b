// The CPU reference backend ("cpu"): the readable statement of every deformation
// kernel, against which the CUDA backend is tested. The kernels themselves are free
// functions in chainmail.cpp, relax.cpp and invert.cpp.
#pragma once

#include <cstdint>
#include <vector>

#include "deform/backend.h"
#include "deform/invert_scatter.h"
#include "deform/relax_multigrid.h"

namespace palpsim {

namespace deform {

/// The CPU state of one session: VOI-local buffers (local index i fastest) sized
/// for the largest VOI, so a step allocates nothing once they have grown.
struct CpuState {
  std::vector<Vec3f> u;          // displacement of each element (voxel)
  std::vector<Vec3f> u_next;     // relaxation's second buffer
  std::vector<float> weight;     // relax_step * material function, per element
  std::vector<int> moved_at;     // last sweep in which the element moved; -1: never
  std::vector<int> visited_at;   // last sweep that examined the element; -1: never
  std::vector<float> j;          // the deformed image J on the VOI
  /// How far (neighbour steps, L1) from the grabbed element the field can be nonzero:
  /// ChainMail's sweeps, plus the explicit relaxation's iterations since; -1: unknown (a
  /// field set by hand, untangled or relaxed by multigrid), every element may be.
  int reach = -1;
  std::vector<Vec3i> movers;     // elements that moved in the previous sweep (local index)
  std::vector<Vec3i> candidates; // their neighbours, examined in this sweep
  std::vector<std::pair<long long, Vec3f>> changes;  // this sweep's new positions, applied after it
  // multigrid relaxation (relax_multigrid.cpp), scalar fields on the VOI: held mask, the
  // solved field (the unit response G when mg_cache says so), CG's residual,
  // preconditioned residual, direction, A times direction and the V-cycle's residual; the
  // coarse levels' correction, right-hand side, residual and held mask (MultigridPlan::offset)
  std::vector<std::uint8_t> mg_held;
  std::vector<float> mg_g, mg_r, mg_z, mg_p, mg_q, mg_res;
  std::vector<float> mg_g_last;  // the unit response a warm start begins from (swapped with mg_g)
  std::vector<float> mg_cx, mg_cf, mg_cres;
  std::vector<std::uint8_t> mg_held_coarse;  // coarse node bytes: held, cut links (relax_multigrid.h)
  MultigridCache mg_cache;  // what mg_g holds
  std::vector<std::uint8_t> cell_folded;     // untangling: 1 where the cell with this lowest corner folds
  std::vector<std::uint8_t> untangle_flags;  // untangling: seed and moved bits per element
  std::vector<SearchVoxel> search_queue;     // inversion: voxels Newton left to the cell search
  std::vector<int> search_slot;              // inversion: each element's entry in search_queue, -1 where none
  ElasticCpu elastic;                        // the elastic model's solver (relax_elastic.h); empty unless a scene asks for it
};

/// ChainMail's start alone: the grabbed element at x (unless it lies in bone), no sweep;
/// for a step that skips ChainMail (ChainMailStats::skipped). The state must be
/// undeformed on the VOI.
void chainmail_grab_cpu(ChainMailStats& st, CpuState& s);

/// ChainMail by plain Jacobi sweeps (paper sec. 2.2): in sweep s every element next
/// to one that moved in sweep s-1 clamps itself, in the fixed neighbour order, into
/// the box allowed by each such neighbour, reading positions of sweep s-1, and counts
/// as moved when its position changed. Bone and the grabbed element never move.
/// `st` comes with voi, grabbed_vox, grabbed_u_vox and grabbed_in_bone set; the state
/// must be undeformed on the VOI.
void chainmail_cpu(const Patient& p, const ChainMailLimits& limits, int max_sweeps, ChainMailStats& st,
                   CpuState& s);

/// Diffusive relaxation of the VOI's displacement: `iterations` explicit steps
/// weighted by the material function; outside the VOI the tissue is undeformed (u = 0),
/// the grabbed element keeps its displacement and bone has weight 0. Each step updates
/// only the elements within relax_reach() of the grabbed element (the rest stay 0).
void relax_cpu(const Patient& p, const ChainMailStats& st, int iterations, float step, float threshold,
               float width, CpuState& s);

/// Multigrid relaxation of the VOI's displacement (deform.relax_method "multigrid"):
/// `cycles` V-cycles towards the explicit scheme's steady state (relax_multigrid.h),
/// the grabbed element (with the soft elements within sqrt(finger_r2) voxels of it, set
/// to its displacement: the fingertip) and elements of material weight 0 (bone) held,
/// u = 0 outside the VOI; the residual of the steady state falls by 3-10x per cycle. With `reuse`, a
/// step whose VOI, grabbed element and steps equal the last solved one's, and whose held
/// elements other than the grabbed one are at rest, takes u = d G from the cached unit
/// response G (the same bits as solving again), and a step with another VOI or grabbed
/// element starts G from the last one shifted onto its grabbed element and runs
/// `warm_cycles` steps, one more where the grabbed element moved far (when above 0;
/// MultigridStart, multigrid_warm_steps).
struct MultigridRun {
  int solves = 0;       // scalar solves run (DeformStats::relax_solves)
  bool warm = false;    // the solve started from the last G (DeformStats::relax_warm)
  int warm_steps = 0;   // its steps when warm (multigrid_warm_steps)
};
MultigridRun relax_multigrid_cpu(const Patient& p, const ChainMailStats& st, int cycles, int warm_cycles,
                                 float threshold, float width, float finger_r2, bool reuse, CpuState& s);

/// The unit response G for VOI `voi` and grabbed element `grabbed_vox` (patient voxels),
/// solved as relax_multigrid_cpu() would solve it on a clean step that reuses (from the
/// last G, or from zero in `cycles` steps) and kept in the cache, without touching the
/// displacement field: DeformBackend::prime(). Nothing is solved when the cache holds
/// that G already (solves 0).
MultigridRun prime_multigrid_cpu(const Patient& p, const Voi& voi, const Vec3i& grabbed_vox, int cycles,
                                 int warm_cycles, float threshold, float width, float finger_r2, CpuState& s);

/// Untangling of the VOI's displacement (DeformBackend::untangle): up to
/// kUntangleMaxRounds rounds of finding the folded cells and Jacobi sweeps from their
/// corners of untangle_pull() towards the neighbours towards the grabbed element, until
/// a quiet sweep or kUntangleMaxSweeps; bone and the grabbed element never move. Ending
/// with more folded cells than it found, it returns the field it got (kept in u_next).
UntangleStats untangle_cpu(const Patient& p, const ChainMailStats& st, CpuState& s);

/// J on the VOI by inverting the displacement (Newton steps, deform_math.h; trilinear
/// sampling of u and I); returns the largest residual |p + u(p) - y| (voxel) and
/// the count of voxels left unresolved.
InvertStats invert_cpu(const Patient& p, const Voi& voi, int iterations, bool search, CpuState& s);

}  // namespace deform

/// The "cpu" backend: the reference implementation.
class CpuDeformBackend final : public DeformBackend {
 public:
  CpuDeformBackend() : DeformBackend("cpu") {}

 protected:
  void bind_impl() override;
  void chainmail_impl(ChainMailStats& stats) override;
  void relax_impl() override;
  UntangleStats untangle_impl() override;
  InvertStats invert_impl() override;
  void upload_impl() override {}  // J is computed in host memory already
  void reset_impl() override;
  void forget_impl() override;
  DeformStats step_impl(const ChainMailStats& setup) override;
  DeformPrime prime_impl(const ChainMailStats& expected) override;
  const deform::MultigridCache* multigrid_cache_impl() const override { return &s_.mg_cache; }
  std::vector<Vec3f> displacement_impl() const override;
  void set_displacement_impl(const std::vector<Vec3f>& u) override;
  const float* deformed_brick_impl() const override { return s_.j.data(); }
  DeformMemory memory_impl() const override;

 private:
  // sizes u_next and weight for the largest VOI (bind() skips them without relaxation)
  void grow_relax_buffers();
  // sizes untangling's flags for the largest VOI (bind() skips them without untangling)
  void grow_untangle_buffers();

  deform::CpuState s_;
  deform::MultigridRun relax_run_;  // the last multigrid relaxation's solves and start
  deform::ElasticRun elastic_run_;  // the last elastic solve
  Voi dirty_;  // the VOI whose buffers hold a deformation
};

}  // namespace palpsim
