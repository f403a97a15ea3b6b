// The exact Euclidean distance transform against brute force, on random masks with
// anisotropic spacing, and its edge cases.
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <random>
#include <thread>

#include "prep/distance.h"

using namespace palpsim;

namespace {

// brute force: the smallest physical distance from each voxel to any site
Volume<float> brute_force(const Volume<std::uint8_t>& m, bool to_nonzero) {
  const Grid& g = m.grid;
  Volume<float> d(g, std::numeric_limits<float>::infinity());
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        double best = std::numeric_limits<double>::infinity();
        for (int c = 0; c < g.size.z; ++c)
          for (int b = 0; b < g.size.y; ++b)
            for (int a = 0; a < g.size.x; ++a) {
              if ((m.at(a, b, c) != 0) != to_nonzero) continue;
              const double dx = (a - i) * g.spacing_mm.x, dy = (b - j) * g.spacing_mm.y, dz = (c - k) * g.spacing_mm.z;
              best = std::min(best, dx * dx + dy * dy + dz * dz);
            }
        d.at(i, j, k) = float(std::sqrt(best));
      }
  return d;
}

Volume<std::uint8_t> random_mask(std::mt19937& rng, Vec3i size, Vec3 spacing, double fill) {
  Grid g;
  g.size = size;
  g.spacing_mm = spacing;
  Volume<std::uint8_t> m(g);
  std::bernoulli_distribution b(fill);
  for (auto& v : m.data) v = b(rng);
  return m;
}

// checks every voxel of `fast` against `slow`, the brute force; float storage of
// squared mm: relative error below 1e-6 (tolerance 1e-4 mm + 1e-6 relative)
void check_against_brute_force(const Volume<float>& fast, const Volume<float>& slow) {
  for (std::size_t i = 0; i < slow.data.size(); ++i) {
    if (std::isinf(slow.data[i])) {
      CHECK(std::isinf(fast.data[i]));
    } else {
      CHECK(fast.data[i] == Approx(slow.data[i]).margin(1e-4).epsilon(1e-6));
    }
  }
}

}  // namespace

TEST_CASE("EDT equals brute force on random masks with anisotropic spacing") {
  std::mt19937 rng(1234);
  // the last three: a single row, a single column of slices, a 2D slice one voxel high
  // (every pass of the EDT, and where its square root is taken, on its own)
  const Vec3i sizes[] = {{9, 7, 5}, {17, 3, 11}, {1, 12, 8}, {13, 13, 1}, {20, 9, 6}, {40, 1, 1}, {7, 1, 9}, {11, 1, 1}};
  const Vec3 spacings[] = {{0.7, 1.3, 3.0}, {2.5, 0.5, 1.0}, {1, 1, 1}, {0.977, 0.977, 2.0}, {3, 0.6, 1.7},
                           {0.8, 1, 1},     {1.5, 1, 0.4},   {2, 2, 2}};
  const double fills[] = {0.002, 0.02, 0.2, 0.6};
  int checked = 0;
  for (int s = 0; s < 8; ++s)
    for (double fill : fills)
      for (int threads : {1, 3}) {
        const auto m = random_mask(rng, sizes[s], spacings[s], fill);
        check_against_brute_force(distance_to_mask_mm(m, threads), brute_force(m, true));
        check_against_brute_force(distance_to_background_mm(m, threads), brute_force(m, false));
        checked += int(m.data.size());
      }
  CHECK(checked > 10000);
}

TEST_CASE("EDT of an empty mask is infinite, of a full mask zero") {
  Grid g;
  g.size = {6, 5, 4};
  g.spacing_mm = {1, 2, 3};
  const Volume<std::uint8_t> empty(g, 0), full(g, 1);
  for (float d : distance_to_mask_mm(empty).data) CHECK(std::isinf(d));
  for (float d : distance_to_mask_mm(full).data) CHECK(d == 0);
  for (float d : distance_to_background_mm(empty).data) CHECK(d == 0);
}

TEST_CASE("EDT of a single voxel is the exact physical distance") {
  Grid g;
  g.size = {31, 21, 11};
  g.spacing_mm = {0.5, 1.25, 2.0};
  Volume<std::uint8_t> m(g, 0);
  m.at(3, 17, 9) = 1;
  const auto d = distance_to_mask_mm(m);
  for (int k = 0; k < g.size.z; k += 2)
    for (int j = 0; j < g.size.y; j += 3)
      for (int i = 0; i < g.size.x; i += 5)
        CHECK(d.at(i, j, k) == Approx(std::sqrt(std::pow((i - 3) * 0.5, 2) + std::pow((j - 17) * 1.25, 2) +
                                                std::pow((k - 9) * 2.0, 2)))
                                   .epsilon(1e-6));
}

TEST_CASE("EDT equals brute force along long lines of every axis") {
  // lines of hundreds of samples build envelopes of many parabolas, most of them
  // popped again, which the small volumes above rarely do; with sparse sites (gaps of
  // infinite samples between them) and dense ones, on each axis's own pass
  std::mt19937 rng(99);
  const Vec3i sizes[] = {{500, 1, 1}, {1, 400, 1}, {1, 1, 300}, {60, 50, 1}};
  const Vec3 spacing{0.9, 1.7, 2.3};
  int checked = 0;
  for (const Vec3i& size : sizes)
    for (double fill : {0.01, 0.3, 0.9}) {
      const auto m = random_mask(rng, size, spacing, fill);
      check_against_brute_force(distance_to_mask_mm(m, 1), brute_force(m, true));
      checked += int(m.data.size());
    }
  CHECK(checked > 10000);
}

TEST_CASE("EDT equals brute force inside smooth shapes with cavities") {
  // a body-like mask: two overlapping ellipsoids cut open by the volume's side, with a
  // spherical cavity and a tunnel along k. Inside smooth shapes most of the last passes'
  // sites are covered by their neighbours' parabolas and left out of the envelopes, and
  // columns along k hold several runs of non-sites (the marks of pass 1), which random
  // noise rarely gives; the plane (45 x 38 = 1710 columns) holds many 32-column blocks
  // and a partial last one
  for (const Vec3& spacing : {Vec3{1.5, 1.5, 1.5}, Vec3{0.8, 1.1, 2.5}}) {
    Grid g;
    g.size = {45, 38, 17};
    g.spacing_mm = spacing;
    Volume<std::uint8_t> m(g, 0);
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          const auto sq = [](double v) { return v * v; };
          const bool a = sq((i - 20) / 18.0) + sq((j - 18) / 14.0) + sq((k - 8) / 12.0) < 1;
          const bool b = sq((i - 38) / 12.0) + sq((j - 20) / 16.0) + sq((k - 6) / 7.0) < 1;  // past i = 44
          const bool cavity = sq(i - 16) + sq(j - 16) + sq(k - 9) < 16;
          const bool tunnel = sq(i - 26) + sq(j - 22) < 5;
          m.at(i, j, k) = (a || b) && !cavity && !tunnel;
        }
    for (int threads : {1, 3}) {
      check_against_brute_force(distance_to_background_mm(m, threads), brute_force(m, false));
      check_against_brute_force(distance_to_mask_mm(m, threads), brute_force(m, true));
    }
  }
}

TEST_CASE("EDT on one thread and on several gives the same maps bit for bit") {
  // the threads split slices and column chunks but each line is transformed by the
  // same code in the same order, so no tolerance: every float must be equal (on a
  // machine of one core both run on one thread)
  std::mt19937 rng(7);
  const auto m = random_mask(rng, {70, 45, 33}, {0.8, 1.1, 2.5}, 0.1);
  const int several = std::max(2, worker_threads(0));
  const auto one = distance_to_mask_mm(m, 1), many = distance_to_mask_mm(m, several);
  const auto one_bg = distance_to_background_mm(m, 1), many_bg = distance_to_background_mm(m, several);
  CHECK(one.data == many.data);
  CHECK(one_bg.data == many_bg.data);
}

TEST_CASE("worker_threads uses the cores and never more") {
  const int cores = int(std::max(1u, std::thread::hardware_concurrency()));
  CHECK(worker_threads(0) == cores);
  CHECK(worker_threads(-3) == cores);
  CHECK(worker_threads(1) == 1);
  CHECK(worker_threads(cores + 5) == cores);
}
