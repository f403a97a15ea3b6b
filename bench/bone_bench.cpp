// palpsim-bench bone: the default bone mask against TotalSegmentator's labels of the
// shared DICOM series (../shared/data/ct/dicom-partial-body), as it comes (2 mm slices)
// and averaged into 4 mm and 6 mm slabs as a thick-slice scanner makes them (its labels
// taken the same way: the label most of a slab's slices hold), and of the shared
// abdomen (3 mm voxels) where the data folder holds its per-structure labels
// (ct/abdomen-lumbar-3mm-labels/, see tests/unit/bone_agreement.h). Per rib recall
// within 3 mm, overall recall and precision, the vertebrae, the spinal cord and the
// discs in the mask, and the preparation's time. Writes one JSON file with the date,
// the machine and the commit (bench/results/bone-*.json).
#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "bench/deform_runs.h"
#include "bench/registry.h"
#include "bench/stats.h"
#include "core/error.h"
#include "prep/ct_io.h"
#include "prep/pipeline.h"
#include "prep/prepare.h"
#include "tests/support/data.h"
#include "tests/unit/bone_agreement.h"
#include "tests/unit/prep_files.h"

namespace palpsim::bench {
namespace {

using Clock = std::chrono::steady_clock;

// one volume's figures
struct BoneCase {
  std::string name;
  double slice_mm = 0;
  double prep_s = 0, bone_mask_s = 0;
  double low_hu = 0, high_hu = 0, thin_seed_hu = 0;
  test::Agreement all, spine;
  std::map<int, test::Agreement> ribs;
  double rib_recall_min = 0, rib_recall_all = 0;
  std::size_t cord = 0, cord_in_bone = 0, disc = 0, disc_in_bone = 0;
  std::size_t disc_soft = 0, disc_soft_in_bone = 0;  // the disc's voxels below test::kDiscSoftHu
  int canal_slices = 0, segments = 0;
  bool spine_found = false;
  double bone_ml = 0;
};

// prepares `image` with the default scene and measures it against the reference that
// `reference` puts on the patient's grid; `discs` are pairs of adjacent vertebrae's ids
template <typename Reference>
BoneCase measure(const std::string& name, double slice_mm, const Volume<float>& image, Reference&& reference,
                 const std::vector<std::pair<int, int>>& discs, int repeats) {
  BoneCase c;
  c.name = name;
  c.slice_mm = slice_mm;
  Scene s = test::ct_scene("", "");
  PatientPtr p;
  PrepReport r;
  std::vector<double> total, bone;
  for (int i = 0; i < repeats; ++i) {
    r = PrepReport{};
    const auto t0 = Clock::now();
    p = build_patient(image, s, name, &r);
    total.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
    for (const auto& [stage, sec] : r.stage_s)
      if (stage == "bone_mask") bone.push_back(sec);
  }
  c.prep_s = spread(total).median;
  c.bone_mask_s = spread(bone).median;
  c.low_hu = r.bone_thresholds.low;
  c.high_hu = r.bone_thresholds.high;
  c.thin_seed_hu = r.bone_thresholds.thin_seed;
  c.spine_found = r.bone_summary.spine_found;
  c.canal_slices = r.bone_summary.column.canal_slices;
  c.segments = r.bone_summary.column.segments;
  c.bone_ml = r.bone_ml;
  const test::LabelReference lr = reference(p->grid);
  c.all = test::agreement(lr.bone, p->bone, lr.cartilage, 3.0);
  c.spine = test::agreement(lr.spine, p->bone, lr.cartilage, 3.0);
  c.ribs = test::recall_per_label(lr.id, p->bone, test::rib_label_ids(), 3.0);
  std::size_t ref = 0, hit = 0;
  c.rib_recall_min = 1;
  for (const auto& [id, a] : c.ribs) {
    if (a.ref == 0) continue;
    ref += a.ref, hit += a.ref_hit;
    c.rib_recall_min = std::min(c.rib_recall_min, a.recall());
  }
  c.rib_recall_all = ref ? double(hit) / double(ref) : 0;
  Volume<std::uint8_t> disc(p->grid, 0);
  for (const auto& [upper, lower] : discs) {
    const Volume<std::uint8_t> d = test::disc_reference(lr.id, upper, lower);
    for (std::size_t i = 0; i < disc.data.size(); ++i) disc.data[i] |= d.data[i];
  }
  for (std::size_t i = 0; i < p->bone.data.size(); ++i) {
    c.cord += lr.id.data[i] == test::kSpinalCordLabel;
    c.cord_in_bone += lr.id.data[i] == test::kSpinalCordLabel && p->bone.data[i];
    c.disc += disc.data[i];
    c.disc_in_bone += disc.data[i] && p->bone.data[i];
    const bool soft = disc.data[i] && p->intensity.data[i] < test::kDiscSoftHu;
    c.disc_soft += soft;
    c.disc_soft_in_bone += soft && p->bone.data[i];
  }
  return c;
}

void print_case(const BoneCase& c) {
  std::printf("%s (%.0f mm slices): prep %.2f s (bone mask %.2f s), thresholds %.0f / %.0f HU (thin seeds %.0f HU), "
              "bone %.0f ml\n",
              c.name.c_str(), c.slice_mm, c.prep_s, c.bone_mask_s, c.low_hu, c.high_hu, c.thin_seed_hu, c.bone_ml);
  std::printf("  bone within 3 mm: recall %.3f, precision %.3f; vertebrae recall %.3f; ribs recall %.3f (lowest %.3f)\n",
              c.all.recall(), c.all.precision(), c.spine.recall(), c.rib_recall_all, c.rib_recall_min);
  std::printf("  spinal cord in the mask %zu of %zu voxels; discs in the mask %zu of %zu (below %.0f HU: %zu of %zu); "
              "canal slices %d, segments %d; spine %s\n",
              c.cord_in_bone, c.cord, c.disc_in_bone, c.disc, double(test::kDiscSoftHu), c.disc_soft_in_bone,
              c.disc_soft, c.canal_slices, c.segments, c.spine_found ? "found" : "not found");
  std::printf("  per rib (recall within 3 mm, labelled voxels):");
  for (const auto& [id, a] : c.ribs)
    if (a.ref) std::printf(" %s %.2f (%zu);", test::label_name(id).c_str(), a.recall(), a.ref);
  std::printf("\n");
}

std::string case_json(const BoneCase& c) {
  std::ostringstream j;
  j << "    {\"case\": " << json_str(c.name) << ", \"slice_mm\": " << json_number(c.slice_mm)
    << ", \"prep_s\": " << json_number(c.prep_s) << ", \"bone_mask_s\": " << json_number(c.bone_mask_s)
    << ", \"low_hu\": " << json_number(c.low_hu) << ", \"seed_hu\": " << json_number(c.high_hu)
    << ", \"thin_seed_hu\": " << json_number(c.thin_seed_hu)
    << ", \"bone_ml\": " << json_number(c.bone_ml) << ", \"recall\": " << json_number(c.all.recall())
    << ", \"precision\": " << json_number(c.all.precision()) << ", \"vertebrae_recall\": " << json_number(c.spine.recall())
    << ", \"rib_recall\": " << json_number(c.rib_recall_all) << ", \"rib_recall_min\": " << json_number(c.rib_recall_min)
    << ", \"cord_voxels\": " << c.cord << ", \"cord_in_bone\": " << c.cord_in_bone << ", \"disc_voxels\": " << c.disc
    << ", \"disc_in_bone\": " << c.disc_in_bone << ", \"disc_soft_voxels\": " << c.disc_soft
    << ", \"disc_soft_in_bone\": " << c.disc_soft_in_bone << ", \"canal_slices\": " << c.canal_slices
    << ", \"segments\": " << c.segments
    << ", \"spine_found\": " << (c.spine_found ? "true" : "false") << ",\n     \"ribs\": {";
  bool first = true;
  for (const auto& [id, a] : c.ribs) {
    if (!a.ref) continue;
    j << (first ? "" : ", ") << json_str(test::label_name(id)) << ": {\"recall\": " << json_number(a.recall())
      << ", \"voxels\": " << a.ref << "}";
    first = false;
  }
  j << "}}";
  return j.str();
}

}  // namespace
}  // namespace palpsim::bench

PALPSIM_BENCH(bone, "the default bone mask against the shared DICOM series' labels at 2 mm and in 4 and 6 mm slabs: "
                    "per rib recall, precision, vertebrae, cord, disc, prep time [--json FILE] [--commit C] [--repeats N]") {
  using namespace palpsim;
  using namespace palpsim::bench;
  std::string json, commit = "unknown";
  int repeats = 3;
  for (int a = 1; a < argc; ++a) {
    const std::string s = argv[a];
    if (s == "--json" && a + 1 < argc) json = argv[++a];
    else if (s == "--commit" && a + 1 < argc) commit = argv[++a];
    else if (s == "--repeats" && a + 1 < argc) repeats = std::max(1, std::atoi(argv[++a]));
    else {
      std::fprintf(stderr, "usage: palpsim-bench bone [--json FILE] [--commit C] [--repeats N]\n");
      return 2;
    }
  }
  const std::string path = test::shared_data_file("ct/dicom-partial-body");
  const std::string labels_path = test::shared_data_file("ct/dicom-partial-body-labels.nii.gz");
  if (path.empty() || labels_path.empty()) return 1;
  const CtImage ct = read_ct(path, PrepSettings{});
  const CtImage labels = read_ct(labels_path, PrepSettings{});
  std::vector<BoneCase> cases;
  const std::vector<std::pair<int, int>> t11_t12 = {{33, 32}};
  for (int n : {1, 2, 3}) {
    const Volume<float> slab = n == 1 ? ct.image : test::average_slabs(ct.image, n);
    const Volume<float> slab_labels = n == 1 ? labels.image : test::majority_slabs(labels.image, n);
    const std::string name = n == 1 ? "dicom 2 mm" : "dicom " + std::to_string(2 * n) + " mm slabs";
    cases.push_back(measure(
        name, slab.grid.spacing_mm.z, slab,
        [&](const Grid& g) { return test::dicom_label_reference(g, slab_labels); }, t11_t12, repeats));
    print_case(cases.back());
  }
  // the abdomen, where its labels are in the data folder
  const std::string abdomen = test::shared_data_file("ct/abdomen-lumbar-3mm.nii.gz");
  const std::string abdomen_labels = test::shared_data_file("ct/abdomen-lumbar-3mm-labels");
  if (!abdomen.empty() && !abdomen_labels.empty()) {
    const CtImage a = read_ct(abdomen, PrepSettings{});
    cases.push_back(measure(
        "abdomen 3 mm", a.image.grid.spacing_mm.z, a.image,
        [&](const Grid& g) { return test::abdomen_label_reference(g, abdomen_labels).labels; },
        {{33, 32}, {32, 31}, {31, 30}, {30, 29}, {29, 28}, {28, 27}}, repeats));
    print_case(cases.back());
  }
  if (json.empty()) return 0;
  std::ofstream o(json);
  if (!o) {
    std::fprintf(stderr, "bone: cannot write %s\n", json.c_str());
    return 1;
  }
  o << json_run_header("bone", "cpu", commit, false) << "\n  \"reference\": \"TotalSegmentator's labels: of "
    << "ct/dicom-partial-body (bone: T11, T12, humeri, ribs 6-12; costal cartilage counts for neither), slabs the "
    << "mean of 2 or 3 consecutive slices and their labels the majority of them; of ct/abdomen-lumbar-3mm.nii.gz "
    << "its per-structure masks (tests/reference_files/example_seg/ of TotalSegmentator at 5de6e4d) in "
    << "ct/abdomen-lumbar-3mm-labels/ (bone: ribs, vertebrae, sacrum, hips, femurs)\",\n  \"discs\": \"voxels "
    << "of no label between two adjacent vertebrae's labels along the axial axis, at most 15 mm apart; "
    << "disc_soft: those below " << test::kDiscSoftHu << " HU (the disc itself; above it mostly end plates and "
    << "bone the labels leave out)\",\n  "
    << "\"tolerance_mm\": 3,\n  \"repeats\": "
    << repeats << ",\n  \"cases\": [\n";
  for (std::size_t i = 0; i < cases.size(); ++i) o << case_json(cases[i]) << (i + 1 < cases.size() ? ",\n" : "\n");
  o << "  ]\n}\n";
  std::printf("wrote %s\n", json.c_str());
  return 0;
}
