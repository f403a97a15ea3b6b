#include "prep/distance.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <thread>
#include <vector>

namespace palpsim {

void parallel_for(std::size_t n, int threads, const std::function<void(std::size_t, std::size_t)>& fn) {
  if (threads <= 0) threads = int(std::max(1u, std::thread::hardware_concurrency()));
  const std::size_t t = std::min<std::size_t>(std::size_t(threads), std::max<std::size_t>(n, 1));
  if (t <= 1) {
    fn(0, n);
    return;
  }
  std::vector<std::thread> pool;
  pool.reserve(t);
  for (std::size_t w = 0; w < t; ++w) {
    const std::size_t b = n * w / t, e = n * (w + 1) / t;
    pool.emplace_back([&fn, b, e] { fn(b, e); });
  }
  for (auto& th : pool) th.join();
}

namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// one line of the lower envelope of parabolas (Felzenszwalb & Huttenlocher 2012)
// with sample positions q*h: d(q) = min_p (h(q-p))^2 + f(p); infinite f(p) are no sites
struct EnvelopeLine {
  std::vector<int> v;       // parabola apexes (sample indices)
  std::vector<double> z;    // boundaries between parabolas (in units of samples)
  std::vector<float> f;     // the input line
  explicit EnvelopeLine(int n) : v(n), z(n + 1), f(n) {}

  // position (in samples) where the parabolas rooted at p and q intersect
  double intersect(int p, int q, double h2) const {
    return ((double(f[q]) + h2 * double(q) * q) - (double(f[p]) + h2 * double(p) * p)) / (2.0 * h2 * (q - p));
  }

  // transforms f (length n) into out, with spacing h (mm)
  void run(int n, double h, float* out) {
    const double h2 = h * h;
    int k = -1;
    for (int q = 0; q < n; ++q) {
      if (!std::isfinite(f[q])) continue;
      if (k < 0) {
        k = 0;
        v[0] = q;
        z[0] = -std::numeric_limits<double>::infinity();
        z[1] = std::numeric_limits<double>::infinity();
        continue;
      }
      // pop parabolas hidden by the new one; z[0] = -inf stops the loop at k = 0
      double s = intersect(v[k], q, h2);
      while (s <= z[k]) {
        --k;
        s = intersect(v[k], q, h2);
      }
      ++k;
      v[k] = q;
      z[k] = s;
      z[k + 1] = std::numeric_limits<double>::infinity();
    }
    if (k < 0) {  // no site on this line
      std::fill(out, out + n, kInf);
      return;
    }
    int j = 0;
    for (int q = 0; q < n; ++q) {
      while (z[j + 1] < q) ++j;
      const double d = h * (q - v[j]);
      out[q] = float(d * d + f[v[j]]);
    }
  }
};

}  // namespace

Volume<float> squared_distance_mm2(const Volume<std::uint8_t>& mask, bool to_nonzero, int threads) {
  const Grid& g = mask.grid;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  Volume<float> d(g, kInf);
  if (g.count() == 0) return d;
  const double hx = g.spacing_mm.x, hy = g.spacing_mm.y, hz = g.spacing_mm.z;
  const auto is_site = [to_nonzero](std::uint8_t m) { return to_nonzero ? m != 0 : m == 0; };

  // pass 1 along i: 1-D distance to the nearest site on each row, by two scans
  parallel_for(std::size_t(ny) * nz, threads, [&](std::size_t b, std::size_t e) {
    std::vector<int> left(nx);
    for (std::size_t row = b; row < e; ++row) {
      const std::size_t base = row * nx;
      const std::uint8_t* m = mask.data.data() + base;
      float* o = d.data.data() + base;
      // forward scan: distance in samples to the last site on the left
      int last = -1;
      for (int i = 0; i < nx; ++i) {
        if (is_site(m[i])) last = i;
        left[i] = last;
      }
      last = -1;
      for (int i = nx - 1; i >= 0; --i) {
        if (is_site(m[i])) last = i;
        double best = std::numeric_limits<double>::infinity();
        if (left[i] >= 0) best = hx * (i - left[i]);
        if (last >= 0) best = std::min(best, hx * (last - i));
        o[i] = std::isfinite(best) ? float(best * best) : kInf;
      }
    }
  });

  // pass 2 along j, pass 3 along k: lower envelopes over each line; lines are
  // handled in blocks of adjacent i so that every read touches contiguous memory
  constexpr int kBlock = 16;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;
  const int iblocks = (nx + kBlock - 1) / kBlock;
  const auto axis_pass = [&](int n, double h, int others, std::size_t other_stride, std::size_t stride) {
    parallel_for(std::size_t(others) * iblocks, threads, [&](std::size_t b, std::size_t e) {
      EnvelopeLine env(n);
      std::vector<float> buf(std::size_t(n) * kBlock);
      for (std::size_t w = b; w < e; ++w) {
        const std::size_t other = w / iblocks;
        const int i0 = int(w % iblocks) * kBlock, bn = std::min(kBlock, nx - i0);
        float* p = d.data.data() + other * other_stride + i0;
        for (int q = 0; q < n; ++q)
          for (int c = 0; c < bn; ++c) buf[std::size_t(c) * n + q] = p[q * stride + c];
        for (int c = 0; c < bn; ++c) {
          std::copy(buf.begin() + std::size_t(c) * n, buf.begin() + std::size_t(c + 1) * n, env.f.begin());
          env.run(n, h, buf.data() + std::size_t(c) * n);
        }
        for (int q = 0; q < n; ++q)
          for (int c = 0; c < bn; ++c) p[q * stride + c] = buf[std::size_t(c) * n + q];
      }
    });
  };
  if (ny > 1) axis_pass(ny, hy, nz, sxy, sx);   // lines along j, one set per k
  if (nz > 1) axis_pass(nz, hz, ny, sx, sxy);   // lines along k, one set per j
  return d;
}

Volume<float> distance_to_mask_mm(const Volume<std::uint8_t>& mask, int threads) {
  Volume<float> d = squared_distance_mm2(mask, true, threads);
  parallel_for(d.data.size(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) d.data[i] = std::sqrt(d.data[i]);
  });
  return d;
}

Volume<float> distance_to_background_mm(const Volume<std::uint8_t>& mask, int threads) {
  Volume<float> d = squared_distance_mm2(mask, false, threads);
  parallel_for(d.data.size(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) d.data[i] = std::sqrt(d.data[i]);
  });
  return d;
}

}  // namespace palpsim
