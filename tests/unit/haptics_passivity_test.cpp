// The server's passivity observer and controller (server/haptics/passivity.h): the energy
// it observes, a force it must leave alone (a field that takes energy from the hand), and
// fields that would give the hand energy (a delayed spring, a force pulling into the body
// as eq. 2 gives at a cropped CT's cut face), which it must keep passive.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <functional>

#include "haptics/passivity.h"

using namespace palpsim;

namespace {

// what a press along -y to `depth_at(t)` gives (1 kHz, 5 s): the energy the hand put in
// (mJ, -sum f_n . (x_{n+1} - x_n), each force held until the next pose) of the raw field
// and of the forces the observer let through, the lowest running energy of the latter,
// and the poses it changed
struct PressRun {
  double raw_mj = 0, sent_mj = 0, sent_min_mj = 0;
  std::uint64_t limited = 0, presses = 0, changed = 0;
  double removed_mj = 0;
};

PressRun press(const std::function<double(double)>& depth_at,
               const std::function<Vec3(double t, double depth, double velocity)>& field, bool limit) {
  PressRun r;
  PassivityObserver o;
  const double dt = 1e-3;
  Vec3 prev_tip{0, 0, 0}, prev_raw{0, 0, 0}, prev_sent{0, 0, 0};
  double running = 0;
  for (int i = 1; i <= 5000; ++i) {
    const double t = i * dt, d = depth_at(t), v = (d - depth_at(t - dt)) / dt;
    const Vec3 tip{0, -d, 0};
    const bool contact = d > 0;
    const Vec3 raw = contact ? field(t, d, v) : Vec3{0, 0, 0};
    r.raw_mj -= dot(prev_raw, tip - prev_tip);
    running -= dot(prev_sent, tip - prev_tip);
    if (!contact) running = 0;  // a press ends at the release, as the observer's do
    r.sent_min_mj = std::min(r.sent_min_mj, running);
    r.sent_mj -= dot(prev_sent, tip - prev_tip);
    Vec3 f = raw;
    const PassivityStep s = o.pose(tip, contact, f, limit);
    r.limited += s.limited;
    r.removed_mj += s.removed_mj;
    r.changed += !(f == raw);
    prev_tip = tip;
    prev_raw = raw;
    prev_sent = f;
  }
  r.presses = o.meter().cycles();
  return r;
}

// five presses of up to 11 mm at 1 Hz, out of the body for part of each
double cycling(double t) { return std::max(0.0, 5.0 - 6.0 * std::cos(2 * M_PI * t)); }

}  // namespace

TEST_CASE("the observer leaves a field that takes energy from the hand exactly as it is", "[haptics][passivity]") {
  // a spring of 0.25 N/mm out of the body with a damper of 0.01 N s/mm: the hand puts in
  // energy on every step (the damper) more than the zero-order hold gives back (k dx^2 / 2 a
  // step, 1e-4 mJ at 0.03 mm), so the controller has nothing to do: every force goes out
  // bit for bit
  const auto field = [](double, double d, double v) { return Vec3{0, 0.25 * d + 0.01 * v, 0}; };
  const PressRun r = press(cycling, field, true);
  CHECK(r.changed == 0);
  CHECK(r.limited == 0);
  CHECK(r.sent_mj > 0);
  CHECK(r.presses == 5);
}

TEST_CASE("the controller keeps a delayed spring from giving the hand energy", "[haptics][passivity]") {
  // the spring 100 ms late (a server whose force lags the hand): it gives back more than it
  // took on every press, the classic instability
  const auto field = [](double t, double, double) { return Vec3{0, 0.25 * cycling(t - 0.1), 0}; };
  const PressRun off = press(cycling, field, false);
  const PressRun on = press(cycling, field, true);
  CHECK(off.raw_mj < -5.0);  // about 7 mJ over five presses
  CHECK(off.sent_min_mj < -1.0);
  CHECK(off.limited == 0);
  // with the controller every press stays passive up to the guesses' misses: the next step
  // is guessed as the last (at most 0.038 mm a step here), and two steps differ by under
  // 2.4e-4 mm, which at forces under 2.8 N is under 7e-4 mJ a step; 0.01 mJ covers the
  // few dozen steps of a release
  CHECK(on.sent_min_mj > -0.01);
  CHECK(on.limited > 100);
  CHECK(on.removed_mj > 1.0);
  CHECK(on.presses == 5);
}

TEST_CASE("the controller takes out a force that pulls the tip into the body", "[haptics][passivity]") {
  // 1 N along the press, into the body (the sign eq. 2 gave on a cropped CT's cut face):
  // the hand gains 11 mJ on each way in without the controller
  const auto field = [](double, double, double) { return Vec3{0, -1.0, 0}; };
  const PressRun off = press(cycling, field, false);
  const PressRun on = press(cycling, field, true);
  CHECK(off.sent_min_mj < -10.0);
  // the pull is cut to zero from the first step in (nothing stored yet) and the way out
  // against it stores energy: no step gives the hand more than the guess misses (the speed
  // changes by under 2.4e-4 mm a step at 1 N: 2.4e-4 mJ)
  CHECK(on.sent_min_mj > -0.01);
  CHECK(on.sent_mj >= 0);
}

TEST_CASE("limit_to_energy cuts only the part along the step, to what the energy allows", "[haptics][passivity]") {
  Vec3 f{1, 2, 0};
  // 0.5 mJ over a 1 mm step along y allows 0.5 N along y; x is untouched
  CHECK(limit_to_energy(f, Vec3{0, 1, 0}, 0.5) == Approx(1.5));
  CHECK(f.x == 1.0);
  CHECK(f.y == Approx(0.5));
  // no motion, or a force against the motion: nothing to cut
  Vec3 g{1, 2, 0};
  CHECK(limit_to_energy(g, Vec3{0, 0, 0}, 0) == 0);
  CHECK(limit_to_energy(g, Vec3{0, -1, 0}, 0) == 0);
  CHECK(g == Vec3{1, 2, 0});
  // a negative energy (a deficit) allows nothing along the motion, and never a push back
  CHECK(limit_to_energy(g, Vec3{0, 2, 0}, -3) == Approx(4.0));
  CHECK(g.y == Approx(0.0).margin(1e-12));
}
