// The bone mask with no tuning: automatic thresholds from the body's histogram,
// hysteresis, the fill of vertebral bodies, the report (thresholds, volume per
// region, warnings); measured against TotalSegmentator's labels of the shared
// DICOM series and against the phantom's closed-form bones.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <tuple>
#include <cstdio>
#include <random>
#include <set>

#include "core/error.h"
#include "prep/ct_io.h"
#include "prep/distance.h"
#include "prep/phantom.h"
#include "prep/pipeline.h"
#include "prep/prepare.h"
#include "support/data.h"
#include "unit/bone_agreement.h"
#include "unit/prep_files.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

Grid cube_grid(Vec3i size, double mm) {
  Grid g;
  g.size = size;
  g.spacing_mm = {mm, mm, mm};
  return g;
}

// soft tissue at 40 HU with Gaussian noise of `sigma` HU (fixed seed), body everywhere
Volume<float> noisy_tissue(const Grid& g, double sigma) {
  Volume<float> v(g);
  std::mt19937 rng(7);
  std::normal_distribution<float> noise(40.0f, float(sigma));
  for (float& x : v.data) x = noise(rng);
  return v;
}

}  // namespace

TEST_CASE("automatic thresholds follow the soft-tissue peak; an explicit threshold wins") {
  const Grid g = cube_grid({40, 40, 40}, 1.0);
  const Volume<std::uint8_t> body(g, 1);
  // quiet tissue (40 +- 10 HU): low = 40 + 100 HU, seeds at 300 HU
  {
    const Volume<float> v = noisy_tissue(g, 10);
    const BoneThresholds t = choose_bone_thresholds(v, body, PrepSettings{});
    CHECK(t.automatic);
    // the histogram's peak (1 HU bins, 21 HU box) within 5 HU of the true mean
    CHECK(t.soft_tissue_hu == Approx(40).margin(5));
    // the spread from the half width within 30% (the box smoothing widens it a little)
    CHECK(t.soft_tissue_sigma_hu == Approx(10).epsilon(0.3));
    CHECK(t.low == Approx(t.soft_tissue_hu + 100));
    CHECK(t.high == kAutoBoneSeedMinHu);
    CHECK(t.grow_mm == kAutoBoneGrowMm);
    CHECK(t.cancellous > t.soft_tissue_hu);
    CHECK(t.cancellous < t.low);
  }
  // noisier tissue (40 +- 40 HU): 3 sigma above the peak (sigma within 15%)
  {
    const Volume<float> v = noisy_tissue(g, 40);
    const BoneThresholds t = choose_bone_thresholds(v, body, PrepSettings{});
    CHECK(t.soft_tissue_sigma_hu == Approx(40).epsilon(0.15));
    CHECK(t.low == Approx(t.soft_tissue_hu + 3 * t.soft_tissue_sigma_hu));
    CHECK(t.high == Approx(std::max(kAutoBoneSeedMinHu, t.soft_tissue_hu + 2 * (t.low - t.soft_tissue_hu))));
  }
  // very noisy tissue (40 +- 60 HU): capped at kAutoBoneLowMaxHu
  {
    const BoneThresholds t = choose_bone_thresholds(noisy_tissue(g, 60), body, PrepSettings{});
    CHECK(t.low == kAutoBoneLowMaxHu);
  }
  // an explicit threshold: a plain threshold at that value, the old cancellous level
  {
    PrepSettings prep;
    prep.bone_threshold = 250, prep.bone_threshold_set = true;
    const BoneThresholds t = choose_bone_thresholds(noisy_tissue(g, 10), body, prep);
    CHECK_FALSE(t.automatic);
    CHECK(t.low == 250);
    CHECK(t.high == 250);
    CHECK(t.cancellous == Approx(cancellous_level(prep)));
    CHECK_THAT(t.reason, Catch::Contains("prep.bone_threshold"));
  }
  // no soft tissue at all: the default as a plain threshold, said so
  {
    const Volume<float> v(g, -200.0f);
    const BoneThresholds t = choose_bone_thresholds(v, body, PrepSettings{});
    CHECK(t.low == PrepSettings{}.bone_threshold);
    CHECK(t.low == t.high);
    CHECK_THAT(t.reason, Catch::Contains("no soft-tissue peak"));
  }
  // an empty body is an error that says so
  CHECK_THROWS_WITH(choose_bone_thresholds(noisy_tissue(g, 10), Volume<std::uint8_t>(g, 0), PrepSettings{}),
                    Catch::Contains("body mask is empty"));
}

TEST_CASE("hysteresis: a 150 HU bone joined to cortex is bone, a 150 HU organ apart is not, a vessel stops at grow_mm") {
  const Grid g = cube_grid({90, 60, 40}, 1.0);
  Volume<float> v(g, 40.0f);
  const Volume<std::uint8_t> body(g, 1);
  for (int k = 0; k < 40; ++k)
    for (int j = 0; j < 60; ++j)
      for (int i = 0; i < 90; ++i) {
        // a bone: a 150 HU block, cortex (900 HU) on its lower face only (a broken shell)
        if (i >= 5 && i < 25 && j >= 20 && j < 36 && k >= 10 && k < 30) v.at(i, j, k) = j < 22 ? 900.0f : 150.0f;
        // an organ of 150 HU (a kidney), 2.4 ml, touching nothing
        if (i >= 35 && i < 50 && j >= 20 && j < 40 && k >= 10 && k < 18) v.at(i, j, k) = 150.0f;
        // a contrast-filled vessel (250 HU) along i, touching a cortical plate at i = 60..62
        if (j >= 25 && j < 33 && k >= 16 && k < 24 && i >= 60) v.at(i, j, k) = i < 63 ? 900.0f : 250.0f;
      }
  const BoneThresholds t = choose_bone_thresholds(v, body, PrepSettings{});
  REQUIRE(t.automatic);
  REQUIRE(t.low < 150);
  REQUIRE(t.high > 250);
  const auto bone = bone_mask(v, body, t, PrepSettings{}, 0);
  CHECK(bone.at(15, 30, 20) == 1);   // the bone's interior, up to 14 mm from its cortex
  CHECK(bone.at(15, 35, 20) == 1);
  CHECK(bone.at(15, 37, 20) == 0);   // tissue beyond it
  CHECK(bone.at(42, 30, 14) == 0);   // the organ
  CHECK(bone.at(64, 29, 20) == 1);   // the vessel next to the plate (within grow_mm) ...
  // ... but not beyond grow_mm plus the closing's reach from the plate (i = 62)
  const int far_i = 62 + int(std::ceil(kAutoBoneGrowMm + PrepSettings{}.bone_closing_mm)) + 1;
  for (int i = far_i; i < 90; ++i) {
    INFO("vessel voxel i = " << i);
    CHECK(bone.at(i, 29, 20) == 0);
  }
  // a plain threshold at 200 HU (an explicit scene value) keeps only the cortex and the vessel
  PrepSettings plain;
  plain.bone_threshold = 200, plain.bone_threshold_set = true, plain.bone_fill_holes = false;
  const auto old = bone_mask(v, body, plain, 0);
  CHECK(old.at(15, 30, 20) == 0);
  CHECK(old.at(80, 29, 20) == 1);
}

namespace {

// a synthetic lumbar column in a 200 x 160 mm body of 2 mm voxels and `slices` slices
// (+x the patient's left, +y posterior; body centroid x = 99, y = 79 mm): vertebral
// bodies 20 x 20 mm, 24 mm tall, between 8 mm discs, each with a ring of posterior
// elements around an 8 x 8 mm canal over its upper 12 mm
void add_column(Volume<std::uint8_t>& bone, int slices) {
  for (int k = 0; k < slices; ++k) {
    const int level = k % 16;  // 12 slices of vertebra, then 4 of disc
    if (level >= 12) continue;
    for (int j = 50; j < 60; ++j)
      for (int i = 45; i < 55; ++i) bone.at(i, j, k) = 1;
    if (level < 6) continue;
    for (int j = 60; j < 68; ++j)
      for (int i = 44; i < 56; ++i)
        if (j >= 66 || i < 46 || i >= 54) bone.at(i, j, k) = 1;
  }
}

}  // namespace

TEST_CASE("bone summary: volume per region, a missing spine and too much bone are warned about") {
  const Grid g = cube_grid({100, 80, 60}, 2.0);
  Volume<std::uint8_t> body(g, 1), bone(g, 0);
  add_column(bone, 60);
  // a rib at x = 170 mm (left), one at x = 20 mm (right), a sternum anterior (y = 10 mm)
  for (int k = 0; k < 60; ++k) {
    for (int j = 40; j < 45; ++j) bone.at(85, j, k) = 1, bone.at(10, j, k) = 1;
    for (int i = 48; i < 52; ++i) bone.at(i, 5, k) = 1;
  }
  const double voxel_ml = 8.0 / 1000.0;
  const std::size_t column_voxels = count_nonzero(bone) - (5 + 5 + 4) * 60;
  BoneSummary s = summarize_bone(body, bone);
  CHECK(s.body_slices == 60);
  CHECK(s.spine_ml == Approx(double(column_voxels) * voxel_ml));
  CHECK(s.left_ml == Approx(5 * 60 * voxel_ml));
  CHECK(s.right_ml == Approx(5 * 60 * voxel_ml));
  CHECK(s.anterior_ml == Approx(4 * 60 * voxel_ml));
  CHECK(s.bone_ml == Approx(s.spine_ml + s.left_ml + s.right_ml + s.anterior_ml));
  // the column: 4 vertebrae (60 slices = 3 whole levels of 16 and 12 slices of a fourth),
  // the canal in the upper half of each (6 slices each), from the first to the last bone slice
  CHECK(s.spine_found);
  CHECK(s.column.found);
  CHECK(s.column.segments == 4);
  CHECK(s.column.canal_slices == 24);
  CHECK(s.column.slices == 60);
  CHECK(s.column.length_mm == Approx(59 * 2.0));
  CHECK(s.column.centroid_mm.x == Approx(99).margin(1));
  CHECK(s.warnings.empty());

  // the spine in only 24 of 60 slices: warned
  for (int k = 24; k < 60; ++k)
    for (int j = 50; j < 68; ++j)
      for (int i = 44; i < 56; ++i) bone.at(i, j, k) = 0;
  s = summarize_bone(body, bone);
  CHECK_FALSE(s.spine_found);
  REQUIRE(s.warnings.size() == 1);
  CHECK_THAT(s.warnings[0], Catch::Contains("no spine found") && Catch::Contains("24 of 60") &&
                                Catch::Contains("shorter than half the body"));

  // bone in 30% of the body: warned too
  for (int k = 0; k < 60; ++k)
    for (int j = 0; j < 24; ++j)
      for (int i = 0; i < 100; ++i) bone.at(i, j, k) = 1;
  s = summarize_bone(body, bone);
  CHECK(s.bone_fraction > kMaxBoneFraction);
  CHECK_THAT(s.warnings.back(), Catch::Contains("% of the body"));

  // no bone at all: one warning, no other
  s = summarize_bone(body, Volume<std::uint8_t>(g, 0));
  REQUIRE(s.warnings.size() == 1);
  CHECK_THAT(s.warnings[0], Catch::Contains("no bone found"));
}

TEST_CASE("bone summary: a bright tube behind the centre, without canal or without vertebrae, is no spine") {
  // a contrast-filled aorta or heart taken as bone: a solid 20 mm tube at the spine's
  // place through every slice, as long as the body, without gaps and without a canal
  const Grid g = cube_grid({100, 80, 60}, 2.0);
  Volume<std::uint8_t> body(g, 1), bone(g, 0);
  for (int k = 0; k < 60; ++k)
    for (int j = 50; j < 60; ++j)
      for (int i = 45; i < 55; ++i) bone.at(i, j, k) = 1;
  const BoneSummary s = summarize_bone(body, bone);
  CHECK(s.spine_slices == 60);  // the spine region holds bone in every slice
  CHECK_FALSE(s.spine_found);
  CHECK(s.column.slices == 60);
  CHECK(s.column.segments == 1);
  CHECK(s.column.canal_slices == 0);
  REQUIRE(s.warnings.size() == 1);
  CHECK_THAT(s.warnings[0], Catch::Contains("no spine found") && Catch::Contains("no spinal canal"));

  // the same tube with a ring around a canal behind it in every slice: a canal, but
  // 118 mm without a disc's dip is no column of vertebrae
  for (int k = 0; k < 60; ++k)
    for (int j = 60; j < 68; ++j)
      for (int i = 44; i < 56; ++i)
        if (j >= 66 || i < 46 || i >= 54) bone.at(i, j, k) = 1;
  const BoneSummary t = summarize_bone(body, bone);
  CHECK(t.column.canal_slices == 60);
  CHECK(t.column.segments == 1);
  CHECK_FALSE(t.spine_found);
  REQUIRE(t.warnings.size() == 1);
  CHECK_THAT(t.warnings[0], Catch::Contains("no spine found") && Catch::Contains("no vertebrae"));
}

TEST_CASE("the phantom with automatic thresholds: between discs and vertebral bodies, spine found, volumes per region") {
  Scene s;
  s.use_phantom = true;
  s.phantom_voxel_mm = 2.0;
  s.prep.use_cache = false;
  PrepReport r;
  const PatientPtr p = prepare_patient(s, &r);
  const BoneThresholds& t = r.bone_thresholds;
  CHECK(t.automatic);
  // the soft tissue of the phantom is viscera and muscle (30 and 50 HU, +-10 HU texture)
  CHECK(t.soft_tissue_hu >= 20);
  CHECK(t.soft_tissue_hu <= 60);
  // low above discs (80 HU + texture), below the vertebral bodies' cancellous bone (180 HU - texture)
  CHECK(t.low > phantom_hu::kDisc + phantom_hu::kTextureAmplitude);
  CHECK(t.low < phantom_hu::kCancellousVertebra - phantom_hu::kTextureAmplitude);
  // seeds: cortex (1000 HU) and the other bones' cancellous bone (300 HU)
  CHECK(t.high <= phantom_hu::kCancellous);
  CHECK(r.bone_summary.spine_found);
  CHECK(r.bone_summary.warnings.empty());
  CHECK_THAT(r.json, Catch::Contains("\"thresholds\": {\"automatic\": true") && Catch::Contains("\"regions_ml\"") &&
                         Catch::Contains("\"warnings\": []"));

  // the closed form's bone per region (voxel centres inside bone, the same regions):
  // the mask adds the partial-volume rim (up to 0.35 voxel outside each surface) and
  // the closing's bridges, and the thin ribs and processes are a few voxels thick at
  // 2 mm, so each region's mask volume lies within 0.9 to 1.6 times the exact one
  const PhantomGeometry geo;
  const Grid& g = p->grid;
  Volume<std::uint8_t> exact(g, 0);
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i)
        exact.at(i, j, k) = p->body.at(i, j, k) &&
                            geo.bone_signed_distance_mm(g.to_physical({double(i), double(j), double(k)})) < 0;
  const BoneSummary e = summarize_bone(p->body, exact);
  const BoneSummary& m = r.bone_summary;
  std::printf("phantom 2 mm bone per region (mask / closed form, ml): spine %.0f / %.0f, left %.0f / %.0f, right %.0f / "
              "%.0f, anterior %.0f / %.0f; thresholds %.0f / %.0f HU\n",
              m.spine_ml, e.spine_ml, m.left_ml, e.left_ml, m.right_ml, e.right_ml, m.anterior_ml, e.anterior_ml,
              t.low, t.high);
  for (auto [name, got, want] : {std::tuple<const char*, double, double>{"spine", m.spine_ml, e.spine_ml},
                                 {"left", m.left_ml, e.left_ml},
                                 {"right", m.right_ml, e.right_ml}}) {
    INFO(name << ": mask " << got << " ml, closed form " << want << " ml");
    CHECK(want > 10);
    CHECK(got >= 0.9 * want);
    CHECK(got <= 1.6 * want);
  }
}

TEST_CASE("DICOM series: the automatic bone mask against TotalSegmentator's labels, within 3 mm") {
  const std::string path = shared_data_file("ct/dicom-partial-body");
  const std::string labels_path = shared_data_file("ct/dicom-partial-body-labels.nii.gz");
  if (path.empty() || labels_path.empty()) return;
  Scene s = ct_scene(path, "");
  PrepReport r;
  const PatientPtr p = prepare_patient(s, &r);
  const CtImage labels = read_ct(labels_path, PrepSettings{});
  REQUIRE(labels.image.grid.size == Vec3i{512, 512, 20});

  const LabelReference lr = dicom_label_reference(p->grid, labels.image);
  const Volume<std::uint8_t>&ref = lr.bone, &cartilage = lr.cartilage, &spine_ref = lr.spine;
  REQUIRE(count_nonzero(ref) > 10000);

  // within 3 mm (the tolerance): TotalSegmentator's outlines are drawn on
  // 2 mm slices and differ from a threshold's by 1-2 mm at thin cortices; the
  // mask's closing adds up to its 3 mm radius between close bones
  const Agreement a = agreement(ref, p->bone, cartilage, 3.0);
  // the old default for comparison: a plain 200 HU threshold
  Scene plain = s;
  plain.prep.bone_threshold = 200, plain.prep.bone_threshold_set = true;
  const PatientPtr p200 = prepare_patient(plain);
  const Agreement a200 = agreement(ref, p200->bone, cartilage, 3.0);
  const Agreement sp = agreement(spine_ref, p->bone, cartilage, 3.0);
  std::printf("DICOM series, automatic (%.0f / %.0f HU): recall %.3f (%zu of %zu), precision %.3f (%zu of %zu); "
              "T11-T12 recall %.3f; bone %.0f ml; plain 200 HU: recall %.3f, precision %.3f\n",
              r.bone_thresholds.low, r.bone_thresholds.high, a.recall(), a.ref_hit, a.ref, a.precision(), a.pred_hit,
              a.pred, sp.recall(), r.bone_ml, a200.recall(), a200.precision());
  CHECK(r.bone_thresholds.automatic);
  // recall: nearly every labelled bone voxel (ribs, vertebrae, humeri) is within 3 mm
  // of the mask (0.997 measured); 3% allows for the thinnest rib ends and the fatty
  // marrow of the humeri, which partial volume on 2 mm slices pulls below any
  // threshold above muscle
  CHECK(a.recall() >= 0.97);
  // the vertebral bodies T11-T12, cancellous interior included, are bone throughout
  // (0.998 measured; 2% for the labels' own outline on 2 mm slices)
  CHECK(sp.recall() >= 0.98);
  // precision: the mask's voxels within 3 mm of labelled bone (0.918 measured, the
  // plain 200 HU threshold 0.91). The rest, looked at slice by slice: the calcified
  // wall of the aorta (rigid, above any bone threshold), the end plates and the parts
  // of the T11-T12 and T12-L1 discs that this series' thick slices blend with them to
  // 140-160 HU (the disc's soft voxels stay open: kDiscBandBelow), and bone the labels
  // leave out (the xiphoid, rib heads). The contrast-filled aorta's lumen (150 HU,
  // 22 ml) alone would cost 0.1, so 0.88 still says that no vessel, organ or
  // whole disc came in
  CHECK(a.precision() >= 0.88);
  CHECK(r.bone_summary.spine_found);
  CHECK(r.bone_summary.warnings.empty());
}

TEST_CASE("abdomen CT with no tuning: vertebral bodies, spinous processes and ribs, no warnings") {
  const std::string path = shared_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  if (path.empty()) return;
  // config/scenes/lumbar_ct.textproto without its bone_threshold: 1.5 mm, automatic
  Scene s = ct_scene(path, "");
  s.prep.spacing_mm = 1.5;
  PrepReport r;
  const PatientPtr p = prepare_patient(s, &r);
  const CtImage ct = read_ct(path, s.prep);
  const Grid& g = ct.image.grid;
  const auto bone_at = [&](int i, int j, int k) {
    const Vec3 c = p->grid.to_index(g.to_physical(Vec3{double(i), double(j), double(k)}));
    return p->bone.at(int(std::lround(c.x)), int(std::lround(c.y)), int(std::lround(c.z)));
  };
  std::printf("abdomen CT, automatic: low %.0f HU, seeds %.0f HU, cavities %.0f HU; bone %.0f ml (spine %.0f ml)\n",
              r.bone_thresholds.low, r.bone_thresholds.high, r.bone_thresholds.cancellous, r.bone_ml,
              r.bone_summary.spine_ml);
  CHECK(r.bone_thresholds.automatic);
  // the vertebral body prep_real_ct_test checks with the scene's 180 HU (100-160 HU
  // interior, below that threshold) is bone
  for (int i : {57, 60, 63})
    for (int j : {32, 35}) {
      INFO("vertebral body at input voxel " << i << "," << j << ",100");
      CHECK(bone_at(i, j, 100) == 1);
    }
  // the spinal canal behind it (CSF, below 100 HU) is not; its centre is the input's
  // row j = 28 (j = 26 is the lamina's partial-volume edge)
  for (int i : {58, 60, 62}) {
    INFO("spinal canal at input voxel " << i << ",28,100");
    CHECK(ct.image.at(i, 28, 100) < 100);
    CHECK(bone_at(i, 28, 100) == 0);
  }
  // every spinous process voxel >= 250 HU (the box prep_real_ct_test uses) is bone
  std::size_t spinous = 0, spinous_bone = 0;
  for (int k = 40; k <= 105; ++k)
    for (int j = 8; j <= 21; ++j)
      for (int i = 56; i <= 66; ++i)
        if (ct.image.at(i, j, k) >= 250) ++spinous, spinous_bone += bone_at(i, j, k);
  CHECK(spinous > 100);
  CHECK(spinous_bone == spinous);
  CHECK(r.bone_summary.spine_found);
  CHECK(r.bone_summary.warnings.empty());
  CHECK(r.bone_ml > 500);
  CHECK(r.bone_ml < 3000);
}
