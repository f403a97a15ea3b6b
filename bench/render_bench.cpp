// palpsim-bench render: what a frame costs, stage by stage (J to texture, ray cast,
// slices, composite, readback, encode) at 1280x720 and 1920x1080 on the 1 mm lumbar
// phantom, for every overlay writer and JPEG encoder this build and machine have, with
// the deformation (cuda where there is a GPU, VOI 64) stepping a press over L3 between
// frames; then the server itself: sessions pressing at 1 kHz, each watched by a viewer at
// render.max_fps = 30, for pose-to-frame latency, frames per second per session and the
// haptic round trip p99 against the same run without viewers.
// Goals on the H100 (issue "frames and bricks"): render + encode within 2 ms at 1280x720
// and 4 ms at 1920x1080; pose-to-frame p50 within 5 ms; 16 sessions at 30 frames/s each
// with the haptic round trip p99 within 1.3x of the run without viewers.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <mutex>
#include <thread>
#include <unistd.h>
#include <vector>
#include <zmq.hpp>

#include "bench/press_load.h"
#include "bench/registry.h"
#include "bench/stats.h"
#include "core/error.h"
#include "core/setting_names.h"
#include "core/thread.h"
#include "deform/engine.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "net/wire_convert.h"
#include "palpsim/wire.pb.h"
#include "prep/prepare.h"
#include "render/egl_context.h"
#include "render/frame_encoder.h"
#include "render/frame_renderer.h"
#include "render/overlay_writer.h"
#include "tests/support/render_support.h"

using namespace palpsim;
namespace v1 = palpsim::v1;
using Clock = std::chrono::steady_clock;
using bench::json_number;
using bench::control;
using bench::machine;
using bench::PressResult;
using bench::press_sessions;
using bench::quantile;
using bench::json_spread;
using bench::spread;
using bench::Spread;

namespace {

struct Options {
  std::string json;
  std::string scene = std::string(PALPSIM_SOURCE_DIR) + "/config/scenes/lumbar_phantom.textproto";
  int frames = 0;                        // per configuration; 0: 200 on a GPU, 8 on llvmpipe
  std::vector<std::pair<int, int>> sizes{{1280, 720}, {1920, 1080}};
  std::vector<int> sessions{1, 16};      // server part
  std::vector<int> batches;              // server part: render.max_batch values ({} = the scene's)
  double seconds = 0;                    // server part, per phase; 0: 6 on a GPU, 8 on llvmpipe
  bool server = true;
  bool sweep = true;                     // ray step x CT precision x preset (GPU only unless asked)
  bool sweep_set = false;
  int nice = 19;                         // the server's worker threads' nice value (ServerOptions::deform_nice)
  std::string writer, encoder;           // the server's render.overlay_writer / jpeg_encoder ("" = the scene's)
  int rounds = 3;                        // server part: rounds of (without, with viewers) per row
  int viewers_nice = 19;                 // server part: the viewer threads' nice value (0: as the server's)
  int deform_batch = net::ServerOptions{}.deform_batch;  // server part: sessions whose steps share launches (1: none)
  bool deform = true;                    // server part: the scene's deformation on (off: frames of the
                                         // undeformed CT, to tell GPU sharing from the render's own cost)
};

// the renderer quality a scene asks for
render::RenderQuality quality_of(const Scene& s) {
  render::RenderQuality q;
  q.ray_step_vox = s.render.ray_step_vox;
  return q;
}


double ms_since(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

struct StageRow {
  int width = 0, height = 0;
  std::string writer, encoder, preset, label;
  Spread j_to_texture, raycast, slices, composite, readback, encode, render_encode, total;
  std::size_t jpeg_bytes = 0;
  int frames = 0;
};

std::string json_stage(const StageRow& r) {
  std::ostringstream s;
  s << "{\"width\": " << r.width << ", \"height\": " << r.height << ", \"overlay_writer\": \"" << r.writer
    << "\", \"jpeg_encoder\": \"" << r.encoder << "\", \"preset\": \"" << r.preset << "\", \"quality\": \"" << r.label
    << "\", \"frames\": " << r.frames
    << ", \"jpeg_bytes\": " << r.jpeg_bytes << ", \"j_to_texture\": " << json_spread(r.j_to_texture)
    << ", \"raycast\": " << json_spread(r.raycast) << ", \"slices\": " << json_spread(r.slices)
    << ", \"composite\": " << json_spread(r.composite) << ", \"readback\": " << json_spread(r.readback)
    << ", \"encode\": " << json_spread(r.encode) << ", \"render_encode\": " << json_spread(r.render_encode)
    << ", \"total\": " << json_spread(r.total) << "}";
  return s.str();
}

// --- stages ---------------------------------------------------------------------------

// every overlay writer and JPEG encoder this build and context can use (upload and cpu always)
void available_writers_and_encoders(render::EglContext& ctx, std::vector<OverlayWriterChoice>& writers,
                                    std::vector<JpegEncoderChoice>& encoders) {
  writers = {OverlayWriterChoice::kUpload};
  encoders = {JpegEncoderChoice::kCpu};
  std::string note;
  try {
    render::make_overlay_writer(OverlayWriterChoice::kCudaGl, ctx, &note);
    writers.push_back(OverlayWriterChoice::kCudaGl);
  } catch (const std::exception& e) {
    std::printf("overlay writer cuda-gl: not here (%s)\n", e.what());
  }
  try {
    render::make_frame_encoder(JpegEncoderChoice::kNvjpeg, ctx, &note);
    encoders.push_back(JpegEncoderChoice::kNvjpeg);
  } catch (const std::exception& e) {
    std::printf("jpeg encoder nvjpeg: not here (%s)\n", e.what());
  }
}

// one configuration's stage times on stdout
void print_stage_row(const StageRow& r) {
  std::printf(
      "%4dx%-4d %-7s %-9s %-11s %-22s J->tex %6.3f  raycast %7.3f  slices %6.3f  composite %6.3f  readback %6.3f"
      "  encode %6.3f | render+encode %7.3f ms (p90 %7.3f)  %zu KB\n",
      r.width, r.height, r.writer.c_str(), r.encoder.c_str(), r.preset.c_str(), r.label.c_str(), r.j_to_texture.median,
      r.raycast.median, r.slices.median, r.composite.median, r.readback.median, r.encode.median,
      r.render_encode.median, r.render_encode.p90, r.jpeg_bytes / 1024);
}

// frames of the phantom at each size, for each writer and encoder, while the deformation
// steps a press that goes 2..12 mm deep and back between frames
std::vector<StageRow> bench_stages(const PatientPtr& patient, const Scene& scene, Options o,
                                   std::string& gl, bool& software) {
  auto ctx = render::EglContext::create();
  gl = ctx->describe();
  software = ctx->software();
  std::printf("GL: %s\n", gl.c_str());
  DeformConfig dc = DeformConfig::from_scene(scene, patient.get());
  dc.settings.backend = DeformBackendChoice::kAuto;
  dc.settings.voi_edge = 64;
  DeformEngine engine(patient, dc);
  std::printf("deformation between frames: %s, VOI 64\n", engine.backend_note().c_str());
  const Vec3i voi{64, 64, 64};
  std::unique_ptr<DeviceBytes> device_j;

  // every writer and encoder this build and context can use
  std::vector<OverlayWriterChoice> writers;
  std::vector<JpegEncoderChoice> encoders;
  available_writers_and_encoders(*ctx, writers, encoders);
  const int frames = o.frames > 0 ? o.frames : (software ? 8 : 200);
  if (!o.sweep_set) o.sweep = !software;  // on llvmpipe the sweep takes minutes; ask for it with --sweep
  const int warmup = software ? 1 : 20;

  std::vector<StageRow> rows;
  // one configuration: `frames` frames after `warmup`, the deformation stepping between them
  auto measure = [&](render::FrameRenderer& renderer, render::FrameRenderer::OverlayId overlay, int w, int h,
                     OverlayWriterChoice wchoice, JpegEncoderChoice echoice, render::Preset preset,
                     const std::string& label) {
        auto writer = render::make_overlay_writer(wchoice, *ctx);
        auto encoder = render::make_frame_encoder(echoice, *ctx);
        render::ViewSettings view;
        view.width = w;
        view.height = h;
        view.preset = preset;
        std::vector<double> jt, rc, sl, cp, rb, en, re, tt;
        std::vector<std::uint8_t> jpeg;
        std::size_t bytes = 0;
        // the press over the L3 spinous process of the phantom, along -y (anterior)
        const Vec3 l3 = test::l3_skin_mm(*patient);
        const DeformContact skin{l3, l3};
        for (int n = 0; n < frames + warmup; ++n) {
          // a new deformation step (not timed): the press 2..12 mm deep
          const double depth = 2 + 10 * (0.5 - 0.5 * std::cos(2 * M_PI * n / 40.0));
          const DeformContact c{skin.skin_point_mm, skin.skin_point_mm - patient->grid.axes_to_physical({0, depth, 0})};
          engine.step(c);
          render::OverlaySource src;
          src.voi = engine.voi();
          src.host_j = engine.deformed_brick();
          if (wchoice == OverlayWriterChoice::kCudaGl && engine.copy_brick_to_device(device_j)) src.device_j = device_j.get();
          render::FrameMarks marks;
          marks.has_tip = true;
          marks.tip_mm = c.tip_mm;
          marks.proxy_mm = c.skin_point_mm;
          marks.contact = true;
          render::FrameTimes t;
          const auto t0 = Clock::now();
          writer->write(renderer, overlay, src);
          t.j_to_texture_ms = ms_since(t0);
          renderer.render(overlay, view, marks, t);
          encoder->encode(renderer, view.jpeg_quality, jpeg, t);
          t.total_ms = ms_since(t0);
          if (n < warmup) continue;
          jt.push_back(t.j_to_texture_ms);
          rc.push_back(t.raycast_ms);
          sl.push_back(t.slices_ms);
          cp.push_back(t.composite_ms);
          rb.push_back(t.readback_ms);
          en.push_back(t.encode_ms);
          re.push_back(t.raycast_ms + t.slices_ms + t.composite_ms + t.readback_ms + t.encode_ms);
          tt.push_back(t.total_ms);
          bytes = jpeg.size();
        }
        StageRow r;
        r.width = w;
        r.height = h;
        r.writer = setting_name(wchoice);
        r.encoder = encoder->name();
        r.preset = setting_name(view.preset);
        r.frames = frames;
        r.j_to_texture = spread(jt);
        r.raycast = spread(rc);
        r.slices = spread(sl);
        r.composite = spread(cp);
        r.readback = spread(rb);
        r.encode = spread(en);
        r.render_encode = spread(re);
        r.total = spread(tt);
        r.jpeg_bytes = bytes;
        r.label = label;
        print_stage_row(r);
        rows.push_back(r);
  };
  // every writer and encoder at every size, the default quality and preset
  render::FrameRenderer renderer(patient, quality_of(scene));
  const auto overlay = renderer.add_overlay(voi);
  for (const auto& [w, h] : o.sizes)
    for (const OverlayWriterChoice wchoice : writers)
      for (const JpegEncoderChoice echoice : encoders)
        measure(renderer, overlay, w, h, wchoice, echoice, render::Preset::kBone, "scene quality");
  renderer.remove_overlay(overlay);
  // what the ray step and the CT texture's precision cost, per preset, at the first size
  // with the fastest writer and encoder here
  if (o.sweep) {
    for (const bool half : {true, false})
      for (const double step : {1.0, 1.5, 2.0}) {
        render::RenderQuality q;
        q.ray_step_vox = step;
        q.half_float_ct = half;
        render::FrameRenderer r(patient, q);
        const auto ov = r.add_overlay(voi);
        char label[64];
        std::snprintf(label, sizeof label, "step %.1f vox, CT %s", step, half ? "fp16" : "fp32");
        for (render::Preset pr : {render::Preset::kBone, render::Preset::kSkin, render::Preset::kSoftTissue})
          measure(r, ov, o.sizes.front().first, o.sizes.front().second, writers.back(), encoders.back(), pr, label);
        r.remove_overlay(ov);
      }
  }
  return rows;
}

// --- the server -------------------------------------------------------------------------

struct ServerRow {
  int sessions = 0;
  int width = 0, height = 0;  // frame size (pixels)
  int max_batch = 0;
  int rounds = 0;                   // of (without, with viewers)
  double rtt_p99_ratio_median = 0;  // the median over rounds of p99 with / p99 without viewers
  double rtt_p99_alone_us = 0, rtt_p99_watched_us = 0, rtt_p50_alone_us = 0, rtt_p50_watched_us = 0;
  double fps_min = 0, fps_median = 0;
  double p2f_p50_ms = 0, p2f_p99_ms = 0;
  std::uint64_t frames = 0, deform_steps = 0;
  std::string backend, encoder, writer;
  // mean stage times (ms) of the frames the viewers got, under this load
  render::FrameTimes load;
  double render_busy = 0;  // the render thread's share of the wall time spent on frames (total_ms summed / s)
};

// `n` sessions pressing at 1 kHz for `seconds` (bench::press_sessions); with `viewers`, each session's frames are read by its own
// viewer thread; returns the round trips (us) and, with viewers, fills fps and latency
void run_sessions(net::Server& server, const v1::PatientInfo& pi, int n, double seconds, bool viewers,
                  std::vector<double>& rtts, std::vector<double>& fps, std::vector<double>& p2f,
                  ServerRow* times = nullptr, int o_viewers_nice = 19) {
  std::vector<std::vector<double>> lat(n);
  std::vector<render::FrameTimes> tsum(n);  // per viewer: stage times summed over its frames
  std::vector<double> twall(n, 0), got(n, 0);  // per viewer: seconds counted, frames got
  std::vector<double> frames(n, 0);
  std::atomic<bool> done{false};
  std::vector<std::thread> watchers;
  std::vector<std::uint64_t> ids(n, 0);
  std::atomic<int> opened{0};
  PressResult pressed;
  std::mutex refusal_mu;
  std::string refusal;  // a viewer's refused WatchSession: the figures would be meaningless
  std::thread press([&] {
    pressed = press_sessions(server.control_endpoint(), pi, n, seconds, &opened,
                             [&](int c, std::uint64_t id) { ids[c] = id; });
  });
  if (viewers) {
    while (opened < n) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    for (int c = 0; c < n; ++c)
      watchers.emplace_back([&, c] {
        // the viewers stand in for remote training stations: on the server's machine
        // they run at the lowest nice (unless --viewers-nice 0) so that their wake-ups
        // do not preempt the server's pose thread, which real remote viewers never do
        if (o_viewers_nice > 0) lower_this_thread(o_viewers_nice, false);
        zmq::context_t ctx(1);
        zmq::socket_t ctl(ctx, zmq::socket_type::req), sub(ctx, zmq::socket_type::sub);
        ctl.set(zmq::sockopt::linger, 0);
        sub.set(zmq::sockopt::linger, 0);
        ctl.connect(server.control_endpoint());
        v1::ControlRequest q;
        q.mutable_watch()->set_session_id(ids[c]);
        q.mutable_watch()->set_frames(true);
        const v1::ControlReply r = control(ctl, q);
        if (!r.has_watch()) {
          std::lock_guard<std::mutex> lock(refusal_mu);
          refusal = r.error().message();
          return;
        }
        sub.connect(r.watch().stream_endpoint());
        sub.set(zmq::sockopt::subscribe, r.watch().frame_topic());
        zmq::pollitem_t it[] = {{sub.handle(), 0, ZMQ_POLLIN, 0}};
        const auto start = Clock::now() + std::chrono::milliseconds(500);  // frames flowing by then
        double counted = 0;
        v1::StreamMessage msg;
        while (!done) {
          zmq::poll(it, 1, std::chrono::milliseconds(20));
          if (!(it[0].revents & ZMQ_POLLIN)) continue;
          zmq::message_t t, b;
          (void)sub.recv(t);
          (void)sub.recv(b);
          if (Clock::now() < start || !msg.ParseFromArray(b.data(), int(b.size())) || !msg.has_frame()) continue;
          ++counted;
          lat[c].push_back(msg.frame().pose_to_frame_ms());
          render::add_times(tsum[c], net::frame_times(msg.frame().times()));
        }
        got[c] = counted;
        twall[c] = std::max(1e-9, std::chrono::duration<double>(Clock::now() - start).count());
        frames[c] = counted / twall[c];
      });
  }
  press.join();
  done = true;
  for (auto& t : watchers) t.join();
  if (!refusal.empty()) throw Error("palpsim-bench render: a viewer's WatchSession was refused: " + refusal);
  for (auto& v : pressed.rtt_us) rtts.insert(rtts.end(), v.begin(), v.end());
  for (auto& v : lat) p2f.insert(p2f.end(), v.begin(), v.end());
  if (viewers) fps = frames;
  if (times) {
    double n_frames = 0, wall = 0;
    render::FrameTimes sum;
    for (int c = 0; c < n; ++c) {
      n_frames += got[c];
      wall = std::max(wall, twall[c]);
      render::add_times(sum, tsum[c]);
    }
    times->load = render::scaled(sum, n_frames > 0 ? 1.0 / n_frames : 0.0);
    times->render_busy = wall > 0 ? sum.total_ms * 1e-3 / wall : 0.0;
  }
}

std::vector<ServerRow> bench_server(const PatientPtr& patient, Scene scene, const Options& o, bool software,
                                    const std::vector<int>& sessions) {
  std::vector<ServerRow> rows;
  const double seconds = o.seconds > 0 ? o.seconds : (software ? 8 : 6);
  scene.effects.frames = scene.effects.bricks = true;
  if (!o.deform) scene.effects.chainmail = scene.effects.relaxation = scene.effects.inversion = false;
  scene.deform.voi_edge = 64;
  scene.render.max_fps = 30;
  scene.server.max_sessions = 64;
  if (!o.writer.empty()) scene.render.overlay_writer = setting_by_name<OverlayWriterChoice>(o.writer);
  if (!o.encoder.empty()) scene.render.jpeg_encoder = setting_by_name<JpegEncoderChoice>(o.encoder);
  net::ServerOptions so;
  so.control_bind = "tcp://127.0.0.1:*";
  so.pose_bind = "tcp://127.0.0.1:*";
  so.stream_bind = "tcp://127.0.0.1:*";
  so.deform_nice = o.nice;
  so.deform_batch = o.deform_batch;
  so.max_sessions_per_client = scene.server.max_sessions;  // one bench client opens every session
  net::Server server(scene, patient, nullptr, so);
  server.start();
  zmq::context_t ctx(1);
  zmq::socket_t ctl(ctx, zmq::socket_type::req);
  ctl.connect(server.control_endpoint());
  v1::ControlRequest iq;
  iq.mutable_info();
  const v1::PatientInfo pi = control(ctl, iq).info().patient();
  for (int n : sessions) {
    ServerRow row;
    row.sessions = n;
    row.width = scene.render.width;
    row.height = scene.render.height;
    row.max_batch = scene.render.max_batch;
    // rounds of (without viewers, with viewers), back to back, so that slow drifts of the
    // machine (a VM's neighbours) fall on both sides alike; the samples are pooled and
    // each round's p99 ratio kept
    std::vector<double> alone, watched, fps, p2f, ratios;
    v1::ControlRequest sq;
    sq.mutable_stats();
    std::uint64_t steps = 0, frames = 0;
    v1::ServerStats st;
    for (int round = 0; round < o.rounds; ++round) {
      std::vector<double> a, w, f, p, unused_fps, unused_p2f;
      run_sessions(server, pi, n, seconds, false, a, unused_fps, unused_p2f);
      const v1::ServerStats st0 = control(ctl, sq).stats().server();
      run_sessions(server, pi, n, seconds, true, w, f, p, &row, o.viewers_nice);
      st = control(ctl, sq).stats().server();
      steps += st.deform_steps() - st0.deform_steps();
      frames += st.stream().frames_published() - st0.stream().frames_published();
      const double pa = quantile(a, 0.99);
      if (pa > 0) ratios.push_back(quantile(w, 0.99) / pa);
      alone.insert(alone.end(), a.begin(), a.end());
      watched.insert(watched.end(), w.begin(), w.end());
      fps.insert(fps.end(), f.begin(), f.end());
      p2f.insert(p2f.end(), p.begin(), p.end());
    }
    row.rounds = o.rounds;
    row.rtt_p99_ratio_median = quantile(ratios, 0.5);
    row.rtt_p50_alone_us = quantile(alone, 0.5);
    row.rtt_p99_alone_us = quantile(alone, 0.99);
    row.rtt_p50_watched_us = quantile(watched, 0.5);
    row.rtt_p99_watched_us = quantile(watched, 0.99);
    row.fps_min = fps.empty() ? 0 : *std::min_element(fps.begin(), fps.end());
    row.fps_median = quantile(fps, 0.5);
    row.p2f_p50_ms = quantile(p2f, 0.5);
    row.p2f_p99_ms = quantile(p2f, 0.99);
    row.frames = frames;
    row.deform_steps = steps;
    row.backend = st.deform_backend();
    row.encoder = st.stream().jpeg_encoder();
    row.writer = st.stream().overlay_writer();
    std::printf(
        "server, %2d sessions at 1 kHz, %dx%d (%s deformation, %s, %s, batch %d, nice %d): frames/s per session min "
        "%.1f median %.1f; pose-to-frame p50 %.2f ms p99 %.2f ms; round trip p99 %.0f us with viewers vs %.0f us without "
        "(%.2fx pooled over %d rounds, median of the rounds' ratios %.2fx; viewer threads at nice %d); "
        "%llu deformation steps\n",
        n, row.width, row.height, row.backend.c_str(), row.encoder.c_str(), row.writer.c_str(), row.max_batch, o.nice,
        row.fps_min,
        row.fps_median, row.p2f_p50_ms, row.p2f_p99_ms, row.rtt_p99_watched_us, row.rtt_p99_alone_us,
        row.rtt_p99_alone_us > 0 ? row.rtt_p99_watched_us / row.rtt_p99_alone_us : 0.0, row.rounds,
        row.rtt_p99_ratio_median, o.viewers_nice, (unsigned long long)row.deform_steps);
    std::printf(
        "        frames under this load (mean ms): J->tex %.3f raycast %.3f slices %.3f composite %.3f readback %.3f "
        "encode %.3f | total %.3f; render thread busy %.0f%% of the time\n",
        row.load.j_to_texture_ms, row.load.raycast_ms, row.load.slices_ms, row.load.composite_ms,
        row.load.readback_ms, row.load.encode_ms, row.load.total_ms,
        100 * row.render_busy);
    rows.push_back(row);
  }
  server.stop();
  return rows;
}

// reads the command line into `o`; false after printing the usage (--help)
bool parse_options(int argc, char** argv, Options& o) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw Error("palpsim-bench render: " + a + " needs a value");
      return argv[++i];
    };
    if (a == "--json") {
      o.json = value();
    } else if (a == "--scene") {
      o.scene = value();
    } else if (a == "--frames") {
      o.frames = std::stoi(value());
    } else if (a == "--seconds") {
      o.seconds = std::stod(value());
    } else if (a == "--overlay-writer") {
      o.writer = value();
    } else if (a == "--jpeg-encoder") {
      o.encoder = value();
    } else if (a == "--nice") {
      o.nice = std::stoi(value());
    } else if (a == "--viewers-nice") {
      o.viewers_nice = std::stoi(value());
      if (o.viewers_nice < 0 || o.viewers_nice > 19) throw Error("palpsim-bench render: --viewers-nice is 0..19");
    } else if (a == "--rounds") {
      o.rounds = std::stoi(value());
      if (o.rounds < 1 || o.rounds > 100) throw Error("palpsim-bench render: --rounds is 1..100");
    } else if (a == "--no-deform") {
      o.deform = false;
    } else if (a == "--deform-batch") {
      o.deform_batch = std::stoi(value());
      if (o.deform_batch < 1 || o.deform_batch > 64) throw Error("palpsim-bench render: --deform-batch is 1..64");
    } else if (a == "--no-server") {
      o.server = false;
    } else if (a == "--sweep" || a == "--no-sweep") {
      o.sweep = a == "--sweep";
      o.sweep_set = true;
    } else if (a == "--batch") {
      std::stringstream ss(value());
      std::string item;
      o.batches.clear();
      while (std::getline(ss, item, ',')) {
        o.batches.push_back(std::stoi(item));
        if (o.batches.back() < 1 || o.batches.back() > 64)
          throw Error("palpsim-bench render: --batch values are 1..64; got '" + item + "'");
      }
    } else if (a == "--sessions" || a == "--sizes") {
      std::stringstream ss(value());
      std::string item;
      if (a == "--sessions") o.sessions.clear(); else o.sizes.clear();
      while (std::getline(ss, item, ',')) {
        if (a == "--sessions") {
          o.sessions.push_back(std::stoi(item));
        } else {
          const auto x = item.find('x');
          if (x == std::string::npos) throw Error("palpsim-bench render: --sizes wants WxH,WxH; got '" + item + "'");
          o.sizes.push_back({std::stoi(item.substr(0, x)), std::stoi(item.substr(x + 1))});
        }
      }
    } else if (a == "--help" || a == "-h") {
      std::printf(
          "usage: palpsim-bench render [--json FILE] [--scene FILE (lumbar phantom)] [--frames N per configuration]\n"
          "                            [--sizes 1280x720,1920x1080] [--sessions 1,16] [--seconds S per phase]\n"
          "                            [--nice N (the server's deformation and render threads, 19)]\n"
          "                            [--overlay-writer auto|upload|cuda-gl] [--jpeg-encoder auto|cpu|nvjpeg] (server)\n"
          "                            [--no-deform (server part: frames of the undeformed CT)]\n"
          "                            [--deform-batch N (server part: sessions whose steps share launches, 64)]\n"
          "                            [--batch 1,4,16 (server part: render.max_batch; the scene's)]\n"
          "                            [--rounds N (server part: rounds of without/with viewers, 3)]\n"
          "                            [--viewers-nice N (server part: the viewer threads', 19)]\n"
          "                            [--no-server] [--sweep|--no-sweep (ray step x CT precision x preset;\n"
          "                            default: on a GPU only)]\n");
      return false;
    } else {
      throw Error("palpsim-bench render: unknown argument '" + a + "'");
    }
  }
  return true;
}

int run(int argc, char** argv) {
  Options o;
  if (!parse_options(argc, argv, o)) return 0;
  const Scene scene = load_scene_file(o.scene);
  PrepReport report;
  const PatientPtr patient = prepare_patient(scene, &report);
  std::printf("patient: %s, %d x %d x %d at %.2f mm\nmachine: %s\n", patient->source.c_str(), patient->grid.size.x,
              patient->grid.size.y, patient->grid.size.z, patient->grid.spacing_mm.x, machine().c_str());
  spdlog::set_level(spdlog::level::warn);

  std::string gl;
  bool software = false;
  const std::vector<StageRow> stages = bench_stages(patient, scene, o, gl, software);
  std::vector<ServerRow> servers;
  if (o.server) {
    if (o.batches.empty()) o.batches.push_back(scene.render.max_batch);
    // every session count at the first size; one session at the other sizes (pose to frame)
    for (int b : o.batches)
      for (std::size_t k = 0; k < o.sizes.size(); ++k) {
        Scene sb = scene;
        sb.render.max_batch = b;
        sb.render.width = o.sizes[k].first;
        sb.render.height = o.sizes[k].second;
        const std::vector<int> one{1};
        if (k > 0 && std::find(o.sessions.begin(), o.sessions.end(), 1) == o.sessions.end()) continue;
        for (const ServerRow& r : bench_server(patient, sb, o, software, k == 0 ? o.sessions : one))
          servers.push_back(r);
      }
  }

  if (!o.json.empty()) {
    std::ofstream out(o.json);
    if (!out) throw Error("palpsim-bench render: cannot write " + o.json);
    char date[32];
    const std::time_t now = std::time(nullptr);
    std::strftime(date, sizeof date, "%Y-%m-%dT%H:%M:%SZ", std::gmtime(&now));
    out << "{\n  \"bench\": \"render\",\n  \"date\": \"" << date << "\",\n  \"machine\": \"" << machine()
        << "\",\n  \"gl\": \"" << gl << "\",\n  \"patient\": \"" << patient->source << " " << patient->grid.size.x
        << "x" << patient->grid.size.y << "x" << patient->grid.size.z << " at " << patient->grid.spacing_mm.x
        << " mm\",\n  \"stages\": [\n";
    for (std::size_t i = 0; i < stages.size(); ++i)
      out << "    " << json_stage(stages[i]) << (i + 1 < stages.size() ? ",\n" : "\n");
    out << "  ],\n  \"server\": [\n";
    for (std::size_t i = 0; i < servers.size(); ++i) {
      const ServerRow& r = servers[i];
      out << "    {\"sessions\": " << r.sessions << ", \"width\": " << r.width << ", \"height\": " << r.height
        << ", \"max_batch\": " << r.max_batch << ", \"deform_backend\": \"" << r.backend << "\", \"jpeg_encoder\": \""
          << r.encoder << "\", \"overlay_writer\": \"" << r.writer
          << "\", \"fps_per_session_min\": " << json_number(r.fps_min)
          << ", \"fps_per_session_median\": " << json_number(r.fps_median)
          << ", \"pose_to_frame_p50_ms\": " << json_number(r.p2f_p50_ms)
          << ", \"pose_to_frame_p99_ms\": " << json_number(r.p2f_p99_ms)
          << ", \"round_trip_p50_us_without_viewers\": " << json_number(r.rtt_p50_alone_us)
          << ", \"round_trip_p99_us_without_viewers\": " << json_number(r.rtt_p99_alone_us)
          << ", \"round_trip_p50_us_with_viewers\": " << json_number(r.rtt_p50_watched_us)
          << ", \"round_trip_p99_us_with_viewers\": " << json_number(r.rtt_p99_watched_us)
          << ", \"viewers_nice\": " << o.viewers_nice << ", \"rounds\": " << r.rounds
          << ", \"round_trip_p99_ratio_median_of_rounds\": "
          << json_number(r.rtt_p99_ratio_median)
          << ", \"frames_published\": " << r.frames << ", \"deform_steps\": " << r.deform_steps
          << ", \"frame_ms_under_load\": {\"j_to_texture\": " << json_number(r.load.j_to_texture_ms)
          << ", \"raycast\": " << json_number(r.load.raycast_ms) << ", \"slices\": " << json_number(r.load.slices_ms)
          << ", \"composite\": " << json_number(r.load.composite_ms)
          << ", \"readback\": " << json_number(r.load.readback_ms) << ", \"encode\": " << json_number(r.load.encode_ms)
          << ", \"total\": " << json_number(r.load.total_ms)
          << "}, \"render_thread_busy\": " << json_number(r.render_busy) << "}"
          << (i + 1 < servers.size() ? ",\n" : "\n");
    }
    out << "  ]\n}\n";
    std::printf("wrote %s\n", o.json.c_str());
  }
  return 0;
}

}  // namespace

PALPSIM_BENCH(render, "frame stages at 1280x720 and 1920x1080, pose-to-frame latency, 16 watched sessions") {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "palpsim-bench render: %s\n", e.what());
    return 1;
  }
}
