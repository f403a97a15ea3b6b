// Relaxation on the CPU: explicit diffusion of the displacement weighted by the
// paper's material function.
#include <algorithm>
#include <cstdlib>
#include <utility>

#include "deform/cpu_backend.h"

namespace palpsim::deform {

void relax_cpu(const Patient& p, const ChainMailStats& st, int iterations, float step, float threshold,
               float width, CpuState& s) {
  const Voi& voi = st.voi;
  const Grid& grid = p.grid;
  const Vec3i g = st.grabbed_vox - voi.lo;
  const long long g_idx = voi.index(g.x, g.y, g.z);
  // the step times the material function, once per element (those step 0 reaches: every
  // one that any step updates)
  const int reach0 = relax_reach(s.reach, 0, iterations);
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        if (std::abs(i - g.x) + std::abs(j - g.y) + std::abs(k - g.z) > reach0) continue;
        const std::size_t gi = grid.index(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k);
        s.weight[voi.index(i, j, k)] =
            step * material_weight(p.intensity.data[gi], p.bone.data[gi] != 0, threshold, width);
      }
  for (int it = 0; it < iterations; ++it) {
    // one Jacobi step of u' = u + w (sum of six neighbours - 6 u), u = 0 outside the VOI,
    // on the elements within reach of the grabbed element (along each row, the run
    // [g.x - rest, g.x + rest]); the others are 0 and are copied as such
    const int reach = relax_reach(s.reach, it, iterations);
    for (int k = 0; k < voi.size.z; ++k)
      for (int j = 0; j < voi.size.y; ++j) {
        const long long row = voi.index(0, j, k);
        const int rest = reach - std::abs(j - g.y) - std::abs(k - g.z);
        const int i0 = rest < 0 ? voi.size.x : std::max(0, g.x - rest);
        const int i1 = rest < 0 ? voi.size.x : std::min(voi.size.x, g.x + rest + 1);
        std::copy(s.u.begin() + row, s.u.begin() + row + i0, s.u_next.begin() + row);
        std::copy(s.u.begin() + row + i1, s.u.begin() + row + voi.size.x, s.u_next.begin() + row + i1);
        // a row off the VOI's j and k faces has all four neighbours across, so only its
        // first and last elements test the i faces (the same sums in the same order)
        const bool inner = j > 0 && j + 1 < voi.size.y && k > 0 && k + 1 < voi.size.z;
        const long long sx = voi.size.x, sxy = sx * voi.size.y;
        const Vec3f* u = s.u.data();
        for (int i = i0; i < i1; ++i) {
          const long long e = row + i;
          const float w = s.weight[e];
          if (e == g_idx || w == 0.0f) {
            s.u_next[e] = u[e];
            continue;
          }
          Vec3f sum6{0, 0, 0};
          if (inner && i > 0 && i + 1 < voi.size.x) {
            sum6 = sum6_inner(u, e, sx, sxy, sum6);
          } else {
            for (int q = 0; q < 6; ++q) {
              const Vec3i n = Vec3i{i, j, k} + neighbour_offset(q);
              if (voi.contains(n.x, n.y, n.z)) sum6 += u[voi.index(n.x, n.y, n.z)];
            }
          }
          s.u_next[e] = relax_update(u[e], sum6, w);
        }
      }
    std::swap(s.u, s.u_next);
  }
  if (s.reach >= 0) s.reach = std::min(s.reach, 1 << 24) + iterations;
}

}  // namespace palpsim::deform
