// The elastic model on the GPU (deform.relax_method "elastic"): relax_elastic_cpu()'s step,
// the same passes in the same order (server/deform/relax_elastic.cpp; elastic_math.h says
// what is solved), in two persistent cooperative kernels with grid.sync() between passes
// and every decision taken on the device, so that a step costs no host wait but its end:
// - the set-up (a new VOI): node moduli, static flags, cell moduli of every level, each
//   level's lmax of D^-1 K by power iteration (all levels in the same passes), and the last
//   field and contact set carried onto the new VOI;
// - the step: the sphere's contact set, the contact rounds (conjugate gradients
//   preconditioned by a V-cycle with Chebyshev smoothing; tension releases, penetration
//   joins), the force, the unit press, u in voxels and the folded cells.
// Every pass covers a level's nodes with the whole grid; coarse levels of at most
// kBlockNodes nodes run in block 0 alone between __syncthreads(), since a grid-wide pass
// costs a grid barrier (2.2-2.5 us at VOI 64 on the H100, relax_multigrid.cu) whatever its
// size. Level 0 takes a thread a node in tiles of a block's nodes held in shared memory
// with their neighbours (elastic_apply_interior: 576 multiply-adds, every load one register
// and a constant apart; held nodes skipped); the coarse
// levels eight lanes a node, one cell each (elastic_add_cell), summed by shuffles, so that
// a small level's pass waits for one cell's products rather than a node's. The cell matrix
// is a kernel argument (__grid_constant__): every thread of a warp reads the same entry, as
// from constant memory, and two sessions with different matrices cannot overwrite each
// other's. The inverse diagonals are computed where they are needed (eight moduli) rather
// than kept. Dot products are double, summed by blocks and atomics into slots of a ring
// that every thread reads after the barrier. Float sums run in another order than the
// CPU's (and with fused multiply-adds), so fields agree to rounding, not to the bit.
#include "cuda/relax_elastic.h"

#include <cooperative_groups.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <string>

#include "deform/deform_math.h"
#include "deform/elastic_math.h"

namespace cg = cooperative_groups;

namespace palpsim::cuda {

namespace {

using deform::ElasticMaterial;
using deform::ElasticPlan;
using deform::ElasticPredict;
using deform::kElasticContact;
using deform::kElasticHeld;
using deform::kElasticMaxDegree;
using deform::kElasticMaxLevels;
using deform::kElasticSkin;
using deform::Voi;

constexpr int kThreads = 512;      // threads per block of both kernels
constexpr int kBlockNodes = 512;   // coarse levels of at most this many nodes run in block 0 alone (the default)
constexpr int kSlot = 4;           // sums a reduction slot holds
constexpr int kRing = 32;          // the step's reduction slots, reused in turn
constexpr int kSetupSums = deform::kElasticPowerIterations * kElasticMaxLevels;  // the set-up's slots
constexpr int kSmooth = deform::kElasticSmoothDegree;
constexpr int kCoarsest = deform::kElasticCoarsestDegree;
static_assert(kSmooth >= 2 && kCoarsest >= 2 && kCoarsest <= kElasticMaxDegree && kSmooth <= kElasticMaxDegree,
              "the passes fuse each smoother's first step into the pass before it and need a second");

// the threads that share a pass: the whole grid, or block 0 alone
struct Team {
  int first, stride;
};

// one vector kind over a range of nodes: component c of node e at p[c * stride + e]
struct Field {
  float* p;
  long long stride;
  __device__ Vec3f at(int e) const { return Vec3f{p[e], p[stride + e], p[2 * stride + e]}; }
  __device__ void set(int e, const Vec3f& v) const {
    p[e] = v.x;
    p[stride + e] = v.y;
    p[2 * stride + e] = v.z;
  }
};

// one level: its nodes start at `off` in the every-level arrays; cell edge `scale` times level 0's
struct Lvl {
  Vec3i n;
  int off, count;
  float scale;
  bool coarse;
  __device__ int at(int i, int j, int k) const { return off + (k * n.y + j) * n.x + i; }
  __device__ void coords(int q, int& i, int& j, int& k) const {
    i = q % n.x;
    const int r = q / n.x;
    j = r % n.y;
    k = r / n.y;
  }
};

// the cell matrix (for E = 1 kPa at level 0) from the kernel's arguments
struct CellMatrix {
  const float* k;
  __device__ float operator()(int r, int c) const { return k[24 * r + c]; }
};

// a level's cell moduli (kPa) by lowest corner
struct CellModuli {
  const float* e;
  Lvl L;
  __device__ float operator()(int i, int j, int k) const { return e[L.at(i, j, k)]; }
};

// a field's node values on a level
struct Load {
  Field x;
  Lvl L;
  __device__ Vec3f operator()(int i, int j, int k) const { return x.at(L.at(i, j, k)); }
};

// the device arrays both kernels work on: the session's own and the scratch's
struct View {
  float* u;            // the field (mm), level 0, stride capacity
  float* u_unit;       // the unit press, likewise (null without the stiffness)
  std::uint8_t* flags; // every level
  float* cell_e;       // every level
  float* lmax;         // every level's largest eigenvalue of D^-1 K
  float* x[2];         // every level, stride total: the V-cycle's corrections
  float *f, *res, *d;  // every level: right-hand side, residual, Chebyshev step
  float* p;            // level 0, stride capacity: CG's direction
  std::uint8_t* tmp_flags;
  double* sums;
  long long capacity, total;
};

__device__ Field level0(float* p, const View& v) { return Field{p, v.capacity}; }
__device__ Field every(float* p, const View& v) { return Field{p, v.total}; }

// the levels of `plan` in the every-level arrays (level l >= 1 after the capacity)
__device__ void make_levels(const ElasticPlan& plan, long long capacity, Lvl* lv) {
  for (int l = 0; l < plan.levels; ++l) {
    const Vec3i n = plan.size[l];
    lv[l] = Lvl{n, l == 0 ? 0 : int(capacity + plan.offset[l]), n.x * n.y * n.z, float(1 << l), l > 0};
  }
}

__device__ Vec3f mul(const Vec3f& a, const Vec3f& b) { return Vec3f{a.x * b.x, a.y * b.y, a.z * b.z}; }
// the inverse Jacobi diagonal, 0 where the diagonal is not positive (no cell: held space)
__device__ Vec3f inverse(const Vec3f& d) {
  return Vec3f{d.x > 0 ? 1 / d.x : 0.0f, d.y > 0 ? 1 / d.y : 0.0f, d.z > 0 ? 1 / d.z : 0.0f};
}
// a . b summed in double, as the CPU's dot_all
__device__ double dot_d(const Vec3f& a, const Vec3f& b) {
  return double(a.x) * b.x + double(a.y) * b.y + double(a.z) * b.z;
}

// level 0's node tiles: kTile nodes along i, j and k, read with a layer of neighbours
// around them into shared memory (kHalo), the cells' moduli likewise
constexpr int kTileX = 32, kTileY = 4, kTileZ = 4;
static_assert(kTileX * kTileY * kTileZ == kThreads, "a tile holds a node per thread");
constexpr int kHaloX = kTileX + 2, kHaloY = kTileY + 2, kHaloZ = kTileZ + 2;
constexpr int kHalo = kHaloX * kHaloY * kHaloZ;

// one tile's shared memory for every gather of a kernel (one function, so one array: each
// instantiation of a template declaring it would have its own)
__device__ float* tile_memory() {
  __shared__ float t[4 * kHalo];
  return t;
}

// calls fn(e, i, j, k, kx, dg) for every node of level 0 (L), the whole grid taking a tile
// of kThreads nodes a block at a time: the tile's nodes and their neighbours' displacements
// x and the cells' moduli go to shared memory, then each thread sums its node's cells from
// there (elastic_apply_interior: every load one register and a constant apart). Held nodes
// get kx = dg = 0 (every caller projects them to 0); a free node on the level's faces
// (none: the VOI's faces are held) would take elastic_apply_node from global memory.
// Every thread of a block runs every tile of the block (the tile's barriers).
template <typename Fn>
__device__ void gather_tiles(const CellMatrix& km, const float* cell_e, const std::uint8_t* flags, const Lvl& L,
                             const Field& x, Fn& fn) {
  float* const tu = tile_memory();  // tu[c * kHalo + h]: component c at halo node h
  float* const te = tu + 3 * kHalo;
  const int tx = (L.n.x + kTileX - 1) / kTileX, ty = (L.n.y + kTileY - 1) / kTileY,
            tz = (L.n.z + kTileZ - 1) / kTileZ;
  const int tiles = tx * ty * tz;
  const int li = threadIdx.x % kTileX, lj = (threadIdx.x / kTileX) % kTileY, lk = threadIdx.x / (kTileX * kTileY);
  for (int tile = blockIdx.x; tile < tiles; tile += gridDim.x) {
    const int i0 = (tile % tx) * kTileX, j0 = ((tile / tx) % ty) * kTileY, k0 = (tile / (tx * ty)) * kTileZ;
    // the halo: nodes (i0 - 1 .. i0 + kTileX) etc., 0 outside the level; the cell at halo
    // position h has its lowest corner there (cells beyond the last node: 0)
    for (int h = threadIdx.x; h < kHalo; h += blockDim.x) {
      const int hi = h % kHaloX, hj = (h / kHaloX) % kHaloY, hk = h / (kHaloX * kHaloY);
      const int i = i0 - 1 + hi, j = j0 - 1 + hj, k = k0 - 1 + hk;
      const bool in = i >= 0 && j >= 0 && k >= 0 && i < L.n.x && j < L.n.y && k < L.n.z;
      const Vec3f u = in ? x.at(L.at(i, j, k)) : Vec3f{0, 0, 0};
      tu[h] = u.x;
      tu[kHalo + h] = u.y;
      tu[2 * kHalo + h] = u.z;
      te[h] = in && i + 1 < L.n.x && j + 1 < L.n.y && k + 1 < L.n.z ? cell_e[L.at(i, j, k)] : 0.0f;
    }
    __syncthreads();
    const int i = i0 + li, j = j0 + lj, k = k0 + lk;
    if (i < L.n.x && j < L.n.y && k < L.n.z) {
      const int e = L.at(i, j, k);
      Vec3f kx{0, 0, 0}, dg{0, 0, 0};
      if (!(flags[e] & kElasticHeld)) {
        if (i > 0 && j > 0 && k > 0 && i + 1 < L.n.x && j + 1 < L.n.y && k + 1 < L.n.z) {
          const int h = ((lk + 1) * kHaloY + lj + 1) * kHaloX + li + 1;
          deform::elastic_apply_interior(
              km, [&](int o) { return te[h + o]; },
              [&](int o) { return Vec3f{tu[h + o], tu[kHalo + h + o], tu[2 * kHalo + h + o]}; }, kHaloX, kHaloX * kHaloY,
              L.scale, kx, dg);
        } else {
          kx = deform::elastic_apply_node(km, CellModuli{cell_e, L}, Load{x, L}, L.n, L.scale, i, j, k);
          dg = deform::elastic_diag_node(km, CellModuli{cell_e, L}, L.n, L.scale, i, j, k);
        }
      }
      fn(e, i, j, k, kx, dg);
    }
    __syncthreads();
  }
}

// calls fn(e, i, j, k, kx, dg) for the nodes of level L that team t covers: kx = (K x) at
// the node (N), dg its Jacobi diagonal (N/mm). Level 0: a thread a node; a coarse level:
// eight lanes a node, lane a adding the cell in which the node is corner a, summed by
// shuffles (whole warps run each round, so that every lane takes part in them)
template <typename Fn>
__device__ void gather(const CellMatrix& km, const float* cell_e, const std::uint8_t* flags, const Lvl& L, Team t,
                       const Field& x, Fn&& fn) {
  const CellModuli ce{cell_e, L};
  const Load load{x, L};
  if (!L.coarse) {
    gather_tiles(km, cell_e, flags, L, x, fn);
    return;
  }
  const int lane = threadIdx.x & 31;
  const int tasks = 8 * L.count;
  for (int t0 = t.first - lane; t0 < tasks; t0 += t.stride) {
    const int q = t0 + lane, node = q >> 3, a = q & 7;
    const bool mine = q < tasks;
    int i = 0, j = 0, k = 0;
    Vec3f kx{0, 0, 0}, dg{0, 0, 0};
    if (mine) {
      L.coords(node, i, j, k);
      deform::elastic_add_cell(km, ce, load, L.n, L.scale, i, j, k, a, kx);
      deform::elastic_add_cell_diag(km, ce, L.n, L.scale, i, j, k, a, dg);
    }
    for (int o = 1; o < 8; o <<= 1) {
      kx.x += __shfl_xor_sync(0xffffffffu, kx.x, o, 8);
      kx.y += __shfl_xor_sync(0xffffffffu, kx.y, o, 8);
      kx.z += __shfl_xor_sync(0xffffffffu, kx.z, o, 8);
      dg.x += __shfl_xor_sync(0xffffffffu, dg.x, o, 8);
      dg.y += __shfl_xor_sync(0xffffffffu, dg.y, o, 8);
      dg.z += __shfl_xor_sync(0xffffffffu, dg.z, o, 8);
    }
    if (mine && a == 0) fn(L.off + node, i, j, k, kx, dg);
  }
}

// the node's Jacobi diagonal alone (a thread a node)
__device__ Vec3f diag_at(const CellMatrix& km, const float* cell_e, const Lvl& L, int i, int j, int k) {
  return deform::elastic_diag_node(km, CellModuli{cell_e, L}, L.n, L.scale, i, j, k);
}

// adds this thread's v[0 .. N-1] to out[0 .. N-1]: block sums, then one atomic each per block
template <int N>
__device__ void block_sum(const double (&v)[N], double* out) {
  __shared__ double warp_sums[32][kSlot];
  double w[N];
  for (int i = 0; i < N; ++i) w[i] = v[i];
  for (int o = 16; o > 0; o >>= 1)
    for (int i = 0; i < N; ++i) w[i] += __shfl_down_sync(0xffffffffu, w[i], o);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  if (lane == 0)
    for (int i = 0; i < N; ++i) warp_sums[warp][i] = w[i];
  __syncthreads();
  if (warp == 0) {
    const bool has = lane < int(blockDim.x >> 5);
    for (int i = 0; i < N; ++i) w[i] = has ? warp_sums[lane][i] : 0.0;
    for (int o = 16; o > 0; o >>= 1)
      for (int i = 0; i < N; ++i) w[i] += __shfl_down_sync(0xffffffffu, w[i], o);
    if (lane == 0)
      for (int i = 0; i < N; ++i) atomicAdd(out + i, w[i]);
  }
  __syncthreads();
}

// ---- the step kernel -----------------------------------------------------------------

struct StepArgs {
  float k[576];        // the cell matrix, E = 1 kPa, level 0
  ElasticPlan plan;
  View v;
  double h[3];         // voxel edges (mm)
  Vec3f nrm;           // the press direction n (unit; 0 when the tip is outside the skin)
  Vec3f centre;        // the sphere's centre (mm, VOI-local)
  float radius;        // its radius (mm)
  float penetration;   // how far (mm) the sphere must pass a free skin node for it to join
  int pressing;        // the tip lies below the skin (depth above 1e-6 mm)
  int had;             // the field and contact set came from the last step
  int unit_warm;       // the unit press starts from the last one
  int predict;         // the warm start's prediction (deform::ElasticPredict) and its factor
  float predict_factor;
  int stiffness;       // solve the unit press
  int max_iterations;
  float tolerance;
  int reciprocal;             // the unit press stops at stiffness_tolerance; force and stiffness by reciprocity
  float stiffness_tolerance;
  int contact_rounds;
  int block_nodes;     // coarse levels of at most this many nodes run in block 0 alone
  float* out[3];       // u in voxels (the displacement buffer the inversion reads)
  ElasticCounters* result;
};

// the reductions' ring: each use adds into the next slot and clears the one kRing / 2
// ahead, which every thread read long ago and which the barrier publishes before its turn
struct Ring {
  double* sums;
  int slot;
};

// the grid's sums of this thread's v[0 .. N-1], read by every thread after a grid barrier
template <int N>
__device__ void reduce(Ring& rg, double (&v)[N], cg::grid_group& g) {
  static_assert(N <= kSlot, "a slot holds kSlot sums");
  double* s = rg.sums + kSlot * rg.slot;
  block_sum<N>(v, s);
  if (blockIdx.x == 0 && threadIdx.x < kSlot) rg.sums[kSlot * ((rg.slot + kRing / 2) % kRing) + threadIdx.x] = 0.0;
  g.sync();
  for (int i = 0; i < N; ++i) v[i] = *(volatile double*)&s[i];
  rg.slot = (rg.slot + 1) % kRing;
}

__device__ double reduce1(Ring& rg, double v, cg::grid_group& g) {
  double s[1] = {v};
  reduce(rg, s, g);
  return s[0];
}

// what every pass of the step kernel reads, in each block's shared memory
struct StepShared {
  Lvl lv[kElasticMaxLevels];
  float ca[kElasticMaxLevels][kElasticMaxDegree], cb[kElasticMaxLevels][kElasticMaxDegree];  // Chebyshev a, b
  int levels, split;  // split: the first level block 0 runs alone (levels: none)
};

// the passes of one step (the kernel's arguments, its blocks' shared table, the barrier
// and the reductions' ring): each is inlined at one call site
struct Step {
  const StepArgs& a;
  const StepShared& sh;
  cg::grid_group& g;
  Ring& ring;
  Team all, block;

  __device__ CellMatrix km() const { return CellMatrix{a.k}; }
  __device__ Field x(int b) const { return every(a.v.x[b], a.v); }
  __device__ Field f() const { return every(a.v.f, a.v); }
  __device__ Field res() const { return every(a.v.res, a.v); }
  __device__ Field d() const { return every(a.v.d, a.v); }
  __device__ Vec3f project(int e, const Vec3f& w) const { return deform::elastic_project(a.v.flags[e], a.nrm, w); }
  __device__ bool on_grid(int l) const { return l < sh.split; }
  __device__ Team team(int l) const { return on_grid(l) ? all : block; }
  // the barrier after a pass of level l: the grid's, or block 0's
  __device__ void sync(int l) const {
    if (on_grid(l))
      g.sync();
    else
      __syncthreads();
  }
  // the buffer holding level l's x after its smoothing (the prolongation reads it)
  __device__ int final_buffer(int l) const { return l == sh.levels - 1 ? (kCoarsest - 1) & 1 : 1; }

  // level l's smoother's first step from 0 at one node whose right-hand side `fe` was just
  // written: d = b0 Pi D^-1 f, x[0] = d
  __device__ void first_step(int l, int e, int i, int j, int k, const Vec3f& fe) const {
    const Vec3f z = project(e, mul(inverse(diag_at(km(), a.v.cell_e, sh.lv[l], i, j, k)), fe));
    const Vec3f dv = z * sh.cb[l][0];
    d().set(e, dv);
    x(0).set(e, dv);
  }

  // one Chebyshev step (s >= 1 of a smoothing from 0, or any of one that is not, `restart`
  // for its first) of level l by team t from x[from] to x[to]: r = Pi (f - K x), d = a_s d +
  // b_s Pi D^-1 r (b_s Pi D^-1 r on `restart`), x[to] = x[from] + d. Returns this thread's
  // part of f . x[to] when `dot` (CG's r . z, on level 0's last step)
  __device__ double smooth(int l, Team t, int s, int from, int to, bool restart, bool dot) const {
    const float ca = sh.ca[l][s], cb = sh.cb[l][s];
    const Field xf = x(from), xt = x(to), fv = f(), dv = d();
    double part = 0;
    gather(km(), a.v.cell_e, a.v.flags, sh.lv[l], t, xf, [&](int e, int, int, int, const Vec3f& kx, const Vec3f& dg) {
      const Vec3f fe = fv.at(e);
      const Vec3f r = project(e, fe - kx);
      const Vec3f z = project(e, mul(inverse(dg), r));
      const Vec3f step = restart ? z * cb : dv.at(e) * ca + z * cb;
      dv.set(e, step);
      const Vec3f xn = xf.at(e) + step;
      xt.set(e, xn);
      if (dot) part += dot_d(fe, xn);
    });
    return part;
  }

  // the residual of level l by team t: res = Pi (f - K x[from])
  __device__ void residual(int l, Team t, int from) const {
    const Field fv = f(), rv = res();
    gather(km(), a.v.cell_e, a.v.flags, sh.lv[l], t, x(from), [&](int e, int, int, int, const Vec3f& kx, const Vec3f&) {
      rv.set(e, project(e, fv.at(e) - kx));
    });
  }

  // level l + 1's right-hand side, the restricted residual of level l (team t), and its
  // smoother's first step
  __device__ void restrict_to(int l, Team t) const {
    const Lvl &F = sh.lv[l], &C = sh.lv[l + 1];
    const Field rv = res(), fv = f();
    for (int q = t.first; q < C.count; q += t.stride) {
      int i, j, k;
      C.coords(q, i, j, k);
      const Vec3f g = deform::elastic_restrict(
          [&](int fi, int fj, int fk) {
            return (fi < 0 || fj < 0 || fk < 0 || fi >= F.n.x || fj >= F.n.y || fk >= F.n.z) ? Vec3f{0, 0, 0}
                                                                                            : rv.at(F.at(fi, fj, fk));
          },
          i, j, k);
      const int e = C.off + q;
      const Vec3f fe = project(e, g);
      fv.set(e, fe);
      first_step(l + 1, e, i, j, k, fe);
    }
  }

  // the coarse correction of level l (team t): x[buf] += Pi P (level l + 1's final x)
  __device__ void correct(int l, Team t, int buf) const {
    const Lvl &F = sh.lv[l], &C = sh.lv[l + 1];
    const Field xf = x(buf), xc = x(final_buffer(l + 1));
    for (int q = t.first; q < F.count; q += t.stride) {
      int i, j, k;
      F.coords(q, i, j, k);
      const Vec3f g = deform::elastic_prolong(
          [&](int ci, int cj, int ck) {
            return (ci >= C.n.x || cj >= C.n.y || ck >= C.n.z) ? Vec3f{0, 0, 0} : xc.at(C.at(ci, cj, ck));
          },
          i, j, k);
      const int e = F.off + q;
      xf.set(e, xf.at(e) + project(e, g));
    }
  }

  // the rest of the V-cycle z = B r (elastic_math.h), after the pass that wrote level 0's r
  // made its smoother's first step. Levels below the split run in block 0 alone while the
  // other blocks wait at the barrier before the first grid level going up. The last pass
  // (level 0's last smoothing step) is not followed by a barrier: the caller's reduction of
  // the r . z it returns (this thread's part) is one
  __device__ double vcycle() const {
    const int last = sh.levels - 1;
    constexpr int pre = (kSmooth - 1) & 1;
    double part = 0;
    // down: each level's smoothing from 0 (the coarsest's is all it does), then its
    // residual and the next level's right-hand side
    for (int l = 0; l <= last; ++l) {
      if (!on_grid(l) && blockIdx.x != 0) break;
      const int degree = l == last ? kCoarsest : kSmooth;
      for (int s = 1; s < degree; ++s) {
        const bool final = l == 0 && last == 0 && s == degree - 1;
        const double pp = smooth(l, team(l), s, (s - 1) & 1, s & 1, false, final);
        if (final)
          part = pp;
        else
          sync(l);
      }
      if (l == last) break;
      residual(l, team(l), pre);
      sync(l);
      restrict_to(l, team(l));
      sync(l);
    }
    // up: each level's coarse correction and smoothing from it
    for (int l = last - 1; l >= 0; --l) {
      if (!on_grid(l) && blockIdx.x != 0) continue;
      if (on_grid(l) && !on_grid(l + 1)) g.sync();  // block 0's levels are done
      correct(l, team(l), pre);
      sync(l);
      for (int s = 0; s < kSmooth; ++s) {
        const bool final = l == 0 && s == kSmooth - 1;
        const double pp = smooth(l, team(l), s, (pre + s) & 1, (pre + s + 1) & 1, s == 0, final);
        if (final)
          part = pp;
        else
          sync(l);
      }
    }
    return part;
  }

  // the sphere's push (mm along n) of a level-0 node at rest, -1 where it is no free skin
  // node under the sphere (relax_elastic_cpu()'s push)
  __device__ float push(std::uint8_t fl, int i, int j, int k) const {
    if (!a.pressing || !(fl & kElasticSkin) || (fl & kElasticHeld)) return -1.0f;
    const Vec3f rest{float(i * a.h[0]), float(j * a.h[1]), float(k * a.h[2])};
    return deform::elastic_sphere_push(rest, a.centre, a.nrm, a.radius);
  }

  struct Solve {
    int iterations;
    double residual;
    bool converged;
  };

  // elastic_solve_cpu(): K w = 0 on the free components of w (level 0, the flags as they
  // are), held nodes keeping their value and contact nodes their part along n; conjugate
  // gradients preconditioned by the V-cycle, to the tolerance or max_iterations steps
  __device__ Solve solve(const Field& w, float tolerance) const {
    const Lvl& L0 = sh.lv[0];
    const View& v = a.v;
    const Field r = f(), kp = res(), p = level0(v.p, v), z = x(final_buffer(0));
    const int last = sh.levels - 1;
    Solve out{0, 0.0, true};
    // the coarse levels' contact flags from level 0's (a coarse node that is not held lies
    // on level-0 node 2^l I, through finer nodes none of which is held)
    for (int l = 1; l <= last; ++l) {
      const Lvl& C = sh.lv[l];
      for (int q = all.first; q < C.count; q += all.stride) {
        int i, j, k;
        C.coords(q, i, j, k);
        std::uint8_t nf = std::uint8_t(v.flags[C.off + q] & ~kElasticContact);
        const int fi = i << l, fj = j << l, fk = k << l;
        if (!(nf & kElasticHeld) && fi < L0.n.x && fj < L0.n.y && fk < L0.n.z)
          nf |= v.flags[L0.at(fi, fj, fk)] & kElasticContact;
        v.flags[C.off + q] = nf;
      }
    }
    // level 0: the scale of the tolerance (the residual of the constrained values alone),
    // r = Pi (0 - K w), and the smoother's first step
    double sums[2] = {0, 0};
    {
      const CellModuli ce{v.cell_e, L0};
      const Load load_w{w, L0};
      auto lift = [&](int i, int j, int k) {
        const int e = L0.at(i, j, k);
        const std::uint8_t fl = v.flags[e];
        const Vec3f we = w.at(e);
        return (fl & kElasticHeld) ? we : ((fl & kElasticContact) ? a.nrm * dot(we, a.nrm) : Vec3f{0, 0, 0});
      };
      for (int q = all.first; q < L0.count; q += all.stride) {
        int i, j, k;
        L0.coords(q, i, j, k);
        const Vec3f t = project(q, deform::elastic_apply_node(km(), ce, lift, L0.n, 1.0f, i, j, k));
        sums[0] += double(dot(t, t));
        const Vec3f re = project(q, -deform::elastic_apply_node(km(), ce, load_w, L0.n, 1.0f, i, j, k));
        r.set(q, re);
        sums[1] += dot_d(re, re);
        first_step(0, q, i, j, k, re);
      }
    }
    reduce(ring, sums, g);
    const double rref = sqrt(sums[0]);
    double rn = sqrt(sums[1]);
    out.residual = rref > 0 ? rn / rref : 0;
    if (rref <= 0 || rn <= double(tolerance) * rref) return out;
    // the V-cycle before the first step, then after each (but the last allowed)
    double rz = 0;
    float beta = 0;
    for (int it = -1; it < a.max_iterations; ++it) {
      if (it >= 0) {
        // p = z (the first step) or z + beta p
        for (int e = all.first; e < L0.count; e += all.stride) p.set(e, it == 0 ? z.at(e) : z.at(e) + p.at(e) * beta);
        g.sync();
        // q = Pi K p, and p . q
        double part = 0;
        gather(km(), v.cell_e, v.flags, L0, all, p, [&](int e, int, int, int, const Vec3f& kx, const Vec3f&) {
          const Vec3f qe = project(e, kx);
          kp.set(e, qe);
          part += dot_d(p.at(e), qe);
        });
        const double pq = reduce1(ring, part, g);
        if (!(pq > 0)) break;
        const float alpha = float(rz / pq);
        // w += alpha p, r -= alpha q, |r|^2, and the next V-cycle's first step
        part = 0;
        for (int e = all.first; e < L0.count; e += all.stride) {
          int i, j, k;
          L0.coords(e, i, j, k);
          w.set(e, w.at(e) + p.at(e) * alpha);
          const Vec3f re = r.at(e) - kp.at(e) * alpha;
          r.set(e, re);
          part += dot_d(re, re);
          first_step(0, e, i, j, k, re);
        }
        rn = sqrt(reduce1(ring, part, g));
        out.iterations = it + 1;
        out.residual = rn / rref;
        if (rn <= double(tolerance) * rref) return out;
        if (it + 1 == a.max_iterations) break;
      }
      const double rz_new = reduce1(ring, vcycle(), g);
      if (it >= 0) beta = float(rz_new / rz);
      rz = rz_new;
    }
    out.converged = out.residual <= double(tolerance);
    return out;
  }
};

// what the step solves, in order: contact rounds, a last solve of u when they ran out
// with the set still changing, the unit press
enum Job { kRound, kLast, kUnit, kDone };

template <int MinBlocks>
__global__ void __launch_bounds__(kThreads, MinBlocks) elastic_step_kernel(const __grid_constant__ StepArgs a) {
  cg::grid_group g = cg::this_grid();
  // the shared table as raw bytes (__shared__ allows no initialisers, which Vec3i has)
  __shared__ alignas(16) unsigned char shared_bytes[sizeof(StepShared)];
  StepShared& sh = *reinterpret_cast<StepShared*>(shared_bytes);
  const View& v = a.v;
  if (threadIdx.x == 0) {
    make_levels(a.plan, v.capacity, sh.lv);
    sh.levels = a.plan.levels;
    sh.split = a.plan.levels;
    for (int l = 1; l < a.plan.levels; ++l)
      if (sh.lv[l].count <= a.block_nodes) {
        sh.split = l;
        break;
      }
    // each level's Chebyshev coefficients from its lmax (the set-up's)
    for (int l = 0; l < a.plan.levels; ++l) {
      const bool coarsest = l + 1 == a.plan.levels;
      const float hi = deform::kElasticChebyshevMargin * v.lmax[l];
      deform::elastic_chebyshev(hi / (coarsest ? deform::kElasticCoarsestRatio : deform::kElasticChebyshevRatio), hi,
                                coarsest ? kCoarsest : kSmooth, sh.ca[l], sh.cb[l]);
    }
  }
  Ring ring{v.sums, 0};
  const Team all{int(blockIdx.x * blockDim.x + threadIdx.x), int(gridDim.x * blockDim.x)};
  for (int e = all.first; e < kSlot * kRing; e += all.stride) v.sums[e] = 0.0;
  __syncthreads();
  g.sync();
  const Step st{a, sh, g, ring, all, Team{int(threadIdx.x), int(blockDim.x)}};
  const Lvl& L0 = sh.lv[0];
  const Field u = level0(v.u, v), unit = level0(v.u_unit, v);
  ElasticCounters out{};
  out.settled = 1;
  out.converged = 1;

  // the contact set: last step's nodes still under the sphere, nodes the last field (as the
  // prediction moves it) leaves inside it, every node under it on a fresh start (the field
  // and contact set zeroed first)
  double under = 0;
  for (int e = all.first; e < L0.count; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    std::uint8_t fl = v.flags[e];
    Vec3f ue = u.at(e);
    if (!a.had) {
      ue = Vec3f{0, 0, 0};
      u.set(e, ue);
      fl = std::uint8_t(fl & ~kElasticContact);
    } else if (a.predict != int(ElasticPredict::kNone)) {
      const ElasticPredict kind = ElasticPredict(a.predict);
      ue = deform::elastic_predicted(kind, a.predict_factor, ue,
                                     kind == ElasticPredict::kUnit ? unit.at(e) : Vec3f{0, 0, 0});
      u.set(e, ue);
    }
    const float t = st.push(fl, i, j, k);
    if (t > 0) under += 1;
    const bool was = (fl & kElasticContact) != 0;
    const bool pen = t > 0 && t - dot(ue, a.nrm) > 0;
    fl = std::uint8_t(fl & ~kElasticContact);
    if (t > 0 && (was || pen || !a.had)) fl |= kElasticContact;
    v.flags[e] = fl;
  }
  if (reduce1(ring, under, g) == 0) {
    // nothing pressed: the tissue at rest
    for (int e = all.first; e < L0.count; e += all.stride) {
      u.set(e, Vec3f{0, 0, 0});
      a.out[0][e] = a.out[1][e] = a.out[2][e] = 0.0f;
    }
    if (blockIdx.x == 0 && threadIdx.x == 0) *a.result = out;
    return;
  }
  out.contact = 1;

  // the solves: contact rounds (after each, nodes the finger pulls leave and skin nodes
  // pushed into the sphere join), one more when the last round still changed the set, then
  // the unit press (every contact node 1 mm along n, the set held) when asked. After each,
  // one pass over the contact nodes sums their forces along n (the finger's push: the
  // reaction, or the stiffness), which after a round that changed nothing is u's reaction
  const int rounds = max(1, a.contact_rounds);
  int round = 0;
  bool settled = false;
  Job job = kRound;
  while (job != kDone) {
    const Field w = job == kUnit ? unit : u;
    if (job == kUnit) {
      for (int e = all.first; e < L0.count; e += all.stride) {
        Vec3f we = a.unit_warm ? w.at(e) : Vec3f{0, 0, 0};
        if (v.flags[e] & kElasticContact) we = we - a.nrm * dot(we, a.nrm) + a.nrm;
        w.set(e, we);
      }
    } else {
      // contact nodes onto the sphere along n (held nodes stay)
      for (int e = all.first; e < L0.count; e += all.stride) {
        const std::uint8_t fl = v.flags[e];
        if (!(fl & kElasticContact)) continue;
        int i, j, k;
        L0.coords(e, i, j, k);
        const Vec3f we = w.at(e);
        w.set(e, we - a.nrm * dot(we, a.nrm) + a.nrm * st.push(fl, i, j, k));
      }
    }
    g.sync();
    const Step::Solve sr = st.solve(w, job == kUnit && a.reciprocal ? a.stiffness_tolerance : a.tolerance);
    if (job == kUnit) {
      out.stiffness_iterations = sr.iterations;
    } else {
      out.iterations += sr.iterations;
      out.residual = sr.residual;
      out.converged = out.converged && sr.converged;
      if (job == kRound) out.rounds = round + 1;
    }
    // the contact nodes' forces along n and their count; after a round, the set's update;
    // after the unit press by reciprocity (elastic_math.h) the push sum of u . K w and w's
    // residual's part of w . K w
    const bool reciprocal = job == kUnit && a.reciprocal;
    const Field rw = st.f();
    double sums[4] = {0, 0, 0, 0};
    for (int e = all.first; e < L0.count; e += all.stride) {
      const std::uint8_t fl = v.flags[e];
      int i, j, k;
      L0.coords(e, i, j, k);
      if (reciprocal) {
        const Vec3f re = rw.at(e);
        sums[2] -= dot_d(u.at(e), re);
        sums[3] += dot_d(w.at(e), re);
      }
      if (fl & kElasticContact) {
        const float fn = dot(deform::elastic_apply_node(st.km(), CellModuli{v.cell_e, L0}, Load{w, L0}, L0.n, 1.0f, i,
                                                        j, k),
                             a.nrm);
        sums[0] += double(fn);
        sums[1] += 1;
        if (reciprocal) sums[2] += double(fn) * double(dot(u.at(e), a.nrm));
        if (job == kRound && fn < 0.0f) {
          v.flags[e] = std::uint8_t(fl & ~kElasticContact);
          sums[2] += 1;
        }
      } else if (job == kRound) {
        const float t = st.push(fl, i, j, k);
        if (t > 0 && t - dot(w.at(e), a.nrm) > a.penetration) {
          v.flags[e] = std::uint8_t(fl | kElasticContact);
          sums[2] += 1;
        }
      }
    }
    reduce(ring, sums, g);
    if (job == kRound) {
      ++round;
      settled = sums[2] == 0;
      if (!settled) {
        job = round < rounds ? kRound : kLast;
        continue;
      }
    }
    if (job == kUnit) {
      out.stiffness_n_per_mm = reciprocal ? sums[0] - sums[3] : sums[0];
      if (reciprocal) out.press_n = sums[2];
      job = kDone;
    } else {
      out.press_n = sums[0];
      out.contact_nodes = int(sums[1]);
      job = a.stiffness && out.contact_nodes > 0 ? kUnit : kDone;
    }
  }
  out.settled = settled;

  // the field in voxels for the inversion, and the cells it folds
  double folded = 0;
  auto load_vox = [&](int i, int j, int k) {
    const Vec3f ue = u.at(L0.at(i, j, k));
    return Vec3f{float(ue.x / a.h[0]), float(ue.y / a.h[1]), float(ue.z / a.h[2])};
  };
  for (int e = all.first; e < L0.count; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    const Vec3f ue = u.at(e);
    a.out[0][e] = float(ue.x / a.h[0]);
    a.out[1][e] = float(ue.y / a.h[1]);
    a.out[2][e] = float(ue.z / a.h[2]);
    if (i + 1 >= L0.n.x || j + 1 >= L0.n.y || k + 1 >= L0.n.z) continue;
    bool moved = false;
    for (int c = 0; c < 8 && !moved; ++c) {
      const Vec3i o = deform::elastic_corner(c);
      const Vec3f w = u.at(L0.at(i + o.x, j + o.y, k + o.z));
      moved = w.x != 0.0f || w.y != 0.0f || w.z != 0.0f;
    }
    if (moved && !(deform::cell_min_det(load_vox, i, j, k) > 0.0f)) folded += 1;
  }
  out.inverted = (unsigned long long)reduce1(ring, folded, g);
  if (blockIdx.x == 0 && threadIdx.x == 0) *a.result = out;
}

// ---- the set-up kernel ---------------------------------------------------------------

struct SetupArgs {
  float k[576];
  ElasticPlan plan;
  View v;
  Voi voi, last;           // the VOI to set up and the one the field is on (patient voxels)
  Vec3i grid;              // the patient grid's size
  ElasticMaterial material;
  ElasticPatient patient;
  int had;                 // carry the last field and contact set over
};

template <int MinBlocks>
__global__ void __launch_bounds__(kThreads, MinBlocks) elastic_setup_kernel(const __grid_constant__ SetupArgs a) {
  cg::grid_group g = cg::this_grid();
  __shared__ alignas(16) unsigned char level_bytes[kElasticMaxLevels * sizeof(Lvl)];  // raw: Vec3i has initialisers
  Lvl* lv = reinterpret_cast<Lvl*>(level_bytes);
  if (threadIdx.x == 0) make_levels(a.plan, a.v.capacity, lv);
  __syncthreads();
  const View& v = a.v;
  const Team all{int(blockIdx.x * blockDim.x + threadIdx.x), int(gridDim.x * blockDim.x)};
  const Lvl& L0 = lv[0];
  const int levels = a.plan.levels;
  const CellMatrix km{a.k};
  const Field u = level0(v.u, v), tmp_u = every(v.f, v);
  float* node_e = v.d;
  double* sums = v.sums + kSlot * kRing;
  const ElasticPatient& pt = a.patient;
  auto patient_index = [&](int gi, int gj, int gk) { return ((long long)gk * a.grid.y + gj) * a.grid.x + gi; };
  auto in_body = [&](int gi, int gj, int gk) {
    return gi >= 0 && gj >= 0 && gk >= 0 && gi < a.grid.x && gj < a.grid.y && gk < a.grid.z &&
           pt.body[patient_index(gi, gj, gk)] != 0;
  };

  // the last field and contact bits aside for the carry; the sums cleared
  const int last_count = int(a.last.count());
  if (a.had)
    for (int e = all.first; e < last_count; e += all.stride) {
      tmp_u.set(e, u.at(e));
      v.tmp_flags[e] = v.flags[e] & kElasticContact;
    }
  for (int e = all.first; e < kSlot * kSetupSums; e += all.stride) sums[e] = 0.0;
  g.sync();

  // node moduli (kPa, into the scratch's d) and level 0's static flags: held (bone, the
  // VOI's faces), body, skin (a face neighbour outside the body)
  for (int e = all.first; e < L0.count; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    const int gi = a.voi.lo.x + i, gj = a.voi.lo.y + j, gk = a.voi.lo.z + k;
    const long long pi = patient_index(gi, gj, gk);
    const bool body = pt.body[pi] != 0, bone = pt.bone[pi] != 0;
    node_e[e] = deform::elastic_node_modulus(a.material, pt.intensity[pi], body, pt.dist_skin_mm[pi]);
    const bool face = i == 0 || j == 0 || k == 0 || i + 1 == L0.n.x || j + 1 == L0.n.y || k + 1 == L0.n.z;
    v.flags[e] = deform::elastic_static_flags(body, bone, face, in_body, gi, gj, gk);
  }
  g.sync();
  // level 0's cell moduli: the mean of the corners' where all eight are in the body, else air's gel
  for (int e = all.first; e < L0.count; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    if (i + 1 >= L0.n.x || j + 1 >= L0.n.y || k + 1 >= L0.n.z) {
      v.cell_e[e] = 0.0f;
      continue;
    }
    v.cell_e[e] = deform::elastic_cell_modulus(
        [&](int c) {
          const Vec3i o = deform::elastic_corner(c);
          return node_e[L0.at(i + o.x, j + o.y, k + o.z)];
        },
        [&](int c) {
          const Vec3i o = deform::elastic_corner(c);
          return pt.body[patient_index(a.voi.lo.x + i + o.x, a.voi.lo.y + j + o.y, a.voi.lo.z + k + o.z)] != 0;
        },
        a.material.air_e_kpa);
  }
  g.sync();
  // coarse levels, each from the one below: moduli and held nodes
  for (int l = 1; l < levels; ++l) {
    const Lvl& F = lv[l - 1];
    const Lvl& C = lv[l];
    for (int q = all.first; q < C.count; q += all.stride) {
      int i, j, k;
      C.coords(q, i, j, k);
      const int e = C.off + q;
      v.cell_e[e] = (i + 1 < C.n.x && j + 1 < C.n.y && k + 1 < C.n.z)
                        ? deform::elastic_coarse_cell_e(CellModuli{v.cell_e, F}, F.n, i, j, k)
                        : 0.0f;
      const bool beyond = 2 * i >= F.n.x || 2 * j >= F.n.y || 2 * k >= F.n.z;
      v.flags[e] =
          deform::elastic_coarse_flags(beyond ? 0 : (v.flags[F.at(2 * i, 2 * j, 2 * k)] & kElasticHeld), beyond);
    }
    g.sync();
  }
  // every level's largest eigenvalue of D^-1 K by power iteration, all levels in the same
  // passes: the start, then x' = Pi D^-1 K x with |x|^2 and |x'|^2 per level
  const Vec3f none{0, 0, 0};
  for (int l = 0; l < levels; ++l) {
    const Lvl& L = lv[l];
    const Field x0 = every(v.x[0], v);
    for (int q = all.first; q < L.count; q += all.stride) {
      const unsigned long long m = 3ull * (unsigned long long)q;
      const int e = L.off + q;
      x0.set(e, deform::elastic_project(v.flags[e], none,
                                        Vec3f{deform::elastic_power_start(m), deform::elastic_power_start(m + 1),
                                              deform::elastic_power_start(m + 2)}));
    }
  }
  g.sync();
  for (int it = 0; it < deform::kElasticPowerIterations; ++it) {
    const Field xf = every(v.x[it & 1], v), xt = every(v.x[(it + 1) & 1], v);
    for (int l = 0; l < levels; ++l) {
      double part[2] = {0, 0};
      gather(km, v.cell_e, v.flags, lv[l], all, xf, [&](int e, int, int, int, const Vec3f& kx, const Vec3f& dg) {
        const Vec3f xe = xf.at(e);
        const Vec3f re = deform::elastic_project(v.flags[e], none, mul(inverse(dg), kx));
        xt.set(e, re);
        part[0] += dot_d(xe, xe);
        part[1] += dot_d(re, re);
      });
      block_sum(part, sums + kSlot * (it * kElasticMaxLevels + l));
    }
    g.sync();
  }
  if (blockIdx.x == 0 && threadIdx.x == 0) {
    for (int l = 0; l < levels; ++l) {
      bool dead = false;
      double lambda = 0;
      for (int it = 0; it < deform::kElasticPowerIterations; ++it) {
        const double* s = sums + kSlot * (it * kElasticMaxLevels + l);
        const double xn = sqrt(s[0]);
        if (!(xn > 0)) {
          dead = true;
          break;
        }
        lambda = sqrt(s[1]) / xn;
      }
      v.lmax[l] = dead || !(lambda > 0) ? 1.0f : float(lambda);
    }
  }
  // the last field and contact set carried onto the new VOI (0 where it has none); held
  // nodes (the new VOI's faces, bone) stay at rest: the solve keeps what they hold
  for (int e = all.first; e < L0.count; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    const int pa = i + a.voi.lo.x - a.last.lo.x, pb = j + a.voi.lo.y - a.last.lo.y, pc = k + a.voi.lo.z - a.last.lo.z;
    const bool carry = a.had && a.last.contains(pa, pb, pc) && !(v.flags[e] & kElasticHeld);
    const int le = carry ? int(a.last.index(pa, pb, pc)) : 0;
    u.set(e, carry ? tmp_u.at(le) : Vec3f{0, 0, 0});
    if (carry) v.flags[e] |= v.tmp_flags[le];
  }
}

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

// blocks of the elastic kernels per multiprocessor: 1 (a thread may use 128 registers) or 2
// (64 registers a thread, the rest spilled to local memory, twice the warps to hide
// latency, twice the blocks at each grid barrier); PALPSIM_ELASTIC_BLOCKS_PER_SM=2 picks 2
// for a measurement (palpsim-bench deform --elastic)
int elastic_blocks_per_sm() {
  static const int n = [] {
    const char* s = std::getenv("PALPSIM_ELASTIC_BLOCKS_PER_SM");
    return s && std::string(s) == "2" ? 2 : 1;
  }();
  return n;
}

// coarse levels of at most this many nodes run in block 0 alone: kBlockNodes, or
// PALPSIM_ELASTIC_BLOCK_NODES for a measurement
int elastic_block_nodes() {
  static const int n = [] {
    const char* s = std::getenv("PALPSIM_ELASTIC_BLOCK_NODES");
    return s && std::atoi(s) > 0 ? std::atoi(s) : kBlockNodes;
  }();
  return n;
}

// the cooperative launch of the kernel instantiated for elastic_blocks_per_sm()
template <typename Args>
void launch_chosen(void (*one)(Args), void (*two)(Args), Args& args, int blocks, long long nodes,
                   cudaStream_t stream) {
  launch(elastic_blocks_per_sm() == 2 ? two : one, args, blocks, nodes, stream);
}

}  // namespace

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
    PALPSIM_CUDA_CHECK(cudaMalloc(&sums, kSlot * std::size_t(kRing + kSetupSums) * sizeof(double)));
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

std::shared_ptr<ElasticScratch> ElasticScratch::shared(long long n, long long nc) {
  return shared_scratch<ElasticScratch>(n, nc);
}

std::size_t ElasticScratch::bytes() const {
  return 15 * std::size_t(capacity + coarse_capacity) * sizeof(float) + 3 * std::size_t(capacity) * sizeof(float) +
         std::size_t(capacity) + kSlot * std::size_t(kRing + kSetupSums) * sizeof(double);
}

ElasticSolver::~ElasticSolver() { release(); }

void ElasticSolver::release() {
  // errors are ignored here: it runs from destructors
  for (void* q : {(void*)u_, (void*)u_unit_, (void*)flags_, (void*)cell_e_, (void*)lmax_}) cudaFree(q);
  u_ = u_unit_ = cell_e_ = lmax_ = nullptr;
  flags_ = nullptr;
  capacity_ = coarse_capacity_ = 0;
  set_up_ = have_u_ = have_unit_ = false;
  voi_ = Voi{};
}

void ElasticSolver::bind(const Patient& p, const deform::ElasticParams& params, const Vec3i& most) {
  release();
  params_ = params;
  k_ = deform::elastic_element(p.grid.spacing_mm, params.poisson);
  const long long n = (long long)most.x * most.y * most.z;
  const long long nc = std::max(1LL, deform::elastic_plan(most).coarse_count);
  if (n + nc >= (1LL << 31))
    throw Error("deform backend \"cuda\": an elastic VOI of " + std::to_string(n) +
                " nodes and its coarse levels are too large (the kernels index them with 32 bits; use a smaller "
                "deform.voi_edge)");
  const std::size_t total = std::size_t(n + nc);
  try {
    PALPSIM_CUDA_CHECK(cudaMalloc(&u_, 3 * std::size_t(n) * sizeof(float)));
    if (params.stiffness) PALPSIM_CUDA_CHECK(cudaMalloc(&u_unit_, 3 * std::size_t(n) * sizeof(float)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&flags_, total));
    PALPSIM_CUDA_CHECK(cudaMalloc(&cell_e_, total * sizeof(float)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&lmax_, kElasticMaxLevels * sizeof(float)));
  } catch (...) {
    release();
    throw;
  }
  capacity_ = n;
  coarse_capacity_ = nc;
}

void ElasticSolver::forget() {
  have_u_ = false;
  have_unit_ = false;
}

std::size_t ElasticSolver::bytes() const {
  if (!bound()) return 0;
  const std::size_t n = std::size_t(capacity_), total = std::size_t(capacity_ + coarse_capacity_);
  return (u_unit_ ? 6 : 3) * n * sizeof(float) + total * (1 + sizeof(float)) + kElasticMaxLevels * sizeof(float);
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
  view.sums = scratch.sums;
  view.capacity = scratch.capacity;
  view.total = scratch.capacity + scratch.coarse_capacity;

  // warm start (relax_elastic_cpu()): the last field and contact set, carried onto this VOI
  // by the set-up when the VOI moved; from rest when there is none (the model is fixed at
  // bind, so a kept field is always of the same model)
  const bool had = have_u_;
  pending_ = deform::ElasticRun{};
  pending_.warm = had;
  const ElasticScratch::Turn turn(scratch, stream);
  if (!set_up_ || !(voi == voi_)) {
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
      last_press_, had && params_.predict, have_unit_ && u_unit_ != nullptr && dot(unit_normal_, nrm) > 0.999f, tip_mm, depth, nrm);
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
  s.had = had;
  s.unit_warm = have_unit_ && unit_normal_ == nrm;
  s.predict = int(pred.kind);
  s.predict_factor = pred.factor;
  s.stiffness = params_.stiffness && u_unit_ != nullptr;
  s.max_iterations = params_.max_iterations;
  s.tolerance = params_.tolerance;
  s.reciprocal = params_.stiffness_tolerance > 0;
  s.stiffness_tolerance = params_.stiffness_tolerance;
  s.contact_rounds = params_.contact_rounds;
  s.block_nodes = elastic_block_nodes();
  s.result = result;
  launch_chosen(elastic_step_kernel<1>, elastic_step_kernel<2>, s, blocks, voi.count(), stream);
  have_u_ = true;
}

deform::ElasticRun ElasticSolver::finish(const ElasticCounters& c) {
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
  // what the next step starts from: the unit press holds this contact set's (along this n)
  if (!r.contact) {
    have_unit_ = false;
  } else if (params_.stiffness && r.contact_nodes > 0) {
    have_unit_ = true;
    unit_normal_ = pending_normal_;
  }
  return r;
}

}  // namespace palpsim::cuda
