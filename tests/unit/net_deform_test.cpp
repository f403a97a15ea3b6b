// Deformation inside the server, in-process on synthetic patients: each session's
// worker steps on the newest contact and reports stage times; poses keep being answered
// while a slow step runs (stale contacts are dropped); resets and leaving the body
// restore the undeformed image; failures are counted and the session keeps being
// served; a scene without chainmail builds nothing for it and says so, nor does one
// without relaxation or inversion for those; the forces are the same bits with and
// without the deformation.
#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>
#include <zmq.hpp>

#include "core/error.h"
#include "deform/backend.h"
#include "deform/engine.h"
#include "net/scene_io.h"
#include "net/server.h"
#include "palpsim/wire.pb.h"
#include "support/net_client.h"
#include "support/synthetic_patient.h"

using namespace palpsim;
using test::stage;
namespace v1 = palpsim::v1;

namespace {

// how long a test waits for the worker before it gives up (a loaded 2-core machine,
// where the worker runs at a lower priority than everything else)
constexpr double kWorkerWaitS = 30;

// a session opened as "deform-unit" whose poses are numbered on their own
struct Client : test::NetClient {
  std::uint64_t seq = 0;

  explicit Client(const net::Server& s) : NetClient(s, "deform-unit") {}
  // one pose and its reply (1 ms of client time per pose)
  v1::PoseReply send_pose(const Vec3& x, bool reset = false) {
    ++seq;
    const v1::PoseReply r = NetClient::send_pose(seq, x, 1.0 + seq * 1e-3, reset);
    REQUIRE(r.error().code() == v1::ERROR_NONE);
    REQUIRE(r.seq() == seq);
    return r;
  }
  // presses straight down into the slab at (x, y) from above the skin to `depth_mm`
  void press(double x, double y, double depth_mm, int poses = 60) {
    const double z0 = test::kSlabSkinZ + 2;
    const double z1 = test::kSlabSkinZ - depth_mm;
    for (int n = 0; n <= poses; ++n) send_pose({x, y, z0 + (z1 - z0) * n / poses});
  }
  // polls the session's deformation stats until `done` holds (false after kWorkerWaitS)
  template <class Pred>
  bool wait_deform(Pred done, v1::DeformSessionStats* out = nullptr) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWorkerWaitS);
    while (std::chrono::steady_clock::now() < end) {
      const v1::StatsReply st = stats();
      if (done(st.session().deform())) {
        if (out) *out = st.session().deform();
        return true;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return false;
  }
};

net::ServerOptions loopback() {
  net::ServerOptions o = test::loopback_options();
  // the worker at the same priority as the haptic thread: a harder case for "poses are
  // answered while it runs", and no starvation when ctest runs other suites beside this one
  o.deform_nice = 0;
  return o;
}

// the default scene with the whole deformation pipeline on the CPU reference at VOI 32
Scene deform_scene() {
  Scene s = default_scene();
  s.effects.chainmail = s.effects.relaxation = s.effects.inversion = true;
  s.deform.backend = DeformBackendChoice::kCpu;
  s.deform.voi_edge = 32;
  return s;
}

// voxels where two volumes differ bit for bit, inside and outside a box of voxels
struct Diff {
  long long inside = 0, outside = 0;
};
Diff diff(const Volume<float>& a, const Volume<float>& b, const v1::DeformSessionStats& d) {
  Diff out;
  const Vec3i& n = a.grid.size;
  for (int k = 0; k < n.z; ++k)
    for (int j = 0; j < n.y; ++j)
      for (int i = 0; i < n.x; ++i) {
        const std::size_t m = a.grid.index(i, j, k);
        if (std::memcmp(&a.data[m], &b.data[m], sizeof(float)) == 0) continue;
        const bool in = i >= int(d.voi_lo_i()) && i < int(d.voi_lo_i() + d.voi_size_i()) && j >= int(d.voi_lo_j()) &&
                        j < int(d.voi_lo_j() + d.voi_size_j()) && k >= int(d.voi_lo_k()) &&
                        k < int(d.voi_lo_k() + d.voi_size_k());
        (in ? out.inside : out.outside) += 1;
      }
  return out;
}

// the press point: tissue away from the slab's bone block (x, y in 24.5..35.5 mm)
constexpr double kPressX = 45, kPressY = 45;
// a press that folds the field (mm; deform.invert_search's test)
constexpr double kSearchPressMm = 20;

}  // namespace

TEST_CASE("a press is deformed on its newest contact and every stage reports its time", "[net][deform]") {
  const auto patient = test::slab_patient();
  net::Server server(deform_scene(), patient, nullptr, loopback());
  server.start();
  REQUIRE(server.deformation_running());
  Client c(server);
  c.press(kPressX, kPressY, 8);
  const std::uint64_t last = c.seq;
  // the worker ends on the newest contact: the last pose of the press
  v1::DeformSessionStats d;
  REQUIRE(c.wait_deform([&](const v1::DeformSessionStats& s) { return s.last_contact_seq() == last; }, &d));
  INFO(d.DebugString());
  CHECK(d.backend() == "cpu");
  CHECK(d.steps() >= 1);
  CHECK(d.failures() == 0);
  CHECK(d.converged());
  CHECK(d.non_converged() == 0);
  CHECK(d.sweeps() >= 2);  // at least one sweep that moved and the quiet one
  CHECK(d.moved() > 0);
  CHECK(d.deformed());
  CHECK(d.max_change_hu() > 0);
  CHECK(std::isfinite(d.invert_residual_vox()));
  CHECK(d.invert_searched() == 0);  // deform.invert_search is off
  // every stage ran and took time; the total includes them (timed around them on one clock)
  CHECK(d.last().chainmail_ms() > 0);
  CHECK(d.last().relax_ms() > 0);
  CHECK(d.last().invert_ms() > 0);
  CHECK(d.last().total_ms() >= d.last().chainmail_ms() + d.last().relax_ms() + d.last().invert_ms());
  CHECK(d.mean().total_ms() > 0);
  // the VOI: at most the scene's edge, around the press
  CHECK(d.voi_size_i() <= 32);
  CHECK(d.voi_size_k() <= 32);
  CHECK(d.bytes_allocated() > 0);
  // the image changed inside the VOI only (J = I outside it)
  Volume<float> j;
  REQUIRE(server.deformed_volume(c.id, j));
  const Diff df = diff(j, patient->intensity, d);
  CHECK(df.inside > 0);
  CHECK(df.outside == 0);
  // stages: the three asked for are built and hold memory; the session's and the server's agree
  const v1::StatsReply st = c.stats();
  for (const char* name : {"chainmail", "relaxation", "inversion"}) {
    INFO(name);
    const v1::StageInfo* s = stage(st.session().stages(), name);
    REQUIRE(s != nullptr);
    CHECK(s->built());
    CHECK(s->bytes_allocated() > 0);
    CHECK(s->runs() == st.session().deform().steps());
    CHECK(s->mean_ms() > 0);
    const v1::StageInfo* all = stage(st.server().stages(), name);
    REQUIRE(all != nullptr);
    CHECK(all->built());
    CHECK(all->bytes_allocated() >= s->bytes_allocated());
  }
  const v1::StageInfo* frames = stage(st.server().stages(), "frames");
  REQUIRE(frames != nullptr);
  CHECK_FALSE(frames->built());
  CHECK(st.server().deform_backend() == "cpu");
  CHECK(st.server().deform_backend_note().find("cpu") != std::string::npos);
  CHECK(st.server().deform_steps() >= d.steps());
  const auto& names = st.info().stages();
  CHECK(std::find(names.begin(), names.end(), "inversion") != names.end());
  server.stop();
}

TEST_CASE("with deform.invert_search the stats count the voxels its cell search took, and none is left unresolved",
          "[net][deform]") {
  // a press deep enough to fold the relaxed field next to the grabbed element, where
  // Newton stalls (measured: the search takes 37 voxels at 20 mm, 1 at 12 mm; > 0 fails
  // if the count never reaches the stats)
  const auto patient = test::slab_patient();
  Scene scene = deform_scene();
  scene.deform.invert_search = true;
  net::Server server(scene, patient, nullptr, loopback());
  server.start();
  Client c(server);
  c.press(kPressX, kPressY, kSearchPressMm);
  const std::uint64_t last = c.seq;
  v1::DeformSessionStats d;
  REQUIRE(c.wait_deform([&](const v1::DeformSessionStats& s) { return s.last_contact_seq() == last; }, &d));
  INFO(d.DebugString());
  CHECK(d.failures() == 0);
  CHECK(d.invert_searched() > 0);
  CHECK(d.invert_unresolved() == 0);
  CHECK(d.invert_residual_vox() < 0.05);
}

TEST_CASE("poses are answered while a slow deformation step runs; stale contacts are dropped", "[net][deform]") {
  // a slow step on purpose (tens of ms against ~0.1 ms per pose): the whole 60^3 volume
  // relaxed 100 times (the relaxation touches only what ChainMail's wave and its steps
  // since can have reached, deform::relax_reach, so a shallow press needs the many steps
  // to reach the whole volume; with 30, two steps once ran on consecutive poses)
  Scene scene = deform_scene();
  scene.deform.whole_volume = true;
  scene.deform.relax_iterations = 100;
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  Client c(server);
  c.press(kPressX, kPressY, 5, 20);
  // stream poses that wiggle in the tissue, one at a time, and watch the step counter:
  // (steps, the contact seq each step ran on) whenever it changes
  std::vector<std::pair<std::uint64_t, std::uint64_t>> seen;
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWorkerWaitS);
  int n = 0, pairs = 0;  // pairs: two consecutive steps seen
  while (pairs < 2 && std::chrono::steady_clock::now() < end) {
    c.send_pose({kPressX + 0.5 * std::sin(n * 0.01), kPressY, test::kSlabSkinZ - 5});
    if (++n % 20 == 0) {
      const v1::DeformSessionStats d = c.stats().session().deform();
      if (d.steps() > 0 && (seen.empty() || seen.back().first != d.steps())) {
        pairs += !seen.empty() && d.steps() == seen.back().first + 1;
        seen.emplace_back(d.steps(), d.last_contact_seq());
      }
    }
  }
  REQUIRE(seen.size() >= 2);
  const v1::StatsReply st = c.stats();
  const v1::DeformSessionStats& d = st.session().deform();
  std::printf("slow steps: %llu steps of %.1f ms (mean), %llu poses, %llu contacts dropped, pose service p99 %.1f us, "
              "max %.1f us\n",
              (unsigned long long)d.steps(), d.mean().total_ms(), (unsigned long long)c.seq,
              (unsigned long long)d.contacts_dropped(), st.server().pose_service().p99_us(),
              st.server().pose_service().max_us());
  // between two consecutive steps the haptic path kept answering: had it waited for the
  // worker, the contact seq would grow by about one pose per step, not by many
  int gaps = 0;
  for (std::size_t k = 1; k < seen.size(); ++k)
    if (seen[k].first == seen[k - 1].first + 1) {
      ++gaps;
      INFO("step " << seen[k].first << " ran on seq " << seen[k].second << ", the one before on " << seen[k - 1].second);
      CHECK(seen[k].second >= seen[k - 1].second + 10);
    }
  CHECK(gaps >= 1);
  // every pose was answered (send_pose requires it), far more poses than steps, and the
  // contacts in between were dropped, not queued: steps + dropped never exceed the poses
  CHECK(d.steps() < c.seq);
  CHECK(d.contacts_dropped() > 0);
  CHECK(d.steps() + d.contacts_dropped() <= c.seq);
  CHECK(d.failures() == 0);
  server.stop();
}

TEST_CASE("a held tip's poses move the stats' last contact on, one at a time, without a step", "[net][deform]") {
  // the same pose again and again, each after the worker has caught up (no contact is
  // dropped): J stands for each in turn, so last_contact_seq must reach each seq; it used
  // to be published only along with a dropped contact, so a client waiting for its last
  // pose's seq waited for ever once steps became faster than poses. Without friction the
  // skin point is a function of the tip, so the held poses are the very same contact
  Scene scene = deform_scene();
  scene.haptics.friction = 0;
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  Client c(server);
  c.press(kPressX, kPressY, 5);
  const Vec3 held{kPressX, kPressY, test::kSlabSkinZ - 5};
  std::uint64_t steps = 0;
  for (int n = 0; n < 5; ++n) {
    c.send_pose(held);
    const std::uint64_t last = c.seq;
    v1::DeformSessionStats d;
    INFO("held pose " << n << ", seq " << last);
    REQUIRE(c.wait_deform([&](const v1::DeformSessionStats& s) { return s.last_contact_seq() == last; }, &d));
    if (n == 0) steps = d.steps();
    CHECK(d.steps() == steps);  // the same contact: nothing to step
  }
}

TEST_CASE("an elastic press held short of bone asks for no step while the tip goes on into the bone", "[net][deform]") {
  // over the slab's bone block (its top 14 mm under the skin): the press stops where half
  // of that tissue is left (deform.elastic.min_tissue_fraction 0.5), so tips 9 to 13 mm
  // deep are one and the same press; without friction the skin point is a function of the
  // tip, so they are one contact and J already stands for each
  Scene scene = deform_scene();
  test::elastic_without_friction(scene);
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  Client c(server);
  c.press(test::kSlabBoneX, test::kSlabBoneY, 9, 30);
  std::uint64_t steps = 0;
  for (int n = 0; n < 5; ++n) {
    c.send_pose({test::kSlabBoneX, test::kSlabBoneY, test::kSlabSkinZ - 9 - n});
    const std::uint64_t last = c.seq;
    v1::DeformSessionStats d;
    INFO("tip " << 9 + n << " mm deep, seq " << last);
    REQUIRE(c.wait_deform([&](const v1::DeformSessionStats& s) { return s.last_contact_seq() == last; }, &d));
    CHECK(d.deformed());
    CHECK(d.failures() == 0);
    if (n == 0) steps = d.steps();
    CHECK(d.steps() == steps);
    // each deeper tip served as current (the first may have been the press's last pose)
    if (n > 0) CHECK(d.contacts_current() >= std::uint64_t(n));
  }
  // shallower than the stop the press moves again
  c.send_pose({test::kSlabBoneX, test::kSlabBoneY, test::kSlabSkinZ - 4});
  const std::uint64_t last = c.seq;
  v1::DeformSessionStats d;
  REQUIRE(c.wait_deform([&](const v1::DeformSessionStats& s) { return s.last_contact_seq() == last; }, &d));
  CHECK(d.steps() == steps + 1);
}

TEST_CASE("a reset, a reset flag and leaving the body restore the undeformed image", "[net][deform]") {
  const auto patient = test::slab_patient();
  net::Server server(deform_scene(), patient, nullptr, loopback());
  server.start();
  Client c(server);
  auto deformed_now = [&] {
    Volume<float> j;
    REQUIRE(server.deformed_volume(c.id, j));
    return j.data.size() == patient->intensity.data.size() &&
           std::memcmp(j.data.data(), patient->intensity.data.data(), j.data.size() * sizeof(float)) != 0;
  };
  c.press(kPressX, kPressY, 8);
  std::uint64_t last = c.seq;
  REQUIRE(c.wait_deform([&](const auto& s) { return s.last_contact_seq() == last && s.deformed(); }));
  CHECK(deformed_now());

  SECTION("ResetSession") {
    v1::ControlRequest q;
    q.mutable_reset()->set_session_id(c.id);
    REQUIRE(c.call(q).has_reset());
    v1::DeformSessionStats d;
    REQUIRE(c.wait_deform([](const auto& s) { return s.resets() == 1 && !s.deformed(); }, &d));
    CHECK(d.max_change_hu() == 0);
    // J is I again, bit for bit
    CHECK_FALSE(deformed_now());
  }
  SECTION("ResetSession right after poses the worker may not have stepped on yet") {
    c.press(kPressX + 2, kPressY, 6, 10);
    v1::ControlRequest q;
    q.mutable_reset()->set_session_id(c.id);
    REQUIRE(c.call(q).has_reset());
    // whether the worker stepped on the last pose before it saw the reset or not, the
    // reset undoes it: no pose came after the reset
    REQUIRE(c.wait_deform([](const auto& s) { return s.resets() == 1; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(50));  // a pass or more of the worker
    CHECK_FALSE(c.stats().session().deform().deformed());
    CHECK_FALSE(deformed_now());
  }
  SECTION("PoseRequest.reset_proxy, then the next contact deforms again") {
    const std::uint64_t steps = c.stats().session().deform().steps();
    c.send_pose({kPressX, kPressY, test::kSlabSkinZ - 4}, true);
    last = c.seq;
    v1::DeformSessionStats d;
    REQUIRE(c.wait_deform([&](const auto& s) { return s.resets() == 1 && s.last_contact_seq() == last; }, &d));
    CHECK(d.steps() > steps);
    CHECK(d.deformed());
    CHECK(deformed_now());
  }
  SECTION("the tip leaves the body") {
    c.send_pose({kPressX, kPressY, test::kSlabSkinZ + 3});
    v1::DeformSessionStats d;
    REQUIRE(c.wait_deform([](const auto& s) { return s.releases() == 1 && !s.deformed(); }, &d));
    CHECK(d.resets() == 0);
    CHECK_FALSE(deformed_now());
  }
  server.stop();
}

TEST_CASE("a step that does not converge or turns NaN is counted; the session keeps being served", "[net][deform]") {
  SECTION("max_sweeps reached: reported, the state kept") {
    Scene scene = deform_scene();
    scene.deform.max_sweeps = 1;
    net::Server server(scene, test::slab_patient(), nullptr, loopback());
    server.start();
    Client c(server);
    c.press(kPressX, kPressY, 6, 20);
    v1::DeformSessionStats d;
    REQUIRE(c.wait_deform([&](const auto& s) { return s.last_contact_seq() == c.seq; }, &d));
    CHECK_FALSE(d.converged());
    CHECK(d.non_converged() >= 1);
    CHECK(d.failures() == 0);
    CHECK(d.deformed());
    CHECK(d.last_error().find("max_sweeps = 1") != std::string::npos);
    CHECK(c.stats().server().deform_non_converged() >= 1);
    CHECK(c.send_pose({kPressX, kPressY, test::kSlabSkinZ - 6}).contact());
    server.stop();
  }
  SECTION("NaN in the image: the session's deformation is reset and counted") {
    // a patient whose tissue intensity is NaN around the press (the material function
    // turns it into NaN displacements, and J samples it), with and without inversion
    auto patient = test::slab_patient();
    for (int k = 25; k < 40; ++k)
      for (int j = 40; j < 50; ++j)
        for (int i = 40; i < 50; ++i) patient->intensity.at(i, j, k) = std::numeric_limits<float>::quiet_NaN();
    Scene scene = deform_scene();
    scene.effects.inversion = GENERATE(true, false);
    INFO("inversion " << scene.effects.inversion);
    net::Server server(scene, patient, nullptr, loopback());
    server.start();
    Client c(server);
    c.press(kPressX, kPressY, 6, 20);
    v1::DeformSessionStats d;
    REQUIRE(c.wait_deform([&](const auto& s) { return s.failures() >= 1 && s.last_error().find("seq " + std::to_string(c.seq)) != std::string::npos; }, &d));
    CHECK_FALSE(d.deformed());
    CHECK(d.last_error().find("non-finite") != std::string::npos);
    CHECK(c.stats().server().deform_failures() >= 1);
    // the haptic path never noticed
    const v1::PoseReply r = c.send_pose({kPressX, kPressY, test::kSlabSkinZ - 6});
    CHECK(r.contact());
    CHECK(std::isfinite(r.force_n().z()));
    server.stop();
  }
}

TEST_CASE("a scene without chainmail builds no deformation and says so", "[net][deform]") {
  Scene scene = default_scene();
  // relaxation and inversion without chainmail build nothing either
  const bool asks_for_relax = GENERATE(false, true);
  scene.effects.relaxation = scene.effects.inversion = asks_for_relax;
  REQUIRE_FALSE(scene.effects.chainmail);
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  server.start();
  CHECK_FALSE(server.deformation_running());
  Client c(server);
  c.press(kPressX, kPressY, 6, 20);
  const v1::StatsReply st = c.stats();
  CHECK_FALSE(st.session().has_deform());
  CHECK(st.server().deform_backend().empty());
  CHECK(st.server().deform_steps() == 0);
  for (const auto* stages : {&st.server().stages(), &st.session().stages()})
    for (const char* name : {"chainmail", "relaxation", "inversion", "frames", "bricks"}) {
      INFO(name);
      const v1::StageInfo* s = stage(*stages, name);
      REQUIRE(s != nullptr);
      CHECK_FALSE(s->built());
      CHECK(s->bytes_allocated() == 0);
      CHECK(s->runs() == 0);
    }
  // haptics is built and ran
  const v1::StageInfo* h = stage(st.server().stages(), "haptics");
  REQUIRE(h != nullptr);
  CHECK(h->built());
  CHECK(h->runs() == c.seq);
  const auto& names = st.info().stages();
  CHECK(std::vector<std::string>(names.begin(), names.end()) == std::vector<std::string>{"haptics"});
  Volume<float> j;
  CHECK_FALSE(server.deformed_volume(c.id, j));
  server.stop();
}

TEST_CASE("relaxation or inversion switched off alone: its stage is not built, holds nothing, never runs",
          "[net][deform]") {
  const std::string off = GENERATE(std::string("relaxation"), std::string("inversion"));
  INFO("switched off: " << off);
  Scene scene = deform_scene();
  (off == "relaxation" ? scene.effects.relaxation : scene.effects.inversion) = false;
  const auto patient = test::slab_patient();
  net::Server server(scene, patient, nullptr, loopback());
  server.start();
  Client c(server);
  c.press(kPressX, kPressY, 8);
  const std::uint64_t last = c.seq;
  v1::DeformSessionStats d;
  REQUIRE(c.wait_deform([&](const v1::DeformSessionStats& s) { return s.last_contact_seq() == last; }, &d));
  CHECK(d.steps() >= 1);
  // the switched-off stage costs no time in any step
  CHECK((off == "relaxation" ? d.last().relax_ms() : d.last().invert_ms()) == 0);
  CHECK((off == "relaxation" ? d.mean().relax_ms() : d.mean().invert_ms()) == 0);
  const v1::StatsReply st = c.stats();
  for (const auto* stages : {&st.server().stages(), &st.session().stages()})
    for (const char* name : {"chainmail", "relaxation", "inversion"}) {
      INFO(name);
      const v1::StageInfo* sg = stage(*stages, name);
      REQUIRE(sg != nullptr);
      if (name == off) {
        CHECK_FALSE(sg->built());
        CHECK(sg->bytes_allocated() == 0);
        CHECK(sg->runs() == 0);
        CHECK(sg->mean_ms() == 0);
      } else {
        CHECK(sg->built());
        CHECK(sg->bytes_allocated() > 0);
        CHECK(sg->runs() >= 1);
      }
    }
  const auto& names = st.info().stages();
  CHECK(std::find(names.begin(), names.end(), off) == names.end());
  // without inversion no J is made: the image stays I; with it the press shows
  Volume<float> j;
  REQUIRE(server.deformed_volume(c.id, j));
  CHECK((j.data == patient->intensity.data) == (off == "inversion"));
  server.stop();
}

TEST_CASE("the forces are the same bits with and without the deformation", "[net][deform]") {
  // the force model reads the undeformed force image: a deformation running beside the
  // poses changes no reply (the pose path shares nothing with it but the contact slot)
  std::vector<v1::PoseReply> replies[2];
  for (int with = 0; with < 2; ++with) {
    Scene scene = with ? deform_scene() : default_scene();
    net::Server server(scene, test::slab_patient(), nullptr, loopback());
    server.start();
    REQUIRE(server.deformation_running() == bool(with));
    Client c(server);
    // a press, a slide across the skin and back out
    const double z0 = test::kSlabSkinZ + 2, z1 = test::kSlabSkinZ - 8;
    for (int n = 0; n <= 120; ++n) {
      const double t = n / 120.0;
      const Vec3 x{kPressX + 6 * std::sin(6.28 * t), kPressY - 4 * t, t < 0.5 ? z0 + (z1 - z0) * 2 * t
                                                                             : z1 + (z0 - z1) * (2 * t - 1)};
      replies[with].push_back(c.send_pose(x));
    }
    server.stop();
  }
  REQUIRE(replies[0].size() == replies[1].size());
  int in_contact = 0;
  for (std::size_t n = 0; n < replies[0].size(); ++n) {
    INFO("pose " << n);
    const v1::PoseReply& a = replies[0][n];
    const v1::PoseReply& b = replies[1][n];
    in_contact += a.contact();
    CHECK(a.contact() == b.contact());
    CHECK(a.force_n().x() == b.force_n().x());
    CHECK(a.force_n().y() == b.force_n().y());
    CHECK(a.force_n().z() == b.force_n().z());
    CHECK(a.proxy_mm().x() == b.proxy_mm().x());
    CHECK(a.proxy_mm().y() == b.proxy_mm().y());
    CHECK(a.proxy_mm().z() == b.proxy_mm().z());
  }
  CHECK(in_contact > 20);  // the press reached the tissue: the comparison covers real forces
}

TEST_CASE("a scene whose deformation cannot be served refuses to start, naming the setting", "[net][deform]") {
  Scene scene = deform_scene();
  scene.deform.relax_step = 0.5;  // above the explicit scheme's stable limit 1/6
  net::Server server(scene, test::slab_patient(), nullptr, loopback());
  CHECK_THROWS_WITH(server.start(), Catch::Contains("relax_step") && Catch::Contains("stable limit"));
}

TEST_CASE("a scene reload starts or drops the deformation", "[net][deform]") {
  const auto slab = test::slab_patient();
  auto loader = [&](const Scene&) -> PatientPtr { return slab; };
  net::Server server(default_scene(), slab, loader, loopback());
  server.start();
  CHECK_FALSE(server.deformation_running());
  Client c(server);
  v1::ControlRequest q;
  q.mutable_load_scene()->set_text(
      "name: \"deforming\"\nphantom { voxel_mm: 2 }\ndeform { voi_edge: 32 backend: \"cpu\" }\n"
      "effects { chainmail: true relaxation: true }\n");
  REQUIRE(c.call(q).error().code() == v1::ERROR_NONE);
  CHECK(server.deformation_running());
  c.press(kPressX, kPressY, 6, 20);
  v1::DeformSessionStats d;
  REQUIRE(c.wait_deform([&](const auto& s) { return s.last_contact_seq() == c.seq; }, &d));
  CHECK(d.deformed());
  CHECK(d.last().invert_ms() == 0);  // not asked for
  const v1::StatsReply st = c.stats();
  CHECK(stage(st.server().stages(), "relaxation")->built());
  CHECK_FALSE(stage(st.server().stages(), "inversion")->built());
  CHECK(stage(st.server().stages(), "inversion")->bytes_allocated() == 0);
  // and back to haptics only: the worker drops every engine
  q.mutable_load_scene()->set_text("name: \"plain\"\nphantom { voxel_mm: 2 }\n");
  REQUIRE(c.call(q).error().code() == v1::ERROR_NONE);
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(kWorkerWaitS);
  v1::StatsReply after;
  do {
    after = c.stats();
  } while (stage(after.server().stages(), "chainmail")->built() && std::chrono::steady_clock::now() < end);
  CHECK_FALSE(stage(after.server().stages(), "chainmail")->built());
  CHECK(stage(after.server().stages(), "chainmail")->bytes_allocated() == 0);
  CHECK(after.server().deform_backend().empty());
  server.stop();
}

TEST_CASE("a reloaded scene whose deformation cannot be served is refused and the old one kept", "[net][deform]") {
  const auto slab = test::slab_patient();
  int loads = 0;
  auto loader = [&](const Scene&) -> PatientPtr {
    ++loads;
    return slab;
  };
  net::Server server(default_scene(), slab, loader, loopback());
  server.start();
  Client c(server);
  v1::ControlRequest q;
  q.mutable_load_scene()->set_text(
      "name: \"unstable\"\nphantom { voxel_mm: 2 }\ndeform { relax_step: 0.5 backend: \"cpu\" }\n"
      "effects { chainmail: true relaxation: true }\n");
  const v1::ControlReply r = c.call(q);
  CHECK(r.error().code() == v1::ERROR_SCENE_LOAD_FAILED);
  CHECK_THAT(r.error().message(), Catch::Contains("relax_step") && Catch::Contains("stable limit"));
  CHECK(loads == 0);  // refused before the patient was made
  CHECK_FALSE(server.deformation_running());
  // the old scene still serves poses
  c.press(kPressX, kPressY, 4);
  server.stop();
}

TEST_CASE("with backend auto the worker prefers cuda where a GPU exists and says which it uses", "[net][deform]") {
  Scene scene = deform_scene();
  scene.deform.backend = DeformBackendChoice::kAuto;
  std::string why;
  const bool cuda = cuda_deform_available(&why);
  std::printf("backend auto: %s (%s)\n", cuda ? "cuda" : "cpu", why.c_str());
  const auto patient = test::slab_patient();
  net::Server server(scene, patient, nullptr, loopback());
  server.start();
  Client c(server);
  c.press(kPressX, kPressY, 8);
  v1::DeformSessionStats d;
  REQUIRE(c.wait_deform([&](const auto& s) { return s.last_contact_seq() == c.seq; }, &d));
  INFO(d.DebugString());
  const std::string expected = cuda ? "cuda" : "cpu";
  CHECK(d.backend() == expected);
  const v1::StatsReply st = c.stats();
  CHECK(st.server().deform_backend() == expected);
  CHECK(st.server().deform_backend_note().find("auto") != std::string::npos);
  CHECK(d.converged());
  CHECK(d.deformed());
  CHECK(d.failures() == 0);
  CHECK(d.moved() > 0);
  CHECK(d.last().invert_ms() > 0);
  // the image changed inside the VOI only, on either backend
  Volume<float> j;
  REQUIRE(server.deformed_volume(c.id, j));
  const Diff df = diff(j, patient->intensity, d);
  CHECK(df.inside > 0);
  CHECK(df.outside == 0);
  server.stop();
}

TEST_CASE("sessions ready together are begun together (caps of 4 and 1): each gets its own contact's J, none starves",
          "[net][deform]") {
  // six sessions pressing at six points in turn, one pose each per round, against a
  // worker that begins at most 4 ready sessions together (a pass with all six ready runs
  // a batch of 4 and one of 2; the cpu backend begins each alone inside a batch, so this
  // checks the worker's grouping, pairing of engines and contacts, and completion), and
  // one that begins each alone (--deform-batch 1)
  const auto patient = test::slab_patient();
  const Scene scene = deform_scene();
  for (int cap : {4, 1}) {
    INFO("batch cap " << cap);
    net::ServerOptions opt = loopback();
    opt.deform_batch = cap;
    net::Server server(scene, patient, nullptr, opt);
    server.start();
    std::vector<std::unique_ptr<Client>> clients;
    for (int s = 0; s < 6; ++s) clients.push_back(std::make_unique<Client>(server));
    // six points on the slab's soft tissue, away from its bone block (x, y in 24.5..35.5 mm)
    auto point = [](int s) { return Vec3{s % 3 == 0 ? 8.0 : (s % 3 == 1 ? 45.0 : 52.0), s < 3 ? 12.0 : 48.0, 0.0}; };
    std::vector<v1::PoseReply> last(6);
    std::vector<Vec3> tip(6);
    const int poses = 40;
    for (int n = 0; n <= poses; ++n)
      for (int s = 0; s < 6; ++s) {
        const Vec3 p = point(s);
        tip[s] = {p.x, p.y, test::kSlabSkinZ + 2 - (2.0 + 3.0 + s) * n / poses};
        last[s] = clients[s]->send_pose(tip[s]);
      }
    DeformEngine alone(patient, DeformConfig::from_scene(scene, patient.get()));
    for (int s = 0; s < 6; ++s) {
      INFO("session " << s);
      // every session gets to its newest contact (none starves behind the others)
      v1::DeformSessionStats d;
      REQUIRE(clients[s]->wait_deform(
          [&](const v1::DeformSessionStats& st) { return st.last_contact_seq() == clients[s]->seq; }, &d));
      CHECK(d.failures() == 0);
      CHECK(d.deformed());
      // J is that of its own newest contact, bit for bit
      REQUIRE(last[s].contact());
      const Vec3 X{last[s].skin_point_mm().x(), last[s].skin_point_mm().y(), last[s].skin_point_mm().z()};
      alone.step(DeformContact{X, tip[s]});
      Volume<float> j;
      REQUIRE(server.deformed_volume(clients[s]->id, j));
      CHECK(j.data == alone.deformed_volume().data);
    }
    // the cpu backend never shares launches
    CHECK(clients[0]->stats().server().deform_batched_steps() == 0);
    server.stop();
  }
}
