#include "prep/field_of_view.h"

#include <cmath>
#include <iomanip>
#include <sstream>

#include "core/setting_names.h"
#include "prep/distance.h"
#include "prep/pipeline.h"

namespace palpsim {
namespace {

// "a", "a and b", "a, b and c"
std::string listed(const std::vector<CutFace>& faces) {
  std::string s;
  for (std::size_t i = 0; i < faces.size(); ++i) {
    if (i > 0) s += i + 1 == faces.size() ? " and " : ", ";
    s += faces[i].name;
  }
  return s;
}

std::string num(double v, int digits) {
  std::ostringstream s;
  s << std::setprecision(digits) << v;
  return s.str();
}

}  // namespace

std::string face_name(const Grid& g, int axis, bool high) {
  // the outward normal: the direction matrix's column for `axis`, reversed at the first index
  const double sign = high ? 1.0 : -1.0;
  const Vec3 n{sign * g.direction[axis], sign * g.direction[3 + axis], sign * g.direction[6 + axis]};
  int along = 0;
  for (int a = 1; a < 3; ++a)
    if (std::abs(n[a]) > std::abs(n[along])) along = a;
  static const char* const names[3][2] = {{"right", "left"}, {"anterior", "posterior"}, {"inferior", "superior"}};
  return names[along][n[along] > 0 ? 1 : 0];
}

FieldOfView find_cut_faces(const Volume<std::uint8_t>& body, CutFaces mode) {
  const Grid& g = body.grid;
  std::size_t total = 0;
  for (std::uint8_t v : body.data) total += v != 0;
  FieldOfView fov;
  for (int axis = 0; axis < 3; ++axis) {
    // the two axes that span the face
    const int u = (axis + 1) % 3, w = (axis + 2) % 3;
    for (const bool high : {false, true}) {
      std::size_t on = 0;
      Vec3i ijk{0, 0, 0};
      ijk[axis] = high ? g.size[axis] - 1 : 0;
      for (ijk[w] = 0; ijk[w] < g.size[w]; ++ijk[w])
        for (ijk[u] = 0; ijk[u] < g.size[u]; ++ijk[u]) on += body.at(ijk.x, ijk.y, ijk.z) != 0;
      const double pixel_mm2 = g.spacing_mm[u] * g.spacing_mm[w];
      if (double(on) * pixel_mm2 < kMinCutAreaMm2) continue;
      CutFace f;
      f.name = face_name(g, axis, high);
      f.axis = axis;
      f.high = high;
      f.body_voxels = on;
      f.area_mm2 = double(on) * pixel_mm2;
      f.face_fraction = double(on) / (double(g.size[u]) * g.size[w]);
      f.body_fraction = total ? double(on) / double(total) : 0.0;
      fov.faces.push_back(f);
    }
  }
  if (!fov.faces.empty())
    fov.warning = "the body is cut at the " + listed(fov.faces) + (fov.faces.size() > 1 ? " faces" : " face") +
                  ": no skin there (prep.cut_faces = \"" + setting_name(mode) + "\": " +
                  (mode == CutFaces::kSkin ? "they count as skin)" : "left open, no depth is measured to them)");
  return fov;
}

Volume<float> depth_under_skin_mm(const Volume<std::uint8_t>& body, CutFaces mode, int threads) {
  if (mode == CutFaces::kOpen) return distance_to_background_mm(body, threads);
  // the mask inside a layer of outside voxels one voxel thick on every face
  const Grid& g = body.grid;
  Grid padded = g;
  padded.size = {g.size.x + 2, g.size.y + 2, g.size.z + 2};
  padded.origin_mm = g.to_physical(Vec3{-1, -1, -1});
  Volume<std::uint8_t> m(padded, std::uint8_t(0));
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) m.at(i + 1, j + 1, k + 1) = body.at(i, j, k);
  const Volume<float> d = distance_to_background_mm(m, threads);
  m = Volume<std::uint8_t>();
  Volume<float> out(g, 0.0f);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) out.at(i, j, k) = d.at(i + 1, j + 1, k + 1);
  return out;
}

BodyCheck check_body(const Volume<std::uint8_t>& body, double air_threshold, const std::string& units) {
  BodyCheck c;
  const std::vector<std::size_t> sizes = component_sizes(body);
  std::size_t total = 0;
  for (std::size_t n : sizes) total += n;
  if (total == 0) return c;
  for (std::size_t n : sizes) c.pieces += double(n) >= kMinPieceFraction * double(total);
  c.largest_fraction = double(sizes[0]) / double(total);
  // the axial slices holding body
  const Grid& g = body.grid;
  const int ax = axial_axis(g), u = (ax + 1) % 3, w = (ax + 2) % 3;
  int slices = 0;
  for (int s = 0; s < g.size[ax]; ++s) {
    bool any = false;
    Vec3i ijk{0, 0, 0};
    ijk[ax] = s;
    for (ijk[w] = 0; ijk[w] < g.size[w] && !any; ++ijk[w])
      for (ijk[u] = 0; ijk[u] < g.size[u] && !any; ++ijk[u]) any = body.at(ijk.x, ijk.y, ijk.z) != 0;
    slices += any;
  }
  const double voxel_mm3 = g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z;
  c.cross_section_cm2 = double(total) * voxel_mm3 / (slices * g.spacing_mm[ax]) / 100.0;
  const std::string air = "prep.air_threshold (" + num(air_threshold, 6) + " " + units + ")";
  if (c.pieces > kMaxBodyPieces || c.largest_fraction < kMinLargestPieceFraction)
    c.warnings.push_back("the body mask falls apart into " + std::to_string(c.pieces) + " pieces (the largest holds " +
                         num(std::round(100 * c.largest_fraction), 3) + "% of it), but a body is one piece with at "
                         "most its two arms apart: " + air + " may lie inside soft tissue");
  if (c.cross_section_cm2 < kMinBodyCrossSectionCm2 || c.cross_section_cm2 > kMaxBodyCrossSectionCm2)
    c.warnings.push_back("the body mask's mean axial cross-section is " + num(std::round(c.cross_section_cm2), 6) +
                         " cm^2 (" + num(std::round(double(total) * voxel_mm3 / 1e5) / 10, 6) + " l over " +
                         num(std::round(slices * g.spacing_mm[ax]), 6) + " mm), but a trunk's is about " +
                         num(kMinBodyCrossSectionCm2, 6) + "-" + num(kMaxBodyCrossSectionCm2, 6) +
                         " cm^2 (an adult abdomen about 470): check " + air);
  return c;
}

std::string field_of_view_json(const FieldOfView& fov, CutFaces mode) {
  std::string s = "{\"cut_faces_treated_as\": \"" + std::string(setting_name(mode)) + "\", \"cut_faces\": [";
  for (std::size_t i = 0; i < fov.faces.size(); ++i) {
    const CutFace& f = fov.faces[i];
    s += std::string(i ? ", " : "") + "{\"face\": \"" + f.name + "\", \"grid_axis\": " + std::to_string(f.axis) +
         ", \"grid_side\": \"" + (f.high ? "last" : "first") + "\", \"body_voxels\": " +
         std::to_string(f.body_voxels) + ", \"area_mm2\": " + num(f.area_mm2, 8) + ", \"fraction_of_face\": " +
         num(f.face_fraction, 4) + ", \"fraction_of_body_voxels\": " + num(f.body_fraction, 4) + "}";
  }
  return s + "]}";
}

}  // namespace palpsim
