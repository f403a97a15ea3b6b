// Scene loading: defaults, presets, paths, and refusal of bad scenes with file:line:column,
// and of scene files that are empty, not regular files or not names.
#include <catch2/catch.hpp>

#include <sys/stat.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <tuple>

#include "core/error.h"
#include "core/setting_names.h"
#include "deform/backend.h"
#include "net/scene_io.h"
#include "unit/prep_files.h"

using namespace palpsim;

namespace {
std::string error_of(const std::string& text) {
  try {
    parse_scene_text(text, "test.textproto");
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST_CASE("the default scene is the phantom with the paper's eq. 1 parameters") {
  const Scene s = default_scene();
  CHECK(s.use_phantom);
  CHECK(s.phantom_voxel_mm == 1.0);
  CHECK(s.force_image.alpha == Approx(200.0 / 3.0));
  CHECK(s.force_image.beta == 2.0);
  CHECK(s.force_image.gamma == Approx(1.0 / 60.0));
  CHECK(s.effects.haptics);
  CHECK_FALSE(s.effects.chainmail);
  CHECK(s.deform.min_dist == 0.5);
  CHECK(s.deform.max_sheer == 0.5);
}

TEST_CASE("preset p2 and single overrides") {
  const Scene s = parse_scene_text("phantom {} deform { preset: P2 max_sheer: 0.75 }", "x.textproto");
  CHECK(s.deform.min_dist == 0.25);
  CHECK(s.deform.max_dist == 1.5);
  CHECK(s.deform.max_sheer == 0.75);
}

TEST_CASE("explicit thresholds are marked as set") {
  const Scene s = parse_scene_text("phantom {} prep { bone_threshold: 180 }", "x.textproto");
  CHECK(s.prep.bone_threshold_set);
  CHECK_FALSE(s.prep.air_threshold_set);
}

TEST_CASE("relative ct paths resolve against the scene file") {
  const Scene s = parse_scene_text("ct_path: \"ct/a.nii.gz\"", "/tmp/scenes/s.textproto");
  CHECK_FALSE(s.use_phantom);
  CHECK(s.ct_path == "/tmp/scenes/ct/a.nii.gz");
}

TEST_CASE("an unknown field is refused with file:line:column") {
  const std::string e = error_of("phantom {}\nprep {\n  bone_treshold: 200\n}\n");
  CHECK(e.find("test.textproto:3:") != std::string::npos);
  CHECK(e.find("bone_treshold") != std::string::npos);
}

TEST_CASE("a wrong type is refused with file:line:column") {
  const std::string e = error_of("phantom {}\nhaptics { max_force_n: \"strong\" }\n");
  CHECK(e.find("test.textproto:2:") != std::string::npos);
}

TEST_CASE("an out-of-range value is refused with its location and the allowed range") {
  const std::string e = error_of("phantom {}\ndeform {\n  voi_edge: 16\n}\n");
  CHECK(e.find("test.textproto:3:3") != std::string::npos);
  CHECK(e.find("deform.voi_edge") != std::string::npos);
  CHECK(e.find("[32, 256]") != std::string::npos);
}

TEST_CASE("zero means automatic where the schema says so") {
  CHECK(error_of("phantom {} prep { spacing_mm: 0 }").empty());
  CHECK_FALSE(error_of("phantom {} prep { spacing_mm: 0.1 }").empty());
}

TEST_CASE("inconsistent settings are refused") {
  CHECK(error_of("phantom {} deform { min_dist: 0.9 max_dist: 1.0 }").empty());
  CHECK(error_of("phantom {} effects { relaxation: true }").find("effects.chainmail") != std::string::npos);
  CHECK(error_of("phantom {} deform { backend: \"opencl\" }").find("deform.backend") != std::string::npos);
}

TEST_CASE("every shipped scene loads, and its deformation settings pass the backends' checks") {
  int n = 0;
  for (const auto& e : std::filesystem::directory_iterator(PALPSIM_SOURCE_DIR "/config/scenes")) {
    if (e.path().extension() != ".textproto") continue;
    INFO(e.path().string());
    Scene s;
    CHECK_NOTHROW(s = load_scene_file(e.path().string()));
    // what the server checks before serving a scene (a fingertip with the explicit
    // relaxation, a step above the stable limit, ...), without a patient or a device
    if (s.effects.chainmail) CHECK_NOTHROW(check_deform_config(DeformConfig::from_scene(s), e.path().string()));
    ++n;
  }
  CHECK(n >= 3);
}

TEST_CASE("the field reference lists defaults and ranges") {
  const std::string doc = scene_field_reference();
  CHECK(doc.find("force_image.alpha") != std::string::npos);
  CHECK(doc.find("deform.voi_edge (int32) default 64, range [32, 256] voxel") != std::string::npos);
}

TEST_CASE("data: paths resolve under PALPSIM_DATA, and stay unresolved without a data folder") {
  const char* old = std::getenv("PALPSIM_DATA");
  const std::string saved = old ? old : "";
  setenv("PALPSIM_DATA", "/opt/ctdata", 1);
  CHECK(parse_scene_text("ct_path: \"data:ct/a.nii.gz\"", "/tmp/x/s.textproto").ct_path == "/opt/ctdata/ct/a.nii.gz");
  unsetenv("PALPSIM_DATA");
  // no shared/data above /tmp/palpsim-no-data: the scene loads, reading the CT will say what is missing
  if (!std::filesystem::exists("/tmp/shared/data") && !std::filesystem::exists("/shared/data"))
    CHECK(parse_scene_text("ct_path: \"data:ct/a.nii.gz\"", "/tmp/palpsim-no-data/s.textproto").ct_path ==
          "data:ct/a.nii.gz");
  if (!saved.empty()) setenv("PALPSIM_DATA", saved.c_str(), 1);
}

TEST_CASE("deform.relax_method and relax_cycles are read, checked and default as DeformSettings does") {
  const Scene d = parse_scene_text("phantom {}", "x.textproto");
  CHECK(d.deform.relax_method == DeformSettings{}.relax_method);
  CHECK(d.deform.relax_cycles == DeformSettings{}.relax_cycles);
  const Scene s = parse_scene_text("phantom {} deform { relax_method: \"multigrid\" relax_cycles: 7 }", "x.textproto");
  CHECK(s.deform.relax_method == RelaxMethod::kMultigrid);
  CHECK(s.deform.relax_cycles == 7);
  CHECK(error_of("phantom {} deform { relax_method: \"sor\" }").find("deform.relax_method") != std::string::npos);
  CHECK(error_of("phantom {} deform { relax_cycles: 101 }").find("deform.relax_cycles") != std::string::npos);
}

TEST_CASE("each named setting is read by its spelling and a misspelt one is refused in one line listing the allowed") {
  const Scene s = parse_scene_text(
      "phantom {} deform { relax_method: \"elastic\" grab_radius_mm: 5 backend: \"cpu\" } "
      "haptics { force_model: \"elastic\" skin_point: \"line\" } effects { chainmail: true relaxation: true }",
      "x.textproto");
  CHECK(s.deform.relax_method == RelaxMethod::kElastic);
  CHECK(s.deform.backend == DeformBackendChoice::kCpu);
  CHECK(s.haptics.force_model == ForceModel::kElastic);
  CHECK(s.haptics.skin_point == SkinPointRule::kLine);
  CHECK(parse_scene_text("phantom {} deform { relax_method: \"explicit\" backend: \"cuda\" }", "x.textproto")
            .deform.backend == DeformBackendChoice::kCuda);
  CHECK(DeformSettings{}.relax_method == RelaxMethod::kExplicit);
  CHECK(DeformSettings{}.backend == DeformBackendChoice::kAuto);
  CHECK(error_of("phantom {} deform { relax_method: \"multigird\" }") ==
        "test.textproto: deform.relax_method = \"multigird\"; allowed: \"explicit\", \"multigrid\", \"elastic\"");
  CHECK(error_of("phantom {} deform { backend: \"gpu\" }") ==
        "test.textproto: deform.backend = \"gpu\"; allowed: \"auto\", \"cpu\", \"cuda\"");
  CHECK(error_of("phantom {} haptics { force_model: \"spring\" }") ==
        "test.textproto: haptics.force_model = \"spring\"; allowed: \"proxy\", \"elastic\"");
  // the same names outside a scene (a benchmark's --backend), refused the same way
  CHECK(deform_backend_choice("cuda") == DeformBackendChoice::kCuda);
  CHECK_THROWS_WITH(deform_backend_choice("Cuda"), "deform.backend = \"Cuda\"; allowed: \"auto\", \"cpu\", \"cuda\"");
}

TEST_CASE("a scene without a haptics block has HapticsSettings' defaults (the schema's equal core/scene.h's)") {
  const HapticsSettings h = parse_scene_text("phantom {}", "x.textproto").haptics, d;
  const auto fields = [](const HapticsSettings& s) {
    return std::tie(s.stiffness_n_per_mm, s.friction, s.max_force_n, s.max_force_rate_n_per_s, s.min_gradient_norm,
                    s.skin_point, s.force_model, s.elastic_max_jump_n, s.passivity);
  };
  CHECK(fields(h) == fields(d));
  CHECK(d.stiffness_n_per_mm == 0.25);  // the documented defaults (README, scene.proto)
  CHECK(d.max_force_n == 3.3);
  CHECK(d.passivity);  // on by default (server/haptics/README.md says why)
  CHECK_FALSE(parse_scene_text("phantom {} haptics { passivity: false }", "x.textproto").haptics.passivity);
}

TEST_CASE("render.preset, jpeg_encoder and overlay_writer: every name is read, a misspelt one refused in one line") {
  // every name in each table parses to its value, and that value's name is the same
  for (const auto& n : SettingNames<RenderPreset>::values)
    CHECK(parse_scene_text(std::string("phantom {} render { preset: \"") + n.name + "\" }", "x.textproto")
              .render.preset == n.value);
  for (const auto& n : SettingNames<JpegEncoderChoice>::values)
    CHECK(parse_scene_text(std::string("phantom {} render { jpeg_encoder: \"") + n.name + "\" }", "x.textproto")
              .render.jpeg_encoder == n.value);
  for (const auto& n : SettingNames<OverlayWriterChoice>::values)
    CHECK(parse_scene_text(std::string("phantom {} render { overlay_writer: \"") + n.name + "\" }", "x.textproto")
              .render.overlay_writer == n.value);
  CHECK(std::string(setting_name(RenderPreset::kSoftTissue)) == "soft_tissue");
  CHECK(std::string(setting_name(OverlayWriterChoice::kCudaGl)) == "cuda-gl");
  // a scene without them gets RenderSettings' defaults
  const Scene d = parse_scene_text("phantom {}", "x.textproto");
  CHECK(d.render.preset == RenderPreset::kBone);
  CHECK(d.render.jpeg_encoder == JpegEncoderChoice::kAuto);
  CHECK(d.render.overlay_writer == OverlayWriterChoice::kAuto);
  CHECK(error_of("phantom {} render { preset: \"bones\" }") ==
        "test.textproto: render.preset = \"bones\"; allowed: \"skin\", \"bone\", \"soft_tissue\"");
  CHECK(error_of("phantom {} render { jpeg_encoder: \"turbojpeg\" }") ==
        "test.textproto: render.jpeg_encoder = \"turbojpeg\"; allowed: \"auto\", \"cpu\", \"nvjpeg\"");
  CHECK(error_of("phantom {} render { overlay_writer: \"cuda_gl\" }") ==
        "test.textproto: render.overlay_writer = \"cuda_gl\"; allowed: \"auto\", \"upload\", \"cuda-gl\"");
  // the same names outside a scene (render_bench's --jpeg-encoder), refused the same way
  CHECK(setting_by_name<JpegEncoderChoice>("nvjpeg") == JpegEncoderChoice::kNvjpeg);
  CHECK_THROWS_WITH(setting_by_name<OverlayWriterChoice>("Upload"),
                    "render.overlay_writer = \"Upload\"; allowed: \"auto\", \"upload\", \"cuda-gl\"");
}

TEST_CASE("haptics.skin_point is read, checked and defaults as HapticsSettings does") {
  CHECK(parse_scene_text("phantom {}", "x.textproto").haptics.skin_point == HapticsSettings{}.skin_point);
  CHECK(HapticsSettings{}.skin_point == SkinPointRule::kNormal);
  CHECK(parse_scene_text("phantom {} haptics { skin_point: \"line\" }", "x.textproto").haptics.skin_point ==
        SkinPointRule::kLine);
  CHECK(parse_scene_text("phantom {} haptics { skin_point: \"normal\" }", "x.textproto").haptics.skin_point ==
        SkinPointRule::kNormal);
  const std::string e = error_of("phantom {} haptics { skin_point: \"nearest\" }");
  CHECK(e.find("haptics.skin_point") != std::string::npos);
  CHECK(e.find("\"nearest\"") != std::string::npos);
}

TEST_CASE("prep.cut_faces is read, checked and defaults as PrepSettings does") {
  CHECK(PrepSettings{}.cut_faces == CutFaces::kSkin);
  CHECK(parse_scene_text("phantom {}", "x.textproto").prep.cut_faces == CutFaces::kSkin);
  CHECK(parse_scene_text("phantom {} prep { cut_faces: \"open\" }", "x.textproto").prep.cut_faces == CutFaces::kOpen);
  CHECK(parse_scene_text("phantom {} prep { cut_faces: \"skin\" }", "x.textproto").prep.cut_faces == CutFaces::kSkin);
  CHECK(error_of("phantom {} prep { cut_faces: \"closed\" }") ==
        "test.textproto: prep.cut_faces = \"closed\"; allowed: \"skin\", \"open\"");
}

TEST_CASE("prep.contrast is read, checked and defaults as PrepSettings does") {
  CHECK(PrepSettings{}.contrast == ContrastAs::kBone);
  CHECK(parse_scene_text("phantom {}", "x.textproto").prep.contrast == ContrastAs::kBone);
  CHECK(parse_scene_text("phantom {} prep { contrast: \"tissue\" }", "x.textproto").prep.contrast ==
        ContrastAs::kTissue);
  CHECK(parse_scene_text("phantom {} prep { contrast: \"bone\" }", "x.textproto").prep.contrast == ContrastAs::kBone);
  CHECK(error_of("phantom {} prep { contrast: \"vessel\" }") ==
        "test.textproto: prep.contrast = \"vessel\"; allowed: \"bone\", \"tissue\"");
}

TEST_CASE("a scene's label for the logs names its file and its CT, so a copied scene is told apart") {
  test::TempDir d;
  std::ofstream(d / "copy.textproto") << "name: \"lumbar CT\"\nct_path: \"other.nii.gz\"\n";
  const Scene s = load_scene_file(d / "copy.textproto");
  CHECK(scene_label(s) == "'lumbar CT' (" + (d / "copy.textproto") + ", CT " + (d / "other.nii.gz") + ")");
  CHECK(scene_label(parse_scene_text("name: \"p\" phantom {}", "")) == "'p' (built-in, phantom)");
}

TEST_CASE("an empty scene file, a folder, a FIFO and a path holding a NUL are refused, naming them") {
  test::TempDir d;
  auto error_of_file = [](const std::string& path) {
    try {
      load_scene_file(path);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  std::ofstream(d / "empty.textproto").close();
  std::ofstream(d / "blank.textproto") << "  \n# only a comment\n\n";
  for (const char* name : {"empty.textproto", "blank.textproto"}) {
    INFO(name);
    CHECK_THAT(error_of_file(d / name), Catch::Contains(name) && Catch::Contains("empty"));
  }
  CHECK_THAT(error_of_file(d.path.string()), Catch::Contains(d.path.string()) && Catch::Contains("folder"));
  // a FIFO is never opened for reading in blocking mode (no writer would ever come)
  REQUIRE(::mkfifo((d / "pipe.textproto").c_str(), 0600) == 0);
  CHECK_THAT(error_of_file(d / "pipe.textproto"), Catch::Contains("pipe.textproto") && Catch::Contains("FIFO"));
  // the part before the NUL names a good scene, which must not be loaded
  std::ofstream(d / "good.textproto") << "name: \"good\" phantom {}\n";
  CHECK_NOTHROW(load_scene_file(d / "good.textproto"));
  CHECK_THAT(error_of_file(d / "good.textproto" + std::string(1, '\0') + "x"), Catch::Contains("NUL"));
  // text that sets no field, as LoadScene's text
  CHECK_THAT(error_of("# nothing\n"), Catch::Contains("empty"));
}

TEST_CASE("haptics.force_model \"elastic\" needs the elastic step, and a scene without it is refused naming both fields") {
  const std::string elastic_deform =
      "phantom {} haptics { force_model: \"elastic\" } deform { relax_method: \"elastic\" grab_radius_mm: 5 } ";
  const Scene s = parse_scene_text(elastic_deform + "effects { chainmail: true relaxation: true }", "x.textproto");
  CHECK(s.haptics.force_model == ForceModel::kElastic);
  CHECK(DeformConfig::from_scene(s).elastic_stiffness);
  CHECK(DeformConfig::from_scene(s).elastic_force);
  {
    // the unit press also serves the prediction: solved with eq. 2's force too, unless the
    // scene predicts nothing; never without the elastic model
    const std::string eq2 = "phantom {} deform { relax_method: \"elastic\" grab_radius_mm: 5 ";
    const std::string effects = "effects { chainmail: true relaxation: true }";
    const DeformConfig predicts = DeformConfig::from_scene(parse_scene_text(eq2 + "} " + effects, "x.textproto"));
    CHECK(predicts.elastic_stiffness);
    CHECK_FALSE(predicts.elastic_force);
    const DeformConfig still =
        DeformConfig::from_scene(parse_scene_text(eq2 + "elastic { predict: false } } " + effects, "x.textproto"));
    CHECK_FALSE(still.elastic_stiffness);
    CHECK_FALSE(DeformConfig::from_scene(parse_scene_text("phantom {}", "x.textproto")).elastic_stiffness);
  }
  CHECK(parse_scene_text("phantom {}", "x.textproto").haptics.force_model == ForceModel::kProxy);
  // another relaxation has no reaction force to render
  for (const char* method : {"explicit", "multigrid"}) {
    const std::string e = error_of(std::string("phantom {} haptics { force_model: \"elastic\" } deform { relax_method: \"") +
                                   method + "\" } effects { chainmail: true relaxation: true }");
    INFO(e);
    CHECK(e.find("test.textproto") != std::string::npos);
    CHECK(e.find("haptics.force_model") != std::string::npos);
    CHECK(e.find("deform.relax_method") != std::string::npos);
    CHECK(e.find(std::string("\"") + method + "\"") != std::string::npos);
  }
  // nor does a scene that builds no elastic step
  const std::string e = error_of(elastic_deform + "effects { chainmail: true }");
  CHECK(e.find("haptics.force_model") != std::string::npos);
  CHECK(e.find("effects.relaxation") != std::string::npos);
  CHECK(error_of(elastic_deform).find("effects.chainmail") != std::string::npos);
}

TEST_CASE("a scene's elastic modulus table is read point by point, each point range-checked at its location") {
  const Scene s = parse_scene_text(
      "phantom {}\ndeform {\n  elastic {\n    modulus { point { hu: -100 e_kpa: 3.5 } point { hu: 40 e_kpa: 11 } }\n  }\n}\n",
      "test.textproto");
  REQUIRE(s.deform.elastic.modulus.size() == 2);
  CHECK(s.deform.elastic.modulus[0].hu == -100);
  CHECK(s.deform.elastic.modulus[0].e_kpa == 3.5);
  CHECK(s.deform.elastic.modulus[1].hu == 40);
  CHECK(s.deform.elastic.modulus[1].e_kpa == 11);
  // a point's hu beyond the schema's range [-1e6, 1e6] HU: the point, its line and column
  const std::string e = error_of("phantom {}\ndeform { elastic { modulus {\n  point { hu: 0 e_kpa: 3 }\n  point { hu: 2e6 e_kpa: 4 }\n} } }\n");
  CHECK_THAT(e, Catch::Contains("test.textproto:4:11") && Catch::Contains("deform.elastic.modulus.point[1].hu") &&
                    Catch::Contains("out of range"));
}

TEST_CASE("bad elastic settings in a scene are refused with the field named") {
  // what the server checks before serving a scene (LoadScene, and the worker at start):
  // the text parsed, then the deformation settings of a scene with the elastic model
  auto refusal = [](const std::string& elastic) -> std::string {
    const std::string text =
        "phantom {}\neffects { chainmail: true relaxation: true }\n"
        "deform { relax_method: \"elastic\" grab_radius_mm: 5\n  elastic { " + elastic + " }\n}\n";
    try {
      const Scene s = parse_scene_text(text, "test.textproto");
      check_deform_config(DeformConfig::from_scene(s), "test.textproto");
    } catch (const Error& e) {
      return e.what();
    }
    return "";
  };
  // the defaults and a good table of one point pass
  CHECK(refusal("").empty());
  CHECK(refusal("modulus { point { hu: 0 e_kpa: 10 } } poisson: 0.49").empty());
  // E <= 0 (and beyond 1e7 kPa, and not a number) in the table and for the skin
  for (const char* e : {"0", "-3", "inf", "nan"}) {
    INFO("e_kpa " << e);
    const std::string m = refusal(std::string("modulus { point { hu: -100 e_kpa: 3 } point { hu: 20 e_kpa: ") + e + " } }");
    CHECK_THAT(m, Catch::Contains("test.textproto") && Catch::Contains("deform.elastic.modulus.point[1].e_kpa") &&
                      Catch::Contains("above 0"));
  }
  CHECK_THAT(refusal("skin_e_kpa: 0"), Catch::Contains("deform.elastic.skin_e_kpa") && Catch::Contains("above 0"));
  CHECK_THAT(refusal("skin_e_kpa: -35"), Catch::Contains("deform.elastic.skin_e_kpa"));
  // nu outside (0, 0.5): both ends are refused (0.5 is incompressible)
  for (const char* nu : {"0", "0.5", "-0.2", "0.7", "nan"}) {
    INFO("poisson " << nu);
    CHECK_THAT(refusal(std::string("poisson: ") + nu),
               Catch::Contains("test.textproto") && Catch::Contains("deform.elastic.poisson") && Catch::Contains("(0, 0.5)"));
  }
  // an unsorted table (a point below the one before it, or equal to it) names the point
  CHECK_THAT(refusal("modulus { point { hu: 20 e_kpa: 12 } point { hu: -100 e_kpa: 3 } }"),
             Catch::Contains("deform.elastic.modulus.point[1].hu") && Catch::Contains("sorted"));
  CHECK_THAT(refusal("modulus { point { hu: -100 e_kpa: 3 } point { hu: 20 e_kpa: 12 } point { hu: 20 e_kpa: 14 } }"),
             Catch::Contains("deform.elastic.modulus.point[2].hu") && Catch::Contains("sorted"));
  // a point's hu that is not a number: out of the schema's range, at its location
  CHECK_THAT(refusal("modulus { point { hu: nan e_kpa: 3 } }"),
             Catch::Contains("test.textproto:4:") && Catch::Contains("deform.elastic.modulus.point[0].hu"));
  // an empty table: the message for `modulus { }` says what to give
  CHECK_THAT(refusal("modulus { }"), Catch::Contains("test.textproto") && Catch::Contains("deform.elastic.modulus is empty"));
  // the V-cycle's degrees: at least 2 (the GPU fuses a smoothing's first step) and at most 32
  CHECK(refusal("smooth_degree: 2 coarse_smooth_degree: 32 coarsest_degree: 2").empty());
  CHECK_THAT(refusal("smooth_degree: 1"), Catch::Contains("test.textproto") && Catch::Contains("deform.elastic.smooth_degree"));
  CHECK_THAT(refusal("coarse_smooth_degree: 33"), Catch::Contains("deform.elastic.coarse_smooth_degree"));
  CHECK_THAT(refusal("coarsest_degree: 0"), Catch::Contains("deform.elastic.coarsest_degree"));
  // every refusal is one line
  CHECK(refusal("poisson: 0.5").find('\n') == std::string::npos);
}
