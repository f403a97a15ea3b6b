// Helpers of the render tests: the prepared phantom (support/prepared_phantom.h), the skin
// point over the L3 spinous process, an EGL context shared by the test cases, image
// statistics and PNG files.
#pragma once

#include <png.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "core/error.h"
#include "prep/prepare.h"
#include "render/egl_context.h"
#include "prepared_phantom.h"

namespace palpsim::test {

/// The skin over the L3 spinous process: on the body's mid-sagittal column at
/// z = -5 mm, the body voxel farthest towards +y (the back, the phantom lies prone).
inline Vec3 l3_skin_mm(const Patient& p) {
  const Grid& g = p.grid;
  const int k = std::clamp(int(std::lround(g.to_index({0, 0, -5}).z)), 0, g.size.z - 1);
  int ilo = g.size.x, ihi = -1;
  for (int j = 0; j < g.size.y; ++j)
    for (int i = 0; i < g.size.x; ++i)
      if (p.body.at(i, j, k)) {
        ilo = std::min(ilo, i);
        ihi = std::max(ihi, i);
      }
  const int i = ihi >= 0 ? (ilo + ihi) / 2 : g.size.x / 2;
  int j = g.size.y - 1;
  while (j > 0 && !p.body.at(i, j, k)) --j;
  return g.to_physical({double(i), double(j), double(k)});
}

/// The EGL context of the test process, made once on the main thread (the tests fail
/// with its error message when there is none: CI machines have Mesa).
inline render::EglContext& render_context() {
  static std::unique_ptr<render::EglContext> ctx = render::EglContext::create();
  return *ctx;
}

/// Mean luminance (0..255) of an RGB8 image's rectangle [x0, x1) x [y0, y1), rows top-down.
inline double mean_luma(const std::vector<std::uint8_t>& rgb, int width, int x0, int y0, int x1, int y1) {
  double sum = 0;
  long n = 0;
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x) {
      const std::uint8_t* p = &rgb[(std::size_t(y) * width + x) * 3];
      sum += 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2];
      ++n;
    }
  return n ? sum / n : 0;
}

/// Writes an RGB8 image (rows top-down) as PNG; throws palpsim::Error on failure.
inline void write_png(const std::string& path, const std::vector<std::uint8_t>& rgb, int width, int height) {
  FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) throw Error("cannot write " + path);
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (!png || !info || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    std::fclose(f);
    throw Error("libpng failed writing " + path);
  }
  png_init_io(png, f);
  png_set_IHDR(png, info, png_uint_32(width), png_uint_32(height), 8, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  for (int y = 0; y < height; ++y)
    png_write_row(png, const_cast<png_bytep>(&rgb[std::size_t(y) * width * 3]));
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  std::fclose(f);
}

}  // namespace palpsim::test
