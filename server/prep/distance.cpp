#include "prep/distance.h"

#include <algorithm>
#include <atomic>
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

// the lower envelope of parabolas (Felzenszwalb & Huttenlocher 2012) over one line
// with sample positions q*h: d(q) = min_p (h(q-p))^2 + f(p); infinite f(p) are no
// sites. The boundaries between parabolas are kept as fractions num/den (den > 0;
// den = 0 with num = +-1 for +-infinity), so no division is needed, and each
// parabola's numbers sit together (one cache line per step).
struct EnvelopeLine {
  // one parabola of the envelope: apex q, g = f(q) + (h q)^2, its left boundary zn/zd
  struct Parabola {
    double g, zn, zd;
    float f;
    int q;
  };
  std::vector<Parabola> st;  // the envelope, left to right, plus a sentinel boundary
  explicit EnvelopeLine(int n) : st(std::size_t(n) + 1) {}

  // transforms f[lo..hi] (inclusive) into out[lo..hi]; h2 = h^2 (mm^2)
  void segment(const float* f, int lo, int hi, double h2, float* out) {
    Parabola* s = st.data();
    int k = -1;
    for (int q = lo; q <= hi; ++q) {
      if (f[q] == kInf) continue;
      const double gq = double(f[q]) + h2 * double(q) * q;
      if (k < 0) {
        k = 0;
        s[0] = {gq, -1, 0, f[q], q};
        continue;
      }
      // pop the parabolas the new one hides: the intersection num/den with the top
      // one lies at or before the top one's own left boundary
      double num = gq - s[k].g, den = 2.0 * h2 * (q - s[k].q);
      while (k > 0 && num * s[k].zd <= s[k].zn * den) {
        --k;
        num = gq - s[k].g, den = 2.0 * h2 * (q - s[k].q);
      }
      s[++k] = {gq, num, den, f[q], q};
    }
    if (k < 0) {  // no site in this segment
      std::fill(out + lo, out + hi + 1, kInf);
      return;
    }
    s[k + 1].zn = 1, s[k + 1].zd = 0;  // +infinity
    int j = 0;
    for (int q = lo; q <= hi; ++q) {
      while (s[j + 1].zn < q * s[j + 1].zd) ++j;
      const double d = double(q - s[j].q);
      out[q] = float(h2 * d * d + double(s[j].f));
    }
  }

  // transforms the line f (length n, spacing h mm) into out: a 0 sample is its own
  // nearest site and no parabola reaches past it ((q-p)^2 h^2 + f(p) > (q-z)^2 h^2
  // for p beyond z), so the runs between zeros are independent segments, each with
  // its bounding zeros; lines of a body's outside cost a comparison per sample
  void run(const float* f, int n, double h, float* out) {
    const double h2 = h * h;
    int q = 0;
    while (q < n) {
      if (f[q] == 0) {
        out[q] = 0;
        ++q;
        continue;
      }
      const int a = q;
      while (q < n && f[q] != 0) ++q;
      segment(f, a > 0 ? a - 1 : a, q < n ? q : n - 1, h2, out);
    }
  }
};

// 1-D squared distances (mm^2) along k, for the columns (i, j) with plane index e in
// [e0, e1), to each column's nearest site: a forward sweep keeps the last site's k per
// column, a backward sweep the next one's; every sweep walks whole rows of a plane,
// so memory streams and the loops vectorise (no gathering of strided lines)
void columns_pass(const Volume<std::uint8_t>& mask, bool to_nonzero, double hz, std::size_t e0, std::size_t e1,
                  std::vector<int>& near, Volume<float>& d) {
  const int nz = mask.grid.size.z;
  const std::size_t sxy = std::size_t(mask.grid.size.x) * mask.grid.size.y, n = e1 - e0;
  const std::uint8_t want = to_nonzero ? 1 : 0;
  near.assign(n, -1);
  // forward: distance (voxels) to the last site at or below k; -1: none yet
  for (int k = 0; k < nz; ++k) {
    const std::uint8_t* m = mask.data.data() + std::size_t(k) * sxy + e0;
    float* o = d.data.data() + std::size_t(k) * sxy + e0;
    for (std::size_t e = 0; e < n; ++e) {
      if ((m[e] != 0) == want) near[e] = k;
      o[e] = near[e] < 0 ? kInf : float(k - near[e]);
    }
  }
  // backward: the nearer of that and the next site above, squared in mm^2
  near.assign(n, -1);
  const double h2 = hz * hz;
  for (int k = nz - 1; k >= 0; --k) {
    const std::uint8_t* m = mask.data.data() + std::size_t(k) * sxy + e0;
    float* o = d.data.data() + std::size_t(k) * sxy + e0;
    for (std::size_t e = 0; e < n; ++e) {
      if ((m[e] != 0) == want) near[e] = k;
      const float up = near[e] < 0 ? kInf : float(near[e] - k);
      const float c = std::min(o[e], up);
      o[e] = c == kInf ? kInf : float(h2 * double(c) * double(c));
    }
  }
}

// lines along an axis of stride `stride` (n samples, spacing h) in blocks of kBlock
// adjacent i starting at `first`: copied into buf, transformed into res, copied back
// (sqrt'ed when `root`), so that every read touches contiguous memory; a block of
// zeros (all sites, e.g. air around a body) is its own result and stays as it is
constexpr int kBlock = 16;
void lines_pass(float* first, int bn, int n, double h, std::size_t stride, bool root,
                EnvelopeLine& env, std::vector<float>& buf, std::vector<float>& res) {
  bool any = false;
  for (int q = 0; q < n; ++q)
    for (int c = 0; c < bn; ++c) {
      const float v = first[q * stride + c];
      buf[std::size_t(c) * n + q] = v;
      any |= v != 0;
    }
  if (!any) return;
  for (int c = 0; c < bn; ++c) {
    float* out = res.data() + std::size_t(c) * n;
    env.run(buf.data() + std::size_t(c) * n, n, h, out);
    if (root)
      for (int q = 0; q < n; ++q) out[q] = std::sqrt(out[q]);
  }
  for (int q = 0; q < n; ++q)
    for (int c = 0; c < bn; ++c) first[q * stride + c] = res[std::size_t(c) * n + q];
}

// runs fn(item, scratch) for every item in [0, n) on `threads` threads (0 = the
// hardware's cores), each taking the next item when done with one: the items'
// costs differ (a line through air costs little), so fixed halves would leave one
// core idle; `make` builds each thread's scratch space
template <typename Make, typename Fn>
void dynamic_for(std::size_t n, int threads, Make&& make, Fn&& fn) {
  if (threads <= 0) threads = int(std::max(1u, std::thread::hardware_concurrency()));
  const std::size_t t = std::min<std::size_t>(std::size_t(threads), std::max<std::size_t>(n, 1));
  std::atomic<std::size_t> next{0};
  const auto work = [&] {
    auto scratch = make();
    for (std::size_t i = next++; i < n; i = next++) fn(i, scratch);
  };
  std::vector<std::thread> pool;
  for (std::size_t w = 1; w < t; ++w) pool.emplace_back(work);
  work();
  for (auto& th : pool) th.join();
}

// what each thread of a lines pass works in: the envelope and a block's lines in and out
struct LineScratch {
  EnvelopeLine env;
  std::vector<float> buf, res;
  explicit LineScratch(int n) : env(n), buf(std::size_t(n) * kBlock), res(std::size_t(n) * kBlock) {}
};

// the exact EDT: squared distances (mm^2), or distances (mm) when `root`. The 1-D
// passes may go in any order (the squared distance separates by axis): along k first,
// on the mask itself, streaming whole planes; then slice by slice (a slice stays in
// cache) the lower envelopes along j and along i, the rows along i contiguous
Volume<float> edt(const Volume<std::uint8_t>& mask, bool to_nonzero, bool root, int threads) {
  const Grid& g = mask.grid;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  Volume<float> d(g, kInf);
  if (g.count() == 0) return d;
  const double hx = g.spacing_mm.x, hy = g.spacing_mm.y, hz = g.spacing_mm.z;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;
  const int iblocks = (nx + kBlock - 1) / kBlock;

  // pass 1 along k: the plane's columns in chunks of whole rows, one chunk per item
  const std::size_t chunk = std::max<std::size_t>(sx, (4096 / sx) * sx);
  const std::size_t chunks = (sxy + chunk - 1) / chunk;
  dynamic_for(
      chunks, threads, [] { return std::vector<int>(); },
      [&](std::size_t c, std::vector<int>& near) {
        columns_pass(mask, to_nonzero, hz, c * chunk, std::min(sxy, (c + 1) * chunk), near, d);
      });

  // passes 2 and 3 slice by slice: lower envelopes along j (blocks of i gathered), then
  // along each row i in place, with the square root when asked
  struct SliceScratch {
    LineScratch j;
    EnvelopeLine row;
    std::vector<float> out;
    SliceScratch(int ny, int nx) : j(ny), row(nx), out(std::size_t(nx)) {}
  };
  dynamic_for(
      std::size_t(nz), threads, [&] { return SliceScratch(ny, nx); },
      [&](std::size_t k, SliceScratch& sc) {
        float* slice = d.data.data() + k * sxy;
        if (ny > 1)
          for (int ib = 0; ib < iblocks; ++ib) {
            const int i0 = ib * kBlock;
            lines_pass(slice + i0, std::min(kBlock, nx - i0), ny, hy, sx, false, sc.j.env, sc.j.buf, sc.j.res);
          }
        for (int j = 0; j < ny; ++j) {
          float* row = slice + std::size_t(j) * sx;
          // a row of sites (zeros) is its own result
          bool any = false;
          for (int i = 0; i < nx; ++i) any |= row[i] != 0;
          if (!any) continue;
          if (nx > 1) {
            sc.row.run(row, nx, hx, sc.out.data());
            std::copy(sc.out.begin(), sc.out.end(), row);
          }
          if (root)
            for (int i = 0; i < nx; ++i) row[i] = std::sqrt(row[i]);
        }
      });
  return d;
}

}  // namespace

Volume<float> squared_distance_mm2(const Volume<std::uint8_t>& mask, bool to_nonzero, int threads) {
  return edt(mask, to_nonzero, false, threads);
}

Volume<float> distance_to_mask_mm(const Volume<std::uint8_t>& mask, int threads) {
  return edt(mask, true, true, threads);
}

Volume<float> distance_to_background_mm(const Volume<std::uint8_t>& mask, int threads) {
  return edt(mask, false, true, threads);
}

}  // namespace palpsim
