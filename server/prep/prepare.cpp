#include "prep/prepare.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <iomanip>
#include <limits>
#include <sstream>

#include "core/error.h"
#include "core/setting_names.h"
#include "prep/cache.h"
#include "prep/ct_io.h"
#include "prep/distance.h"
#include "prep/hash.h"
#include "prep/pipeline.h"
#include "prep/phantom.h"

namespace palpsim {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// JSON helpers: numbers (inf/nan as null), strings, arrays
std::string jnum(double v) {
  if (!std::isfinite(v)) return "null";
  std::ostringstream s;
  s << std::setprecision(10) << v;
  return s.str();
}
std::string jstr(const std::string& v) {
  std::string o = "\"";
  for (char c : v) {
    if (c == '"' || c == '\\') o += '\\', o += c;
    else if (c == '\n') o += "\\n";
    else if (static_cast<unsigned char>(c) < 0x20) o += ' ';
    else o += c;
  }
  return o + "\"";
}
std::string jvec(const Vec3& v) { return "[" + jnum(v.x) + ", " + jnum(v.y) + ", " + jnum(v.z) + "]"; }
std::string jgrid(const Grid& g) {
  std::string d = "[";
  for (int i = 0; i < 9; ++i) d += (i ? ", " : "") + jnum(g.direction[i]);
  d += "]";
  return "{\"size\": [" + std::to_string(g.size.x) + ", " + std::to_string(g.size.y) + ", " +
         std::to_string(g.size.z) + "], \"spacing_mm\": " + jvec(g.spacing_mm) + ", \"origin_mm\": " +
         jvec(g.origin_mm) + ", \"direction\": " + d + ", \"voxels\": " + std::to_string(g.count()) + "}";
}

// the settings that decide the result, for the cache key and the report
std::string settings_text(const Scene& s) {
  const PrepSettings& p = s.prep;
  const ForceImageSettings& f = s.force_image;
  std::ostringstream o;
  o << std::setprecision(17) << "spacing_mm=" << p.spacing_mm << " air_threshold=" << p.air_threshold
    << " bone_threshold=" << p.bone_threshold << " air_threshold_set=" << p.air_threshold_set
    << " bone_threshold_set=" << p.bone_threshold_set << " bone_min_volume_ml=" << p.bone_min_volume_ml
    << " bone_closing_mm=" << p.bone_closing_mm << " bone_fill_holes=" << p.bone_fill_holes
    << " dicom_series_uid=" << p.dicom_series_uid << " body_opening_mm=" << p.body_opening_mm
    << " body_min_part_ml=" << p.body_min_part_ml << " cut_faces=" << setting_name(p.cut_faces)
    << " contrast=" << setting_name(p.contrast) << " alpha=" << f.alpha << " beta=" << f.beta
    << " gamma=" << f.gamma;
  return o.str();
}

// the scene's settings for prep.json; a bone threshold the scene leaves unset is "auto" (the
// thresholds prep chose stand in the report's bone section)
std::string settings_json(const Scene& s) {
  const PrepSettings& p = s.prep;
  const ForceImageSettings& f = s.force_image;
  return "{\"prep\": {\"spacing_mm\": " + jnum(p.spacing_mm) + ", \"air_threshold\": " + jnum(p.air_threshold) +
         ", \"bone_threshold\": " + (p.bone_threshold_set ? jnum(p.bone_threshold) : std::string("\"auto\"")) +
         ", \"bone_min_volume_ml\": " +
         jnum(p.bone_min_volume_ml) + ", \"bone_closing_mm\": " + jnum(p.bone_closing_mm) +
         ", \"bone_fill_holes\": " + (p.bone_fill_holes ? "true" : "false") + ", \"body_opening_mm\": " +
         jnum(p.body_opening_mm) + ", \"body_min_part_ml\": " + jnum(p.body_min_part_ml) + ", \"cut_faces\": " + jstr(setting_name(p.cut_faces)) +
         ", \"contrast\": " + jstr(setting_name(p.contrast)) + ", \"max_memory_mb\": " +
         jnum(p.max_memory_mb) + "}, \"force_image\": {\"alpha\": " + jnum(f.alpha) + ", \"beta\": " +
         jnum(f.beta) + ", \"gamma\": " + jnum(f.gamma) + "}}";
}

// runs one stage and records its time
template <typename Fn>
auto timed(PrepReport& r, const char* name, Fn&& fn) {
  const auto t0 = Clock::now();
  if constexpr (std::is_void_v<decltype(fn())>) {
    fn();
    r.stage_s.emplace_back(name, seconds_since(t0));
  } else {
    auto v = fn();
    r.stage_s.emplace_back(name, seconds_since(t0));
    return v;
  }
}

std::string stages_json(const PrepReport& r) {
  std::string s = "{";
  for (std::size_t i = 0; i < r.stage_s.size(); ++i)
    s += (i ? ", " : "") + jstr(r.stage_s[i].first) + ": " + jnum(r.stage_s[i].second);
  return s + "}";
}

std::string jstrings(const std::vector<std::string>& v) {
  std::string w = "[";
  for (std::size_t i = 0; i < v.size(); ++i) w += (i ? ", " : "") + jstr(v[i]);
  return w + "]";
}

// the body mask's check: pieces, cross-section, warnings
std::string body_check_json(const BodyCheck& c) {
  return "{\"pieces\": " + std::to_string(c.pieces) + ", \"largest_piece_fraction\": " + jnum(c.largest_fraction) +
         ", \"mean_cross_section_cm2\": " + jnum(c.cross_section_cm2) + ", \"warnings\": " + jstrings(c.warnings) +
         "}";
}

// the vertebral column: extent along the superior axis, segments, canal, verdict
std::string spine_json(const SpineColumn& c) {
  return "{\"found\": " + std::string(c.found ? "true" : "false") + ", \"from_mm\": " + jnum(c.from_mm) +
         ", \"to_mm\": " + jnum(c.to_mm) + ", \"length_mm\": " + jnum(c.length_mm) + ", \"slices\": " +
         std::to_string(c.slices) + ", \"bone_slices\": " + std::to_string(c.bone_slices) + ", \"segments\": " +
         std::to_string(c.segments) + ", \"canal_slices\": " + std::to_string(c.canal_slices) +
         ", \"centroid_mm\": " + jvec(c.centroid_mm) + ", \"reason\": " + jstr(c.reason) + "}";
}

// the bone section of the report: thresholds (in `units`: HU, or the image's own units for
// an image not in HU, so their keys name no unit) and why, volume per region, warnings
std::string bone_json(const BoneThresholds& t, const BoneSummary& b, const std::string& units,
                      const std::vector<ContrastRegion>& contrast, double contrast_removed_ml) {
  const std::string w = jstrings(b.warnings);
  return "{\"thresholds\": {\"automatic\": " + std::string(t.automatic ? "true" : "false") + ", \"units\": " +
         jstr(units) + ", \"low\": " +
         jnum(t.low) + ", \"high\": " + jnum(t.high) + ", \"thin_seed\": " + jnum(t.thin_seed) +
         ", \"cancellous\": " + jnum(t.cancellous) +
         ", \"cancellous_axial\": " + jnum(t.cancellous_axial) + ", \"grow_mm\": " + jnum(t.grow_mm) +
         (t.automatic ? ", \"soft_tissue\": " + jnum(t.soft_tissue_hu) + ", \"soft_tissue_sigma\": " +
                            jnum(t.soft_tissue_sigma_hu) + ", \"disc_band\": [" + jnum(t.disc_lo) + ", " +
                            jnum(t.disc_hi) + "]"
                      : std::string()) +
         ", \"reason\": " + jstr(t.reason) + "}, \"regions_ml\": {\"spine\": " + jnum(b.spine_ml) +
         ", \"left\": " + jnum(b.left_ml) + ", \"right\": " + jnum(b.right_ml) + ", \"anterior\": " +
         jnum(b.anterior_ml) + "}, \"fraction_of_body\": " + jnum(b.bone_fraction) + ", \"spine_found\": " +
         (b.spine_found ? "true" : "false") + ", \"spine_slices\": " + std::to_string(b.spine_slices) +
         ", \"spine\": " + spine_json(b.column) + ", \"contrast_regions\": " + contrast_regions_json(contrast) +
         ", \"contrast_removed_ml\": " + jnum(contrast_removed_ml) +
         ", \"body_slices\": " + std::to_string(b.body_slices) + ", \"warnings\": " + w + "}";
}

// whether to look for contrast-filled regions: their limits (contrast.h) are in HU, so on
// an image in other units none is looked for, and a scene that asked for prep.contrast =
// "tissue" gets a warning (in the bone summary's) that nothing was left out
bool seek_contrast(const PrepSettings& prep, PrepReport& r) {
  if (r.units == "HU") return true;
  if (prep.contrast == ContrastAs::kTissue)
    r.bone_summary.warnings.push_back(
        "prep.contrast = \"tissue\" left nothing out: contrast-filled regions are found by limits in Hounsfield "
        "units, and this image is in " + r.units);
  return false;
}

// derives F and grad F, which the cache does not store
void derive_force(Patient& p, const Scene& scene, PrepReport& r) {
  p.force = timed(r, "force", [&] { return force_image(p, scene.force_image); });
  p.grad_force = timed(r, "gradient", [&] { return gradient_physical(p.force); });
}

// a cached patient's report: volumes, thresholds, bone per region, field of view and body
// check measured again; the units the first run found, from its report (a header cannot tell)
void measure_cached(Patient& p, const PrepSettings& prep, const std::string& core, PrepReport& r) {
  const double voxel_ml = p.grid.spacing_mm.x * p.grid.spacing_mm.y * p.grid.spacing_mm.z / 1000.0;
  r.body_ml = double(count_nonzero(p.body)) * voxel_ml;
  r.bone_ml = double(count_nonzero(p.bone)) * voxel_ml;
  r.bone_thresholds = choose_bone_thresholds(p.intensity, p.body, prep);
  p.bone_threshold_hu = r.bone_thresholds.low;
  r.bone_summary = summarize_bone(p.body, p.bone);
  r.units = core.find("\"units\": \"image units\"") != std::string::npos ? "image units" : "HU";
  if (seek_contrast(prep, r))
    r.contrast_regions = find_contrast_regions(p.intensity, p.body, p.bone, r.bone_thresholds, r.bone_summary.column);
  const std::size_t at = core.find("\"contrast_removed_ml\": ");
  if (at != std::string::npos) r.contrast_removed_ml = std::atof(core.c_str() + at + 23);
  r.field_of_view = find_cut_faces(p.body, prep.cut_faces);
  r.body_check = check_body(p.body, prep.air_threshold, r.units);
}

// the report's warnings (field of view, body mask, bone), logged on every run, a cached
// patient's too: a server that loads a patient from the cache warns as the first run did
void log_warnings(const std::string& source, const PrepReport& r) {
  if (!r.field_of_view.warning.empty()) spdlog::warn("prep: {}: {}", source, r.field_of_view.warning);
  for (const std::string& w : r.body_check.warnings) spdlog::warn("prep: {}: {}", source, w);
  for (const std::string& w : r.bone_summary.warnings) spdlog::warn("prep: {}: {}", source, w);
}

// "HU", or "image units" where the image failed the HU check and the scene's thresholds let it pass
std::string image_units(const std::string& what, const CtInfo& info, const PrepSettings& prep) {
  PrepSettings strict = prep;
  strict.air_threshold_set = strict.bone_threshold_set = false;
  try {
    check_hounsfield(what, info.pixel_type, info.min_value, info.max_value, strict);
  } catch (const Error&) {
    return "image units";
  }
  return "HU";
}

// the report's core (what the cache keeps): input, grid, settings, volumes, field of
// view, body check, bone, stage times
std::string report_core(const Scene& scene, const std::string& source, const CtInfo& info, const Patient& p,
                        const PrepReport& r) {
  const PrepSettings& prep = scene.prep;
  std::size_t patient_bytes = p.intensity.bytes() + p.body.bytes() + p.bone.bytes() + p.dist_bone_mm.bytes() +
                              p.dist_skin_mm.bytes() + p.force.bytes() + p.grad_force.bytes();
  float fmax = 0;
  for (float v : p.force.data) fmax = std::max(fmax, v);
  std::ostringstream s;
  s << "\n  \"format_version\": " << kPrepFormatVersion << ",\n  \"source\": " << jstr(source)
    << ",\n  \"input\": {\"path\": " << jstr(info.path) << ", \"format\": " << jstr(info.format)
    << ", \"pixel_type\": " << jstr(info.pixel_type) << ", \"stored_pixel_type\": " << jstr(info.stored_pixel_type)
    << ", \"series_uid\": " << jstr(info.series_uid)
    << ", \"files\": " << info.files.size() << ", \"grid\": " << jgrid(info.grid) << "},\n  \"value_range\": {\"min\": "
    << jnum(info.min_value) << ", \"max\": " << jnum(info.max_value) << ", \"units\": "
    << jstr(r.units) << "},\n  \"grid\": " << jgrid(p.grid) << ",\n  \"settings\": "
    << settings_json(scene) << ",\n  \"body_ml\": " << jnum(r.body_ml) << ",\n  \"bone_ml\": " << jnum(r.bone_ml)
    << ",\n  \"field_of_view\": " << field_of_view_json(r.field_of_view, prep.cut_faces)
    << ",\n  \"body_check\": " << body_check_json(r.body_check)
    << ",\n  \"has_bone\": " << (p.has_bone ? "true" : "false")
    << ",\n  \"bone\": " << bone_json(r.bone_thresholds, r.bone_summary, r.units, r.contrast_regions, r.contrast_removed_ml) << ",\n  \"force_max_mm\": " << jnum(fmax)
    << ",\n  \"patient_mb\": " << jnum(double(patient_bytes) / (1024.0 * 1024.0))
    << ",\n  \"stages_s\": " << stages_json(r);
  return s.str();
}

// the contrast-filled regions: found, logged, and with prep.contrast = "tissue" left
// out of the bone mask (small pieces of bone left beside them go too; the summary is
// measured again)
void find_contrast(Patient& p, const PrepSettings& prep, const std::string& source, PrepReport& r) {
  if (!seek_contrast(prep, r)) {
    spdlog::info("prep: {}: no contrast-filled regions looked for: their limits hold for Hounsfield units only, and "
                 "the image is in {}",
                 source, r.units);
    return;
  }
  Volume<std::uint8_t> regions;
  r.contrast_regions = timed(r, "contrast", [&] {
    return find_contrast_regions(p.intensity, p.body, p.bone, r.bone_thresholds, r.bone_summary.column, &regions);
  });
  for (const ContrastRegion& c : r.contrast_regions)
    spdlog::info("prep: {}: contrast-filled region of {:.0f} ml at ({:.0f}, {:.0f}, {:.0f}) mm LPS, mean {:.0f} {}, "
                 "{:.0f} ml of it in the bone mask",
                 source, c.volume_ml, c.centroid_mm.x, c.centroid_mm.y, c.centroid_mm.z, c.mean_hu, r.units, c.bone_ml);
  if (prep.contrast != ContrastAs::kTissue || r.contrast_regions.empty()) return;
  const double voxel_ml = p.grid.spacing_mm.x * p.grid.spacing_mm.y * p.grid.spacing_mm.z / 1000.0;
  const std::size_t before = count_nonzero(p.bone);
  for (std::size_t i = 0; i < p.bone.data.size(); ++i)
    if (regions.data[i]) p.bone.data[i] = 0;
  remove_small_components(p.bone, std::size_t(std::ceil(prep.bone_min_volume_ml / voxel_ml)));
  r.contrast_removed_ml = double(before - count_nonzero(p.bone)) * voxel_ml;
  r.bone_summary = summarize_bone(p.body, p.bone);
}

}  // namespace

void check_hounsfield(const std::string& what, const std::string& pixel_type, double min_value, double max_value,
                      const PrepSettings& prep) {
  std::string why;
  std::ostringstream s;
  if (pixel_type == "uint8") {
    why = "its voxels are unsigned 8-bit (0..255), which cannot hold Hounsfield units";
  } else if (min_value > -500) {
    s << "its smallest value is " << min_value << ", but a CT in HU holds air near -1000";
    why = s.str();
  } else if (min_value < -32768 || max_value > 32767) {
    s << "its values span " << min_value << " .. " << max_value << ", beyond any CT's -32768 .. 32767 HU";
    why = s.str();
  }
  if (why.empty() || (prep.air_threshold_set && prep.bone_threshold_set)) return;
  // a hint: where -400 HU (air) and 200 HU (bone) fall when -1000..1000 HU span the image's range
  const double span = max_value - min_value;
  throw Error(what + " does not look like Hounsfield units: " + why +
              ". To process it anyway, set both scene fields prep.air_threshold and prep.bone_threshold "
              "(palpsim-prep: --air-threshold V --bone-threshold V) in the image's own units; where the image "
              "maps -1000..1000 HU linearly onto its range " + jnum(min_value) + ".." + jnum(max_value) +
              ", the default -400 and 200 HU are about " + jnum(std::round(min_value + 0.3 * span)) + " and " +
              jnum(std::round(min_value + 0.6 * span)));
}

PatientPtr build_patient(const Volume<float>& image, const Scene& scene, const std::string& source,
                         PrepReport* report) {
  PrepReport local;
  PrepReport& r = report ? *report : local;
  const PrepSettings& prep = scene.prep;
  auto p = std::make_shared<Patient>();
  p->source = source;

  // all air: nothing at or above the air threshold
  float hi = -std::numeric_limits<float>::infinity();
  for (float v : image.data) hi = std::max(hi, v);
  if (!(hi >= prep.air_threshold)) {
    std::ostringstream s;
    s << source << ": an all-air volume (largest value " << hi << " is below prep.air_threshold = "
      << prep.air_threshold << "); there is no patient to palpate";
    throw Error(s.str());
  }

  // isotropic patient grid, air outside the input
  const Grid grid = isotropic_grid(image.grid, patient_spacing_mm(image.grid, prep.spacing_mm));
  p->grid = grid;
  const float air = float(std::min(-1024.0, prep.air_threshold - 1.0));
  if (grid.same_geometry(image.grid)) {
    p->intensity = timed(r, "resample", [&] { return image; });
  } else {
    p->intensity = timed(r, "resample", [&] { return resample_linear(image, grid, air); });
  }

  // masks
  p->body = timed(r, "body_mask", [&] {
    return body_mask(p->intensity, prep.air_threshold, prep.body_opening_mm, prep.body_min_part_ml);
  });
  const double voxel_ml = grid.spacing_mm.x * grid.spacing_mm.y * grid.spacing_mm.z / 1000.0;
  r.body_ml = double(count_nonzero(p->body)) * voxel_ml;
  if (r.body_ml == 0)
    throw Error(source + ": no body found (only thin structures above prep.air_threshold = " +
                jnum(prep.air_threshold) + ", e.g. a table or noise)");
  r.field_of_view = find_cut_faces(p->body, prep.cut_faces);
  r.body_check = check_body(p->body, prep.air_threshold, r.units);
  // cavities are looked for after a closing of twice the input's coarsest spacing
  const double coarsest = std::max({image.grid.spacing_mm.x, image.grid.spacing_mm.y, image.grid.spacing_mm.z});
  p->bone = timed(r, "bone_mask", [&] {
    r.bone_thresholds = choose_bone_thresholds(p->intensity, p->body, prep);
    return bone_mask(p->intensity, p->body, r.bone_thresholds, prep, 2 * coarsest);
  });
  p->bone_threshold_hu = r.bone_thresholds.low;
  r.bone_summary = summarize_bone(p->body, p->bone);
  find_contrast(*p, prep, source, r);
  r.bone_ml = double(count_nonzero(p->bone)) * voxel_ml;
  log_warnings(source, r);
  p->has_bone = r.bone_ml > 0;

  // distance maps: A to bone (inf without bone), B depth under the skin
  p->dist_bone_mm = timed(r, "dist_bone", [&] { return distance_to_mask_mm(p->bone); });
  p->dist_skin_mm = timed(r, "dist_skin", [&] { return depth_under_skin_mm(p->body, prep.cut_faces); });
  derive_force(*p, scene, r);
  return p;
}

PatientPtr prepare_patient(const Scene& scene, PrepReport* report, const PathPolicy* files) {
  const auto t0 = Clock::now();
  PrepReport local;
  PrepReport& r = report ? *report : local;
  r = PrepReport{};
  const PrepSettings& prep = scene.prep;

  // the input: the phantom, or the CT's header (checked before anything is hashed)
  CtInfo info;
  Volume<float> phantom;
  std::string source;
  Sha256 sha;
  sha.update_field("palpsim-prep format " + std::to_string(kPrepFormatVersion));
  sha.update_field(settings_text(scene));
  if (scene.use_phantom) {
    source = "phantom";
    // the memory estimate from the phantom's geometry alone, before any voxel is made
    const Grid in = phantom_grid(scene.phantom_voxel_mm);
    const Grid out = isotropic_grid(in, patient_spacing_mm(in, prep.spacing_mm));
    const double mb = double(estimate_prep_bytes(in, out)) / (1024.0 * 1024.0);
    if (mb > prep.max_memory_mb)
      throw Error("phantom at " + jnum(scene.phantom_voxel_mm) + " mm: preparing it would need about " + jnum(std::round(mb)) +
                  " MiB, above the scene's prep.max_memory_mb = " + jnum(prep.max_memory_mb));
    phantom = timed(r, "phantom", [&] { return make_phantom(scene.phantom_voxel_mm).hu; });
    info.path = "phantom";
    info.format = "procedural phantom";
    info.pixel_type = info.stored_pixel_type = "float";
    info.grid = phantom.grid;
    float lo = std::numeric_limits<float>::infinity(), hi = -lo;
    for (float v : phantom.data) lo = std::min(lo, v), hi = std::max(hi, v);
    info.min_value = lo, info.max_value = hi;
    timed(r, "hash", [&] {
      sha.update_field("phantom");
      sha.update(&phantom.grid.size, sizeof phantom.grid.size);
      sha.update(&phantom.grid.spacing_mm, sizeof phantom.grid.spacing_mm);
      sha.update(&phantom.grid.origin_mm, sizeof phantom.grid.origin_mm);
      sha.update(phantom.data.data(), phantom.bytes());
    });
  } else {
    source = scene.ct_path;
    info = timed(r, "header", [&] { return read_ct_info(scene.ct_path, prep, files); });
    if (prep.use_cache)
      timed(r, "hash", [&] {
        for (const auto& f : info.files) {
          sha.update_field(fs::path(f).filename().string());
          hash_file(sha, f);
        }
      });
  }

  // a cached patient with the same content key
  const std::string root = prep.use_cache ? cache_root(prep) : "";
  if (prep.use_cache) {
    r.cache_key = sha.hex();
    const std::string entry = (fs::path(root) / r.cache_key).string();
    const auto tl = Clock::now();
    auto p = std::make_shared<Patient>();
    std::string core;
    if (load_cached_patient(entry, *p, core)) {
      r.stage_s.emplace_back("cache_read", seconds_since(tl));
      derive_force(*p, scene, r);
      r.from_cache = true;
      r.cache_path = entry;
      measure_cached(*p, prep, core, r);
      log_warnings(source, r);
      r.total_s = seconds_since(t0);
      r.json = "{" + core + ",\n  \"cache\": {\"hit\": true, \"key\": " + jstr(r.cache_key) + ", \"path\": " +
               jstr(entry) + ", \"this_run_stages_s\": " + stages_json(r) + "},\n  \"total_s\": " +
               jnum(r.total_s) + "}";
      spdlog::info("prep: {} from cache {} in {:.2f} s", source, entry, r.total_s);
      return p;
    }
  }

  // read the CT (memory limit, NaN/Inf and truncation checked there)
  if (!scene.use_phantom) {
    CtImage ct = timed(r, "read", [&] { return read_ct(scene.ct_path, prep, files); });
    info = ct.info;
    phantom = std::move(ct.image);
  }
  const std::string what = scene.use_phantom ? std::string("the phantom") : "CT '" + source + "'";
  check_hounsfield(what, info.pixel_type, info.min_value, info.max_value, prep);
  r.units = image_units(what, info, prep);
  PatientPtr p = build_patient(phantom, scene, what, &r);
  phantom = Volume<float>();

  // the report (the cache keeps its core)
  const std::string core = report_core(scene, source, info, *p, r);

  // store in the cache; a cache that cannot be written costs only the reuse
  if (prep.use_cache) {
    try {
      const auto tw = Clock::now();
      r.cache_path = store_cached_patient(root, r.cache_key, *p, core);
      r.stage_s.emplace_back("cache_write", seconds_since(tw));
    } catch (const Error& e) {
      spdlog::warn("prep: not cached: {}", e.what());
      r.cache_path.clear();
    }
  }
  r.total_s = seconds_since(t0);
  r.json = "{" + core + ",\n  \"cache\": {\"hit\": false, \"key\": " + jstr(r.cache_key) + ", \"path\": " +
           jstr(r.cache_path) + "},\n  \"total_s\": " + jnum(r.total_s) + "}";
  spdlog::info("prep: {} prepared in {:.2f} s ({} x {} x {} voxels of {} mm)", source, r.total_s, p->grid.size.x,
               p->grid.size.y, p->grid.size.z, p->grid.spacing_mm.x);
  return p;
}

std::vector<std::string> PrepReport::summary_lines() const {
  const BoneThresholds& t = bone_thresholds;
  const BoneSummary& b = bone_summary;
  std::vector<std::string> lines;
  std::ostringstream s;
  const std::string u = " " + units;
  s << std::fixed << std::setprecision(0);
  if (t.automatic && t.high > t.low)
    s << "bone auto: " << t.low << u << " grown from seeds " << t.high << u << " (thin " << t.thin_seed << u
      << ", soft tissue " << t.soft_tissue_hu << u << "), cavities from " << t.cancellous << u;
  else
    s << "bone threshold " << t.low << u << " (" << t.reason << "), cavities from " << t.cancellous << u;
  lines.push_back(s.str());
  s.str("");
  s << "bone " << b.bone_ml << " ml (" << std::setprecision(1) << 100 * b.bone_fraction << std::setprecision(0)
    << "% of body " << b.body_ml << " ml): spine " << b.spine_ml << ", left " << b.left_ml << ", right " << b.right_ml
    << ", anterior " << b.anterior_ml << " ml";
  lines.push_back(s.str());
  s.str("");
  const SpineColumn& c = b.column;
  if (c.found)
    s << "spine: " << c.length_mm << " mm along the axis (z " << c.from_mm << " .. " << c.to_mm << " mm), "
      << c.segments << " vertebra-like segments, canal in " << c.canal_slices << " slices";
  else
    s << "no spine: " << c.reason;
  lines.push_back(s.str());
  if (!contrast_regions.empty()) {
    s.str("");
    double total = 0;
    for (const ContrastRegion& r : contrast_regions) total += r.volume_ml;
    s << "contrast-filled regions: " << total << " ml in " << contrast_regions.size() << " (";
    for (std::size_t i = 0; i < contrast_regions.size() && i < 3; ++i) {
      const ContrastRegion& r = contrast_regions[i];
      s << (i ? "; " : "") << r.volume_ml << " ml at " << r.centroid_mm.x << ", " << r.centroid_mm.y << ", "
        << r.centroid_mm.z << " mm";
    }
    s << (contrast_regions.size() > 3 ? "; ..." : "") << "), "
      << (contrast_removed_ml > 0 ? "left out of the bone mask (prep.contrast = \"tissue\")"
                                  : "bone where the thresholds put them (prep.contrast = \"bone\")");
    lines.push_back(s.str());
  }
  if (!field_of_view.warning.empty()) lines.push_back("warning: " + field_of_view.warning);
  for (const std::string& w : body_check.warnings) lines.push_back("warning: " + w);
  for (const std::string& w : b.warnings) lines.push_back("warning: " + w);
  return lines;
}

}  // namespace palpsim
