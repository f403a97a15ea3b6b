// PickRequest against the real palpsim-server on loopback: the skin point under a pixel
// of a session's frame is where a pose starts touching the body, the pixel's ray goes
// through the tip the view follows, and bad picks are refused naming the field.
#include <catch2/catch.hpp>

#include <cmath>
#include <string>
#include <zmq.hpp>

#include "palpsim/wire.pb.h"
#include "server_process.h"
#include "support/zmq_exchange.h"

using namespace palpsim;
namespace v1 = palpsim::v1;

namespace {

// the 2 mm phantom, the scene's default view (no frames needed to pick), a session
// timeout long enough for the whole test
std::string pick_scene_text() {
  return "name: \"pick integration\"\nphantom { voxel_mm: 2.0 }\nrender { width: 480 height: 270 }\n"
         "server { session_timeout_s: 30 }\n";
}

struct Vec { double x, y, z; };
Vec of(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }
Vec along(const Vec& p, const Vec& d, double t) { return {p.x + d.x * t, p.y + d.y * t, p.z + d.z * t}; }
double dist(const Vec& a, const Vec& b) { return std::hypot(a.x - b.x, a.y - b.y, a.z - b.z); }

// one station: a REQ for control requests, a DEALER for poses, one open session
struct Station {
  zmq::context_t ctx{1};
  zmq::socket_t ctl{ctx, zmq::socket_type::req};
  zmq::socket_t pose{ctx, zmq::socket_type::dealer};
  std::uint64_t id = 0;
  std::uint64_t seq = 0;

  explicit Station(const test::ServerProcess& server) {
    ctl.set(zmq::sockopt::linger, 0);
    pose.set(zmq::sockopt::linger, 0);
    ctl.connect(server.control());
    pose.connect(server.pose());
    v1::ControlRequest q;
    q.mutable_open()->set_client_name("pick test");
    const auto r = call(q);
    REQUIRE(r.has_open());
    id = r.open().session_id();
  }
  v1::ControlReply call(v1::ControlRequest q) {
    q.set_schema_version(1);
    return test::exchange<v1::ControlReply>(ctl, q);
  }
  v1::ControlReply pick(double x, double y, std::uint64_t session) {
    v1::ControlRequest q;
    auto* p = q.mutable_pick();
    p->set_session_id(session);
    p->set_x_px(x);
    p->set_y_px(y);
    return call(q);
  }
  v1::PoseReply send_pose(const Vec& tip) {
    v1::PoseRequest q;
    q.set_schema_version(1);
    q.set_session_id(id);
    q.set_seq(++seq);
    q.mutable_tip_mm()->set_x(tip.x);
    q.mutable_tip_mm()->set_y(tip.y);
    q.mutable_tip_mm()->set_z(tip.z);
    q.set_client_time_s(0.001 * double(seq));
    return test::exchange<v1::PoseReply>(pose, q);
  }
};

}  // namespace

TEST_CASE("a pick answers the skin point under a pixel, where a press along its ray touches", "[integration][pick]") {
  test::ServerProcess server(test::temp_file("pick-scene", pick_scene_text()));
  const bool ready = server.wait_ready(120);
  INFO("server stderr:\n" << server.child().err());
  REQUIRE(ready);
  Station st(server);

  // 480 x 270 frame: the 3D view is the left 480 - 90 = 390 pixels; its centre pixel's ray
  // is the view direction through the body's centre (no pose yet), which meets the phantom
  const v1::ControlReply centre = st.pick(195, 135, st.id);
  INFO(centre.DebugString());
  REQUIRE(centre.has_pick());
  const v1::PickReply& p = centre.pick();
  REQUIRE(p.hit());
  CHECK(p.view().width() == 480);
  const Vec eye = of(p.ray_origin_mm()), dir = of(p.ray_direction()), skin = of(p.point_mm());
  CHECK(std::abs(std::hypot(dir.x, dir.y, dir.z) - 1) < 1e-9);  // a unit direction (rounding only)
  CHECK(std::abs(dist(eye, skin) - p.distance_mm()) < 1e-6);    // 1e-6 mm: rounding of the same sum

  // 3 mm before the skin point along the ray the tip is outside, 4 mm past it inside with
  // a force: the point is the body's boundary on the ray to within the 2 mm voxels' nearest
  // neighbour rounding (the pick locates C's crossing to 0.02 mm; haptics reads the same C)
  const v1::PoseReply before = st.send_pose(along(skin, dir, -3));
  INFO(before.DebugString());
  CHECK_FALSE(before.has_error());
  CHECK_FALSE(before.contact());
  const v1::PoseReply pressed = st.send_pose(along(skin, dir, 4));
  INFO(pressed.DebugString());
  CHECK(pressed.contact());
  CHECK(std::hypot(pressed.force_n().x(), pressed.force_n().y(), pressed.force_n().z()) > 0);

  // the view follows the tip (look_at_tip, the scene default): now the centre pixel's ray
  // goes through the tip of the newest pose; the tip lies on the line eye + t dir to
  // within rounding (1e-6 mm over a few hundred mm)
  const v1::ControlReply followed = st.pick(195, 135, st.id);
  REQUIRE(followed.has_pick());
  const Vec eye2 = of(followed.pick().ray_origin_mm()), dir2 = of(followed.pick().ray_direction());
  const Vec tip = along(skin, dir, 4);
  const double t = (tip.x - eye2.x) * dir2.x + (tip.y - eye2.y) * dir2.y + (tip.z - eye2.z) * dir2.z;
  CHECK(dist(along(eye2, dir2, t), tip) < 1e-6);
  // its first body hit is the skin on that ray, before the tip (inside the body)
  REQUIRE(followed.pick().hit());
  CHECK(followed.pick().distance_mm() < t);

  // a corner pixel of a view that frames the grid's bounding sphere sees past the phantom
  const v1::ControlReply corner = st.pick(0.5, 0.5, st.id);
  REQUIRE(corner.has_pick());
  CHECK_FALSE(corner.pick().hit());
  CHECK(corner.pick().distance_mm() == 0);
}

TEST_CASE("bad picks are refused naming the field", "[integration][pick]") {
  test::ServerProcess server(test::temp_file("pick-scene", pick_scene_text()));
  const bool ready = server.wait_ready(120);
  INFO("server stderr:\n" << server.child().err());
  REQUIRE(ready);
  Station st(server);

  // a pixel of the slice column (x >= 390), one outside the frame, a NaN
  for (const auto& xy : {std::pair<double, double>{400, 10}, {-1, 10}, {10, 270}, {std::nan(""), 10}}) {
    const v1::ControlReply r = st.pick(xy.first, xy.second, st.id);
    INFO(r.DebugString());
    CHECK(r.error().code() == v1::ERROR_BAD_PARAMETER);
    CHECK(r.error().message().find("PickRequest.x_px, y_px") != std::string::npos);
    CHECK(r.error().message().find("slice column starts at x = 390") != std::string::npos);
  }
  // a session that is not open
  const v1::ControlReply unknown = st.pick(10, 10, st.id ^ 0x5a5a0000ULL);
  INFO(unknown.DebugString());
  CHECK(unknown.error().code() == v1::ERROR_UNKNOWN_SESSION);
  CHECK(unknown.error().message().find("PickRequest.session_id") != std::string::npos);
  // the server keeps serving: a good pick still answers
  CHECK(st.pick(195, 135, st.id).has_pick());
}
