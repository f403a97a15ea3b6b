// The scene's spellings of the settings that take one of a few names (deform.relax_method,
// deform.backend, haptics.skin_point, haptics.force_model, render.preset,
// render.jpeg_encoder, render.overlay_writer, prep.cut_faces, prep.contrast): one table per setting, the only place those
// names are listed, so that the parser, its messages and the code that needs a name
// (make_deform_backend by name, the wire's ViewSettings.preset) agree.
#pragma once

#include <string>

#include "core/error.h"
#include "core/scene.h"

namespace palpsim {

/// One value of a setting's enum and its spelling in a scene.
template <class E>
struct SettingName {
  E value;
  const char* name;
};

/// The table of a setting's names, specialised below, one per enum (`field` is the
/// setting as a scene names it, for messages).
template <class E>
struct SettingNames;

template <>
struct SettingNames<RelaxMethod> {
  static constexpr const char* field = "deform.relax_method";
  static constexpr SettingName<RelaxMethod> values[] = {
      {RelaxMethod::kExplicit, "explicit"}, {RelaxMethod::kMultigrid, "multigrid"}, {RelaxMethod::kElastic, "elastic"}};
};

template <>
struct SettingNames<DeformBackendChoice> {
  static constexpr const char* field = "deform.backend";
  static constexpr SettingName<DeformBackendChoice> values[] = {
      {DeformBackendChoice::kAuto, "auto"}, {DeformBackendChoice::kCpu, "cpu"}, {DeformBackendChoice::kCuda, "cuda"}};
};

template <>
struct SettingNames<SkinPointRule> {
  static constexpr const char* field = "haptics.skin_point";
  static constexpr SettingName<SkinPointRule> values[] = {{SkinPointRule::kNormal, "normal"},
                                                          {SkinPointRule::kLine, "line"}};
};

template <>
struct SettingNames<ForceModel> {
  static constexpr const char* field = "haptics.force_model";
  static constexpr SettingName<ForceModel> values[] = {{ForceModel::kProxy, "proxy"}, {ForceModel::kElastic, "elastic"}};
};

template <>
struct SettingNames<RenderPreset> {
  static constexpr const char* field = "render.preset";
  static constexpr SettingName<RenderPreset> values[] = {
      {RenderPreset::kSkin, "skin"}, {RenderPreset::kBone, "bone"}, {RenderPreset::kSoftTissue, "soft_tissue"}};
};

template <>
struct SettingNames<JpegEncoderChoice> {
  static constexpr const char* field = "render.jpeg_encoder";
  static constexpr SettingName<JpegEncoderChoice> values[] = {
      {JpegEncoderChoice::kAuto, "auto"}, {JpegEncoderChoice::kCpu, "cpu"}, {JpegEncoderChoice::kNvjpeg, "nvjpeg"}};
};

template <>
struct SettingNames<OverlayWriterChoice> {
  static constexpr const char* field = "render.overlay_writer";
  static constexpr SettingName<OverlayWriterChoice> values[] = {{OverlayWriterChoice::kAuto, "auto"},
                                                                {OverlayWriterChoice::kUpload, "upload"},
                                                                {OverlayWriterChoice::kCudaGl, "cuda-gl"}};
};

template <>
struct SettingNames<CutFaces> {
  static constexpr const char* field = "prep.cut_faces";
  static constexpr SettingName<CutFaces> values[] = {{CutFaces::kSkin, "skin"}, {CutFaces::kOpen, "open"}};
};

template <>
struct SettingNames<ContrastAs> {
  static constexpr const char* field = "prep.contrast";
  static constexpr SettingName<ContrastAs> values[] = {{ContrastAs::kBone, "bone"}, {ContrastAs::kTissue, "tissue"}};
};

/// The scene's spelling of `v` ("" for a value outside the table, which a cast can make).
template <class E>
const char* setting_name(E v) {
  for (const auto& n : SettingNames<E>::values)
    if (n.value == v) return n.name;
  return "";
}

/// Finds `text` among the setting's names; false (and `*out` untouched) when it is none of them.
template <class E>
bool parse_setting(const std::string& text, E* out) {
  for (const auto& n : SettingNames<E>::values)
    if (text == n.name) {
      *out = n.value;
      return true;
    }
  return false;
}

/// The setting's names in table order, for messages outside a scene ("skin, bone, soft_tissue").
template <class E>
std::string setting_names_listed() {
  std::string m;
  for (const auto& n : SettingNames<E>::values) m += (m.empty() ? "" : ", ") + std::string(n.name);
  return m;
}

/// The one line that refuses a name the setting does not have, e.g.
/// `deform.relax_method = "multigird"; allowed: "explicit", "multigrid", "elastic"`.
template <class E>
std::string unknown_setting_message(const std::string& text) {
  std::string m = std::string(SettingNames<E>::field) + " = \"" + text + "\"; allowed: ";
  bool first = true;
  for (const auto& n : SettingNames<E>::values) {
    m += (first ? "\"" : ", \"") + std::string(n.name) + "\"";
    first = false;
  }
  return m;
}

/// The value `text` names, for names outside a scene (a benchmark's command line); an
/// unknown name throws palpsim::Error with unknown_setting_message().
template <class E>
E setting_by_name(const std::string& text) {
  E value{};
  if (!parse_setting(text, &value)) throw Error(unknown_setting_message<E>(text));
  return value;
}

}  // namespace palpsim
