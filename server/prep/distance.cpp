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

// 1-D squared distances (mm^2) along each row of slice k to the row's nearest site
void rows_pass(const Volume<std::uint8_t>& mask, bool to_nonzero, const std::vector<float>& sq, int k,
               Volume<float>& d) {
  const int nx = mask.grid.size.x, ny = mask.grid.size.y;
  for (int j = 0; j < ny; ++j) {
    const std::size_t base = (std::size_t(k) * ny + j) * nx;
    const std::uint8_t* m = mask.data.data() + base;
    float* o = d.data.data() + base;
    // runs of sites are zeros; a run between sites takes the nearer one's distance
    int prev = -1;  // the last site before the run, -1 for none
    int i = 0;
    while (i < nx) {
      const int a = i;
      if ((m[i] != 0) == to_nonzero) {
        while (i < nx && (m[i] != 0) == to_nonzero) ++i;
        std::fill(o + a, o + i, 0.0f);
        prev = i - 1;
        continue;
      }
      while (i < nx && (m[i] != 0) != to_nonzero) ++i;
      if (prev < 0 && i == nx) {
        std::fill(o + a, o + i, kInf);  // no site in the row
      } else if (prev < 0) {
        for (int q = a; q < i; ++q) o[q] = sq[std::size_t(i - q)];
      } else if (i == nx) {
        for (int q = a; q < i; ++q) o[q] = sq[std::size_t(q - prev)];
      } else {
        for (int q = a; q < i; ++q) o[q] = sq[std::size_t(std::min(q - prev, i - q))];
      }
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

// the exact EDT: squared distances (mm^2), or distances (mm) when `root`
Volume<float> edt(const Volume<std::uint8_t>& mask, bool to_nonzero, bool root, int threads) {
  const Grid& g = mask.grid;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  Volume<float> d(g, kInf);
  if (g.count() == 0) return d;
  const double hx = g.spacing_mm.x, hy = g.spacing_mm.y, hz = g.spacing_mm.z;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;
  const int iblocks = (nx + kBlock - 1) / kBlock;
  // squared row distances (mm^2) by sample count: (h q)^2
  std::vector<float> sq(std::size_t(nx) + 1);
  for (int q = 0; q <= nx; ++q) sq[std::size_t(q)] = float((hx * q) * (hx * q));

  // passes 1 and 2 slice by slice (a slice stays in cache between them): along i,
  // then lower envelopes along j; the square root here when the volume has one slice
  const bool root_j = root && nz == 1;
  dynamic_for(
      std::size_t(nz), threads, [&] { return LineScratch(ny); },
      [&](std::size_t k, LineScratch& sc) {
        rows_pass(mask, to_nonzero, sq, int(k), d);
        if (ny > 1) {
          for (int ib = 0; ib < iblocks; ++ib) {
            const int i0 = ib * kBlock;
            lines_pass(d.data.data() + k * sxy + i0, std::min(kBlock, nx - i0), ny, hy, sx, root_j, sc.env, sc.buf,
                       sc.res);
          }
        } else if (root_j) {
          for (std::size_t i = k * sxy; i < (k + 1) * sxy; ++i) d.data[i] = std::sqrt(d.data[i]);
        }
      });

  // pass 3 along k, one set of lines per j, with the square root when asked
  if (nz > 1) {
    dynamic_for(
        std::size_t(ny) * iblocks, threads, [&] { return LineScratch(nz); },
        [&](std::size_t w, LineScratch& sc) {
          const std::size_t j = w / iblocks;
          const int i0 = int(w % iblocks) * kBlock;
          lines_pass(d.data.data() + j * sx + i0, std::min(kBlock, nx - i0), nz, hz, sxy, root, sc.env, sc.buf,
                     sc.res);
        });
  }
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
