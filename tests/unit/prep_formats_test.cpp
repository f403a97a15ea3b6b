// Every CT format reads with its origin, spacing, direction and values: NRRD (.nrrd,
// .nhdr + raw), MetaImage (.mha, .mhd + raw), NIfTI (.nii, .nii.gz).
#include <catch2/catch.hpp>

#include <cstdlib>
#include <fstream>

#include "prep/ct_io.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

// a small int16 volume with a value ramp, so voxel order errors show
std::vector<std::int16_t> ramp(int nx, int ny, int nz) {
  std::vector<std::int16_t> v(std::size_t(nx) * ny * nz);
  for (std::size_t i = 0; i < v.size(); ++i) v[i] = std::int16_t(int(i % 3000) - 1000);
  return v;
}

void check_read(const std::string& path, const std::vector<std::int16_t>& vox, Vec3 spacing, Vec3 origin,
                std::array<double, 9> direction, const char* format) {
  INFO(path);
  const CtImage ct = read_ct(path, PrepSettings{});
  CHECK(ct.info.format == format);
  CHECK(ct.info.pixel_type == "int16");
  CHECK(ct.image.grid.size == Vec3i{12, 10, 8});
  for (int a = 0; a < 3; ++a) {
    // the headers carry 6+ significant digits; NIfTI stores float32
    CHECK(ct.image.grid.spacing_mm[a] == Approx(spacing[a]).epsilon(1e-6));
    CHECK(ct.image.grid.origin_mm[a] == Approx(origin[a]).margin(1e-4));
  }
  for (int e = 0; e < 9; ++e) CHECK(ct.image.grid.direction[e] == Approx(direction[e]).margin(1e-6));
  REQUIRE(ct.image.data.size() == vox.size());
  bool same = true;
  for (std::size_t i = 0; i < vox.size(); ++i) same = same && ct.image.data[i] == float(vox[i]);
  CHECK(same);
  CHECK(ct.info.min_value == -1000);
}

}  // namespace

TEST_CASE("NRRD, MetaImage and NIfTI keep origin, spacing, direction and voxel order") {
  TempDir d;
  const auto vox = ramp(12, 10, 8);
  const std::string bytes(reinterpret_cast<const char*>(vox.data()), vox.size() * 2);
  const Vec3 sp{0.8, 1.25, 2.5}, org{-100.5, 20.25, 300};
  // a rotation about S by 90 degrees: columns are the axes' directions
  const std::array<double, 9> rot{0, -1, 0, 1, 0, 0, 0, 0, 1};

  // NRRD with attached and detached data
  const std::string nrrd_head =
      "NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\nsizes: 12 10 8\n"
      "space directions: (0,0.8,0) (-1.25,0,0) (0,0,2.5)\nspace origin: (-100.5,20.25,300)\n"
      "kinds: domain domain domain\nendian: little\nencoding: raw\n";
  std::ofstream(d / "a.nrrd", std::ios::binary) << nrrd_head << "\n" << bytes;
  std::ofstream(d / "b.nhdr") << nrrd_head << "data file: b.raw\n\n";
  std::ofstream(d / "b.raw", std::ios::binary) << bytes;
  check_read(d / "a.nrrd", vox, sp, org, rot, "NRRD");
  check_read(d / "b.nhdr", vox, sp, org, rot, "NRRD");
  CHECK(read_ct_info(d / "b.nhdr", PrepSettings{}).files.size() == 2);  // header and data are hashed

  // MetaImage: TransformMatrix lists the direction's columns one after another
  const std::string mha_head =
      "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
      "TransformMatrix = 0 1 0 -1 0 0 0 0 1\nOffset = -100.5 20.25 300\nElementSpacing = 0.8 1.25 2.5\n"
      "DimSize = 12 10 8\nElementType = MET_SHORT\n";
  std::ofstream(d / "c.mha", std::ios::binary) << mha_head << "ElementDataFile = LOCAL\n" << bytes;
  std::ofstream(d / "e.mhd") << mha_head << "ElementDataFile = e.raw\n";
  std::ofstream(d / "e.raw", std::ios::binary) << bytes;
  check_read(d / "c.mha", vox, sp, org, rot, "MetaImage");
  check_read(d / "e.mhd", vox, sp, org, rot, "MetaImage");
  CHECK(read_ct_info(d / "e.mhd", PrepSettings{}).files.size() == 2);

  // NIfTI (RAS on disk): ITK turns a scaled-identity sform into LPS direction diag(-1, -1, 1)
  const double nsp[3] = {0.8, 1.25, 2.5};
  write_nifti_int16(d / "f.nii", 12, 10, 8, nsp, vox);
  check_read(d / "f.nii", vox, sp, Vec3{0, 0, 0}, {-1, 0, 0, 0, -1, 0, 0, 0, 1}, "NIfTI");
  REQUIRE(std::system(("gzip -k -f '" + (d / "f.nii") + "'").c_str()) == 0);
  check_read(d / "f.nii.gz", vox, sp, Vec3{0, 0, 0}, {-1, 0, 0, 0, -1, 0, 0, 0, 1}, "NIfTI");
}
