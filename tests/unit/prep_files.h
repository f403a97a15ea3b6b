// Helpers of the prep tests: small CT files written by hand (NRRD, NIfTI,
// MetaImage) in a temporary folder, so bad inputs can be made without ITK.
#pragma once

#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "core/scene.h"
#include "core/volume.h"

namespace palpsim::test {

/// A fresh temporary folder, removed when the object goes.
struct TempDir {
  std::filesystem::path path;
  TempDir() {
    std::mt19937_64 rng(std::random_device{}());
    path = std::filesystem::temp_directory_path() /
           ("palpsim-prep-test-" + std::to_string(::getpid()) + "-" + std::to_string(rng() % 100000000));
    std::filesystem::create_directories(path);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path, ec);
  }
  std::string operator/(const std::string& name) const { return (path / name).string(); }
};

/// Writes a NRRD file (raw, little-endian) of `type` ("float", "short", "uchar", ...)
/// with `sizes` (2 to 4 axes), spacing per axis and the given bytes.
inline void write_nrrd_file(const std::string& path, const std::string& type, const std::vector<int>& sizes,
                            const std::vector<double>& spacing, const void* data, std::size_t bytes) {
  std::ofstream o(path, std::ios::binary);
  o << "NRRD0004\ntype: " << type << "\ndimension: " << sizes.size() << "\nsizes:";
  for (int s : sizes) o << " " << s;
  o << "\nspacings:";
  for (double s : spacing) o << " " << s;
  o << "\nendian: little\nencoding: raw\n\n";
  o.write(static_cast<const char*>(data), std::streamsize(bytes));
}

/// Writes a 3D float volume as NRRD with its spacing (LPS, origin and direction as given).
inline void write_volume_nrrd(const std::string& path, const Volume<float>& v) {
  const Grid& g = v.grid;
  std::ofstream o(path, std::ios::binary);
  o.precision(17);
  o << "NRRD0004\ntype: float\ndimension: 3\nspace: left-posterior-superior\nsizes: " << g.size.x << " "
    << g.size.y << " " << g.size.z << "\nspace directions:";
  const double sp[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z};
  for (int a = 0; a < 3; ++a)
    o << " (" << g.direction[a] * sp[a] << "," << g.direction[3 + a] * sp[a] << "," << g.direction[6 + a] * sp[a]
      << ")";
  o << "\nspace origin: (" << g.origin_mm.x << "," << g.origin_mm.y << "," << g.origin_mm.z
    << ")\nendian: little\nencoding: raw\n\n";
  o.write(reinterpret_cast<const char*>(v.data.data()), std::streamsize(v.bytes()));
}

/// The 352 bytes of a NIfTI-1 header (.nii, little-endian) for nx x ny x nz voxels of
/// `datatype` (4 = int16, 16 = float32) and `bitpix` bits, pixdim = spacing and the sform
/// a scaled identity; tests damage single fields through the byte offsets of nifti1.h.
inline std::string nifti_header(int nx, int ny, int nz, const double spacing[3], int datatype, int bitpix) {
  std::string h(352, '\0');
  const auto put_i32 = [&](int off, std::int32_t v) { std::memcpy(&h[off], &v, 4); };
  const auto put_i16 = [&](int off, std::int16_t v) { std::memcpy(&h[off], &v, 2); };
  const auto put_f32 = [&](int off, float v) { std::memcpy(&h[off], &v, 4); };
  put_i32(0, 348);
  put_i16(40, 3), put_i16(42, std::int16_t(nx)), put_i16(44, std::int16_t(ny)), put_i16(46, std::int16_t(nz));
  put_i16(48, 1), put_i16(50, 1), put_i16(52, 1), put_i16(54, 1);
  put_i16(70, std::int16_t(datatype));
  put_i16(72, std::int16_t(bitpix));
  put_f32(76, 1), put_f32(80, float(spacing[0])), put_f32(84, float(spacing[1])), put_f32(88, float(spacing[2]));
  put_f32(108, 352);  // vox_offset
  put_f32(112, 1);    // scl_slope
  h[123] = 2;         // xyzt_units: mm
  put_i16(252, 0), put_i16(254, 1);  // qform 0, sform 1 (scaled identity in RAS)
  put_f32(280, float(spacing[0])), put_f32(300, float(spacing[1])), put_f32(320, float(spacing[2]));
  std::memcpy(&h[344], "n+1\0", 4);
  return h;
}

/// Writes a NIfTI-1 file (.nii) of int16 voxels with pixdim = spacing.
inline void write_nifti_int16(const std::string& path, int nx, int ny, int nz, const double spacing[3],
                              const std::vector<std::int16_t>& voxels) {
  std::ofstream o(path, std::ios::binary);
  o << nifti_header(nx, ny, nz, spacing, 4, 16);
  o.write(reinterpret_cast<const char*>(voxels.data()), std::streamsize(voxels.size() * 2));
}

/// Writes a NIfTI-1 file (.nii) of float32 voxels with pixdim = spacing.
inline void write_nifti_float(const std::string& path, int nx, int ny, int nz, const double spacing[3],
                              const std::vector<float>& voxels) {
  std::ofstream o(path, std::ios::binary);
  o << nifti_header(nx, ny, nz, spacing, 16, 32);
  o.write(reinterpret_cast<const char*>(voxels.data()), std::streamsize(voxels.size() * 4));
}

/// A synthetic torso in HU on an anisotropic grid: an elliptic body of soft tissue
/// with a cortical bone tube (hollow, filled with 150 HU marrow), a gas pocket, and
/// air around it. Sizes in voxels; `spacing_mm` per axis.
inline Volume<float> synthetic_torso(Vec3i size, Vec3 spacing_mm) {
  Grid g;
  g.size = size;
  g.spacing_mm = spacing_mm;
  g.origin_mm = {-0.5 * (size.x - 1) * spacing_mm.x, -0.5 * (size.y - 1) * spacing_mm.y, 0};
  Volume<float> v(g, -1000.0f);
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j < size.y; ++j)
      for (int i = 0; i < size.x; ++i) {
        const Vec3 p = g.to_physical(Vec3{double(i), double(j), double(k)});
        const double body = (p.x / 60) * (p.x / 60) + (p.y / 40) * (p.y / 40);  // ellipse 120 x 80 mm
        const double r_bone = std::hypot(p.x, p.y - 15);                       // tube centred 15 mm posterior
        const double r_gas = std::hypot(p.x + 30, p.y + 10);
        float hu = -1000;
        if (body <= 1) hu = 40;
        if (r_gas <= 8) hu = -1000;
        if (r_bone <= 10) hu = r_bone >= 7 ? 900.0f : 150.0f;
        v.at(i, j, k) = hu;
      }
  return v;
}

/// Voxels lo..hi-1 of `v` on a grid that keeps their physical place (a cropped field of view).
inline Volume<float> crop(const Volume<float>& v, Vec3i lo, Vec3i hi) {
  Grid g = v.grid;
  g.size = {hi.x - lo.x, hi.y - lo.y, hi.z - lo.z};
  g.origin_mm = v.grid.to_physical(Vec3{double(lo.x), double(lo.y), double(lo.z)});
  Volume<float> out(g);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) out.at(i, j, k) = v.at(lo.x + i, lo.y + j, lo.z + k);
  return out;
}

/// A scene for a CT file with the cache in `cache_dir` ("" = cache off).
inline Scene ct_scene(const std::string& ct, const std::string& cache_dir) {
  Scene s;
  s.use_phantom = false;
  s.ct_path = ct;
  s.prep.cache_dir = cache_dir;
  s.prep.use_cache = !cache_dir.empty();
  return s;
}

/// The message of the palpsim::Error that fn throws ("" if none).
template <typename Fn>
std::string error_message(Fn&& fn) {
  try {
    fn();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

}  // namespace palpsim::test
