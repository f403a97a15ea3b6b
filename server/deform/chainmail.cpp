// ChainMail on the CPU: the reference Jacobi sweeps (paper sec. 2.2, Fig. 2).
#include "deform/cpu_backend.h"

namespace palpsim::deform {

void chainmail_grab_cpu(ChainMailStats& st, CpuState& s) {
  const Vec3i g = st.grabbed_vox - st.voi.lo;
  st.sweeps = 0;
  st.moved = 0;
  st.converged = true;
  // a grabbed bone element does not move, so nothing does
  if (st.grabbed_in_bone) return;
  const long long g_idx = st.voi.index(g.x, g.y, g.z);
  s.u[g_idx] = st.grabbed_u_vox;
  s.moved_at[g_idx] = 0;
}

void chainmail_cpu(const Patient& p, const ChainMailLimits& limits, int max_sweeps, ChainMailStats& st,
                   CpuState& s) {
  const Voi& voi = st.voi;
  const Grid& grid = p.grid;
  const Vec3i g = st.grabbed_vox - voi.lo;
  const long long g_idx = voi.index(g.x, g.y, g.z);
  chainmail_grab_cpu(st, s);
  if (st.grabbed_in_bone) return;
  s.movers.assign(1, g);

  auto is_bone = [&](const Vec3i& l) {
    return p.bone.data[grid.index(voi.lo.x + l.x, voi.lo.y + l.y, voi.lo.z + l.z)] != 0;
  };
  for (int sweep = 1; sweep <= max_sweeps; ++sweep) {
    st.sweeps = sweep;
    // the elements next to one that moved in the previous sweep (each once)
    s.candidates.clear();
    for (const Vec3i& m : s.movers)
      for (int q = 0; q < 6; ++q) {
        const Vec3i n = m + neighbour_offset(q);
        if (!voi.contains(n.x, n.y, n.z)) continue;
        const long long ni = voi.index(n.x, n.y, n.z);
        if (ni == g_idx || s.visited_at[ni] == sweep || is_bone(n)) continue;
        s.visited_at[ni] = sweep;
        s.candidates.push_back(n);
      }
    // each clamps itself into the box of every neighbour that has moved in an earlier sweep
    // (the grabbed element included), not only of those that moved in the previous one:
    // the grabbed element and elements that have settled keep their hold on it (else a
    // later clamp can take it out of their box and a quiet sweep ends the run)
    s.changes.clear();
    for (const Vec3i& c : s.candidates) {
      const long long ci = voi.index(c.x, c.y, c.z);
      Vec3f v = s.u[ci];
      for (int q = 0; q < 6; ++q) {
        const Vec3i n = c + neighbour_offset(q);
        if (!voi.contains(n.x, n.y, n.z)) continue;
        const long long ni = voi.index(n.x, n.y, n.z);
        if (s.moved_at[ni] >= 0) chainmail_clamp(v, s.u[ni], neighbour_axis(q), neighbour_below(q), limits);
      }
      if (v != s.u[ci]) s.changes.emplace_back(ci, v);
    }
    // a quiet sweep ends the propagation
    if (s.changes.empty()) return;
    // apply the sweep's positions together (Jacobi)
    s.movers.clear();
    for (const auto& [ci, v] : s.changes) {
      s.u[ci] = v;
      if (s.moved_at[ci] < 0) ++st.moved;
      s.moved_at[ci] = sweep;
      const long long sx = voi.size.x, sxy = sx * voi.size.y;
      s.movers.push_back(Vec3i{int(ci % sx), int((ci / sx) % voi.size.y), int(ci / sxy)});
    }
  }
  st.converged = false;
}

}  // namespace palpsim::deform
