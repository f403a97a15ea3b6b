// The elastic model on the GPU (deform.relax_method "elastic"): relax_elastic_cpu()'s step,
// the same passes in the same order (server/deform/relax_elastic.cpp; elastic_math.h says
// what is solved), in two persistent cooperative kernels with grid.sync() between passes
// and every decision taken on the device, so that a step costs no host wait but its end:
// - the set-up (a new VOI): node moduli, static flags, cell moduli of every level, each
//   level's lmax of D^-1 K by Lanczos steps (all levels in the same passes), and the last
//   field and contact set carried onto the new VOI;
// - the step: the sphere's contact set, the contact rounds (conjugate gradients
//   preconditioned by a V-cycle with Chebyshev smoothing; tension releases, penetration
//   joins), the force, the unit press, u in voxels and the folded cells.
// Every pass covers a level's nodes with the whole grid; coarse levels of at most
// kBlockNodes nodes run in block 0 alone between __syncthreads(), since a grid-wide pass
// costs a grid barrier whatever its size. Level 0 takes a thread a node in tiles of a block's nodes held in shared memory
// with their neighbours (elastic_apply_interior_once: 576 multiply-adds, every load one register
// and a constant apart; held nodes skipped, tiles all held left out); coarse levels of
// at least kTileNodes nodes in the same tiles; smaller coarse levels eight lanes a node,
// one cell each (elastic_add_cell), summed by shuffles, so that a small level's pass
// waits for one cell's products rather than a node's. The cell matrix
// is a kernel argument (__grid_constant__): every thread of a warp reads the same entry, as
// from constant memory, and two sessions with different matrices cannot overwrite each
// other's. The inverse diagonals are computed where they are needed (eight moduli) rather
// than kept. Dot products are double, summed by blocks and atomics into slots of a ring
// that every thread reads after the barrier. Float sums run in another order than the
// CPU's (and with fused multiply-adds), so fields agree to rounding, not to the bit.
#include "cuda/relax_elastic.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <vector>

#include "cuda/elastic_device.cuh"
#include "cuda/elastic_setup.cuh"
#include "cuda/elastic_step.cuh"

namespace palpsim::cuda {

namespace {

// a kernel's arguments within the 4 KB every CUDA version passes (the cell matrix is 2.3 KB)
static_assert(sizeof(StepArgs) <= 4096 && sizeof(SetupArgs) <= 4096, "kernel arguments above 4 KB");

// the cooperative launch of `kernel` with `args` on `blocks` blocks (at most what the VOI's
// level 0 needs, at least one)
template <typename Args>
void launch(void (*kernel)(Args), Args& args, int blocks, long long nodes, cudaStream_t stream) {
  const int need = int(std::max<long long>(1, (nodes + kThreads - 1) / kThreads));
  void* p[] = {&args};
  PALPSIM_CUDA_CHECK(cudaLaunchCooperativeKernel((const void*)kernel, dim3(std::max(1, std::min(blocks, need))),
                                                 dim3(kThreads), p, 0, stream));
}

// the positive integer in environment variable `name`, else `fallback`
int env_positive(const char* name, int fallback) {
  const char* s = std::getenv(name);
  const int v = s ? std::atoi(s) : 0;
  return v > 0 ? v : fallback;
}

// blocks of the elastic kernels per multiprocessor: 1 (a thread may use 128 registers) or 2
// (64 registers a thread, the rest spilled to local memory, twice the warps to hide
// latency, twice the blocks at each grid barrier); PALPSIM_ELASTIC_BLOCKS_PER_SM=2 picks 2
// for a measurement (palpsim-bench deform --elastic)
int elastic_blocks_per_sm() {
  static const int n = env_positive("PALPSIM_ELASTIC_BLOCKS_PER_SM", 1) == 2 ? 2 : 1;
  return n;
}

// coarse levels of at most this many nodes run in block 0 alone: kBlockNodes, or
// PALPSIM_ELASTIC_BLOCK_NODES for a measurement
int elastic_block_nodes() {
  static const int n = env_positive("PALPSIM_ELASTIC_BLOCK_NODES", kBlockNodes);
  return n;
}

// coarse levels of at least this many nodes on the grid take level 0's tiles in the
// gathers: kTileNodes, or PALPSIM_ELASTIC_TILE_NODES for a measurement
int elastic_tile_nodes() {
  static const int n = env_positive("PALPSIM_ELASTIC_TILE_NODES", kTileNodes);
  return n;
}

// the cooperative launch of the kernel instantiated for elastic_blocks_per_sm()
template <typename Args>
void launch_chosen(void (*one)(Args), void (*two)(Args), Args& args, int blocks, long long nodes,
                   cudaStream_t stream) {
  launch(elastic_blocks_per_sm() == 2 ? two : one, args, blocks, nodes, stream);
}

// what a traced pass is called (TracePass)
const char* pass_name(int pass) {
  static const char* const names[] = {"?",           "start",        "smooth down",     "residual",
                                      "restrict",    "block 0's levels", "correct",     "smooth up",
                                      "CG direction", "CG apply",     "CG update",       "V-cycle's last",
                                      "solve start", "contact",      "field",
                                      "nodes",       "cells",        "coarse cells",    "Lanczos step",
                                      "carry",       "shift",        "solve flags"};
  return pass >= 0 && pass < int(sizeof(names) / sizeof(names[0])) ? names[pass] : "?";
}

}  // namespace

// PALPSIM_ELASTIC_TRACE=1, a measurement: each step's kernels note when each pass ended on
// block 0's clock (a grid pass's time is its slowest block's and the barrier's), and the
// solver prints on release where its steps spent their time, per kind of pass and level
class ElasticTrace {
 public:
  static constexpr int kPairs = 8192;  // (pass, ns) pairs a kernel run may note
  ElasticTrace() { PALPSIM_CUDA_CHECK(cudaMalloc(&dev_, kBytes)); }
  ~ElasticTrace() {
    print();
    cudaFree(dev_);
  }
  ElasticTrace(const ElasticTrace&) = delete;
  ElasticTrace& operator=(const ElasticTrace&) = delete;
  unsigned long long* setup() { return dev_; }
  unsigned long long* step() { return dev_ + 2 * kPairs; }
  // before a step's launches (on its stream)
  void clear(cudaStream_t stream, bool setup) {
    PALPSIM_CUDA_CHECK(cudaMemsetAsync(dev_, 0, kBytes, stream));
    setup_ran_ = setup;
  }
  // after the step's stream finished: its intervals into the sums
  void collect() {
    std::vector<unsigned long long> h(4 * kPairs);
    PALPSIM_CUDA_CHECK(cudaMemcpy(h.data(), dev_, kBytes, cudaMemcpyDeviceToHost));
    const unsigned long long setup_end = setup_ran_ ? add(h.data(), setup_) : 0;
    const unsigned long long* st = h.data() + 2 * kPairs;
    if (setup_end && st[1]) gap_ns_ += double(st[1] - setup_end);
    add(st, step_);
    ++steps_;
    setups_ += setup_ran_;
  }

 private:
  static constexpr std::size_t kBytes = 4 * std::size_t(kPairs) * sizeof(unsigned long long);
  struct Sum {
    long long passes = 0;
    double ns = 0;
  };
  // one kernel run's intervals by tag (the first stamp opens them); the last stamp's time
  static unsigned long long add(const unsigned long long* t, std::map<int, Sum>& into) {
    int n = 0;
    while (n < kPairs && t[2 * n + 1] != 0) ++n;
    for (int i = 1; i < n; ++i) {
      Sum& s = into[int(t[2 * i])];
      ++s.passes;
      s.ns += double(t[2 * i + 1] - t[2 * i - 1]);
    }
    Sum& whole = into[-1];
    ++whole.passes;
    if (n > 1) whole.ns += double(t[2 * n - 1] - t[1]);
    return n ? t[2 * n - 1] : 0;
  }
  void table(const char* kernel, const std::map<int, Sum>& sums, long long runs) const {
    if (runs == 0) return;
    std::vector<std::pair<int, Sum>> rows(sums.begin(), sums.end());
    std::sort(rows.begin(), rows.end(), [](const auto& a, const auto& b) { return a.second.ns > b.second.ns; });
    for (const auto& [tag, s] : rows) {
      const double per_step = s.ns / 1e3 / double(steps_);
      if (tag < 0)
        std::fprintf(stderr, "  %-6s whole run (first to last barrier) %9.1f us a step, %lld runs\n", kernel, per_step,
                     runs);
      else
        std::fprintf(stderr, "  %-6s %-17s level %d %7.1f passes %9.1f us a step %7.2f us a pass\n", kernel,
                     pass_name(tag / 16), tag % 16, double(s.passes) / double(steps_), per_step,
                     s.ns / 1e3 / double(s.passes));
    }
  }
  void print() const {
    if (steps_ == 0) return;
    std::fprintf(stderr, "elastic trace over %lld steps (%lld set-ups; block 0's clock):\n", steps_, setups_);
    table("setup", setup_, setups_);
    if (setups_) std::fprintf(stderr, "  set-up's end to the step's first barrier %.1f us a step\n", gap_ns_ / 1e3 / double(steps_));
    table("step", step_, steps_);
  }
  unsigned long long* dev_ = nullptr;
  bool setup_ran_ = false;
  std::map<int, Sum> setup_, step_;
  long long steps_ = 0, setups_ = 0;
  double gap_ns_ = 0;
};

int relax_elastic_blocks() {
  int dev = 0, sms = 0, per_sm_step = 0, per_sm_setup = 0;
  const int per_sm = elastic_blocks_per_sm();
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev));
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(
      &per_sm_step, per_sm == 2 ? elastic_step_kernel<2> : elastic_step_kernel<1>, kThreads, 0));
  PALPSIM_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(
      &per_sm_setup, per_sm == 2 ? elastic_setup_kernel<2> : elastic_setup_kernel<1>, kThreads, 0));
  // blocks a multiprocessor as chosen (the other persistent kernels take 1): a grid barrier
  // costs about one atomic per block
  const int blocks = sms * std::min({per_sm_step, per_sm_setup, per_sm});
  if (blocks < 1) throw Error("CUDA: the elastic kernels do not fit on the device");
  return blocks;
}

ElasticScratch::ElasticScratch(long long n, long long nc) : capacity(n), coarse_capacity(nc) {
  PALPSIM_CUDA_CHECK(cudaGetDevice(&device));
  const std::size_t total = std::size_t(n + nc);
  try {
    for (float** v : {&x[0], &x[1], &f, &res, &d}) PALPSIM_CUDA_CHECK(cudaMalloc(v, 3 * total * sizeof(float)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&p, 3 * std::size_t(n) * sizeof(float)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&tmp_flags, std::size_t(n)));
    // every slot clear, the ring's next slot 0, done before any step's kernel can run: the
    // steps' streams do not wait for the legacy default stream's fill, so it is waited for
    PALPSIM_CUDA_CHECK(cudaMalloc(&sums, kSumsEntries * sizeof(double)));
    PALPSIM_CUDA_CHECK(cudaMemset(sums, 0, kSumsEntries * sizeof(double)));
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(0));
    PALPSIM_CUDA_CHECK(cudaEventCreateWithFlags(&done, cudaEventDisableTiming));
  } catch (...) {
    for (void* v : {(void*)x[0], (void*)x[1], (void*)f, (void*)res, (void*)d, (void*)p, (void*)tmp_flags, (void*)sums})
      cudaFree(v);
    throw;
  }
}

ElasticScratch::~ElasticScratch() {
  // errors are ignored here: a destructor must not throw
  if (done) cudaEventDestroy(done);
  for (void* v : {(void*)x[0], (void*)x[1], (void*)f, (void*)res, (void*)d, (void*)p, (void*)tmp_flags, (void*)sums})
    cudaFree(v);
}

std::shared_ptr<ElasticScratch> ElasticScratch::shared(long long n, long long nc, int lane) {
  static SharedCache<ElasticScratch> scratches;
  int dev = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  return scratches.get(
      [&](const ElasticScratch& s) {
        return s.device == dev && s.capacity == n && s.coarse_capacity == nc && s.lane == lane;
      },
      [&] {
        auto s = std::make_shared<ElasticScratch>(n, nc);
        s->lane = lane;
        return s;
      });
}

int relax_elastic_lanes() {
  static const int n = std::min(8, env_positive("PALPSIM_ELASTIC_LANES", kElasticLanes));
  return n;
}

std::size_t ElasticScratch::bytes() const {
  return 15 * std::size_t(capacity + coarse_capacity) * sizeof(float) + 3 * std::size_t(capacity) * sizeof(float) +
         std::size_t(capacity) + kSumsEntries * sizeof(double);
}

ElasticSolver::ElasticSolver() = default;
ElasticSolver::~ElasticSolver() { release(); }

void ElasticSolver::release() {
  trace_.reset();
  // errors are ignored here: it runs from destructors
  for (void* q : {(void*)u_, (void*)u_unit_, (void*)react_, (void*)flags_, (void*)cell_e_, (void*)lmax_, (void*)tiles_})
    cudaFree(q);
  u_ = u_unit_ = react_ = cell_e_ = lmax_ = nullptr;
  flags_ = nullptr;
  tiles_ = nullptr;
  tile_ints_ = 0;
  capacity_ = coarse_capacity_ = 0;
  set_up_ = have_u_ = have_unit_ = false;
  voi_ = Voi{};
}

void ElasticSolver::bind(const Patient& p, const deform::ElasticParams& params, const Vec3i& most) {
  release();
  params_ = params;
  k_ = deform::elastic_element_base(deform::elastic_element(p.grid.spacing_mm, params.poisson));
  const long long n = (long long)most.x * most.y * most.z;
  const long long nc = std::max(1LL, deform::elastic_plan(most).coarse_count);
  if (n + nc >= (1LL << 31))
    throw Error("deform backend \"cuda\": an elastic VOI of " + std::to_string(n) +
                " nodes and its coarse levels are too large (the kernels index them with 32 bits; use a smaller "
                "deform.voi_edge)");
  const std::size_t total = std::size_t(n + nc);
  try {
    PALPSIM_CUDA_CHECK(cudaMalloc(&u_, 3 * std::size_t(n) * sizeof(float)));
    if (params.stiffness) {
      PALPSIM_CUDA_CHECK(cudaMalloc(&u_unit_, 3 * std::size_t(n) * sizeof(float)));
      PALPSIM_CUDA_CHECK(cudaMalloc(&react_, 2 * std::size_t(n) * sizeof(float)));
    }
    PALPSIM_CUDA_CHECK(cudaMalloc(&flags_, total));
    PALPSIM_CUDA_CHECK(cudaMalloc(&cell_e_, total * sizeof(float)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&lmax_, kElasticMaxLevels * sizeof(float)));
    // level 0's tiles: the list and the marks (list_tiles)
    const long long tiles = (long long)((most.x + kTileX - 1) / kTileX) * ((most.y + kTileY - 1) / kTileY) *
                            ((most.z + kTileZ - 1) / kTileZ);
    tile_ints_ = std::size_t(1 + 2 * tiles);
    PALPSIM_CUDA_CHECK(cudaMalloc(&tiles_, tile_ints_ * sizeof(int)));
  } catch (...) {
    release();
    throw;
  }
  capacity_ = n;
  coarse_capacity_ = nc;
  if (env_positive("PALPSIM_ELASTIC_TRACE", 0) > 0) trace_ = std::make_unique<ElasticTrace>();
}

void ElasticSolver::forget() {
  have_u_ = false;
  have_unit_ = false;
}

std::size_t ElasticSolver::bytes() const {
  if (!bound()) return 0;
  const std::size_t n = std::size_t(capacity_), total = std::size_t(capacity_ + coarse_capacity_);
  return (u_unit_ ? 8 : 3) * n * sizeof(float) + total * (1 + sizeof(float)) + kElasticMaxLevels * sizeof(float) +
         tile_ints_ * sizeof(int);
}

void ElasticSolver::enqueue(const Patient& pat, const ElasticPatient& patient, const Voi& voi, const Vec3& skin_vox,
                            const Vec3& tip_vox, ElasticScratch& scratch, int blocks, float* const out[3],
                            ElasticCounters* result, cudaStream_t stream) {
  if (!bound()) throw Error("deform backend \"cuda\": the elastic model's buffers are missing (bind() not run for it)");
  // the every-level arrays of the session and of the scratch share one layout (level l >= 1
  // after the capacity): the scratch must be made for the session's capacities
  const ElasticPlan plan = deform::elastic_plan(voi.size);
  if (voi.count() > capacity_ || plan.coarse_count > coarse_capacity_)
    throw Error("deform backend \"cuda\": the elastic buffers are smaller than this VOI needs");
  if (scratch.capacity != capacity_ || scratch.coarse_capacity != coarse_capacity_)
    throw Error("deform backend \"cuda\": the elastic scratch was made for another VOI size");
  const Vec3 h = pat.grid.spacing_mm;
  View view{};
  view.u = u_;
  view.u_unit = u_unit_;
  view.react = react_;
  view.flags = flags_;
  view.cell_e = cell_e_;
  view.lmax = lmax_;
  view.x[0] = scratch.x[0];
  view.x[1] = scratch.x[1];
  view.f = scratch.f;
  view.res = scratch.res;
  view.d = scratch.d;
  view.p = scratch.p;
  view.tmp_flags = scratch.tmp_flags;
  view.tiles = tiles_;
  view.sums = scratch.sums;
  view.capacity = scratch.capacity;
  view.total = scratch.capacity + scratch.coarse_capacity;

  // warm start (relax_elastic_cpu()): the last field and contact set, carried onto this VOI
  // by the set-up when the VOI moved; from rest when there is none (elastic_warm; the model
  // is fixed at bind, so a kept field is always of the same model)
  const bool had = deform::elastic_warm(have_u_, last_press_.pressing, voi_, voi);
  pending_ = deform::ElasticRun{};
  pending_.warm = had;
  const ElasticScratch::Turn turn(scratch, stream);
  const bool setup = !set_up_ || !(voi == voi_);
  if (trace_) trace_->clear(stream, setup);
  if (setup) {
    SetupArgs s;
    std::copy(k_.begin(), k_.end(), s.k);
    s.plan = plan;
    s.v = view;
    s.voi = voi;
    s.last = set_up_ ? voi_ : Voi{};
    s.grid = pat.grid.size;
    s.material = params_.material;
    s.patient = patient;
    s.had = had && set_up_;
    s.tile_nodes = elastic_tile_nodes();
    s.trace = trace_ ? trace_->setup() : nullptr;
    s.trace_pairs = ElasticTrace::kPairs;
    launch_chosen(elastic_setup_kernel<1>, elastic_setup_kernel<2>, s, blocks, voi.count(), stream);
    voi_ = voi;
    set_up_ = true;
    have_unit_ = false;
  } else if (!had) {
    have_unit_ = false;
  }
  // the press: n from X to x (mm along the grid axes), the sphere's centre R behind the tip
  const Vec3 d_mm{(tip_vox.x - skin_vox.x) * h.x, (tip_vox.y - skin_vox.y) * h.y, (tip_vox.z - skin_vox.z) * h.z};
  const double depth = deform::elastic_tip_inside(pat, tip_vox) ? norm(d_mm) : 0.0;
  const Vec3f nrm = depth > 1e-6 ? Vec3f{float(d_mm.x / depth), float(d_mm.y / depth), float(d_mm.z / depth)}
                                 : Vec3f{0, 0, 0};
  const float radius = params_.finger_radius_mm;
  const Vec3f tip_local{float((tip_vox.x - voi.lo.x) * h.x), float((tip_vox.y - voi.lo.y) * h.y),
                        float((tip_vox.z - voi.lo.z) * h.z)};
  pending_.depth_mm = depth;
  pending_.normal = Vec3(nrm);
  pending_normal_ = nrm;
  // the warm start's prediction of this press from the last one (elastic_prediction)
  const Vec3 tip_mm{tip_vox.x * h.x, tip_vox.y * h.y, tip_vox.z * h.z};
  const deform::ElasticPrediction pred = deform::elastic_prediction(
      last_press_, had && params_.predict, have_unit_ && u_unit_ != nullptr && dot(unit_normal_, nrm) > 0.999f, tip_mm, depth, nrm, h);
  pending_.prediction = pred.kind;
  last_press_ = deform::ElasticLastPress{depth > 1e-6, tip_mm, depth, nrm};

  StepArgs s;
  std::copy(k_.begin(), k_.end(), s.k);
  s.plan = plan;
  s.v = view;
  for (int c = 0; c < 3; ++c) {
    s.h[c] = h[c];
    s.out[c] = out[c];
  }
  s.nrm = nrm;
  s.centre = tip_local - nrm * radius;
  s.radius = radius;
  s.penetration = deform::kElasticPenetrationVox * float(h.x);
  s.pressing = depth > 1e-6;
  s.depth = float(depth);
  s.had = had;
  s.unit_warm = have_unit_ && unit_normal_ == nrm;
  s.unit_scale = deform::elastic_unit_start_scale(depth);
  s.predict = int(pred.kind);
  s.predict_factor = pred.factor;
  s.shift_vox = pred.shift_vox;
  s.stiffness = params_.stiffness && u_unit_ != nullptr;
  // superposing, as far as the host can tell (the kernel adds that the set stays as it was)
  s.superpose = s.stiffness && have_unit_ && react_ != nullptr &&
                superpose_.allows(pred, dot(unit_normal_, nrm), depth, params_);
  s.last_push_n = superpose_.last_push_n;
  s.last_stiffness = superpose_.last_stiffness;
  s.last_residual = superpose_.last_residual;
  pending_factor_ = pred.factor;
  s.max_iterations = params_.max_iterations;
  s.tolerance = params_.tolerance;
  s.reciprocal = params_.stiffness_tolerance > 0;
  s.stiffness_tolerance = params_.stiffness_tolerance;
  s.contact_rounds = params_.contact_rounds;
  s.degrees = params_.degrees;
  s.block_nodes = elastic_block_nodes();
  s.tile_nodes = elastic_tile_nodes();
  s.result = result;
  s.trace = trace_ ? trace_->step() : nullptr;
  s.trace_pairs = ElasticTrace::kPairs;
  launch_chosen(elastic_step_kernel<1>, elastic_step_kernel<2>, s, blocks, voi.count(), stream);
  have_u_ = true;
}

deform::ElasticRun ElasticSolver::finish(const ElasticCounters& c) {
  if (trace_) trace_->collect();
  deform::ElasticRun r = pending_;
  r.contact = c.contact != 0;
  r.contact_nodes = c.contact_nodes;
  r.rounds = c.rounds;
  r.contact_settled = c.settled != 0;
  r.iterations = c.iterations;
  r.residual = c.residual;
  r.converged = c.converged != 0;
  r.force_n = r.normal * -c.press_n;
  r.stiffness_n_per_mm = c.stiffness_n_per_mm;
  r.stiffness_iterations = c.stiffness_iterations;
  r.inverted_cells = (long long)c.inverted;
  r.superposed = c.superposed != 0;
  // what the next step starts from: the unit press holds this contact set's (along this n;
  // a superposed step kept the set and the unit press as they were)
  if (!r.contact) {
    have_unit_ = false;
  } else if (!r.superposed && params_.stiffness && r.contact_nodes > 0) {
    have_unit_ = true;
    unit_normal_ = pending_normal_;
  }
  superpose_.after(r, pending_factor_);
  return r;
}

}  // namespace palpsim::cuda
