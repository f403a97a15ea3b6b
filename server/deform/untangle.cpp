// Untangling on the CPU (issue 8, section 4): removes the folds that relaxation leaves
// next to the grabbed element, so that the inversion has one answer everywhere.
#include <algorithm>

#include "deform/cpu_backend.h"

namespace palpsim::deform {

namespace {

// flags of UntangleState: bit 0 the element is a corner of a folded cell (a seed of this
// round), bit 1 it moved in an earlier sweep
constexpr std::uint8_t kSeed = 1, kMoved = 2;

}  // namespace

UntangleStats untangle_cpu(const Patient& p, const ChainMailStats& st, CpuState& s) {
  UntangleStats out;
  const Voi& voi = st.voi;
  const Grid& grid = p.grid;
  const Vec3i g = st.grabbed_vox - voi.lo;
  const long long n = voi.count();
  if (st.grabbed_in_bone || n == 0) return out;
  auto soft = [&](int i, int j, int k) {
    return p.bone.data[grid.index(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k)] == 0;
  };
  auto load_u = [&](int i, int j, int k) { return voi.contains(i, j, k) ? s.u[voi.index(i, j, k)] : Vec3f{0, 0, 0}; };
  std::fill_n(s.untangle_flags.begin(), n, std::uint8_t(0));
  // the field as relaxation left it, to return to if untangling ends with more folds
  std::copy_n(s.u.begin(), n, s.u_next.begin());
  // the box of the elements that can be active (the folded cells' corners and the elements
  // moved, grown by one): the sweeps visit only it, as the CUDA kernel does
  Vec3i lo{voi.size.x, voi.size.y, voi.size.z}, hi{-1, -1, -1};
  auto grow = [&](int i, int j, int k) {
    lo = Vec3i{std::min(lo.x, i), std::min(lo.y, j), std::min(lo.z, k)};
    hi = Vec3i{std::max(hi.x, i), std::max(hi.y, j), std::max(hi.z, k)};
  };
  for (int round = 0;; ++round) {
    // the folded cells (all eight corners soft and in the VOI): count them, mark their corners
    long long folded = 0;
    std::fill_n(s.cell_folded.begin(), n, std::uint8_t(0));
    for (int k = 0; k + 1 < voi.size.z; ++k)
      for (int j = 0; j + 1 < voi.size.y; ++j)
        for (int i = 0; i + 1 < voi.size.x; ++i)
          if (untangle_cell_soft(soft, i, j, k) && cell_min_det(load_u, i, j, k) <= kUntangleFoldDet) {
            s.cell_folded[voi.index(i, j, k)] = 1;
            ++folded;
            grow(i, j, k);
            grow(i + 1, j + 1, k + 1);
          }
    if (round == 0) out.folded_before = folded;
    out.folded_after = folded;
    out.rounds = round;
    if (folded > out.folded_before && round == kUntangleMaxRounds) {
      // worse than relaxation alone: its field back (what moved lies in the box)
      for (int k = lo.z; k <= hi.z; ++k)
        for (int j = lo.y; j <= hi.y; ++j)
          for (int i = lo.x; i <= hi.x; ++i) s.u[voi.index(i, j, k)] = s.u_next[voi.index(i, j, k)];
      out.folded_after = out.folded_before;
      out.reverted = true;
    }
    if (folded == 0 || round == kUntangleMaxRounds) return out;
    for (int k = lo.z; k <= hi.z; ++k)
      for (int j = lo.y; j <= hi.y; ++j)
        for (int i = lo.x; i <= hi.x; ++i) {
          std::uint8_t& f = s.untangle_flags[voi.index(i, j, k)];
          const bool seed =
              untangle_is_seed([&](int a, int b, int c) { return s.cell_folded[voi.index(a, b, c)] != 0; }, voi, i, j, k);
          f = std::uint8_t((f & kMoved) | (seed ? kSeed : 0));
        }
    // Jacobi sweeps: each free element that is a seed, or whose neighbour towards the
    // grabbed element has moved, is pulled towards those neighbours; a quiet sweep ends the round
    for (int sweep = 0; sweep < kUntangleMaxSweeps; ++sweep) {
      s.changes.clear();
      const Vec3i blo{std::max(lo.x - 1, 0), std::max(lo.y - 1, 0), std::max(lo.z - 1, 0)};
      const Vec3i bhi{std::min(hi.x + 1, voi.size.x - 1), std::min(hi.y + 1, voi.size.y - 1),
                      std::min(hi.z + 1, voi.size.z - 1)};
      for (int k = blo.z; k <= bhi.z; ++k)
        for (int j = blo.y; j <= bhi.y; ++j)
          for (int i = blo.x; i <= bhi.x; ++i) {
            const Vec3i e{i, j, k};
            if (e == g || !soft(i, j, k)) continue;
            const long long ei = voi.index(i, j, k);
            bool active = (s.untangle_flags[ei] & kSeed) != 0;
            Vec3f v = s.u[ei];
            for (int a = 0; a < 3; ++a) {
              if (e[a] == g[a]) continue;
              Vec3i nb = e;
              nb[a] += e[a] > g[a] ? -1 : 1;  // the neighbour towards the grabbed element
              if (!soft(nb.x, nb.y, nb.z)) continue;
              const long long ni = voi.index(nb.x, nb.y, nb.z);
              active = active || (s.untangle_flags[ni] & kMoved) != 0;
              untangle_pull(v, s.u[ni], a, e[a] > g[a]);
            }
            if (active && v != s.u[ei]) s.changes.emplace_back(ei, v);
          }
      ++out.sweeps;
      if (s.changes.empty()) break;
      const long long sx = voi.size.x, sxy = sx * voi.size.y;
      for (const auto& [ei, v] : s.changes) {
        s.u[ei] = v;
        out.moved += (s.untangle_flags[ei] & kMoved) == 0;
        s.untangle_flags[ei] |= kMoved;
        grow(int(ei % sx), int((ei / sx) % voi.size.y), int(ei / sxy));
      }
    }
  }
}

}  // namespace palpsim::deform
