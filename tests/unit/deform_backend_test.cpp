// Backend choice by name, the validating wrapper's refusals, and what a step reports
// about J.
#include <catch2/catch.hpp>

#include <cmath>
#include <functional>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/error.h"
#include "deform/cpu_backend.h"
#include "deform/engine.h"
#include "support/deform_fixtures.h"

using namespace palpsim;
using namespace palpsim::test;

namespace {
std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST_CASE("backends are chosen by name; an unavailable cuda says why") {
  CHECK(make_deform_backend("cpu")->name() == "cpu");
  CHECK(error_of([] { make_deform_backend("gpu"); }).find("\"auto\", \"cpu\", \"cuda\"") != std::string::npos);
  std::string why, note;
  const bool have_cuda = cuda_deform_available(&why);
  CHECK_FALSE(why.empty());
  auto a = make_deform_backend("auto", &note);
  CHECK(a->name() == (have_cuda ? "cuda" : "cpu"));
  CHECK(note.find(a->name()) != std::string::npos);
  if (!have_cuda) {
    const std::string e = error_of([] { make_deform_backend("cuda"); });
    CHECK(e.find("unavailable") != std::string::npos);
    CHECK(e.find(why) != std::string::npos);
  }
}

TEST_CASE("deform.backend cuda and auto make what is registered for cuda, and say why it cannot be used") {
  // a fake "cuda" in the registry (the real one, in a CUDA build, is put back at the end)
  const std::optional<DeformBackendRegistry::Factory> real = deform_backends().find(DeformBackendChoice::kCuda);
  bool usable = true;
  int made = 0;
  deform_backends().add(DeformBackendChoice::kCuda,
                        {[&](std::string* why) {
                           *why = usable ? "fake device" : "fake: no device";
                           return usable;
                         },
                         [&] {
                           ++made;
                           return std::unique_ptr<DeformBackend>(std::make_unique<CpuDeformBackend>());
                         }});
  std::string why, note;
  CHECK(cuda_deform_available(&why));
  CHECK(why == "fake device");
  make_deform_backend("cuda", &note);
  make_deform_backend("auto");
  CHECK(made == 2);
  CHECK(note == "deform backend \"cuda\" (fake device)");
  usable = false;
  CHECK(error_of([] { make_deform_backend("cuda"); }).find("unavailable: fake: no device") != std::string::npos);
  CHECK(make_deform_backend("auto", &note)->name() == "cpu");
  CHECK(note == "deform backend \"cpu\" (auto: cuda unavailable: fake: no device)");
  CHECK(made == 2);
  // nothing registered: what a build without CUDA says
  deform_backends().remove(DeformBackendChoice::kCuda);
  CHECK_FALSE(cuda_deform_available(&why));
  CHECK(why.find("PALPSIM_CUDA=OFF") != std::string::npos);
  if (real) deform_backends().add(DeformBackendChoice::kCuda, *real);
}

TEST_CASE("sessions are batched only when every setting the batched kernels share is equal") {
  using Change = std::function<void(DeformConfig&)>;
  struct Named {
    const char* name;
    Change change;
  };
  // each key member changed alone, from an explicit and from a multigrid configuration
  const std::vector<Named> shared = {
      {"relax", [](DeformConfig& c) { c.relax = !c.relax; }},
      {"invert", [](DeformConfig& c) { c.invert = !c.invert; }},
      {"bone_threshold", [](DeformConfig& c) { c.bone_threshold += 1; }},
      {"relax_method", [](DeformConfig& c) {
         c.settings.relax_method = c.settings.relax_method == RelaxMethod::kExplicit ? RelaxMethod::kMultigrid
                                                                                      : RelaxMethod::kExplicit;
       }},
      {"max_sweeps", [](DeformConfig& c) { c.settings.max_sweeps += 1; }},
      {"relax_iterations", [](DeformConfig& c) { c.settings.relax_iterations += 1; }},
      {"relax_step", [](DeformConfig& c) { c.settings.relax_step *= 0.5; }},
      {"material_width", [](DeformConfig& c) { c.settings.material_width += 1; }},
      {"invert_iterations", [](DeformConfig& c) { c.settings.invert_iterations += 1; }},
      {"invert_search", [](DeformConfig& c) { c.settings.invert_search = !c.settings.invert_search; }},
      {"min_dist", [](DeformConfig& c) { c.settings.min_dist = 0.25; }},
      {"max_dist", [](DeformConfig& c) { c.settings.max_dist = 2; }},
      {"max_sheer", [](DeformConfig& c) { c.settings.max_sheer = 1; }},
  };
  // multigrid's: key members with multigrid only
  const std::vector<Named> multigrid = {
      {"relax_cycles", [](DeformConfig& c) { c.settings.relax_cycles += 1; }},
      {"relax_warm_cycles", [](DeformConfig& c) { c.settings.relax_warm_cycles += 1; }},
      {"relax_reuse", [](DeformConfig& c) { c.relax_reuse = !c.relax_reuse; }},
      {"skip_chainmail", [](DeformConfig& c) { c.skip_chainmail = !c.skip_chainmail; }},
  };
  // the session's own
  const std::vector<Named> own = {
      {"voi_edge", [](DeformConfig& c) { c.settings.voi_edge = 48; }},
      {"whole_volume", [](DeformConfig& c) { c.settings.whole_volume = true; }},
      {"grab_radius_mm", [](DeformConfig& c) { c.settings.grab_radius_mm = 3; }},
      {"backend", [](DeformConfig& c) { c.settings.backend = DeformBackendChoice::kAuto; }},
      {"voi_hold", [](DeformConfig& c) { c.voi_hold = !c.voi_hold; }},
      {"elastic_stiffness", [](DeformConfig& c) { c.elastic_stiffness = !c.elastic_stiffness; }},
      {"elastic_force", [](DeformConfig& c) { c.elastic_force = !c.elastic_force; }},
      {"elastic_superpose", [](DeformConfig& c) { c.elastic_superpose = !c.elastic_superpose; }},
  };
  DeformConfig ex = preset_config(1), mg = preset_config(1);
  mg.settings.relax_method = RelaxMethod::kMultigrid;
  for (const DeformConfig& base : {ex, mg}) {
    const bool is_mg = base.settings.relax_method == RelaxMethod::kMultigrid;
    INFO((is_mg ? "multigrid" : "explicit"));
    CHECK(deform_batchable(base, base));
    for (const Named& n : shared) {
      INFO(n.name);
      DeformConfig c = base;
      n.change(c);
      CHECK_FALSE(deform_batchable(base, c));
      CHECK_FALSE(deform_batchable(c, base));
    }
    // multigrid's settings do not part explicit sessions
    for (const Named& n : multigrid) {
      INFO(n.name);
      DeformConfig c = base;
      n.change(c);
      CHECK(deform_batchable(base, c) == !is_mg);
    }
    for (const Named& n : own) {
      INFO(n.name);
      DeformConfig c = base;
      n.change(c);
      CHECK(deform_batchable(base, c));
    }
  }
  // elastic sessions batch with their own kind, whatever their elastic settings (each
  // solve is a launch of its own); untangling steps alone, even beside its own kind
  DeformConfig el = preset_config(1), un = preset_config(1);
  el.settings.relax_method = RelaxMethod::kElastic;
  un.settings.untangle = true;
  CHECK(deform_batchable(el, el));
  CHECK_FALSE(deform_batchable(el, ex));
  CHECK_FALSE(deform_batchable(el, mg));
  {
    DeformConfig stiff = el;
    stiff.elastic_stiffness = true;
    stiff.settings.elastic.poisson = 0.3;
    CHECK(deform_batchable(el, stiff));
  }
  CHECK_FALSE(deform_batch_key(un));
  CHECK_FALSE(deform_batchable(un, un));
  CHECK_FALSE(deform_batchable(ex, un));
  // without relaxation neither matters
  DeformConfig still = ex;
  el.relax = un.relax = still.relax = false;
  CHECK(deform_batchable(el, el));
  CHECK(deform_batchable(un, still));
}

TEST_CASE("bad settings and contacts are refused with the field named") {
  auto patient = make_soft_patient(16);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 8;
  CpuDeformBackend b;
  CHECK(error_of([&] { b.chainmail(voxel_contact({8, 8, 8}, {1, 0, 0})); }).find("before bind") != std::string::npos);
  DeformConfig bad = cfg;
  bad.settings.min_dist = 1.5;
  CHECK(error_of([&] { b.bind(patient, bad); }).find("deform.min_dist") != std::string::npos);
  bad = cfg;
  bad.settings.material_width = 0;
  CHECK(error_of([&] { b.bind(patient, bad); }).find("deform.material_width") != std::string::npos);
  b.bind(patient, cfg);
  CHECK(error_of([&] { b.relax(); }).find("before chainmail") != std::string::npos);
  CHECK(error_of([&] { b.chainmail({Vec3(40, 8, 8), Vec3(8, 8, 8)}); }).find("skin_point_mm (X)") != std::string::npos);
  CHECK(error_of([&] { b.chainmail({Vec3(8, 8, 8), Vec3(8, NAN, 8)}); }).find("tip_mm (x) is not finite") !=
        std::string::npos);
  // after a refused contact the backend still works
  CHECK(b.chainmail(voxel_contact({8, 8, 8}, {1, 0, 0})).converged);
  CHECK(error_of([&] { b.set_displacement(std::vector<Vec3f>(3)); }).find("got 3 values") != std::string::npos);
}

TEST_CASE("DeformConfig::from_scene takes Deform{}, prep's bone threshold and the effects") {
  Scene s;
  s.deform.voi_edge = 96;
  s.prep.bone_threshold = 250;
  s.effects.relaxation = false;
  s.effects.inversion = true;
  const DeformConfig c = DeformConfig::from_scene(s);
  CHECK(c.settings.voi_edge == 96);
  CHECK(c.bone_threshold == 250);
  CHECK_FALSE(c.relax);
  CHECK(c.invert);
  // the threshold prep chose for the patient, unless the scene set one explicitly
  Patient p;
  CHECK(DeformConfig::from_scene(s, &p).bone_threshold == 250);  // prep chose none (NaN)
  p.bone_threshold_hu = 137;
  CHECK(DeformConfig::from_scene(s, &p).bone_threshold == 137);
  s.prep.bone_threshold_set = true;
  CHECK(DeformConfig::from_scene(s, &p).bone_threshold == 250);
}

TEST_CASE("a step reports J's largest change from I and its non-finite voxels, as J holds them") {
  auto torso = make_torso_patient(64);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  CpuDeformBackend b;
  b.bind(torso, cfg);
  const DeformStats st = b.step(voxel_contact({32, 14, 32}, {0.5, 5.0, -1.0}));
  // the same figures from J itself, on the host
  const Voi& v = b.voi();
  const float* j = b.deformed_brick();
  double change = 0;
  long long nonfinite = 0;
  for (int k = 0; k < v.size.z; ++k)
    for (int jj = 0; jj < v.size.y; ++jj)
      for (int i = 0; i < v.size.x; ++i) {
        const float x = j[v.index(i, jj, k)];
        if (!std::isfinite(x)) {
          ++nonfinite;
          continue;
        }
        change = std::max(change, double(std::fabs(x - torso->intensity.at(v.lo.x + i, v.lo.y + jj, v.lo.z + k))));
      }
  CHECK(st.invert_nonfinite == 0);
  CHECK(nonfinite == 0);
  // the press moves the skin: J changes by hundreds of HU there; the step computes the
  // same floats as this loop, so the two agree exactly
  CHECK(change > 100);
  CHECK(st.invert_max_change == change);

  SECTION("NaN in the image makes J non-finite there, and the count says so") {
    auto bad = std::make_shared<Patient>(*torso);
    for (int k = 30; k < 34; ++k)
      for (int jj = 20; jj < 24; ++jj)
        for (int i = 30; i < 34; ++i) bad->intensity.at(i, jj, k) = std::numeric_limits<float>::quiet_NaN();
    CpuDeformBackend nb;
    nb.bind(bad, cfg);
    const DeformStats ns = nb.step(voxel_contact({32, 14, 32}, {0.5, 5.0, -1.0}));
    // at least the 64 NaN voxels themselves (J samples I there; the material function
    // spreads NaN further through relaxation), and the largest change is over the rest
    CHECK(ns.invert_nonfinite >= 64);
    CHECK(std::isfinite(ns.invert_max_change));
  }
}

TEST_CASE("a step in two halves equals a whole step, and the halves keep their order") {
  auto torso = make_torso_patient(64);
  DeformConfig cfg = preset_config(1);
  cfg.settings.voi_edge = 32;
  CpuDeformBackend whole, halves;
  whole.bind(torso, cfg);
  halves.bind(torso, cfg);
  const DeformContact k = voxel_contact({32, 14, 32}, {0.5, 5.0, -1.0});
  const DeformStats a = whole.step(k);
  halves.set_gpu_share(4);  // no GPU here: the cpu backend ignores it
  halves.begin_step(k);
  CHECK_THROWS_WITH(halves.begin_step(k), Catch::Contains("begin_step() twice"));
  const DeformStats b = halves.end_step();
  CHECK(b.chainmail.moved == a.chainmail.moved);
  CHECK(b.invert_max_change == a.invert_max_change);
  CHECK(std::vector<float>(halves.deformed_brick(), halves.deformed_brick() + halves.voi().count()) ==
        std::vector<float>(whole.deformed_brick(), whole.deformed_brick() + whole.voi().count()));
  CHECK_THROWS_WITH(halves.end_step(), Catch::Contains("end_step() without begin_step()"));
}

TEST_CASE("begin_steps begins every backend whose contact is good; each end_step equals its step") {
  // the cpu backend has no batched launches: begin_steps begins each alone, and a refused
  // contact or a backend already in a step fails only its own index
  auto torso = make_torso_patient(64);
  DeformConfig cfg = preset_config(2);
  cfg.settings.voi_edge = 24;
  CpuDeformBackend alone;
  alone.bind(torso, cfg);
  std::vector<std::unique_ptr<CpuDeformBackend>> owned;
  std::vector<DeformBackend*> backends;
  for (int s = 0; s < 4; ++s) {
    owned.push_back(std::make_unique<CpuDeformBackend>());
    owned.back()->bind(torso, cfg);
    backends.push_back(owned.back().get());
  }
  std::vector<DeformContact> k = {voxel_contact({30, 14, 30}, {0.5, 4.0, -1.0}), voxel_contact({34, 14, 30}, {0.0, 3.0, 0.5}),
                                  voxel_contact({30, 14, 34}, {-1.0, 5.0, 0.0}), voxel_contact({34, 14, 34}, {0.5, 2.0, 1.0})};
  k[1].tip_mm = Vec3(std::numeric_limits<double>::quiet_NaN(), 0.0, 0.0);
  backends[3]->begin_step(k[3]);  // already in a step: begin_steps must not begin it again
  const std::vector<std::exception_ptr> errors = DeformBackend::begin_steps(backends, k);
  REQUIRE(errors.size() == 4);
  CHECK(!errors[0]);
  CHECK(!errors[2]);
  REQUIRE(errors[1]);
  CHECK_THROWS_WITH(std::rethrow_exception(errors[1]), Catch::Contains("tip_mm (x) is not finite"));
  REQUIRE(errors[3]);
  CHECK_THROWS_WITH(std::rethrow_exception(errors[3]), Catch::Contains("begin_step() twice"));
  CHECK_THROWS_WITH(backends[1]->end_step(), Catch::Contains("end_step() without begin_step()"));
  for (int s : {0, 2, 3}) {
    INFO("session " << s);
    const DeformStats b = backends[s]->end_step();
    const DeformStats a = alone.step(k[s]);
    CHECK(b.batch == 1);
    CHECK(b.chainmail.moved == a.chainmail.moved);
    CHECK(b.chainmail.sweeps == a.chainmail.sweeps);
    CHECK(std::vector<float>(backends[s]->deformed_brick(), backends[s]->deformed_brick() + backends[s]->voi().count()) ==
          std::vector<float>(alone.deformed_brick(), alone.deformed_brick() + alone.voi().count()));
  }
  // a mismatch of backends and contacts is the caller's error
  CHECK_THROWS_WITH(DeformBackend::begin_steps(backends, {k[0]}), Catch::Contains("4 backends and 1 contacts"));
}
