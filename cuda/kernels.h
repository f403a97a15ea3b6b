// The CUDA kernels' arguments and launchers (chainmail.cu, relax.cu, untangle.cu, invert.cu).
// Buffers are VOI-local structure-of-arrays: u[b][c] is component c (x, y, z) of
// displacement buffer b, local index i fastest; the patient volumes are whole.
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

#include "deform/deform_math.h"
#include "deform/relax_multigrid.h"

namespace palpsim::cuda {

/// What bounds the cells the inversion's scatter must visit (invert.cu, scatter_cells):
/// the largest |u| per axis over the VOI and the box of the queued voxels, each kept
/// with atomicMax from zero (float bits order as unsigned for values >= 0).
struct ScatterBounds {
  unsigned int umax_bits[3];  // max |u_a| over the VOI's voxels (voxel), float bits
  unsigned int lo_flip[3];    // INT_MAX - the lowest queued voxel's coordinate (0: none queued)
  unsigned int hi_plus[3];    // the highest queued voxel's coordinate + 1 (0: none queued)
};

/// What the elastic step kernel leaves for the host (relax_elastic.cu); the rest of
/// deform::ElasticRun the host knows.
struct ElasticCounters {
  int contact;               // the sphere covered skin nodes
  int contact_nodes;         // contact nodes at the end
  int rounds;                // contact rounds run
  int settled;               // the last round changed no node's contact
  int iterations;            // CG steps over the rounds
  int converged;             // every solve reached the tolerance
  int stiffness_iterations;  // CG steps of the unit press
  int superposed;            // no solve: the last press plus the unit press times the tip's move (deform::elastic_superposes)
  double residual;              // the last round's relative residual
  double press_n;               // the finger's push along n, summed over the contact nodes (N)
  double stiffness_n_per_mm;    // the unit press's force along n (N/mm), when asked
  unsigned long long inverted;  // folded cells
};

/// Small results the kernels write on the device and the host reads once per step.
struct Counters {
  int sweep_moved[3];              // elements moved per sweep, by sweep % 3
  int sweeps;                      // sweeps run
  int converged;                   // 1 when a quiet sweep came within the cap
  unsigned long long moved_total;  // elements that moved at least once
  unsigned int residual_bits;      // max inversion residual (voxel) as float bits (>= 0)
  unsigned long long unresolved;   // voxels with a residual above deform::kInvertResolvedVox
  unsigned int change_bits;        // max |J - I| over finite J as float bits (>= 0)
  unsigned long long nonfinite;    // voxels whose J is NaN or Inf
  int untangle_folded[deform::kUntangleMaxRounds + 1];  // folded cells found by each round
  int untangle_rounds;             // rounds of sweeps run
  int untangle_sweeps;             // sweeps run over all rounds
  unsigned long long untangle_moved;  // elements untangling moved
  int untangle_changed[3];         // elements changed per sweep, by sweep % 3
  int untangle_box[6];             // lo and hi (VOI-local) of the elements untangling may move
  int untangle_reverted;           // 1: it ended with more folds and restored the relaxed field
  unsigned int search_queued;      // inversion: voxels Newton left to the cell search, queued (may pass the queue's capacity)
  unsigned int search_candidates;  // inversion: (cell, queued voxel) pairs the scatter found (may pass the list's capacity)
  ScatterBounds search_bounds;     // inversion: what bounds the scatter's cells (invert.cu)
  unsigned int search_scattered;   // inversion: queued voxels that took the scatter's pick (the rest walked the rings)
  int search_spill;                // inversion: 1 when the scatter gave up (a full list, a huge cell): every queued voxel takes the ring search
  int relax_solves;                // multigrid: scalar solves run (0: the unit response was reused)
  int relax_warm;                  // multigrid: 1 when the solve started from the last unit response
  ElasticCounters elastic;         // the elastic model's step (relax_method "elastic")
};

/// A voxel queued for the inversion's cell search (invert.cu): its VOI-local index,
/// Newton's answer, the search's centre, and what the scatter of cells found for it.
struct InvertQueued {
  unsigned long long key;  // the best cell so far: residual's float bits, ring, index in the ring (invert.cu, pick_key)
  int e;
  float px, py, pz;  // Newton's source (VOI-local voxel)
  float r;           // its residual (voxel)
  int mx, my, mz;    // the search's centre cell (deform::search_centre)
  int last_ring;     // the first ring with a source within deform::kInvertSearchVox; INT_MAX: none found
  float sx, sy, sz;  // the best cell's source
};

/// A cell whose deformed box holds a queued voxel (invert.cu's scatter), and its solve there.
struct InvertCandidate {
  int slot;          // the voxel's entry in the queue
  int ring, idx;     // the cell's ring around the voxel's search centre and its index in that ring
  int ox, oy, oz;    // the cell's lowest corner (VOI-local voxel)
  float rc;          // the cell's residual (voxel), once solved
  float px, py, pz;  // its source, once solved
};

/// Device pointers of one session's state.
struct DeviceBuffers {
  const float* intensity = nullptr;     // whole patient volume
  const std::uint8_t* bone = nullptr;   // whole patient volume
  float* u[2][3] = {{nullptr, nullptr, nullptr}, {nullptr, nullptr, nullptr}};
  int* stamp[2] = {nullptr, nullptr};   // last sweep an element moved, by sweep parity; -1 never
  float* j = nullptr;                   // J on the VOI
  float* relax_w = nullptr;             // explicit relaxation: relax_step x the material weight per element, 0 at the grabbed element
  std::uint8_t* cell_folded = nullptr;  // untangling: 1 where the cell with this lowest corner folds
  std::uint8_t* untangle_flags = nullptr;  // untangling: seed, moved and changes bits per element
  float* untangle_new[3] = {nullptr, nullptr, nullptr};  // untangling: a sweep's new displacements
  /// The inversion's search queue (invert.cu): voxels whose Newton steps ended above
  /// deform::kInvertSearchVox, searched afterwards by a warp each; only with deform.invert_search.
  InvertQueued* search_queue = nullptr;
  unsigned search_capacity = 0;         // entries search_queue holds; voxels beyond it are searched in place
  int* search_slot = nullptr;           // per VOI element: its entry in search_queue, -1 where not queued
  InvertCandidate* search_candidates = nullptr;  // the scatter's (cell, voxel) pairs
  unsigned candidate_capacity = 0;      // entries search_candidates holds
  Counters* counters = nullptr;
};

/// Device buffers of the multigrid relaxation (relax_multigrid.cu), allocated only when
/// the scene asks for it, scalar fields on the VOI: the solved field X (the unit response G
/// after a clean step), CG's residual r (two buffers, one written while the other is read),
/// preconditioned residual z, direction p (two buffers), A p (q), the V-cycle's residual and
/// the held mask; the coarse levels' correction, right-hand side, residual and node bytes
/// (deform::MultigridPlan::offset);
/// the dot sums; and what G was solved for.
struct MultigridBuffers {
  float *g = nullptr, *r[2] = {nullptr, nullptr}, *z = nullptr, *p[2] = {nullptr, nullptr}, *q = nullptr;
  float* g_last = nullptr;             // the last solve's field, a warm start's source (the host swaps it with g)
  std::uint8_t* held = nullptr;
  float* res = nullptr;                // the V-cycle's residual on level 0
  float *cx = nullptr, *cf = nullptr, *cres = nullptr;
  std::uint8_t* cheld = nullptr;      // coarse node bytes: held, cut links (deform::multigrid_cuts)
  double* dots = nullptr;             // 2 per step and solve (3 solves at most): r . z and p . q
  int* flags = nullptr;               // [0], [1]: a held element other than the grabbed one moved (by launch parity); [2]: the last solve's field holds G
  long long capacity = 0;             // VOI elements the VOI buffers hold
  long long coarse_capacity = 0;      // nodes the coarse buffers hold
  deform::MultigridCache cache;       // the host's record of the last launch's VOI, grabbed element and steps
  unsigned long long launches = 0;    // launches so far (picks the dirty flag)
  int warm_steps = 0;                 // the last launch's steps if its start was taken (DeformStats::relax_cycles)
};

/// Where a step works: the VOI, the patient grid size and the grabbed element.
struct StepGeometry {
  deform::Voi voi;
  Vec3i volume_size{0, 0, 0};
  Vec3i grabbed{0, 0, 0};  // VOI-local

  /// The patient volume's linear index of VOI-local voxel (i, j, k).
  PALPSIM_HD long long patient_index(int i, int j, int k) const {
    return ((long long)(voi.lo.z + k) * volume_size.y + (voi.lo.y + j)) * volume_size.x + (voi.lo.x + i);
  }
};

/// Sessions one batched launch steps at most (batch.cu): the batched ChainMail keeps a
/// few bytes per session in each block's shared memory and scans them in one warp.
constexpr int kMaxBatch = 64;

/// One session of a batched step (batch.cu): where it works, its buffers, where each
/// stage reads, and the pinned host copy of its counters that the batch fills.
struct BatchItem {
  StepGeometry geo;
  Vec3f u0{0, 0, 0};               // the grabbed element's displacement (voxel)
  int chainmail = 0;               // 1: ChainMail runs; 2: its start alone (skipped); 0: the grabbed element is in bone
  int relax_src = 0;               // displacement buffer the relaxation starts from
  /// Explicit relaxation steps the field had since this step's ChainMail (its extent:
  /// counters->sweeps plus these, deform::relax_reach); -1: unknown (set by hand,
  /// untangled), every element is relaxed.
  int relax_extra = 0;
  int invert_src = 0;              // displacement buffer the inversion reads
  /// Multigrid: the unit response a step that reuses it writes u = d G from, in the batch's
  /// one reuse launch (launch_multigrid_reuse_batch); nullptr: the step launches the solver.
  const float* mg_g = nullptr;
  float finger_r2 = 0;             // multigrid: the fingertip's radius squared (voxel^2; deform::finger_r2)
  unsigned reset_count = 0;        // elements the previous step left deformed (the reset zeroes them)
  DeviceBuffers b;
  Counters* host_counters = nullptr;  // pinned host memory, written by launch_gather_batch
};

#ifdef __CUDACC__
/// The undeformed state on the first n elements of one session's buffers (both
/// displacement fields zero, sweep stamps -1: never moved), element t0 and every
/// `stride`-th after it; the thread with t0 == 0 zeroes the counters too.
__device__ inline void reset_elements(unsigned n, const DeviceBuffers& b, unsigned t0, unsigned stride) {
  for (unsigned e = t0; e < n; e += stride) {
    for (int p = 0; p < 2; ++p) {
      b.u[p][0][e] = 0.0f;
      b.u[p][1][e] = 0.0f;
      b.u[p][2][e] = 0.0f;
      b.stamp[p][e] = -1;
    }
  }
  if (t0 == 0) *b.counters = Counters{};
}
#endif

/// Threads per block and blocks per multiprocessor of the persistent kernels.
constexpr int kPersistentThreads = 1024;
constexpr int kPersistentBlocksPerSm = 1;

/// Cooperative grid sizes of the persistent kernels on this device.
struct LaunchShape {
  int chainmail_blocks = 0;
  int relax_blocks = 0;
  int threads = kPersistentThreads;
};

/// Queries how many blocks of each persistent kernel fit on the device at once.
LaunchShape persistent_launch_shape();
/// Blocks of the relaxation kernel that fit on one multiprocessor at `threads` per block.
int relax_blocks_per_sm(int threads);

/// ChainMail's start alone, for a step that skips ChainMail (ChainMailStats::skipped):
/// the grabbed element gets `u0` in both buffers, the counters say converged after 0
/// sweeps. The buffers must be undeformed on the VOI.
void launch_chainmail_start(const StepGeometry& g, const Vec3f& u0, const DeviceBuffers& b, cudaStream_t stream);

/// ChainMail sweeps until a quiet sweep or `max_sweeps`, in one cooperative launch.
/// The grabbed element gets `u0`; the buffers must be undeformed on the VOI.
void launch_chainmail(const StepGeometry& g, const Vec3f& u0, const deform::ChainMailLimits& limits,
                      int max_sweeps, const DeviceBuffers& b, const LaunchShape& shape, cudaStream_t stream);

/// `iterations` relaxation steps starting from buffer `src`, in one cooperative
/// launch; the result is in buffer (src + iterations) & 1. `b.relax_w` must hold the VOI.
/// `extra`: BatchItem::relax_extra (the steps only touch the elements the field can reach).
void launch_relax(const StepGeometry& g, int src, int extra, int iterations, float step, float threshold, float width,
                  const DeviceBuffers& b, const LaunchShape& shape, cudaStream_t stream);

/// Blocks of the multigrid relaxation kernel that run at once on this device (one per SM).
int relax_multigrid_blocks();

/// `cycles` multigrid-preconditioned CG steps on displacement buffer `src`, in place, in
/// one cooperative launch of at most `max_blocks` blocks; `m` must hold the VOI's plan.
/// With `reuse`, a step with the last launch's VOI, grabbed element and steps whose held
/// elements other than the grabbed one are at rest takes u = d G from the kept unit response,
/// and another VOI or grabbed element starts G from the kept one (deform::MultigridStart)
/// and runs `warm_cycles` steps (when above 0). With `prime` (DeformBackend::prime) it
/// solves G for `g` alone, as a clean step would, and keeps it: the displacement buffers
/// and the step counters are not touched (`src` is unused); the caller skips the launch
/// when `m` holds that G already. Returns whether the solve starts from the kept field
/// (the device takes it where that field is a G).
bool launch_relax_multigrid(const StepGeometry& g, int src, int cycles, int warm_cycles, float threshold, float width,
                            float finger_r2, bool reuse, const DeviceBuffers& b, MultigridBuffers& m, int max_blocks,
                            cudaStream_t stream, bool prime = false);
/// Untangles displacement buffer `cur` in place (server/deform/untangle.cpp's rounds and
/// sweeps; the other buffer keeps the relaxed field), in one cooperative launch; counts
/// in counters.
void launch_untangle(const StepGeometry& g, int cur, const DeviceBuffers& b, const LaunchShape& shape,
                     cudaStream_t stream);

/// J on the VOI from displacement buffer `src`; the max residual goes to counters.
void launch_invert(const StepGeometry& g, int src, int iterations, bool search, const DeviceBuffers& b,
                   cudaStream_t stream);

// ---- batched stages (batch.cu): `items` is a device array of n <= kMaxBatch sessions
// with the same settings; each session's results equal its own launches' to the bit.

/// The undeformed state on each session's reset_count elements, and zero counters.
void launch_reset_batch(const BatchItem* items, int n, unsigned max_reset, cudaStream_t stream);
/// ChainMail of every session with `chainmail` set, in one cooperative launch that
/// sweeps until each has converged or `max_sweeps`.
void launch_chainmail_batch(const BatchItem* items, int n, const deform::ChainMailLimits& limits, int max_sweeps,
                            const LaunchShape& shape, cudaStream_t stream);
/// `iterations` relaxation steps of every session from its relax_src, in one cooperative
/// launch; `most` is the largest VOI size along each axis.
void launch_relax_batch(const BatchItem* items, int n, const Vec3i& most, int iterations, float step, float threshold,
                        float width, const LaunchShape& shape, cudaStream_t stream);
/// J of every session from its invert_src, in one launch.
void launch_invert_batch(const BatchItem* items, int n, unsigned max_count, int iterations, bool search,
                         cudaStream_t stream);
/// Whether a multigrid launch for `g` with `cycles` steps would reuse the unit response
/// the buffers keep (the host's half of relax_multigrid.cu's test; the device also needs
/// the kept field to be a G, which the caller vouches for).
bool multigrid_reuses(const StepGeometry& g, int cycles, bool reuse, const MultigridBuffers& m);
/// u = d G on every free element (and d on the fingertip's) of each session whose item has
/// mg_g set, and its counters' solves and warm start to 0, in one launch: what
/// relax_multigrid.cu does for a reused G, the same bits, for steps whose elements held at
/// rest are at rest (ChainMail left out: ChainMailStats::skipped).
void launch_multigrid_reuse_batch(const BatchItem* items, int n, unsigned max_count, float threshold, float width,
                                  cudaStream_t stream);
/// Copies every session's counters to its host_counters, in one launch.
void launch_gather_batch(const BatchItem* items, int n, cudaStream_t stream);

}  // namespace palpsim::cuda
