// The field of view: which faces of the image cut the body (named in patient terms
// from the grid's direction), the depth under the skin (B) and a press at a cut face
// with prep.cut_faces "skin" and "open", the body mask's plausibility warnings and the
// landmarks; on a cropped phantom and on crops of the shared abdomen (cropped here,
// never copied).
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "haptics/force_model.h"
#include "prep/ct_io.h"
#include "prep/field_of_view.h"
#include "prep/landmarks.h"
#include "prep/phantom.h"
#include "prep/prepare.h"
#include "support/data.h"
#include "support/log_capture.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

std::vector<std::string> names(const FieldOfView& f) {
  std::vector<std::string> n;
  for (const CutFace& c : f.faces) n.push_back(c.name);
  return n;
}

// the largest and smallest B (mm) over the body voxels on the face at `axis`, `high`
std::pair<float, float> face_depths(const Patient& p, int axis, bool high) {
  const Grid& g = p.grid;
  const int u = (axis + 1) % 3, w = (axis + 2) % 3;
  float lo = INFINITY, hi = 0;
  Vec3i ijk{0, 0, 0};
  ijk[axis] = high ? g.size[axis] - 1 : 0;
  for (ijk[w] = 0; ijk[w] < g.size[w]; ++ijk[w])
    for (ijk[u] = 0; ijk[u] < g.size[u]; ++ijk[u])
      if (p.body.at(ijk.x, ijk.y, ijk.z)) {
        const float b = p.dist_skin_mm.at(ijk.x, ijk.y, ijk.z);
        lo = std::min(lo, b), hi = std::max(hi, b);
      }
  return {lo, hi};
}

Scene scene_at(double spacing_mm, CutFaces mode) {
  Scene s;
  s.prep.spacing_mm = spacing_mm;
  s.prep.use_cache = false;
  s.prep.cut_faces = mode;
  return s;
}

}  // namespace

TEST_CASE("face names follow the grid's direction matrix in LPS") {
  Grid g;
  g.size = {4, 4, 4};
  CHECK(face_name(g, 0, false) == "right");  // identity: -x is the patient's right
  CHECK(face_name(g, 0, true) == "left");
  CHECK(face_name(g, 1, false) == "anterior");
  CHECK(face_name(g, 1, true) == "posterior");
  CHECK(face_name(g, 2, false) == "inferior");
  CHECK(face_name(g, 2, true) == "superior");
  // a NIfTI in RAS read into LPS: i and j run the other way
  g.direction = {-1, 0, 0, 0, -1, 0, 0, 0, 1};
  CHECK(face_name(g, 0, false) == "left");
  CHECK(face_name(g, 1, true) == "anterior");
  // axial slices stored along j (a coronal acquisition): j's last index is superior
  g.direction = {1, 0, 0, 0, 0, 1, 0, 1, 0};
  CHECK(face_name(g, 1, true) == "superior");
  CHECK(face_name(g, 2, false) == "anterior");
}

TEST_CASE("a cropped phantom: the cut faces are named, counted, warned about, and B counts them as skin") {
  // the 3 mm phantom (prone, back at +y), its anterior half cut away: cut at the
  // anterior face, and at the inferior and superior faces as every phantom is
  const PhantomCt ph = make_phantom(3.0);
  const Vec3i n = ph.hu.grid.size;
  const Volume<float> img = crop(ph.hu, {0, n.y / 2, 0}, n);
  const double h = 3.0;

  PrepReport skin;
  const PatientPtr p = build_patient(img, scene_at(h, CutFaces::kSkin), "cropped phantom", &skin);
  INFO(skin.field_of_view.warning);
  REQUIRE(names(skin.field_of_view) == std::vector<std::string>{"anterior", "inferior", "superior"});
  const CutFace& front = skin.field_of_view.faces[0];
  CHECK(front.axis == 1);
  CHECK_FALSE(front.high);
  // the torso (310 mm wide at its centre) spans most of the 340 mm face's width over all its 220 mm
  CHECK(front.face_fraction > 0.7);
  CHECK(front.face_fraction <= 1.0);
  CHECK(front.area_mm2 == Approx(front.body_voxels * h * h));
  CHECK(front.body_fraction > 0.0);
  CHECK(skin.field_of_view.warning ==
        "the body is cut at the anterior, inferior and superior faces: no skin there (prep.cut_faces = \"skin\": "
        "they count as skin)");
  const std::vector<std::string> lines = skin.summary_lines();
  CHECK(std::find(lines.begin(), lines.end(), "warning: " + skin.field_of_view.warning) != lines.end());

  // "skin": every body voxel on a cut face lies one voxel under the skin, as one beside
  // outside air does (the distance between voxel centres is exact, so no tolerance)
  for (const CutFace& f : skin.field_of_view.faces) {
    const auto [lo, hi] = face_depths(*p, f.axis, f.high);
    INFO(f.name);
    CHECK(lo == Approx(h));
    CHECK(hi == Approx(h));
  }

  // "open": the same voxels measure to the air in the image; at the anterior cut, the
  // middle of the body lies more than 60 mm from it (the torso's semi-axes are 155 x 110 mm)
  PrepReport open;
  const PatientPtr q = build_patient(img, scene_at(h, CutFaces::kOpen), "cropped phantom", &open);
  CHECK(names(open.field_of_view) == names(skin.field_of_view));
  CHECK_THAT(open.field_of_view.warning, Catch::Contains("prep.cut_faces = \"open\": left open"));
  CHECK(face_depths(*q, 1, false).second > 60);
  // away from the cut faces (deeper than any of them) both agree
  const Grid& g = p->grid;
  const Vec3 back = g.to_index({0, 100, 0});  // 10 mm under the back's skin, mid-height
  const int i = int(std::lround(back.x)), j = int(std::lround(back.y)), k = int(std::lround(back.z));
  CHECK(p->dist_skin_mm.at(i, j, k) == q->dist_skin_mm.at(i, j, k));
}

TEST_CASE("a cropped CT prepared from the cache warns of its cut faces as its first preparation did") {
  // the 3 mm phantom's posterior half as a NRRD file, prepared twice with the cache on:
  // palpsim-server loads most patients from the cache, so its log must warn there too
  const PhantomCt ph = make_phantom(3.0);
  const Vec3i n = ph.hu.grid.size;
  TempDir d;
  write_volume_nrrd(d / "back.nrrd", crop(ph.hu, {0, n.y / 2, 0}, n));
  Scene s = ct_scene(d / "back.nrrd", d / "cache");
  s.prep.spacing_mm = 3.0;
  const std::string cut = "the body is cut at the anterior, inferior and superior faces";
  for (const bool cached : {false, true}) {
    LogCapture log;
    PrepReport r;
    prepare_patient(s, &r);
    INFO((cached ? "from the cache" : "first preparation"));
    REQUIRE(r.from_cache == cached);
    CHECK_THAT(r.field_of_view.warning, Catch::StartsWith(cut));
    const std::vector<std::string> warned = log.lines_with(cut);
    REQUIRE(warned.size() == 1);
    CHECK_THAT(warned[0], Catch::Contains("back.nrrd") && Catch::Contains("warn"));
  }
}

TEST_CASE("the whole phantom is cut only at its inferior and superior faces; its body mask looks like a body") {
  const PhantomCt ph = make_phantom(3.0);
  PrepReport r;
  build_patient(ph.hu, scene_at(3.0, CutFaces::kSkin), "phantom", &r);
  CHECK(names(r.field_of_view) == std::vector<std::string>{"inferior", "superior"});
  // one piece (the table is not body); an elliptic torso of 155 x 110 mm semi-axes, pi a b = 536 cm^2
  INFO(r.body_check.cross_section_cm2);
  CHECK(r.body_check.pieces == 1);
  CHECK(r.body_check.cross_section_cm2 == Approx(536).epsilon(0.1));  // the skin's partial volume: a few %
  CHECK(r.body_check.warnings.empty());
}

TEST_CASE("a body mask in pieces or of no trunk's size is warned about, naming prep.air_threshold") {
  // an air threshold between fat (-100 HU) and muscle (50 HU): fat and skin fall out,
  // and the muscles, organs and bone fall apart
  const PhantomCt ph = make_phantom(3.0);
  Scene s = scene_at(3.0, CutFaces::kSkin);
  s.prep.air_threshold = 45;
  PrepReport r;
  build_patient(ph.hu, s, "phantom", &r);
  INFO(r.body_check.pieces << " pieces, largest " << r.body_check.largest_fraction);
  REQUIRE(!r.body_check.warnings.empty());
  CHECK_THAT(r.body_check.warnings[0],
             Catch::StartsWith("the body mask falls apart into") && Catch::Contains("prep.air_threshold (45 HU)"));

  // a 4 x 4 cm column of tissue, 100 mm long: 16 cm^2, no trunk
  Grid g;
  g.size = {40, 40, 50};
  g.spacing_mm = {2, 2, 2};
  Volume<std::uint8_t> body(g, 0);
  for (int k = 0; k < 50; ++k)
    for (int j = 10; j < 30; ++j)
      for (int i = 10; i < 30; ++i) body.at(i, j, k) = 1;
  const BodyCheck c = check_body(body, 60, "image units");
  CHECK(c.pieces == 1);
  CHECK(c.cross_section_cm2 == Approx(16));
  REQUIRE(c.warnings.size() == 1);
  CHECK_THAT(c.warnings[0], Catch::Contains("16 cm^2") && Catch::Contains("prep.air_threshold (60 image units)"));
}

TEST_CASE("crops of the shared abdomen: the anterior cut is found and pressed into as skin") {
  const std::string path = shared_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  if (path.empty()) return;
  const CtImage ct = read_ct(path, PrepSettings{});
  const Vec3i n = ct.image.grid.size;
  // the NIfTI's RAS, read as LPS: j runs anteriorly, so its last index is the anterior face
  REQUIRE(face_name(ct.image.grid, 1, true) == "anterior");

  // the whole scan: cut at its first and last slices, and where the flanks touch the
  // image's sides (10% of the left face, 558 mm^2 of the right); the table is not body
  PrepReport whole;
  build_patient(ct.image, scene_at(3.0, CutFaces::kSkin), "abdomen", &whole);
  CHECK(names(whole.field_of_view) == std::vector<std::string>{"left", "right", "inferior", "superior"});

  // the posterior 60 of 101 rows (the back, the spine and the table): cut anteriorly too
  const Volume<float> img = crop(ct.image, {0, 0, 0}, {n.x, 60, n.z});
  PrepReport r;
  const PatientPtr p = build_patient(img, scene_at(3.0, CutFaces::kSkin), "cropped abdomen", &r);
  INFO(r.field_of_view.warning);
  REQUIRE(names(r.field_of_view) == std::vector<std::string>{"left", "right", "anterior", "inferior", "superior"});
  CHECK_THAT(r.field_of_view.warning,
             Catch::StartsWith("the body is cut at the left, right, anterior, inferior and superior faces"));
  CHECK(r.field_of_view.faces[2].face_fraction > 0.5);  // the abdomen fills most of its width, in every slice
  const auto [lo, hi] = face_depths(*p, 1, true);
  CHECK(lo == Approx(3.0));
  CHECK(hi == Approx(3.0));

  PrepReport o;
  const PatientPtr q = build_patient(img, scene_at(3.0, CutFaces::kOpen), "cropped abdomen", &o);
  CHECK(face_depths(*q, 1, true).second > 30);  // the middle of the cut lies deep under the real skin
}

TEST_CASE("landmarks on the phantom: each spinous process tip and iliac crest top, with a press start outside the skin") {
  // the 3 mm phantom, whose tips and crest tops are known in closed form
  const PhantomCt ph = make_phantom(3.0);
  const PatientPtr p = build_patient(ph.hu, scene_at(3.0, CutFaces::kSkin), "phantom");
  const std::vector<SkinLandmark> marks = find_landmarks(*p);
  // a found bone point is the centre of a bone voxel (1.5 mm from its surface) that the
  // 3 mm closing may widen by a voxel: within 4.5 mm of the tip across and along y; along
  // z a process's posterior edge runs nearly flat over 10-20 mm at 3 mm voxels: within
  // 10 mm, under a third of the 34 mm between processes, so it is that process's and no
  // neighbour's
  std::vector<std::string> found_tips;
  for (const PhantomLandmark& l : ph.geometry.landmarks()) {
    // S1's tip (z = -101 mm) lies by the inferior face, where no slice below shows it standing out
    if (l.name.rfind("spinous_tip_", 0) != 0 || l.name == "spinous_tip_S1") continue;
    int hits = 0;
    for (const SkinLandmark& m : marks)
      if (m.name.rfind("spinous process", 0) == 0 && std::abs(m.bone_mm.z - l.p_mm.z) <= 10 &&
          std::abs(m.bone_mm.y - l.p_mm.y) <= 4.5 && std::abs(m.bone_mm.x - l.p_mm.x) <= 4.5)
        ++hits;
    INFO(l.name << " at z " << l.p_mm.z);
    CHECK(hits == 1);
    if (hits) found_tips.push_back(l.name);
  }
  CHECK(found_tips.size() == 6);  // T12 to L5 (S1's tip lies by the volume's inferior face)
  int spinous = 0;
  for (const SkinLandmark& m : marks) {
    INFO(m.name << " bone (" << m.bone_mm.x << ", " << m.bone_mm.y << ", " << m.bone_mm.z << ")");
    spinous += m.name.rfind("spinous process", 0) == 0;
    // the skin point: on the phantom's skin (its signed distance within a voxel of 0), the
    // bone under it by depth_mm, and the press start 10 mm outside it along +y
    CHECK(std::abs(ph.geometry.skin_signed_distance_mm(m.skin_mm)) <= 3.0);
    CHECK(m.depth_mm == Approx(m.skin_mm.y - m.bone_mm.y));
    CHECK(m.press_start_mm.y == Approx(m.skin_mm.y + kPressStandoffMm));
    CHECK(ph.geometry.skin_signed_distance_mm(m.press_start_mm) > 5);
    // the press reaches the bone point and goes kPressBeyondBoneMm past it (the scripted
    // press's default 40 mm stopped 30 mm under the skin, short of the crests at 54 mm)
    const double end_y = m.press_start_mm.y - m.press_travel_mm;
    CHECK(end_y == Approx(m.bone_mm.y - kPressBeyondBoneMm));
    char expected[128];
    std::snprintf(expected, sizeof expected, "press:%.1f,%.1f,%.1f,%.1f", m.press_start_mm.x, m.press_start_mm.y,
                  m.press_start_mm.z, m.press_travel_mm);
    CHECK(press_argument(m) == expected);
  }
  CHECK(spinous == int(found_tips.size()));  // no other peak taken for a tip
  // the crest tops at z = -34 mm, x = +-128 mm: the top slice's centroid lies within
  // 6 mm in z and, the crest being a rim 25 mm wide, within 15 mm in x
  for (const char* side : {"left", "right"}) {
    const Vec3 top = ph.geometry.landmark(std::string("iliac_crest_top_") + side);
    int hits = 0;
    for (const SkinLandmark& m : marks)
      if (m.name == std::string("iliac crest ") + side && std::abs(m.bone_mm.z - top.z) <= 6 &&
          std::abs(m.bone_mm.x - top.x) <= 15)
        ++hits;
    INFO(side);
    CHECK(hits == 1);
  }
}

TEST_CASE("a press into a cut face meets skin at the face with \"skin\", deep under it with \"open\"") {
  // the cropped phantom of above (anterior face at y = -10 mm); a tip moving along +y
  // (anterior to posterior) 60 mm left of the spine, from 5 mm outside the grid to 25 mm in
  const PhantomCt ph = make_phantom(3.0);
  const Vec3i n = ph.hu.grid.size;
  const Volume<float> img = crop(ph.hu, {0, n.y / 2, 0}, n);
  const double face_y = img.grid.origin_mm.y, h = 3.0;
  for (const CutFaces mode : {CutFaces::kSkin, CutFaces::kOpen}) {
    const PatientPtr p = build_patient(img, scene_at(h, mode), "cropped phantom");
    ProxyState state;
    double first = -1, previous = 0;
    bool monotone = true;
    for (double y = face_y - 0.5 * h - 5; y <= face_y + 25; y += 0.25) {
      const ForceSample f = compute_force(*p, HapticsSettings{}, {60, y, 0}, 0.001, state);
      if (!f.contact) continue;
      if (first < 0) first = f.depth_mm;
      monotone = monotone && f.depth_mm >= previous - 1e-6;
      previous = f.depth_mm;
    }
    INFO((mode == CutFaces::kSkin ? "skin" : "open") << ": depth at first contact " << first << " mm, at 25 mm in "
                                                     << previous << " mm");
    REQUIRE(first >= 0);
    if (mode == CutFaces::kSkin) {
      // the grid's face lies half a voxel beyond the face voxels' centres, which the
      // sampling replicates out to it: contact starts there with a skin voxel's depth,
      // B - h/2 = 1.5 mm (1e-9: rounding), and grows with the press (25 mm in: at least
      // 25 - 1.5 mm, the half voxel again)
      CHECK(first <= 0.5 * h + 1e-9);
      CHECK(monotone);
      CHECK(previous >= 25 - 0.5 * h);
    } else {
      // open: the first contact is already deep (the 27.7 mm), the real skin being far
      CHECK(first > 20);
    }
  }
}
