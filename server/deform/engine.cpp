// DeformEngine: backend choice and the per-session step.
#include "deform/engine.h"

#include "deform/press_cap.h"

namespace palpsim {

DeformEngine::DeformEngine(PatientPtr patient, const DeformConfig& config) {
  backend_ = make_deform_backend(config.settings.backend, &note_);
  backend_->bind(std::move(patient), config);
}

DeformStats DeformEngine::step(const DeformContact& contact) {
  has_brick_ = false;
  DeformStats st = backend_->step(pressed(contact));
  has_brick_ = backend_->config().invert;
  return st;
}

void DeformEngine::begin_step(const DeformContact& contact) {
  has_brick_ = false;
  backend_->begin_step(pressed(contact));
}

std::vector<std::exception_ptr> DeformEngine::begin_steps(const std::vector<DeformEngine*>& engines,
                                                         const std::vector<DeformContact>& contacts) {
  std::vector<DeformBackend*> backends;
  for (DeformEngine* e : engines) {
    e->has_brick_ = false;
    backends.push_back(e->backend_.get());
  }
  // each contact as its engine presses it (begin_steps() checks that the counts agree)
  std::vector<DeformContact> pressed(contacts);
  for (std::size_t i = 0; i < pressed.size() && i < engines.size(); ++i) pressed[i] = engines[i]->pressed(contacts[i]);
  return DeformBackend::begin_steps(backends, pressed);
}

DeformStats DeformEngine::end_step() {
  DeformStats st = backend_->end_step();
  has_brick_ = backend_->config().invert;
  return st;
}

DeformContact DeformEngine::pressed(const DeformContact& contact) const {
  return deform::capped_press(backend_->patient(), backend_->config(), contact);
}

void DeformEngine::reset() {
  has_brick_ = false;
  backend_->reset();
}

Volume<float> DeformEngine::deformed_volume() const {
  Volume<float> out;
  backend_->compose_deformed(out);
  return out;
}

}  // namespace palpsim
