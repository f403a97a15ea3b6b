// The elastic set-up kernel: node moduli and flags, every level's cells and largest
// eigenvalue, and the last field carried onto a new VOI.
#pragma once
// Included by cuda/relax_elastic.cu alone (one translation unit: the kernels are templates
// in its anonymous namespace); see that file for what the elastic step does on the GPU.
#include <cooperative_groups.h>

#include "cuda/elastic_device.cuh"

#include <algorithm>
#include <cmath>

#include "cuda/relax_elastic.h"
#include "deform/deform_math.h"
#include "deform/elastic_math.h"

namespace palpsim::cuda {

namespace {

namespace cg = cooperative_groups;
struct SetupArgs {
  float k[72];  // the cell matrix, E = 1 kPa, level 0: corner 0's row block (CellMatrix)
  ElasticPlan plan;
  View v;
  Voi voi, last;           // the VOI to set up and the one the field is on (patient voxels)
  Vec3i grid;              // the patient grid's size
  ElasticMaterial material;
  ElasticPatient patient;
  int had;                 // carry the last field and contact set over
  int tile_nodes;          // coarse levels of at least this many nodes take tiles (gather)
  unsigned long long* trace;  // null, or (pass, ns) pairs block 0 writes at each barrier (PALPSIM_ELASTIC_TRACE)
  int trace_pairs;            // the pairs it holds
};

// every level's largest eigenvalue of D^-1 K by kElasticLanczosSteps Lanczos steps
// (deform::elastic_lanczos_lmax), all levels in the same passes (the whole grid), as
// relax_elastic.cpp's estimate_lmax: the start u_0 in x[0]; step 0 applies A = Pi D^-1 K to
// u_0 (z_0 into res), step j >= 1 to z_{j-1} and gets u_j (x[0] / x[1]) and z_j = A u_j (res /
// d) from the last two by the recurrence, each over u_{j-2} and z_{j-2} at the same node;
// the sums <u_j, u_j>_D and <z_j, u_j>_D per level and step, into v.lmax by block 0's thread
// 0 after the last pass. The scratch's d held the node moduli, done with by now.
__device__ void estimate_lmax(const SetupArgs& a, const Lvl* lv, const Team& all, cg::grid_group& g, Tracer& tr) {
  const View& v = a.v;
  const int levels = a.plan.levels;
  const CellMatrix km{a.k};
  double* sums = v.sums + kSlot * kRing;
  const Vec3f none{0, 0, 0};
  const Field U[2] = {every(v.x[0], v), every(v.x[1], v)};
  const Field Z[2] = {every(v.res, v), every(v.d, v)};
  // the start, and the other vectors at 0 (the gathers leave out tiles all held)
  for (int l = 0; l < levels; ++l) {
    const Lvl& L = lv[l];
    for (int q = all.first; q < L.count; q += all.stride) {
      const unsigned long long m = 3ull * (unsigned long long)q;
      const int e = L.off + q;
      U[0].set(e, deform::elastic_project(v.flags[e], none,
                                          Vec3f{deform::elastic_power_start(m), deform::elastic_power_start(m + 1),
                                                deform::elastic_power_start(m + 2)}));
      U[1].set(e, none);
      Z[0].set(e, none);
      Z[1].set(e, none);
    }
  }
  g.sync();
  // <a, b>_D with the node's diagonal `dg` (no weight where there is none)
  auto dot_w = [](const Vec3f& x, const Vec3f& y, const Vec3f& dg) {
    return (dg.x > 0 ? double(x.x) * y.x * dg.x : 0.0) + (dg.y > 0 ? double(x.y) * y.y * dg.y : 0.0) +
           (dg.z > 0 ? double(x.z) * y.z * dg.z : 0.0);
  };
  for (int j = 0; j < deform::kElasticLanczosSteps; ++j) {
    const Field un = U[j & 1], zn = Z[j & 1], up = U[(j + 1) & 1], zp = Z[(j + 1) & 1];
    for (int l = 0; l < levels; ++l) {
      // this level's recurrence coefficients from the last two steps' sums
      double alpha = 0, beta = 0;
      if (j > 0) {
        const double* s1 = sums + kSlot * ((j - 1) * kElasticMaxLevels + l);
        if (s1[0] > 0) alpha = s1[1] / s1[0];
        if (j > 1) {
          const double* s2 = sums + kSlot * ((j - 2) * kElasticMaxLevels + l);
          if (s2[0] > 0) beta = s1[0] / s2[0];
        }
      }
      double part[2] = {0, 0};
      gather(km, v.cell_e, v.flags, v.tiles, a.tile_nodes, lv[l], all, j == 0 ? U[0] : zp, NoPre{},
             [&](int e, int, int, int, const Vec3f& kx, const Vec3f& dg, const Vec3f& xe, int) {
               const Vec3f t = deform::elastic_project(v.flags[e], none, mul(inverse(dg), kx));
               Vec3f ue = xe, ze = t;
               if (j > 0) {
                 ue = xe - up.at(e) * float(alpha) - un.at(e) * float(beta);
                 ze = t - xe * float(alpha) - zn.at(e) * float(beta);
                 un.set(e, ue);
               }
               zn.set(e, ze);
               part[0] += dot_w(ue, ue, dg);
               part[1] += dot_w(ze, ue, dg);
             });
      block_sum(part, sums + kSlot * (j * kElasticMaxLevels + l));
    }
    g.sync();
    tr.stamp(kPassSetupLanczos * 16);
  }
  // block 0's thread l takes level l
  if (blockIdx.x == 0) {
    for (int l = int(threadIdx.x); l < levels; l += int(blockDim.x)) {
      double s[deform::kElasticLanczosSteps], n[deform::kElasticLanczosSteps];
      for (int j = 0; j < deform::kElasticLanczosSteps; ++j) {
        s[j] = sums[kSlot * (j * kElasticMaxLevels + l)];
        n[j] = sums[kSlot * (j * kElasticMaxLevels + l) + 1];
      }
      v.lmax[l] = float(deform::elastic_lanczos_lmax(s, n, deform::kElasticLanczosSteps));
    }
  }
}

template <int MinBlocks>
__global__ void __launch_bounds__(kThreads, MinBlocks) elastic_setup_kernel(const __grid_constant__ SetupArgs a) {
  cg::grid_group g = cg::this_grid();
  __shared__ alignas(16) unsigned char level_bytes[kElasticMaxLevels * sizeof(Lvl)];  // raw: Vec3i has initialisers
  Lvl* lv = reinterpret_cast<Lvl*>(level_bytes);
  if (threadIdx.x == 0) make_levels(a.plan, a.v.capacity, lv);
  copy_cell_matrix(a.k);
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
  Tracer tr{a.trace, a.trace_pairs, 0};
  tr.stamp(kPassStart * 16);

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
  tr.stamp(kPassSetupNodes * 16);
  // level 0's tiles with a node that is not held (the gathers take those alone): marked by
  // every block, listed by block 0 while the others go on to the cells
  mark_tiles(v.flags, L0, v.tiles);
  g.sync();
  if (blockIdx.x == 0) list_tiles(L0, v.tiles);
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
  tr.stamp(kPassSetupCells * 16);
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
          deform::elastic_coarse_flags(beyond ? 0 : (v.flags[F.at(2 * i, 2 * j, 2 * k)] & (kElasticHeld | kElasticAir)), beyond);
    }
    g.sync();
    tr.stamp(kPassSetupCoarse * 16 + l);
  }
  estimate_lmax(a, lv, all, g, tr);
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
  __syncthreads();
  tr.stamp(kPassSetupEnd * 16);
}

}  // namespace

}  // namespace palpsim::cuda
