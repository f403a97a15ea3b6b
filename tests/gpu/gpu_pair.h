// What the GPU deformation tests share (tests/gpu/deform_gpu_*.cpp): the cpu and cuda
// backends side by side on one patient, exact ChainMail comparisons, the presses that
// need the inversion's cell search, and one step of a batch against the same step alone.
#pragma once

#include <catch2/catch.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "deform/backend.h"
#include "deform/engine.h"
#include "support/deform_fixtures.h"
#include "support/phantom_press.h"
#include "support/synthetic_patient.h"

namespace palpsim::test::gpu {

// true when the cuda backend can run here; else prints why the test is skipped
inline bool have_gpu() {
  std::string why;
  if (cuda_deform_available(&why)) return true;
  std::printf("SKIPPED: %s\n", why.c_str());
  return false;
}

// the cpu reference and the cuda backend bound to the same patient and configuration
struct Pair {
  std::unique_ptr<DeformBackend> cpu, gpu;
  Pair(PatientPtr p, const DeformConfig& cfg) : cpu(make_deform_backend("cpu")), gpu(make_deform_backend("cuda")) {
    cpu->bind(p, cfg);
    gpu->bind(p, cfg);
  }
};

// ChainMail on both; every field of the stats and every displacement must be equal
inline void same_chainmail(Pair& b, const DeformContact& c) {
  const ChainMailStats a = b.cpu->chainmail(c);
  const ChainMailStats g = b.gpu->chainmail(c);
  CHECK(g.voi == a.voi);
  CHECK(g.moved == a.moved);
  CHECK(g.sweeps == a.sweeps);
  CHECK(g.converged == a.converged);
  const auto ua = b.cpu->displacement(), ug = b.gpu->displacement();
  REQUIRE(ua.size() == ug.size());
  long long differ = 0;
  for (std::size_t e = 0; e < ua.size(); ++e) differ += ua[e] != ug[e];
  CHECK(differ == 0);
}

// the largest displacement component (voxel)
inline float max_abs(const std::vector<Vec3f>& u) {
  float m = 0;
  for (const Vec3f& v : u) m = std::max({m, std::fabs(v.x), std::fabs(v.y), std::fabs(v.z)});
  return m;
}

// the phantom (340 mm over 256 voxels), the skin point over L3's spinous tip, and the
// server's lumbar configuration with the inversion's cell search: deep presses from there
// fold and send hundreds of voxels to the search
struct SearchPress {
  PatientPtr phantom;
  Vec3 X;  // skin point over L3 (mm)
  DeformConfig cfg;
};

inline SearchPress search_press() {
  PhantomCt ct = make_phantom(340.0 / 255.0);
  SearchPress sp;
  sp.X = spinous_press(ct.geometry).contact.skin_point_mm;
  sp.phantom = patient_from_intensity(std::move(ct.hu), "phantom");
  sp.cfg = preset_config(1);
  sp.cfg.settings.voi_edge = 64;
  sp.cfg.settings.relax_iterations = 20;
  sp.cfg.settings.invert_search = true;
  return sp;
}

// one batched step of every session (DeformBackend::begin_steps), each one's stats
inline std::vector<DeformStats> step_batch(const std::vector<std::unique_ptr<DeformEngine>>& sessions,
                                           const std::vector<DeformBackend*>& backends,
                                           const std::vector<DeformContact>& k) {
  const std::vector<std::exception_ptr> errors = DeformBackend::begin_steps(backends, k);
  std::vector<DeformStats> st(sessions.size());
  for (std::size_t s = 0; s < sessions.size(); ++s) {
    REQUIRE(!errors[s]);
    st[s] = sessions[s]->end_step();
  }
  return st;
}

// a session's batched step (b, on `batched`) against the same step alone (a): every
// element runs the single kernels' device functions on its own session's buffers, so the
// stats, the field and J are the same bits
inline void check_same_step(const DeformStats& b, const DeformStats& a, DeformEngine& batched, DeformEngine& alone, int n) {
  CHECK(b.batch == n);
  CHECK(b.chainmail.voi == a.chainmail.voi);
  CHECK(b.chainmail.grabbed_in_bone == a.chainmail.grabbed_in_bone);
  CHECK(b.chainmail.moved == a.chainmail.moved);
  CHECK(b.chainmail.sweeps == a.chainmail.sweeps);
  CHECK(b.chainmail.converged == a.chainmail.converged);
  CHECK(b.invert_unresolved == a.invert_unresolved);
  CHECK(b.invert_residual_vox == a.invert_residual_vox);
  CHECK(b.invert_max_change == a.invert_max_change);
  CHECK(b.invert_nonfinite == a.invert_nonfinite);
  CHECK(batched.backend().displacement() == alone.backend().displacement());
  const float* jb = batched.deformed_brick();
  REQUIRE(jb);
  CHECK(std::vector<float>(jb, jb + b.chainmail.voi.count()) ==
        std::vector<float>(alone.deformed_brick(), alone.deformed_brick() + a.chainmail.voi.count()));
}

// an elastic scene's deformation settings on the phantom: the model, the fingertip of 5 mm,
// VOI 64, the rest at preset 1's and the scene defaults (the elastic cases and batches)
inline DeformConfig phantom_elastic_config() {
  DeformConfig cfg = preset_config(1);
  cfg.settings.relax_method = RelaxMethod::kElastic;
  cfg.settings.grab_radius_mm = 5;
  cfg.settings.voi_edge = 64;
  return cfg;
}

// four sessions' presses at different points of make_torso_patient(96)'s back
inline std::vector<DeformContact> four_presses() {
  return {voxel_contact({44, 14, 44}, {1.0, 6.0, -1.0}), voxel_contact({52, 14, 44}, {0.0, 5.0, 0.5}),
          voxel_contact({44, 14, 52}, {-1.0, 7.0, 0.0}), voxel_contact({52, 14, 52}, {0.5, 4.0, 1.0})};
}

}  // namespace palpsim::test::gpu
