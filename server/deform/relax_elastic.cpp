// The elastic model on the CPU: the per-VOI set-up (moduli, flags, diagonals of every
// level), the contact rounds and conjugate gradients preconditioned by
// a multigrid V-cycle (elastic_math.h says what is solved and how).
#include "deform/relax_elastic.h"

#include <algorithm>
#include <cmath>

#include "deform/node_loops.h"

namespace palpsim::deform {

namespace {

// one level's arrays (level 0: the session's own; coarse: slices of the coarse buffers)
struct Level {
  Vec3i n{0, 0, 0};
  float scale = 1;  // cell edge over level 0's
  std::uint8_t* flags = nullptr;
  float* e = nullptr;  // cell moduli (kPa) at their lowest corner's index
  Vec3f* inv_diag = nullptr;
  Vec3f* x = nullptr;  // the V-cycle's correction
  Vec3f* f = nullptr;  // its right-hand side
  Vec3f* r = nullptr;  // its residual
  Vec3f* d = nullptr;  // the smoother's last step
  float lmax = 1;      // the largest eigenvalue of D^-1 K (power estimate)
  long long count() const { return (long long)n.x * n.y * n.z; }
  long long index(int i, int j, int k) const { return ((long long)k * n.y + j) * n.x + i; }
};

// the levels of the session's plan over its buffers
struct Levels {
  Level lv[kElasticMaxLevels];
  int count = 0;
};

Levels levels_of(ElasticCpu& s) {
  Levels L;
  L.count = s.plan.levels;
  const long long n0 = (long long)s.voi.count();
  for (int l = 0; l < L.count; ++l) {
    Level& v = L.lv[l];
    v.n = s.plan.size[l];
    v.scale = float(1 << l);
    if (l == 0) {
      v.flags = s.flags.data();
      v.e = s.cell_e.data();
      v.inv_diag = s.inv_diag.data();
      v.x = s.z.data();
      v.f = s.r.data();
      v.r = s.res0.data();
      v.d = s.cheb_d.data();
    } else {
      const long long o = s.plan.offset[l];
      v.flags = s.c_flags.data() + o;
      v.e = s.c_e.data() + o;
      v.inv_diag = s.inv_diag.data() + n0 + o;
      v.x = s.c_x.data() + o;
      v.f = s.c_f.data() + o;
      v.r = s.c_r.data() + o;
      v.d = s.c_d.data() + o;
    }
    v.lmax = s.lmax[l];
  }
  return L;
}

// y = K x on a level (every node, held ones included): cell by cell, each cell's 24 x 24
// matrix times its corners, scattered to them
void apply_level(const Level& L, const std::array<float, 576>& k, const Vec3f* x, Vec3f* y) {
  std::fill_n(y, L.count(), Vec3f{0, 0, 0});
  const Vec3i n = L.n;
  const long long sx = n.x, sxy = (long long)n.x * n.y;
  long long off[8];
  for (int c = 0; c < 8; ++c) {
    const Vec3i o = elastic_corner(c);
    off[c] = o.x + o.y * sx + o.z * sxy;
  }
  for (int ck = 0; ck + 1 < n.z; ++ck)
    for (int cj = 0; cj + 1 < n.y; ++cj)
      for (int ci = 0; ci + 1 < n.x; ++ci) {
        const long long base = L.index(ci, cj, ck);
        const float e = L.e[base];
        if (e == 0.0f) continue;
        float uc[24];
        bool any = false;
        for (int c = 0; c < 8; ++c) {
          const Vec3f& v = x[base + off[c]];
          uc[3 * c] = v.x;
          uc[3 * c + 1] = v.y;
          uc[3 * c + 2] = v.z;
          any = any || v.x != 0.0f || v.y != 0.0f || v.z != 0.0f;
        }
        if (!any) continue;
        // the matrix is symmetric: column c is row c
        float yc[24] = {};
        for (int c = 0; c < 24; ++c) {
          const float v = uc[c];
          if (v == 0.0f) continue;
          const float* col = k.data() + 24 * c;
          for (int r = 0; r < 24; ++r) yc[r] += col[r] * v;
        }
        const float w = e * L.scale;
        for (int c = 0; c < 8; ++c) {
          Vec3f& t = y[base + off[c]];
          t.x += yc[3 * c] * w;
          t.y += yc[3 * c + 1] * w;
          t.z += yc[3 * c + 2] * w;
        }
      }
}

double dot_all(const Vec3f* a, const Vec3f* b, long long count) {
  double s = 0;
  for (long long e = 0; e < count; ++e) s += double(a[e].x) * b[e].x + double(a[e].y) * b[e].y + double(a[e].z) * b[e].z;
  return s;
}

// res = Pi (f - K x)
void residual(const Level& L, const std::array<float, 576>& k, const Vec3f& nrm, const Vec3f* f, const Vec3f* x,
              Vec3f* res) {
  apply_level(L, k, x, res);
  for (long long e = 0; e < L.count(); ++e) res[e] = elastic_project(L.flags[e], nrm, f[e] - res[e]);
}

// x = S f (from_zero) or x += S (f - K x): the level's Chebyshev smoother of `degree`
// over [lmax / ratio, lmax] (margin included), f projected
void smooth(const Level& v, const std::array<float, 576>& k, const Vec3f& nrm, const Vec3f* f, Vec3f* x,
            bool from_zero, int degree, float ratio) {
  float a[kElasticMaxDegree], b[kElasticMaxDegree];
  const float hi = kElasticChebyshevMargin * v.lmax;
  elastic_chebyshev(hi / ratio, hi, degree, a, b);
  for (int st = 0; st < degree; ++st) {
    const bool first = st == 0 && from_zero;
    if (!first) residual(v, k, nrm, f, x, v.r);
    const Vec3f* r = first ? f : v.r;
    for (long long e = 0; e < v.count(); ++e) {
      const Vec3f dg = v.inv_diag[e];
      const Vec3f z = elastic_project(v.flags[e], nrm, Vec3f{dg.x * r[e].x, dg.y * r[e].y, dg.z * r[e].z});
      v.d[e] = st == 0 ? z * b[0] : v.d[e] * a[st] + z * b[st];
      x[e] = first ? v.d[e] : x[e] + v.d[e];
    }
  }
}

// the V-cycle from level l down: L.lv[l].x = B L.lv[l].f (both projected)
void vcycle(const Levels& L, int l, const std::array<float, 576>& k, const Vec3f& nrm, const ElasticDegrees& deg) {
  const Level& v = L.lv[l];
  const int degree = deg.at(l, L.count);
  if (l + 1 == L.count) {
    smooth(v, k, nrm, v.f, v.x, true, degree, kElasticCoarsestRatio);
    return;
  }
  smooth(v, k, nrm, v.f, v.x, true, degree, kElasticChebyshevRatio);
  // the coarse level's right-hand side: the restricted residual
  residual(v, k, nrm, v.f, v.x, v.r);
  const Level& c = L.lv[l + 1];
  each_node(c.n, [&](int i, int j, int kk) {
    const Vec3f g = elastic_restrict(
        [&](int a, int b, int d) {
          return (a < 0 || b < 0 || d < 0 || a >= v.n.x || b >= v.n.y || d >= v.n.z) ? Vec3f{0, 0, 0}
                                                                                    : v.r[v.index(a, b, d)];
        },
        i, j, kk);
    const long long e = c.index(i, j, kk);
    c.f[e] = elastic_project(c.flags[e], nrm, g);
  });
  vcycle(L, l + 1, k, nrm, deg);
  // the coarse correction, then the post-smoothing
  each_node(v.n, [&](int i, int j, int kk) {
    const Vec3f g = elastic_prolong(
        [&](int a, int b, int d) {
          return (a >= c.n.x || b >= c.n.y || d >= c.n.z) ? Vec3f{0, 0, 0} : c.x[c.index(a, b, d)];
        },
        i, j, kk);
    const long long e = v.index(i, j, kk);
    v.x[e] += elastic_project(v.flags[e], nrm, g);
  });
  smooth(v, k, nrm, v.f, v.x, false, degree, kElasticChebyshevRatio);
}

// the largest eigenvalue of D^-1 K on a level (held nodes out): kElasticLanczosSteps
// Lanczos steps (elastic_lanczos_lmax) from a fixed pseudo-random start
// (elastic_power_start), as the GPU runs them: step j >= 1 applies A = Pi D^-1 K to z_{j-1}
// = A u_{j-1} and gets z_j = A u_j by linearity (A z_{j-1} - alpha z_{j-1} - beta z_{j-2}),
// so that each step is one application to a vector the last step wrote; uses the level's
// x and f (u), r and d (z)
float estimate_lmax(const Level& v, const std::array<float, 576>& k) {
  const Vec3f none{0, 0, 0};
  const long long n = v.count();
  Vec3f* u[2] = {v.x, v.f};
  Vec3f* z[2] = {v.r, v.d};
  std::vector<Vec3f> kz(static_cast<std::size_t>(n));
  // A y at every node, into kz
  auto apply = [&](const Vec3f* y) {
    apply_level(v, k, y, kz.data());
    for (long long e = 0; e < n; ++e) {
      const Vec3f dg = v.inv_diag[e];
      kz[std::size_t(e)] = elastic_project(v.flags[e], none, Vec3f{dg.x * kz[e].x, dg.y * kz[e].y, dg.z * kz[e].z});
    }
  };
  // <a, b>_D (D: the inverse of inv_diag; no weight where there is no diagonal)
  auto dot_d = [&](const Vec3f& a, const Vec3f& b, const Vec3f& inv) {
    return (inv.x > 0 ? double(a.x) * b.x / inv.x : 0.0) + (inv.y > 0 ? double(a.y) * b.y / inv.y : 0.0) +
           (inv.z > 0 ? double(a.z) * b.z / inv.z : 0.0);
  };
  double s[kElasticLanczosSteps], nz[kElasticLanczosSteps];
  for (long long e = 0; e < n; ++e) {
    const unsigned long long m = 3ull * (unsigned long long)e;
    u[0][e] = elastic_project(v.flags[e], none,
                              Vec3f{elastic_power_start(m), elastic_power_start(m + 1), elastic_power_start(m + 2)});
    u[1][e] = z[1][e] = none;
  }
  for (int j = 0; j < kElasticLanczosSteps; ++j) {
    const double alpha = j > 0 && s[j - 1] > 0 ? nz[j - 1] / s[j - 1] : 0.0;
    const double beta = j > 1 && s[j - 2] > 0 ? s[j - 1] / s[j - 2] : 0.0;
    Vec3f* const un = u[j & 1];  // u_j over u_{j-2}
    Vec3f* const zn = z[j & 1];  // z_j over z_{j-2}
    const Vec3f* const up = u[(j + 1) & 1];
    const Vec3f* const zp = z[(j + 1) & 1];
    apply(j == 0 ? u[0] : zp);
    double sj = 0, nj = 0;
    for (long long e = 0; e < n; ++e) {
      if (j > 0) {
        un[e] = zp[e] - up[e] * float(alpha) - un[e] * float(beta);
        zn[e] = kz[std::size_t(e)] - zp[e] * float(alpha) - zn[e] * float(beta);
      } else {
        zn[e] = kz[std::size_t(e)];
      }
      sj += dot_d(un[e], un[e], v.inv_diag[e]);
      nj += dot_d(zn[e], un[e], v.inv_diag[e]);
    }
    s[j] = sj;
    nz[j] = nj;
  }
  return float(elastic_lanczos_lmax(s, nz, kElasticLanczosSteps));
}

struct SolveResult {
  int iterations = 0;
  double residual = 0;  // relative to rref
  bool converged = true;
};

// conjugate gradients on level 0 for `u` (its constrained components set already), to
// |r| <= tol rref or max_it steps; r, z, p, q, res0 are scratch
SolveResult pcg(ElasticCpu& s, const Levels& L, const Vec3f& nrm, Vec3f* u, double rref, int max_it, float tol) {
  const Level& v = L.lv[0];
  const long long n = v.count();
  Vec3f* r = s.r.data();
  Vec3f* z = s.z.data();
  Vec3f* p = s.p.data();
  Vec3f* q = s.q.data();
  SolveResult out;
  // r = Pi (0 - K u): no load but the constraints
  apply_level(v, s.k, u, r);
  for (long long e = 0; e < n; ++e) r[e] = elastic_project(v.flags[e], nrm, -r[e]);
  double rn = std::sqrt(dot_all(r, r, n));
  out.residual = rref > 0 ? rn / rref : 0;
  if (rref <= 0 || rn <= tol * rref) return out;
  vcycle(L, 0, s.k, nrm, s.degrees);  // z = B r
  std::copy_n(z, n, p);
  double rz = dot_all(r, z, n);
  for (int it = 0; it < max_it; ++it) {
    apply_level(v, s.k, p, q);
    for (long long e = 0; e < n; ++e) q[e] = elastic_project(v.flags[e], nrm, q[e]);
    const double pq = dot_all(p, q, n);
    if (!(pq > 0)) break;
    const float alpha = float(rz / pq);
    for (long long e = 0; e < n; ++e) {
      u[e] += p[e] * alpha;
      r[e] -= q[e] * alpha;
    }
    out.iterations = it + 1;
    rn = std::sqrt(dot_all(r, r, n));
    out.residual = rn / rref;
    if (rn <= tol * rref) return out;
    vcycle(L, 0, s.k, nrm, s.degrees);
    const double rz_new = dot_all(r, z, n);
    const float beta = float(rz_new / rz);
    rz = rz_new;
    for (long long e = 0; e < n; ++e) p[e] = z[e] + p[e] * beta;
  }
  out.converged = out.residual <= tol;
  return out;
}

template <typename T>
void grow(std::vector<T>& v, std::size_t n) {
  if (v.size() < n) v.resize(n);
}

// the moduli, static flags and diagonals of every level for a new VOI
}  // namespace

std::uint64_t material_key(const ElasticMaterial& m) {
  // FNV-1a over the material's bytes: a changed table, skin or gel asks for a new set-up
  const unsigned char* b = reinterpret_cast<const unsigned char*>(&m);
  std::uint64_t h = 1469598103934665603ull;
  for (std::size_t i = 0; i < sizeof(m); ++i) h = (h ^ b[i]) * 1099511628211ull;
  return h;
}

void elastic_set_up_cpu(const Patient& p, const Voi& voi, const ElasticParams& prm, ElasticCpu& s) {
  const Grid& g = p.grid;
  s.k = elastic_element(g.spacing_mm, prm.poisson);
  s.poisson = prm.poisson;
  s.have_u = false;
  s.have_unit = false;
  s.plan = elastic_plan(voi.size);
  const std::size_t n0 = std::size_t(voi.count());
  const std::size_t nc = std::size_t(s.plan.coarse_count);
  for (auto* v : {&s.u, &s.u_unit, &s.r, &s.z, &s.p, &s.q, &s.ku, &s.res0, &s.cheb_d}) grow(*v, n0);
  grow(s.c_d, nc);
  grow(s.flags, n0);
  grow(s.cell_e, n0);
  grow(s.push, n0);
  if (prm.stiffness) {
    grow(s.react_press, n0);
    grow(s.react_unit, n0);
  }
  grow(s.inv_diag, n0 + nc);
  grow(s.c_flags, nc);
  grow(s.c_e, nc);
  grow(s.c_x, nc);
  grow(s.c_f, nc);
  grow(s.c_r, nc);
  // node moduli (kPa) into push (scratch here), flags
  auto in_body = [&](int i, int j, int k) { return g.contains(i, j, k) && p.body.data[g.index(i, j, k)] != 0; };
  each_node(voi.size, [&](int i, int j, int k) {
    const int gi = voi.lo.x + i, gj = voi.lo.y + j, gk = voi.lo.z + k;
    const std::size_t pi = g.index(gi, gj, gk);
    const bool body = p.body.data[pi] != 0;
    const bool bone = p.bone.data[pi] != 0;
    const long long e = voi.index(i, j, k);
    s.push[e] = elastic_node_modulus(prm.material, p.intensity.data[pi], body, p.dist_skin_mm.data[pi]);
    const bool face = i == 0 || j == 0 || k == 0 || i + 1 == voi.size.x || j + 1 == voi.size.y || k + 1 == voi.size.z;
    s.flags[e] = elastic_static_flags(body, bone, face, in_body, gi, gj, gk);
  });
  // cell moduli: the mean of the corners' where all eight are in the body (bone counts),
  // else air's gel, so that the tissue ends at the skin nodes (traction-free there, but for the gel)
  each_node(voi.size, [&](int i, int j, int k) {
    const long long e = voi.index(i, j, k);
    if (i + 1 >= voi.size.x || j + 1 >= voi.size.y || k + 1 >= voi.size.z) {
      s.cell_e[e] = 0;
      return;
    }
    s.cell_e[e] = elastic_cell_modulus(
        [&](int c) {
          const Vec3i o = elastic_corner(c);
          return s.push[voi.index(i + o.x, j + o.y, k + o.z)];
        },
        [&](int c) {
          const Vec3i o = elastic_corner(c);
          return p.body.data[g.index(voi.lo.x + i + o.x, voi.lo.y + j + o.y, voi.lo.z + k + o.z)] != 0;
        },
        prm.material.air_e_kpa);
  });
  std::fill_n(s.push.begin(), n0, -1.0f);
  s.voi = voi;
  Levels L = levels_of(s);
  // coarse levels: moduli and held nodes from the level below
  for (int l = 1; l < L.count; ++l) {
    const Level& f = L.lv[l - 1];
    const Level& c = L.lv[l];
    each_node(c.n, [&](int i, int j, int k) {
      const long long e = c.index(i, j, k);
      c.e[e] = (i + 1 < c.n.x && j + 1 < c.n.y && k + 1 < c.n.z)
                   ? elastic_coarse_cell_e([&](int a, int b, int d) { return f.e[f.index(a, b, d)]; }, f.n, i, j, k)
                   : 0.0f;
      const bool beyond = 2 * i >= f.n.x || 2 * j >= f.n.y || 2 * k >= f.n.z;
      c.flags[e] = elastic_coarse_flags(beyond ? 0 : (f.flags[f.index(2 * i, 2 * j, 2 * k)] & (kElasticHeld | kElasticAir)), beyond);
    });
  }
  // every level's inverse Jacobi diagonal
  for (int l = 0; l < L.count; ++l) {
    const Level& v = L.lv[l];
    each_node(v.n, [&](int i, int j, int k) {
      const Vec3f d = elastic_diag_node([&](int r, int c) { return s.k[std::size_t(24 * r + c)]; },
                                        [&](int a, int b, int cc) { return v.e[v.index(a, b, cc)]; }, v.n, v.scale, i, j, k);
      v.inv_diag[v.index(i, j, k)] = Vec3f{d.x > 0 ? 1 / d.x : 0.0f, d.y > 0 ? 1 / d.y : 0.0f, d.z > 0 ? 1 / d.z : 0.0f};
    });
  }
  // every level's largest eigenvalue of D^-1 K, for its smoother
  for (int l = 0; l < L.count; ++l) {
    s.lmax[l] = estimate_lmax(L.lv[l], s.k);
    L.lv[l].lmax = s.lmax[l];
  }
}

namespace {

// the coarse levels' contact flags from level 0's
void coarsen_contact(const Levels& L) {
  for (int l = 1; l < L.count; ++l) {
    const Level& f = L.lv[l - 1];
    const Level& c = L.lv[l];
    each_node(c.n, [&](int i, int j, int k) {
      std::uint8_t& cf = c.flags[c.index(i, j, k)];
      cf = std::uint8_t(cf & ~kElasticContact);
      const bool beyond = 2 * i >= f.n.x || 2 * j >= f.n.y || 2 * k >= f.n.z;
      if (!beyond && !(cf & kElasticHeld)) cf |= f.flags[f.index(2 * i, 2 * j, 2 * k)] & kElasticContact;
    });
  }
}

}  // namespace

ElasticSolve elastic_solve_cpu(ElasticCpu& s, const Vec3f& nrm, Vec3f* u, int max_iterations, float tolerance) {
  Levels L = levels_of(s);
  const Level& v0 = L.lv[0];
  const long long n = v0.count();
  coarsen_contact(L);
  // the scale of the tolerance: the residual of the constrained values alone (free parts 0)
  Vec3f* lift = s.q.data();
  for (long long e = 0; e < n; ++e) {
    const std::uint8_t f = v0.flags[e];
    lift[e] = (f & kElasticHeld) ? u[e] : ((f & kElasticContact) ? nrm * dot(u[e], nrm) : Vec3f{0, 0, 0});
  }
  apply_level(v0, s.k, lift, s.ku.data());
  double r2 = 0;
  for (long long e = 0; e < n; ++e) {
    const Vec3f t = elastic_project(v0.flags[e], nrm, s.ku[std::size_t(e)]);
    r2 += double(dot(t, t));
  }
  const SolveResult r = pcg(s, L, nrm, u, std::sqrt(r2), max_iterations, tolerance);
  return ElasticSolve{r.iterations, r.residual, r.converged};
}

void elastic_operator_cpu(ElasticCpu& s, const Vec3f& nrm, const Vec3f* x, Vec3f* y) {
  Levels L = levels_of(s);
  coarsen_contact(L);
  apply_level(L.lv[0], s.k, x, y);
  for (long long e = 0; e < L.lv[0].count(); ++e) y[e] = elastic_project(L.lv[0].flags[e], nrm, y[e]);
}

void elastic_precondition_cpu(ElasticCpu& s, const Vec3f& nrm, const Vec3f* r, Vec3f* z) {
  Levels L = levels_of(s);
  coarsen_contact(L);
  const long long n = L.lv[0].count();
  std::copy_n(r, n, s.r.begin());
  vcycle(L, 0, s.k, nrm, s.degrees);
  std::copy_n(s.z.begin(), n, z);
}

Vec3f elastic_node_force_cpu(const ElasticCpu& s, const Vec3f* u, int i, int j, int k) {
  const Voi& voi = s.voi;
  return elastic_apply_node([&](int r, int c) { return s.k[std::size_t(24 * r + c)]; },
                            [&](int a, int b, int c) { return s.cell_e[std::size_t(voi.index(a, b, c))]; },
                            [&](int a, int b, int c) { return u[voi.index(a, b, c)]; }, voi.size, 1.0f, i, j, k);
}

bool elastic_tip_inside(const Patient& p, const Vec3& tip_vox) {
  const Grid& g = p.grid;
  const Vec3f t{float(tip_vox.x), float(tip_vox.y), float(tip_vox.z)};
  const float c = trilinear<float>(
      [&](int i, int j, int k) { return g.contains(i, j, k) ? float(p.body.data[g.index(i, j, k)] != 0) : 0.0f; }, t);
  return c > 0.5f;
}

long long elastic_inverted_cells(const Voi& voi, const Vec3f* u_vox) {
  auto load = [&](int i, int j, int k) { return u_vox[voi.index(i, j, k)]; };
  long long n = 0;
  for (int k = 0; k + 1 < voi.size.z; ++k)
    for (int j = 0; j + 1 < voi.size.y; ++j)
      for (int i = 0; i + 1 < voi.size.x; ++i) {
        if (cell_folded(load, i, j, k)) ++n;
      }
  return n;
}

std::size_t elastic_cpu_bytes(const ElasticCpu& s) {
  auto b = [](const auto& v) { return v.capacity() * sizeof(v[0]); };
  return b(s.u) + b(s.u_unit) + b(s.r) + b(s.z) + b(s.p) + b(s.q) + b(s.ku) + b(s.flags) + b(s.cell_e) + b(s.push) +
         b(s.react_press) + b(s.react_unit) + b(s.inv_diag) + b(s.c_flags) + b(s.c_e) + b(s.c_x) + b(s.c_f) +
         b(s.c_r) + b(s.res0) + b(s.tmp_u) + b(s.tmp_flags) + b(s.cheb_d) + b(s.c_d);
}

namespace {

// the warm start (relax_elastic_cpu()): the last field and contact set shifted onto this
// VOI when it or the model changed (the set-up first), the tissue at rest when there is
// none (elastic_warm); whether a last field is the start
bool warm_start(const Patient& pat, const Voi& voi, const ElasticParams& prm, ElasticCpu& s) {
  const long long n = voi.count();
  const bool same_model = s.poisson == prm.poisson && s.material_key == material_key(prm.material);
  const Voi last = s.voi;
  const bool had = elastic_warm(s.have_u && same_model, s.last_press.pressing, last, voi);
  if (!(voi == last) || !same_model) {
    if (had) {
      grow(s.tmp_u, std::size_t(last.count()));
      grow(s.tmp_flags, std::size_t(last.count()));
      std::copy_n(s.u.begin(), last.count(), s.tmp_u.begin());
      std::copy_n(s.flags.begin(), last.count(), s.tmp_flags.begin());
    }
    elastic_set_up_cpu(pat, voi, prm, s);
    s.material_key = material_key(prm.material);
    each_node(voi.size, [&](int i, int j, int kk) {
      const long long e = voi.index(i, j, kk);
      const int a = i + voi.lo.x - last.lo.x, b = j + voi.lo.y - last.lo.y, c = kk + voi.lo.z - last.lo.z;
      // held nodes (the new VOI's faces, bone) stay at rest: the solve keeps what they hold
      const bool carry = had && last.contains(a, b, c) && !(s.flags[std::size_t(e)] & kElasticHeld);
      s.u[std::size_t(e)] = carry ? s.tmp_u[std::size_t(last.index(a, b, c))] : Vec3f{0, 0, 0};
      if (carry) s.flags[std::size_t(e)] |= s.tmp_flags[std::size_t(last.index(a, b, c))] & kElasticContact;
    });
  } else if (!had) {
    std::fill_n(s.u.begin(), n, Vec3f{0, 0, 0});
    for (long long e = 0; e < n; ++e) s.flags[std::size_t(e)] &= std::uint8_t(~kElasticContact);
    s.have_unit = false;
  }
  return had;
}

// one step's press in the VOI's frame: n from X to x (mm along the grid axes, 0 when the
// tip is outside the skin), the depth (mm), the sphere's centre R behind the tip (mm,
// VOI-local), the tip (mm, patient)
struct Press {
  double depth;
  Vec3f nrm, centre;
  float radius;
  Vec3 tip_mm;
};

Press press_of(const Patient& pat, const Voi& voi, const Vec3& skin_vox, const Vec3& tip_vox, const ElasticParams& prm) {
  const Vec3 h = pat.grid.spacing_mm;
  Press pr;
  const Vec3 d_mm{(tip_vox.x - skin_vox.x) * h.x, (tip_vox.y - skin_vox.y) * h.y, (tip_vox.z - skin_vox.z) * h.z};
  pr.depth = elastic_tip_inside(pat, tip_vox) ? norm(d_mm) : 0.0;
  pr.nrm = pr.depth > 1e-6 ? Vec3f{float(d_mm.x / pr.depth), float(d_mm.y / pr.depth), float(d_mm.z / pr.depth)}
                           : Vec3f{0, 0, 0};
  pr.radius = prm.finger_radius_mm;
  const Vec3f tip_local{float((tip_vox.x - voi.lo.x) * h.x), float((tip_vox.y - voi.lo.y) * h.y),
                        float((tip_vox.z - voi.lo.z) * h.z)};
  pr.centre = tip_local - pr.nrm * pr.radius;
  pr.tip_mm = Vec3{tip_vox.x * h.x, tip_vox.y * h.y, tip_vox.z * h.z};
  return pr;
}

// the pushes of skin nodes under the sphere and the contact set (elastic_start_contact):
// last step's nodes still under it and nodes the last field leaves inside it, or on a fresh
// start the nodes within Hertz's contact area; how many nodes lie under it, and into
// `changed` how many nodes joined or left the set
long long contact_set(ElasticCpu& s, const Voi& voi, const Vec3& h, const Press& pr, bool had,
                      const ElasticPrediction& pred, long long& changed) {
  const bool shifted = elastic_shifts(pred.shift_vox);
  const float touch = elastic_start_touch(shifted, pred.kind, float(h.x));
  const bool reactions =
      elastic_start_weighs_reactions(pred.kind, pred.shift_vox) && !s.react_press.empty() && !s.react_unit.empty();
  long long under = 0;
  changed = 0;
  const Vec3f* u = s.u.data();
  each_node(voi.size, [&](int i, int j, int kk) {
    const long long e = voi.index(i, j, kk);
    std::uint8_t& f = s.flags[std::size_t(e)];
    const bool skin = pr.depth > 1e-6 && (f & kElasticSkin) && !(f & kElasticHeld);
    const Vec3f rest{float(i * h.x), float(j * h.y), float(kk * h.z)};
    const float t = skin ? elastic_sphere_push(rest, pr.centre, pr.nrm, pr.radius) : -1.0f;
    s.push[std::size_t(e)] = t;
    if (t > 0) ++under;
    const bool was = (f & kElasticContact) != 0;
    f = std::uint8_t(f & ~kElasticContact);
    const bool pulled =
        was && reactions &&
        elastic_predicted_pull(s.react_press[std::size_t(e)], s.react_unit[std::size_t(e)], pred.factor);
    if (elastic_start_contact(t, dot(u[e], pr.nrm), was, had, float(pr.depth), touch, pulled)) f |= kElasticContact;
    changed += was != ((f & kElasticContact) != 0);
  });
  return under;
}

// the warm start's prediction (elastic_prediction): the last field and its unit press moved
// with the tip across n (held nodes keep their 0; the contact set then starts from the moved
// field's penetration), then the press's change along n
void predict_start(ElasticCpu& s, const Voi& voi, const ElasticPrediction& pred) {
  const long long n = voi.count();
  const bool unit = pred.kind == ElasticPredict::kUnit;
  if (elastic_shifts(pred.shift_vox)) {
    grow(s.tmp_u, std::size_t(n));
    auto shift_field = [&](std::vector<Vec3f>& f) {
      std::copy_n(f.begin(), n, s.tmp_u.begin());
      const auto load = [&](int a, int b, int c) {
        return voi.contains(a, b, c) ? s.tmp_u[std::size_t(voi.index(a, b, c))] : Vec3f{0, 0, 0};
      };
      each_node(voi.size, [&](int i, int j, int kk) {
        const std::size_t e = std::size_t(voi.index(i, j, kk));
        if (!(s.flags[e] & kElasticHeld)) f[e] = elastic_shifted(load, i, j, kk, pred.shift_vox);
      });
    };
    shift_field(s.u);
    if (unit) shift_field(s.u_unit);
    // the contact set from the moved field's penetration alone (elastic_shifted)
    for (long long e = 0; e < n; ++e) s.flags[std::size_t(e)] &= std::uint8_t(~kElasticContact);
  }
  for (long long e = 0; e < n; ++e)
    s.u[std::size_t(e)] =
        elastic_predicted(pred.kind, pred.factor, s.u[std::size_t(e)], unit ? s.u_unit[std::size_t(e)] : Vec3f{0, 0, 0});
}

// the contact rounds: contact nodes onto the sphere along n (held nodes stay at 0), solve,
// then nodes the finger pulls leave and skin nodes pushed into the sphere join; a last
// solve when the last round still changed the set
void contact_rounds(ElasticCpu& s, const Voi& voi, const Vec3& h, const Vec3f& nrm, const ElasticParams& prm,
                    ElasticRun& out) {
  const long long n = voi.count();
  Vec3f* u = s.u.data();
  auto place = [&]() {
    for (long long e = 0; e < n; ++e)
      if (s.flags[std::size_t(e)] & kElasticContact) u[e] = u[e] - nrm * dot(u[e], nrm) + nrm * s.push[std::size_t(e)];
  };
  auto solve = [&]() {
    const ElasticSolve sr = elastic_solve_cpu(s, nrm, u, prm.max_iterations, prm.tolerance);
    out.iterations += sr.iterations;
    out.residual = sr.residual;
    out.converged = out.converged && sr.converged;
  };
  bool settled = false;
  for (int round = 0; round < std::max(1, prm.contact_rounds) && !settled; ++round) {
    place();
    solve();
    out.rounds = round + 1;
    settled = true;
    each_node(voi.size, [&](int i, int j, int kk) {
      const long long e = voi.index(i, j, kk);
      std::uint8_t& f = s.flags[std::size_t(e)];
      const float t = s.push[std::size_t(e)];
      if (f & kElasticContact) {
        if (dot(elastic_node_force_cpu(s, u, i, j, kk), nrm) < 0.0f) {
          f = std::uint8_t(f & ~kElasticContact);
          settled = false;
        }
      } else if (t > 0 && t - dot(u[e], nrm) > kElasticPenetrationVox * float(h.x)) {
        f |= kElasticContact;
        settled = false;
      }
    });
  }
  out.contact_settled = settled;
  if (!settled) {
    place();
    solve();
  }
}

// the reaction: the force the finger applies along n, summed over the contact nodes
void reaction(ElasticCpu& s, const Voi& voi, const Vec3f& nrm, ElasticRun& out) {
  double press = 0;
  int contacts = 0;
  each_node(voi.size, [&](int i, int j, int kk) {
    const std::size_t e = std::size_t(voi.index(i, j, kk));
    if (!(s.flags[e] & kElasticContact)) return;
    ++contacts;
    const float fn = dot(elastic_node_force_cpu(s, s.u.data(), i, j, kk), nrm);
    if (!s.react_press.empty()) s.react_press[e] = fn;
    press += fn;
  });
  out.contact_nodes = contacts;
  out.force_n = Vec3(nrm) * -press;
}

// the stiffness: the unit press (every contact node 1 mm along n) with the set held; with
// stiffness_tolerance, the force and stiffness by reciprocity (elastic_math.h)
void unit_press(ElasticCpu& s, const Voi& voi, const Vec3f& nrm, const ElasticParams& prm, ElasticRun& out) {
  const long long n = voi.count();
  const Vec3f* u = s.u.data();
  Vec3f* w = s.u_unit.data();
  // without a last unit press along n to start from: the press's field scaled to the tip's
  // 1 mm (the unit press's shape to first order; held nodes hold 0 in both)
  if (!s.have_unit || !(s.unit_normal == nrm)) {
    const float scale = elastic_unit_start_scale(out.depth_mm);
    for (long long e = 0; e < n; ++e) w[e] = u[e] * scale;
  }
  for (long long e = 0; e < n; ++e) {
    const std::uint8_t f = s.flags[std::size_t(e)];
    if (f & kElasticContact) w[e] = w[e] - nrm * dot(w[e], nrm) + nrm;
  }
  const bool reciprocal = prm.stiffness_tolerance > 0;
  const ElasticSolve sr = elastic_solve_cpu(s, nrm, w, prm.max_iterations, prm.unit_tolerance());
  out.stiffness_iterations = sr.iterations;
  double k_n = 0, push_k = 0;
  each_node(voi.size, [&](int i, int j, int kk) {
    const long long e = voi.index(i, j, kk);
    if (!(s.flags[std::size_t(e)] & kElasticContact)) return;
    const float fn = dot(elastic_node_force_cpu(s, w, i, j, kk), nrm);
    if (!s.react_unit.empty()) s.react_unit[std::size_t(e)] = fn;
    const double kn = fn;
    k_n += kn;
    push_k += kn * dot(u[e], nrm);
  });
  if (reciprocal) {
    // w.K.u and w.K.w, with the free components of K w as the unit press's residual r
    // leaves them (K w = -r there)
    double wr = 0, ur = 0;
    for (long long e = 0; e < n; ++e) {
      wr += double(dot(w[e], s.r[std::size_t(e)]));
      ur += double(dot(u[e], s.r[std::size_t(e)]));
    }
    out.force_n = Vec3(nrm) * -(push_k - ur);
    k_n -= wr;
  }
  out.stiffness_n_per_mm = k_n;
  s.have_unit = true;
  s.unit_normal = nrm;
}

}  // namespace

ElasticRun relax_elastic_cpu(const Patient& pat, const Voi& voi, const Vec3& skin_vox, const Vec3& tip_vox,
                             const ElasticParams& prm, ElasticCpu& s, Vec3f* u_vox) {
  const Vec3 h = pat.grid.spacing_mm;
  ElasticRun out;
  const long long n = voi.count();
  const bool had = warm_start(pat, voi, prm, s);
  s.degrees = prm.degrees;
  out.warm = had;
  Vec3f* u = s.u.data();
  const Press pr = press_of(pat, voi, skin_vox, tip_vox, prm);
  out.depth_mm = pr.depth;
  out.normal = Vec3(pr.nrm);
  // the warm start's prediction of this press from the last one (elastic_prediction)
  const ElasticPrediction pred =
      elastic_prediction(s.last_press, had && prm.predict, s.have_unit && dot(s.unit_normal, pr.nrm) > 0.999f,
                         pr.tip_mm, pr.depth, pr.nrm, h);
  if (pred.kind != ElasticPredict::kNone) predict_start(s, voi, pred);
  out.prediction = pred.kind;
  s.last_press = ElasticLastPress{pr.depth > 1e-6, pr.tip_mm, pr.depth, pr.nrm};
  // superposing, as far as the host can tell (the set must also stay as it was)
  const bool superpose = s.have_unit && !s.react_press.empty() && !s.react_unit.empty() &&
                         s.superpose.allows(pred, dot(s.unit_normal, pr.nrm), pr.depth, prm);
  long long changed = 0;
  if (contact_set(s, voi, h, pr, had, pred, changed) == 0) {
    // nothing pressed: the tissue at rest
    std::fill_n(u, n, Vec3f{0, 0, 0});
    s.have_u = true;
    s.have_unit = false;
    s.superpose.after(out, pred.factor);
    std::fill_n(u_vox, n, Vec3f{0, 0, 0});
    return out;
  }
  out.contact = true;
  if (superpose && changed == 0) {
    // the last press plus factor unit presses (predict_start wrote it): the contact nodes'
    // reactions and the force grow by factor times the unit press's, the rest as it was
    out.superposed = true;
    out.rounds = 0;
    out.residual = s.superpose.last_residual;
    for (long long e = 0; e < n; ++e)
      if (s.flags[std::size_t(e)] & kElasticContact) {
        ++out.contact_nodes;
        s.react_press[std::size_t(e)] += pred.factor * s.react_unit[std::size_t(e)];
      }
    out.force_n = Vec3(pr.nrm) * -s.superpose.superposed_push(pred.factor);
    out.stiffness_n_per_mm = s.superpose.last_stiffness;
  } else {
    contact_rounds(s, voi, h, pr.nrm, prm, out);
    reaction(s, voi, pr.nrm, out);
    if (prm.stiffness && out.contact_nodes > 0) unit_press(s, voi, pr.nrm, prm, out);
  }
  // what the next steps may superpose on
  s.superpose.after(out, pred.factor);
  s.have_u = true;
  // the field in voxels for the backend's buffers, and the folds it holds
  for (long long e = 0; e < n; ++e) u_vox[e] = Vec3f{float(u[e].x / h.x), float(u[e].y / h.y), float(u[e].z / h.z)};
  out.inverted_cells = elastic_inverted_cells(voi, u_vox);
  return out;
}

}  // namespace palpsim::deform
