// The elastic kernels' shared pieces: node ranges and levels, the device arrays, the
// gathered operator (level 0 and large coarse levels in shared-memory tiles, small coarse levels eight lanes a node) and
// block sums.
#pragma once
// Included by cuda/relax_elastic.cu alone (one translation unit: the kernels are templates
// in its anonymous namespace); see that file for what the elastic step does on the GPU.
#include <cooperative_groups.h>

#include <algorithm>
#include <cmath>

#include "cuda/relax_elastic.h"
#include "deform/deform_math.h"
#include "deform/elastic_math.h"

namespace palpsim::cuda {

namespace {

namespace cg = cooperative_groups;
using deform::ElasticMaterial;
using deform::ElasticPlan;
using deform::ElasticPredict;
using deform::kElasticAir;
using deform::kElasticContact;
using deform::kElasticHeld;
using deform::kElasticMaxDegree;
using deform::kElasticMaxLevels;
using deform::kElasticSkin;
using deform::Voi;

constexpr int kThreads = 512;      // threads per block of both kernels
// coarse levels of at most this many nodes run in block 0 alone (the default: a coarsest
// level of 4^3, as a VOI of 48 ends on; the phantom's 64 x 49 x 64 ends on 5 x 4 x 5 on the
// grid); PALPSIM_ELASTIC_BLOCK_NODES sets it for a measurement
constexpr int kBlockNodes = 64;
constexpr int kTileNodes = 8192;   // coarse levels of at least this many nodes on the grid take tiles (the default)
constexpr int kSlot = 4;           // sums a reduction slot holds
constexpr int kRing = 32;          // the step's reduction slots, reused in turn
constexpr int kSetupSums = deform::kElasticLanczosSteps * kElasticMaxLevels;  // the set-up's slots
// the sums' last entry: the ring's slot at which the next step starts. Each use of a slot
// clears the one kRing / 2 ahead, so the kRing / 2 slots from the next one on are clear when
// a step ends (used before the step began, or cleared since): a step starts there with no
// clearing pass and no barrier
constexpr int kRingNext = kSlot * (kRing + kSetupSums);
constexpr int kSumsEntries = kRingNext + 1;  // doubles the sums hold

// what a traced barrier ends (elastic_trace_summary() names them), times 16, plus the level
enum TracePass : int {
  kPassStart = 1,
  kPassSmoothDown,
  kPassResidual,
  kPassRestrict,
  kPassBlockLevels,
  kPassCorrect,
  kPassSmoothUp,
  kPassCgDirection,
  kPassCgApply,
  kPassCgUpdate,
  kPassVcycleLast,
  kPassSolveStart,
  kPassContact,
  kPassField,
  kPassSetupNodes,
  kPassSetupCells,
  kPassSetupCoarse,
  kPassSetupLanczos,
  kPassSetupEnd,
  kPassShift,
  kPassSolveFlags,
};

// the passes' ends of one kernel run, when it is traced: block 0's thread 0 notes the time
// (globaltimer, ns) at which pass `tag` (TracePass * 16 + level) ended, after its barrier
struct Tracer {
  unsigned long long* trace;  // (tag, ns) pairs, or null
  int pairs, stamps;          // the pairs it holds, and those written
  __device__ void stamp(int tag) {
    if (!trace || blockIdx.x != 0 || threadIdx.x != 0 || stamps >= pairs) return;
    unsigned long long ns;
    asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(ns));
    trace[2 * stamps] = (unsigned long long)tag;
    trace[2 * stamps + 1] = ns;
    ++stamps;
  }
};

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

// the cell matrix (for E = 1 kPa at level 0) from corner 0's row block in the kernel's
// arguments or its copy in shared memory: 72 floats, which the constant cache holds
// (the full matrix's 576 missed it a product in two)
using CellMatrix = deform::ElasticCellBase;

// the block's copy of the row block (one function, so one array), for the eight-lane
// gathers: their lanes read eight row blocks at once, which the kernel argument serves one
// address at a time
__device__ float* cell_matrix_shared() {
  __shared__ float k[72];
  return k;
}

// every thread of the block its entries of the copy; a __syncthreads() must follow before
// a gather reads it
__device__ void copy_cell_matrix(const float* k) {
  float* const to = cell_matrix_shared();
  for (int i = int(threadIdx.x); i < 72; i += int(blockDim.x)) to[i] = k[i];
}

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

// the same, 0 beyond the level's nodes (a shifted field's reads, deform::elastic_shifted)
struct LoadOrZero {
  Field x;
  Lvl L;
  __device__ Vec3f operator()(int i, int j, int k) const {
    if (i < 0 || j < 0 || k < 0 || i >= L.n.x || j >= L.n.y || k >= L.n.z) return Vec3f{0, 0, 0};
    return x.at(L.at(i, j, k));
  }
};

// the device arrays both kernels work on: the session's own and the scratch's
struct View {
  float* u;            // the field (mm), level 0, stride capacity
  float* u_unit;       // the unit press, likewise (null without the stiffness)
  float* react;        // the last step's reactions (N along n) at its contact nodes, level 0: the press's,
                       // then the unit press's at capacity on (null without the stiffness)
  std::uint8_t* flags; // every level
  float* cell_e;       // every level
  float* lmax;         // every level's largest eigenvalue of D^-1 K
  float* x[2];         // every level, stride total: the V-cycle's corrections
  float *f, *res, *d;  // every level: right-hand side, residual, Chebyshev step
  float* p;            // level 0, stride capacity: CG's direction
  std::uint8_t* tmp_flags;
  int* tiles;          // level 0's tiles with a node not held: count, then their indices (the set-up's; tile_list())
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
constexpr int kHaloRounds = (kHalo + kThreads - 1) / kThreads;  // halo nodes a thread loads

// one tile's shared memory for every gather of a kernel (one function each, so one array:
// each instantiation of a template declaring it would have its own): a halo node's first
// field and the modulus of the cell whose lowest corner it is, as one float4 (x, y, z, E),
// which a product reads with one load; a second field's components in planes
constexpr int kTileFields = 2;  // fields a tile pass gathers at most (gather_pair)
__device__ float4* tile_nodes() {
  __shared__ float4 t[kHalo];
  return t;
}
__device__ float* tile_planes() {
  __shared__ float t[3 * (kTileFields - 1) * kHalo];
  return t;
}

// a tile's node at offset o from one (`at`: the tile's float4s from that node on) as
// elastic_apply_interior_once() reads it: field 0 and the modulus of the cell there
struct TileNode {
  const float4* at;
  __device__ __forceinline__ deform::ElasticNodeCell operator()(int o) const {
    const float4 q = at[o];
    return deform::ElasticNodeCell{Vec3f{q.x, q.y, q.z}, q.w};
  }
};

// the same for field 1, from the planes (`at`: plane 0 from that node on)
struct TilePlanes {
  const float4* cell;
  const float* at;
  __device__ __forceinline__ deform::ElasticNodeCell operator()(int o) const {
    return deform::ElasticNodeCell{Vec3f{at[o], at[kHalo + o], at[2 * kHalo + o]}, cell[o].w};
  }
};

// level 0's tiles (L): kTile nodes along each axis, the last ones cut by the level's end
__device__ Vec3i tile_grid(const Lvl& L) {
  return Vec3i{(L.n.x + kTileX - 1) / kTileX, (L.n.y + kTileY - 1) / kTileY, (L.n.z + kTileZ - 1) / kTileZ};
}

// a coarse level's tiles that hold a node below its last layer along every axis: the tiles
// left out hold nodes of the level's high faces alone, which are held (a coarse node lies on
// a held level-0 face node or beyond the fine grid: elastic_coarse_flags)
__device__ Vec3i coarse_tile_grid(const Lvl& L) {
  return Vec3i{(L.n.x - 1 + kTileX - 1) / kTileX, (L.n.y - 1 + kTileY - 1) / kTileY, (L.n.z - 1 + kTileZ - 1) / kTileZ};
}

// what a gather's caller reads at a node before the node's products are summed (`pre`):
// nothing. A caller that reads more (its right-hand side, its last Chebyshev step) gives a
// functor pre(mine, e) returning those values, loaded where `mine`, so that their loads wait
// beside the tile's rather than after the products
struct NoPre {
  __device__ int operator()(bool, int) const { return 0; }
};

// calls fn(e, i, j, k, kx, dg, own, pv) for every node of level L in a tile of `tiles` (its
// count, then tile indices: level 0's with a node that is not held; null, on a coarse level:
// every tile but those of its high faces alone, coarse_tile_grid()), the whole grid taking a
// tile of kThreads nodes a block at a time: the tile's nodes and their neighbours' values
// of the F fields x and the cells' moduli go to shared memory, then each thread sums its
// node's cells from there (elastic_apply_interior_once: every load one register and a
// constant apart), kx[f] = (K x[f]) at the node, own[f] = x[f] at the node (from the tile), pv =
// pre(true, e) (loaded before the tile). Held nodes get kx = dg = 0 (every caller projects
// them to 0); the nodes of the tiles left out are all held, and every caller's outputs
// hold 0 there already (each solve and the set-up's Lanczos steps clear them first, on every
// level). A free node on the level's faces (none: the VOI's faces are held) would take
// elastic_apply_node from global memory. Every thread of a block runs every tile of the
// block (the tile's barriers). What is left of the tiles after the whole rounds is summed
// in parts of a tile along k (see `split`; one field's gathers).
// (The gathers and the step's passes that call them are inlined: an outlined one takes the
// kernel's arguments by a generic pointer, which ptxas serves from a local copy of all of
// them, 2.6 KB a thread.)
template <int F, typename Pre, typename Fn>
__device__ __forceinline__ void gather_tiles(const CellMatrix& km, const float* cell_e, const std::uint8_t* flags,
                                             const int* tiles, const Lvl& L, const Field (&x)[F], Pre& pre, Fn& fn) {
  static_assert(F >= 1 && F <= kTileFields, "the tile's memory holds kTileFields fields");
  float4* const tn = tile_nodes();   // tn[h]: field 0 at halo node h and the cell there
  float* const tp = tile_planes();   // tp[c * kHalo + h]: field 1's component c
  const Vec3i tg = tiles ? tile_grid(L) : coarse_tile_grid(L);
  const int tx = tg.x, ty = tg.y;
  const int li = threadIdx.x % kTileX, lj = (threadIdx.x / kTileX) % kTileY, lk = threadIdx.x / (kTileX * kTileY);
  const int active = tiles ? tiles[0] : tg.x * tg.y * tg.z;
  // the work units: the tiles of the whole rounds (every block one tile a round), then the
  // rest of the tiles cut along k into `split` parts of kTileZ / split layers, as many as
  // the grid takes in one round, so that the last round's blocks each sum fewer nodes
  // instead of most blocks waiting for a few whole tiles. Gathers of one field only: the
  // pair's registers do not hold it (the H100 measured a step's start 2 % slower with it)
  const int whole = F == 1 ? active - active % int(gridDim.x) : active;
  const int rest = active - whole;
  int split = 1;
  while (F == 1 && split < kTileZ && rest * split * 2 <= int(gridDim.x)) split *= 2;
  const int units = whole + rest * split;
  for (int q = blockIdx.x; q < units; q += gridDim.x) {
    const int tq = q < whole ? q : whole + (q - whole) / split;
    const int layers = q < whole ? kTileZ : kTileZ / split;  // the unit's node layers along k
    const int part = q < whole ? 0 : (q - whole) % split;
    const int tile = tiles ? tiles[1 + tq] : tq;
    const int i0 = (tile % tx) * kTileX, j0 = ((tile / tx) % ty) * kTileY,
              k0 = (tile / (tx * ty)) * kTileZ + part * layers;
    const int halo = kHaloX * kHaloY * (layers + 2);  // the unit's halo nodes (kHalo for a whole tile)
    // this thread's node and what the caller reads there, loaded first
    const int i = i0 + li, j = j0 + lj, k = k0 + lk;
    const bool mine = lk < layers && i < L.n.x && j < L.n.y && k < L.n.z;
    const int e = mine ? L.at(i, j, k) : 0;
    const auto pv = pre(mine, e);
    // the halo: nodes (i0 - 1 .. i0 + kTileX) etc., 0 outside the level; the cell at halo
    // position h has its lowest corner there (cells beyond the last node: 0); every load
    // of every round before the first store, so that the thread waits for them once
    float hv[1 + 3 * F][kHaloRounds];
    bool first_nonzero = false;  // two fields: the first is not 0 at a halo node this thread loaded
#pragma unroll
    for (int r = 0; r < kHaloRounds; ++r) {
      const int h = int(threadIdx.x) + r * kThreads;
      const int hi = h % kHaloX, hj = (h / kHaloX) % kHaloY, hk = h / (kHaloX * kHaloY);
      const int ni = i0 - 1 + hi, nj = j0 - 1 + hj, nk = k0 - 1 + hk;
      const bool in = h < halo && ni >= 0 && nj >= 0 && nk >= 0 && ni < L.n.x && nj < L.n.y && nk < L.n.z;
      const int he = in ? L.at(ni, nj, nk) : 0;
      hv[0][r] = in && ni + 1 < L.n.x && nj + 1 < L.n.y && nk + 1 < L.n.z ? cell_e[he] : 0.0f;
#pragma unroll
      for (int f = 0; f < F; ++f)
#pragma unroll
        for (int c = 0; c < 3; ++c) hv[1 + 3 * f + c][r] = in ? x[f].p[c * x[f].stride + he] : 0.0f;
      if (F == 2) first_nonzero = first_nonzero || hv[1][r] != 0.0f || hv[2][r] != 0.0f || hv[3][r] != 0.0f;
    }
#pragma unroll
    for (int r = 0; r < kHaloRounds; ++r) {
      const int h = int(threadIdx.x) + r * kThreads;
      if (h < halo) {
        tn[h] = make_float4(hv[1][r], hv[2][r], hv[3][r], hv[0][r]);
#pragma unroll
        for (int c = 0; c < 3 * (F - 1); ++c) tp[c * kHalo + h] = hv[4 + c][r];
      }
    }
    // (two fields: whether the first is 0 on the whole tile and its halo, where its products
    // are 0 and left out: a solve start's constrained values lie at the contact alone)
    const bool first_needed = F == 1 ? true : __syncthreads_or(first_nonzero) != 0;
    if (F == 1) __syncthreads();
    if (mine) {
      const int h = ((lk + 1) * kHaloY + lj + 1) * kHaloX + li + 1;
      Vec3f kx[F], own[F], dg{0, 0, 0};
      const TileNode node0{tn + h};
      const TilePlanes node1{tn + h, tp + h};
#pragma unroll
      for (int f = 0; f < F; ++f) {
        kx[f] = Vec3f{0, 0, 0};
        own[f] = f == 0 ? node0(0).u : node1(0).u;
      }
      if (!(flags[e] & kElasticHeld)) {
        if (i > 0 && j > 0 && k > 0 && i + 1 < L.n.x && j + 1 < L.n.y && k + 1 < L.n.z) {
#pragma unroll
          for (int f = 0; f < F; ++f) {
            if (f == 0 && !first_needed) continue;  // K 0 = 0 (kx[0] holds it)
            // (each of the 27 neighbours one float4 load; the cell-by-cell form read 64 corners)
            if (f == 0)
              deform::elastic_apply_interior_once(km, node0, kHaloX, kHaloX * kHaloY, L.scale, kx[f], dg);
            else
              deform::elastic_apply_interior_once(km, node1, kHaloX, kHaloX * kHaloY, L.scale, kx[f], dg);
          }
        } else {
#pragma unroll
          for (int f = 0; f < F; ++f)
            kx[f] = deform::elastic_apply_node(km, CellModuli{cell_e, L}, Load{x[f], L}, L.n, L.scale, i, j, k);
          dg = deform::elastic_diag_node(km, CellModuli{cell_e, L}, L.n, L.scale, i, j, k);
        }
      }
      fn(e, i, j, k, kx, dg, own, pv);
    }
    __syncthreads();
  }
}

// level 0's gather of two fields in one tile pass: fn(e, i, j, k, K a, K b, dg) (a solve's
// start, which needs both)
template <typename Fn>
__device__ __forceinline__ void gather_pair(const CellMatrix& km, const float* cell_e, const std::uint8_t* flags,
                                            const int* tiles, const Lvl& L0, const Field& a, const Field& b, Fn&& fn) {
  const Field x[2] = {a, b};
  NoPre none;
  auto each = [&](int e, int i, int j, int k, const Vec3f (&kx)[2], const Vec3f& dg, const Vec3f (&)[2], int) {
    fn(e, i, j, k, kx[0], kx[1], dg);
  };
  gather_tiles<2>(km, cell_e, flags, tiles, L0, x, none, each);
}

// calls fn(e, i, j, k, kx, dg, own, pv) for the nodes of level L that team t covers: kx = (K
// x) at the node (N), dg its Jacobi diagonal (N/mm), own = x at the node, pv = pre(true, e)
// (what the caller reads there, loaded before the products). Level 0 and coarse levels of
// at least tile_nodes nodes on the grid: tiles, a thread a node; other coarse levels:
// eight lanes a node, lane a adding the cell in which the node is corner a, summed by
// shuffles (whole warps run each round, so that every lane takes part in them)
template <typename Pre, typename Fn>
__device__ __forceinline__ void gather(const CellMatrix& km, const float* cell_e, const std::uint8_t* flags,
                                       const int* tiles, int tile_nodes, const Lvl& L, Team t, const Field& x, Pre&& pre,
                                       Fn&& fn) {
  // level 0 always runs on the whole grid (t is every thread): its listed tiles; a coarse
  // level of at least tile_nodes nodes on the whole grid: all its tiles (the lanes' cells
  // wait on more loads a pass there than a tile does)
  if (!L.coarse || (t.stride == int(gridDim.x * blockDim.x) && L.count >= tile_nodes)) {
    const Field one[1] = {x};
    auto each = [&](int e, int i, int j, int k, const Vec3f (&kx)[1], const Vec3f& dg, const Vec3f (&own)[1],
                    const auto& pv) { fn(e, i, j, k, kx[0], dg, own[0], pv); };
    gather_tiles<1>(km, cell_e, flags, L.coarse ? nullptr : tiles, L, one, pre, each);
    return;
  }
  const CellModuli ce{cell_e, L};
  const Load load{x, L};
  const CellMatrix ks{cell_matrix_shared()};  // the same entries as km, from shared memory
  const int lane = threadIdx.x & 31;
  const int tasks = 8 * L.count;
  for (int t0 = t.first - lane; t0 < tasks; t0 += t.stride) {
    const int q = t0 + lane, node = q >> 3, a = q & 7;
    const bool mine = q < tasks;
    const int e = L.off + (mine ? node : 0);
    const auto pv = pre(mine && a == 0, e);
    int i = 0, j = 0, k = 0;
    Vec3f kx{0, 0, 0}, dg{0, 0, 0};
    if (mine) {
      L.coords(node, i, j, k);
      deform::elastic_add_cell(ks, ce, load, L.n, L.scale, i, j, k, a, kx);
      deform::elastic_add_cell_diag(ks, ce, L.n, L.scale, i, j, k, a, dg);
    }
    for (int o = 1; o < 8; o <<= 1) {
      kx.x += __shfl_xor_sync(0xffffffffu, kx.x, o, 8);
      kx.y += __shfl_xor_sync(0xffffffffu, kx.y, o, 8);
      kx.z += __shfl_xor_sync(0xffffffffu, kx.z, o, 8);
      dg.x += __shfl_xor_sync(0xffffffffu, dg.x, o, 8);
      dg.y += __shfl_xor_sync(0xffffffffu, dg.y, o, 8);
      dg.z += __shfl_xor_sync(0xffffffffu, dg.z, o, 8);
    }
    if (mine && a == 0) fn(e, i, j, k, kx, dg, x.at(e), pv);
  }
}

// the node's Jacobi diagonal alone (a thread a node)
__device__ Vec3f diag_at(const CellMatrix& km, const float* cell_e, const Lvl& L, int i, int j, int k) {
  return deform::elastic_diag_node(km, CellModuli{cell_e, L}, L.n, L.scale, i, j, k);
}

// every block its tiles of level 0 (L): 1 at tiles[1 + n_tiles + t] where tile t holds a
// node that is not held, else 0 (list_tiles() reads the marks)
__device__ void mark_tiles(const std::uint8_t* flags, const Lvl& L, int* tiles) {
  const Vec3i tg = tile_grid(L);
  const int n = tg.x * tg.y * tg.z;
  const int li = threadIdx.x % kTileX, lj = (threadIdx.x / kTileX) % kTileY, lk = threadIdx.x / (kTileX * kTileY);
  for (int tile = blockIdx.x; tile < n; tile += gridDim.x) {
    const int i = (tile % tg.x) * kTileX + li, j = ((tile / tg.x) % tg.y) * kTileY + lj,
              k = (tile / (tg.x * tg.y)) * kTileZ + lk;
    const bool free = i < L.n.x && j < L.n.y && k < L.n.z && !(flags[L.at(i, j, k)] & kElasticHeld);
    const int any = __syncthreads_or(free);
    if (threadIdx.x == 0) tiles[1 + n + tile] = any;
  }
}

// block 0 alone, after the grid's barrier that follows mark_tiles(): the marked tiles'
// count into tiles[0] and their indices in order after it (gather_tiles()'s list); each
// thread takes a run of tiles and writes from the sum of the counts of the runs before it
__device__ void list_tiles(const Lvl& L, int* tiles) {
  __shared__ int warp_counts[32];
  const Vec3i tg = tile_grid(L);
  const int n = tg.x * tg.y * tg.z;
  const int run = (n + int(blockDim.x) - 1) / int(blockDim.x);
  const int first = int(threadIdx.x) * run, end = min(n, first + run);
  int count = 0;
  for (int t = first; t < end; ++t) count += tiles[1 + n + t] != 0;
  // this thread's first slot: the counts of the threads before it
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  int before = count;
  for (int o = 1; o < 32; o <<= 1) {
    const int v = __shfl_up_sync(0xffffffffu, before, o);
    if (lane >= o) before += v;
  }
  if (lane == 31) warp_counts[warp] = before;
  __syncthreads();
  int warps_before = 0;
  for (int w = 0; w < warp; ++w) warps_before += warp_counts[w];
  int slot = warps_before + before - count;
  for (int t = first; t < end; ++t)
    if (tiles[1 + n + t]) tiles[1 + slot++] = t;
  if (threadIdx.x + 1 == blockDim.x) tiles[0] = slot;
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

}  // namespace

}  // namespace palpsim::cuda
