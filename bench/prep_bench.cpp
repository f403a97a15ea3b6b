// palpsim-bench prep: wall time of every preparation stage on the phantom at 1 mm and
// 0.5 mm and on the real abdominal CT, the patient's memory, and, on the same mask,
// our exact EDT against scipy.ndimage.distance_transform_edt (bench/prep_edt_scipy.py).
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "bench/registry.h"
#include "core/error.h"
#include "prep/ct_io.h"
#include "prep/distance.h"
#include "prep/phantom.h"
#include "prep/pipeline.h"

using namespace palpsim;
namespace fs = std::filesystem;

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// peak resident memory of this process so far (MiB)
double peak_rss_mb() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss / 1024.0;
}

std::string machine_json() {
  std::string cpu = "unknown";
  std::ifstream ci("/proc/cpuinfo");
  for (std::string l; std::getline(ci, l);)
    if (l.rfind("model name", 0) == 0) {
      cpu = l.substr(l.find(':') + 2);
      break;
    }
  double mem_gb = 0;
  std::ifstream mi("/proc/meminfo");
  for (std::string l; std::getline(mi, l);)
    if (l.rfind("MemTotal:", 0) == 0) mem_gb = std::stod(l.substr(9)) / (1024.0 * 1024.0);
  char host[256] = {};
  gethostname(host, sizeof host - 1);
  std::ostringstream s;
  s << "{\"cpu\": \"" << cpu << "\", \"threads\": " << std::thread::hardware_concurrency() << ", \"memory_gb\": " << mem_gb
    << ", \"host\": \"" << host << "\"}";
  return s.str();
}

struct Stage {
  std::string name;
  double s;
};

struct Case {
  std::string name;
  Grid grid;
  std::vector<Stage> stages;
  double total_s = 0, patient_mb = 0, peak_rss_mb = 0, body_ml = 0, bone_ml = 0;
  double our_edt_s = 0, our_edt_1t_s = -1, scipy_edt_s = -1, max_diff_mm = -1;
  int edt_threads = 1;
  std::string scipy_note;
};

// runs scipy on `mask` (distance inside it to its zeros) and compares with ours
void compare_scipy(Case& c, const Volume<std::uint8_t>& mask, const Volume<float>& ours, int repeats) {
  const char* env = std::getenv("PALPSIM_PYTHON");
  const std::string py = env && *env ? env : "/work/main/.venv/bin/python";
  const std::string script = std::string(PALPSIM_SOURCE_DIR) + "/bench/prep_edt_scipy.py";
  const fs::path dir = fs::temp_directory_path() / ("palpsim-bench-prep-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string in = (dir / "mask.raw").string(), out = (dir / "dist.raw").string();
  std::ofstream(in, std::ios::binary).write(reinterpret_cast<const char*>(mask.data.data()), std::streamsize(mask.bytes()));
  const Grid& g = mask.grid;
  std::ostringstream cmd;
  cmd << py << " " << script << " " << in << " " << g.size.x << " " << g.size.y << " " << g.size.z << " "
      << g.spacing_mm.x << " " << g.spacing_mm.y << " " << g.spacing_mm.z << " " << out << " " << repeats;
  FILE* p = popen(cmd.str().c_str(), "r");
  std::string text;
  char buf[512];
  while (p && std::fgets(buf, sizeof buf, p)) text += buf;
  const int rc = p ? pclose(p) : -1;
  const std::size_t at = text.find("\"seconds\": ");
  if (rc != 0 || at == std::string::npos) {
    c.scipy_note = "scipy run failed (" + py + "): " + text;
  } else {
    c.scipy_edt_s = std::stod(text.substr(at + 11));
    std::vector<float> theirs(g.count());
    std::ifstream(out, std::ios::binary).read(reinterpret_cast<char*>(theirs.data()), std::streamsize(theirs.size() * 4));
    double md = 0;
    for (std::size_t i = 0; i < theirs.size(); ++i) md = std::max(md, double(std::abs(theirs[i] - ours.data[i])));
    c.max_diff_mm = md;
  }
  std::error_code ec;
  fs::remove_all(dir, ec);
}

// every stage of build_patient, timed one by one (the same calls, same order)
Case run_case(const std::string& name, Volume<float> image, double in_s, const char* in_name,
              const PrepSettings& prep, const ForceImageSettings& force, int repeats) {
  Case c;
  c.name = name;
  c.stages.push_back({in_name, in_s});
  auto t = Clock::now();
  const Grid grid = isotropic_grid(image.grid, patient_spacing_mm(image.grid, prep.spacing_mm));
  Patient p;
  p.grid = grid;
  p.intensity = grid.same_geometry(image.grid) ? std::move(image) : resample_linear(image, grid, -1024);
  const double coarsest = std::max({image.grid.spacing_mm.x, image.grid.spacing_mm.y, image.grid.spacing_mm.z});
  image = Volume<float>();
  c.stages.push_back({"resample", since(t)});
  t = Clock::now();
  p.body = body_mask(p.intensity, prep.air_threshold, prep.body_opening_mm, prep.body_min_part_ml);
  c.stages.push_back({"body_mask", since(t)});
  t = Clock::now();
  p.bone = bone_mask(p.intensity, p.body, prep, 2 * (coarsest > 0 ? coarsest : grid.spacing_mm.x));
  c.stages.push_back({"bone_mask", since(t)});
  t = Clock::now();
  p.dist_bone_mm = distance_to_mask_mm(p.bone);
  c.stages.push_back({"dist_bone", since(t)});
  t = Clock::now();
  p.dist_skin_mm = distance_to_background_mm(p.body);
  c.our_edt_s = since(t);
  c.stages.push_back({"dist_skin", c.our_edt_s});
  t = Clock::now();
  p.force = force_image(p, force);
  c.stages.push_back({"force", since(t)});
  t = Clock::now();
  p.grad_force = gradient_physical(p.force);
  c.stages.push_back({"gradient", since(t)});
  for (const auto& s : c.stages) c.total_s += s.s;
  c.grid = grid;
  const double ml = grid.spacing_mm.x * grid.spacing_mm.y * grid.spacing_mm.z / 1000.0;
  c.body_ml = double(count_nonzero(p.body)) * ml;
  c.bone_ml = double(count_nonzero(p.bone)) * ml;
  c.patient_mb = double(p.intensity.bytes() + p.body.bytes() + p.bone.bytes() + p.dist_bone_mm.bytes() +
                        p.dist_skin_mm.bytes() + p.force.bytes() + p.grad_force.bytes()) / (1024.0 * 1024.0);
  c.peak_rss_mb = peak_rss_mb();
  // the same EDT in scipy: depth under the skin (inside C to its outside); scipy's time is
  // the best of `repeats` runs, so ours for the ratio is too (the stage above is one
  // run), on all cores and on one (scipy runs on one)
  c.edt_threads = worker_threads(0);
  if (repeats > 0) {
    for (int r = 1; r < repeats; ++r) {
      t = Clock::now();
      const Volume<float> again = distance_to_background_mm(p.body);
      c.our_edt_s = std::min(c.our_edt_s, since(t));
    }
    for (int r = 0; r < repeats; ++r) {
      t = Clock::now();
      const Volume<float> again = distance_to_background_mm(p.body, 1);
      const double s = since(t);
      c.our_edt_1t_s = r == 0 ? s : std::min(c.our_edt_1t_s, s);
    }
    compare_scipy(c, p.body, p.dist_skin_mm, repeats);
  }
  return c;
}

void print_case(const Case& c) {
  std::printf("\n== %s: %d x %d x %d voxels of %.3g mm (%.1f M), body %.0f ml, bone %.0f ml\n", c.name.c_str(),
              c.grid.size.x, c.grid.size.y, c.grid.size.z, c.grid.spacing_mm.x, c.grid.count() / 1e6, c.body_ml,
              c.bone_ml);
  for (const auto& s : c.stages) std::printf("  %-10s %8.3f s\n", s.name.c_str(), s.s);
  std::printf("  %-10s %8.3f s   patient %.0f MiB, process peak RSS %.0f MiB\n", "total", c.total_s, c.patient_mb,
              c.peak_rss_mb);
  if (c.scipy_edt_s > 0)
    std::printf("  EDT depth under the skin: ours %.3f s on %d threads, %.3f s on 1; scipy (1 thread) %.3f s;"
                " scipy/ours = %.2fx (%.2fx thread for thread), max |diff| %.2g mm\n",
                c.our_edt_s, c.edt_threads, c.our_edt_1t_s, c.scipy_edt_s, c.scipy_edt_s / c.our_edt_s,
                c.scipy_edt_s / c.our_edt_1t_s, c.max_diff_mm);
  else if (!c.scipy_note.empty())
    std::printf("  %s\n", c.scipy_note.c_str());
}

std::string case_json(const Case& c) {
  std::ostringstream s;
  s.precision(6);
  s << "{\"name\": \"" << c.name << "\", \"grid\": [" << c.grid.size.x << ", " << c.grid.size.y << ", " << c.grid.size.z
    << "], \"spacing_mm\": " << c.grid.spacing_mm.x << ", \"voxels\": " << c.grid.count() << ", \"stages_s\": {";
  for (std::size_t i = 0; i < c.stages.size(); ++i) s << (i ? ", " : "") << "\"" << c.stages[i].name << "\": " << c.stages[i].s;
  s << "}, \"total_s\": " << c.total_s << ", \"patient_mb\": " << c.patient_mb << ", \"peak_rss_mb\": " << c.peak_rss_mb
    << ", \"body_ml\": " << c.body_ml << ", \"bone_ml\": " << c.bone_ml << ", \"edt\": {\"threads\": " << c.edt_threads
    << ", \"ours_s\": " << c.our_edt_s << ", \"ours_1thread_s\": " << c.our_edt_1t_s << ", \"scipy_s\": " << c.scipy_edt_s
    << ", \"scipy_over_ours\": " << (c.scipy_edt_s > 0 ? c.scipy_edt_s / c.our_edt_s : -1)
    << ", \"scipy_over_ours_1thread\": " << (c.scipy_edt_s > 0 ? c.scipy_edt_s / c.our_edt_1t_s : -1)
    << ", \"max_abs_diff_mm\": " << c.max_diff_mm << "}}";
  return s.str();
}

}  // namespace

PALPSIM_BENCH(prep, "prep stages on the phantom (1 mm, 0.5 mm) and the real CT; EDT vs scipy [--json FILE] [--quick] [--repeats N] [--commit C]") {
  std::string json_path, commit = "unknown";
  bool quick = false;
  int repeats = 1;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--json") && i + 1 < argc) json_path = argv[++i];
    else if (!std::strcmp(argv[i], "--quick")) quick = true;  // skip the 0.5 mm phantom
    else if (!std::strcmp(argv[i], "--repeats") && i + 1 < argc) repeats = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--commit") && i + 1 < argc) commit = argv[++i];  // of the build, into the JSON
    else {
      std::fprintf(stderr, "palpsim-bench prep: unknown argument '%s'\n", argv[i]);
      return 2;
    }
  }
  std::printf("palpsim-bench prep: %u hardware threads\n", std::thread::hardware_concurrency());
  std::vector<Case> cases;
  try {
    // the real CT with the settings of config/scenes/lumbar_ct.textproto
    const char* data_env = std::getenv("PALPSIM_DATA");
    const std::string data = data_env && *data_env ? data_env : PALPSIM_SHARED_DATA;
    const std::string ct = data + "/ct/abdomen-lumbar-3mm.nii.gz";
    if (fs::exists(ct)) {
      PrepSettings prep;
      prep.spacing_mm = 1.5;
      prep.bone_threshold = 180;
      prep.bone_threshold_set = true;  // explicit in the scene, as in lumbar_ct.textproto
      auto t = Clock::now();
      CtImage img = read_ct(ct, prep);
      const double s = since(t);
      cases.push_back(run_case("abdomen CT 3 mm -> 1.5 mm", std::move(img.image), s, "read", prep, {}, repeats));
      print_case(cases.back());
    } else {
      std::printf("\nSKIPPED real CT: %s not found\n", ct.c_str());
    }
    for (double mm : quick ? std::vector<double>{1.0} : std::vector<double>{1.0, 0.5}) {
      auto t = Clock::now();
      PhantomCt ph = make_phantom(mm);
      const double s = since(t);
      cases.push_back(run_case("phantom " + std::to_string(mm).substr(0, 3) + " mm", std::move(ph.hu), s, "phantom",
                               PrepSettings{}, {}, repeats));
      print_case(cases.back());
    }
  } catch (const Error& e) {
    std::fprintf(stderr, "palpsim-bench prep: %s\n", e.what());
    return 1;
  }
  if (!json_path.empty()) {
    std::time_t now = std::time(nullptr);
    char date[64];
    std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
    std::ofstream o(json_path);
    o << "{\"bench\": \"prep\", \"date\": \"" << date << "\", \"commit\": \"" << commit << "\", \"repeats\": " << repeats
      << ", \"machine\": " << machine_json() << ", \"cases\": [\n";
    for (std::size_t i = 0; i < cases.size(); ++i) o << "  " << case_json(cases[i]) << (i + 1 < cases.size() ? ",\n" : "\n");
    o << "]}\n";
    std::printf("\nwrote %s\n", json_path.c_str());
  }
  return 0;
}
