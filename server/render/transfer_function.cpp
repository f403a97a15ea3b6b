#include "render/transfer_function.h"

#include <algorithm>
#include <cmath>

namespace palpsim::render {
namespace {

// A control point: intensity (HU), colour (0..1), extinction (1/mm); the function is
// linear between points and constant beyond the ends.
struct Point {
  float hu, r, g, b, tau;
};

TransferFunction from_points(const std::vector<Point>& pts) {
  TransferFunction tf;
  tf.rgb.resize(3 * kTfSize);
  tf.tau.resize(kTfSize);
  for (int n = 0; n < kTfSize; ++n) {
    const float hu = TransferFunction::hu_of(n);
    // the segment holding hu, and the weight of its upper point
    std::size_t s = 0;
    while (s + 1 < pts.size() && pts[s + 1].hu < hu) ++s;
    const Point& a = pts[s];
    const Point& b = pts[std::min(s + 1, pts.size() - 1)];
    const float w = (b.hu > a.hu) ? std::clamp((hu - a.hu) / (b.hu - a.hu), 0.f, 1.f) : 0.f;
    tf.rgb[3 * n + 0] = a.r + w * (b.r - a.r);
    tf.rgb[3 * n + 1] = a.g + w * (b.g - a.g);
    tf.rgb[3 * n + 2] = a.b + w * (b.b - a.b);
    tf.tau[n] = a.tau + w * (b.tau - a.tau);
  }
  return tf;
}

}  // namespace

TransferFunction make_transfer_function(Preset p) {
  switch (p) {
    case Preset::kSkin:
      // an opaque skin-coloured surface where air turns into tissue (about -300 HU)
      return from_points({{-1024, 0.90f, 0.70f, 0.58f, 0},
                          {-450, 0.90f, 0.70f, 0.58f, 0},
                          {-250, 0.92f, 0.72f, 0.60f, 8.0f},
                          {3000, 0.92f, 0.72f, 0.60f, 8.0f}});
    case Preset::kBone:
      // soft tissue a faint reddish haze that gives the body's outline; bone (above
      // about 200 HU) opaque ivory, so a ray's first step into the cortex takes nearly
      // all of its opacity (no rings where the samples fall)
      return from_points({{-1024, 0.5f, 0.3f, 0.25f, 0},
                          {-400, 0.6f, 0.4f, 0.30f, 0},
                          {-100, 0.75f, 0.60f, 0.40f, 0.0008f},
                          {40, 0.75f, 0.38f, 0.30f, 0.0014f},
                          {140, 0.80f, 0.55f, 0.45f, 0.002f},
                          {200, 0.90f, 0.82f, 0.66f, 0.3f},
                          {300, 0.94f, 0.89f, 0.76f, 4.0f},
                          {1000, 1.00f, 0.97f, 0.90f, 8.0f}});
    case Preset::kSoftTissue:
      // the soft-tissue window (W400/L40) in translucent warm colours: fat a faint
      // yellow, fluid and organs pink, muscle red and denser, bone white and opaque
      return from_points({{-1024, 0.8f, 0.7f, 0.4f, 0},
                          {-300, 0.85f, 0.75f, 0.45f, 0},
                          {-160, 0.90f, 0.78f, 0.48f, 0.0005f},
                          {-60, 0.92f, 0.80f, 0.50f, 0.002f},
                          {0, 0.92f, 0.60f, 0.50f, 0.006f},
                          {20, 0.90f, 0.50f, 0.45f, 0.015f},
                          {40, 0.85f, 0.32f, 0.26f, 0.04f},
                          {80, 0.80f, 0.25f, 0.20f, 0.06f},
                          {150, 0.95f, 0.70f, 0.60f, 0.1f},
                          {220, 1.00f, 0.97f, 0.94f, 2.0f},
                          {300, 1.00f, 1.00f, 1.00f, 6.0f},
                          {1000, 1.00f, 1.00f, 1.00f, 8.0f}});
  }
  return make_transfer_function(Preset::kBone);
}

std::vector<float> preintegrate(const TransferFunction& tf, double step_mm) {
  // integrals of tau (T) and of tau * colour (K) over intensity, from the first entry,
  // in units of entries; the integrands are piecewise linear / quadratic, so sub-steps
  constexpr int kSub = 8;
  std::vector<double> T(kTfSize, 0.0), K(3 * kTfSize, 0.0);
  for (int n = 1; n < kTfSize; ++n) {
    double t = 0, k[3] = {0, 0, 0};
    for (int s = 0; s < kSub; ++s) {
      const double w = (s + 0.5) / kSub;  // midpoint rule on each sub-step
      const double tau = (1 - w) * tf.tau[n - 1] + w * tf.tau[n];
      t += tau / kSub;
      for (int c = 0; c < 3; ++c) k[c] += tau * ((1 - w) * tf.rgb[3 * (n - 1) + c] + w * tf.rgb[3 * n + c]) / kSub;
    }
    T[n] = T[n - 1] + t;
    for (int c = 0; c < 3; ++c) K[3 * n + c] = K[3 * (n - 1) + c] + k[c];
  }
  // each (front, back) pair: the mean extinction and colour along the step
  std::vector<float> out(std::size_t(4) * kTfSize * kTfSize);
  for (int b = 0; b < kTfSize; ++b)
    for (int f = 0; f < kTfSize; ++f) {
      float* o = &out[(std::size_t(b) * kTfSize + f) * 4];
      double tau_mean, rgb[3];
      const double dT = T[b] - T[f];
      if (f == b || std::fabs(dT) < 1e-12) {
        // constant intensity (or no extinction at all): the mean of the two ends
        tau_mean = 0.5 * (tf.tau[f] + tf.tau[b]);
        for (int c = 0; c < 3; ++c) rgb[c] = 0.5 * (tf.rgb[3 * f + c] + tf.rgb[3 * b + c]);
      } else {
        tau_mean = dT / double(b - f);
        for (int c = 0; c < 3; ++c) rgb[c] = (K[3 * b + c] - K[3 * f + c]) / dT;
      }
      const double alpha = 1.0 - std::exp(-tau_mean * step_mm);
      for (int c = 0; c < 3; ++c) o[c] = float(std::clamp(rgb[c], 0.0, 1.0) * alpha);
      o[3] = float(alpha);
    }
  return out;
}

float surface_hu(Preset p) { return p == Preset::kSkin ? -350.f : p == Preset::kBone ? 240.f : 200.f; }

Window slice_window(Preset p) { return p == Preset::kBone ? Window{300, 1500} : Window{40, 400}; }

}  // namespace palpsim::render
