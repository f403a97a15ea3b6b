#include "prep/outputs.h"

#include <png.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <limits>
#include <random>
#include <sstream>
#include <vector>

#include "core/error.h"

namespace palpsim {
namespace {

namespace fs = std::filesystem;

// the NRRD header shared by both voxel types
std::string nrrd_header(const Grid& g, const char* type) {
  std::ostringstream s;
  s.precision(17);
  s << "NRRD0004\n# written by palpsim-prep\ntype: " << type << "\ndimension: 3\n"
    << "space: left-posterior-superior\nsizes: " << g.size.x << " " << g.size.y << " " << g.size.z << "\n"
    << "space directions:";
  const double sp[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z};
  for (int a = 0; a < 3; ++a)
    s << " (" << g.direction[a] * sp[a] << "," << g.direction[3 + a] * sp[a] << "," << g.direction[6 + a] * sp[a]
      << ")";
  s << "\nkinds: domain domain domain\nendian: little\nencoding: raw\n"
    << "space units: \"mm\" \"mm\" \"mm\"\n"
    << "space origin: (" << g.origin_mm.x << "," << g.origin_mm.y << "," << g.origin_mm.z << ")\n\n";
  return s.str();
}

template <typename T>
void write_nrrd_any(const std::string& path, const Volume<T>& v, const char* type) {
  std::ofstream out(path, std::ios::binary);
  if (!out) throw Error("cannot create '" + path + "'");
  const std::string h = nrrd_header(v.grid, type);
  out.write(h.data(), std::streamsize(h.size()));
  out.write(reinterpret_cast<const char*>(v.data.data()), std::streamsize(v.bytes()));
  out.close();
  if (!out) throw Error("error writing '" + path + "' (disk full?)");
}

// the physical bounding box of the grid's voxel centres
void bounds(const Grid& g, Vec3& lo, Vec3& hi) {
  lo = Vec3{1e300, 1e300, 1e300}, hi = -lo;
  for (int c = 0; c < 8; ++c) {
    const Vec3 p = g.to_physical(Vec3{(c & 1) ? g.size.x - 1.0 : 0.0, (c & 2) ? g.size.y - 1.0 : 0.0,
                                      (c & 4) ? g.size.z - 1.0 : 0.0});
    for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], p[a]), hi[a] = std::max(hi[a], p[a]);
  }
}

// nearest voxel of a physical point, or -1 outside
long long nearest_voxel(const Grid& g, const Vec3& p) {
  const Vec3 c = g.to_index(p);
  const int i = int(std::lround(c.x)), j = int(std::lround(c.y)), k = int(std::lround(c.z));
  return g.contains(i, j, k) ? (long long)g.index(i, j, k) : -1;
}


// a 5 x 7 pixel font for the preview's caption: rows top to bottom, bit 4 the left
// column; lowercase is drawn as uppercase, unknown characters as '?'
struct Glyph {
  char c;
  std::array<std::uint8_t, 7> rows;
};
constexpr Glyph kFont[] = {
    {' ', {0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00}},
    {'!', {0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x04}},
    {'"', {0x0a, 0x0a, 0x00, 0x00, 0x00, 0x00, 0x00}},
    {'%', {0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03}},
    {'\'', {0x04, 0x04, 0x08, 0x00, 0x00, 0x00, 0x00}},
    {'(', {0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02}},
    {')', {0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08}},
    {'+', {0x00, 0x04, 0x04, 0x1f, 0x04, 0x04, 0x00}},
    {',', {0x00, 0x00, 0x00, 0x00, 0x0c, 0x04, 0x08}},
    {'-', {0x00, 0x00, 0x00, 0x1f, 0x00, 0x00, 0x00}},
    {'.', {0x00, 0x00, 0x00, 0x00, 0x00, 0x0c, 0x0c}},
    {'/', {0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00}},
    {'0', {0x0e, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0e}},
    {'1', {0x04, 0x0c, 0x04, 0x04, 0x04, 0x04, 0x0e}},
    {'2', {0x0e, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1f}},
    {'3', {0x1f, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0e}},
    {'4', {0x02, 0x06, 0x0a, 0x12, 0x1f, 0x02, 0x02}},
    {'5', {0x1f, 0x10, 0x1e, 0x01, 0x01, 0x11, 0x0e}},
    {'6', {0x06, 0x08, 0x10, 0x1e, 0x11, 0x11, 0x0e}},
    {'7', {0x1f, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08}},
    {'8', {0x0e, 0x11, 0x11, 0x0e, 0x11, 0x11, 0x0e}},
    {'9', {0x0e, 0x11, 0x11, 0x0f, 0x01, 0x02, 0x0c}},
    {':', {0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x0c, 0x00}},
    {';', {0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x04, 0x08}},
    {'<', {0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02}},
    {'=', {0x00, 0x00, 0x1f, 0x00, 0x1f, 0x00, 0x00}},
    {'>', {0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08}},
    {'?', {0x0e, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04}},
    {'A', {0x0e, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11}},
    {'B', {0x1e, 0x11, 0x11, 0x1e, 0x11, 0x11, 0x1e}},
    {'C', {0x0e, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0e}},
    {'D', {0x1e, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1e}},
    {'E', {0x1f, 0x10, 0x10, 0x1e, 0x10, 0x10, 0x1f}},
    {'F', {0x1f, 0x10, 0x10, 0x1e, 0x10, 0x10, 0x10}},
    {'G', {0x0e, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0f}},
    {'H', {0x11, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11}},
    {'I', {0x0e, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0e}},
    {'J', {0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0c}},
    {'K', {0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11}},
    {'L', {0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1f}},
    {'M', {0x11, 0x1b, 0x15, 0x15, 0x11, 0x11, 0x11}},
    {'N', {0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11}},
    {'O', {0x0e, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0e}},
    {'P', {0x1e, 0x11, 0x11, 0x1e, 0x10, 0x10, 0x10}},
    {'Q', {0x0e, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0d}},
    {'R', {0x1e, 0x11, 0x11, 0x1e, 0x14, 0x12, 0x11}},
    {'S', {0x0f, 0x10, 0x10, 0x0e, 0x01, 0x01, 0x1e}},
    {'T', {0x1f, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04}},
    {'U', {0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0e}},
    {'V', {0x11, 0x11, 0x11, 0x11, 0x11, 0x0a, 0x04}},
    {'W', {0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0a}},
    {'X', {0x11, 0x11, 0x0a, 0x04, 0x0a, 0x11, 0x11}},
    {'Y', {0x11, 0x11, 0x0a, 0x04, 0x04, 0x04, 0x04}},
    {'Z', {0x1f, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1f}},
    {'_', {0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1f}},

};

const std::array<std::uint8_t, 7>& glyph(char c) {
  if (c >= 'a' && c <= 'z') c = char(c - 'a' + 'A');
  for (const Glyph& g : kFont)
    if (g.c == c) return g.rows;
  for (const Glyph& g : kFont)
    if (g.c == '?') return g.rows;
  return kFont[0].rows;
}

using Rgb = std::array<std::uint8_t, 3>;

// draws `text` with its top-left corner at (x, y), each font pixel `fs` x `fs` image pixels
void draw_text(std::vector<Rgb>& img, int width, int height, int x, int y, const std::string& text, int fs,
               const Rgb& colour) {
  for (std::size_t n = 0; n < text.size(); ++n) {
    const auto& rows = glyph(text[n]);
    const int gx = x + int(n) * 6 * fs;
    for (int r = 0; r < 7; ++r)
      for (int c = 0; c < 5; ++c) {
        if (!(rows[std::size_t(r)] & (0x10 >> c))) continue;
        for (int dy = 0; dy < fs; ++dy)
          for (int dx = 0; dx < fs; ++dx) {
            const int px = gx + c * fs + dx, py = y + r * fs + dy;
            if (px >= 0 && py >= 0 && px < width && py < height) img[std::size_t(py) * width + px] = colour;
          }
      }
  }
}

// splits `line` at spaces into pieces of at most `max_chars` characters (longer words are cut)
std::vector<std::string> wrap(const std::string& line, std::size_t max_chars) {
  std::vector<std::string> out;
  std::string cur;
  std::istringstream words(line);
  for (std::string w; words >> w;) {
    while (w.size() > max_chars) {
      if (!cur.empty()) out.push_back(cur), cur.clear();
      out.push_back(w.substr(0, max_chars));
      w = w.substr(max_chars);
    }
    if (!cur.empty() && cur.size() + 1 + w.size() > max_chars) out.push_back(cur), cur.clear();
    cur += (cur.empty() ? "" : " ") + w;
  }
  if (!cur.empty()) out.push_back(cur);
  return out;
}

// "-400" or "0.25": a threshold as the histogram's label shows it
std::string short_number(double v) {
  std::ostringstream s;
  s << std::setprecision(4) << v;
  return s.str();
}

// the histogram of every voxel's value (log counts; the 0.1 to 99.9 percentile, widened
// to the thresholds) in a strip of `bars_h` pixels from row `y0`, the thresholds as
// vertical lines (air cyan, bone low yellow, seeds orange) and up to two lines of text under it
void draw_histogram(std::vector<Rgb>& img, int width, int height, int y0, int bars_h, int fs, const Patient& p,
                    const PreviewOptions& o) {
  std::vector<float> v;
  v.reserve(p.intensity.data.size() / 3 + 1);
  for (std::size_t i = 0; i < p.intensity.data.size(); i += 3) v.push_back(p.intensity.data[i]);
  if (v.empty()) return;
  std::sort(v.begin(), v.end());
  double lo = v[std::size_t(0.001 * (v.size() - 1))], hi = v[std::size_t(0.999 * (v.size() - 1))];
  for (double t : {o.air_threshold, o.bone_low, o.bone_high})
    if (std::isfinite(t)) lo = std::min(lo, t), hi = std::max(hi, t);
  if (!(hi > lo)) hi = lo + 1;
  const int x0 = 4, bins = std::max(16, width - 8);
  const auto column = [&](double value) { return x0 + int(std::lround((value - lo) / (hi - lo) * (bins - 1))); };
  std::vector<double> count(std::size_t(bins), 0);
  for (float f : v)
    if (f >= lo && f <= hi) count[std::size_t(column(f) - x0)] += 1;
  const double top = std::log1p(*std::max_element(count.begin(), count.end()));
  const auto put = [&](int x, int y, Rgb c) {
    if (x >= 0 && y >= 0 && x < width && y < height) img[std::size_t(y) * width + x] = c;
  };
  for (int b = 0; b < bins; ++b) {
    const int bar = top > 0 ? int(std::lround(std::log1p(count[std::size_t(b)]) / top * bars_h)) : 0;
    for (int y = 0; y < bars_h; ++y) put(x0 + b, y0 + y, y >= bars_h - bar ? Rgb{170, 170, 190} : Rgb{40, 40, 64});
  }
  const Rgb air{0, 220, 255}, low{255, 210, 0}, seeds{255, 150, 40};
  // seeds first, so a plain threshold (low = seeds) shows in yellow
  const std::pair<double, Rgb> marks[3] = {{o.bone_high, seeds}, {o.bone_low, low}, {o.air_threshold, air}};
  for (const auto& [t, c] : marks)
    if (std::isfinite(t))
      for (int y = 0; y < bars_h; ++y) put(column(t), y0 + y, c);
  std::string text = short_number(lo) + ".." + short_number(hi) + " " + o.units + " (log count): air " +
                     short_number(o.air_threshold) + ", bone " + short_number(o.bone_low);
  if (std::isfinite(o.bone_high) && o.bone_high != o.bone_low) text += ", seeds " + short_number(o.bone_high);
  const std::vector<std::string> rows = wrap(text, std::size_t(std::max(10, (width - 8) / (6 * fs))));
  for (std::size_t r = 0; r < rows.size() && r < 2; ++r)
    draw_text(img, width, height, x0, y0 + bars_h + 2 * fs + int(r) * 9 * fs, rows[r], fs, Rgb{230, 230, 230});
}

}  // namespace

void write_rgb_png(const std::string& path, const std::vector<std::array<std::uint8_t, 3>>& img, int width,
                   int height, int scale) {
  std::vector<std::uint8_t> rows(std::size_t(width) * scale * 3 * height * scale);
  const std::size_t stride = std::size_t(width) * scale * 3;
  for (int y = 0; y < height * scale; ++y)
    for (int x = 0; x < width * scale; ++x)
      for (int c = 0; c < 3; ++c) rows[y * stride + std::size_t(x) * 3 + c] = img[std::size_t(y / scale) * width + x / scale][c];
  std::vector<png_bytep> ptrs(std::size_t(height) * scale);
  for (std::size_t y = 0; y < ptrs.size(); ++y) ptrs[y] = rows.data() + y * stride;
  const png_uint_32 w = png_uint_32(width * scale), h = png_uint_32(height * scale);

  std::FILE* fp = std::fopen(path.c_str(), "wb");
  if (!fp) throw Error("cannot create '" + path + "'");
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  png_infop info = png ? png_create_info_struct(png) : nullptr;
  if (!png || !info || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    std::fclose(fp);
    throw Error("error writing '" + path + "'");
  }
  png_init_io(png, fp);
  png_set_IHDR(png, info, w, h, 8, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  png_write_image(png, ptrs.data());
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  if (std::fclose(fp) != 0) throw Error("error writing '" + path + "' (disk full?)");
}

void write_nrrd(const std::string& path, const Volume<float>& v) { write_nrrd_any(path, v, "float"); }
void write_nrrd(const std::string& path, const Volume<std::uint8_t>& v) { write_nrrd_any(path, v, "uint8"); }

Vec3 preview_centre_mm(const Patient& p) {
  const Grid& g = p.grid;
  const IndexBox b = mask_box(p.has_bone ? p.bone : p.body);
  const Vec3i lo = b.lo, hi = b.hi;
  if (b.empty()) return g.to_physical(Vec3{(g.size.x - 1) / 2.0, (g.size.y - 1) / 2.0, (g.size.z - 1) / 2.0});
  return g.to_physical(Vec3{(lo.x + hi.x) / 2.0, (lo.y + hi.y) / 2.0, (lo.z + hi.z) / 2.0});
}

void write_preview_png(const std::string& path, const Patient& p, const Vec3& centre_mm, const PreviewOptions& o) {
  const std::vector<std::string>& caption = o.caption;
  const bool border_is_skin = o.border_is_skin;
  const Grid& g = p.grid;
  const double px = g.spacing_mm.x;  // isotropic grid: one pixel per voxel edge
  Vec3 lo, hi;
  bounds(g, lo, hi);

  // grey scale: 0 .. 99th percentile of F inside the body
  std::vector<float> inside;
  for (std::size_t i = 0; i < g.count(); i += 7)
    if (p.body.data[i]) inside.push_back(p.force.data[i]);
  float top = 1;
  if (!inside.empty()) {
    const std::size_t at = std::size_t(0.99 * (inside.size() - 1));
    std::nth_element(inside.begin(), inside.begin() + at, inside.end());
    top = std::max(inside[at], 1e-6f);
  }

  // three views: (physical axis across, sign, physical axis down, sign, fixed axis)
  struct View { int across, down, fixed; double across_sign, down_sign; };
  // axial: x (R->L) across, y (A->P) down; coronal: x across, z (S->I) down;
  // sagittal: y (A->P) across, z (S->I) down
  const View views[3] = {{0, 1, 2, +1, +1}, {0, 2, 1, +1, -1}, {1, 2, 0, +1, -1}};
  int width = 0, height = 0, sizes[3][2];
  for (int v = 0; v < 3; ++v) {
    sizes[v][0] = int(std::floor((hi[views[v].across] - lo[views[v].across]) / px)) + 1;
    sizes[v][1] = int(std::floor((hi[views[v].down] - lo[views[v].down]) / px)) + 1;
    width += sizes[v][0];
    height = std::max(height, sizes[v][1]);
  }
  const int gap = 4;
  width += 2 * gap;
  // small grids are enlarged so the preview stays readable
  const int scale = std::max(1, int(std::ceil(400.0 / std::max(height, 1))));
  // the caption below the slices: font pixels of 2 image pixels on large previews,
  // wrapped to the preview's width; warnings in orange
  const int fs = scale >= 2 ? 1 : 2, line_h = 9 * fs;
  std::vector<std::pair<std::string, bool>> lines;
  for (const std::string& c : caption) {
    const bool warning = c.rfind("warning", 0) == 0;
    for (const std::string& piece : wrap(c, std::size_t(std::max(10, (width - 8) / (6 * fs)))))
      lines.emplace_back(piece, warning);
  }
  const int slices_h = height;
  // the histogram's strip: bars, then a line of text
  const bool histogram = std::isfinite(o.air_threshold) || std::isfinite(o.bone_low);
  const int hist_bars_h = histogram ? std::max(40, slices_h / 4) : 0;
  const int hist_h = histogram ? hist_bars_h + 2 * line_h + 2 * fs + 6 : 0;
  height += hist_h;
  if (!lines.empty()) height += int(lines.size()) * line_h + 2 * fs + 4;
  std::vector<std::array<std::uint8_t, 3>> img(std::size_t(width) * height, {24, 24, 48});
  int x0 = 0;
  for (int v = 0; v < 3; ++v) {
    const View& w = views[v];
    const int sw = sizes[v][0], sh = sizes[v][1];
    std::vector<long long> vox(std::size_t(sw) * sh);
    for (int y = 0; y < sh; ++y)
      for (int x = 0; x < sw; ++x) {
        Vec3 q = centre_mm;
        q[w.across] = w.across_sign > 0 ? lo[w.across] + x * px : hi[w.across] - x * px;
        q[w.down] = w.down_sign > 0 ? lo[w.down] + y * px : hi[w.down] - y * px;
        vox[std::size_t(y) * sw + x] = nearest_voxel(g, q);
      }
    // beyond the image (or the grid) is outside the body where the border counts as skin,
    // and body otherwise, so that no contour is drawn along a cut
    const auto in_body = [&](int x, int y) {
      if (x < 0 || y < 0 || x >= sw || y >= sh) return !border_is_skin;
      const long long i = vox[std::size_t(y) * sw + x];
      return i >= 0 ? p.body.data[std::size_t(i)] != 0 : !border_is_skin;
    };
    const auto in_bone = [&](int x, int y) {
      if (x < 0 || y < 0 || x >= sw || y >= sh) return false;
      const long long i = vox[std::size_t(y) * sw + x];
      return i >= 0 && p.bone.data[std::size_t(i)] != 0;
    };
    for (int y = 0; y < sh; ++y)
      for (int x = 0; x < sw; ++x) {
        const long long i = vox[std::size_t(y) * sw + x];
        auto& px_out = img[std::size_t(y) * width + x0 + x];
        if (i < 0) continue;
        // square root: the soft-tissue halo stays visible beside the bright bone
        const double f = std::sqrt(std::clamp(double(p.force.data[std::size_t(i)]) / top, 0.0, 1.0));
        const auto grey = std::uint8_t(std::lround(255 * f));
        px_out = {grey, grey, grey};
        // skin contour: body pixels with a non-body 4-neighbour
        if (in_body(x, y) && (!in_body(x - 1, y) || !in_body(x + 1, y) || !in_body(x, y - 1) || !in_body(x, y + 1)))
          px_out = {255, 0, 0};
        // bone contour, the same way, in yellow
        else if (in_bone(x, y) &&
                 (!in_bone(x - 1, y) || !in_bone(x + 1, y) || !in_bone(x, y - 1) || !in_bone(x, y + 1)))
          px_out = {255, 210, 0};
      }
    x0 += sw + gap;
  }
  if (histogram) draw_histogram(img, width, height, slices_h + 4, hist_bars_h, fs, p, o);
  // the caption
  for (std::size_t n = 0; n < lines.size(); ++n)
    draw_text(img, width, height, 4, slices_h + hist_h + 2 * fs + 2 + int(n) * line_h, lines[n].first, fs,
              lines[n].second ? Rgb{255, 150, 40} : Rgb{230, 230, 230});

  write_rgb_png(path, img, width, height, scale);
}

void write_patient_outputs(const std::string& out_dir, const Patient& p, const std::string& prep_json,
                           const PreviewOptions& preview) {
  const fs::path out = fs::absolute(fs::path(out_dir)).lexically_normal();
  const fs::path parent = out.has_filename() ? out.parent_path() : out.parent_path().parent_path();
  const std::string name = (out.has_filename() ? out : out.parent_path()).filename().string();
  std::error_code ec;
  fs::create_directories(parent, ec);
  if (ec) throw Error("cannot create the output's parent folder '" + parent.string() + "': " + ec.message());
  if (fs::exists(out) && !fs::is_directory(out))
    throw Error("output '" + out.string() + "' exists and is not a folder");

  // a unique temporary sibling, removed on any failure
  std::mt19937_64 rng(std::random_device{}());
  const fs::path tmp = parent / ("." + name + ".tmp-" + std::to_string(::getpid()) + "-" + std::to_string(rng() % 1000000));
  fs::create_directory(tmp, ec);
  if (ec) throw Error("cannot create the temporary folder '" + tmp.string() + "': " + ec.message());
  try {
    write_nrrd((tmp / "F.nrrd").string(), p.force);
    write_nrrd((tmp / "body.nrrd").string(), p.body);
    write_nrrd((tmp / "bone.nrrd").string(), p.bone);
    write_nrrd((tmp / "dist_bone.nrrd").string(), p.dist_bone_mm);
    write_nrrd((tmp / "dist_skin.nrrd").string(), p.dist_skin_mm);
    write_preview_png((tmp / "preview.png").string(), p, preview_centre_mm(p), preview);
    {
      std::ofstream j(tmp / "prep.json");
      j << prep_json << "\n";
      j.close();
      if (!j) throw Error("error writing '" + (tmp / "prep.json").string() + "'");
    }
    // swap in: move an old output aside, rename the new one, then drop the old
    fs::path old;
    if (fs::exists(out)) {
      old = parent / ("." + name + ".old-" + std::to_string(::getpid()) + "-" + std::to_string(rng() % 1000000));
      fs::rename(out, old);
    }
    fs::rename(tmp, out);
    if (!old.empty()) fs::remove_all(old, ec);
  } catch (const std::exception& e) {
    fs::remove_all(tmp, ec);
    if (dynamic_cast<const Error*>(&e)) throw;
    throw Error("cannot write the outputs to '" + out.string() + "': " + e.what());
  }
}

}  // namespace palpsim
