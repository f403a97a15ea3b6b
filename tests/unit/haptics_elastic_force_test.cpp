// The elastic force model's renderer (haptics/elastic_force.h): the force of one local
// linear model in physical space, exactly zero outside the body (and a new press waits for
// its own model), an update's jump taken in steps of elastic_max_jump_n, the clamps, and
// no energy gained over closed paths whatever models come.
#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "haptics/elastic_force.h"

using namespace palpsim;

namespace {

// a model pressing along unit n at x0 with force p0 (N) on the finger and stiffness k (N/mm),
// built as the deformation worker builds it, on an axis-aligned grid
ElasticModel press_model(const Vec3& x0, const Vec3& n, double p0, double k, double time_s) {
  ElasticModel m = make_elastic_model(Grid{}, x0, true, n * -p0, n, k, 1.0, 9);
  m.pose_server_time_s = time_s;
  return m;
}

// clamps far away: the model's force as it is
HapticsSettings loose() {
  HapticsSettings s;
  s.max_force_n = 100;
  s.max_force_rate_n_per_s = 1e9;
  s.elastic_max_jump_n = 0.05;
  return s;
}

}  // namespace

TEST_CASE("a local model: f0 at x0, K = -k n n^T along n, nothing across n, never pulling, in physical axes",
          "[haptics][elastic]") {
  // a grid whose k axis points along physical -y: a step's force and normal along the grid
  // axes are rotated into physical space
  Grid g;
  g.direction = {1, 0, 0, 0, 0, -1, 0, 1, 0};  // columns: i -> +x, j -> +z, k -> -y
  const Vec3 x0{10, 20, 30};
  const ElasticModel m = make_elastic_model(g, x0, true, {0, 0, -1.5}, {0, 0, 1}, 0.4, 3.0, 12);
  REQUIRE(m.contact);
  CHECK(m.normal == Vec3{0, -1, 0});
  CHECK(m.f0_n == Vec3{0, 1.5, 0});  // out of the body: against n
  CHECK(m.depth_mm == 3.0);
  CHECK(m.contact_nodes == 12);
  // K = -k n n^T: symmetric, -k along n, 0 across it
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) CHECK(m.k_n_per_mm[3 * r + c] == m.k_n_per_mm[3 * c + r]);
  CHECK(m.k_n_per_mm[4] == Approx(-0.4));
  CHECK(m.k_n_per_mm[0] == 0.0);
  CHECK(m.k_n_per_mm[8] == 0.0);
  // at x0 the step's force; 2 mm further in, 0.8 N more; sliding across n changes nothing
  CHECK(elastic_model_force(m, x0) == m.f0_n);
  CHECK(elastic_model_force(m, x0 + m.normal * 2.0).y == Approx(1.5 + 0.8));
  CHECK(elastic_model_force(m, x0 + Vec3{3, 0, -4}) == m.f0_n);
  // out along n the force falls to 0 at 1.5 / 0.4 = 3.75 mm, and never pulls beyond
  CHECK(elastic_model_force(m, x0 - m.normal * 3.0).y == Approx(1.5 - 1.2));
  CHECK(elastic_model_force(m, x0 - m.normal * 3.75).y == Approx(0.0).margin(1e-12));
  const Vec3 beyond = elastic_model_force(m, x0 - m.normal * 10.0);
  CHECK(beyond == Vec3{0, 0, 0});
  // a step without contact, or one with a value no force can be made of, gives no force
  const double nan = std::numeric_limits<double>::quiet_NaN();
  CHECK_FALSE(make_elastic_model(g, x0, false, {0, 0, -1.5}, {0, 0, 1}, 0.4, 3, 12).contact);
  CHECK_FALSE(make_elastic_model(g, x0, true, {0, nan, -1.5}, {0, 0, 1}, 0.4, 3, 12).contact);
  CHECK_FALSE(make_elastic_model(g, x0, true, {0, 0, -1.5}, {0, 0, 0}, 0.4, 3, 12).contact);
  CHECK_FALSE(make_elastic_model(g, x0, true, {0, 0, -1.5}, {0, 0, 1}, nan, 3, 12).contact);
  CHECK(elastic_model_force(ElasticModel{}, x0) == Vec3{0, 0, 0});
}

TEST_CASE("the elastic force is exactly zero outside the body, and a new press does not take the last press's model",
          "[haptics][elastic]") {
  const HapticsSettings s = loose();
  const Vec3 n{0, 0, -1}, x0{0, 0, 10};
  ElasticRenderState st;
  double t = 1.0;
  // in the body with a model: its force (jump 0.4 N taken in steps of 0.05 N)
  const ElasticModel a = press_model(x0, n, 0.4, 0.2, t);
  render_elastic(st, &a, s, x0, true, 1e-3, t += 1e-3);
  for (int i = 0; i < 10; ++i) render_elastic(st, nullptr, s, x0, true, 1e-3, t += 1e-3);
  REQUIRE(render_elastic(st, nullptr, s, x0, true, 1e-3, t += 1e-3).force_n.z == Approx(0.4));
  // out: exactly zero at once (no rate clamp, no jump steps), whatever model arrives
  const ElasticRenderStep out = render_elastic(st, nullptr, s, x0 + Vec3{0, 0, 5}, false, 1e-3, t += 1e-3);
  CHECK(out.force_n == Vec3{0, 0, 0});
  const ElasticModel late = press_model(x0, n, 0.4, 0.2, t - 0.5e-3);  // stepped on a pose before the exit
  CHECK(render_elastic(st, &late, s, x0 + Vec3{0, 0, 5}, false, 1e-3, t += 1e-3).force_n == Vec3{0, 0, 0});
  // back in: that late model belongs to the last press and is not taken; the force stays 0
  // until this press's own model comes
  const ElasticRenderStep back = render_elastic(st, &late, s, x0, true, 1e-3, t += 1e-3);
  CHECK_FALSE(back.updated);
  CHECK(back.force_n == Vec3{0, 0, 0});
  const ElasticModel own = press_model(x0, n, 0.03, 0.2, t - 0.5e-3);
  const ElasticRenderStep taken = render_elastic(st, &own, s, x0, true, 1e-3, t += 1e-3);
  CHECK(taken.updated);
  CHECK(taken.force_n.z == Approx(0.03));
}

TEST_CASE("a model update's jump is taken in steps of elastic_max_jump_n, one a pose, and reported",
          "[haptics][elastic]") {
  HapticsSettings s = loose();
  s.elastic_max_jump_n = 0.05;
  const Vec3 n{0, 0, -1}, x{0, 0, 10};
  ElasticRenderState st;
  double t = 1;
  // a first model of 0.03 N: under the bound, taken at once
  const ElasticModel a = press_model(x, n, 0.03, 0.2, t);
  const ElasticRenderStep first = render_elastic(st, &a, s, x, true, 1e-3, t += 1e-3);
  CHECK(first.updated);
  CHECK(first.jump_n == Approx(0.03));
  CHECK_FALSE(first.jump_bounded);
  CHECK(first.force_n.z == Approx(0.03));
  // a model 1 N stronger at the held tip: 0.05 N a pose for 20 poses, then the model's force
  const ElasticModel b = press_model(x, n, 1.03, 0.2, t);
  double last = first.force_n.z;
  ElasticRenderStep r = render_elastic(st, &b, s, x, true, 1e-3, t += 1e-3);
  CHECK(r.updated);
  CHECK(r.jump_n == Approx(1.0));
  CHECK(r.jump_bounded);
  int poses = 1;
  for (; r.force_n.z < 1.03 - 1e-12 && poses < 100; ++poses) {
    // each pose moves the force by the bound (to rounding: 1e-12 N)
    CHECK(r.force_n.z - last == Approx(0.05).margin(1e-12));
    last = r.force_n.z;
    r = render_elastic(st, nullptr, s, x, true, 1e-3, t += 1e-3);
  }
  CHECK(poses == 20);
  CHECK(r.force_n.z == Approx(1.03).epsilon(1e-12));
  CHECK(r.force_n.x == 0.0);
  // and back down: a weaker model is stepped down the same way
  const ElasticModel c = press_model(x, n, 0.53, 0.2, t);
  r = render_elastic(st, &c, s, x, true, 1e-3, t += 1e-3);
  CHECK(r.jump_bounded);
  CHECK(r.force_n.z == Approx(0.98));
}

TEST_CASE("the elastic force keeps eq. 2's magnitude and rate clamps", "[haptics][elastic]") {
  HapticsSettings s;
  s.max_force_n = 3.3;
  s.max_force_rate_n_per_s = 100;  // 0.1 N a millisecond
  s.elastic_max_jump_n = 10;       // no jump steps: the clamps alone
  const Vec3 n{1, 0, 0}, x{5, 0, 0};
  ElasticRenderState st;
  const ElasticModel m = press_model(x, n, 10.0, 1.0, 1.0);
  ElasticRenderStep r = render_elastic(st, &m, s, x, true, 1e-3, 1.001);
  CHECK(r.clamped);
  CHECK(r.force_n.x == Approx(-0.1));
  for (int i = 0; i < 100; ++i) r = render_elastic(st, nullptr, s, x, true, 1e-3, 1.002 + i * 1e-3);
  CHECK(r.clamped);
  CHECK(norm(r.force_n) == Approx(3.3));
}

TEST_CASE("over closed paths the hand gains no energy, whatever models come", "[haptics][elastic]") {
  // The hand's gain over a path that starts and ends outside the body is the work the sent
  // forces did on it, each acting until the next pose (a zero-order hold):
  // W = sum f_{n-1} . (x_n - x_{n-1}). The renderer's energy bound keeps W at most
  // sum |f_n| |(x_{n+1} - x_n) - g_n|, g_n its guess of the next step (elastic_force.h),
  // which is small for smooth motion. The models come from a lagged Hertz press (the
  // server's case: a step solves a pose some poses old; without the bound such a cycle
  // gains 0.6-0.8 % of the energy put in) or are chosen to pump energy (stronger and stiffer
  // while the tip comes out: without the bound the hand gains 2-8 times what it put in).
  const Vec3 n{0, 0, -1};  // into the body; skin at z = 0
  auto depth_of = [&](const Vec3& x) { return dot(x, n); };
  // Hertz-like tissue: P(d) = c d^1.5 (N, d in mm)
  const double c = 0.05;
  auto hertz = [&](double d) { return d > 0 ? c * std::pow(d, 1.5) : 0.0; };
  auto hertz_k = [&](double d) { return d > 0 ? 1.5 * c * std::sqrt(d) : 0.0; };
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> uni(0, 1);

  struct Case {
    const char* name;
    bool pumping;  // models made to pump energy
    double jitter_mm;
  };
  const Case cases[] = {{"lagged Hertz press", false, 0.0},
                        {"lagged Hertz press, jittery hand", false, 0.02},
                        {"models that pump", true, 0.0},
                        {"models that pump, jittery hand", true, 0.02}};
  for (const Case& cs : cases) {
    for (int rep = 0; rep < 4; ++rep) {
      INFO(cs.name << ", path " << rep);
      HapticsSettings s = loose();
      s.max_force_n = 3.3;
      s.max_force_rate_n_per_s = 2000;
      ElasticRenderState st;
      // a path of N poses at 1 kHz: from 2 mm outside to D deep and out, through a loop
      // across n (the tip slides while it presses), then a few poses outside
      const int N = 1500 + 500 * rep;
      const double D = 6 + 2 * rep, side = 3.0 * rep;
      const int lag = 20 + 15 * rep, every = 10 + 7 * rep;  // a model every `every` poses, of a pose `lag` old
      std::vector<Vec3> path;
      for (int i = 0; i <= N; ++i) {
        const double ph = 2 * M_PI * i / N;
        Vec3 x{side * std::sin(ph), side * (1 - std::cos(ph)) * 0.5, 2 - (D + 2) * 0.5 * (1 - std::cos(ph))};
        if (cs.jitter_mm > 0) x += Vec3{uni(rng) - 0.5, uni(rng) - 0.5, uni(rng) - 0.5} * cs.jitter_mm;
        path.push_back(x);
      }
      for (int i = 0; i < 5; ++i) path.push_back(path.back());
      std::vector<Vec3> sent, guess;
      double t = 10;
      long limited = 0;
      for (std::size_t i = 0; i < path.size(); ++i) {
        const Vec3& x = path[i];
        t += 1e-3;
        ElasticModel m;
        const ElasticModel* fresh = nullptr;
        if (i % std::size_t(every) == 0 && i >= std::size_t(lag)) {
          const Vec3& x0 = path[i - std::size_t(lag)];
          const double d0 = depth_of(x0);
          double p0 = hertz(d0), k = hertz_k(d0);
          const bool coming_out = depth_of(x) < depth_of(path[i - 1]);
          if (cs.pumping) {
            // stronger and stiffer on the way out, weaker on the way in: a cycle that pumps
            p0 *= coming_out ? 3.0 : 0.3;
            k *= coming_out ? 4.0 * (1 + uni(rng)) : 0.2;
          }
          m = press_model(x0, n, p0, k, t - lag * 1e-3);
          m.contact = d0 > 0;
          fresh = &m;
        }
        const ElasticRenderStep r = render_elastic(st, fresh, s, x, depth_of(x) > 0, 1e-3, t);
        limited += r.passivity_limited;
        sent.push_back(r.force_n);
        guess.push_back(st.step_mm);
      }
      REQUIRE(sent.back() == Vec3{0, 0, 0});
      double gain = 0, bound = 0, absorbed = 0;
      for (std::size_t i = 1; i < path.size(); ++i) {
        const double w = dot(sent[i - 1], path[i] - path[i - 1]);
        gain += w;
        absorbed += std::max(0.0, -w);
      }
      for (std::size_t i = 1; i + 1 < path.size(); ++i)
        bound += norm(sent[i]) * norm((path[i + 1] - path[i]) - guess[i]);
      std::printf("%-34s path %d: the hand put in %.3f mJ, gained %+.5f mJ (bound %.5f mJ), %ld poses limited\n",
                  cs.name, rep, absorbed, gain, bound, limited);
      // the bound is the theorem's, plus rounding of sums of ~N products of 1e-3 N mm (1e-9 mJ)
      CHECK(gain <= bound + 1e-9);
      // for a trembling hand that bound is loose (it sums every miss): the gain itself stays
      // within 2 % of the energy put in (measured at most 0.9 % on these seeded paths, where
      // the last step as the guess gave 13-50 % and no bound 160-500 %)
      if (cs.jitter_mm > 0) CHECK(gain <= 0.02 * absorbed);
      CHECK(absorbed > 0.05);  // the press did work (a path that never pressed proves nothing)
    }
  }
}

TEST_CASE("a model holding a non-finite value resets the renderer instead of poisoning it", "[haptics][elastic]") {
  const HapticsSettings s = loose();
  ElasticRenderState st;
  ElasticModel bad = press_model({0, 0, 5}, {0, 0, -1}, 1.0, 0.5, 1.0);
  bad.f0_n.x = std::numeric_limits<double>::infinity();
  const ElasticRenderStep r = render_elastic(st, &bad, s, {0, 0, 5}, true, 1e-3, 1.001);
  CHECK(r.reset);
  CHECK(r.force_n == Vec3{0, 0, 0});
  // the next pose renders from a clean state (no model until a good one comes)
  const ElasticRenderStep next = render_elastic(st, nullptr, s, {0, 0, 5}, true, 1e-3, 1.002);
  CHECK(next.force_n == Vec3{0, 0, 0});
  CHECK_FALSE(next.reset);
  const ElasticModel good = press_model({0, 0, 5}, {0, 0, -1}, 0.02, 0.5, 1.0015);
  CHECK(render_elastic(st, &good, s, {0, 0, 5}, true, 1e-3, 1.003).force_n.z == Approx(0.02));
}
