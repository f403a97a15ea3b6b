#include "prep/distance.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <thread>
#include <vector>

namespace palpsim {

int worker_threads(int requested) {
  const int cores = int(std::max(1u, std::thread::hardware_concurrency()));
  return requested <= 0 ? cores : std::min(requested, cores);
}

void parallel_for(std::size_t n, int threads, const std::function<void(std::size_t, std::size_t)>& fn) {
  const std::size_t t = std::min<std::size_t>(std::size_t(worker_threads(threads)), std::max<std::size_t>(n, 1));
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
// den = 0 with num = -1 for -infinity), so building needs no division, and each
// parabola's numbers sit together (one cache line per step).
struct EnvelopeLine {
  // one parabola of the envelope: apex q, g = f(q) + (h q)^2, its left boundary zn/zd
  struct Parabola {
    double g, zn, zd;
    float f;
    int q;
  };
  std::vector<Parabola> st;  // the envelope, left to right, plus the slot above its top
  std::vector<int> site;     // a segment's finite samples, when it has infinite ones
  std::vector<int> owner;    // per sample, the parabola whose range starts there
  explicit EnvelopeLine(int n) : st(std::size_t(n) + 1), site(std::size_t(n)), owner(std::size_t(n)) {}

  // builds the envelope of the m sites at(0) < ... < at(m-1) and returns its top
  // index. Branch-free: each step either pops the top (the new parabola's
  // intersection with it lies at or before its own left boundary) or pushes the new
  // one; the slot above the top is written either way, as it is free. The popping
  // decision is a coin toss to a branch predictor, so a branch would cost more
  template <typename At>
  int build(const float* f, int m, At at, double h2) {
    Parabola* s = st.data();
    const int first = at(0);
    s[0] = {double(f[first]) + h2 * double(first) * first, -1, 0, f[first], first};
    int k = 0;
    for (int i = 1; i < m;) {
      const int u = at(i);
      const double gu = double(f[u]) + h2 * double(u) * u;
      const Parabola& t = s[k];
      const double num = gu - t.g, den = 2.0 * h2 * (u - t.q);
      const bool pop = num * t.zd <= t.zn * den;  // never for the bottom (zd = 0)
      s[k + 1] = {gu, num, den, f[u], u};
      k += pop ? -1 : 1;
      i += pop ? 0 : 1;
    }
    return k;
  }

  // transforms f[lo..hi] (inclusive) into out[lo..hi], square roots when `root`;
  // h2 = h^2 (mm^2); `inf`: whether f[lo..hi] has infinite samples. out may be f:
  // every f is read before the first write
  void segment(const float* f, int lo, int hi, bool inf, double h2, bool root, float* out) {
    int k;
    if (!inf) {
      k = build(f, hi - lo + 1, [lo](int i) { return lo + i; }, h2);
    } else {
      int m = 0;
      for (int q = lo; q <= hi; ++q) {
        site[std::size_t(m)] = q;
        m += f[q] != kInf;
      }
      if (m == 0) {  // no site in this segment
        std::fill(out + lo, out + hi + 1, kInf);
        return;
      }
      k = build(f, m, [this](int i) { return site[std::size_t(i)]; }, h2);
    }
    // parabola j rules from the first sample at or after its left boundary to the
    // next one's; owner marks those starts, a running maximum spreads them
    int* own = owner.data();
    std::fill(own + lo, own + hi + 1, 0);
    for (int j = 1; j <= k; ++j) {
      const double start = std::ceil(st[std::size_t(j)].zn / st[std::size_t(j)].zd);
      if (start <= hi) own[start < lo ? lo : int(start)] = j;
    }
    int j = 0;
    for (int q = lo; q <= hi; ++q) {
      j = std::max(j, own[q]);
      const Parabola& p = st[std::size_t(j)];
      const double d = double(q - p.q);
      const float v = float(h2 * d * d + double(p.f));
      out[q] = root ? std::sqrt(v) : v;
    }
  }

  // transforms the line f (length n, spacing h mm) into out (which may be f), square
  // roots when `root`: a 0 sample is its own nearest site and no parabola reaches
  // past it ((q-p)^2 h^2 + f(p) > (q-z)^2 h^2 for p beyond z), so the runs between
  // zeros are independent segments, each with its bounding zeros (whose 0 the segment
  // writes again); lines of a body's outside cost a comparison per sample
  void run(const float* f, int n, double h, bool root, float* out) {
    const double h2 = h * h;
    int q = 0;
    while (q < n) {
      if (f[q] == 0) {
        out[q] = 0;
        ++q;
        continue;
      }
      const int a = q;
      bool inf = false;
      for (; q < n && f[q] != 0; ++q) inf |= f[q] == kInf;
      segment(f, a > 0 ? a - 1 : a, q < n ? q : n - 1, inf, h2, root, out);
    }
  }
};

// 1-D squared distances (mm^2) along k, for the columns (i, j) with plane index e in
// [e0, e1), to each column's nearest site: a forward sweep keeps the last site's k per
// column, a backward sweep the next one's; every sweep walks whole rows of a plane,
// so memory streams and the loops vectorise (no gathering of strided lines, no
// branch: a column without a site yet has its site at -1e30 or +1e30 (float), whose
// squared distance overflows to +infinity)
void columns_pass(const Volume<std::uint8_t>& mask, bool to_nonzero, double hz, std::size_t e0, std::size_t e1,
                  std::vector<float>& near, Volume<float>& d) {
  const int nz = mask.grid.size.z;
  const std::size_t sxy = std::size_t(mask.grid.size.x) * mask.grid.size.y, n = e1 - e0;
  const std::uint8_t want = to_nonzero ? 1 : 0;
  constexpr float kFar = 1e30f;
  near.assign(n, -kFar);
  // forward: distance (voxels) to the last site at or below k
  for (int k = 0; k < nz; ++k) {
    const std::uint8_t* m = mask.data.data() + std::size_t(k) * sxy + e0;
    float* o = d.data.data() + std::size_t(k) * sxy + e0;
    const float fk = float(k);
    for (std::size_t e = 0; e < n; ++e) {
      near[e] = (m[e] != 0) == want ? fk : near[e];
      o[e] = fk - near[e];
    }
  }
  // backward: the nearer of that and the next site above, squared in mm^2
  near.assign(n, kFar);
  const double h2 = hz * hz;
  for (int k = nz - 1; k >= 0; --k) {
    const std::uint8_t* m = mask.data.data() + std::size_t(k) * sxy + e0;
    float* o = d.data.data() + std::size_t(k) * sxy + e0;
    const float fk = float(k);
    for (std::size_t e = 0; e < n; ++e) {
      near[e] = (m[e] != 0) == want ? fk : near[e];
      const double c = std::min(o[e], near[e] - fk);
      o[e] = float(h2 * c * c);
    }
  }
}

// lines along an axis of stride `stride` (n samples, spacing h) in blocks of kBlock
// adjacent i starting at `first`: copied into buf, transformed there, copied back, so
// that every read touches contiguous memory; a block of zeros (all sites, e.g. air
// around a body) is its own result and stays as it is
constexpr int kBlock = 16;
void lines_pass(float* first, int bn, int n, double h, std::size_t stride, EnvelopeLine& env,
                std::vector<float>& buf) {
  bool any = false;
  for (int q = 0; q < n; ++q)
    for (int c = 0; c < bn; ++c) {
      const float v = first[q * stride + c];
      buf[std::size_t(c) * n + q] = v;
      any |= v != 0;
    }
  if (!any) return;
  for (int c = 0; c < bn; ++c) env.run(buf.data() + std::size_t(c) * n, n, h, false, buf.data() + std::size_t(c) * n);
  for (int q = 0; q < n; ++q)
    for (int c = 0; c < bn; ++c) first[q * stride + c] = buf[std::size_t(c) * n + q];
}

// runs fn(item, scratch) for every item in [0, n) on worker_threads(threads)
// threads, each taking the next item when done with one: the items' costs differ
// (a line through air costs little), so fixed halves would leave one core idle;
// `make` builds each thread's scratch space
template <typename Make, typename Fn>
void dynamic_for(std::size_t n, int threads, Make&& make, Fn&& fn) {
  const std::size_t t = std::min<std::size_t>(std::size_t(worker_threads(threads)), std::max<std::size_t>(n, 1));
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
      chunks, threads, [] { return std::vector<float>(); },
      [&](std::size_t c, std::vector<float>& near) {
        columns_pass(mask, to_nonzero, hz, c * chunk, std::min(sxy, (c + 1) * chunk), near, d);
      });

  // passes 2 and 3 slice by slice: lower envelopes along j (blocks of i gathered), then
  // along each row i in place, with the square root when asked
  struct SliceScratch {
    EnvelopeLine col, row;
    std::vector<float> buf;
    SliceScratch(int ny, int nx) : col(ny), row(nx), buf(std::size_t(ny) * kBlock) {}
  };
  dynamic_for(
      std::size_t(nz), threads, [&] { return SliceScratch(ny, nx); },
      [&](std::size_t k, SliceScratch& sc) {
        float* slice = d.data.data() + k * sxy;
        if (ny > 1)
          for (int ib = 0; ib < iblocks; ++ib) {
            const int i0 = ib * kBlock;
            lines_pass(slice + i0, std::min(kBlock, nx - i0), ny, hy, sx, sc.col, sc.buf);
          }
        for (int j = 0; j < ny; ++j) {
          float* row = slice + std::size_t(j) * sx;
          sc.row.run(row, nx, hx, root, row);
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
