// The CUDA render path (cuda/render_interop.cu) on an NVIDIA GPU through EGL: the
// "cuda-gl" overlay writer against the "upload" writer (bit for bit: both copy the same
// floats), the deformation backend's device copy of J against its host copy (bit for
// bit), and the "nvjpeg" encoder against the rendered frame and the CPU encoder (within
// the JPEG tolerances stated at each check). Prints, without asserting, the time per call
// of the encoders and writers at 1280x720 and a 64^3 VOI.
#include <catch2/catch.hpp>

#define GL_GLEXT_PROTOTYPES 1
#include <GL/glcorearb.h>

#include <cuda_runtime.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "core/device_bytes.h"
#include "core/error.h"
#include "cuda/render_interop.h"
#include "deform/backend.h"
#include "deform/engine.h"
#include "render/egl_context.h"
#include "render/frame_encoder.h"
#include "render/frame_renderer.h"
#include "render/overlay_writer.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {

// ---- set-up ----

bool have_gpu() {
  std::string why;
  if (cuda::cuda_render_available(&why)) return true;
  std::printf("SKIPPED: %s\n", why.c_str());
  return false;
}

// A headless GL 4.5 context on the NVIDIA GPU (the interop needs GL and CUDA on one device).
std::unique_ptr<render::EglContext> nvidia_context() {
  auto ctx = render::EglContext::create();
  INFO("EGL context: " << ctx->describe());
  std::printf("EGL context: %s\n", ctx->describe().c_str());
  REQUIRE(ctx->nvidia());
  return ctx;
}

// The 96^3 torso of the deformation tests (1 mm, origin 0: voxel index = mm) with the
// body mask C set where there is tissue (not air), so that the renderer draws it; bone
// (intensity above 200 HU) comes from the fixture.
PatientPtr render_patient() {
  auto p = std::make_shared<Patient>(*make_torso_patient(96));
  p->body = Volume<std::uint8_t>(p->grid);
  for (std::size_t e = 0; e < p->intensity.data.size(); ++e) p->body.data[e] = p->intensity.data[e] > -500.0f ? 1 : 0;
  p->source = "synthetic torso 96^3";
  return p;
}

// The cuda backend with the paper's preset 1, relaxation and inversion on.
DeformConfig cuda_config(int voi_edge) {
  DeformConfig c = preset_config(1);
  c.settings.voi_edge = voi_edge;
  c.settings.backend = DeformBackendChoice::kCuda;
  return c;
}

// A press into the torso's top skin (the contact of the whole-step GPU test).
DeformContact press(int s) { return voxel_contact({48 + 3 * s, 14, 48}, {1.0, 6.0 + s, -1.0}); }

// A frame of the whole press: tip marker at the contact, camera and slices on it.
render::FrameMarks marks_at(const DeformContact& c) {
  render::FrameMarks m;
  m.has_tip = true;
  m.tip_mm = c.tip_mm;
  m.proxy_mm = c.tip_mm;
  m.contact = true;
  return m;
}

render::ViewSettings view_of(int w, int h) {
  render::ViewSettings v;
  v.width = w;
  v.height = h;
  v.preset = render::Preset::kBone;
  REQUIRE(render::check_view(v).empty());
  return v;
}

// Device memory owned by the test (cudaMalloc), for a J the test makes itself.
class TestDeviceBytes final : public DeviceBytes {
 public:
  explicit TestDeviceBytes(std::size_t n) : size_(n) { REQUIRE(cudaMalloc(&p_, n) == cudaSuccess); }
  ~TestDeviceBytes() override { cudaFree(p_); }
  void* data() override { return p_; }
  const void* data() const override { return p_; }
  std::size_t size() const override { return size_; }

 private:
  void* p_ = nullptr;
  std::size_t size_ = 0;
};

// ---- GL readback of an overlay texture ----

// Level 0 of a GL_R32F 3D texture as floats (i fastest) and its size, with the pack
// state set to plain tightly packed rows for the read and restored afterwards.
std::vector<float> read_r32f_texture(unsigned tex, Vec3i& size) {
  {
    // the renderer and the interop leave no GL error behind them
    INFO("a GL error was pending before the overlay readback");
    REQUIRE(glGetError() == GL_NO_ERROR);
  }
  GLint w = 0, h = 0, d = 0;
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_WIDTH, &w);
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_HEIGHT, &h);
  glGetTextureLevelParameteriv(tex, 0, GL_TEXTURE_DEPTH, &d);
  size = Vec3i{w, h, d};
  const GLenum pnames[] = {GL_PACK_ALIGNMENT,   GL_PACK_ROW_LENGTH, GL_PACK_IMAGE_HEIGHT,
                           GL_PACK_SKIP_PIXELS, GL_PACK_SKIP_ROWS,  GL_PACK_SKIP_IMAGES};
  GLint saved[6] = {}, pack_buffer = 0;
  for (int i = 0; i < 6; ++i) glGetIntegerv(pnames[i], &saved[i]);
  glGetIntegerv(GL_PIXEL_PACK_BUFFER_BINDING, &pack_buffer);
  glBindBuffer(GL_PIXEL_PACK_BUFFER, 0);
  for (int i = 0; i < 6; ++i) glPixelStorei(pnames[i], i == 0 ? 4 : 0);
  std::vector<float> v(std::size_t(w) * std::size_t(h) * std::size_t(d));
  glGetTextureImage(tex, 0, GL_RED, GL_FLOAT, GLsizei(v.size() * sizeof(float)), v.data());
  for (int i = 0; i < 6; ++i) glPixelStorei(pnames[i], saved[i]);
  glBindBuffer(GL_PIXEL_PACK_BUFFER, GLuint(pack_buffer));
  REQUIRE(glGetError() == GL_NO_ERROR);
  return v;
}

// Voxels of the VOI box where the overlay texture's bits differ from J's (i fastest).
long long texture_differs(unsigned tex, const Voi& voi, const float* j) {
  Vec3i size;
  const std::vector<float> t = read_r32f_texture(tex, size);
  REQUIRE(size.x >= voi.size.x);
  REQUIRE(size.y >= voi.size.y);
  REQUIRE(size.z >= voi.size.z);
  long long n = 0;
  for (int k = 0; k < voi.size.z; ++k)
    for (int jj = 0; jj < voi.size.y; ++jj)
      for (int i = 0; i < voi.size.x; ++i) {
        const float a = t[(std::size_t(k) * size.y + jj) * size.x + i], b = j[voi.index(i, jj, k)];
        n += std::memcmp(&a, &b, sizeof a) != 0;
      }
  return n;
}

// ---- image comparison ----

// mean absolute difference of two RGB8 images of equal size (levels of 255)
double mean_abs_diff(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b) {
  REQUIRE(a.size() == b.size());
  REQUIRE(!a.empty());
  double s = 0;
  for (std::size_t e = 0; e < a.size(); ++e) s += std::abs(int(a[e]) - int(b[e]));
  return s / double(a.size());
}

// the mean of channel c (0 R, 1 G, 2 B) of an RGB8 image
double channel_mean(const std::vector<std::uint8_t>& rgb, int c) {
  double s = 0;
  for (std::size_t e = std::size_t(c); e < rgb.size(); e += 3) s += rgb[e];
  return s / double(rgb.size() / 3);
}

// decodes a JPEG; the decoder must accept it
std::vector<std::uint8_t> decode(const std::vector<std::uint8_t>& jpeg, int& w, int& h) {
  std::vector<std::uint8_t> rgb;
  w = h = 0;
  REQUIRE(render::decode_jpeg_rgb(jpeg.data(), jpeg.size(), rgb, w, h));
  return rgb;
}

// JPEG at quality 90 with 4:2:0 chroma, against the exact frame (mean absolute error
// over every byte, levels of 255). The luminance quantiser steps at q90 are 1..~25
// levels of DCT coefficient, which leaves pixel errors of 1-3 levels in shaded regions;
// chroma at half resolution smears the 1-pixel cut lines, frames and markers (tens of
// levels, on a few percent of the pixels); the black background stays exact. Measured
// with libjpeg-turbo on this scene's frames (Mesa llvmpipe, 2026-11-23): 0.62 / 0.94 /
// 1.56 levels at 1280x720 / 640x360 / 320x180 (small frames have relatively more edges).
// 4 levels leaves room (2.5x at the worst size) for nvJPEG's own DCT and chroma filter,
// and still fails a flipped, shifted or garbage image by a wide margin (tens of levels).
constexpr double kJpegMaeQ90 = 4.0;
// JPEG keeps block averages up to rounding (the DC term is quantised with a step of
// ~2-3 levels at q90, and pixels clip at 0 and 255 only near edges): each channel's mean
// over the frame stays within 1.5 levels of the frame's (libjpeg-turbo: within 0.16 on
// this scene), while swapping R and B moves it by 2.3 levels here (the frame's R and B
// means are 35.7 and 38.0) and a dimmed or brightened image by more.
constexpr double kJpegChannelMeanQ90 = 1.5;

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

}  // namespace

TEST_CASE("the cuda-gl writer fills the overlay bit for bit as the upload writer, and the frames agree") {
  if (!have_gpu()) return;
  auto ctx = nvidia_context();
  const PatientPtr patient = render_patient();
  DeformEngine eng(patient, cuda_config(48));
  REQUIRE(eng.backend_name() == "cuda");
  const DeformContact c = press(0);
  const DeformStats st = eng.step(c);
  REQUIRE(st.chainmail.moved > 0);
  const Voi voi = eng.voi();
  const float* host_j = eng.deformed_brick();
  REQUIRE(host_j != nullptr);
  std::unique_ptr<DeviceBytes> dev_j;
  REQUIRE(eng.copy_brick_to_device(dev_j));

  // two overlays the size of this VOI (so that every texel is written), one per writer
  render::FrameRenderer r(patient);
  const auto ov_upload = r.add_overlay(voi.size), ov_cuda = r.add_overlay(voi.size);
  auto upload = render::make_overlay_writer(OverlayWriterChoice::kUpload, *ctx);
  auto cudagl = cuda::make_cuda_overlay_writer();
  CHECK(std::string(upload->name()) == "upload");
  CHECK(std::string(cudagl->name()) == "cuda-gl");
  render::OverlaySource host_src, dev_src;
  host_src.voi = dev_src.voi = voi;
  host_src.host_j = host_j;
  dev_src.device_j = dev_j.get();
  upload->write(r, ov_upload, host_src);
  cudagl->write(r, ov_cuda, dev_src);

  // the textures hold J exactly: same floats, same bits, at texel (i, j, k) of the VOI
  std::printf("VOI %dx%dx%d at (%d, %d, %d); overlay textures %u (upload) and %u (cuda-gl)\n", voi.size.x, voi.size.y,
              voi.size.z, voi.lo.x, voi.lo.y, voi.lo.z, r.overlay_texture(ov_upload), r.overlay_texture(ov_cuda));
  CHECK(texture_differs(r.overlay_texture(ov_upload), voi, host_j) == 0);
  CHECK(texture_differs(r.overlay_texture(ov_cuda), voi, host_j) == 0);

  // so the frames are the same bytes; and J shows: the frame differs from the undeformed one
  const render::ViewSettings view = view_of(640, 360);
  const render::FrameMarks marks = marks_at(c);
  render::FrameTimes t;
  std::vector<std::uint8_t> f_upload, f_cuda, f_plain;
  r.render(ov_upload, view, marks, t);
  r.read_rgb(f_upload, t);
  r.render(ov_cuda, view, marks, t);
  r.read_rgb(f_cuda, t);
  REQUIRE(f_upload.size() == std::size_t(640) * 360 * 3);
  CHECK(f_upload == f_cuda);
  const auto ov_plain = r.add_overlay(voi.size);  // starts empty: J = I
  r.render(ov_plain, view, marks, t);
  r.read_rgb(f_plain, t);
  CHECK(f_plain != f_upload);

  // an empty VOI clears the overlay: the frame is the undeformed one again
  cudagl->write(r, ov_cuda, render::OverlaySource{});
  std::vector<std::uint8_t> f_cleared;
  r.render(ov_cuda, view, marks, t);
  r.read_rgb(f_cleared, t);
  CHECK(f_cleared == f_plain);

  // without a device copy the writer falls back to the host upload, same texels
  cudagl->write(r, ov_cuda, host_src);
  CHECK(texture_differs(r.overlay_texture(ov_cuda), voi, host_j) == 0);

  // a removed overlay's texture name, reused by a new overlay, is registered afresh: the
  // writer must write the new texture, not the deleted one it had registered
  const unsigned old_name = r.overlay_texture(ov_cuda);
  cudagl->write(r, ov_cuda, dev_src);
  r.remove_overlay(ov_cuda);
  const auto ov_new = r.add_overlay(voi.size);
  std::printf("overlay texture name %u %s after remove + add\n", r.overlay_texture(ov_new),
              r.overlay_texture(ov_new) == old_name ? "reused" : "not reused");
  cudagl->write(r, ov_new, dev_src);
  CHECK(texture_differs(r.overlay_texture(ov_new), voi, host_j) == 0);
  std::vector<std::uint8_t> f_new;
  r.render(ov_new, view, marks, t);
  r.read_rgb(f_new, t);
  CHECK(f_new == f_upload);

  // J in neither memory, or a device copy too small for the VOI: refused, named
  render::OverlaySource none;
  none.voi = voi;
  CHECK_THROWS_AS(cudagl->write(r, ov_new, none), Error);
  TestDeviceBytes tiny(16);
  render::OverlaySource small = dev_src;
  small.device_j = &tiny;
  CHECK_THROWS_AS(cudagl->write(r, ov_new, small), Error);

  // writers go before the renderer and the context (CUDA resources of its textures)
  cudagl.reset();
  upload.reset();
}

TEST_CASE("copy_brick_to_device of a cuda step equals its host brick bit for bit") {
  if (!have_gpu()) return;
  const PatientPtr patient = make_torso_patient(96);
  DeformEngine eng(patient, cuda_config(64));
  REQUIRE(eng.backend_name() == "cuda");
  std::unique_ptr<DeviceBytes> d;
  // no J before the first step
  CHECK_FALSE(eng.copy_brick_to_device(d));
  CHECK(d == nullptr);
  const void* first = nullptr;
  for (int s = 0; s < 3; ++s) {
    INFO("step " << s);
    eng.step(press(s));
    const Voi voi = eng.voi();
    const float* host = eng.deformed_brick();
    REQUIRE(host != nullptr);
    REQUIRE(eng.copy_brick_to_device(d));
    REQUIRE(d != nullptr);
    const std::size_t bytes = std::size_t(voi.count()) * sizeof(float);
    REQUIRE(d->size() >= bytes);
    // the backend sizes the copy for its largest VOI (64^3 here), so it is allocated once
    if (s == 0) first = d->data();
    CHECK(d->data() == first);
    CHECK(d->size() == std::size_t(64) * 64 * 64 * sizeof(float));
    std::vector<float> back(std::size_t(voi.count()));
    REQUIRE(cudaMemcpy(back.data(), d->data(), bytes, cudaMemcpyDeviceToHost) == cudaSuccess);
    CHECK(std::memcmp(back.data(), host, bytes) == 0);
  }
  // after reset there is no J again
  eng.reset();
  CHECK_FALSE(eng.copy_brick_to_device(d));
  // the cpu backend keeps no J on a GPU
  DeformConfig cpu = cuda_config(64);
  cpu.settings.backend = DeformBackendChoice::kCpu;
  DeformEngine c(patient, cpu);
  c.step(press(0));
  std::unique_ptr<DeviceBytes> none;
  CHECK_FALSE(c.copy_brick_to_device(none));
  CHECK(none == nullptr);
}

TEST_CASE("the nvjpeg encoder's JPEG decodes to the frame within JPEG error and near the cpu encoder's") {
  if (!have_gpu()) return;
  auto ctx = nvidia_context();
  const PatientPtr patient = render_patient();
  render::FrameRenderer r(patient);
  const auto ov = r.add_overlay({48, 48, 48});

  // the factories pick the GPU paths on an NVIDIA context of a CUDA build
  std::string enc_note, writer_note;
  auto enc_auto = render::make_frame_encoder(JpegEncoderChoice::kAuto, *ctx, &enc_note);
  auto writer_auto = render::make_overlay_writer(OverlayWriterChoice::kAuto, *ctx, &writer_note);
  std::printf("auto: %s; %s\n", enc_note.c_str(), writer_note.c_str());
  CHECK(std::string(enc_auto->name()) == "nvjpeg");
  CHECK(std::string(writer_auto->name()) == "cuda-gl");
  writer_auto.reset();
  enc_auto.reset();

  const render::ViewSettings view = view_of(1280, 720);
  render::FrameTimes t;
  r.render(ov, view, marks_at(press(0)), t);
  std::vector<std::uint8_t> frame;
  r.read_rgb(frame, t);
  REQUIRE(frame.size() == std::size_t(1280) * 720 * 3);

  auto nv = cuda::make_nvjpeg_frame_encoder();
  auto tj = render::make_frame_encoder(JpegEncoderChoice::kCpu, *ctx);
  CHECK(std::string(nv->name()) == "nvjpeg");
  std::vector<std::uint8_t> j_nv, j_tj, j_nv30;
  render::FrameTimes tn, tt;
  nv->encode(r, 90, j_nv, tn);
  tj->encode(r, 90, j_tj, tt);
  nv->encode(r, 30, j_nv30, tn);
  CHECK(tn.readback_ms > 0);
  CHECK(tn.encode_ms > 0);

  int w = 0, h = 0;
  const std::vector<std::uint8_t> d_nv = decode(j_nv, w, h);
  CHECK(w == 1280);
  CHECK(h == 720);
  const std::vector<std::uint8_t> d_tj = decode(j_tj, w, h);
  REQUIRE(w == 1280);
  REQUIRE(h == 720);
  const std::vector<std::uint8_t> d_nv30 = decode(j_nv30, w, h);
  REQUIRE(w == 1280);
  REQUIRE(h == 720);

  const double e_nv = mean_abs_diff(d_nv, frame), e_tj = mean_abs_diff(d_tj, frame);
  const double e_nv_tj = mean_abs_diff(d_nv, d_tj), e_nv30 = mean_abs_diff(d_nv30, frame);
  std::printf("1280x720 q90: nvjpeg %zu bytes, mean |error| %.3f levels; turbojpeg %zu bytes, %.3f; "
              "nvjpeg vs turbojpeg %.3f; nvjpeg q30 %zu bytes, %.3f\n",
              j_nv.size(), e_nv, j_tj.size(), e_tj, e_nv_tj, j_nv30.size(), e_nv30);
  CHECK(e_nv <= kJpegMaeQ90);
  CHECK(e_tj <= kJpegMaeQ90);
  // each decode is within kJpegMaeQ90 of the frame, so within twice that of each other
  // by the triangle inequality; both encoders quantise the same DCT with tables of the
  // same quality, so they land far closer: one bound's worth is asserted
  CHECK(e_nv_tj <= kJpegMaeQ90);
  for (int ch = 0; ch < 3; ++ch) {
    INFO("channel " << ch << ": frame mean " << channel_mean(frame, ch) << ", nvjpeg " << channel_mean(d_nv, ch));
    CHECK(std::fabs(channel_mean(d_nv, ch) - channel_mean(frame, ch)) <= kJpegChannelMeanQ90);
  }
  // quality is honoured: q30 is smaller and coarser than q90
  CHECK(j_nv30.size() < j_nv.size());
  CHECK(e_nv30 > e_nv);
  // the same quality gives JPEGs of comparable size (same tables' scaling, baseline
  // Huffman coding in both); a factor of 2 either way allows for nvJPEG's own tables
  CHECK(double(j_nv.size()) <= 2.0 * double(j_tj.size()));
  CHECK(double(j_tj.size()) <= 2.0 * double(j_nv.size()));

  CHECK_THROWS_AS(nv->encode(r, 0, j_nv, tn), Error);
  CHECK_THROWS_AS(nv->encode(r, 101, j_nv, tn), Error);
}

TEST_CASE("batches: cuda-gl writes of several overlays and nvjpeg encodes of several targets equal one at a time") {
  if (!have_gpu()) return;
  auto ctx = nvidia_context();
  const PatientPtr patient = render_patient();
  DeformEngine eng(patient, cuda_config(48));
  const DeformContact c = press(0);
  REQUIRE(eng.step(c).chainmail.moved > 0);
  const Voi voi = eng.voi();
  const float* host_j = eng.deformed_brick();
  std::unique_ptr<DeviceBytes> dev_j;
  REQUIRE(eng.copy_brick_to_device(dev_j));
  render::FrameRenderer r(patient);
  auto cudagl = cuda::make_cuda_overlay_writer();
  render::OverlaySource dev_src, host_src;
  dev_src.voi = host_src.voi = voi;
  dev_src.device_j = dev_j.get();
  host_src.host_j = host_j;

  // one write_batch: two overlays from the device copy (one of them twice: the last
  // write wins), one from the host copy, one cleared
  const auto a = r.add_overlay(voi.size), b = r.add_overlay(voi.size), h = r.add_overlay(voi.size),
             e = r.add_overlay(voi.size);
  cudagl->write(r, e, dev_src);
  cudagl->write_batch(r, {render::OverlayWrite{a, render::OverlaySource{}}, render::OverlayWrite{b, dev_src},
                          render::OverlayWrite{h, host_src}, render::OverlayWrite{e, render::OverlaySource{}},
                          render::OverlayWrite{a, dev_src}});
  CHECK(texture_differs(r.overlay_texture(a), voi, host_j) == 0);
  CHECK(texture_differs(r.overlay_texture(b), voi, host_j) == 0);
  CHECK(texture_differs(r.overlay_texture(h), voi, host_j) == 0);

  // three frames drawn into three targets (sizes, views, qualities differ), encoded in
  // one batch: the same JPEG bytes as each frame rendered and encoded alone
  auto nv = cuda::make_nvjpeg_frame_encoder();
  const render::FrameMarks marks = marks_at(c);
  render::ViewSettings views[3] = {view_of(640, 360), view_of(320, 180), view_of(1280, 720)};
  views[1].azimuth_deg = -50;
  const int quality[3] = {90, 60, 85};
  const render::FrameRenderer::OverlayId ovs[3] = {a, e, h};
  std::vector<std::uint8_t> alone[3], batched[3];
  render::FrameTimes t;
  for (int n = 0; n < 3; ++n) {
    r.render(ovs[n], views[n], marks, t);
    nv->encode(r, quality[n], alone[n], t);
  }
  render::FrameRenderer::TargetId tg[3];
  render::FrameTimes times[3];
  std::vector<render::EncodeJob> jobs;
  for (int n = 0; n < 3; ++n) {
    tg[n] = r.add_target();
    r.draw(ovs[n], tg[n], views[n], marks);
    jobs.push_back(render::EncodeJob{tg[n], quality[n], &batched[n], &times[n]});
  }
  nv->encode_batch(r, jobs);
  for (int n = 0; n < 3; ++n) {
    INFO("frame " << n);
    CHECK(batched[n] == alone[n]);
    r.draw_times(tg[n], times[n]);
    CHECK(times[n].raycast_ms > 0);
    CHECK(times[n].encode_ms > 0);
  }
  // a target twice in one batch is refused; after a target is removed and another made,
  // the encoder registers the new texture (again the same bytes)
  CHECK_THROWS_AS(nv->encode_batch(r, {render::EncodeJob{tg[0], 90, &batched[0], &times[0]},
                                       render::EncodeJob{tg[0], 90, &batched[1], &times[1]}}),
                  Error);
  r.remove_target(tg[1]);
  const auto again = r.add_target();
  r.draw(ovs[1], again, views[1], marks);
  std::vector<std::uint8_t> re;
  nv->encode_batch(r, {render::EncodeJob{again, quality[1], &re, &times[1]}});
  CHECK(re == alone[1]);
  nv.reset();
  cudagl.reset();
}

TEST_CASE("the nvjpeg encoder follows the frame size: 320x180, 640x360, 320x180") {
  if (!have_gpu()) return;
  auto ctx = nvidia_context();
  const PatientPtr patient = render_patient();
  render::FrameRenderer r(patient);
  const auto ov = r.add_overlay({48, 48, 48});
  auto nv = cuda::make_nvjpeg_frame_encoder();
  const int sizes[3][2] = {{320, 180}, {640, 360}, {320, 180}};
  for (const auto& s : sizes) {
    INFO("frame " << s[0] << "x" << s[1]);
    render::FrameTimes t;
    r.render(ov, view_of(s[0], s[1]), marks_at(press(0)), t);
    REQUIRE(r.width() == s[0]);
    REQUIRE(r.height() == s[1]);
    std::vector<std::uint8_t> frame, jpeg;
    r.read_rgb(frame, t);
    nv->encode(r, 90, jpeg, t);
    int w = 0, h = 0;
    const std::vector<std::uint8_t> d = decode(jpeg, w, h);
    CHECK(w == s[0]);
    CHECK(h == s[1]);
    if (w == s[0] && h == s[1]) {
      const double e = mean_abs_diff(d, frame);
      std::printf("%dx%d q90: nvjpeg %zu bytes, mean |error| %.3f levels\n", w, h, jpeg.size(), e);
      // the bound of the 1280x720 case, which allows for the smallest frame's edges
      CHECK(e <= kJpegMaeQ90);
    }
  }
}

TEST_CASE("time per call: nvjpeg and turbojpeg at 1280x720, cuda-gl and upload writers at a 64^3 VOI") {
  if (!have_gpu()) return;
  auto ctx = nvidia_context();
  const PatientPtr patient = render_patient();
  render::FrameRenderer r(patient);
  const Vec3i edge{64, 64, 64};
  const auto ov = r.add_overlay(edge);
  constexpr int kWarm = 5, kCalls = 50;

  // a 64^3 J in the middle of the grid: the patient's intensity there, shifted
  Voi voi;
  voi.lo = Vec3i{16, 16, 16};
  voi.size = edge;
  std::vector<float> j(std::size_t(voi.count()));
  for (int k = 0; k < edge.z; ++k)
    for (int jj = 0; jj < edge.y; ++jj)
      for (int i = 0; i < edge.x; ++i)
        j[voi.index(i, jj, k)] = patient->intensity.at(voi.lo.x + i, voi.lo.y + jj, voi.lo.z + k) + 25.0f;
  TestDeviceBytes dj(j.size() * sizeof(float));
  REQUIRE(cudaMemcpy(dj.data(), j.data(), dj.size(), cudaMemcpyHostToDevice) == cudaSuccess);

  // writers: wall time per write
  auto cudagl = cuda::make_cuda_overlay_writer();
  auto upload = render::make_overlay_writer(OverlayWriterChoice::kUpload, *ctx);
  render::OverlaySource dsrc, hsrc;
  dsrc.voi = hsrc.voi = voi;
  dsrc.device_j = &dj;
  hsrc.host_j = j.data();
  auto time_writer = [&](render::OverlayWriter& wr, const render::OverlaySource& src) {
    std::vector<double> ms;
    for (int n = 0; n < kWarm + kCalls; ++n) {
      const auto t0 = std::chrono::steady_clock::now();
      wr.write(r, ov, src);
      glFinish();  // the upload is queued GL work: count it finished, as interop's sync does
      const double dt = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
      if (n >= kWarm) ms.push_back(dt);
    }
    return median(ms);
  };
  const double w_cuda = time_writer(*cudagl, dsrc), w_upload = time_writer(*upload, hsrc);
  CHECK(texture_differs(r.overlay_texture(ov), voi, j.data()) == 0);

  // encoders: readback and encode per call, from FrameTimes
  render::FrameTimes t;
  r.render(ov, view_of(1280, 720), marks_at(press(0)), t);
  auto nv = cuda::make_nvjpeg_frame_encoder();
  auto tj = render::make_frame_encoder(JpegEncoderChoice::kCpu, *ctx);
  struct Med {
    double readback, encode, total;
    std::size_t bytes;
  };
  auto time_encoder = [&](render::FrameEncoder& enc) {
    std::vector<double> rb, en, tot;
    std::vector<std::uint8_t> jpeg;
    for (int n = 0; n < kWarm + kCalls; ++n) {
      render::FrameTimes ft;
      enc.encode(r, 85, jpeg, ft);
      if (n < kWarm) continue;
      rb.push_back(ft.readback_ms);
      en.push_back(ft.encode_ms);
      tot.push_back(ft.readback_ms + ft.encode_ms);
    }
    return Med{median(rb), median(en), median(tot), jpeg.size()};
  };
  const Med m_nv = time_encoder(*nv), m_tj = time_encoder(*tj);

  std::printf("median of %d calls:\n", kCalls);
  std::printf("  nvjpeg    1280x720 q85: readback %.3f ms + encode %.3f ms = %.3f ms (%zu bytes)\n", m_nv.readback,
              m_nv.encode, m_nv.total, m_nv.bytes);
  std::printf("  turbojpeg 1280x720 q85: readback %.3f ms + encode %.3f ms = %.3f ms (%zu bytes)\n", m_tj.readback,
              m_tj.encode, m_tj.total, m_tj.bytes);
  std::printf("  cuda-gl writer, VOI 64^3: %.3f ms per write; upload writer: %.3f ms per write\n", w_cuda, w_upload);
  cudagl.reset();
  upload.reset();
  nv.reset();
  tj.reset();
}
