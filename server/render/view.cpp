#include "render/view.h"

#include <cmath>
#include <sstream>

#include "core/setting_names.h"

namespace palpsim::render {

namespace {

// "name = value is outside lo..hi unit", with values printed as a person would write them
template <typename T>
std::string outside(const char* name, T value, T lo, T hi, const char* unit) {
  std::ostringstream s;
  s << name << " = " << value << " is outside " << lo << ".." << hi;
  if (unit && *unit) s << " " << unit;
  return s.str();
}

std::string not_finite(const char* name, double value) {
  std::ostringstream s;
  s << name << " = " << value << " is not a finite number";
  return s.str();
}

// true when lo <= v <= hi (false for NaN)
bool within(double v, double lo, double hi) { return v >= lo && v <= hi; }

}  // namespace

std::string check_view(const ViewSettings& v) {
  // frame size (pixels)
  if (v.width < kMinFrameEdge || v.width > kMaxFrameWidth)
    return outside("width", v.width, kMinFrameEdge, kMaxFrameWidth, "pixels");
  if (v.height < kMinFrameEdge || v.height > kMaxFrameHeight)
    return outside("height", v.height, kMinFrameEdge, kMaxFrameHeight, "pixels");
  // the preset must be one of the enum's values (a cast integer may not be)
  if (!*setting_name(v.preset)) {
    std::ostringstream s;
    s << "preset = " << int(v.preset) << " is not one of " << setting_names_listed<Preset>();
    return s.str();
  }
  // camera
  if (!std::isfinite(v.azimuth_deg)) return not_finite("azimuth_deg", v.azimuth_deg);
  if (!std::isfinite(v.elevation_deg)) return not_finite("elevation_deg", v.elevation_deg);
  if (!within(v.elevation_deg, -89, 89)) return outside("elevation_deg", v.elevation_deg, -89.0, 89.0, "degrees");
  if (!std::isfinite(v.zoom)) return not_finite("zoom", v.zoom);
  if (!within(v.zoom, kMinZoom, kMaxZoom)) return outside("zoom", v.zoom, kMinZoom, kMaxZoom, "");
  if (!is_finite(v.center_mm)) {
    std::ostringstream s;
    s << "center_mm = (" << v.center_mm.x << ", " << v.center_mm.y << ", " << v.center_mm.z
      << ") is not a finite point (mm)";
    return s.str();
  }
  // encoding and slices
  if (v.jpeg_quality < 1 || v.jpeg_quality > 100) return outside("jpeg_quality", v.jpeg_quality, 1, 100, "");
  if (!std::isfinite(v.slice_fov_mm)) return not_finite("slice_fov_mm", v.slice_fov_mm);
  if (!within(v.slice_fov_mm, kMinSliceFovMm, kMaxSliceFovMm))
    return outside("slice_fov_mm", v.slice_fov_mm, kMinSliceFovMm, kMaxSliceFovMm, "mm");
  return {};
}

}  // namespace palpsim::render
