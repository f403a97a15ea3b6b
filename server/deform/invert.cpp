// Inversion on the CPU: the deformed image J on the VOI from the displacement field.
#include <algorithm>
#include <cmath>

#include "deform/cpu_backend.h"
#include "deform/invert_scatter.h"

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
  long long unresolved = 0, nonfinite = 0, scattered = 0;
  // J at voxel v from its source x0 with residual r, and what the stats need of it
  auto finish = [&](const Vec3i& v, const Vec3f& x0, float r) {
    const float jv = sample_at_source<float>(load_i, x0);
    s.j[voi.index(v.x, v.y, v.z)] = jv;
    worst = std::max(worst, r);
    unresolved += r > kInvertResolvedVox;
    // how far J moved from I here, and whether it is a number at all
    if (std::isfinite(jv))
      change = std::max(change, std::fabs(jv - load_i(v.x, v.y, v.z)));
    else
      ++nonfinite;
  };
  // a searched voxel's J: the search's source where its residual is lower than Newton's
  // (invert_voxel()), else Newton's
  auto finish_searched = [&](const SearchVoxel& q, const Vec3f& ps, float rs) {
    finish(q.v, rs < q.newton_r ? ps : q.newton_p, rs < q.newton_r ? rs : q.newton_r);
  };
  // Newton for every voxel (invert_voxel()'s first half); where it ends above
  // kInvertSearchVox and the search is on, the voxel waits for the cell search
  const bool searching = search && iterations > 0;
  s.search_queue.clear();
  if (searching) s.search_slot.assign(std::size_t(voi.count()), -1);
  for (int k = 0; k < voi.size.z; ++k)
    for (int j = 0; j < voi.size.y; ++j)
      for (int i = 0; i < voi.size.x; ++i) {
        const Vec3f y{float(i), float(j), float(k)};
        float r = 0;
        const Vec3f x0 = invert_point(load_u, y, iterations, r);
        if (searching && r > kInvertSearchVox) {
          int rmax;
          s.search_slot[voi.index(i, j, k)] = int(s.search_queue.size());
          s.search_queue.push_back(
              SearchVoxel{{i, j, k}, search_centre(voi.size, y - trilinear<Vec3f>(load_u, y), rmax), x0, r});
          continue;
        }
        finish({i, j, k}, x0, r);
      }
  // the cell search (invert_voxel()'s second half) for the queued voxels: rings 0 and 1
  // of pass 0, then for the voxels still without a source the scatter's pick where
  // pass 0 decides it, else the whole ring search; the lower residual of it and Newton's
  // wins. The voxels found near leave the scatter's queue (and its bounds)
  constexpr int kNearRings = 1;
  std::size_t far = 0;
  for (std::size_t n = 0; n < s.search_queue.size(); ++n) {
    SearchVoxel q = s.search_queue[n];
    const Vec3f y{float(q.v.x), float(q.v.y), float(q.v.z)};
    q.found = invert_search_near(load_u, voi.size, y, q.centre, kNearRings, q.p, q.residual);
    if (q.found) {
      ++scattered;
      s.search_slot[voi.index(q.v.x, q.v.y, q.v.z)] = -1;
      finish_searched(q, q.p, q.residual);
      continue;
    }
    s.search_slot[voi.index(q.v.x, q.v.y, q.v.z)] = int(far);
    s.search_queue[far++] = q;
  }
  const long long searched = (long long)s.search_queue.size();
  s.search_queue.resize(far);
  const bool scatter = scatter_search(load_u, voi.size, s.search_queue, s.search_slot);
  for (const SearchVoxel& q : s.search_queue) {
    const Vec3f y{float(q.v.x), float(q.v.y), float(q.v.z)};
    float rs = q.residual;
    Vec3f ps = q.p;
    if (scatter && q.found)
      ++scattered;
    else
      ps = invert_search(load_u, voi.size, y, y - trilinear<Vec3f>(load_u, y), rs);
    finish_searched(q, ps, rs);
  }
  return {worst, unresolved, change, nonfinite, searched, scattered};
}

}  // namespace palpsim::deform
