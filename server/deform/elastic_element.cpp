// The elastic model's cell matrix (elastic_element(), relax_elastic.h): a trilinear
// hexahedron with selective reduced integration, for E = 1 kPa, shared by both backends.
#include <cmath>

#include "deform/relax_elastic.h"

namespace palpsim::deform {

std::array<float, 576> elastic_element(const Vec3& h_mm, double nu) {
  // Lame parameters for E = 1 kPa = 1e-3 N/mm^2
  const double e = 1e-3;
  const double lambda = e * nu / ((1 + nu) * (1 - 2 * nu));
  const double mu = e / (2 * (1 + nu));
  const double vol = h_mm.x * h_mm.y * h_mm.z;
  // gradient (1/mm) of corner c's shape function at local point t in [0, 1]^3
  auto grad = [&](int c, const double t[3], double g[3]) {
    const Vec3i o = elastic_corner(c);
    const int off[3] = {o.x, o.y, o.z};
    double l[3], dl[3];
    for (int a = 0; a < 3; ++a) {
      l[a] = off[a] ? t[a] : 1 - t[a];
      dl[a] = off[a] ? 1 : -1;
    }
    g[0] = dl[0] * l[1] * l[2] / h_mm.x;
    g[1] = l[0] * dl[1] * l[2] / h_mm.y;
    g[2] = l[0] * l[1] * dl[2] / h_mm.z;
  };
  double k[24][24] = {};
  // mu part: 2 mu eps(u) : eps(v) at the 2x2x2 Gauss points (weight vol / 8 each)
  const double gp[2] = {0.5 - 0.5 / std::sqrt(3.0), 0.5 + 0.5 / std::sqrt(3.0)};
  for (int q = 0; q < 8; ++q) {
    const double t[3] = {gp[q & 1], gp[(q >> 1) & 1], gp[(q >> 2) & 1]};
    double g[8][3];
    for (int c = 0; c < 8; ++c) grad(c, t, g[c]);
    for (int a = 0; a < 8; ++a)
      for (int b = 0; b < 8; ++b) {
        const double gg = g[a][0] * g[b][0] + g[a][1] * g[b][1] + g[a][2] * g[b][2];
        for (int al = 0; al < 3; ++al)
          for (int be = 0; be < 3; ++be)
            k[3 * a + al][3 * b + be] += vol / 8 * mu * ((al == be ? gg : 0.0) + g[a][be] * g[b][al]);
      }
  }
  // lambda part: lambda div u div v at the centre (weight vol)
  const double centre[3] = {0.5, 0.5, 0.5};
  double g[8][3];
  for (int c = 0; c < 8; ++c) grad(c, centre, g[c]);
  for (int a = 0; a < 8; ++a)
    for (int b = 0; b < 8; ++b)
      for (int al = 0; al < 3; ++al)
        for (int be = 0; be < 3; ++be) k[3 * a + al][3 * b + be] += vol * lambda * g[a][al] * g[b][be];
  // every entry from corner 0's row block by the mirror symmetry (elastic_mirror_negates),
  // which the sums above hold to rounding: exactly so, for a backend that keeps that block
  std::array<float, 576> out{};
  for (int r = 0; r < 24; ++r)
    for (int c = 0; c < 24; ++c) {
      const int a = r / 3, i = r % 3, b = c / 3, j = c % 3;
      const float v = float(k[i][3 * (a ^ b) + j]);
      out[std::size_t(24 * r + c)] = elastic_mirror_negates(a, i, j) ? -v : v;
    }
  return out;
}

std::array<float, 72> elastic_element_base(const std::array<float, 576>& k) {
  std::array<float, 72> base{};
  for (int d = 0; d < 8; ++d)
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) base[std::size_t(9 * d + 3 * i + j)] = k[std::size_t(24 * i + 3 * d + j)];
  return base;
}

}  // namespace palpsim::deform
