// Transfer functions of the 3D view: per preset, colour and extinction over intensity
// (HU), and their pre-integrated table (a 2D lookup by the intensities at the front and
// back of one ray step), so thin opacity ramps such as the air/skin boundary are not
// missed between samples and one-voxel steps show no wood-grain rings.
#pragma once

#include <vector>

#include "render/view.h"

namespace palpsim::render {

/// Intensity range the tables cover (HU); values outside clamp to the ends.
constexpr float kTfMinHu = -1024, kTfMaxHu = 2048;
/// Entries per axis of the tables (about 12 HU apart).
constexpr int kTfSize = 256;

/// One preset's 1D transfer function on kTfSize entries evenly spaced over
/// kTfMinHu..kTfMaxHu: colour (0..1, not premultiplied) and extinction (1/mm).
struct TransferFunction {
  std::vector<float> rgb;  // 3 per entry
  std::vector<float> tau;  // extinction coefficient per entry (1/mm)
  /// Intensity (HU) of entry n.
  static float hu_of(int n) { return kTfMinHu + (kTfMaxHu - kTfMinHu) * float(n) / float(kTfSize - 1); }
};

/// The 1D transfer function of a preset.
TransferFunction make_transfer_function(Preset p);

/// Pre-integrated table of `tf` for ray steps of `step_mm`: kTfSize x kTfSize RGBA
/// (premultiplied colour, opacity), entry (front, back) at index back * kTfSize + front,
/// 4 floats each; the opacity of a step whose intensity runs linearly from front to back.
std::vector<float> preintegrate(const TransferFunction& tf, double step_mm);

/// Where a preset's opaque surfaces lie (HU): the middle of its main opacity ramp (skin
/// -350, bone 240, the soft-tissue preset's bone 200); shading takes the normal where a
/// ray step crosses it.
float surface_hu(Preset p);

/// Intensity window of the slices per preset (HU): bone W1500/L300, else W400/L40.
struct Window {
  double level_hu, width_hu;
};
Window slice_window(Preset p);

}  // namespace palpsim::render
