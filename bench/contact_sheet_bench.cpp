// palpsim-bench contact_sheet: one press over L3's spinous process of the built-in phantom
// (config/scenes/lumbar_phantom.textproto), deformed by three models side by side on the cpu
// backend: the paper's explicit relaxation (20 iterations, the grabbed element alone), the
// shipped multigrid diffusion (as the scene ships it: a 5 mm fingertip, the inversion's cell
// search) and the elastic model (a 5 mm fingertip sphere). The press is the demo's
// (clients/python/palpsim/demo.py, palpsim.record): at the body's mid x and z = -5 mm (L3's
// spinous tip), along -y from 10 mm above the body, 0.1 mm a pose at 200 Hz through the
// force model, which finds the skin and gives X; the tip goes 15 mm under the skin.
// Each model steps the press a millimetre at a time (the warm path a press takes), and from
// rest at the last depth on a fresh backend: the step times of both. Writes, into --out, the
// slices through the press (sagittal at X's x, axial at X's z) of the deformed image J and
// of |u| (mm) per model, of the undeformed I, body and bone masks, as .npy, and
// contact_sheet.json; bench/contact_sheet.py composes the sheet from them.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include "bench/registry.h"
#include "bench/stats.h"
#include "core/error.h"
#include "core/setting_names.h"
#include "deform/backend.h"
#include "deform/press_cap.h"
#include "haptics/force_model.h"
#include "net/scene_io.h"
#include "prep/prepare.h"

using namespace palpsim;
namespace fs = std::filesystem;

namespace {

using bench::json_number;
using bench::json_spread;
using bench::machine;
using bench::Spread;
using bench::spread;

std::string json_vec(const Vec3& v) {
  return "[" + json_number(v.x) + ", " + json_number(v.y) + ", " + json_number(v.z) + "]";
}

// the machine's load (1-minute average) from /proc/loadavg: the cores are shared, so the
// times are read beside it
double load_average() {
  std::ifstream in("/proc/loadavg");
  double v = -1;
  in >> v;
  return v;
}

std::string quoted(const std::string& s) {
  std::string o = "\"";
  for (char ch : s) o += (ch == '"' || ch == '\\') ? std::string("\\") + ch : std::string(1, ch);
  return o + "\"";
}

// a 2D float32 array as a NumPy .npy file (version 1.0, C order), rows x cols
void write_npy(const fs::path& path, const std::vector<float>& v, int rows, int cols) {
  std::string header = "{'descr': '<f4', 'fortran_order': False, 'shape': (" + std::to_string(rows) + ", " +
                       std::to_string(cols) + "), }";
  // magic (6) + version (2) + length (2) + header, padded with spaces to 64 bytes, newline last
  const std::size_t total = (10 + header.size() + 1 + 63) / 64 * 64;
  header.append(total - 10 - header.size() - 1, ' ');
  header += '\n';
  std::ofstream o(path, std::ios::binary);
  const unsigned char magic[8] = {0x93, 'N', 'U', 'M', 'P', 'Y', 1, 0};
  o.write(reinterpret_cast<const char*>(magic), 8);
  const std::uint16_t len = std::uint16_t(header.size());
  const unsigned char l[2] = {static_cast<unsigned char>(len & 0xff), static_cast<unsigned char>(len >> 8)};
  o.write(reinterpret_cast<const char*>(l), 2);
  o << header;
  o.write(reinterpret_cast<const char*>(v.data()), std::streamsize(v.size() * sizeof(float)));
  if (!o) throw Error("cannot write " + path.string());
}

struct Options {
  std::string scene = std::string(PALPSIM_SOURCE_DIR) + "/config/scenes/lumbar_phantom.textproto";
  std::string out = "out/contact-sheet";
  std::string commit = "unknown";
  double z_mm = -5.0;       // the demo's PHANTOM_L3_Z_MM: over L3's spinous tip
  double depth_mm = 15.0;   // under the skin
  int repeats = 3;          // of each model's press and step from rest (median and spread)
  double half_fov_mm = 45;  // slices: +-this around X across, from 70 mm under to 20 mm above the skin
};

// the press as the haptic path makes it (palpsim.record's): the skin found along -y from
// above the body, the proxy reset above it, then the tip down a pose at a time; the
// contacts the deformation gets at each whole millimetre under the skin, and the last pose's
// force sample
struct Press {
  Vec3 top_mm, skin_mm;
  std::vector<DeformContact> contacts;  // 1, 2, ... depth_mm under the skin
  ForceSample last;
  long poses = 0;
};

Press press_over(const Patient& p, const HapticsSettings& hs, const Vec3& top, double depth_mm) {
  constexpr double kRateHz = 200, kSpeedMmPerS = 20;  // palpsim.record's
  const double step = kSpeedMmPerS / kRateHz, dt = 1 / kRateHz;
  const Vec3 d{0, -1, 0};
  Press out;
  out.top_mm = top;
  ProxyState st{};
  if (compute_force(p, hs, top, dt, st).contact) throw Error("the start point is inside the body");
  double travel = 0, skin = -1;
  for (long k = 1; skin < 0; ++k) {
    travel = k * step;
    if (travel > 300) throw Error("no skin within 300 mm below the start point");
    if (compute_force(p, hs, top + d * travel, dt, st).contact) skin = travel;
    ++out.poses;
  }
  out.skin_mm = top + d * skin;
  // back 5 mm above the skin with a fresh proxy, then down to depth_mm under it
  st = ProxyState{};
  travel = std::max(skin - 5, 0.0);
  int next_mm = 1;
  const long n = std::lround((skin + depth_mm - travel) / step);
  const double start = travel;
  for (long k = 1; k <= n; ++k) {
    travel = start + k * step;
    const Vec3 tip = top + d * travel;
    const ForceSample f = compute_force(p, hs, tip, dt, st);
    ++out.poses;
    if (travel >= skin + next_mm - 1e-9 && next_mm <= depth_mm + 1e-9) {
      if (!f.contact) throw Error("the press lost contact under the skin");
      out.contacts.push_back({f.skin_point_mm, tip});
      out.last = f;
      ++next_mm;
    }
  }
  return out;
}

struct Model {
  std::string key, label;
  DeformConfig cfg;
  // measured
  Spread rest_ms, press_ms, press_relax_ms, press_invert_ms;
  DeformStats last;           // the pressed backend's last step (the press's deepest)
  std::vector<Vec3f> u;       // its field (voxel, VOI)
  std::vector<float> j;       // its J (VOI)
  Voi voi;
  long long bone_moved = 0;   // bone voxels of the VOI with u != 0
  double max_u_mm = 0;
  Vec3 pressed_tip_mm{0, 0, 0};  // the deepest contact's tip as the model presses it (held short of bone)
  double pressed_depth_mm = 0;   // and its depth under the skin point
};

// a plane of the patient grid through voxel `at` along axis `normal` (0: x, sagittal; 2: z,
// axial), over the index window [lo, hi] of its two other axes (rows: y from high to low,
// posterior up; columns: the other axis, low to high)
struct Plane {
  std::string name;
  int normal = 0, at = 0;
  int col_axis = 2;
  int row_lo = 0, row_hi = 0, col_lo = 0, col_hi = 0;  // y rows, col_axis columns (voxel indices, inclusive)
  int rows() const { return row_hi - row_lo + 1; }
  int cols() const { return col_hi - col_lo + 1; }
  Vec3i voxel(int r, int c) const {
    Vec3i v{0, 0, 0};
    v[normal] = at;
    v.y = row_hi - r;
    v[col_axis] = col_lo + c;
    return v;
  }
};

// samples one plane of `f(voxel)` into a row-major array
template <typename F>
std::vector<float> sample(const Plane& pl, const F& f) {
  std::vector<float> out(std::size_t(pl.rows()) * pl.cols());
  for (int r = 0; r < pl.rows(); ++r)
    for (int c = 0; c < pl.cols(); ++c) out[std::size_t(r) * pl.cols() + c] = f(pl.voxel(r, c));
  return out;
}

// reads the command line into `o`; false after printing the usage (--help)
bool parse_options(int argc, char** argv, Options& o) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw Error(a + " needs a value");
      return argv[++i];
    };
    if (a == "--out") o.out = value();
    else if (a == "--scene") o.scene = value();
    else if (a == "--commit") o.commit = value();
    else if (a == "--z-mm") o.z_mm = std::stod(value());
    else if (a == "--depth-mm") o.depth_mm = std::stod(value());
    else if (a == "--repeats") o.repeats = std::max(1, std::stoi(value()));
    else if (a == "--help" || a == "-h") {
      std::printf("usage: palpsim-bench contact_sheet [--out DIR (out/contact-sheet)] [--depth-mm 15] [--z-mm -5] "
                  "[--repeats 3] [--commit C] [--scene FILE (lumbar_phantom)]\n");
      return false;
    } else {
      throw Error("unknown argument '" + a + "'");
    }
  }
  return true;
}

// the three models on the scene's deformation settings `base`: the paper's explicit
// relaxation, the shipped multigrid diffusion and the elastic model
std::vector<Model> three_models(const DeformConfig& base) {
  std::vector<Model> models(3);
  models[0].key = "explicit";
  models[0].label = "paper: explicit relaxation, 20 iterations";
  models[0].cfg = base;
  models[0].cfg.settings.relax_method = RelaxMethod::kExplicit;
  models[0].cfg.settings.relax_iterations = 20;
  models[0].cfg.settings.grab_radius_mm = 0;
  models[1].key = "multigrid";
  models[1].label = "shipped: multigrid diffusion, 5 mm fingertip";
  models[1].cfg = base;
  models[2].key = "elastic";
  models[2].label = "elastic, 5 mm fingertip sphere";
  models[2].cfg = base;
  models[2].cfg.settings.relax_method = RelaxMethod::kElastic;
  models[2].cfg.settings.grab_radius_mm = 5;
  return models;
}

// `m`'s press on `patient`, `repeats` times, a fresh backend from rest and the press a
// millimetre a step (its last step timed and kept); its largest |u| and moved bone, printed
void run_model(Model& m, const PatientPtr& patient, const Press& press, int repeats) {
  const Patient& p = *patient;
  const Vec3& h = p.grid.spacing_mm;
  const DeformContact& deepest = press.contacts.back();
  std::vector<double> rest, step, relax, inv;
  for (int r = 0; r < repeats; ++r) {
    // from rest: a fresh backend's one step at the deepest contact
    auto fresh = make_deform_backend("cpu");
    fresh->bind(patient, m.cfg);
    rest.push_back(fresh->step(deform::capped_press(p, m.cfg, deepest)).times.total_ms);
    // the press, a millimetre a step; its last step is the one timed and shown
    auto b = make_deform_backend("cpu");
    b->bind(patient, m.cfg);
    // each contact as the server's engine presses it (the elastic one held short of bone)
    for (const DeformContact& k : press.contacts) m.last = b->step(deform::capped_press(p, m.cfg, k));
    step.push_back(m.last.times.total_ms);
    relax.push_back(m.last.times.relax_ms);
    inv.push_back(m.last.times.invert_ms);
    if (r + 1 == repeats) {
      m.voi = b->voi();
      m.u = b->displacement();
      m.j.assign(b->deformed_brick(), b->deformed_brick() + m.voi.count());
    }
  }
  const DeformContact pressed = deform::capped_press(p, m.cfg, deepest);
  m.pressed_tip_mm = pressed.tip_mm;
  m.pressed_depth_mm = norm(pressed.tip_mm - pressed.skin_point_mm);
  m.rest_ms = spread(rest);
  m.press_ms = spread(step);
  m.press_relax_ms = spread(relax);
  m.press_invert_ms = spread(inv);
  for (int k = 0; k < m.voi.size.z; ++k)
    for (int j = 0; j < m.voi.size.y; ++j)
      for (int i = 0; i < m.voi.size.x; ++i) {
        const Vec3f& v = m.u[std::size_t(m.voi.index(i, j, k))];
        m.max_u_mm = std::max(m.max_u_mm, norm(Vec3(v.x * h.x, v.y * h.y, v.z * h.z)));
        m.bone_moved += p.bone.at(m.voi.lo.x + i, m.voi.lo.y + j, m.voi.lo.z + k) && !(v == Vec3f{0, 0, 0});
      }
  std::printf("%-46s step while pressing %8.1f ms (relax %.1f, invert %.1f), from rest %8.1f ms; max |u| %.2f mm, "
              "bone moved %lld, J unresolved %lld%s\n",
              m.label.c_str(), m.press_ms.median, m.press_relax_ms.median, m.press_invert_ms.median, m.rest_ms.median,
              m.max_u_mm, m.bone_moved, m.last.invert_unresolved,
              m.cfg.settings.relax_method == RelaxMethod::kElastic
                  ? (", force " + std::to_string(norm(m.last.elastic.force_n)) + " N").c_str()
                  : "");
}

// one model's settings, times and figures as JSON
std::string model_json(const Model& m) {
  std::ostringstream js;
  const DeformSettings& s = m.cfg.settings;
  const deform::ElasticRun& el = m.last.elastic;
  js << "\n    {\"key\": " << quoted(m.key) << ", \"label\": " << quoted(m.label)
     << ", \"relax_method\": " << quoted(setting_name(s.relax_method)) << ", \"relax_iterations\": " << s.relax_iterations
     << ", \"relax_cycles\": " << s.relax_cycles << ", \"grab_radius_mm\": " << json_number(s.grab_radius_mm)
     << ", \"voi_edge\": " << s.voi_edge << ", \"invert_search\": " << (s.invert_search ? "true" : "false")
     << ",\n     \"step_while_pressing\": " << json_spread(m.press_ms) << ", \"relax_while_pressing\": "
     << json_spread(m.press_relax_ms) << ", \"invert_while_pressing\": " << json_spread(m.press_invert_ms)
     << ", \"step_from_rest\": " << json_spread(m.rest_ms) << ",\n     \"voi_lo\": [" << m.voi.lo.x << ", "
     << m.voi.lo.y << ", " << m.voi.lo.z << "], \"voi_size\": [" << m.voi.size.x << ", " << m.voi.size.y << ", "
     << m.voi.size.z << "], \"max_u_mm\": " << json_number(m.max_u_mm) << ", \"bone_moved_voxels\": " << m.bone_moved
     << ", \"invert_residual_vox\": " << json_number(m.last.invert_residual_vox)
     << ", \"invert_unresolved\": " << m.last.invert_unresolved << ", \"invert_nonfinite\": " << m.last.invert_nonfinite
     << ", \"chainmail_skipped\": " << (m.last.chainmail.skipped ? "true" : "false");
  if (s.relax_method == RelaxMethod::kElastic)
    js << ",\n     \"elastic\": {\"force_n\": " << json_vec(el.force_n) << ", \"force_norm_n\": "
       << json_number(norm(el.force_n)) << ", \"contact_nodes\": " << el.contact_nodes << ", \"rounds\": " << el.rounds
       << ", \"iterations\": " << el.iterations << ", \"residual\": " << json_number(el.residual)
       << ", \"converged\": " << (el.converged ? "true" : "false") << ", \"warm\": " << (el.warm ? "true" : "false")
       << ", \"inverted_cells\": " << el.inverted_cells << ", \"poisson\": " << json_number(s.elastic.poisson)
       << ", \"normal\": " << json_vec(el.normal) << ", \"radius_mm\": " << json_number(s.grab_radius_mm)
       << ", \"min_tissue_fraction\": " << json_number(s.elastic.min_tissue_fraction) << ", \"pressed_tip_mm\": "
       << json_vec(m.pressed_tip_mm) << ", \"pressed_depth_mm\": " << json_number(m.pressed_depth_mm) << "}";
  js << "}";
  return js.str();
}

int run(int argc, char** argv) {
  Options o;
  if (!parse_options(argc, argv, o)) return 0;
  if (!(o.depth_mm >= 1 && o.depth_mm <= 60)) throw Error("--depth-mm must lie in [1, 60]");

  // the scene's patient
  const Scene scene = load_scene_file(o.scene);
  PrepReport report;
  const PatientPtr patient = prepare_patient(scene, &report);
  const Patient& p = *patient;
  const Grid& g = p.grid;
  std::printf("scene '%s': patient %d x %d x %d at %.2f mm (%s, %.1f s)\nmachine: %s\n", scene.name.c_str(), g.size.x,
              g.size.y, g.size.z, g.spacing_mm.x, report.from_cache ? "cached" : "prepared", report.total_s,
              machine().c_str());

  // the press: x at the middle of the body's box, 10 mm above its top (the demo's)
  const IndexBox box = mask_box(p.body);
  const Vec3i bl = box.lo, bh = box.hi;
  const Vec3 body_lo = g.to_physical(Vec3(bl.x, bl.y, bl.z)), body_hi = g.to_physical(Vec3(bh.x, bh.y, bh.z));
  const Vec3 top{0.5 * (body_lo.x + body_hi.x), body_hi.y + 10, o.z_mm};
  const Press press = press_over(p, scene.haptics, top, o.depth_mm);
  const DeformContact& deepest = press.contacts.back();
  std::printf("press at x %.1f, z %.1f mm: skin at y %.2f mm, tip %.1f mm under it (%zu steps of 1 mm, %ld poses); X "
              "(%.2f, %.2f, %.2f) mm; eq. 2 force %.3f N\n",
              top.x, top.z, press.skin_mm.y, o.depth_mm, press.contacts.size(), press.poses, deepest.skin_point_mm.x,
              deepest.skin_point_mm.y, deepest.skin_point_mm.z, norm(press.last.force_n));

  // the three models on the scene's deformation settings
  DeformConfig base = DeformConfig::from_scene(scene, patient.get());
  base.settings.backend = DeformBackendChoice::kCpu;
  std::vector<Model> models = three_models(base);

  const Vec3& h = g.spacing_mm;
  const double load_before = load_average();
  for (Model& m : models) run_model(m, patient, press, o.repeats);

  const double load_after = load_average();
  std::printf("load average %.2f before the models, %.2f after\n", load_before, load_after);

  // the slices through X: sagittal (x = X's) and axial (z = X's)
  const Vec3 Xi = g.to_index(deepest.skin_point_mm);
  const Vec3i X{int(std::lround(Xi.x)), int(std::lround(Xi.y)), int(std::lround(Xi.z))};
  auto clampi = [&](double v, int a) { return std::clamp(int(std::lround(v)), 0, g.size[a] - 1); };
  const int row_lo = clampi(Xi.y - 70 / h.y, 1), row_hi = clampi(Xi.y + 20 / h.y, 1);
  std::vector<Plane> planes(2);
  planes[0] = {"sagittal", 0, X.x, 2, row_lo, row_hi, clampi(Xi.z - o.half_fov_mm / h.z, 2), clampi(Xi.z + o.half_fov_mm / h.z, 2)};
  planes[1] = {"axial", 2, X.z, 0, row_lo, row_hi, clampi(Xi.x - o.half_fov_mm / h.x, 0), clampi(Xi.x + o.half_fov_mm / h.x, 0)};
  fs::create_directories(o.out);
  const fs::path out(o.out);
  std::ostringstream planes_json;
  for (std::size_t q = 0; q < planes.size(); ++q) {
    const Plane& pl = planes[q];
    auto file = [&](const std::string& what) { return pl.name + "-" + what + ".npy"; };
    write_npy(out / file("I"), sample(pl, [&](const Vec3i& v) { return p.intensity.at(v.x, v.y, v.z); }), pl.rows(), pl.cols());
    write_npy(out / file("body"), sample(pl, [&](const Vec3i& v) { return float(p.body.at(v.x, v.y, v.z)); }), pl.rows(), pl.cols());
    write_npy(out / file("bone"), sample(pl, [&](const Vec3i& v) { return float(p.bone.at(v.x, v.y, v.z)); }), pl.rows(), pl.cols());
    for (const Model& m : models) {
      auto in_voi = [&](const Vec3i& v) { return m.voi.contains(v.x - m.voi.lo.x, v.y - m.voi.lo.y, v.z - m.voi.lo.z); };
      auto at = [&](const Vec3i& v) { return std::size_t(m.voi.index(v.x - m.voi.lo.x, v.y - m.voi.lo.y, v.z - m.voi.lo.z)); };
      write_npy(out / file("J-" + m.key),
                sample(pl, [&](const Vec3i& v) { return in_voi(v) ? m.j[at(v)] : p.intensity.at(v.x, v.y, v.z); }),
                pl.rows(), pl.cols());
      write_npy(out / file("u-" + m.key), sample(pl, [&](const Vec3i& v) {
                  if (!in_voi(v)) return 0.0f;
                  const Vec3f& w = m.u[at(v)];
                  return float(norm(Vec3(w.x * h.x, w.y * h.y, w.z * h.z)));
                }), pl.rows(), pl.cols());
    }
    // extents (mm) of the voxels' outer edges: left, right (columns), bottom, top (rows)
    const int ca = pl.col_axis;
    const double c0 = g.to_physical(Vec3(ca == 0 ? pl.col_lo : 0, 0, ca == 2 ? pl.col_lo : 0))[ca] - 0.5 * h[ca];
    const double c1 = g.to_physical(Vec3(ca == 0 ? pl.col_hi : 0, 0, ca == 2 ? pl.col_hi : 0))[ca] + 0.5 * h[ca];
    const double r0 = g.to_physical(Vec3(0, pl.row_lo, 0)).y - 0.5 * h.y, r1 = g.to_physical(Vec3(0, pl.row_hi, 0)).y + 0.5 * h.y;
    const double cut = g.to_physical(Vec3(pl.normal == 0 ? pl.at : 0, 0, pl.normal == 2 ? pl.at : 0))[pl.normal];
    planes_json << (q ? ",\n    " : "") << "{\"name\": " << quoted(pl.name) << ", \"cut_axis\": " << pl.normal
                << ", \"cut_mm\": " << json_number(cut) << ", \"column_axis\": " << ca << ", \"rows\": " << pl.rows()
                << ", \"cols\": " << pl.cols() << ", \"extent_mm\": [" << json_number(c0) << ", " << json_number(c1)
                << ", " << json_number(r0) << ", " << json_number(r1) << "]}";
  }

  // the JSON
  std::time_t now = std::time(nullptr);
  char date[64];
  std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
  std::ostringstream js;
  js << "{\"area\": \"contact_sheet\", \"date\": \"" << date << "\", \"commit\": " << quoted(o.commit)
     << ", \"backend\": \"cpu\", \"machine\": " << quoted(machine()) << ", \"repeats\": " << o.repeats
     << ", \"load_average\": [" << json_number(load_before) << ", " << json_number(load_after) << "]"
     << ",\n  \"scene\": " << quoted(fs::path(o.scene).filename().string()) << ", \"patient\": {\"size\": [" << g.size.x
     << ", " << g.size.y << ", " << g.size.z << "], \"spacing_mm\": " << json_vec(g.spacing_mm)
     << ", \"bone_threshold_hu\": " << json_number(base.bone_threshold) << "},\n  \"press\": {\"top_mm\": "
     << json_vec(press.top_mm) << ", \"direction\": [0, -1, 0], \"skin_mm\": " << json_vec(press.skin_mm)
     << ", \"depth_mm\": " << json_number(o.depth_mm) << ", \"steps_mm\": 1, \"X_mm\": " << json_vec(deepest.skin_point_mm)
     << ", \"tip_mm\": " << json_vec(deepest.tip_mm) << ", \"eq2_force_n\": " << json_vec(press.last.force_n)
     << ", \"eq2_force_norm_n\": " << json_number(norm(press.last.force_n)) << "},\n  \"models\": [";
  for (std::size_t i = 0; i < models.size(); ++i) js << (i ? "," : "") << model_json(models[i]);
  js << "\n  ],\n  \"planes\": [\n    " << planes_json.str() << "\n  ],\n  \"files\": \"<plane>-<I|body|bone|J-<key>|u-<key>>.npy\"}\n";
  std::ofstream(out / "contact_sheet.json") << js.str();
  std::printf("wrote %s (contact_sheet.json and %zu slices)\n", o.out.c_str(), planes.size() * (3 + 2 * models.size()));
  return 0;
}

}  // namespace

PALPSIM_BENCH(contact_sheet,
              "a 15 mm press over L3 of the phantom by the paper's explicit relaxation, the shipped multigrid and the "
              "elastic model: slices of J and |u| and a JSON for bench/contact_sheet.py [--out DIR] [--depth-mm D] "
              "[--z-mm Z] [--repeats N] [--commit C] [--scene FILE]") {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-bench contact_sheet: %s\n", e.what());
    return 1;
  }
}
