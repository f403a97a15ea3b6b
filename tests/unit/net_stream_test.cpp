// Frames and bricks inside the server, in-process on the synthetic slab (llvmpipe here):
// a session is rendered only while watched; bricks decode to exactly the J the server
// computed; a press changes the frame near the tip and nowhere else, and with
// deformation off it changes nothing; bad viewer input gets a clear error while the
// other viewers and the poses go on; a scene without frames and bricks builds nothing.
#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <string>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "net/scene_io.h"
#include "net/server.h"
#include "palpsim/wire.pb.h"
#include "render/frame_encoder.h"
#include "support/net_client.h"
#include "support/stream_viewer.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
using test::stage;
namespace v1 = palpsim::v1;

namespace {

// how long a test waits for the render thread or the worker (a loaded 2-core machine
// rendering with llvmpipe at nice 19)
constexpr double kWaitS = 60;

// the press point on the slab's skin (z = 39.5 mm), away from its bone block
constexpr double kPressX = 45, kPressY = 45;

// a session as "stream-unit", with watch requests and numbered poses
struct Client : test::NetClient {
  std::uint64_t seq = 0;
  explicit Client(const net::Server& s, std::string token = "") : NetClient(s, "stream-unit", std::move(token)) {}

  v1::ControlReply watch(const v1::WatchSession& w) {
    v1::ControlRequest q;
    *q.mutable_watch() = w;
    return call(q);
  }
  // watches this session's frames with the scene's view (the reply names the stream)
  v1::ControlReply watch_frames() {
    v1::WatchSession w;
    w.set_session_id(id);
    w.set_frames(true);
    const v1::ControlReply r = watch(w);
    REQUIRE(r.has_watch());
    return r;
  }
  v1::PoseReply send_pose(const Vec3& x) {
    ++seq;
    const v1::PoseReply r = NetClient::send_pose(seq, x, 1.0 + seq * 1e-3);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    return r;
  }
  // presses straight down from 2 mm above the skin to `depth_mm` under it
  void press(double depth_mm, int poses = 40) {
    const double z0 = test::kSlabSkinZ + 2, z1 = test::kSlabSkinZ - depth_mm;
    for (int n = 0; n <= poses; ++n) send_pose({kPressX, kPressY, z0 + (z1 - z0) * n / poses});
  }
};

net::ServerOptions loopback() {
  net::ServerOptions o = test::loopback_options();
  o.stream_bind = "tcp://127.0.0.1:*";
  // the workers at the haptic thread's priority: ctest runs other suites beside this one
  o.deform_nice = 0;
  return o;
}

// the slab with frames and bricks (small frames: llvmpipe renders them in milliseconds)
Scene stream_scene(bool deform) {
  Scene s = default_scene();
  s.name = deform ? "stream with deformation" : "stream without deformation";
  s.effects.frames = s.effects.bricks = true;
  if (deform) {
    s.effects.chainmail = s.effects.relaxation = s.effects.inversion = true;
    s.deform.backend = DeformBackendChoice::kCpu;
    s.deform.voi_edge = 32;
  }
  s.render.width = 192;
  s.render.height = 108;
  s.render.max_fps = 100;
  s.render.jpeg_encoder = JpegEncoderChoice::kCpu;
  s.render.overlay_writer = OverlayWriterChoice::kUpload;
  return s;
}

// a decoded frame
struct Rgb {
  std::vector<std::uint8_t> px;
  int w = 0, h = 0;
  int at(int x, int y, int c) const { return px[(std::size_t(y) * w + x) * 3 + c]; }
};
Rgb decode(const v1::Frame& f) {
  Rgb r;
  REQUIRE(render::decode_jpeg_rgb(reinterpret_cast<const std::uint8_t*>(f.jpeg().data()), f.jpeg().size(), r.px, r.w,
                                  r.h));
  REQUIRE(r.w == int(f.width()));
  REQUIRE(r.h == int(f.height()));
  return r;
}
// the largest channel difference of two frames inside a pixel box [x0, x1) x [y0, y1)
int max_diff(const Rgb& a, const Rgb& b, int x0, int y0, int x1, int y1) {
  int m = 0;
  for (int y = y0; y < y1; ++y)
    for (int x = x0; x < x1; ++x)
      for (int c = 0; c < 3; ++c) m = std::max(m, std::abs(a.at(x, y, c) - b.at(x, y, c)));
  return m;
}

}  // namespace

TEST_CASE("a scene without frames and bricks builds no stream, no render thread and no EGL context",
          "[net][stream]") {
  Scene s = default_scene();
  s.effects.chainmail = true;
  s.deform.backend = DeformBackendChoice::kCpu;
  s.deform.voi_edge = 32;
  net::Server server(s, test::slab_patient(), nullptr, loopback());
  server.start();
  CHECK(server.stream_endpoint().empty());
  Client c(server);
  const v1::StatsReply st = c.stats();
  CHECK_FALSE(st.server().has_stream());  // no publisher, no render thread, no EGL context
  CHECK(st.info().stream_endpoint().empty());
  for (const char* name : {"frames", "bricks"}) {
    INFO(name);
    const v1::StageInfo* a = stage(st.server().stages(), name);
    REQUIRE(a != nullptr);
    CHECK_FALSE(a->built());
    CHECK(a->bytes_allocated() == 0);
    CHECK(a->runs() == 0);
    const v1::StageInfo* b = stage(st.session().stages(), name);
    REQUIRE(b != nullptr);
    CHECK_FALSE(b->built());
    CHECK(b->bytes_allocated() == 0);
  }
  CHECK_FALSE(st.session().has_stream());
  // and a viewer is told so
  v1::WatchSession w;
  w.set_session_id(c.id);
  w.set_frames(true);
  const v1::ControlReply r = c.watch(w);
  CHECK(r.error().code() == v1::ERROR_NOT_BUILT);
  CHECK(r.error().message().find("effects.frames") != std::string::npos);
  server.stop();
}

TEST_CASE("bricks only: a publisher but no render thread and no EGL context", "[net][stream]") {
  Scene s = stream_scene(false);
  s.effects.frames = false;
  net::Server server(s, test::slab_patient(), nullptr, loopback());
  server.start();
  CHECK_FALSE(server.stream_endpoint().empty());
  Client c(server);
  const v1::StatsReply st = c.stats();
  REQUIRE(st.server().has_stream());
  CHECK(st.server().stream().publisher_thread());
  CHECK_FALSE(st.server().stream().render_thread());
  CHECK_FALSE(st.server().stream().egl_context());
  CHECK(st.server().stream().gl_renderer().empty());
  const v1::StageInfo* f = stage(st.server().stages(), "frames");
  REQUIRE(f != nullptr);
  CHECK_FALSE(f->built());
  CHECK(f->bytes_allocated() == 0);
  v1::WatchSession w;
  w.set_session_id(c.id);
  w.set_frames(true);
  CHECK(c.watch(w).error().code() == v1::ERROR_NOT_BUILT);
  server.stop();
}

TEST_CASE("a session is rendered while a subscriber holds its frame topic, and only then", "[net][stream]") {
  net::Server server(stream_scene(false), test::slab_patient(), nullptr, loopback());
  server.start();
  Client c(server);
  // the render thread runs on an EGL context and says which renderer it got
  v1::StatsReply st = c.stats();
  REQUIRE(st.server().has_stream());
  CHECK(st.server().stream().render_thread());
  CHECK(st.server().stream().egl_context());
  CHECK_FALSE(st.server().stream().gl_renderer().empty());
  CHECK(st.server().stream().jpeg_encoder() == "turbojpeg");
  // poses without a viewer: nothing is rendered
  for (int n = 0; n < 50; ++n) c.send_pose({kPressX, kPressY, 45.0 - n * 0.01});
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  CHECK(c.stats().server().stream().frames_rendered() == 0);

  v1::WatchSession w;
  w.set_session_id(c.id);
  w.set_frames(true);
  const v1::ControlReply r = c.watch(w);
  REQUIRE(r.error().code() == v1::ERROR_NONE);
  REQUIRE(r.has_watch());
  CHECK(r.watch().session_id() == c.id);
  CHECK(r.watch().stream_endpoint() == server.stream_endpoint());
  CHECK(r.watch().view().width() == 192);
  CHECK(r.watch().view().preset() == "bone");
  test::StreamViewer v(r.watch().stream_endpoint());
  v.subscribe(r.watch().frame_topic());
  // frames come while poses change the tip; each decodes at its size and names its pose
  v1::StreamMessage m;
  std::uint64_t last_seq = 0;
  int frames = 0;
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWaitS);
  while (frames < 3 && std::chrono::steady_clock::now() < end) {
    c.send_pose({kPressX, kPressY, 44.0 - frames});
    if (!v.next(m, nullptr, 200) || !m.has_frame()) continue;
    const v1::Frame& f = m.frame();
    CHECK(f.session_id() == c.id);
    CHECK(f.frame_seq() > last_seq);
    last_seq = f.frame_seq();
    CHECK(f.pose_seq() >= 1);
    CHECK(f.pose_seq() <= c.seq);
    CHECK(f.pose_to_frame_ms() >= 0);
    CHECK(f.encoder() == "turbojpeg");
    CHECK(f.times().raycast_ms() > 0);
    CHECK(f.times().encode_ms() > 0);
    const Rgb img = decode(f);
    // not blank: the slab's slices and its surface give some non-black pixels
    long lit = 0;
    for (std::size_t e = 0; e < img.px.size(); ++e) lit += img.px[e] > 40;
    CHECK(lit > long(img.px.size() / 50));
    ++frames;
  }
  REQUIRE(frames == 3);
  st = c.stats();
  CHECK(st.session().stream().frames_watched());
  CHECK(st.session().stream().frames_published() >= 3);
  CHECK(st.session().stream().pose_to_frame_p50_ms() > 0);
  const v1::StageInfo* fs = stage(st.server().stages(), "frames");
  REQUIRE(fs != nullptr);
  CHECK(fs->built());
  CHECK(fs->bytes_allocated() > 0);  // the slab's texture and the framebuffer
  CHECK(fs->runs() >= 3);

  // the viewer leaves: rendering stops (after the frame in flight)
  v.unsubscribe(r.watch().frame_topic());
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  const std::uint64_t before = c.stats().server().stream().frames_rendered();
  for (int n = 0; n < 50; ++n) c.send_pose({kPressX, kPressY, 40.0 + n * 0.02});
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  CHECK(c.stats().server().stream().frames_rendered() == before);
  CHECK_FALSE(c.stats().session().stream().frames_watched());
  server.stop();
}

TEST_CASE("a hold on the control socket renders without a subscriber; any session picks the client's newest",
          "[net][stream]") {
  net::Server server(stream_scene(false), test::slab_patient(), nullptr, loopback());
  server.start();
  // a and b are one client (one token); a session of another client is opened last
  Client a(server, "station"), b(server, "station"), other(server);
  v1::WatchSession w;
  w.set_frames(true);
  w.set_hold_s(30);
  const v1::ControlReply r = a.watch(w);  // session 0: the client's newest open one, b
  REQUIRE(r.has_watch());
  CHECK(r.watch().session_id() == b.id);
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWaitS);
  while (b.stats().session().stream().frames_rendered() == 0 && std::chrono::steady_clock::now() < end) {
    b.send_pose({kPressX, kPressY, 45});
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const v1::StatsReply st = b.stats();
  CHECK(st.session().stream().frames_rendered() > 0);
  CHECK(st.session().stream().hold_left_s() > 0);
  CHECK(a.stats().session().stream().frames_rendered() == 0);
  server.stop();
}

TEST_CASE("bricks decode to exactly the J the server computed", "[net][stream][bricks]") {
  const auto patient = test::slab_patient();
  net::Server server(stream_scene(true), patient, nullptr, loopback());
  server.start();
  // float32 bricks are J bit for bit; int16 bricks are J rounded to the nearest HU
  for (const bool float32 : {true, false}) {
    const bool zstd = !float32;
    DYNAMIC_SECTION((float32 ? "float32" : "int16, zstd")) {
      Client c(server);
      v1::WatchSession w;
      w.set_session_id(c.id);
      w.set_bricks(true);
      w.set_brick_encoding(float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16);
      w.set_brick_compression(zstd ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE);
      const v1::ControlReply r = c.watch(w);
      REQUIRE(r.has_watch());
      CHECK(r.watch().frame_topic().empty());
      test::StreamViewer v(r.watch().stream_endpoint());
      v.subscribe(r.watch().brick_topic());
      // the key: the undeformed image in slabs along k, all of one key id
      Volume<float> key(patient->grid, std::numeric_limits<float>::quiet_NaN());
      std::uint32_t parts = 0, got = 0;
      REQUIRE(v.until(
          [&](const v1::StreamMessage& m) {
            if (!m.has_brick() || !m.brick().key()) return false;
            const v1::Brick& b = m.brick();
            CHECK(b.session_id() == c.id);
            CHECK(b.grid_size_i() == 60);
            CHECK(b.spacing_mm() == 1.0);
            CHECK(b.direction_size() == 9);
            CHECK(b.encoding() == (float32 ? v1::BRICK_FLOAT32 : v1::BRICK_INT16));
            CHECK(b.compression() == (zstd ? v1::COMPRESSION_ZSTD : v1::COMPRESSION_NONE));
            test::paste_brick(b, key);
            parts = b.key_parts();
            return ++got == parts;
          },
          kWaitS));
      for (std::size_t e = 0; e < key.data.size(); ++e) {
        const float want = float32 ? patient->intensity.data[e] : float(std::lround(patient->intensity.data[e]));
        if (std::memcmp(&key.data[e], &want, sizeof want) != 0) FAIL("key voxel " << e << ": " << key.data[e]);
      }
      // a press; when the worker has stepped on its last pose, the brick of that step
      c.press(8);
      const std::uint64_t last = c.seq;
      v1::StreamMessage m;
      REQUIRE(v.until(
          [&](const v1::StreamMessage& x) {
            return x.has_brick() && !x.brick().key() && x.brick().pose_seq() == last && x.brick().deformed();
          },
          kWaitS, &m));
      const v1::Brick& b = m.brick();
      CHECK(b.deform_step() >= 1);
      CHECK(b.size_i() <= 32);
      Volume<float> j;
      REQUIRE(server.deformed_volume(c.id, j));
      Volume<float> rebuilt = key;
      test::paste_brick(b, rebuilt);
      long long differ = 0, changed = 0;
      for (std::size_t e = 0; e < j.data.size(); ++e) {
        const float want = float32 ? j.data[e] : float(std::lround(std::clamp(j.data[e], -32768.f, 32767.f)));
        differ += std::memcmp(&rebuilt.data[e], &want, sizeof want) != 0;
        changed += j.data[e] != patient->intensity.data[e];
      }
      CHECK(changed > 0);  // the press did deform the image
      CHECK(differ == 0);
    }
  }
  server.stop();
}

TEST_CASE("a press changes the frame near the tip and nowhere else; without deformation it changes nothing",
          "[net][stream]") {
  for (const bool deform : {true, false}) {
    DYNAMIC_SECTION((deform ? "deformation on" : "deformation off")) {
      net::Server server(stream_scene(deform), test::slab_patient(), nullptr, loopback());
      server.start();
      Client c(server);
      // a fixed view centred on the press point, no markers: only the image can change
      v1::WatchSession w;
      w.set_session_id(c.id);
      w.set_frames(true);
      auto* view = w.mutable_view();
      view->set_look_at_tip(false);
      view->mutable_center_mm()->set_x(kPressX);
      view->mutable_center_mm()->set_y(kPressY);
      view->mutable_center_mm()->set_z(test::kSlabSkinZ);
      view->set_show_tip(false);
      view->set_preset("soft_tissue");
      view->set_slice_fov_mm(40);
      view->set_jpeg_quality(95);
      const v1::ControlReply r = c.watch(w);
      REQUIRE(r.has_watch());
      test::StreamViewer v(r.watch().stream_endpoint());
      v.subscribe(r.watch().frame_topic());
      // before: the tip above the skin
      v1::StreamMessage before, after;
      c.send_pose({kPressX, kPressY, test::kSlabSkinZ + 3});
      REQUIRE(v.until([&](const v1::StreamMessage& m) { return m.has_frame() && m.frame().pose_seq() == c.seq; },
                      kWaitS, &before));
      // after: pressed 8 mm in, and (with deformation) once J of that pose is drawn
      c.press(8);
      const std::uint64_t last = c.seq;
      const bool got = v.until(
          [&](const v1::StreamMessage& m) {
            return m.has_frame() && m.frame().pose_seq() == last &&
                   (!deform || (m.frame().deformed() && m.frame().deform_pose_seq() == last));
          },
          kWaitS, &after);
      REQUIRE(got);
      const Rgb a = decode(before.frame()), b = decode(after.frame());
      const int side = a.h / 3, left = a.w - side;
      if (!deform) {
        CHECK(after.frame().deform_step() == 0);
        CHECK(a.px == b.px);  // bit-identical frames
      } else {
        CHECK(after.frame().deform_step() >= 1);
        // near the tip: the middle of each slice, where the skin was pushed in (JPEG blocks
        // that hold changed pixels differ; 8 of 255 is far above JPEG noise of equal input, which is 0)
        int near = 0;
        for (int s = 0; s < 3; ++s)
          near = std::max(near, max_diff(a, b, left + side / 4, s * side + side / 4, left + 3 * side / 4,
                                         s * side + 3 * side / 4));
        CHECK(near > 8);
        // far from it: the outer 16 pixels of the 3D view hold only the background, the
        // same before and after (JPEG works on 16x16 blocks, so unchanged blocks are equal)
        CHECK(max_diff(a, b, 0, 0, 16, a.h) == 0);
        CHECK(max_diff(a, b, 0, 0, left, 16) == 0);
      }
      server.stop();
    }
  }
}

TEST_CASE("a frame names the newest pose its J stands for when an elastic press goes on past the hold",
          "[net][stream]") {
  // over the slab's bone block (its top 14 mm under the skin) the elastic press stops
  // where half that tissue is left (deform.elastic.min_tissue_fraction 0.5: 7 mm), so
  // tips 9 to 12 mm deep are one press, J is not stepped again, and it stands for each of
  // those poses; a frame drawn at a deeper tip used to name the pose of the step, and a
  // client waiting for a frame of its newest pose (palpsim-record) waited for ever.
  // Without friction the skin point is a function of the tip: one contact
  Scene scene = stream_scene(true);
  test::elastic_without_friction(scene);
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  Client c(server);
  const v1::ControlReply r = c.watch_frames();
  test::StreamViewer v(r.watch().stream_endpoint());
  v.subscribe(r.watch().frame_topic());
  const double x = test::kSlabBoneX, y = test::kSlabBoneY;
  for (int n = 0; n <= 30; ++n) c.send_pose({x, y, test::kSlabSkinZ + 2 - 11.0 * n / 30});  // to 9 mm
  std::uint64_t steps = 0;
  for (int depth = 9; depth <= 12; ++depth) {
    if (depth > 9) c.send_pose({x, y, test::kSlabSkinZ - depth});
    const std::uint64_t last = c.seq;
    v1::StreamMessage m;
    INFO("tip " << depth << " mm deep, pose " << last);
    REQUIRE(v.until(
        [&](const v1::StreamMessage& x) {
          return x.has_frame() && x.frame().pose_seq() == last && x.frame().deformed() &&
                 x.frame().deform_pose_seq() == last;
        },
        kWaitS, &m));
    // the deeper tips are served by the J in place: no step
    if (depth == 9) steps = m.frame().deform_step();
    CHECK(m.frame().deform_step() == steps);
  }
  const v1::DeformSessionStats d = c.stats().session().deform();
  CHECK(d.contacts_current() >= 3);
  CHECK(d.failures() == 0);
  server.stop();
}

TEST_CASE("bad viewer input is refused with a clear error; other viewers and the poses go on", "[net][stream]") {
  net::Server server(stream_scene(false), test::slab_patient(), nullptr, loopback());
  server.start();
  Client c(server);
  // a good viewer first
  const v1::ControlReply ok = c.watch_frames();
  test::StreamViewer good(ok.watch().stream_endpoint());
  good.subscribe(ok.watch().frame_topic());

  struct Bad {
    const char* what;
    std::function<void(v1::WatchSession&)> set;
    v1::ErrorCode code;
    const char* says;
  };
  const std::vector<Bad> bad = {
      {"unknown session", [](v1::WatchSession& x) { x.set_session_id(0x1234567890ull); }, v1::ERROR_UNKNOWN_SESSION,
       "not an open session"},
      {"size 0x0", [](v1::WatchSession& x) { x.mutable_view()->set_width(0); x.mutable_view()->set_height(0); },
       v1::ERROR_BAD_VIEW, "64..3840"},
      {"size 100000x100000",
       [](v1::WatchSession& x) { x.mutable_view()->set_width(100000); x.mutable_view()->set_height(100000); },
       v1::ERROR_BAD_VIEW, "64..3840"},
      {"unknown preset", [](v1::WatchSession& x) { x.mutable_view()->set_preset("xray"); }, v1::ERROR_BAD_VIEW,
       "skin, bone, soft_tissue"},
      {"NaN camera",
       [](v1::WatchSession& x) { x.mutable_view()->set_azimuth_deg(std::numeric_limits<double>::quiet_NaN()); },
       v1::ERROR_BAD_VIEW, "azimuth"},
      {"NaN centre",
       [](v1::WatchSession& x) { x.mutable_view()->mutable_center_mm()->set_y(std::numeric_limits<double>::infinity()); },
       v1::ERROR_BAD_VIEW, "center"},
      {"negative hold", [](v1::WatchSession& x) { x.set_hold_s(-1); }, v1::ERROR_BAD_PARAMETER, "hold_s"},
  };
  for (const Bad& b : bad) {
    INFO(b.what);
    v1::WatchSession x;
    x.set_session_id(c.id);
    x.set_frames(true);
    b.set(x);
    const v1::ControlReply r = c.watch(x);
    CHECK(r.error().code() == b.code);
    CHECK(r.error().message().find(b.says) != std::string::npos);
    CHECK(r.error().message().find("WatchSession") != std::string::npos);
  }
  // the session's view is as the good viewer set it: refused requests changed nothing
  CHECK(c.stats().session().stream().view().width() == 192);

  // a subscription to a topic that names no session gets a notice on that topic
  {
    test::StreamViewer stray(ok.watch().stream_endpoint());
    stray.subscribe("frame.00000000deadbeef");
    v1::StreamMessage m;
    REQUIRE(stray.until([](const v1::StreamMessage& x) { return x.has_notice(); }, kWaitS, &m));
    CHECK(m.notice().event() == "unknown_session");
    CHECK(m.notice().error().code() == v1::ERROR_UNKNOWN_SESSION);
    CHECK(m.notice().message().find("00000000deadbeef") != std::string::npos);
  }
  // subscribers that disconnect mid-frame: the good viewer keeps getting frames
  for (int n = 0; n < 5; ++n) {
    test::StreamViewer gone(ok.watch().stream_endpoint());
    gone.subscribe(ok.watch().frame_topic());
    c.send_pose({kPressX, kPressY, 44.0 - n});
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }  // each closes here, maybe while a frame is on its way
  std::uint64_t seen = 0;
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWaitS);
  while (seen < 3 && std::chrono::steady_clock::now() < end) {
    c.send_pose({kPressX, kPressY, 42.0 + 0.1 * double(seen)});
    v1::StreamMessage m;
    if (good.next(m, nullptr, 200) && m.has_frame()) ++seen;
  }
  CHECK(seen == 3);
  const v1::StatsReply st = c.stats();
  CHECK(st.server().stream().bad_subscriptions() >= 1);
  CHECK(st.server().stream().render_failures() == 0);
  // every refusal is counted by its kind
  CHECK(st.server().bad_view() == 5);
  CHECK(st.server().bad_parameter() == 1);
  CHECK(st.server().unknown_session() >= 1);

  // the session closes: its viewer is told
  v1::ControlRequest q;
  q.mutable_close()->set_session_id(c.id);
  REQUIRE(c.call(q).has_close());
  v1::StreamMessage m;
  REQUIRE(good.until([](const v1::StreamMessage& x) { return x.has_notice(); }, kWaitS, &m));
  CHECK(m.notice().event() == "closed");
  CHECK(m.notice().session_id() == c.id);
  server.stop();
}

TEST_CASE("LoadScene starts and stops the stream's threads as the new scene asks; viewers hear of it",
          "[net][stream]") {
  const auto patient = test::slab_patient();
  net::Server server(stream_scene(false), patient, [patient](const Scene&) { return patient; }, loopback());
  server.start();
  Client c(server);
  v1::WatchSession w;
  w.set_session_id(c.id);
  w.set_bricks(true);
  const v1::ControlReply r = c.watch(w);
  REQUIRE(r.has_watch());
  test::StreamViewer v(r.watch().stream_endpoint());
  v.subscribe(r.watch().brick_topic());
  // the first key, then a new scene with bricks but no frames: a notice and a new key
  REQUIRE(v.until([](const v1::StreamMessage& m) { return m.has_brick() && m.brick().key_id() == 1; }, kWaitS));
  v1::ControlRequest load;
  load.mutable_load_scene()->set_text(
      "name: \"bricks only\" phantom { voxel_mm: 2 } effects { haptics: true bricks: true }");
  REQUIRE(c.call(load).has_load_scene());
  v1::StreamMessage m;
  REQUIRE(v.until([](const v1::StreamMessage& x) { return x.has_notice(); }, kWaitS, &m));
  CHECK(m.notice().event() == "scene_changed");
  CHECK(m.notice().message().find("bricks only") != std::string::npos);
  REQUIRE(v.until([](const v1::StreamMessage& x) { return x.has_brick() && x.brick().key_id() == 2; }, kWaitS));
  v1::StatsReply st = c.stats();
  CHECK(st.server().stream().publisher_thread());
  CHECK_FALSE(st.server().stream().render_thread());  // frames off: the render thread and its context are gone
  CHECK_FALSE(st.server().stream().egl_context());
  // a scene with neither: the publisher goes too, and the stream's stages say so
  load.mutable_load_scene()->set_text("name: \"haptics only\" phantom { voxel_mm: 2 }");
  REQUIRE(c.call(load).has_load_scene());
  st = c.stats();
  CHECK_FALSE(st.server().has_stream());
  CHECK(st.info().stream_endpoint().empty());
  CHECK(server.stream_endpoint().empty());
  CHECK(c.watch(w).error().code() == v1::ERROR_NOT_BUILT);
  // and back to frames: the render thread is started again
  load.mutable_load_scene()->set_text(
      "name: \"frames again\" phantom { voxel_mm: 2 } effects { haptics: true frames: true } "
      "render { width: 128 height: 72 jpeg_encoder: \"cpu\" }");
  REQUIRE(c.call(load).has_load_scene());
  st = c.stats();
  CHECK(st.server().stream().render_thread());
  CHECK(st.server().stream().egl_context());
  CHECK_FALSE(server.stream_endpoint().empty());
  server.stop();
}

TEST_CASE("sessions due together are drawn in batches; every frame shows its own session", "[net][stream][batch]") {
  // three watched sessions and batches of two: one pass draws two frames together and
  // the third alone, so a mix-up of batch slots (J, view, marks, framebuffer, JPEG)
  // would put one session's tip or size into another's frame
  Scene scene = stream_scene(false);
  scene.render.max_batch = 2;
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  Client a(server), b(server), c(server);
  Client* clients[3] = {&a, &b, &c};
  const double tip_x[3] = {20, 35, 50};  // mm: each session's tip, 2 mm above the skin
  const int widths[3] = {192, 160, 128};  // each session's frame width (pixels)
  test::StreamViewer v(server.stream_endpoint());
  std::map<std::string, int> topic_of;
  for (int n = 0; n < 3; ++n) {
    v1::WatchSession w;
    w.set_session_id(clients[n]->id);
    w.set_frames(true);
    w.mutable_view()->set_width(widths[n]);
    w.mutable_view()->set_height(108);
    const v1::ControlReply r = clients[n]->watch(w);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    v.subscribe(r.watch().frame_topic());
    topic_of[r.watch().frame_topic()] = n;
  }
  // every session moves its own tip; frames of all three come, each with its own tip and size
  int frames[3] = {0, 0, 0};
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWaitS);
  int step = 0;
  while ((frames[0] < 3 || frames[1] < 3 || frames[2] < 3) && std::chrono::steady_clock::now() < end) {
    ++step;
    for (int n = 0; n < 3; ++n) clients[n]->send_pose({tip_x[n], kPressY + 0.01 * step, test::kSlabSkinZ + 2});
    v1::StreamMessage m;
    std::string topic;
    while (v.next(m, &topic, 20)) {
      if (!m.has_frame() || !topic_of.count(topic)) continue;
      const int n = topic_of[topic];
      const v1::Frame& f = m.frame();
      INFO("session " << n << ", frame " << f.frame_seq());
      CHECK(f.session_id() == clients[n]->id);
      CHECK(f.width() == unsigned(widths[n]));
      CHECK(decode(f).w == widths[n]);
      // a session that becomes watched gets a frame at once, which may come before its
      // first pose on a loaded machine (seen once in 15 runs beside two busy loops): no tip
      // yet (pose_seq 0, tip at the zero vector); every later frame shows its own
      if (f.pose_seq() == 0) {
        CHECK(f.tip_mm().x() == 0);
        continue;
      }
      CHECK(f.tip_mm().x() == tip_x[n]);
      ++frames[n];
    }
  }
  CHECK(frames[0] >= 3);
  CHECK(frames[1] >= 3);
  CHECK(frames[2] >= 3);
  CHECK(c.stats().server().stream().render_failures() == 0);
  server.stop();
}

TEST_CASE("a session whose frames are watched is stepped at most once a frame; an unwatched one as often as it can",
          "[net][stream]") {
  Scene scene = stream_scene(true);
  scene.deform.voi_edge = 8;  // cpu steps of about a millisecond: the pacing, not the step, limits
  scene.render.max_fps = 10;  // one step per 100 ms at most for the watched session
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  Client watched(server, "station"), free_running(server);
  v1::WatchSession w;
  w.set_frames(true);
  w.set_hold_s(30);
  w.set_session_id(watched.id);
  REQUIRE(watched.watch(w).has_watch());
  // both press for a second with a new contact every 2 ms
  const auto t0 = std::chrono::steady_clock::now();
  for (int n = 0; std::chrono::steady_clock::now() - t0 < std::chrono::seconds(1); ++n) {
    const double z = test::kSlabSkinZ - 3 - 0.001 * (n % 1000);
    watched.send_pose({kPressX, kPressY, z});
    free_running.send_pose({kPressX + 10, kPressY, z});
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const std::uint64_t a = watched.stats().session().deform().steps();
  const std::uint64_t b = free_running.stats().session().deform().steps();
  INFO("watched " << a << " steps, unwatched " << b << " steps in " << seconds << " s");
  // at most one step per 100 ms frame interval, plus the first (the interval starts at it)
  CHECK(a >= 1);
  CHECK(double(a) <= seconds * scene.render.max_fps + 1);
  // the unwatched session is not held back: several times as many (its 1 ms steps allow
  // hundreds; the 2-core CI machine shares its cores with the render thread and the client)
  CHECK(b >= 3 * a);
  server.stop();
}
