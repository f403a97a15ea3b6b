#include "prep/distance.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
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
//
// The gather leaves out a site q that its two neighbours' parabolas cover strictly:
// P(q-1) - P(q) rises in x (slope 2h^2) through 0 at x - q = a = (f(q) - f(q-1) - h^2) /
// 2h^2, P(q+1) - P(q) falls through 0 at b = (f(q+1) - f(q) + h^2) / 2h^2, so where b < a,
// that is 2 f(q) - f(q-1) - f(q+1) > 2h^2, one of them lies below P(q) at every x and q is
// nobody's nearest site: the lower envelope, and each sample's value, stay the same bit
// for bit (the margin of 1e-7 h^2 keeps a tie, where rounding could decide, in). On the
// real CT that leaves out 38% of the last pass's sites (7.1 M -> 4.5 M; 1.6 M make the
// envelopes) and made its depth under the skin 0.0925 -> 0.0875 s on one thread.
// Testing against the last site kept instead of q - 1 (a chain from site to site) or
// against q -+ 2 as well was slower (0.100 s). Rows (contiguous) skip runs of zeros and
// of infinities four samples at a time: 0.0875 -> 0.0847 s.

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

// the bits of +infinity (float), and whether four floats from p all have the bits `bits`
// (+0 or +infinity: the values a pass writes for a site and for no site)
constexpr std::uint32_t kInfBits = 0x7f800000u;
inline bool all_four(const float* p, std::uint32_t bits) {
  std::uint64_t a, b;
  std::memcpy(&a, p, 8);
  std::memcpy(&b, p + 2, 8);
  const std::uint64_t two = std::uint64_t(bits) << 32 | bits;
  return ((a ^ two) | (b ^ two)) == 0;
}

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
      // contiguous rows apart (their gather compiled alone: the columns' ran 20% faster)
      if (stride == 1)
        for (int c = c0; c < c1; ++c) gather<true>(base + std::size_t(c) * line_stride, 1, n, h2);
      else
        for (int c = c0; c < c1; ++c) gather<false>(base + std::size_t(c) * line_stride, stride, n, h2);
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

  // the segments of one line: their sites' g and hq into st (kContiguous: sd is 1)
  template <bool kContiguous>
  void gather(float* f, std::size_t sd, int n, double h2) {
    const double h22 = 2.0 * h2, cover = 2.0000001 * h2;
    int q = 0;
    while (q < n) {
      if (kContiguous)  // contiguous: past runs of zeros four at a time
        while (q + 4 <= n && all_four(f + q, 0)) q += 4;
      if (q == n) break;
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
      // discarding each), less those that both neighbours' parabolas cover (the slot is
      // written either way and kept by m += 1: no branch on a decision that varies)
      float prev = a > 0 ? 0.f : kInf, cur = f[q * sd];
      for (;;) {
        if (kContiguous && cur == kInf)  // contiguous: past runs of infinities four at a time
          while (q + 5 <= n && all_four(f + q + 1, kInfBits)) q += 4;
        const float next = q + 1 < n ? f[(q + 1) * sd] : kInf;
        if (cur != kInf) {
          const double dq = double(q), c = double(cur);
          s[m].g = c + h2 * dq * dq;
          s[m].hq = h22 * dq;
          m += !(2 * c - double(prev) - double(next) > cover);
        }
        prev = cur;
        ++q;
        if (q == n || next == 0) break;
        cur = next;
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

// Pass 1, the 1-D squared distances (mm^2) along k to each column's nearest site, needs
// a voxel's last site at or below it and its next site at or above. An upward sweep over
// the mask alone notes, as a Mark, at the top of every run of non-sites in a column the
// last site below the run: there the downward sweep, which goes slice by slice together
// with the slices' envelopes, enters the run; it keeps each column's next site above and
// takes the last one below from the marks. So a slice's distances along k are written
// just before its envelopes read them (in cache), with no store and reload of a whole
// volume between two sweeps (the forward sweep that wrote one took 7.5 of 82 ms on one
// thread on the real CT, 2026-11-28; now the marks take 2.7). A column with no site yet
// has its site at -1e30 or +1e30 (float), whose squared distance overflows to +infinity:
// no branch, and the plane loops vectorise.
constexpr float kFar = 1e30f;

// the top of a column's run of non-sites: slice k, column e (plane index), the k of the
// column's last site below (-kFar for none)
struct Mark {
  int k;
  std::uint32_t e;
  float below;
};

// the upward sweep for the columns with plane index in [e0, e1): their marks, by k. A
// run's last site below is its bottom's k - 1, noted per column at its bottom. Per slice
// a loop over the mask's bytes, which vectorises, flags the runs' bottoms (1) and tops
// (2); the flagged bytes (few) are found 32 at a time. (Keeping every column's last site
// instead, a float per voxel, took 4.0 ms on one thread on the real CT; this 2.7.)
void mark_runs(const Volume<std::uint8_t>& mask, bool to_nonzero, std::size_t e0, std::size_t e1,
               std::vector<float>& below, std::vector<std::uint8_t>& flag, std::vector<Mark>& marks) {
  const int nz = mask.grid.size.z;
  const std::size_t sxy = std::size_t(mask.grid.size.x) * mask.grid.size.y, n = e1 - e0;
  const std::uint8_t want = to_nonzero ? 1 : 0;
  below.assign(n, -kFar);
  flag.assign((n + 31) / 32 * 32, 0);  // whole blocks of 32: the bytes past n stay 0
  marks.clear();
  for (int k = 0; k < nz; ++k) {
    const std::uint8_t* m = mask.data.data() + std::size_t(k) * sxy + e0;
    const std::uint8_t* dn = k > 0 ? m - sxy : nullptr;
    const std::uint8_t* up = k + 1 < nz ? m + sxy : nullptr;
    std::uint8_t* fl = flag.data();
    // a non-site with a site (or the volume's end) below: 1; above: 2
    if (dn && up)
      for (std::size_t e = 0; e < n; ++e)
        fl[e] = std::uint8_t(((m[e] != 0) != want) * (((dn[e] != 0) == want) | ((up[e] != 0) == want) << 1));
    else
      for (std::size_t e = 0; e < n; ++e)
        fl[e] = std::uint8_t(((m[e] != 0) != want) * ((!dn || (dn[e] != 0) == want) | (!up || (up[e] != 0) == want) << 1));
    const float bottom_below = k > 0 ? float(k - 1) : -kFar;
    for (std::size_t e0w = 0; e0w < n; e0w += 32) {
      std::uint64_t w4[4];
      std::memcpy(w4, fl + e0w, 32);
      if ((w4[0] | w4[1] | w4[2] | w4[3]) == 0) continue;
      for (std::size_t q = 0; q < 4; ++q) {
        std::uint64_t w = w4[q];
        const std::size_t e = e0w + 8 * q;
        while (w) {
          const unsigned bit = unsigned(__builtin_ctzll(w)) & ~7u;
          const std::size_t c = e + bit / 8;
          w &= ~(std::uint64_t(0xff) << bit);
          if (fl[c] & 1) below[c] = bottom_below;
          if (fl[c] & 2) marks.push_back({k, std::uint32_t(e0 + c), below[c]});
        }
      }
    }
  }
}

// one thread's downward sweep: each column's next site above and last site below
class DownSweep {
 public:
  DownSweep(const Volume<std::uint8_t>& mask, bool to_nonzero, const std::vector<std::vector<Mark>>& marks)
      : mask_(mask), marks_(marks), want_(to_nonzero ? 1 : 0), n_(std::size_t(mask.grid.size.x) * mask.grid.size.y),
        above_(n_), below_(n_), left_(marks.size()) {}

  // starts at slice k with nothing swept above it: a column's lowest mark at or above k
  // is, where the voxel at k is a non-site, the top of its run (the next site is one
  // above that, the last one below is the mark's); a site at k needs neither
  void start(int k) {
    const int nz = mask_.grid.size.z;
    std::fill(above_.begin(), above_.end(), kFar);
    std::fill(below_.begin(), below_.end(), -kFar);
    for (std::size_t c = 0; c < marks_.size(); ++c) {
      const std::vector<Mark>& mk = marks_[c];
      const auto from = std::lower_bound(mk.begin(), mk.end(), k, [](const Mark& a, int v) { return a.k < v; });
      for (auto it = mk.end(); it != from;) {  // from the top down: the lowest one written last
        --it;
        above_[it->e] = it->k + 1 < nz ? float(it->k + 1) : kFar;
        below_[it->e] = it->below;
      }
      left_[c] = std::size_t(from - mk.begin());
    }
  }

  // slice k, the one below the last swept (or the one started at): the marks of runs
  // whose top is here set the last site below, then every voxel's distance along k,
  // squared in mm^2, into the slice of d
  void sweep(int k, double hz, Volume<float>& d) {
    for (std::size_t c = 0; c < marks_.size(); ++c)
      for (std::size_t& l = left_[c]; l > 0 && marks_[c][l - 1].k == k; --l) below_[marks_[c][l - 1].e] = marks_[c][l - 1].below;
    const double h2 = hz * hz;
    const std::uint8_t* m = mask_.data.data() + std::size_t(k) * n_;
    float* o = d.data.data() + std::size_t(k) * n_;
    float *above = above_.data(), *below = below_.data();
    const float fk = float(k);
    // both loaded whether used or not: a load under a condition kept the loop from vectorising
    for (std::size_t e = 0; e < n_; ++e) {
      const bool site = (m[e] != 0) == want_;
      const float up = above[e], down = below[e];
      const float a = site ? fk : up, b = site ? fk : down;  // a site: 0 either way
      above[e] = a;
      const double c = std::min(fk - b, a - fk);
      o[e] = float(h2 * c * c);
    }
  }

 private:
  const Volume<std::uint8_t>& mask_;
  const std::vector<std::vector<Mark>>& marks_;
  const std::uint8_t want_;
  const std::size_t n_;                // columns in the plane
  std::vector<float> above_, below_;   // per column, the k of its next site above, last below
  std::vector<std::size_t> left_;      // per chunk, its marks not yet taken (those below)
};

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
// on the mask itself; then slice by slice, the slice in cache, the lower envelopes along
// i and along j. The output is allocated unset: pass 1's downward sweep writes every
// voxel, and its pages are first touched there, just before the slice's envelopes
// (touching them all ahead on both threads made the real CT's EDT 3% slower: the
// zeroed pages had left the cache by then)
Volume<float> edt(const Volume<std::uint8_t>& mask, bool to_nonzero, bool root, int threads) {
  const Grid& g = mask.grid;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  Volume<float> d(g, Uninitialized{});
  if (g.count() == 0) return d;
  const double hx = g.spacing_mm.x, hy = g.spacing_mm.y, hz = g.spacing_mm.z;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;

  // pass 1's upward sweep: the plane's columns in chunks of whole rows, one chunk per item
  const std::size_t chunk = std::max<std::size_t>(sx, (4096 / sx) * sx);
  const std::size_t chunks = (sxy + chunk - 1) / chunk;
  std::vector<std::vector<Mark>> marks(chunks);
  dynamic_for(
      chunks, threads, [] { return std::pair<std::vector<float>, std::vector<std::uint8_t>>(); },
      [&](std::size_t c, std::pair<std::vector<float>, std::vector<std::uint8_t>>& scratch) {
        mark_runs(mask, to_nonzero, c * chunk, std::min(sxy, (c + 1) * chunk), scratch.first, scratch.second, marks[c]);
      });

  // then the slices from the top down in blocks of kBlock: pass 1's downward sweep, then
  // in the slice (in cache) the envelopes along each row i (contiguous), then along j
  // (the slice's columns), with the square root when asked (this order was 2-5% faster
  // than j then i on the real CT and the phantom, 4% on one thread with the gather's
  // pruning). A thread starts its sweep at a block's top (DownSweep::start, a pass over
  // the marks above) and goes on into the block below while no other thread has it;
  // thread t starts at block t * blocks / threads, and a thread whose next block is
  // taken takes the middle one of the longest stretch left. So each thread sweeps a few
  // long stretches of its own and never waits for another. (One sweep for all, a slice
  // at a time in turn, each thread waiting for the other's, was as fast at its best but
  // had single runs of 0.17-0.30 s among forty of 0.041-0.05 s on the real CT, where the
  // thread whose turn it was had stopped; blocks of 1, 2, 4 or 8 slices were alike.)
  constexpr int kBlock = 2;
  const int blocks = (nz + kBlock - 1) / kBlock;
  std::vector<std::atomic<bool>> taken(static_cast<std::size_t>(blocks));  // blocks a thread has
  for (auto& b : taken) b = false;
  const int workers = std::min(worker_threads(threads), blocks);
  parallel_for(std::size_t(workers), workers, [&](std::size_t w, std::size_t) {
    DownSweep sweep(mask, to_nonzero, marks);
    LineBatch lines(std::max(nx, ny));
    int b = int(w) * blocks / workers;
    bool go_on = false;  // the sweep stands just above block b
    for (;;) {
      while (b < 0 || taken[std::size_t(b)].exchange(true)) {  // taken: the middle of the longest stretch left
        int best = 0, at = -1;
        for (int i = 0, run = 0; i < blocks; ++i) {
          run = taken[std::size_t(i)].load() ? 0 : run + 1;
          if (run > best) best = run, at = i - run + 1;
        }
        if (at < 0) return;
        b = at + best / 2;
        go_on = false;
      }
      const int top = nz - 1 - b * kBlock, bottom = std::max(0, top - kBlock + 1);
      if (!go_on) sweep.start(top);
      for (int k = top; k >= bottom; --k) {
        sweep.sweep(k, hz, d);
        float* slice = d.data.data() + std::size_t(k) * sxy;
        lines.transform(slice, sx, ny, 1, nx, hx, root && ny == 1);
        if (ny > 1) lines.transform(slice, 1, nx, sx, ny, hy, root);
      }
      b = b + 1 < blocks ? b + 1 : -1;
      go_on = true;
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
