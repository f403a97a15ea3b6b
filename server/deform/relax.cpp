// Relaxation on the CPU: explicit diffusion of the displacement weighted by the
// paper's material function.
#include <utility>

#include "deform/cpu_backend.h"

namespace palpsim::deform {

void relax_cpu(const Patient& p, const ChainMailStats& st, int iterations, float step, float threshold,
               float width, CpuState& s) {
  const Voi& voi = st.voi;
  const Grid& grid = p.grid;
  const Vec3i g = st.grabbed_vox - voi.lo;
  const long long g_idx = voi.index(g.x, g.y, g.z);
  // the step times the material function, once per element
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const std::size_t gi = grid.index(voi.lo.x + i, voi.lo.y + j, voi.lo.z + k);
        s.weight[voi.index(i, j, k)] =
            step * material_weight(p.intensity.data[gi], p.bone.data[gi] != 0, threshold, width);
      }
  for (int it = 0; it < iterations; ++it) {
    // one Jacobi step of u' = u + w (sum of six neighbours - 6 u), u = 0 outside the VOI
    for (int k = 0; k < voi.size.z; ++k)
      for (int j = 0; j < voi.size.y; ++j)
        for (int i = 0; i < voi.size.x; ++i) {
          const long long e = voi.index(i, j, k);
          const float w = s.weight[e];
          if (e == g_idx || w == 0.0f) {
            s.u_next[e] = s.u[e];
            continue;
          }
          Vec3f sum6{0, 0, 0};
          for (int q = 0; q < 6; ++q) {
            const Vec3i n = Vec3i{i, j, k} + neighbour_offset(q);
            if (voi.contains(n.x, n.y, n.z)) sum6 += s.u[voi.index(n.x, n.y, n.z)];
          }
          s.u_next[e] = relax_update(s.u[e], sum6, w);
        }
    std::swap(s.u, s.u_next);
  }
}

}  // namespace palpsim::deform
