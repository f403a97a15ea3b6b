// Inversion on the GPU: J on the VOI by the same Newton steps and cell search as
// server/deform/invert.cpp (invert_voxel() of deform_math.h); one thread per voxel, one
// launch (for one session or a batch of them), each search shared by the thread's warp.
#include <algorithm>
#include <climits>

#include "cuda/check.h"
#include "cuda/kernels.h"
#include "deform/invert_scatter.h"

namespace palpsim::cuda {

namespace {

// invert_search() of deform_math.h with each ring's cells split over the kWarps x 32
// threads of a group (a searching thread alone spent 0.3 ms on the Table 1 press's fold,
// its cells' loads one after another): a warp (kWarps 1, the search in place) or a whole
// block of kWarps warps (the queued search: a fold's queued voxels are a few thousand, too
// few to fill the GPU a warp each, and each ring's cells are a chain of dependent loads).
// Every thread of the group takes part and gets the same answer: per ring the lowest
// residual, the lowest ring index among equals, as the CPU's loop in ring order; pass 1
// visits only the rings of pass 0 with a cell whose box holds y, as the CPU. `shared`: a
// block's scratch for kWarps > 1 (GroupScratch), unused for a warp
template <int kWarps>
struct GroupScratch {
  float r[kWarps];
  int idx[kWarps];
  float p[kWarps][3];
  int held[kWarps];
};

template <int kWarps>
__device__ Vec3f group_search(const deform::Voi& voi, const float* ux, const float* uy, const float* uz,
                              const Vec3f& y, const Vec3f& guess, float& residual, GroupScratch<kWarps>* shared) {
  auto load_u = [&](int i, int j, int k) {
    if (!voi.contains(i, j, k)) return Vec3f{0, 0, 0};
    const int n = (k * voi.size.y + j) * voi.size.x + i;
    return Vec3f{ux[n], uy[n], uz[n]};
  };
  const int lane = int(threadIdx.x & 31);
  const int t = kWarps == 1 ? lane : int(threadIdx.x);
  int rmax;
  const Vec3i m = deform::search_centre(voi.size, guess, rmax);
  Vec3f best = guess;
  residual = 3.4e38f;
  int r_lo = rmax + 1, r_hi = -1;
  for (int pass = 0; pass < 2 && !(residual <= deform::kInvertSearchVox); ++pass)
    for (int r = pass ? r_lo : 0; r <= (pass ? r_hi : rmax) && !(residual <= deform::kInvertSearchVox); ++r) {
      // this thread's best of the ring, then the warp's, then the group's
      float br = 3.4e38f;
      int bi = INT_MAX;
      Vec3f bp = best;
      bool held = false;
      for (int idx = t, n = deform::search_ring_size(r); idx < n; idx += 32 * kWarps) {
        Vec3f p;
        float rc;
        if (!deform::search_cell(load_u, voi.size, m + deform::search_ring_cell(r, idx), y, pass, p, rc)) continue;
        held = true;
        if (rc < br) {
          br = rc;
          bi = idx;
          bp = p;
        }
      }
      held = __any_sync(0xffffffffu, held);
      for (int o = 16; o > 0; o >>= 1) {
        const float orr = __shfl_xor_sync(0xffffffffu, br, o);
        const int oi = __shfl_xor_sync(0xffffffffu, bi, o);
        const Vec3f op{__shfl_xor_sync(0xffffffffu, bp.x, o), __shfl_xor_sync(0xffffffffu, bp.y, o),
                       __shfl_xor_sync(0xffffffffu, bp.z, o)};
        if (orr < br || (orr == br && oi < bi)) {
          br = orr;
          bi = oi;
          bp = op;
        }
      }
      if constexpr (kWarps > 1) {
        const int w = int(threadIdx.x / 32);
        if (lane == 0) {
          shared->r[w] = br;
          shared->idx[w] = bi;
          shared->p[w][0] = bp.x;
          shared->p[w][1] = bp.y;
          shared->p[w][2] = bp.z;
          shared->held[w] = held;
        }
        __syncthreads();
        for (int q = 0; q < kWarps; ++q) {
          held = held || shared->held[q] != 0;
          if (shared->r[q] < br || (shared->r[q] == br && shared->idx[q] < bi)) {
            br = shared->r[q];
            bi = shared->idx[q];
            bp = Vec3f{shared->p[q][0], shared->p[q][1], shared->p[q][2]};
          }
        }
        __syncthreads();  // the scratch is written again next ring
      }
      if (held) {
        r_lo = min(r_lo, r);
        r_hi = max(r_hi, r);
      }
      if (br < residual) {
        residual = br;
        best = bp;
      }
    }
  return best;
}

// a session's displacement at a VOI-local voxel, zero outside the VOI (undeformed tissue)
struct ULoader {
  const deform::Voi* voi;
  const float *ux, *uy, *uz;
  __device__ Vec3f operator()(int i, int j, int k) const {
    if (!voi->contains(i, j, k)) return Vec3f{0, 0, 0};
    const int n = (k * voi->size.y + j) * voi->size.x + i;
    return Vec3f{ux[n], uy[n], uz[n]};
  }
};

// a session's intensity at a VOI-local voxel, clamped at the volume border
struct ILoader {
  const deform::Voi* voi;
  Vec3i size;
  const float* intensity;
  __device__ float operator()(int i, int j, int k) const {
    const int gi = min(max(voi->lo.x + i, 0), size.x - 1);
    const int gj = min(max(voi->lo.y + j, 0), size.y - 1);
    const int gk = min(max(voi->lo.z + k, 0), size.z - 1);
    return intensity[((long long)gk * size.y + gj) * size.x + gi];
  }
};

// VOI-local voxel of element e
__device__ __forceinline__ Vec3i element_voxel(const deform::Voi& voi, int e) {
  const int sxy = voi.size.x * voi.size.y;
  const int k = e / sxy, rem = e - k * sxy, j = rem / voi.size.x;
  return Vec3i{rem - j * voi.size.x, j, k};
}

// J at p for element e at voxel v: written, and what the reduction needs of it
__device__ __forceinline__ void write_j(const ILoader& load_i, const DeviceBuffers& b, int e, const Vec3i& v,
                                       const Vec3f& p, float& change, bool& broken) {
  const float jv = deform::sample_at_source<float>(load_i, p);
  b.j[e] = jv;
  // how far J moved from I here, and whether it is a number at all
  broken = !isfinite(jv);
  change = broken ? 0.0f : fabsf(jv - load_i(v.x, v.y, v.z));
}

// J at VOI-local element e of one session from displacement buffer src (e past the VOI:
// nothing); its residual r, |J - I| and whether J is not a number go to the reduction.
// Newton (invert_point) for every voxel; where it ends above kInvertSearchVox and the
// search is on, the voxel goes to the session's search queue (search_kernel searches
// it, a block per voxel, and writes its J), and only where the queue is full does
// the warp search here, for each lane that needs it in turn: a fold's voxels lie side by
// side, so searching in place left a few warps to search 32 voxels each one after another
// while the rest of the GPU idled.
// Every lane of the warp must call it (the ballots), and a warp's lanes belong to one
// session (a block never spans two sessions)
__device__ __forceinline__ void invert_element(const StepGeometry& geo, int src, int iterations, bool search,
                                               const DeviceBuffers& b, int e, float& r, float& change, bool& broken) {
  const deform::Voi& voi = geo.voi;
  const bool mine = e < int(voi.count());
  const ULoader load_u{&voi, b.u[src][0], b.u[src][1], b.u[src][2]};
  const ILoader load_i{&voi, geo.volume_size, b.intensity};
  const Vec3i v = mine ? element_voxel(voi, e) : Vec3i{0, 0, 0};
  const Vec3f y{float(v.x), float(v.y), float(v.z)};
  r = 0.0f;
  change = 0.0f;
  broken = false;
  Vec3f p = y;
  if (mine) p = deform::invert_point(load_u, y, iterations, r);
  unsigned need = __ballot_sync(0xffffffffu, search && mine && iterations > 0 && r > deform::kInvertSearchVox);
  const int lane = int(threadIdx.x & 31);
  bool queued = false;
  if (need && b.search_queue) {
    // one atomic per warp: the lanes that need the search take consecutive slots
    unsigned first = 0;
    if (lane == __ffs(need) - 1) first = atomicAdd(&b.counters->search_queued, unsigned(__popc(need)));
    first = __shfl_sync(0xffffffffu, first, __ffs(need) - 1);
    const unsigned slot = first + unsigned(__popc(need & ((1u << lane) - 1u)));
    if ((need >> lane) & 1u && slot < b.search_capacity) {
      int rmax;
      const Vec3i m = deform::search_centre(voi.size, y - deform::trilinear<Vec3f>(load_u, y), rmax);
      b.search_queue[slot] = InvertQueued{~0ull, e, p.x, p.y, p.z, r, m.x, m.y, m.z, INT_MAX, 0.0f, 0.0f, 0.0f};
      b.search_slot[e] = int(slot);
      queued = true;
    }
    need &= ~__ballot_sync(0xffffffffu, queued);
    // the box of the queued voxels, for the scatter: one atomic per warp and bound
    ScatterBounds& sb = b.counters->search_bounds;
    for (int a = 0; a < 3; ++a) {
      const unsigned lo = __reduce_max_sync(0xffffffffu, queued ? unsigned(INT_MAX - v[a]) : 0u);
      const unsigned hi = __reduce_max_sync(0xffffffffu, queued ? unsigned(v[a] + 1) : 0u);
      if (lane == 0 && hi) {
        atomicMax(&sb.lo_flip[a], lo);
        atomicMax(&sb.hi_plus[a], hi);
      }
    }
  }
  // the largest |u| per axis over the VOI, for the scatter: a warp's maximum, and an
  // atomic only where it beats the maximum seen so far (a stale read costs an atomic, no
  // more); NaN's bits order above every number, so a broken field widens the scatter to
  // the whole VOI
  if (search && b.search_queue) {
    const Vec3f uv = mine ? load_u(v.x, v.y, v.z) : Vec3f{0.0f, 0.0f, 0.0f};
    unsigned* umax = b.counters->search_bounds.umax_bits;
    for (int a = 0; a < 3; ++a) {
      const unsigned m = __reduce_max_sync(0xffffffffu, __float_as_uint(fabsf(uv[a])));
      if (lane == 0 && m > *(volatile unsigned*)&umax[a]) atomicMax(&umax[a], m);
    }
  }
  // the scatter finds queued voxels by this map: every other voxel is marked not queued
  if (mine && b.search_slot && !queued) b.search_slot[e] = -1;
  // the queue is full: the warp searches for its lanes in turn
  while (need) {
    const int who = __ffs(need) - 1;
    need &= need - 1;
    const Vec3f yw{__shfl_sync(0xffffffffu, y.x, who), __shfl_sync(0xffffffffu, y.y, who),
                   __shfl_sync(0xffffffffu, y.z, who)};
    float rs;
    const Vec3f q = group_search<1>(voi, load_u.ux, load_u.uy, load_u.uz, yw, yw - deform::trilinear<Vec3f>(load_u, yw),
                                    rs, nullptr);
    if (lane == who && rs < r) {
      r = rs;
      p = q;
    }
  }
  // a queued voxel's J, residual and change come from the search kernel
  if (queued) r = 0.0f;
  if (mine && !queued) write_j(load_i, b, e, v, p, change, broken);
}

// the warp's unresolved and non-finite voxels, largest residual and largest change of
// the image into the session's counters: one atomic per warp and counter
__device__ __forceinline__ void invert_reduce(const DeviceBuffers& b, float r, float change, bool broken) {
  // unresolved voxels of the warp, counted before r is reduced
  const unsigned bad = __popc(__ballot_sync(0xffffffffu, r > deform::kInvertResolvedVox));
  const unsigned nonfinite = __popc(__ballot_sync(0xffffffffu, broken));
  // the largest residual: warp maximum, then one atomic per warp (float bits order as unsigned for r >= 0)
  // and the largest change of the image, likewise
  for (int o = 16; o > 0; o >>= 1) {
    r = fmaxf(r, __shfl_down_sync(0xffffffffu, r, o));
    change = fmaxf(change, __shfl_down_sync(0xffffffffu, change, o));
  }
  if ((threadIdx.x & 31) == 0) {
    atomicMax(&b.counters->residual_bits, __float_as_uint(r));
    atomicMax(&b.counters->change_bits, __float_as_uint(change));
    if (bad) atomicAdd(&b.counters->unresolved, (unsigned long long)bad);
    if (nonfinite) atomicAdd(&b.counters->nonfinite, (unsigned long long)nonfinite);
  }
}

__global__ void __launch_bounds__(256) invert_kernel(StepGeometry geo, int src, int iterations, bool search,
                                                     DeviceBuffers b) {
  const int e = int(blockIdx.x * blockDim.x + threadIdx.x);  // VOIs hold < 2^31 voxels (checked at bind)
  float r = 0.0f, change = 0.0f;
  bool broken = false;
  invert_element(geo, src, iterations, search, b, e, r, change, broken);
  invert_reduce(b, r, change, broken);
}

// the inversion of several sessions in one launch (batch.cu says why): blockIdx.y is
// the session, each of its elements as in the kernel above
__global__ void __launch_bounds__(256) invert_batch_kernel(const BatchItem* __restrict__ items, int iterations,
                                                           bool search) {
  const BatchItem& item = items[blockIdx.y];
  const int e = int(blockIdx.x * blockDim.x + threadIdx.x);
  float r = 0.0f, change = 0.0f;
  bool broken = false;
  invert_element(item.geo, item.invert_src, iterations, search, item.b, e, r, change, broken);
  invert_reduce(item.b, r, change, broken);
}

// ---- the scatter: each queued voxel's source without walking the rings ----
// Lumbar presses queue a few hundred voxels a step whose sources lie 9-13 rings (up to
// 21) from y - u(y) (make_phantom, 25 mm along the midline, VOI 64), so the ring search
// read 10,000-80,000 cells a voxel to solve about 9. Instead every cell of the search
// ([-1, size - 1]^3 lowest corners, within the bounds scatter_cells() gives) goes to the
// queued voxels its deformed box holds, each such pair is solved from the cell's centre
// (pass 0) by a thread of its own, and each voxel then takes, among its cells in
// rings up to the first ring holding a source within kInvertSearchVox, the lowest
// residual, then ring, then index in the ring: the ring search's own pick
// (deform_math.h's functions, the same float operations; a CPU test checks the rule
// against invert_search() bit for bit). A voxel without such a ring, and every voxel of
// a step where the scatter gave up (a full list, a cell whose box spans more than
// kScatterMaxVoxels voxels, a ring or index beyond the key's bits), takes the ring search.

// the pick's order as one 64-bit key: residual (float bits order as unsigned for r >= 0),
// ring (10 bits), index in the ring (22 bits)
__device__ __forceinline__ unsigned long long pick_key(float rc, int ring, int idx) {
  return ((unsigned long long)__float_as_uint(rc) << 32) | ((unsigned long long)ring << 22) | unsigned(idx);
}

// cells t0, t0 + stride, ... of one session's search: each to the queued voxels its box holds
__device__ __forceinline__ void scatter_cells(const StepGeometry& geo, int src, const DeviceBuffers& b, unsigned t0,
                                              unsigned stride) {
  if (b.counters->search_queued == 0) return;
  const deform::Voi& voi = geo.voi;
  const Vec3i size = voi.size;
  const ULoader load_u{&voi, b.u[src][0], b.u[src][1], b.u[src][2]};
  // only cells whose box may hold a queued voxel (deform::scatter_cell_range()): a press
  // moves tissue mostly along one axis, so this is a slab of the VOI, not all of it
  const ScatterBounds& sb = b.counters->search_bounds;
  Vec3i first, extent;
  for (int a = 0; a < 3; ++a) {
    int last;
    deform::scatter_cell_range(INT_MAX - int(sb.lo_flip[a]), int(sb.hi_plus[a]) - 1,
                               __uint_as_float(sb.umax_bits[a]), size[a], first[a], last);
    extent[a] = max(0, last - first[a] + 1);
  }
  const unsigned cx = unsigned(extent.x), cxy = cx * unsigned(extent.y);
  const unsigned cells = cxy * unsigned(extent.z);
  for (unsigned t = t0; t < cells; t += stride) {
    const Vec3i o{first.x + int(t % cx), first.y + int((t / cx) % unsigned(extent.y)), first.z + int(t / cxy)};
    Vec3f c[8], lo, hi;
    deform::load_cell(load_u, o.x, o.y, o.z, c);
    deform::cell_box(c, o, lo, hi);
    int from[3], to[3];
    const long long span = deform::cell_voxel_span(lo, hi, size, from, to);
    if (span == 0) continue;
    if (!(span <= deform::kScatterMaxVoxels)) {
      b.counters->search_spill = 1;
      continue;
    }
    for (int k = from[2]; k <= to[2]; ++k)
      for (int j = from[1]; j <= to[1]; ++j)
        for (int i = from[0]; i <= to[0]; ++i) {
          const int slot = b.search_slot[(k * size.y + j) * size.x + i];
          if (slot < 0) continue;
          const Vec3f y{float(i), float(j), float(k)};
          if (!deform::box_holds(lo, hi, y)) continue;
          const InvertQueued& q = b.search_queue[slot];
          const Vec3i d{o.x - q.mx, o.y - q.my, o.z - q.mz};
          const int ring = max(abs(d.x), max(abs(d.y), abs(d.z)));
          const int idx = deform::search_ring_index(ring, d);
          if (ring >= (1 << 10) || idx >= (1 << 22)) {
            b.counters->search_spill = 1;
            continue;
          }
          const unsigned at = atomicAdd(&b.counters->search_candidates, 1u);
          if (at >= b.candidate_capacity) {
            b.counters->search_spill = 1;
            continue;
          }
          // solved by solve_candidates(), a thread each
          b.search_candidates[at] = InvertCandidate{slot, ring, idx, o.x, o.y, o.z, 0.0f, 0.0f, 0.0f, 0.0f};
        }
  }
}

// candidates t0, t0 + stride, ...: each solved in its cell from the centre (pass 0, as
// search_cell() does), and the first ring with a source within kInvertSearchVox kept per
// voxel. A thread per pair, not per cell: a cell stretched over a fold holds dozens of
// queued voxels, and their solves one after another in one thread (12 Newton steps each,
// a chain of dependent operations) kept a few threads busy while the rest of the GPU
// idled
__device__ __forceinline__ void solve_candidates(const StepGeometry& geo, int src, const DeviceBuffers& b, unsigned t0,
                                                 unsigned stride) {
  if (b.counters->search_spill) return;
  const deform::Voi& voi = geo.voi;
  const ULoader load_u{&voi, b.u[src][0], b.u[src][1], b.u[src][2]};
  const unsigned n = min(b.counters->search_candidates, b.candidate_capacity);
  for (unsigned t = t0; t < n; t += stride) {
    InvertCandidate& c = b.search_candidates[t];
    InvertQueued& q = b.search_queue[c.slot];
    const Vec3i v = element_voxel(voi, q.e);
    Vec3f corners[8];
    deform::load_cell(load_u, c.ox, c.oy, c.oz, corners);
    float rc;
    const Vec3f p = deform::invert_in_cell(corners, Vec3i{c.ox, c.oy, c.oz}, Vec3f{float(v.x), float(v.y), float(v.z)},
                                           false, rc);
    c.rc = rc;
    c.px = p.x;
    c.py = p.y;
    c.pz = p.z;
    if (rc <= deform::kInvertSearchVox) atomicMin(&q.last_ring, c.ring);
  }
}

// candidates t0, t0 + stride, ...: `write` false, each in a ring up to its voxel's first
// ring with a source offers its key; true, the one whose key won writes its source
__device__ __forceinline__ void pick_candidates(const DeviceBuffers& b, bool write, unsigned t0, unsigned stride) {
  if (b.counters->search_spill) return;
  const unsigned n = min(b.counters->search_candidates, b.candidate_capacity);
  for (unsigned t = t0; t < n; t += stride) {
    const InvertCandidate c = b.search_candidates[t];
    InvertQueued& q = b.search_queue[c.slot];
    // the ring search keeps a cell only below its start of 3.4e38 (NaN never)
    if (c.ring > q.last_ring || !(c.rc < 3.4e38f)) continue;
    const unsigned long long key = pick_key(c.rc, c.ring, c.idx);
    if (!write) {
      atomicMin(&q.key, key);
    } else if (key == q.key) {
      q.sx = c.px;
      q.sy = c.py;
      q.sz = c.pz;
    }
  }
}

__global__ void __launch_bounds__(256) scatter_kernel(StepGeometry geo, int src, DeviceBuffers b) {
  scatter_cells(geo, src, b, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

// blockIdx.y is the session
__global__ void __launch_bounds__(256) scatter_batch_kernel(const BatchItem* __restrict__ items) {
  const BatchItem& item = items[blockIdx.y];
  if (!item.b.search_queue) return;
  scatter_cells(item.geo, item.invert_src, item.b, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

__global__ void __launch_bounds__(256) solve_kernel(StepGeometry geo, int src, DeviceBuffers b) {
  solve_candidates(geo, src, b, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

// blockIdx.y is the session
__global__ void __launch_bounds__(256) solve_batch_kernel(const BatchItem* __restrict__ items) {
  const BatchItem& item = items[blockIdx.y];
  if (!item.b.search_queue) return;
  solve_candidates(item.geo, item.invert_src, item.b, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

__global__ void __launch_bounds__(256) pick_kernel(DeviceBuffers b, bool write) {
  pick_candidates(b, write, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

// blockIdx.y is the session
__global__ void __launch_bounds__(256) pick_batch_kernel(const BatchItem* __restrict__ items, bool write) {
  const BatchItem& item = items[blockIdx.y];
  if (!item.b.search_queue) return;
  pick_candidates(item.b, write, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

// warps of the block that searches one queued voxel (group_search says why)
constexpr int kSearchWarps = 4;
constexpr int kSearchThreads = 32 * kSearchWarps;

// the cell search of one session's queued voxels (invert_element queued them), a block
// per voxel, the launch's `blocks` blocks striding over the queue: the same search from
// the same guess as in place, the lower residual of it and Newton's kept (as
// invert_voxel()), then J there; the block's largest residual and change and its
// unresolved and non-finite voxels into the counters at the end
__device__ __forceinline__ void search_queued(const StepGeometry& geo, int src, const DeviceBuffers& b, int block,
                                              int blocks) {
  __shared__ GroupScratch<kSearchWarps> scratch;
  const deform::Voi& voi = geo.voi;
  const ULoader load_u{&voi, b.u[src][0], b.u[src][1], b.u[src][2]};
  const ILoader load_i{&voi, geo.volume_size, b.intensity};
  const unsigned n = min(b.counters->search_queued, b.search_capacity);
  const bool spill = b.counters->search_spill != 0;
  float r_max = 0.0f, change_max = 0.0f;
  unsigned long long bad = 0, nonfinite = 0;
  unsigned scattered = 0;
  for (unsigned q = unsigned(block); q < n; q += unsigned(blocks)) {
    const InvertQueued in = b.search_queue[q];
    const Vec3i v = element_voxel(voi, in.e);
    const Vec3f y{float(v.x), float(v.y), float(v.z)};
    float rs;
    Vec3f s;
    if (!spill && in.last_ring != INT_MAX) {
      // the scatter's pick: the ring search's answer (pick_kernel says why)
      rs = __uint_as_float(unsigned(in.key >> 32));
      s = Vec3f{in.sx, in.sy, in.sz};
      ++scattered;
    } else {
      s = group_search<kSearchWarps>(voi, load_u.ux, load_u.uy, load_u.uz, y, y - deform::trilinear<Vec3f>(load_u, y),
                                     rs, &scratch);
    }
    float r = in.r;
    Vec3f p{in.px, in.py, in.pz};
    if (rs < r) {
      r = rs;
      p = s;
    }
    if (threadIdx.x == 0) {
      float change;
      bool broken;
      write_j(load_i, b, in.e, v, p, change, broken);
      r_max = fmaxf(r_max, r);
      change_max = fmaxf(change_max, change);
      bad += r > deform::kInvertResolvedVox;
      nonfinite += broken;
    }
  }
  if (threadIdx.x == 0 && unsigned(block) < n) {
    atomicMax(&b.counters->residual_bits, __float_as_uint(r_max));
    atomicMax(&b.counters->change_bits, __float_as_uint(change_max));
    if (bad) atomicAdd(&b.counters->unresolved, bad);
    if (nonfinite) atomicAdd(&b.counters->nonfinite, nonfinite);
    if (scattered) atomicAdd(&b.counters->search_scattered, scattered);
  }
}

__global__ void __launch_bounds__(kSearchThreads) search_kernel(StepGeometry geo, int src, DeviceBuffers b) {
  search_queued(geo, src, b, int(blockIdx.x), int(gridDim.x));
}

// blockIdx.y is the session
__global__ void __launch_bounds__(kSearchThreads) search_batch_kernel(const BatchItem* __restrict__ items) {
  const BatchItem& item = items[blockIdx.y];
  if (!item.b.search_queue) return;
  search_queued(item.geo, item.invert_src, item.b, int(blockIdx.x), int(gridDim.x));
}

// blocks of the search kernel: eight per multiprocessor in all, at least 8 per session,
// so that a fold's few hundred to few thousand voxels spread over the whole GPU
unsigned search_blocks(int sessions) {
  int dev = 0, sms = 0;
  PALPSIM_CUDA_CHECK(cudaGetDevice(&dev));
  PALPSIM_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev));
  return unsigned(std::max(8, 8 * sms / std::max(1, sessions)));
}

}  // namespace

void launch_invert(const StepGeometry& g, int src, int iterations, bool search, const DeviceBuffers& b,
                   cudaStream_t stream) {
  const long long n = g.voi.count();
  const int threads = 256;
  invert_kernel<<<unsigned((n + threads - 1) / threads), threads, 0, stream>>>(g, src, iterations, search, b);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
  if (search && iterations > 0 && b.search_queue) {
    const long long cells = (long long)(g.voi.size.x + 1) * (g.voi.size.y + 1) * (g.voi.size.z + 1);
    scatter_kernel<<<unsigned((cells + threads - 1) / threads), threads, 0, stream>>>(g, src, b);
    const unsigned picks = search_blocks(1);
    solve_kernel<<<picks, threads, 0, stream>>>(g, src, b);
    pick_kernel<<<picks, threads, 0, stream>>>(b, false);
    pick_kernel<<<picks, threads, 0, stream>>>(b, true);
    search_kernel<<<search_blocks(1), kSearchThreads, 0, stream>>>(g, src, b);
    PALPSIM_CUDA_CHECK(cudaGetLastError());
  }
}

void launch_invert_batch(const BatchItem* items, int n, unsigned max_count, int iterations, bool search,
                         cudaStream_t stream) {
  if (n < 1) return;
  const unsigned threads = 256;
  invert_batch_kernel<<<dim3((max_count + threads - 1) / threads, unsigned(n)), threads, 0, stream>>>(items, iterations, search);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
  if (search && iterations > 0) {
    // about a thread per cell of the largest VOI, at most 4096 blocks in all: each
    // session's threads stride over its own cells
    const unsigned per = std::max(1u, std::min((max_count + threads - 1) / threads + 1, 4096u / unsigned(n) + 1));
    scatter_batch_kernel<<<dim3(per, unsigned(n)), threads, 0, stream>>>(items);
    const unsigned picks = search_blocks(n);
    solve_batch_kernel<<<dim3(picks, unsigned(n)), threads, 0, stream>>>(items);
    pick_batch_kernel<<<dim3(picks, unsigned(n)), threads, 0, stream>>>(items, false);
    pick_batch_kernel<<<dim3(picks, unsigned(n)), threads, 0, stream>>>(items, true);
    search_batch_kernel<<<dim3(search_blocks(n), unsigned(n)), kSearchThreads, 0, stream>>>(items);
    PALPSIM_CUDA_CHECK(cudaGetLastError());
  }
}

}  // namespace palpsim::cuda
