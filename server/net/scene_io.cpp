#include "net/scene_io.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/io/tokenizer.h>
#include <google/protobuf/text_format.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <sstream>

#include "core/error.h"
#include "core/path_policy.h"
#include "core/setting_names.h"
#include "palpsim/options.pb.h"
#include "palpsim/scene.pb.h"

namespace palpsim {
namespace {

namespace fs = std::filesystem;
namespace gp = google::protobuf;
using gp::TextFormat;

// collects the parser's first error with its 1-based position
class FirstError : public gp::io::ErrorCollector {
 public:
  void AddError(int line, gp::io::ColumnNumber column, const std::string& message) override {
    if (message_.empty()) {
      std::ostringstream s;
      s << (line + 1) << ":" << (column + 1) << ": " << message;
      message_ = s.str();
    }
  }
  void AddWarning(int, gp::io::ColumnNumber, const std::string&) override {}
  const std::string& message() const { return message_; }

 private:
  std::string message_;
};

std::string where(const std::string& origin, const TextFormat::ParseLocation& loc) {
  std::ostringstream s;
  s << (origin.empty() ? "<scene>" : origin) << ":" << (loc.line + 1) << ":" << (loc.column + 1);
  return s.str();
}

// the setting a scene names by one of its spellings (core/setting_names.h), or the one
// line that refuses the name with the file and the allowed ones
template <class E>
E named_setting(const std::string& origin, const std::string& text) {
  E value{};
  if (!parse_setting(text, &value)) throw Error(origin + ": " + unknown_setting_message<E>(text));
  return value;
}

std::string fmt(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

// numeric value of a set scalar field, as double
double numeric_value(const gp::Message& m, const gp::FieldDescriptor* f) {
  const gp::Reflection* r = m.GetReflection();
  switch (f->cpp_type()) {
    case gp::FieldDescriptor::CPPTYPE_INT32: return r->GetInt32(m, f);
    case gp::FieldDescriptor::CPPTYPE_INT64: return double(r->GetInt64(m, f));
    case gp::FieldDescriptor::CPPTYPE_UINT32: return r->GetUInt32(m, f);
    case gp::FieldDescriptor::CPPTYPE_UINT64: return double(r->GetUInt64(m, f));
    case gp::FieldDescriptor::CPPTYPE_DOUBLE: return r->GetDouble(m, f);
    case gp::FieldDescriptor::CPPTYPE_FLOAT: return r->GetFloat(m, f);
    default: return 0;
  }
}

bool is_numeric(const gp::FieldDescriptor* f) {
  switch (f->cpp_type()) {
    case gp::FieldDescriptor::CPPTYPE_INT32:
    case gp::FieldDescriptor::CPPTYPE_INT64:
    case gp::FieldDescriptor::CPPTYPE_UINT32:
    case gp::FieldDescriptor::CPPTYPE_UINT64:
    case gp::FieldDescriptor::CPPTYPE_DOUBLE:
    case gp::FieldDescriptor::CPPTYPE_FLOAT: return true;
    default: return false;
  }
}

std::string range_text(const gp::FieldDescriptor* f) {
  const auto& o = f->options();
  std::string s = "[" + fmt(o.GetExtension(v1::min)) + ", " + fmt(o.GetExtension(v1::max)) + "]";
  if (o.GetExtension(v1::zero_means_auto)) s += " or 0 (automatic)";
  const std::string unit = o.GetExtension(v1::unit);
  if (!unit.empty() && unit != "1") s += " " + unit;
  return s;
}

// checks every set numeric field of `m` (recursively, each element of a repeated message as
// name[i]) against its (min)/(max) options
void check_ranges(const gp::Message& m, const TextFormat::ParseInfoTree* tree, const std::string& origin,
                  const std::string& prefix) {
  const gp::Reflection* r = m.GetReflection();
  std::vector<const gp::FieldDescriptor*> fields;
  r->ListFields(m, &fields);
  for (const gp::FieldDescriptor* f : fields) {
    const std::string name = prefix + f->name();
    if (f->cpp_type() == gp::FieldDescriptor::CPPTYPE_MESSAGE) {
      if (!f->is_repeated()) {
        check_ranges(r->GetMessage(m, f), tree ? tree->GetTreeForNested(f, -1) : nullptr, origin, name + ".");
        continue;
      }
      for (int i = 0; i < r->FieldSize(m, f); ++i)
        check_ranges(r->GetRepeatedMessage(m, f, i), tree ? tree->GetTreeForNested(f, i) : nullptr, origin,
                     name + "[" + std::to_string(i) + "].");
      continue;
    }
    if (!is_numeric(f) || f->is_repeated()) continue;
    // the location of a singular field (index -1; a repeated one's needs its index)
    const TextFormat::ParseLocation loc = tree ? tree->GetLocation(f, -1) : TextFormat::ParseLocation();
    const auto& o = f->options();
    if (!o.HasExtension(v1::min) && !o.HasExtension(v1::max)) continue;
    const double v = numeric_value(m, f);
    if (v == 0 && o.GetExtension(v1::zero_means_auto)) continue;
    const bool ok = std::isfinite(v) && (!o.HasExtension(v1::min) || v >= o.GetExtension(v1::min)) &&
                    (!o.HasExtension(v1::max) || v <= o.GetExtension(v1::max));
    if (!ok)
      throw Error(where(origin, loc) + ": " + name + " = " + fmt(v) + " is out of range; allowed: " +
                  range_text(f));
  }
}

// resolves "data:REL" and relative CT paths
std::string resolve_ct_path(const std::string& raw, const std::string& origin) {
  const fs::path base = origin.empty() ? fs::current_path() : fs::absolute(origin).parent_path();
  const std::string prefix = "data:";
  if (raw.rfind(prefix, 0) == 0) {
    const std::string rel = raw.substr(prefix.size());
    if (const char* env = std::getenv("PALPSIM_DATA"); env && *env) return (fs::path(env) / rel).string();
    // the nearest shared/data folder above the scene file
    for (fs::path d = base; !d.empty(); d = d.parent_path()) {
      if (fs::is_directory(d / "shared" / "data")) return (d / "shared" / "data" / rel).string();
      if (d == d.parent_path()) break;
    }
    // no data folder here: keep the name, so the scene still loads and reading the CT
    // later fails with a message that says how to provide the data
    return raw;
  }
  const fs::path p(raw);
  return (p.is_absolute() ? p : base / p).lexically_normal().string();
}

// prep: how the CT becomes a patient
PrepSettings to_prep(const v1::Prep& p, const std::string& origin) {
  PrepSettings out;
  out.spacing_mm = p.spacing_mm();
  out.air_threshold = p.air_threshold();
  out.bone_threshold = p.bone_threshold();
  out.air_threshold_set = p.has_air_threshold();
  out.bone_threshold_set = p.has_bone_threshold();
  out.bone_min_volume_ml = p.bone_min_volume_ml();
  out.bone_closing_mm = p.bone_closing_mm();
  out.bone_fill_holes = p.bone_fill_holes();
  out.max_memory_mb = p.max_memory_mb();
  out.dicom_series_uid = p.dicom_series_uid();
  out.cache_dir = p.cache_dir();
  out.use_cache = p.use_cache();
  out.body_opening_mm = p.body_opening_mm();
  out.body_min_part_ml = p.body_min_part_ml();
  out.cut_faces = named_setting<CutFaces>(origin, p.cut_faces());
  out.contrast = named_setting<ContrastAs>(origin, p.contrast());
  return out;
}

// haptics: the force model and its limits
HapticsSettings to_haptics(const v1::Haptics& h, const std::string& origin) {
  HapticsSettings out;
  out.stiffness_n_per_mm = h.stiffness_n_per_mm();
  out.friction = h.friction();
  out.max_force_n = h.max_force_n();
  out.max_force_rate_n_per_s = h.max_force_rate_n_per_s();
  out.min_gradient_norm = h.min_gradient_norm();
  out.skin_point = named_setting<SkinPointRule>(origin, h.skin_point());
  out.force_model = named_setting<ForceModel>(origin, h.force_model());
  out.elastic_max_jump_n = h.elastic_max_jump_n();
  out.passivity = h.passivity();
  return out;
}

// deform.elastic: the table as given (checked with the rest of deform by
// check_deform_config, which names the field), the defaults where it is left out
void read_elastic(const v1::Elastic& el, ElasticSettings& out) {
  if (el.has_modulus()) {
    out.modulus.clear();
    for (const auto& pt : el.modulus().point()) out.modulus.push_back({pt.hu(), pt.e_kpa()});
  }
  out.skin_e_kpa = el.skin_e_kpa();
  out.skin_thickness_mm = el.skin_thickness_mm();
  out.poisson = el.poisson();
  out.max_iterations = el.max_iterations();
  out.tolerance = el.tolerance();
  out.contact_rounds = el.contact_rounds();
  out.predict = el.predict();
  out.stiffness_tolerance = el.stiffness_tolerance();
  out.smooth_degree = el.smooth_degree();
  out.coarse_smooth_degree = el.coarse_smooth_degree();
  out.coarsest_degree = el.coarsest_degree();
  out.min_tissue_fraction = el.min_tissue_fraction();
}

// deform: the preset's ChainMail limits, the fields given over them, the rest as given
DeformSettings to_deform(const v1::Deform& d, const std::string& origin) {
  DeformSettings out;
  if (d.preset() == v1::Deform::P2) {
    out.min_dist = 0.25, out.max_dist = 1.5, out.max_sheer = 1.0;
  } else {
    out.min_dist = 0.5, out.max_dist = 1.5, out.max_sheer = 0.5;
  }
  if (d.has_min_dist()) out.min_dist = d.min_dist();
  if (d.has_max_dist()) out.max_dist = d.max_dist();
  if (d.has_max_sheer()) out.max_sheer = d.max_sheer();
  if (out.min_dist >= out.max_dist)
    throw Error(origin + ": deform.min_dist (" + fmt(out.min_dist) + ") must be below deform.max_dist (" +
                fmt(out.max_dist) + ")");
  out.voi_edge = d.voi_edge();
  out.whole_volume = d.whole_volume();
  out.max_sweeps = d.max_sweeps();
  out.relax_iterations = d.relax_iterations();
  out.relax_step = d.relax_step();
  out.relax_method = named_setting<RelaxMethod>(origin, d.relax_method());
  out.relax_cycles = d.relax_cycles();
  out.relax_warm_cycles = d.relax_warm_cycles();
  out.grab_radius_mm = d.grab_radius_mm();
  out.material_width = d.material_width();
  out.invert_iterations = d.invert_iterations();
  out.untangle = d.untangle();
  out.invert_search = d.invert_search();
  out.backend = named_setting<DeformBackendChoice>(origin, d.backend());
  read_elastic(d.elastic(), out.elastic);
  return out;
}

// effects, and the settings they need from the rest of the scene
EffectsSettings to_effects(const v1::Scene& s, const Scene& scene, const std::string& origin) {
  EffectsSettings out;
  const auto& e = s.effects();
  out.haptics = e.haptics();
  out.chainmail = e.chainmail();
  out.relaxation = e.relaxation();
  out.inversion = e.inversion();
  out.frames = e.frames();
  out.bricks = e.bricks();
  if ((out.relaxation || out.inversion) && !out.chainmail)
    throw Error(origin + ": effects.relaxation and effects.inversion need effects.chainmail: true");
  // the elastic force is the elastic step's reaction: without that step there is none to render
  if (scene.haptics.force_model == ForceModel::kElastic) {
    if (scene.deform.relax_method != RelaxMethod::kElastic)
      throw Error(origin + ": haptics.force_model = \"elastic\" needs deform.relax_method = \"elastic\" (got \"" +
                  s.deform().relax_method() + "\"): the force is the elastic step's reaction on the fingertip");
    if (!out.chainmail || !out.relaxation)
      throw Error(origin +
                  ": haptics.force_model = \"elastic\" needs effects.chainmail: true and effects.relaxation: true "
                  "(the deformation worker's elastic step computes the force)");
  }
  return out;
}

// frames and bricks: names checked here so a bad scene is refused with its file
RenderSettings to_render(const v1::Render& r, const std::string& origin) {
  RenderSettings out;
  out.width = r.width();
  out.height = r.height();
  out.preset = named_setting<RenderPreset>(origin, r.preset());
  out.azimuth_deg = r.azimuth_deg();
  out.elevation_deg = r.elevation_deg();
  out.zoom = r.zoom();
  out.jpeg_quality = r.jpeg_quality();
  out.slice_fov_mm = r.slice_fov_mm();
  out.show_proxy = r.show_proxy();
  out.max_fps = r.max_fps();
  out.ray_step_vox = r.ray_step_vox();
  out.max_batch = r.max_batch();
  out.jpeg_encoder = named_setting<JpegEncoderChoice>(origin, r.jpeg_encoder());
  out.overlay_writer = named_setting<OverlayWriterChoice>(origin, r.overlay_writer());
  if (!r.record_dir().empty()) {
    const fs::path dir(r.record_dir());
    const fs::path base = origin.empty() ? fs::current_path() : fs::absolute(origin).parent_path();
    out.record_dir = (dir.is_absolute() ? dir : base / dir).lexically_normal().string();
  }
  return out;
}

Scene to_scene(const v1::Scene& s, const std::string& origin) {
  Scene out;
  out.file = origin;
  out.name = s.name();
  out.description = s.description();
  if (s.has_ct_path()) {
    if (s.ct_path().empty()) throw Error(origin + ": ct_path is empty");
    out.use_phantom = false;
    out.ct_path = resolve_ct_path(s.ct_path(), origin);
  } else {
    out.use_phantom = true;
    out.phantom_voxel_mm = s.phantom().voxel_mm();
  }
  out.prep = to_prep(s.prep(), origin);
  const auto& f = s.force_image();
  out.force_image.alpha = f.alpha();
  out.force_image.beta = f.beta();
  out.force_image.gamma = f.gamma();
  out.haptics = to_haptics(s.haptics(), origin);
  out.deform = to_deform(s.deform(), origin);
  out.effects = to_effects(s, out, origin);
  out.server.session_timeout_s = s.server().session_timeout_s();
  out.server.max_sessions = s.server().max_sessions();
  out.render = to_render(s.render(), origin);
  return out;
}

void describe(const gp::Descriptor* d, const std::string& prefix, std::ostringstream& out) {
  for (int i = 0; i < d->field_count(); ++i) {
    const gp::FieldDescriptor* f = d->field(i);
    const std::string name = prefix + f->name();
    if (f->cpp_type() == gp::FieldDescriptor::CPPTYPE_MESSAGE) {
      describe(f->message_type(), name + ".", out);
      continue;
    }
    out << name << " (" << f->type_name() << ")";
    if (f->has_default_value()) {
      switch (f->cpp_type()) {
        case gp::FieldDescriptor::CPPTYPE_DOUBLE: out << " default " << fmt(f->default_value_double()); break;
        case gp::FieldDescriptor::CPPTYPE_INT32: out << " default " << f->default_value_int32(); break;
        case gp::FieldDescriptor::CPPTYPE_BOOL: out << " default " << (f->default_value_bool() ? "true" : "false"); break;
        case gp::FieldDescriptor::CPPTYPE_STRING: out << " default \"" << f->default_value_string() << "\""; break;
        case gp::FieldDescriptor::CPPTYPE_ENUM: out << " default " << f->default_value_enum()->name(); break;
        default: break;
      }
    }
    const auto& o = f->options();
    if (o.HasExtension(v1::min) || o.HasExtension(v1::max)) out << ", range " << range_text(f);
    else if (o.HasExtension(v1::unit)) out << ", unit " << o.GetExtension(v1::unit);
    out << "\n";
  }
}

}  // namespace

Scene parse_scene_text(const std::string& text, const std::string& origin) {
  v1::Scene msg;
  TextFormat::Parser parser;
  FirstError errors;
  TextFormat::ParseInfoTree tree;
  parser.RecordErrorsTo(&errors);
  parser.WriteLocationsTo(&tree);
  if (!parser.ParseFromString(text, &msg))
    throw Error((origin.empty() ? "<scene>" : origin) + ":" + errors.message());
  // an empty scene (no byte, only blanks or comments) is a mistake, not the defaults
  std::vector<const gp::FieldDescriptor*> set;
  msg.GetReflection()->ListFields(msg, &set);
  if (set.empty())
    throw Error((origin.empty() ? std::string("<scene>") : origin) +
                ": the scene is empty (no field set); a scene names at least its ct_path or phantom");
  check_ranges(msg, &tree, origin, "");
  return to_scene(msg, origin);
}

Scene load_scene_file(const std::string& path) {
  // opened without blocking and read only when it is a regular file (a FIFO would stall)
  const std::string text = read_file_head(path, kMaxSceneBytes + 1, "scene file");
  if (text.size() > kMaxSceneBytes)
    throw Error(path + ": the scene file is larger than " + std::to_string(kMaxSceneBytes) + " bytes");
  return parse_scene_text(text, path);
}

Scene default_scene() {
  Scene s = parse_scene_text("name: \"phantom (built-in default)\" phantom {}", "");
  s.file.clear();
  return s;
}

std::string scene_field_reference() {
  std::ostringstream out;
  describe(v1::Scene::descriptor(), "", out);
  return out.str();
}

}  // namespace palpsim
