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

// The lower envelope of parabolas (Felzenszwalb & Huttenlocher 2012) along lines with
// sample positions q*h: d(q) = min_p (h(q-p))^2 + f(p); infinite f(p) are no sites. A
// 0 sample is its own nearest site and no parabola reaches past it ((q-p)^2 h^2 + f(p) >
// (q-z)^2 h^2 for p beyond z), so the runs between zeros are independent segments, each
// with its bounding zeros as sites (whose 0 the segment writes again); lines of a body's
// outside cost a comparison per sample.
//
// A LineBatch transforms a batch of lines in three phases: it gathers every segment's
// sites, builds all the envelopes, then writes the lines. The builds run eight segments
// interleaved, each step a pop or a push chosen by arithmetic (no branch): one envelope's
// steps form a chain (each waits for the last decision), and a branch that guesses the
// decision stalls on a wrong guess, which on real CT was every other step (0 or 1 pops
// per push about equally often); independent chains keep the core busy instead (eight
// rather than four, and the step as k += 2 push - 1 rather than a select: the real CT's
// depth under the skin 0.0957-0.0962 -> 0.0922-0.0928 s on one thread, best of 15, three
// runs each, 2026-11-28; 12 or 16 chains were slower, 0.101 s; integers of voxel^2 in
// place of doubles on the isotropic grid, the same maps, were slower too, 0.105 s).
// Measured on the 2-core VM against one line at a time with the branch (best of nine, two
// threads, the same maps bit for bit), with the segment and gather shortcuts below: the
// real CT's depth under the skin 0.059-0.066 -> 0.050-0.053 s, its distance to bone
// 0.076-0.085 -> 0.058-0.061 s; the phantom's distance to bone 0.110-0.113 -> 0.087 s,
// its depth under the skin 0.071-0.079 -> 0.072-0.074 s (on its smooth, regular shapes
// the branch guessed well; interleaving alone was 10% slower there).

// one parabola of an envelope (site q): g = f(q) + (h q)^2, hq = 2 h^2 q, its left
// boundary zn/zd (zd > 0; zd = 0 with zn = -1 for -infinity). The boundaries are kept as
// fractions so building needs no division. Before a site joins the envelope its g and
// hq sit in the same slot (the envelope grows into the gathered sites behind it: its top
// never passes the site being pushed)
struct Parabola {
  double g, zn, zd, hq;
};

// one segment of a line: samples lo..hi (inclusive), its `sites` sites from st[first]
struct Segment {
  float* line;
  std::size_t stride;  // floats between the line's samples
  int lo, hi, first, sites;
  int top;       // the envelope's top index once built
  bool between;  // no site but the bounding zeros at lo and hi: no envelope needed
};

class LineBatch {
 public:
  // the most lines a batch holds: their sites stay in cache between the phases
  static constexpr int kLines = 16;

  // scratch for lines of at most n samples
  explicit LineBatch(int n)
      : st(std::size_t(kLines) * (2 * std::size_t(n) + 2)), own(std::size_t(n)), qq(std::size_t(n) + 1),
        ff(std::size_t(n) + 1) {}

  // transforms `count` lines of n samples, line c at base + c * line_stride with `stride`
  // floats between its samples, spacing h mm, in place; square roots when `root`
  void transform(float* base, std::size_t line_stride, int count, std::size_t stride, int n, double h, bool root) {
    const double h2 = h * h;
    for (int c0 = 0; c0 < count; c0 += kLines) {
      segs.clear();
      used = 0;
      const int c1 = std::min(count, c0 + kLines);
      for (int c = c0; c < c1; ++c) gather(base + std::size_t(c) * line_stride, stride, n, h2);
      build_all();
      write(h2, root);
    }
  }

 private:
  std::vector<Parabola> st;   // the gathered sites, then the envelopes, segment by segment
  std::vector<Segment> segs;  // this batch's segments
  std::size_t used = 0;       // slots of st taken
  std::vector<int> own;       // per sample, the parabola whose range starts there
  std::vector<double> qq, ff; // per envelope parabola, its apex q and f(q)

  // the segments of one line: their sites' g and hq into st
  void gather(float* f, std::size_t sd, int n, double h2) {
    const double h22 = 2.0 * h2;
    int q = 0;
    while (q < n) {
      if (f[q * sd] == 0) {
        ++q;
        continue;
      }
      const int a = q, first = int(used);
      Parabola* s = st.data() + first;
      int m = 0;
      if (a > 0) {  // the bounding zero on the left
        s[m].g = h2 * double(a - 1) * (a - 1);
        s[m++].hq = h22 * (a - 1);
      }
      // the finite samples (an infinite one is no site; the branch skips whole runs of
      // them, as in the phantom's second pass: its EDT 6% faster than storing and
      // discarding each)
      for (; q < n; ++q) {
        const float v = f[q * sd];
        if (v == 0) break;
        if (v == kInf) continue;
        const double dq = double(q);
        s[m].g = double(v) + h2 * dq * dq;
        s[m].hq = h22 * dq;
        ++m;
      }
      if (q < n) {  // ... and on the right
        s[m].g = h2 * double(q) * q;
        s[m++].hq = h22 * q;
      }
      used += std::size_t(m);
      segs.push_back({f, sd, a > 0 ? a - 1 : a, q < n ? q : n - 1, first, m, 0, m == 2 && a > 0 && q < n});
    }
  }

  // the envelope's bottom parabola: its left boundary is -infinity
  void start(const Segment& sg) {
    st[std::size_t(sg.first)].zn = -1;
    st[std::size_t(sg.first)].zd = 0;
  }

  // builds a segment's envelope from site i on, with top k (one chain, branching: alone,
  // a chain waits for each decision, and the branch-free step made the EDT 1-4% slower
  // as the batch's last segments' builder)
  int finish(const Segment& sg, int i, int k) {
    Parabola* s = st.data() + sg.first;
    for (; i < sg.sites; ++i) {
      const double gu = s[i].g, hu = s[i].hq;
      double num, den;
      for (;;) {  // the bottom parabola (zd = 0) is never popped
        const Parabola& t = s[k];
        num = gu - t.g;
        den = hu - t.hq;
        if (num * t.zd > t.zn * den) break;
        --k;
      }
      s[++k] = {gu, num, den, hu};
    }
    return k;
  }

  // builds every segment's envelope, kWays at a time: each way holds a segment's next
  // site i and top k (indices into st); a step compares site i with the top parabola and
  // either pops it (k - 1) or pushes the site (k + 1, i + 1), writing the pushed parabola
  // either way (above the top it is no part of the envelope)
  void build_all() {
    constexpr int kWays = 8;
    Parabola* s = st.data();
    const std::size_t count = segs.size();
    std::size_t next = 0;
    int seg[kWays], first[kWays], i[kWays], k[kWays], end[kWays];
    // hands way w the next segment that needs an envelope of two parabolas or more
    auto take = [&](int w) {
      for (; next < count && (segs[next].sites <= 1 || segs[next].between); ++next) {
        if (segs[next].sites == 1) start(segs[next]);
        segs[next].top = 0;
      }
      if (next == count) return false;
      const Segment& sg = segs[next];
      start(sg);
      seg[w] = int(next++);
      first[w] = k[w] = sg.first;
      i[w] = sg.first + 1;
      end[w] = sg.first + sg.sites;
      return true;
    };
    int ways = 0;
    while (ways < kWays && take(ways)) ++ways;
    bool running = ways == kWays;
    while (running) {
      bool done = false;
      for (int w = 0; w < kWays; ++w) {
        const Parabola t = s[k[w]];
        const double gu = s[i[w]].g, hu = s[i[w]].hq;
        const double num = gu - t.g, den = hu - t.hq;
        const int push = num * t.zd > t.zn * den;  // 0 or 1, used as a number: no branch to guess
        s[k[w] + 1] = {gu, num, den, hu};
        k[w] += 2 * push - 1;
        i[w] += push;
        done |= i[w] == end[w];
      }
      if (!done) continue;
      for (int w = 0; w < kWays && running; ++w) {
        if (i[w] != end[w]) continue;
        segs[std::size_t(seg[w])].top = k[w] - first[w];
        if (!take(w)) {
          running = false;
          i[w] = -1;  // finished, nothing to take over
        }
      }
    }
    // the last segments, one at a time
    for (int w = 0; w < ways; ++w)
      if (i[w] >= 0) {
        Segment& sg = segs[std::size_t(seg[w])];
        sg.top = finish(sg, i[w] - first[w], k[w] - first[w]);
      }
  }

  // writes every segment's samples from its envelope: parabola j rules from the first
  // sample at or after its left boundary to the next one's; `own` marks those starts, a
  // running maximum spreads them. f(q) = g - (h q)^2 (the same products as gather's)
  void write(double h2, bool root) {
    const double to_q = 1.0 / (2.0 * h2);
    for (const Segment& sg : segs) {
      float* f = sg.line;
      const std::size_t sd = sg.stride;
      if (sg.sites == 0) {  // no site in this segment
        for (int q = sg.lo; q <= sg.hi; ++q) f[q * sd] = kInf;
        continue;
      }
      if (sg.between) {  // the nearer bounding zero (as the envelope would give, bit for bit)
        for (int q = sg.lo; q <= sg.hi; ++q) {
          const double d = double(std::min(q - sg.lo, sg.hi - q));
          const float v = float(h2 * d * d);
          f[q * sd] = root ? std::sqrt(v) : v;
        }
        continue;
      }
      const Parabola* s = st.data() + sg.first;
      int* o = own.data();
      std::fill(o + sg.lo, o + sg.hi + 1, 0);
      for (int j = 0; j <= sg.top; ++j) {
        const int q = int(s[j].hq * to_q + 0.5);
        qq[std::size_t(j)] = double(q);
        ff[std::size_t(j)] = s[j].g - h2 * double(q) * q;
        if (j == 0) continue;
        const double from = std::ceil(s[j].zn / s[j].zd);
        if (from <= sg.hi) o[from < sg.lo ? sg.lo : int(from)] = j;
      }
      int j = 0;
      for (int q = sg.lo; q <= sg.hi; ++q) {
        j = std::max(j, o[q]);
        const double d = double(q) - qq[std::size_t(j)];
        const float v = float(h2 * d * d + ff[std::size_t(j)]);
        f[q * sd] = root ? std::sqrt(v) : v;
      }
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
// cache) the lower envelopes along i and along j. The
// output is allocated unset: pass 1 writes every voxel, so its pages are first touched
// on all threads (zeroing them ahead on one thread took 16 of 84 ms on the real CT)
Volume<float> edt(const Volume<std::uint8_t>& mask, bool to_nonzero, bool root, int threads) {
  const Grid& g = mask.grid;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  Volume<float> d(g, Uninitialized{});
  if (g.count() == 0) return d;
  const double hx = g.spacing_mm.x, hy = g.spacing_mm.y, hz = g.spacing_mm.z;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;

  // pass 1 along k: the plane's columns in chunks of whole rows, one chunk per item
  const std::size_t chunk = std::max<std::size_t>(sx, (4096 / sx) * sx);
  const std::size_t chunks = (sxy + chunk - 1) / chunk;
  dynamic_for(
      chunks, threads, [] { return std::vector<float>(); },
      [&](std::size_t c, std::vector<float>& near) {
        columns_pass(mask, to_nonzero, hz, c * chunk, std::min(sxy, (c + 1) * chunk), near, d);
      });

  // passes 2 and 3 slice by slice (a slice stays in cache): the envelopes along each
  // row i (contiguous), then along j (the slice's columns), with the square root when
  // asked; this order was 2-5% faster than j then i on the real CT and the phantom
  dynamic_for(
      std::size_t(nz), threads, [&] { return LineBatch(std::max(nx, ny)); },
      [&](std::size_t k, LineBatch& lines) {
        float* slice = d.data.data() + k * sxy;
        lines.transform(slice, sx, ny, 1, nx, hx, root && ny == 1);
        if (ny > 1) lines.transform(slice, 1, nx, sx, ny, hy, root);
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
