// palpsim-bench bone: the default bone mask against TotalSegmentator's labels of the
// shared DICOM series (../shared/data/ct/dicom-partial-body), as it comes (2 mm slices)
// and averaged into 4 mm and 6 mm slabs as a thick-slice scanner makes them (its labels
// taken the same way: the label most of a slab's slices hold), and of the shared
// abdomen (3 mm voxels) where the data folder holds its per-structure labels
// (ct/abdomen-lumbar-3mm-labels/, see tests/unit/bone_agreement.h). Per rib recall
// within 3 mm, overall recall and precision, the vertebrae, the spinal cord and the
// discs in the mask, the precision's misses (what the mask holds more than 3 mm from
// labelled bone: by the reference's label there, and the largest connected parts, with an
// optional picture of three slices of the 2 mm series), and the preparation's time. Writes
// one JSON file with the date, the machine and the commit (bench/results/bone-*.json).
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <map>
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
#include "prep/distance.h"
#include "prep/outputs.h"
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
  // the precision's misses: mask voxels (cartilage left out) more than 3 mm from labelled
  // bone, by the reference's label there, and their largest 26-connected parts
  std::size_t misses = 0;
  std::map<int, std::size_t> misses_by_label;
  struct Part {
    std::size_t voxels = 0;
    double ml = 0, mean_hu = 0;
    Vec3 centre_mm{0, 0, 0};  // LPS
    int label = 0;            // the reference's label most of its voxels lie in
  };
  std::vector<Part> miss_parts;
};

// the largest 26-connected parts (at most `most`) of `m` (0/1), with their sizes, centres,
// mean intensity and the label of `ids` most of each lies in
std::vector<BoneCase::Part> largest_parts(const Volume<std::uint8_t>& m, const Volume<float>& hu,
                                          const Volume<std::uint8_t>& ids, std::size_t most) {
  const Grid& g = m.grid;
  std::vector<std::uint8_t> seen(m.data.size(), 0);
  std::vector<BoneCase::Part> parts;
  std::vector<Vec3i> stack;
  const double voxel_ml = g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z / 1000.0;
  for (int k = 0; k < g.size.z; ++k)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i) {
        if (!m.at(i, j, k) || seen[g.index(i, j, k)]) continue;
        BoneCase::Part part;
        Vec3 sum{0, 0, 0};
        std::map<int, std::size_t> labels;
        seen[g.index(i, j, k)] = 1;
        stack.assign(1, Vec3i{i, j, k});
        while (!stack.empty()) {
          const Vec3i v = stack.back();
          stack.pop_back();
          ++part.voxels;
          sum = sum + Vec3{double(v.x), double(v.y), double(v.z)};
          part.mean_hu += hu.at(v.x, v.y, v.z);
          ++labels[ids.at(v.x, v.y, v.z)];
          for (int dz = -1; dz <= 1; ++dz)
            for (int dy = -1; dy <= 1; ++dy)
              for (int dx = -1; dx <= 1; ++dx) {
                const int a = v.x + dx, b = v.y + dy, c = v.z + dz;
                if (!g.contains(a, b, c) || !m.at(a, b, c) || seen[g.index(a, b, c)]) continue;
                seen[g.index(a, b, c)] = 1;
                stack.push_back(Vec3i{a, b, c});
              }
        }
        const double n = double(part.voxels);
        part.ml = n * voxel_ml;
        part.mean_hu /= n;
        part.centre_mm = g.to_physical(sum * (1.0 / n));
        part.label = std::max_element(labels.begin(), labels.end(), [](const auto& x, const auto& y) {
                       return x.second < y.second;
                     })->first;
        parts.push_back(part);
      }
  std::sort(parts.begin(), parts.end(), [](const auto& x, const auto& y) { return x.voxels > y.voxels; });
  if (parts.size() > most) parts.resize(most);
  return parts;
}

// three axial slices (a sixth, half and five sixths up the volume) of the 2 mm series,
// cropped to the body: the image in grey (-200 to 600 HU), the mask in green, its misses in red, the labelled
// bone's outline in cyan and the costal cartilage's in yellow; patient's right on the
// left, anterior up
void write_misses_png(const std::string& path, const Patient& p, const test::LabelReference& lr,
                      const Volume<std::uint8_t>& miss) {
  const Grid& g = p.grid;
  int slice[3];
  for (int s = 0; s < 3; ++s) slice[s] = std::clamp(int(std::lround((2 * s + 1) * (g.size.z - 1) / 6.0)), 0, g.size.z - 1);
  // the body's box in the three slices, 4 voxels around it
  int i0 = g.size.x, i1 = -1, j0 = g.size.y, j1 = -1;
  for (int s = 0; s < 3; ++s)
    for (int j = 0; j < g.size.y; ++j)
      for (int i = 0; i < g.size.x; ++i)
        if (p.body.at(i, j, slice[s])) i0 = std::min(i0, i), i1 = std::max(i1, i), j0 = std::min(j0, j), j1 = std::max(j1, j);
  if (i1 < 0) i0 = 0, i1 = g.size.x - 1, j0 = 0, j1 = g.size.y - 1;
  i0 = std::max(0, i0 - 4), j0 = std::max(0, j0 - 4), i1 = std::min(g.size.x - 1, i1 + 4), j1 = std::min(g.size.y - 1, j1 + 4);
  const int w = i1 - i0 + 1, h = j1 - j0 + 1;
  std::vector<std::array<std::uint8_t, 3>> img(std::size_t(3 * w) * h);
  auto edge = [&](const Volume<std::uint8_t>& v, int i, int j, int k) {
    if (!v.at(i, j, k)) return false;
    return (i == 0 || !v.at(i - 1, j, k)) || (i + 1 == g.size.x || !v.at(i + 1, j, k)) || (j == 0 || !v.at(i, j - 1, k)) ||
           (j + 1 == g.size.y || !v.at(i, j + 1, k));
  };
  for (int s = 0; s < 3; ++s) {
    const int k = slice[s];
    for (int j = j0; j <= j1; ++j)
      for (int i = i0; i <= i1; ++i) {
        const double grey = std::clamp((p.intensity.at(i, j, k) + 200.0) / 800.0, 0.0, 1.0) * 255.0;
        std::array<double, 3> c{grey, grey, grey};
        auto blend = [&](std::array<double, 3> col, double a) {
          for (int q = 0; q < 3; ++q) c[q] = (1 - a) * c[q] + a * col[q];
        };
        if (miss.at(i, j, k)) blend({255, 0, 0}, 0.7);
        else if (p.bone.at(i, j, k)) blend({0, 255, 0}, 0.35);
        if (edge(lr.bone, i, j, k)) c = {0, 255, 255};
        if (edge(lr.cartilage, i, j, k)) c = {255, 255, 0};
        std::array<std::uint8_t, 3>& px = img[std::size_t(j - j0) * 3 * w + std::size_t(s) * w + (i - i0)];
        for (int q = 0; q < 3; ++q) px[q] = std::uint8_t(std::lround(c[q]));
      }
  }
  write_rgb_png(path, img, 3 * w, h, 1);
}

// prepares `image` with the default scene and measures it against the reference that
// `reference` puts on the patient's grid; `discs` are pairs of adjacent vertebrae's ids
template <typename Reference>
BoneCase measure(const std::string& name, double slice_mm, const Volume<float>& image, Reference&& reference,
                 const std::vector<std::pair<int, int>>& discs, int repeats, const std::string& misses_png = "") {
  BoneCase c;
  c.name = name;
  c.slice_mm = slice_mm;
  Scene s = test::ct_scene("", "");
  PatientPtr p;
  PrepReport r;
  std::vector<double> total, bone;
  for (int i = 0; i < repeats; ++i) {
    PrepReport run;
    const auto t0 = Clock::now();
    p = build_patient(image, s, name, &run);
    total.push_back(std::chrono::duration<double>(Clock::now() - t0).count());
    for (const auto& [stage, sec] : run.stage_s)
      if (stage == "bone_mask") bone.push_back(sec);
    r = std::move(run);
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
  // the precision's misses, as test::agreement counts them
  Volume<std::uint8_t> ref_or_cartilage = lr.bone, miss(p->grid, 0);
  for (std::size_t i = 0; i < ref_or_cartilage.data.size(); ++i) ref_or_cartilage.data[i] |= lr.cartilage.data[i];
  const Volume<float> to_ref = distance_to_mask_mm(ref_or_cartilage);
  for (std::size_t i = 0; i < miss.data.size(); ++i) {
    if (!p->bone.data[i] || lr.cartilage.data[i] || to_ref.data[i] <= 3.0f) continue;
    miss.data[i] = 1;
    ++c.misses;
    ++c.misses_by_label[lr.id.data[i]];
  }
  c.miss_parts = largest_parts(miss, p->intensity, lr.id, 8);
  if (!misses_png.empty()) write_misses_png(misses_png, *p, lr, miss);
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
  std::printf("  precision's misses (mask voxels more than 3 mm from labelled bone) %zu:", c.misses);
  for (const auto& [id, n] : c.misses_by_label) std::printf(" %s %zu;", test::label_name(id).c_str(), n);
  std::printf("\n  their largest parts:");
  for (const auto& m : c.miss_parts)
    std::printf(" %.1f ml at (%.0f, %.0f, %.0f) mm, %.0f HU, %s;", m.ml, m.centre_mm.x, m.centre_mm.y, m.centre_mm.z,
                m.mean_hu, test::label_name(m.label).c_str());
  std::printf("\n");
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
    << ", \"spine_found\": " << (c.spine_found ? "true" : "false") << ",\n     \"misses\": " << c.misses
    << ", \"misses_by_label\": {";
  bool first_label = true;
  for (const auto& [id, n] : c.misses_by_label) {
    j << (first_label ? "" : ", ") << json_str(test::label_name(id)) << ": " << n;
    first_label = false;
  }
  j << "},\n     \"miss_parts\": [";
  for (std::size_t i = 0; i < c.miss_parts.size(); ++i) {
    const auto& m = c.miss_parts[i];
    j << (i ? ", " : "") << "{\"voxels\": " << m.voxels << ", \"ml\": " << json_number(m.ml) << ", \"centre_mm\": ["
      << json_number(m.centre_mm.x) << ", " << json_number(m.centre_mm.y) << ", " << json_number(m.centre_mm.z)
      << "], \"mean_hu\": " << json_number(m.mean_hu) << ", \"label\": " << json_str(test::label_name(m.label)) << "}";
  }
  j << "],\n     \"ribs\": {";
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
                    "per rib recall, precision and its misses, vertebrae, cord, disc, prep time [--json FILE] [--commit C] "
                    "[--repeats N] [--misses-png FILE: three slices of the 2 mm series with the misses]") {
  using namespace palpsim;
  using namespace palpsim::bench;
  std::string json, commit = "unknown", misses_png;
  int repeats = 3;
  for (int a = 1; a < argc; ++a) {
    const std::string s = argv[a];
    if (s == "--json" && a + 1 < argc) json = argv[++a];
    else if (s == "--commit" && a + 1 < argc) commit = argv[++a];
    else if (s == "--repeats" && a + 1 < argc) repeats = std::max(1, std::atoi(argv[++a]));
    else if (s == "--misses-png" && a + 1 < argc) misses_png = argv[++a];
    else {
      std::fprintf(stderr, "usage: palpsim-bench bone [--json FILE] [--commit C] [--repeats N] [--misses-png FILE]\n");
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
        [&](const Grid& g) { return test::dicom_label_reference(g, slab_labels); }, t11_t12, repeats,
        n == 1 ? misses_png : std::string()));
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
