// Volume storage (core/volume.h): large volumes sit on 2 MiB boundaries (offered to the
// kernel as huge pages), small ones on the ordinary heap, and both copy, move and fill
// like any vector.
#include <catch2/catch.hpp>

#include <cstdint>
#include <utility>

#include "core/volume.h"

using namespace palpsim;

namespace {

Grid grid_of(int nx, int ny, int nz) {
  Grid g;
  g.size = {nx, ny, nz};
  g.spacing_mm = {1, 1, 1};
  return g;
}

bool on_huge_page_boundary(const void* p) { return reinterpret_cast<std::uintptr_t>(p) % kHugePageBytes == 0; }

}  // namespace

TEST_CASE("a volume of 4 MiB or more starts on a 2 MiB boundary and behaves as a vector", "[core]") {
  // 64 x 64 x 300 floats: 4.9 MB, above kHugeBlockBytes
  const Grid g = grid_of(64, 64, 300);
  REQUIRE(g.count() * sizeof(float) >= kHugeBlockBytes);
  Volume<float> filled(g, 2.5f);
  CHECK(on_huge_page_boundary(filled.data.data()));
  bool all = true;
  for (float v : filled.data) all = all && v == 2.5f;
  CHECK(all);

  // unset, then written whole (the makers' way), copied and moved
  Volume<float> fresh(g, Uninitialized{});
  CHECK(on_huge_page_boundary(fresh.data.data()));
  for (std::size_t i = 0; i < fresh.data.size(); ++i) fresh.data[i] = float(i % 977);
  const Volume<float> copy = fresh;
  CHECK(on_huge_page_boundary(copy.data.data()));
  CHECK(copy.data == fresh.data);
  const float* before = fresh.data.data();
  Volume<float> moved = std::move(fresh);
  CHECK(moved.data.data() == before);
  CHECK(moved.data == copy.data);

  // a volume of bytes as large: the same boundary
  const Volume<std::uint8_t> mask(grid_of(256, 256, 80), 1);
  CHECK(on_huge_page_boundary(mask.data.data()));
}

TEST_CASE("a small volume comes from the ordinary heap and keeps its values", "[core]") {
  const Grid g = grid_of(16, 16, 16);
  REQUIRE(g.count() * sizeof(float) < kHugeBlockBytes);
  Volume<float> v(g, -1.0f);
  v.at(3, 4, 5) = 7.0f;
  Volume<float> w = v;
  CHECK(w.at(3, 4, 5) == 7.0f);
  CHECK(w.at(0, 0, 0) == -1.0f);
  w = Volume<float>(grid_of(300, 300, 20), 0.5f);  // replaced by a large one and back
  CHECK(on_huge_page_boundary(w.data.data()));
  w = v;
  CHECK(w.data == v.data);
}
