// Inversion on the CPU: the deformed image J on the VOI from the displacement field.
#include <algorithm>
#include <cmath>

#include "deform/cpu_backend.h"

namespace palpsim::deform {

InvertStats invert_cpu(const Patient& p, const Voi& voi, int iterations, bool search, CpuState& s) {
  const Grid& grid = p.grid;
  // displacement of a VOI-local voxel, zero outside the VOI (undeformed tissue)
  auto load_u = [&](int i, int j, int k) {
    return voi.contains(i, j, k) ? s.u[voi.index(i, j, k)] : Vec3f{0, 0, 0};
  };
  // intensity at a VOI-local voxel, clamped at the volume border
  auto load_i = [&](int i, int j, int k) {
    const int gi = std::clamp(voi.lo.x + i, 0, grid.size.x - 1);
    const int gj = std::clamp(voi.lo.y + j, 0, grid.size.y - 1);
    const int gk = std::clamp(voi.lo.z + k, 0, grid.size.z - 1);
    return p.intensity.data[grid.index(gi, gj, gk)];
  };
  float worst = 0, change = 0;
  long long unresolved = 0, nonfinite = 0, searched = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        float r = 0;
        bool took_search = false;
        const Vec3f x0 =
            invert_voxel(load_u, voi.size, Vec3f(float(i), float(j), float(k)), iterations, search, r, took_search);
        searched += took_search;
        const float jv = trilinear<float>(load_i, x0);
        s.j[voi.index(i, j, k)] = jv;
        worst = std::max(worst, r);
        unresolved += r > kInvertResolvedVox;
        // how far J moved from I here, and whether it is a number at all
        if (std::isfinite(jv))
          change = std::max(change, std::fabs(jv - load_i(i, j, k)));
        else
          ++nonfinite;
      }
  return {worst, unresolved, change, nonfinite, searched, 0};
}

}  // namespace palpsim::deform
