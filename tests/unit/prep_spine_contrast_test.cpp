// The vertebral column as prep finds it (a column with vertebrae and a canal, not bone
// behind the body's centre) and contrast-filled chambers and vessels (reported, and
// with prep.contrast = "tissue" left out of the bone mask): on the phantom, the shared
// abdomen, a crop of its anterior organs, and the shared DICOM series against
// TotalSegmentator's labels.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "prep/ct_io.h"
#include "prep/phantom.h"
#include "prep/pipeline.h"
#include "prep/prepare.h"
#include "support/data.h"
#include "unit/bone_agreement.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

Scene scene_at(double spacing_mm) {
  Scene s;
  s.prep.use_cache = false;
  s.prep.spacing_mm = spacing_mm;
  return s;
}

void print_column(const char* what, const BoneSummary& b) {
  const SpineColumn& c = b.column;
  std::printf("%s: spine %s, %.0f mm (z %.0f .. %.0f), %d slices (%d with bone) of %d, %d segments, canal in %d; "
              "spine region in %d slices\n",
              what, c.found ? "found" : "not found", c.length_mm, c.from_mm, c.to_mm, c.slices, c.bone_slices,
              b.body_slices, c.segments, c.canal_slices, b.spine_slices);
}

}  // namespace

TEST_CASE("spine column: the phantom's lumbar spine, with its vertebrae and canal") {
  Scene s = scene_at(0);
  s.use_phantom = true;
  s.phantom_voxel_mm = 2.0;
  PrepReport r;
  prepare_patient(s, &r);
  print_column("phantom 2 mm", r.bone_summary);
  const SpineColumn& c = r.bone_summary.column;
  CHECK(c.found);
  // T12, L1-L5 and the top of S1, which the volume cuts at z = -110 mm; every slice
  // from one end of the volume to the other
  CHECK(c.segments == 7);
  CHECK(c.from_mm == Approx(-110));
  CHECK(c.to_mm == Approx(110));
  // the canal lies between pedicles and laminae over 8 of each level's 34 mm at least
  CHECK(c.canal_slices >= 6 * 4);
  CHECK(std::abs(c.centroid_mm.x) < 1);  // on the midline, by symmetry
  CHECK(r.contrast_regions.empty());     // the phantom's bones all have a cortex
  CHECK_THAT(r.json, Catch::Contains("\"spine\": {\"found\": true, \"from_mm\": -110, \"to_mm\": 110") &&
                         Catch::Contains("\"segments\": 7") && Catch::Contains("\"contrast_regions\": []"));
}

TEST_CASE("spine column: the shared abdomen has one; a slab of its anterior pelvis has none") {
  const std::string path = shared_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  if (path.empty()) return;
  const CtImage ct = read_ct(path, PrepSettings{});
  const Vec3i n = ct.image.grid.size;
  PrepReport whole;
  build_patient(ct.image, scene_at(3.0), "abdomen", &whole);
  print_column("abdomen", whole.bone_summary);
  const SpineColumn& c = whole.bone_summary.column;
  CHECK(c.found);
  // from the sacrum (the scan's inferior slices hold the pelvis, z = 94-145 mm) to its
  // superior end at z = 427 mm; the discs' dips split it into segments (5 on this 3 mm
  // grid, 7 on the default 2 mm one: the shallowest discs' dips blur at 3 mm)
  CHECK(c.to_mm == Approx(427).margin(3));
  CHECK(c.length_mm > 250);
  CHECK(c.segments >= 4);
  CHECK(c.canal_slices >= 20);
  CHECK(whole.bone_summary.warnings.empty());

  // the anterior 46 of 101 rows (bladder, bowel, the pubic bones) of the lowest 14
  // slices: the pubic symphysis lies behind that crop's centre near its midline in 10
  // of its 14 slices, which the old rule (spine-region bone in half the slices) took
  // for a spine; it is 27 mm of one bone, without discs or canal
  PrepReport r;
  build_patient(crop(ct.image, {0, 55, 0}, {n.x, n.y, 14}), scene_at(3.0), "anterior pelvis", &r);
  print_column("anterior pelvis", r.bone_summary);
  const BoneSummary& b = r.bone_summary;
  CHECK(2 * b.spine_slices >= b.body_slices);  // what the old rule saw
  CHECK_FALSE(b.spine_found);
  CHECK(b.column.segments <= 1);
  CHECK(b.column.canal_slices <= 1);
  REQUIRE_FALSE(b.warnings.empty());
  CHECK_THAT(b.warnings[0], Catch::Contains("no spine found") && Catch::Contains("no spinal canal"));
}

TEST_CASE("contrast: the DICOM series' aorta is found, and left out of the bone mask on request; the spine keeps") {
  const std::string path = shared_data_file("ct/dicom-partial-body");
  const std::string labels_path = shared_data_file("ct/dicom-partial-body-labels.nii.gz");
  if (path.empty() || labels_path.empty()) return;
  Scene s = ct_scene(path, "");
  s.prep.use_cache = false;
  PrepReport r;
  const PatientPtr p = prepare_patient(s, &r);
  print_column("DICOM", r.bone_summary);
  Scene t = s;
  t.prep.contrast = ContrastAs::kTissue;
  PrepReport rt;
  const PatientPtr q = prepare_patient(t, &rt);
  const CtImage labels = read_ct(labels_path, PrepSettings{});
  const LabelReference lr = dicom_label_reference(p->grid, labels.image);
  // within 3 mm, as the bone mask's own test (prep_bone_test) measures it
  const Agreement a = agreement(lr.bone, p->bone, lr.cartilage, 3.0), b = agreement(lr.bone, q->bone, lr.cartilage, 3.0);
  const Agreement sa = agreement(lr.spine, p->bone, lr.cartilage, 3.0),
                  sb = agreement(lr.spine, q->bone, lr.cartilage, 3.0);
  double contrast_s = 0;
  for (const auto& [stage, sec] : r.stage_s) contrast_s += stage == "contrast" ? sec : 0;
  std::printf("DICOM: %zu contrast regions, largest %.1f ml at (%.0f, %.0f, %.0f) mm, mean %.0f HU, sd %.0f HU, %.1f ml "
              "of it bone; contrast stage %.2f s of %.2f s; bone %.1f -> %.1f ml; recall %.3f -> %.3f, precision "
              "%.3f -> %.3f, T11-T12 recall %.3f -> %.3f\n",
              r.contrast_regions.size(), r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].volume_ml,
              r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].centroid_mm.x,
              r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].centroid_mm.y,
              r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].centroid_mm.z,
              r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].mean_hu,
              r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].sd_hu,
              r.contrast_regions.empty() ? 0.0 : r.contrast_regions[0].bone_ml, contrast_s, r.total_s, r.bone_ml,
              rt.bone_ml, a.recall(), b.recall(), a.precision(), b.precision(), sa.recall(), sb.recall());

  // one region: the aorta's lumen (TotalSegmentator's label 52), in front of and left of
  // T12, about 25 mm wide over the series' 38 mm: 15-20 ml with its partial-volume rim
  REQUIRE(r.contrast_regions.size() == 1);
  const ContrastRegion& aorta = r.contrast_regions[0];
  CHECK(aorta.volume_ml > 10);
  CHECK(aorta.volume_ml < 25);
  CHECK(aorta.mean_hu > 130);  // contrast, above the liver's 93 HU peak
  {
    const Vec3 c = labels.image.grid.to_index(aorta.centroid_mm);
    CHECK(int(std::lround(labels.image.at(int(std::lround(c.x)), int(std::lround(c.y)), int(std::lround(c.z))))) == 52);
  }
  CHECK(aorta.bone_ml > 0.5);  // the mask took part of it (the wall's calcification grown inwards)
  CHECK(r.contrast_removed_ml == 0);
  CHECK(rt.contrast_removed_ml > 0.5);
  CHECK_THAT(rt.json, Catch::Contains("\"contrast_regions\": [{\"volume_ml\": ") &&
                          Catch::Contains("\"contrast\": \"tissue\""));
  const std::vector<std::string> lines = rt.summary_lines();
  CHECK(std::any_of(lines.begin(), lines.end(), [](const std::string& l) {
    return l.rfind("contrast-filled regions: ", 0) == 0 && l.find("left out of the bone mask") != std::string::npos;
  }));

  // left out: precision rises (no labelled bone lies in the lumen), recall and the
  // spine's recall (vertebral bodies, discs between them, the canal's walls) stay:
  // no labelled voxel is lost beyond the 3 mm tolerance
  CHECK(b.precision() > a.precision());
  CHECK(b.ref_hit == a.ref_hit);
  CHECK(sb.ref_hit == sa.ref_hit);
  CHECK(sb.recall() >= 0.98);  // the bone mask test's bound for T11-T12
  CHECK(rt.bone_summary.spine_found);
}

TEST_CASE("contrast: the shared abdomen's aorta lies in front of the column; left out, the spine keeps its vertebrae") {
  const std::string path = shared_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  if (path.empty()) return;
  const CtImage ct = read_ct(path, PrepSettings{});
  // the default 2 mm grid (the 3 mm input's spacing clamped to 2 mm)
  Scene s = scene_at(2.0);
  PrepReport r, rt;
  build_patient(ct.image, s, "abdomen", &r);
  s.prep.contrast = ContrastAs::kTissue;
  build_patient(ct.image, s, "abdomen", &rt);
  const SpineColumn &c = r.bone_summary.column, &ct_ = rt.bone_summary.column;
  std::printf("abdomen 2 mm: %zu contrast regions; bone %.1f -> %.1f ml (removed %.1f); spine %d -> %d segments, canal "
              "%d -> %d slices\n",
              r.contrast_regions.size(), r.bone_ml, rt.bone_ml, rt.contrast_removed_ml, c.segments, ct_.segments,
              c.canal_slices, ct_.canal_slices);
  // one region: the abdominal aorta in front of L2-L3 (LPS: anterior is -y), on the
  // midline within the aorta's usual 0-20 mm to the left, its lumen 150-170 HU with
  // the scanner's noise, and part of it taken by the hysteresis from the vertebrae
  REQUIRE(r.contrast_regions.size() == 1);
  const ContrastRegion& a = r.contrast_regions[0];
  CHECK(c.centroid_mm.y - a.centroid_mm.y > 20);
  CHECK(c.centroid_mm.y - a.centroid_mm.y < 50);
  CHECK(std::abs(a.centroid_mm.x - c.centroid_mm.x) < 20);
  CHECK(a.mean_hu > 130);
  CHECK(a.mean_hu < 200);
  CHECK(a.sd_hu < kMaxContrastSdHu);
  CHECK(a.bone_ml > 3);
  // left out of the bone mask: that bone goes, the column keeps its extent, vertebrae and canal
  CHECK(rt.contrast_removed_ml > 3);
  CHECK(rt.bone_ml == Approx(r.bone_ml - rt.contrast_removed_ml).margin(0.01));
  CHECK(rt.bone_summary.spine_found);
  CHECK(ct_.segments == c.segments);
  // the canal: holes that the aorta's bone closed against a vertebral body (4 of 61
  // slices measured) go with it; the canal itself stays in at least 90% of the slices
  CHECK(ct_.canal_slices <= c.canal_slices);
  CHECK(ct_.canal_slices >= 0.9 * c.canal_slices);
  CHECK(ct_.length_mm == Approx(c.length_mm));
  CHECK(rt.bone_summary.warnings.empty());
}

TEST_CASE("contrast: an image not in HU is not searched for contrast; prep.contrast \"tissue\" leaves its bone alone") {
  // the shared abdomen as an 8-bit image, value = (HU + 1000) / 8 (air 0, soft tissue
  // about 130, the bone threshold 200 HU at 150), prepared with both thresholds in its
  // units, as palpsim-prep --air-threshold 75 --bone-threshold 150 would. The regions'
  // limits are in HU (a spread of 50 HU is 6 of these units): here every smooth bright
  // part passed them and "tissue" took most of the bone away (1683 -> 186 ml at 3 mm)
  const std::string path = shared_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  if (path.empty()) return;
  const CtImage ct = read_ct(path, PrepSettings{});
  Volume<float> u8 = ct.image;
  for (float& v : u8.data) v = std::round(std::clamp((v + 1000.0f) / 8.0f, 0.0f, 255.0f));
  Scene s = scene_at(3.0);
  s.prep.air_threshold = 75, s.prep.air_threshold_set = true;
  s.prep.bone_threshold = 150, s.prep.bone_threshold_set = true;
  PrepReport r, rt;
  r.units = rt.units = "image units";  // what prepare_patient finds for an 8-bit file
  const PatientPtr p = build_patient(u8, s, "abdomen 8-bit", &r);
  s.prep.contrast = ContrastAs::kTissue;
  const PatientPtr q = build_patient(u8, s, "abdomen 8-bit", &rt);
  std::printf("abdomen 8-bit 3 mm: %zu / %zu contrast regions, bone %.1f / %.1f ml\n", r.contrast_regions.size(),
              rt.contrast_regions.size(), r.bone_ml, rt.bone_ml);
  CHECK(r.contrast_regions.empty());
  CHECK(rt.contrast_regions.empty());
  CHECK(rt.contrast_removed_ml == 0);
  CHECK(rt.bone_ml == r.bone_ml);
  CHECK((q->bone.data == p->bone.data));  // the same mask, voxel for voxel
  CHECK(rt.bone_summary.spine_found);
  // the scene asked for something not done: said so, naming the setting
  REQUIRE_FALSE(rt.bone_summary.warnings.empty());
  CHECK_THAT(rt.bone_summary.warnings.back(), Catch::Contains("prep.contrast") && Catch::Contains("image units"));
  CHECK(r.bone_summary.warnings.empty());
}
