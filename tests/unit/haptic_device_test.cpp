// The thin haptic client's scripted devices: CSV paths (with or without a header),
// replay of a client log, the built-in press, and clear errors for bad files.
#include <catch2/catch.hpp>

#include <cstdio>
#include <fstream>
#include <stdexcept>
#include <string>
#include <unistd.h>

#include "device.h"

using namespace palpsim::haptic;

namespace {
std::string write(const std::string& stem, const std::string& text) {
  const std::string p = "/tmp/palpsim-device-" + std::to_string(::getpid()) + "-" + stem;
  std::ofstream(p) << text;
  return p;
}
std::string error_of(const std::string& spec) {
  try {
    make_device(spec, PatientBox{});
  } catch (const std::runtime_error& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST_CASE("a CSV path is interpolated linearly and ends after its last sample", "[haptic-client]") {
  const std::string p = write("plain.csv", "0,0,0,0\n1,10,20,30\n3,10,20,10\n");
  auto d = make_device("csv:" + p, PatientBox{});
  V3 tip;
  REQUIRE(d->read_tip(0.5, tip));
  // halfway along the first segment: exact in binary floating point
  CHECK(tip.x == 5.0);
  CHECK(tip.y == 10.0);
  CHECK(tip.z == 15.0);
  REQUIRE(d->read_tip(2.0, tip));
  CHECK(tip.z == 20.0);
  REQUIRE(d->read_tip(3.0, tip));
  CHECK(tip.z == 10.0);
  CHECK_FALSE(d->read_tip(3.001, tip));
  std::remove(p.c_str());
}

TEST_CASE("a CSV header may order the columns as it likes", "[haptic-client]") {
  const std::string p = write("header.csv", "z,y,x,t\n1,2,3,0\n5,6,7,2\n");
  auto d = make_device("csv:" + p, PatientBox{});
  V3 tip;
  REQUIRE(d->read_tip(1.0, tip));
  CHECK(tip.x == 5.0);
  CHECK(tip.y == 4.0);
  CHECK(tip.z == 3.0);
  std::remove(p.c_str());
}

TEST_CASE("a recorded client log replays its tip at the recorded times", "[haptic-client]") {
  const std::string p = write(
      "log.csv",
      "step,time_s,tip_x_mm,tip_y_mm,tip_z_mm,force_x_n,force_y_n,force_z_n,rtt_us,reply_seq,contact,depth_mm,"
      "watchdog_scale\n1,0.000,1,2,3,0,0,0,nan,0,0,0,0\n2,0.002,3,2,1,0,0,0.5,80.0,1,1,0.5,1\n");
  auto d = make_device("replay:" + p, PatientBox{});
  V3 tip;
  REQUIRE(d->read_tip(0.001, tip));
  // halfway between the two rows, to rounding of 0.001 / 0.002
  CHECK(tip.x == Approx(2.0).margin(1e-12));
  CHECK(tip.z == Approx(2.0).margin(1e-12));
  CHECK_FALSE(d->read_tip(0.01, tip));
  // a log needs its header
  const std::string bare = write("bare.csv", "0,1,2,3\n");
  CHECK(error_of("replay:" + bare).find(bare + ":1") != std::string::npos);
  std::remove(p.c_str());
  std::remove(bare.c_str());
}

TEST_CASE("the built-in press goes 40 mm in from behind the back and comes out again", "[haptic-client]") {
  PatientBox box;
  box.body_min_mm = {-100, -80, -50};
  box.body_max_mm = {100, 90, 50};
  auto d = make_device("press", box);
  V3 tip;
  REQUIRE(d->read_tip(0, tip));
  CHECK(tip.x == 0.0);
  CHECK(tip.y == 100.0);  // 10 mm behind the back (LPS +y is posterior)
  CHECK(tip.z == 0.0);
  REQUIRE(d->read_tip(2.0, tip));  // 40 mm at 20 mm/s
  CHECK(tip.y == 60.0);
  REQUIRE(d->read_tip(4.5, tip));  // hold 0.5 s, 2 s back
  CHECK(tip.y == 100.0);
  REQUIRE(d->read_tip(13.5, tip));  // three presses
  CHECK_FALSE(d->read_tip(13.6, tip));
  auto at = make_device("press:1,2,3", box);
  REQUIRE(at->read_tip(0, tip));
  CHECK((tip.x == 1.0 && tip.y == 2.0 && tip.z == 3.0));
  // a travel of 90 mm (a landmark's press from palpsim-prep): 4.5 s in at 20 mm/s
  auto far = make_device("press:1,2,3,90", box);
  REQUIRE(far->read_tip(4.5, tip));
  CHECK(tip.y == Approx(2.0 - 90.0));
  CHECK(far->describe().find("90.0 mm along -y") != std::string::npos);
}

TEST_CASE("bad device files and specs are refused with file, line and problem", "[haptic-client]") {
  CHECK(error_of("csv:/no/such/path.csv").find("/no/such/path.csv: cannot open") != std::string::npos);
  const std::string nan = write("nan.csv", "0,0,0,0\n1,2,abc,4\n");
  CHECK(error_of("csv:" + nan).find(nan + ":2") != std::string::npos);
  const std::string back = write("back.csv", "0,0,0,0\n2,0,0,0\n1,0,0,0\n");
  CHECK(error_of("csv:" + back).find("time goes backwards") != std::string::npos);
  const std::string empty = write("empty.csv", "t,x,y,z\n");
  CHECK(error_of("csv:" + empty).find("no samples") != std::string::npos);
  const std::string missing = write("missing.csv", "t,x,y\n0,1,2\n");
  CHECK(error_of("csv:" + missing).find("no column 'z'") != std::string::npos);
  CHECK(error_of("joystick").find("expected press") != std::string::npos);
  CHECK(error_of("press:1,2").find("press:X,Y,Z") != std::string::npos);
  CHECK(error_of("press:1,2,3,0").find("TRAVEL '0'") != std::string::npos);
  CHECK(error_of("press:1,2,3,-5").find("TRAVEL '-5'") != std::string::npos);
  CHECK(error_of("press:1,2,3,nan").find("TRAVEL 'nan'") != std::string::npos);
  CHECK(error_of("press:1,2,3,400").find("(0, 300]") != std::string::npos);
  CHECK(error_of("press:1,2,3,4,5").find("press:X,Y,Z,TRAVEL") != std::string::npos);
  for (const auto& f : {nan, back, empty, missing}) std::remove(f.c_str());
}
