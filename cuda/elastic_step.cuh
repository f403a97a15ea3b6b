// The elastic step kernel: contact rounds of conjugate gradients preconditioned by a
// V-cycle, the force, the unit press and u in voxels, on the grid with barriers between passes.
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
struct StepArgs {
  float k[72];         // the cell matrix, E = 1 kPa, level 0: corner 0's row block (CellMatrix)
  ElasticPlan plan;
  View v;
  double h[3];         // voxel edges (mm)
  Vec3f nrm;           // the press direction n (unit; 0 when the tip is outside the skin)
  Vec3f centre;        // the sphere's centre (mm, VOI-local)
  float radius;        // its radius (mm)
  float penetration;   // how far (mm) the sphere must pass a free skin node for it to join
  int pressing;        // the tip lies below the skin (depth above 1e-6 mm)
  float depth;         // the tip's depth along n (mm): a fresh start's contact set (elastic_start_contact)
  int had;             // the field and contact set came from the last step
  int unit_warm;       // the unit press starts from the last one
  float unit_scale;    // ... else from u times this (elastic_unit_start_scale)
  int predict;         // the warm start's prediction (deform::ElasticPredict) and its factor
  float predict_factor;
  Vec3f shift_vox;     // ... after moving the last field and unit press with the tip across n by this
                       // (voxels along the grid axes; 0: no move, deform::elastic_shifts)
  int stiffness;       // solve the unit press
  // superpose where the start leaves the contact set as it was (deform::elastic_superposes,
  // the host's part), on the last step's push along n (N), stiffness (N/mm) and residual
  int superpose;
  double last_push_n, last_stiffness, last_residual;
  int max_iterations;
  float tolerance;
  int reciprocal;             // the unit press stops at stiffness_tolerance; force and stiffness by reciprocity
  float stiffness_tolerance;
  int contact_rounds;
  deform::ElasticDegrees degrees;  // the V-cycle's Chebyshev degrees (each in [2, kElasticMaxDegree]: backend.cpp checks)
  int block_nodes;     // coarse levels of at most this many nodes run in block 0 alone
  int tile_nodes;      // coarse levels of at least this many nodes on the grid take tiles (gather)
  float* out[3];       // u in voxels (the displacement buffer the inversion reads)
  ElasticCounters* result;
  unsigned long long* trace;  // null, or (pass, ns) pairs block 0 writes at each barrier (PALPSIM_ELASTIC_TRACE)
  int trace_pairs;            // the pairs it holds
};


// the reductions' ring: each use adds into the next slot and clears the one kRing / 2
// ahead, which every thread read long ago and which the barrier publishes before its turn
struct Ring {
  double* sums;
  int slot;
  Tracer tracer;
};

// the grid's sums of this thread's v[0 .. N-1], read by every thread after a grid barrier
template <int N>
__device__ void reduce(Ring& rg, double (&v)[N], cg::grid_group& g, int tag) {
  static_assert(N <= kSlot, "a slot holds kSlot sums");
  double* s = rg.sums + kSlot * rg.slot;
  block_sum<N>(v, s);
  if (blockIdx.x == 0 && threadIdx.x < kSlot) rg.sums[kSlot * ((rg.slot + kRing / 2) % kRing) + threadIdx.x] = 0.0;
  g.sync();
  rg.tracer.stamp(tag);
  for (int i = 0; i < N; ++i) v[i] = *(volatile double*)&s[i];
  rg.slot = (rg.slot + 1) % kRing;
}

__device__ double reduce1(Ring& rg, double v, cg::grid_group& g, int tag) {
  double s[1] = {v};
  reduce(rg, s, g, tag);
  return s[0];
}

// what every pass of the step kernel reads, in each block's shared memory
struct StepShared {
  Lvl lv[kElasticMaxLevels];
  float ca[kElasticMaxLevels][kElasticMaxDegree], cb[kElasticMaxLevels][kElasticMaxDegree];  // Chebyshev a, b
  int degree[kElasticMaxLevels];  // each level's Chebyshev degree
  int levels, split;  // split: the first level block 0 runs alone (levels: none)
};

// a node's right-hand side and last Chebyshev step, as a smoothing step reads them
struct NodeRhs {
  Vec3f f, d;
};

// the passes of one step (the kernel's arguments, its blocks' shared table, the barrier
// and the reductions' ring): each is inlined at one call site
struct Step {
  const StepArgs& a;
  const StepShared& sh;
  cg::grid_group& g;
  Ring& ring;
  Team all, block;

  __device__ CellMatrix km() const { return CellMatrix{a.k}; }
  __device__ Field x(int b) const { return every(a.v.x[b], a.v); }
  __device__ Field f() const { return every(a.v.f, a.v); }
  __device__ Field res() const { return every(a.v.res, a.v); }
  __device__ Field d() const { return every(a.v.d, a.v); }
  __device__ Vec3f project(int e, const Vec3f& w) const { return deform::elastic_project(a.v.flags[e], a.nrm, w); }
  __device__ bool on_grid(int l) const { return l < sh.split; }
  __device__ Team team(int l) const { return on_grid(l) ? all : block; }
  // the barrier after a pass of level l (`pass` a TracePass): the grid's, or block 0's
  __device__ void sync(int l, int pass) const {
    if (on_grid(l))
      g.sync();
    else
      __syncthreads();
    ring.tracer.stamp(pass * 16 + l);
  }
  // the grid's barrier after a pass of level 0 (`pass` a TracePass)
  __device__ void grid_sync(int pass) const {
    g.sync();
    ring.tracer.stamp(pass * 16);
  }
  // the buffer holding level l's x after its smoothing (the prolongation reads it)
  __device__ int final_buffer(int l) const { return l == sh.levels - 1 ? (sh.degree[l] - 1) & 1 : 1; }

  // level l's smoother's first step from 0 at one node whose right-hand side `fe` was just
  // written: d = b0 Pi D^-1 f, x[0] = d
  __device__ void first_step(int l, int e, int i, int j, int k, const Vec3f& fe) const {
    first_step_from(l, e, diag_at(km(), a.v.cell_e, sh.lv[l], i, j, k), fe);
  }
  // the same with the node's Jacobi diagonal `dg` known (a gather's)
  __device__ void first_step_from(int l, int e, const Vec3f& dg, const Vec3f& fe) const {
    const Vec3f z = project(e, mul(inverse(dg), fe));
    const Vec3f dv = z * sh.cb[l][0];
    d().set(e, dv);
    x(0).set(e, dv);
  }

  // one Chebyshev step (s >= 1 of a smoothing from 0, or any of one that is not, `restart`
  // for its first) of level l by team t from x[from] to x[to]: r = Pi (f - K x), d = a_s d +
  // b_s Pi D^-1 r (b_s Pi D^-1 r on `restart`), x[to] = x[from] + d. Returns this thread's
  // part of f . x[to] when `dot` (CG's r . z, on level 0's last step)
  __device__ double smooth(int l, Team t, int s, int from, int to, bool restart, bool dot) const {
    const float ca = sh.ca[l][s], cb = sh.cb[l][s];
    const Field xf = x(from), xt = x(to), fv = f(), dv = d();
    double part = 0;
    // the node's right-hand side and last step, loaded before its products are summed
    gather(
        km(), a.v.cell_e, a.v.flags, a.v.tiles, a.tile_nodes, sh.lv[l], t, xf,
        [&](bool mine, int e) {
          NodeRhs v{Vec3f{0, 0, 0}, Vec3f{0, 0, 0}};
          if (mine) {
            v.f = fv.at(e);
            if (!restart) v.d = dv.at(e);
          }
          return v;
        },
        [&](int e, int, int, int, const Vec3f& kx, const Vec3f& dg, const Vec3f& xe, const NodeRhs& pv) {
          const Vec3f r = project(e, pv.f - kx);
          const Vec3f z = project(e, mul(inverse(dg), r));
          const Vec3f step = restart ? z * cb : pv.d * ca + z * cb;
          dv.set(e, step);
          const Vec3f xn = xe + step;
          xt.set(e, xn);
          if (dot) part += dot_d(pv.f, xn);
        });
    return part;
  }

  // the residual of level l by team t: res = Pi (f - K x[from])
  __device__ __forceinline__ void residual(int l, Team t, int from) const {
    const Field fv = f(), rv = res();
    gather(
        km(), a.v.cell_e, a.v.flags, a.v.tiles, a.tile_nodes, sh.lv[l], t, x(from),
        [&](bool mine, int e) { return mine ? fv.at(e) : Vec3f{0, 0, 0}; },
        [&](int e, int, int, int, const Vec3f& kx, const Vec3f&, const Vec3f&, const Vec3f& fe) {
          rv.set(e, project(e, fe - kx));
        });
  }

  // level l + 1's right-hand side, the restricted residual of level l (team t), and its
  // smoother's first step
  __device__ void restrict_to(int l, Team t) const {
    const Lvl &F = sh.lv[l], &C = sh.lv[l + 1];
    const Field rv = res(), fv = f();
    for (int q = t.first; q < C.count; q += t.stride) {
      int i, j, k;
      C.coords(q, i, j, k);
      const Vec3f g = deform::elastic_restrict(
          [&](int fi, int fj, int fk) {
            return (fi < 0 || fj < 0 || fk < 0 || fi >= F.n.x || fj >= F.n.y || fk >= F.n.z) ? Vec3f{0, 0, 0}
                                                                                            : rv.at(F.at(fi, fj, fk));
          },
          i, j, k);
      const int e = C.off + q;
      const Vec3f fe = project(e, g);
      fv.set(e, fe);
      first_step(l + 1, e, i, j, k, fe);
    }
  }

  // the coarse correction of level l (team t): x[buf] += Pi P (level l + 1's final x)
  __device__ void correct(int l, Team t, int buf) const {
    const Lvl &F = sh.lv[l], &C = sh.lv[l + 1];
    const Field xf = x(buf), xc = x(final_buffer(l + 1));
    for (int q = t.first; q < F.count; q += t.stride) {
      int i, j, k;
      F.coords(q, i, j, k);
      const Vec3f g = deform::elastic_prolong(
          [&](int ci, int cj, int ck) {
            return (ci >= C.n.x || cj >= C.n.y || ck >= C.n.z) ? Vec3f{0, 0, 0} : xc.at(C.at(ci, cj, ck));
          },
          i, j, k);
      const int e = F.off + q;
      xf.set(e, xf.at(e) + project(e, g));
    }
  }

  // the rest of the V-cycle z = B r (elastic_math.h), after the pass that wrote level 0's r
  // made its smoother's first step. Levels below the split run in block 0 alone while the
  // other blocks wait at the barrier before the first grid level going up. The last pass
  // (level 0's last smoothing step) is not followed by a barrier: the caller's reduction of
  // the r . z it returns (this thread's part) is one
  __device__ double vcycle() const {
    const int last = sh.levels - 1;
    double part = 0;
    // down: each level's smoothing from 0 (the coarsest's is all it does), then its
    // residual and the next level's right-hand side
    for (int l = 0; l <= last; ++l) {
      if (!on_grid(l) && blockIdx.x != 0) break;
      const int degree = sh.degree[l];
      for (int s = 1; s < degree; ++s) {
        const bool final = l == 0 && last == 0 && s == degree - 1;
        const double pp = smooth(l, team(l), s, (s - 1) & 1, s & 1, false, final);
        if (final)
          part = pp;
        else
          sync(l, kPassSmoothDown);
      }
      if (l == last) break;
      residual(l, team(l), (degree - 1) & 1);
      sync(l, kPassResidual);
      restrict_to(l, team(l));
      sync(l, kPassRestrict);
    }
    // up: each level's coarse correction and smoothing from it
    for (int l = last - 1; l >= 0; --l) {
      if (!on_grid(l) && blockIdx.x != 0) continue;
      if (on_grid(l) && !on_grid(l + 1)) {  // block 0's levels are done
        g.sync();
        ring.tracer.stamp(kPassBlockLevels * 16 + l + 1);
      }
      const int degree = sh.degree[l], pre = (degree - 1) & 1;  // pre: the buffer the smoothing down left
      correct(l, team(l), pre);
      sync(l, kPassCorrect);
      for (int s = 0; s < degree; ++s) {
        const bool final = l == 0 && s == degree - 1;
        const double pp = smooth(l, team(l), s, (pre + s) & 1, (pre + s + 1) & 1, s == 0, final);
        if (final)
          part = pp;
        else
          sync(l, kPassSmoothUp);
      }
    }
    return part;
  }

  // the sphere's push (mm along n) of a level-0 node at rest, -1 where it is no free skin
  // node under the sphere (relax_elastic_cpu()'s push)
  __device__ float push(std::uint8_t fl, int i, int j, int k) const {
    if (!a.pressing || !(fl & kElasticSkin) || (fl & kElasticHeld)) return -1.0f;
    const Vec3f rest{float(i * a.h[0]), float(j * a.h[1]), float(k * a.h[2])};
    return deform::elastic_sphere_push(rest, a.centre, a.nrm, a.radius);
  }

  struct Solve {
    int iterations;
    double residual;
    bool converged;
  };

  // elastic_solve_cpu(): K w = 0 on the free components of w (level 0, the flags as they
  // are), held nodes keeping their value and contact nodes their part along n; conjugate
  // gradients preconditioned by the V-cycle, to the tolerance or max_iterations steps
  __device__ __forceinline__ Solve solve(const Field& w, float tolerance) const {
    const Lvl& L0 = sh.lv[0];
    const View& v = a.v;
    const Field r = f(), kp = res(), p = level0(v.p, v), z = x(final_buffer(0));
    const int last = sh.levels - 1;
    Solve out{0, 0.0, true};
    // the coarse levels' contact flags from level 0's (a coarse node that is not held lies
    // on level-0 node 2^l I, through finer nodes none of which is held); level 0's
    // constrained values alone (held nodes' w, contact nodes' part of it along n) into p;
    // at held nodes of every level what the gathers would write there (0), which those of
    // tiles left out never do
    const Vec3f zero{0, 0, 0};
    for (int l = 1; l <= last; ++l) {
      const Lvl& C = sh.lv[l];
      for (int q = all.first; q < C.count; q += all.stride) {
        int i, j, k;
        C.coords(q, i, j, k);
        std::uint8_t nf = std::uint8_t(v.flags[C.off + q] & ~kElasticContact);
        const int fi = i << l, fj = j << l, fk = k << l;
        if (!(nf & kElasticHeld) && fi < L0.n.x && fj < L0.n.y && fk < L0.n.z)
          nf |= v.flags[L0.at(fi, fj, fk)] & kElasticContact;
        v.flags[C.off + q] = nf;
        if (nf & kElasticHeld) {
          x(0).set(C.off + q, zero);
          x(1).set(C.off + q, zero);
          res().set(C.off + q, zero);
        }
      }
    }
    for (int e = all.first; e < L0.count; e += all.stride) {
      const std::uint8_t fl = v.flags[e];
      const Vec3f we = w.at(e);
      p.set(e, (fl & kElasticHeld) ? we : ((fl & kElasticContact) ? a.nrm * dot(we, a.nrm) : zero));
      if (fl & kElasticHeld) {
        x(0).set(e, zero);
        x(1).set(e, zero);
        d().set(e, zero);
        r.set(e, zero);
        kp.set(e, zero);
      }
    }
    grid_sync(kPassSolveFlags);
    // level 0: the scale of the tolerance (the residual of the constrained values alone),
    // r = Pi (0 - K w), and the smoother's first step (both products in one tile pass: each
    // reads what the pass before the barrier wrote)
    double sums[2] = {0, 0};
    gather_pair(km(), v.cell_e, v.flags, v.tiles, L0, p, w,
                [&](int e, int, int, int, const Vec3f& kp_e, const Vec3f& kw_e, const Vec3f& dg) {
                  const Vec3f t = project(e, kp_e);
                  sums[0] += double(dot(t, t));
                  const Vec3f re = project(e, -kw_e);
                  r.set(e, re);
                  sums[1] += dot_d(re, re);
                  first_step_from(0, e, dg, re);
                });
    reduce(ring, sums, g, kPassSolveStart * 16);
    const double rref = sqrt(sums[0]);
    double rn = sqrt(sums[1]);
    out.residual = rref > 0 ? rn / rref : 0;
    if (rref <= 0 || rn <= double(tolerance) * rref) return out;
    // the V-cycle before the first step, then after each (but the last allowed)
    double rz = 0;
    float beta = 0;
    for (int it = -1; it < a.max_iterations; ++it) {
      if (it >= 0) {
        // p = z (the first step) or z + beta p
        for (int e = all.first; e < L0.count; e += all.stride) p.set(e, it == 0 ? z.at(e) : z.at(e) + p.at(e) * beta);
        grid_sync(kPassCgDirection);
        // q = Pi K p, and p . q
        double part = 0;
        gather(km(), v.cell_e, v.flags, v.tiles, a.tile_nodes, L0, all, p, NoPre{},
               [&](int e, int, int, int, const Vec3f& kx, const Vec3f&, const Vec3f& pe, int) {
                 const Vec3f qe = project(e, kx);
                 kp.set(e, qe);
                 part += dot_d(pe, qe);
               });
        const double pq = reduce1(ring, part, g, kPassCgApply * 16);
        if (!(pq > 0)) break;
        const float alpha = float(rz / pq);
        // w += alpha p, r -= alpha q, |r|^2, and the next V-cycle's first step
        part = 0;
        for (int e = all.first; e < L0.count; e += all.stride) {
          int i, j, k;
          L0.coords(e, i, j, k);
          w.set(e, w.at(e) + p.at(e) * alpha);
          const Vec3f re = r.at(e) - kp.at(e) * alpha;
          r.set(e, re);
          part += dot_d(re, re);
          first_step(0, e, i, j, k, re);
        }
        rn = sqrt(reduce1(ring, part, g, kPassCgUpdate * 16));
        out.iterations = it + 1;
        out.residual = rn / rref;
        if (rn <= double(tolerance) * rref) return out;
        if (it + 1 == a.max_iterations) break;
      }
      const double rz_new = reduce1(ring, vcycle(), g, kPassVcycleLast * 16);
      if (it >= 0) beta = float(rz_new / rz);
      rz = rz_new;
    }
    out.converged = out.residual <= double(tolerance);
    return out;
  }
};

// the step's shared table (thread 0 of each block): the levels, the first level block 0
// runs alone, each level's Chebyshev coefficients from its lmax (the set-up's)
__device__ void make_step_table(const StepArgs& a, StepShared& sh) {
  const View& v = a.v;
  make_levels(a.plan, v.capacity, sh.lv);
  sh.levels = a.plan.levels;
  sh.split = a.plan.levels;
  for (int l = 1; l < a.plan.levels; ++l)
    if (sh.lv[l].count <= a.block_nodes) {
      sh.split = l;
      break;
    }
  for (int l = 0; l < a.plan.levels; ++l) {
    const bool coarsest = l + 1 == a.plan.levels;
    sh.degree[l] = min(kElasticMaxDegree, max(2, a.degrees.at(l, a.plan.levels)));
    const float hi = deform::kElasticChebyshevMargin * v.lmax[l];
    deform::elastic_chebyshev(hi / (coarsest ? deform::kElasticCoarsestRatio : deform::kElasticChebyshevRatio), hi,
                              sh.degree[l], sh.ca[l], sh.cb[l]);
  }
}

// the warm start's shift (deform::elastic_prediction: the tip moved across n; every thread
// its nodes): the last field and unit press copied into x[0] and x[1], for start_contact()
// to read them moved, then the grid's barrier
__device__ void shift_copy(const StepArgs& a, const Step& st) {
  const View& v = a.v;
  const Lvl& L0 = st.sh.lv[0];
  const Field u = level0(v.u, v), unit = level0(v.u_unit, v), cu = st.x(0), cw = st.x(1);
  const bool with_unit = a.predict == int(ElasticPredict::kUnit);
  for (int e = st.all.first; e < L0.count; e += st.all.stride) {
    cu.set(e, u.at(e));
    if (with_unit) cw.set(e, unit.at(e));
  }
  st.grid_sync(kPassShift);
}

// the contact set at the step's start (every thread its nodes, elastic_start_contact): last
// step's nodes still under the sphere and nodes the last field (as the prediction moves it)
// leaves inside it, or on a fresh start (the field and contact set zeroed first) the nodes
// within Hertz's contact area; this thread's count of nodes under the sphere, and into
// `changed` and `contacts` its nodes that joined or left the set and its contact nodes
__device__ double start_contact(const StepArgs& a, const Step& st, double& changed, double& contacts) {
  const View& v = a.v;
  const Lvl& L0 = st.sh.lv[0];
  const Team all = st.all;
  const Field u = level0(v.u, v), unit = level0(v.u_unit, v);
  const bool reactions =
      deform::elastic_start_weighs_reactions(ElasticPredict(a.predict), a.shift_vox) && v.react != nullptr;
  const float touch =
      deform::elastic_start_touch(deform::elastic_shifts(a.shift_vox), ElasticPredict(a.predict), float(a.h[0]));
  double under = 0;
  for (int e = all.first; e < L0.count; e += all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    std::uint8_t fl = v.flags[e];
    Vec3f ue = u.at(e);
    if (!a.had) {
      ue = Vec3f{0, 0, 0};
      u.set(e, ue);
      fl = std::uint8_t(fl & ~kElasticContact);
    } else if (a.predict != int(ElasticPredict::kNone)) {
      const ElasticPredict kind = ElasticPredict(a.predict);
      Vec3f we = kind == ElasticPredict::kUnit ? unit.at(e) : Vec3f{0, 0, 0};
      // moved with the tip across n (held nodes keep their 0): the copies shift_copy() made;
      // the contact set from the moved field's penetration alone (deform::elastic_shifted)
      if (deform::elastic_shifts(a.shift_vox)) {
        fl = std::uint8_t(fl & ~kElasticContact);
        if (!(fl & kElasticHeld)) {
          ue = deform::elastic_shifted(LoadOrZero{st.x(0), L0}, i, j, k, a.shift_vox);
          if (kind == ElasticPredict::kUnit) {
            we = deform::elastic_shifted(LoadOrZero{st.x(1), L0}, i, j, k, a.shift_vox);
            unit.set(e, we);
          }
        }
      }
      ue = deform::elastic_predicted(kind, a.predict_factor, ue, we);
      u.set(e, ue);
    }
    const float t = st.push(fl, i, j, k);
    if (t > 0) under += 1;
    const bool was = (fl & kElasticContact) != 0;
    fl = std::uint8_t(fl & ~kElasticContact);
    const bool pulled = was && reactions &&
                        deform::elastic_predicted_pull(v.react[e], v.react[v.capacity + e], a.predict_factor);
    if (deform::elastic_start_contact(t, dot(ue, a.nrm), was, a.had != 0, a.depth, touch, pulled))
      fl |= kElasticContact;
    v.flags[e] = fl;
    const bool is = (fl & kElasticContact) != 0;
    changed += double(was != is);
    contacts += double(is);
  }
  return under;
}

// the start of a solve (every thread its nodes): the unit press's w (from the last one or
// u scaled to a 1 mm press, every contact node 1 mm along n), or u's contact nodes onto
// the sphere along n (held nodes stay)
__device__ void job_start(const StepArgs& a, const Step& st, bool unit_press, const Field& w) {
  const View& v = a.v;
  const Lvl& L0 = st.sh.lv[0];
  const Team all = st.all;
  if (unit_press) {
    for (int e = all.first; e < L0.count; e += all.stride) {
      Vec3f we = a.unit_warm ? w.at(e) : level0(v.u, v).at(e) * a.unit_scale;
      if (v.flags[e] & kElasticContact) we = we - a.nrm * dot(we, a.nrm) + a.nrm;
      w.set(e, we);
    }
  } else {
    // contact nodes onto the sphere along n (held nodes stay)
    for (int e = all.first; e < L0.count; e += all.stride) {
      const std::uint8_t fl = v.flags[e];
      if (!(fl & kElasticContact)) continue;
      int i, j, k;
      L0.coords(e, i, j, k);
      const Vec3f we = w.at(e);
      w.set(e, we - a.nrm * dot(we, a.nrm) + a.nrm * st.push(fl, i, j, k));
    }
  }
}

// node e's field in voxels for the inversion: u / h, as the CPU's u_vox
__device__ void write_node_field(const StepArgs& a, const Field& u, int e) {
  const Vec3f ue = u.at(e);
  a.out[0][e] = float(ue.x / a.h[0]);
  a.out[1][e] = float(ue.y / a.h[1]);
  a.out[2][e] = float(ue.z / a.h[2]);
}

// the field in voxels for the inversion (every thread its nodes)
__device__ void write_field(const StepArgs& a, const Step& st) {
  const Field u = level0(a.v.u, a.v);
  for (int e = st.all.first; e < st.sh.lv[0].count; e += st.all.stride) write_node_field(a, u, e);
}

// after a solve (every thread its nodes, into sums): the contact nodes' forces along n and
// their count, each kept for the next step's start (View::react: the press's, or the unit
// press's for `unit`); after a round (`round`), the set's update and how many nodes changed; after
// the unit press by reciprocity (elastic_math.h, `reciprocal`) the push sum of u . K w and
// w's residual's part of w . K w; with `field`, u in voxels for the inversion (u is final:
// write_field(), the barrier of the sums' reduction serving folded_cells())
__device__ void contact_sums(const StepArgs& a, const Step& st, bool unit, bool round, bool reciprocal, bool field,
                             const Field& w, double (&sums)[4]) {
  const View& v = a.v;
  const Lvl& L0 = st.sh.lv[0];
  const Team all = st.all;
  const Field u = level0(v.u, v);
  const Field rw = st.f();
  for (int e = all.first; e < L0.count; e += all.stride) {
    const std::uint8_t fl = v.flags[e];
    int i, j, k;
    L0.coords(e, i, j, k);
    if (field) write_node_field(a, u, e);
    if (reciprocal) {
      const Vec3f re = rw.at(e);
      sums[2] -= dot_d(u.at(e), re);
      sums[3] += dot_d(w.at(e), re);
    }
    if (fl & kElasticContact) {
      const float fn = dot(deform::elastic_apply_node(st.km(), CellModuli{v.cell_e, L0}, Load{w, L0}, L0.n, 1.0f, i,
                                                      j, k),
                           a.nrm);
      if (v.react) v.react[(unit ? v.capacity : 0) + e] = fn;
      sums[0] += double(fn);
      sums[1] += 1;
      if (reciprocal) sums[2] += double(fn) * double(dot(u.at(e), a.nrm));
      if (round && fn < 0.0f) {
        v.flags[e] = std::uint8_t(fl & ~kElasticContact);
        sums[2] += 1;
      }
    } else if (round) {
      const float t = st.push(fl, i, j, k);
      if (t > 0 && t - dot(w.at(e), a.nrm) > a.penetration) {
        v.flags[e] = std::uint8_t(fl | kElasticContact);
        sums[2] += 1;
      }
    }
  }
}

// after write_field() and a barrier: this thread's count of the cells the field in voxels
// folds (elastic_inverted_cells() on the CPU)
__device__ double folded_cells(const StepArgs& a, const Step& st) {
  const Lvl& L0 = st.sh.lv[0];
  double folded = 0;
  auto load_vox = [&](int i, int j, int k) {
    const int e = L0.at(i, j, k);
    return Vec3f{a.out[0][e], a.out[1][e], a.out[2][e]};
  };
  for (int e = st.all.first; e < L0.count; e += st.all.stride) {
    int i, j, k;
    L0.coords(e, i, j, k);
    if (i + 1 >= L0.n.x || j + 1 >= L0.n.y || k + 1 >= L0.n.z) continue;
    if (deform::cell_folded(load_vox, i, j, k)) folded += 1;
  }
  return folded;
}

// the step's counters for the host but the folded cells' count, which the threads add to
// the result themselves
static_assert(sizeof(ElasticCounters) == 64, "write_result() writes every counter but inverted: add a new one there");
__device__ void write_result(ElasticCounters* r, const ElasticCounters& out) {
  r->contact = out.contact;
  r->contact_nodes = out.contact_nodes;
  r->rounds = out.rounds;
  r->settled = out.settled;
  r->iterations = out.iterations;
  r->converged = out.converged;
  r->stiffness_iterations = out.stiffness_iterations;
  r->residual = out.residual;
  r->press_n = out.press_n;
  r->stiffness_n_per_mm = out.stiffness_n_per_mm;
  r->superposed = out.superposed;
}

// the step's end, once the field in voxels is written and a barrier passed: the cells it
// folds (each thread adds its count to the result, zeroed at the start, with no barrier
// after: the host reads it once the kernel ended), the counters, the ring's next slot
__device__ void end_step(const StepArgs& a, const Step& st, const Ring& ring, const ElasticCounters& out) {
  const double folded = folded_cells(a, st);
  if (folded > 0) atomicAdd(&a.result->inverted, (unsigned long long)folded);
  if (blockIdx.x == 0 && threadIdx.x == 0) {
    write_result(a.result, out);
    a.v.sums[kRingNext] = ring.slot;
  }
}

// what the step solves, in order: contact rounds, a last solve of u when they ran out
// with the set still changing, the unit press
enum Job { kRound, kLast, kUnit, kDone };

template <int MinBlocks>
__global__ void __launch_bounds__(kThreads, MinBlocks) elastic_step_kernel(const __grid_constant__ StepArgs a) {
  cg::grid_group g = cg::this_grid();
  // the shared table as raw bytes (__shared__ allows no initialisers, which Vec3i has)
  __shared__ alignas(16) unsigned char shared_bytes[sizeof(StepShared)];
  StepShared& sh = *reinterpret_cast<StepShared*>(shared_bytes);
  const View& v = a.v;
  if (threadIdx.x == 0) make_step_table(a, sh);
  copy_cell_matrix(a.k);
  // the folded cells' count, which every thread adds to at the end (after many barriers)
  if (blockIdx.x == 0 && threadIdx.x == 0) a.result->inverted = 0;
  // the ring from where the last step left it (kRingNext)
  Ring ring{v.sums, int(v.sums[kRingNext]) % kRing, Tracer{a.trace, a.trace_pairs, 0}};
  const Team all{int(blockIdx.x * blockDim.x + threadIdx.x), int(gridDim.x * blockDim.x)};
  __syncthreads();
  ring.tracer.stamp(kPassStart * 16);
  const Step st{a, sh, g, ring, all, Team{int(threadIdx.x), int(blockDim.x)}};
  const Lvl& L0 = sh.lv[0];
  const Field u = level0(v.u, v), unit = level0(v.u_unit, v);
  ElasticCounters out{};
  out.settled = 1;
  out.converged = 1;

  // the contact set (start_contact), the last field moved with the tip first (shift_copy)
  if (a.had && deform::elastic_shifts(a.shift_vox) && a.predict != int(ElasticPredict::kNone)) shift_copy(a, st);
  double started[3] = {0, 0, 0};  // under the sphere, joined or left, in contact
  started[0] = start_contact(a, st, started[1], started[2]);
  reduce(ring, started, g, kPassContact * 16);
  if (started[0] == 0) {
    // nothing pressed: the tissue at rest
    for (int e = all.first; e < L0.count; e += all.stride) {
      u.set(e, Vec3f{0, 0, 0});
      a.out[0][e] = a.out[1][e] = a.out[2][e] = 0.0f;
    }
    if (blockIdx.x == 0 && threadIdx.x == 0) {
      write_result(a.result, out);
      v.sums[kRingNext] = ring.slot;
    }
    return;
  }
  out.contact = 1;

  if (a.superpose && started[1] == 0) {
    // superposed (deform::elastic_superposes): the last press plus factor unit presses,
    // which start_contact() wrote; the contact nodes' reactions and the push grow by factor
    // times the unit press's, and the field in voxels, then the folds
    const float factor = a.predict_factor;
    for (int e = all.first; e < L0.count; e += all.stride) {
      write_node_field(a, u, e);
      if (v.react && (v.flags[e] & kElasticContact)) v.react[e] += factor * v.react[v.capacity + e];
    }
    out.superposed = 1;
    out.rounds = 0;
    out.contact_nodes = int(started[2]);
    out.residual = a.last_residual;
    out.press_n = a.last_push_n + double(factor) * a.last_stiffness;
    out.stiffness_n_per_mm = a.last_stiffness;
    st.grid_sync(kPassField);
    end_step(a, st, ring, out);
    return;
  }

  // the solves: contact rounds (after each, nodes the finger pulls leave and skin nodes
  // pushed into the sphere join), one more when the last round still changed the set, then
  // the unit press (every contact node 1 mm along n, the set held) when asked. After each,
  // one pass over the contact nodes sums their forces along n (the finger's push: the
  // reaction, or the stiffness), which after a round that changed nothing is u's reaction
  const int rounds = max(1, a.contact_rounds);
  int round = 0;
  bool settled = false, field = false;  // field: the last contact_sums() wrote the field in voxels
  Job job = kRound;
  while (job != kDone) {
    const Field w = job == kUnit ? unit : u;
    // (no barrier: the solve's first pass reads w at the nodes this thread wrote it)
    job_start(a, st, job == kUnit, w);
    const Step::Solve sr = st.solve(w, job == kUnit && a.reciprocal ? a.stiffness_tolerance : a.tolerance);
    if (job == kUnit) {
      out.stiffness_iterations = sr.iterations;
    } else {
      out.iterations += sr.iterations;
      out.residual = sr.residual;
      out.converged = out.converged && sr.converged;
      if (job == kRound) out.rounds = round + 1;
    }
    // the contact nodes' forces along n and their count; after a round, the set's update;
    // after the unit press by reciprocity (elastic_math.h) the push sum of u . K w and w's
    // residual's part of w . K w; u in voxels where u is final: after the unit press, and
    // after any solve of u without one (a later round writes it again)
    const bool reciprocal = job == kUnit && a.reciprocal;
    field = job == kUnit || !a.stiffness;
    double sums[4] = {0, 0, 0, 0};
    contact_sums(a, st, job == kUnit, job == kRound, reciprocal, field, w, sums);
    reduce(ring, sums, g, kPassContact * 16);
    if (job == kRound) {
      ++round;
      settled = sums[2] == 0;
      if (!settled) {
        job = round < rounds ? kRound : kLast;
        continue;
      }
    }
    if (job == kUnit) {
      out.stiffness_n_per_mm = reciprocal ? sums[0] - sums[3] : sums[0];
      if (reciprocal) out.press_n = sums[2];
      job = kDone;
    } else {
      out.press_n = sums[0];
      out.contact_nodes = int(sums[1]);
      job = a.stiffness && out.contact_nodes > 0 ? kUnit : kDone;
    }
  }
  out.settled = settled;

  // the field in voxels for the inversion, here only where the last sums' pass did not
  // write it (the unit press was asked for, but no node was left in contact to press),
  // then the cells it folds
  if (!field) {
    write_field(a, st);
    st.grid_sync(kPassField);
  }
  end_step(a, st, ring, out);
}

}  // namespace

}  // namespace palpsim::cuda
