// Validated scene settings in the project's own types (the schema is proto/palpsim/scene.proto;
// server/net/scene_io.cpp converts a text-format file into this struct).
#pragma once

#include <string>
#include <vector>

namespace palpsim {

/// How prep treats the faces where the image's border cuts the body (prep.cut_faces).
enum class CutFaces {
  kSkin,  // a cut face counts as skin: the depth under the skin (B) measures to it, so a press into it meets skin
  kOpen,  // a cut face is missing data, not skin: B measures only to the outside air within the image
};

/// What prep makes of large smooth bright regions inside soft tissue, contrast-filled
/// chambers and vessels (prep.contrast).
enum class ContrastAs {
  kBone,    // they stay in the bone mask where its thresholds put them (the report names them)
  kTissue,  // they are left out of the bone mask: soft tissue that the finger can press
};

/// Preprocessing settings (Prep in the schema).
struct PrepSettings {
  double spacing_mm = 0;            // 0 = smallest input spacing clamped to [0.5, 2] mm
  double air_threshold = -400;      // HU (or image units when air_threshold_set)
  double bone_threshold = 200;      // HU (or image units when bone_threshold_set); the bone mask's only when set
  bool air_threshold_set = false;   // the scene set it explicitly
  bool bone_threshold_set = false;  // the scene set it explicitly; false: the bone mask's thresholds are automatic
                                    // (and relaxation's material function steps at the automatic low one)
  double bone_min_volume_ml = 0.5;  // smaller bone components are removed unless within 10 mm of larger bone (a rib's end)
  double bone_closing_mm = 3.0;     // closing radius before hole filling
  bool bone_fill_holes = true;      // fill cavities enclosed by bone
  double max_memory_mb = 8192;      // refuse larger patients
  std::string dicom_series_uid;     // "" = the only series in the folder
  std::string cache_dir;            // "" = $PALPSIM_CACHE or ~/.cache/palpsim
  bool use_cache = true;
  double body_opening_mm = 5.0;     // opening radius that cuts the table's thin shell off the body
  double body_min_part_ml = 20;     // body parts apart from the largest are kept from this size up
  CutFaces cut_faces = CutFaces::kSkin;  // whether the faces where the image cuts the body count as skin
  ContrastAs contrast = ContrastAs::kBone;  // whether contrast-filled chambers and vessels may be bone
};

/// Eq. 1 parameters; A, B and F in mm.
struct ForceImageSettings {
  double alpha = 200.0 / 3.0;  // mm^2
  double beta = 2.0;           // mm
  double gamma = 1.0 / 60.0;   // dimensionless
};

/// Where the skin point X, the deformation's grabbed element, is put (haptics.skin_point).
enum class SkinPointRule {
  kNormal,  // the skin point nearest to the tip (out along the skin's normal): the dent under the finger
  kLine,    // the paper's: where the line through x and p crosses the skin (nearest skin point where
            // that line runs within ~20 degrees of the skin or misses it)
};

/// Which force the pose thread renders (haptics.force_model).
enum class ForceModel {
  kProxy,    // eq. 2: the proxy on F's gradient and a spring (the paper's)
  kElastic,  // the elastic model's reaction on the fingertip, from the deformation worker's local linear model
};

/// Force model parameters. These defaults are the server's one source (a session slot
/// starts with them); scene.proto's [default]s, which a scene without the field gets, must
/// equal them (tests/unit/scene_io_test.cpp checks).
struct HapticsSettings {
  double stiffness_n_per_mm = 0.25;      // N/mm
  double friction = 0.2;                 // 0 = none, towards 1 = proxy sticks
  double max_force_n = 3.3;              // N (a Phantom Omni / Touch's largest)
  double max_force_rate_n_per_s = 2000;
  double min_gradient_norm = 1e-4;       // |grad F| below this keeps the last direction
  SkinPointRule skin_point = SkinPointRule::kNormal;  // scene-wide (not a session parameter)
  ForceModel force_model = ForceModel::kProxy;         // scene-wide
  double elastic_max_jump_n = 0.05;      // elastic: the most a new local model may move the force at once (N)
  bool passivity = true;                 // scene-wide: the pose path's passivity controller limits the force
                                         // (haptics/passivity.h); its observer runs either way
};

/// One point of the elastic model's table from intensity to Young's modulus.
struct ModulusPoint {
  double hu = 0;     // intensity (HU, or the image's units)
  double e_kpa = 0;  // Young's modulus (kPa)
};

/// The elastic model's settings (Deform.elastic in the schema; server/deform/README.md).
struct ElasticSettings {
  // Young's modulus by intensity, sorted by HU, linear between points (defaults: lung
  // and gas, fat, soft tissue and muscle; the schema's comment cites the sources)
  std::vector<ModulusPoint> modulus = {{-900, 1.0}, {-200, 3.25}, {-50, 3.25}, {20, 12.0}};
  double skin_e_kpa = 35;          // body voxels within skin_thickness_mm of the skin
  double skin_thickness_mm = 2;
  double poisson = 0.45;           // in (0, 0.5)
  int max_iterations = 60;         // conjugate-gradient steps per contact round
  double tolerance = 1e-3;         // relative residual of a round
  int contact_rounds = 4;          // contact set updates per step
  bool predict = true;             // a warm step starts from the last press's field moved to this one
  double stiffness_tolerance = 0.01;  // the unit press's relative residual; above 0: force and stiffness by reciprocity
  int smooth_degree = 8;           // the V-cycle's Chebyshev degree on the finest level
  int coarse_smooth_degree = 2;    // ... on the coarse levels above the coarsest
  int coarsest_degree = 2;         // ... on the coarsest level
  double min_tissue_fraction = 0.5;  // the press stops where the tissue between it and bone would fall below this
                                     // fraction of its thickness along the press (deform/press_cap.h); 0: no stop
};

/// How relaxation follows ChainMail (deform.relax_method; names in core/setting_names.h).
enum class RelaxMethod {
  kExplicit,   // the paper's: relax_iterations explicit diffusion steps
  kMultigrid,  // relax_cycles multigrid-preconditioned steps towards the steady state
  kElastic,    // static linear elasticity pressed by a fingertip sphere (ElasticSettings)
};

/// Which deformation backend a scene asks for (deform.backend; names in core/setting_names.h).
enum class DeformBackendChoice {
  kAuto,  // cuda where a device and a CUDA build exist, else cpu
  kCpu,   // the CPU reference
  kCuda,  // the CUDA backend, refused where it is unavailable
};

/// ChainMail, relaxation and inversion parameters (voxel edge lengths where noted).
struct DeformSettings {
  double min_dist = 0.5;        // voxel
  double max_dist = 1.5;        // voxel
  double max_sheer = 0.5;       // voxel
  int voi_edge = 64;            // voxel
  bool whole_volume = false;
  int max_sweeps = 2048;
  RelaxMethod relax_method = RelaxMethod::kExplicit;
  int relax_iterations = 20;    // explicit steps
  double relax_step = 0.15;     // explicit diffusion step, stable below 1/6
  int relax_cycles = 4;         // multigrid steps (one V-cycle each) from zero
  int relax_warm_cycles = 1;    // multigrid steps when the last step's unit response is the start (the tip entered another voxel; one more where the grabbed element moved over a voxel); 0: relax_cycles from zero
  double grab_radius_mm = 0;    // multigrid: soft elements this close to the grabbed one move with it (a fingertip); 0: it alone;
                                // elastic: the fingertip sphere's radius (above 0)
  double material_width = 50;   // HU, width of the material function's step at bone
  int invert_iterations = 8;
  bool untangle = false;        // untangle relaxation's folds before the inversion (server/deform/README.md)
  bool invert_search = false;   // search the cells where Newton stalls: every voxel resolved (server/deform/README.md)
  DeformBackendChoice backend = DeformBackendChoice::kAuto;
  ElasticSettings elastic;      // RelaxMethod::kElastic
};

/// Effects a scene calls for; only these stages are built.
struct EffectsSettings {
  bool haptics = true;
  bool chainmail = false;
  bool relaxation = false;
  bool inversion = false;
  bool frames = false;
  bool bricks = false;
};

/// Server settings.
struct ServerSettings {
  double session_timeout_s = 5;
  int max_sessions = 64;
};

/// The 3D view's transfer-function preset, and the slices' window (render.preset, a
/// viewer's ViewSettings.preset; names in core/setting_names.h).
enum class RenderPreset {
  kSkin,        // the skin surface, opaque, skin-coloured, with gradient shading
  kBone,        // bone opaque and ivory, soft tissue faint; slices in a bone window
  kSoftTissue,  // muscle and organs translucent in a soft-tissue window, fat faint, bone white
};

/// Which JPEG encoder the render thread uses (render.jpeg_encoder; names in core/setting_names.h).
enum class JpegEncoderChoice {
  kAuto,    // nvjpeg where it can be used, else cpu
  kCpu,     // libjpeg-turbo
  kNvjpeg,  // nvJPEG through CUDA-GL interop, refused where it is unavailable
};

/// How the render thread writes J into the overlay textures (render.overlay_writer; names
/// in core/setting_names.h).
enum class OverlayWriterChoice {
  kAuto,    // cuda-gl where it can be used, else upload
  kUpload,  // a glTexSubImage3D upload from the host
  kCudaGl,  // CUDA-GL interop from the device copy, refused where it is unavailable
};

/// Frames and bricks (Render in the schema): every session's default view, the frame
/// rate and the encoders. View fields mirror render::ViewSettings (server/render/view.h).
struct RenderSettings {
  int width = 1280;                     // pixels
  int height = 720;                     // pixels
  RenderPreset preset = RenderPreset::kBone;
  double azimuth_deg = 35;
  double elevation_deg = 25;
  double zoom = 1;
  int jpeg_quality = 85;
  double slice_fov_mm = 120;
  bool show_proxy = false;
  double max_fps = 30;                  // frames per second per session, at most
  JpegEncoderChoice jpeg_encoder = JpegEncoderChoice::kAuto;
  OverlayWriterChoice overlay_writer = OverlayWriterChoice::kAuto;
  std::string record_dir;               // resolved; "" = render only watched sessions
  double ray_step_vox = 1;              // the 3D view's ray step (voxel)
  int max_batch = 2;                    // frames drawn, then encoded together (render thread)
};

/// A whole validated scene.
struct Scene {
  std::string name;
  std::string description;
  std::string file;              // the scene file it came from ("" for the built-in default)
  bool use_phantom = true;       // false: ct_path names the CT
  std::string ct_path;           // resolved CT path (file or DICOM folder)
  double phantom_voxel_mm = 1.0;
  PrepSettings prep;
  ForceImageSettings force_image;
  HapticsSettings haptics;
  DeformSettings deform;
  EffectsSettings effects;
  ServerSettings server;
  RenderSettings render;
};

/// The scene as log lines name it: its name with its file and its CT ("'lumbar CT'
/// (scenes/a.textproto, CT /data/ct.nii.gz)"), since a scene copied to another CT
/// keeps its name.
inline std::string scene_label(const Scene& s) {
  return "'" + s.name + "' (" + (s.file.empty() ? std::string("built-in") : s.file) + ", " +
         (s.use_phantom ? std::string("phantom") : "CT " + s.ct_path) + ")";
}

}  // namespace palpsim
