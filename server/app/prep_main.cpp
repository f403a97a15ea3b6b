// palpsim-prep: prepares a patient from a CT (a file or a DICOM folder) or the
// built-in phantom and writes F.nrrd, body.nrrd, bone.nrrd, dist_bone.nrrd,
// dist_skin.nrrd, preview.png and prep.json into an output folder.
#include <spdlog/spdlog.h>

#include <cstdio>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include "core/error.h"
#include "net/scene_io.h"
#include "prep/landmarks.h"
#include "prep/outputs.h"
#include "prep/prepare.h"

namespace {

const char* kUsage =
    "usage: palpsim-prep [CT] [--scene FILE] --out DIR [--no-cache] [--air-threshold V --bone-threshold V]\n"
    "       palpsim-prep --scene-doc\n"
    "  CT        a CT file (.nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd), a DICOM folder, or the\n"
    "            word 'phantom'; without CT the scene's source is used\n"
    "  --scene   a scene file (config/scenes/*.textproto); default: the built-in phantom scene\n"
    "  --out     the output folder (written atomically: complete or absent)\n"
    "  --no-cache  neither read nor write the patient cache\n"
    "  --air-threshold V, --bone-threshold V\n"
    "            the scene's prep.air_threshold and prep.bone_threshold, in the image's own units\n"
    "            (both are needed for an image not in Hounsfield units)\n"
    "  --scene-doc print every scene field with its default, unit and range\n";

// a threshold flag's value: a finite number within the scene field's range, else one error line and exit 2
double threshold_value(const char* flag, const std::string& text) {
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (text.empty() || *end != '\0' || !std::isfinite(v) || v < -1e6 || v > 1e6) {
    std::fprintf(stderr, "palpsim-prep: %s '%s' is not a number in -1e6..1e6 (a threshold in the image's units)\n",
                 flag, text.c_str());
    std::exit(2);
  }
  return v;
}

// the landmarks with the press that reaches each (the scripted press moves along -y from its start)
void print_landmarks(const std::vector<palpsim::SkinLandmark>& marks) {
  if (marks.empty()) {
    std::printf("  landmarks: no spinous process or iliac crest stands out in the bone mask\n");
    return;
  }
  std::printf("  landmarks: the skin above each along +y (posterior); palpsim-haptic --device press:X,Y,Z,TRAVEL "
              "starts %.0f mm outside that skin point and presses along -y through it to %.0f mm past the bone:\n",
              palpsim::kPressStandoffMm, palpsim::kPressBeyondBoneMm);
  for (const palpsim::SkinLandmark& l : marks)
    std::printf("    %-18s skin (%.1f, %.1f, %.1f) mm, bone %.1f mm under it, skin normal %.0f deg off +y: %s\n",
                l.name.c_str(), l.skin_mm.x, l.skin_mm.y, l.skin_mm.z, l.depth_mm, l.normal_angle_deg,
                palpsim::press_argument(l).c_str());
}

}  // namespace

int main(int argc, char** argv) {
  std::string ct, scene_file, out;
  bool no_cache = false;
  double air_threshold = NAN, bone_threshold = NAN;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const auto value = [&](const char* name) -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "palpsim-prep: %s needs a value\n%s", name, kUsage);
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--help" || a == "-h") {
      std::printf("%s", kUsage);
      return 0;
    } else if (a == "--scene-doc") {
      std::printf("%s", palpsim::scene_field_reference().c_str());
      return 0;
    } else if (a == "--scene") {
      scene_file = value("--scene");
    } else if (a == "--out") {
      out = value("--out");
    } else if (a == "--no-cache") {
      no_cache = true;
    } else if (a == "--air-threshold") {
      air_threshold = threshold_value("--air-threshold", value("--air-threshold"));
    } else if (a == "--bone-threshold") {
      bone_threshold = threshold_value("--bone-threshold", value("--bone-threshold"));
    } else if (!a.empty() && a[0] == '-') {
      std::fprintf(stderr, "palpsim-prep: unknown option '%s'\n%s", a.c_str(), kUsage);
      return 2;
    } else if (ct.empty()) {
      ct = a;
    } else {
      std::fprintf(stderr, "palpsim-prep: more than one CT given ('%s' and '%s')\n%s", ct.c_str(), a.c_str(), kUsage);
      return 2;
    }
  }
  if (out.empty()) {
    std::fprintf(stderr, "palpsim-prep: --out DIR is required\n%s", kUsage);
    return 2;
  }

  try {
    // the scene, then the CT named on the command line (relative to the working folder)
    palpsim::Scene scene = scene_file.empty() ? palpsim::default_scene() : palpsim::load_scene_file(scene_file);
    if (ct == "phantom") {
      scene.use_phantom = true;
    } else if (!ct.empty()) {
      scene.use_phantom = false;
      scene.ct_path = std::filesystem::absolute(ct).lexically_normal().string();
    }
    if (no_cache) scene.prep.use_cache = false;
    if (!std::isnan(air_threshold)) scene.prep.air_threshold = air_threshold, scene.prep.air_threshold_set = true;
    if (!std::isnan(bone_threshold)) scene.prep.bone_threshold = bone_threshold, scene.prep.bone_threshold_set = true;

    palpsim::PrepReport report;
    const palpsim::PatientPtr patient = palpsim::prepare_patient(scene, &report);
    palpsim::PreviewOptions preview;
    preview.caption = report.summary_lines();
    preview.border_is_skin = scene.prep.cut_faces == palpsim::CutFaces::kSkin;
    preview.air_threshold = scene.prep.air_threshold;
    preview.bone_low = report.bone_thresholds.low;
    preview.bone_high = report.bone_thresholds.high;
    preview.units = report.units;
    palpsim::write_patient_outputs(out, *patient, report.json, preview);
    std::printf("palpsim-prep: %s -> %s (%d x %d x %d voxels of %.3g mm, body %.0f ml, bone %.0f ml, %.2f s%s)\n",
                patient->source.c_str(), out.c_str(), patient->grid.size.x, patient->grid.size.y,
                patient->grid.size.z, patient->grid.spacing_mm.x, report.body_ml, report.bone_ml, report.total_s,
                report.from_cache ? ", from cache" : "");
    // the chosen bone thresholds and the warnings, also in prep.json and under the preview
    std::printf("  scene %s\n", palpsim::scene_label(scene).c_str());
    for (const std::string& line : report.summary_lines()) std::printf("  %s\n", line.c_str());
    print_landmarks(palpsim::find_landmarks(*patient));
    return 0;
  } catch (const palpsim::Error& e) {
    std::fprintf(stderr, "palpsim-prep: error: %s\n", e.what());
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-prep: unexpected error: %s\n", e.what());
    return 1;
  }
}
