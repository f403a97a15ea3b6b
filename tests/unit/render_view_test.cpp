// View settings of the render path: preset names and check_view's ranges (a bad value
// is refused with the field, its value and the allowed range, never clamped).
#include <catch2/catch.hpp>

#include <cmath>
#include <limits>
#include <string>

#include "core/setting_names.h"
#include "render/transfer_function.h"
#include "render/view.h"

using namespace palpsim;
using namespace palpsim::render;

namespace {

// true when `text` contains `part`
bool has(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

}  // namespace

TEST_CASE("preset names round-trip and unknown names are refused", "[render][view]") {
  for (Preset p : {Preset::kSkin, Preset::kBone, Preset::kSoftTissue}) {
    Preset q = Preset::kSkin;
    REQUIRE(parse_setting(setting_name(p), &q));
    CHECK(q == p);
    CHECK(has(setting_names_listed<Preset>(), setting_name(p)));
  }
  CHECK(setting_names_listed<Preset>() == "skin, bone, soft_tissue");
  Preset q = Preset::kSoftTissue;
  CHECK_FALSE(parse_setting("bones", &q));
  CHECK_FALSE(parse_setting("", &q));
  CHECK_FALSE(parse_setting("Bone", &q));  // names are lower case
  CHECK(q == Preset::kSoftTissue);         // untouched on failure
}

TEST_CASE("check_view accepts the defaults and the ends of every range", "[render][view]") {
  ViewSettings v;
  CHECK(check_view(v).empty());
  v.width = kMinFrameEdge;
  v.height = kMinFrameEdge;
  v.zoom = kMinZoom;
  v.elevation_deg = -89;
  v.jpeg_quality = 1;
  v.slice_fov_mm = kMinSliceFovMm;
  v.azimuth_deg = -12345;  // any finite azimuth (taken modulo 360)
  CHECK(check_view(v).empty());
  v.width = kMaxFrameWidth;
  v.height = kMaxFrameHeight;
  v.zoom = kMaxZoom;
  v.elevation_deg = 89;
  v.jpeg_quality = 100;
  v.slice_fov_mm = kMaxSliceFovMm;
  CHECK(check_view(v).empty());
}

TEST_CASE("check_view names the first bad field, its value and the range", "[render][view]") {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  ViewSettings v;

  SECTION("0 x 0") {
    v.width = 0;
    v.height = 0;
    CHECK(check_view(v) == "width = 0 is outside 64..3840 pixels");
    v.width = 640;
    CHECK(check_view(v) == "height = 0 is outside 64..2160 pixels");
  }
  SECTION("100000 x 100000") {
    v.width = 100000;
    v.height = 100000;
    CHECK(check_view(v) == "width = 100000 is outside 64..3840 pixels");
    v.width = 3840;
    CHECK(check_view(v) == "height = 100000 is outside 64..2160 pixels");
  }
  SECTION("NaN and infinity in the camera") {
    v.azimuth_deg = nan;
    CHECK(has(check_view(v), "azimuth_deg"));
    v.azimuth_deg = inf;
    CHECK(has(check_view(v), "azimuth_deg"));
    v.azimuth_deg = 0;
    v.elevation_deg = nan;
    CHECK(has(check_view(v), "elevation_deg"));
    v.elevation_deg = 90;
    CHECK(check_view(v) == "elevation_deg = 90 is outside -89..89 degrees");
    v.elevation_deg = 0;
    v.zoom = nan;
    CHECK(has(check_view(v), "zoom"));
    v.zoom = 0;
    CHECK(check_view(v) == "zoom = 0 is outside 0.1..20");
    v.zoom = 1;
    v.center_mm = {0, nan, 0};
    CHECK(has(check_view(v), "center_mm"));
    v.center_mm = {0, 0, -inf};
    CHECK(has(check_view(v), "center_mm"));
  }
  SECTION("slices and JPEG") {
    v.slice_fov_mm = 5;
    CHECK(check_view(v) == "slice_fov_mm = 5 is outside 10..2000 mm");
    v.slice_fov_mm = nan;
    CHECK(has(check_view(v), "slice_fov_mm"));
    v.slice_fov_mm = 100;
    v.jpeg_quality = 0;
    CHECK(check_view(v) == "jpeg_quality = 0 is outside 1..100");
    v.jpeg_quality = 101;
    CHECK(has(check_view(v), "jpeg_quality = 101"));
  }
  SECTION("an unknown preset") {
    v.preset = static_cast<Preset>(7);
    CHECK(has(check_view(v), "preset = 7"));
    CHECK(has(check_view(v), setting_names_listed<Preset>()));
  }
}

TEST_CASE("pre-integrated transfer functions: constant steps and thin ramps", "[render][tf]") {
  const TransferFunction tf = make_transfer_function(Preset::kSkin);
  const double step_mm = 1.0;
  const std::vector<float> t = preintegrate(tf, step_mm);
  REQUIRE(t.size() == std::size_t(4) * kTfSize * kTfSize);
  auto at = [&](int front, int back) { return &t[(std::size_t(back) * kTfSize + front) * 4]; };
  auto entry = [](float hu) { return int(std::lround((hu - kTfMinHu) / (kTfMaxHu - kTfMinHu) * (kTfSize - 1))); };
  // a step through constant intensity: opacity 1 - exp(-tau * length), colour times it
  // (float storage: 1e-6)
  for (int n : {entry(-1000), entry(-350), entry(40), entry(1000)}) {
    const float* e = at(n, n);
    const double a = 1 - std::exp(-tf.tau[n] * step_mm);
    CHECK(e[3] == Approx(a).margin(1e-6));
    CHECK(e[0] == Approx(tf.rgb[3 * n] * a).margin(1e-6));
  }
  // air stays clear; a step from air into skin, whose ends both miss the thin -450..-250
  // ramp's middle, is still nearly opaque (what point sampling would miss), and the same
  // both ways
  CHECK(at(entry(-1000), entry(-1000))[3] == 0.f);
  const float into = at(entry(-1000), entry(30))[3], out_of = at(entry(30), entry(-1000))[3];
  CHECK(into > 0.9f);
  CHECK(out_of == Approx(into).margin(1e-6));
  // the presets' windows of the slices
  CHECK(slice_window(Preset::kBone).width_hu == 1500);
  CHECK(slice_window(Preset::kBone).level_hu == 300);
  CHECK(slice_window(Preset::kSoftTissue).width_hu == 400);
  CHECK(slice_window(Preset::kSkin).level_hu == 40);
}
