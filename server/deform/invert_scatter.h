// The inversion's cell search for many voxels at once, run backwards (the CPU backend's;
// cuda/invert.cu runs the same rule in its scatter, solve and pick kernels): instead of
// walking rings of cells around each voxel (a lumbar press's sources lie 9-13 rings
// away, up to 21: 10,000-80,000 cells read per voxel to solve about 9), every cell that
// can reach a queued voxel is visited once and solved for each queued voxel its deformed
// box holds. On a press over L3 30 mm deep (798 voxels searched, VOI 64, the 2-core VM)
// the CPU's inversion takes 59 ms with the scatter, 276 ms with the ring search alone and
// 45 ms with Newton alone (no search).
#pragma once

#include <algorithm>
#include <climits>
#include <cmath>
#include <vector>

#include "deform/deform_math.h"

namespace palpsim::deform {

/// Voxels a cell's deformed box may span before the scatter gives up for the step (a
/// cell stretched over thousands of voxels: the tip metres away), and every queued voxel
/// takes the ring search; both backends.
constexpr long long kScatterMaxVoxels = 512;

/// The lowest corners, along one axis of `size` voxels, of the cells whose deformed box
/// may hold a queued voxel in [qlo, qhi]: a cell's corners move at most `umax` along the
/// axis, so its box lies within [o - umax, o + 1 + umax]; one cell more each side covers
/// the float rounding of the corners' positions. umax above 1e6 or NaN: every cell,
/// -1 .. size - 1. [first, last] (empty where last < first); both backends' scatter.
PALPSIM_HD void scatter_cell_range(int qlo, int qhi, float umax, int size, int& first, int& last) {
  first = -1;
  last = size - 1;
  if (!(umax <= 1e6f)) return;
  const int f = int(floorf(float(qlo) - 1.0f - umax - kInvertSearchVox)) - 1;
  const int l = int(ceilf(float(qhi) + umax + kInvertSearchVox)) + 1;
  first = f > first ? f : first;
  last = l < last ? l : last;
}

/// The VOI voxels within a cell's deformed box [lo, hi] grown by kInvertSearchVox, from[a]
/// to to[a] along each axis (box_holds() then decides each one exactly); returns how many
/// (0: none); both backends' scatter.
PALPSIM_HD long long cell_voxel_span(const Vec3f& lo, const Vec3f& hi, const Vec3i& size, int from[3], int to[3]) {
  long long span = 1;
  for (int a = 0; a < 3; ++a) {
    from[a] = int(fmaxf(0.0f, ceilf(lo[a] - kInvertSearchVox)));
    to[a] = int(fminf(float(size[a] - 1), floorf(hi[a] + kInvertSearchVox)));
    span *= to[a] >= from[a] ? to[a] - from[a] + 1 : 0;
  }
  return span;
}

/// A voxel Newton left above kInvertSearchVox, queued for scatter_search().
struct SearchVoxel {
  Vec3i v;                    // VOI-local voxel (y)
  Vec3i centre;               // the ring search's centre cell: search_centre() of y - u(y)
  Vec3f newton_p;             // Newton's source (VOI-local voxel)
  float newton_r = 0;         // its residual (voxel)
  bool found = false;         // the scatter's pick is the ring search's answer
  float residual = 3.4e38f;   // that pick's residual (voxel)
  Vec3f p{0, 0, 0};           // and its source
};

/// The first rings of invert_search()'s pass 0 around centre m, rings 0 to max_ring: true,
/// with p and its residual, where one of them holds a source within kInvertSearchVox
/// (invert_search() ends at that ring with the same answer, the same cells solved in the
/// same order); false where the source lies further or pass 1 decides. The CPU backend
/// asks this (rings 0 and 1) before the scatter: with one Newton step thousands of voxels
/// stall with their source in the next cell, where 27 cells beat a scatter over the VOI
/// (the accuracy bench's press, one step: 44 ms a step instead of 53 with the scatter alone).
template <typename LoadU>
bool invert_search_near(const LoadU& load_u, const Vec3i& size, const Vec3f& y, const Vec3i& m, int max_ring,
                        Vec3f& p, float& residual) {
  residual = 3.4e38f;
  int r_lo = max_ring + 1, r_hi = -1;  // pass 1's rings: not needed here
  for (int r = 0; r <= max_ring; ++r) {
    search_ring(load_u, size, m, y, 0, r, p, residual, r_lo, r_hi);
    if (residual <= kInvertSearchVox) return true;
  }
  return false;
}

/// For every queued voxel, the answer of invert_search() where it is decided on pass 0
/// (a cell's centre start gets within kInvertSearchVox): among its cells in rings up to
/// the first such ring, the lowest residual, then the lowest ring, then the lowest index
/// in the ring (search_ring_index()), which is the ring search's own pick, bit for bit
/// (tests/unit/deform_untangle_test.cpp). Sets `found` on those voxels; the rest need the
/// ring search's second pass. `slot` holds each VOI voxel's index in `queue`, -1 where not
/// queued. Returns false, with nothing found, where a cell's box spans more than
/// kScatterMaxVoxels voxels.
template <typename LoadU>
bool scatter_search(const LoadU& load_u, const Vec3i& size, std::vector<SearchVoxel>& queue,
                    const std::vector<int>& slot) {
  if (queue.empty()) return true;
  // only cells whose box may hold a queued voxel (scatter_cell_range(); NaN: the whole VOI)
  Vec3f umax{0, 0, 0};
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j < size.y; ++j)
      for (int i = 0; i < size.x; ++i) {
        const Vec3f u = load_u(i, j, k);
        for (int a = 0; a < 3; ++a) umax[a] = std::fabs(u[a]) > umax[a] || std::isnan(u[a]) ? std::fabs(u[a]) : umax[a];
      }
  Vec3i qlo = size, qhi{-1, -1, -1};
  for (const SearchVoxel& q : queue)
    for (int a = 0; a < 3; ++a) {
      qlo[a] = std::min(qlo[a], q.v[a]);
      qhi[a] = std::max(qhi[a], q.v[a]);
    }
  Vec3i first, last;
  for (int a = 0; a < 3; ++a) scatter_cell_range(qlo[a], qhi[a], umax[a], size[a], first[a], last[a]);
  // every such cell, solved from its centre (pass 0) for each queued voxel its box holds
  struct Candidate {
    int slot, ring, idx;
    float rc;
    Vec3f p;
  };
  std::vector<Candidate> cand;
  std::vector<int> source_ring(queue.size(), INT_MAX);  // first ring with a source within kInvertSearchVox
  for (int oz = first.z; oz <= last.z; ++oz)
    for (int oy = first.y; oy <= last.y; ++oy)
      for (int ox = first.x; ox <= last.x; ++ox) {
        const Vec3i o{ox, oy, oz};
        Vec3f c[8], lo, hi;
        load_cell(load_u, ox, oy, oz, c);
        cell_box(c, o, lo, hi);
        int from[3], to[3];
        const long long span = cell_voxel_span(lo, hi, size, from, to);
        if (span == 0) continue;
        if (!(span <= kScatterMaxVoxels)) return false;
        for (int k = from[2]; k <= to[2]; ++k)
          for (int j = from[1]; j <= to[1]; ++j)
            for (int i = from[0]; i <= to[0]; ++i) {
              const int s = slot[std::size_t((k * size.y + j) * size.x + i)];
              if (s < 0) continue;
              const Vec3f y{float(i), float(j), float(k)};
              if (!box_holds(lo, hi, y)) continue;
              const Vec3i& m = queue[std::size_t(s)].centre;
              const Vec3i d{ox - m.x, oy - m.y, oz - m.z};
              const int ring = std::max({std::abs(d.x), std::abs(d.y), std::abs(d.z)});
              Candidate q{s, ring, search_ring_index(ring, d), 0.0f, {}};
              q.p = invert_in_cell(c, o, y, false, q.rc);
              // the ring search keeps a cell only below its start of 3.4e38 (NaN never)
              if (!(q.rc < 3.4e38f)) continue;
              if (q.rc <= kInvertSearchVox) source_ring[std::size_t(s)] = std::min(source_ring[std::size_t(s)], ring);
              cand.push_back(q);
            }
      }
  // each voxel's pick among its cells in rings up to its first with a source
  std::vector<const Candidate*> best(queue.size(), nullptr);
  for (const Candidate& q : cand) {
    if (q.ring > source_ring[std::size_t(q.slot)]) continue;
    const Candidate*& b = best[std::size_t(q.slot)];
    if (!b || q.rc < b->rc || (q.rc == b->rc && (q.ring < b->ring || (q.ring == b->ring && q.idx < b->idx)))) b = &q;
  }
  for (std::size_t s = 0; s < queue.size(); ++s) {
    if (source_ring[s] == INT_MAX) continue;  // no source on pass 0: pass 1 decides
    queue[s].found = true;
    queue[s].residual = best[s]->rc;
    queue[s].p = best[s]->p;
  }
  return true;
}

}  // namespace palpsim::deform
