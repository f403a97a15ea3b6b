#include "runtime/stream_state.h"

#include <algorithm>
#include <cinttypes>
#include <cstdio>

namespace palpsim::runtime {

double LatencyRing::quantile(double q) const {
  const std::size_t n = std::size_t(std::min<std::uint64_t>(count, kSize));
  if (n == 0) return 0;
  std::array<float, kSize> v;
  std::copy(ms.begin(), ms.begin() + n, v.begin());
  const std::size_t k = std::min(n - 1, std::size_t(q * double(n)));
  std::nth_element(v.begin(), v.begin() + k, v.begin() + n);
  return v[k];
}

render::ViewSettings default_view(const RenderSettings& r) {
  render::ViewSettings v;
  v.width = r.width;
  v.height = r.height;
  v.preset = r.preset;
  v.azimuth_deg = r.azimuth_deg;
  v.elevation_deg = r.elevation_deg;
  v.zoom = r.zoom;
  v.jpeg_quality = r.jpeg_quality;
  v.slice_fov_mm = r.slice_fov_mm;
  v.show_proxy = r.show_proxy;
  return v;
}

namespace {
std::string topic(const char* kind, std::uint64_t id) {
  char b[40];
  std::snprintf(b, sizeof b, "%s.%016" PRIx64, kind, id);
  return b;
}
}  // namespace

std::string frame_topic(std::uint64_t session_id) { return topic("frame", session_id); }
std::string brick_topic(std::uint64_t session_id) { return topic("brick", session_id); }

std::size_t held_bytes(const Latest<JSnapshot>& h) {
  std::size_t n = 0;
  for (int i = 0; i < 3; ++i) {
    const JSnapshot& s = h.buffer(i);
    n += s.host_j.capacity() * sizeof(float) + (s.device_j ? s.device_j->size() : 0);
  }
  return n;
}
std::size_t held_bytes(const Latest<EncodedFrame>& h) {
  std::size_t n = 0;
  for (int i = 0; i < 3; ++i) n += h.buffer(i).jpeg.capacity();
  return n;
}

}  // namespace palpsim::runtime
