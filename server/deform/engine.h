// DeformEngine: one session's deformation, as the server's deformation worker runs
// it. It owns the chosen backend and its state for one patient; step() runs the whole
// pipeline on a contact (the newest one: the caller drops stale contacts) and reports
// stage times; the deformed VOI brick stays readable until the next step or reset.
#pragma once

#include <exception>
#include <memory>
#include <string>
#include <vector>

#include "deform/backend.h"

namespace palpsim {

/// The deformation of one session: ChainMail, relaxation and inversion on the newest
/// contact, on the backend the configuration names ("auto", "cpu" or "cuda").
class DeformEngine {
 public:
  /// Chooses the backend by `config.settings.backend` and binds it to `patient`;
  /// throws palpsim::Error for bad settings or an unavailable backend.
  DeformEngine(PatientPtr patient, const DeformConfig& config);

  /// One step from the undeformed state: reset, ChainMail, relaxation and inversion
  /// as configured, and the upload of J's VOI; returns counts and stage times.
  /// Throws palpsim::Error for a non-finite contact or X outside the patient grid.
  DeformStats step(const DeformContact& contact);
  /// step() in two halves (DeformBackend::begin_step, end_step): the worker overlaps
  /// several sessions' steps on one GPU.
  void begin_step(const DeformContact& contact);
  DeformStats end_step();
  /// begin_step() of several engines at once, batched where their backend can
  /// (DeformBackend::begin_steps); the error of an engine whose step was not begun is at
  /// its index (nullptr: begun, end it with end_step()).
  static std::vector<std::exception_ptr> begin_steps(const std::vector<DeformEngine*>& engines,
                                                     const std::vector<DeformContact>& contacts);

  /// Solves the multigrid unit response for a contact expected soon, between steps,
  /// leaving the deformation in place as it is (DeformBackend::prime).
  DeformPrime prime(const DeformContact& expected) { return backend_->prime(expected); }
  /// Whether a multigrid unit response is held, and its grabbed element (DeformBackend::unit_response).
  bool unit_response(Vec3i& grabbed_vox) const { return backend_->unit_response(grabbed_vox); }

  /// The contact a step presses: the elastic model's held short of the bone under it
  /// (deform/press_cap.h, deform.elastic.min_tissue_fraction), any other as given. step()
  /// and begin_step() take it themselves; the worker asks to know which tip J stands for.
  DeformContact pressed(const DeformContact& contact) const;

  /// Returns everything to undeformed (J = I).
  void reset();

  /// The VOI of the latest step and J on it (voi().count() floats, i fastest), or
  /// nullptr when no J exists (before a step, after reset, without inversion).
  const Voi& voi() const { return backend_->voi(); }
  const float* deformed_brick() const { return has_brick_ ? backend_->deformed_brick() : nullptr; }
  /// Whether a J exists (deformed_brick() would not be nullptr), without reading it: the
  /// cuda backend copies a batched step's J to the host only when it is first read.
  bool has_deformed_brick() const { return has_brick_; }
  /// Copies J's VOI into device memory for the renderer (DeformBackend::copy_brick_to_device);
  /// false when there is no J or the backend keeps none on a GPU.
  bool copy_brick_to_device(std::unique_ptr<DeviceBytes>& dst) const {
    return has_brick_ && backend_->copy_brick_to_device(dst);
  }

  /// The whole deformed image J (I outside the VOI), for tools and tests: copies the volume.
  Volume<float> deformed_volume() const;

  /// The backend in use ("cpu" or "cuda") and why it was chosen, for the server's log.
  const std::string& backend_name() const { return backend_->name(); }
  const std::string& backend_note() const { return note_; }

  /// The memory the engine's state holds, by stage (host and device bytes).
  DeformMemory memory() const { return backend_->memory(); }

  /// The backend itself, for stage-by-stage use in tests and benchmarks.
  DeformBackend& backend() { return *backend_; }

 private:
  std::unique_ptr<DeformBackend> backend_;
  std::string note_;
  bool has_brick_ = false;
};

}  // namespace palpsim
