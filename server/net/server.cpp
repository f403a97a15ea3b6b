// The server's threads (control, pose, patch) and the addresses it derives; the control
// thread itself is net/control.h.
#include "net/server.h"

#include <string>
#include <utility>

#include "core/error.h"
#include "core/thread.h"
#include "net/control.h"
#include "net/patch_worker.h"
#include "net/pose_service.h"
#include "runtime/heap_trimmer.h"

namespace palpsim::net {

namespace {
// the address `offset` ports above a tcp control address ("*" stays "*"), or the control
// path with `suffix` for ipc:// and inproc:// ("." or "-" joined)
std::string derive_endpoint(const std::string& control, int offset, const std::string& suffix) {
  if (control.rfind("tcp://", 0) == 0) {
    const auto colon = control.rfind(':');
    if (colon == std::string::npos || colon < 6) throw Error("--bind " + control + ": a tcp address needs :PORT");
    const std::string port = control.substr(colon + 1);
    if (port == "*") return control;
    try {
      std::size_t used = 0;
      const int p = std::stoi(port, &used);
      if (used != port.size() || p <= 0 || p + offset > 65535) throw std::invalid_argument(port);
      return control.substr(0, colon + 1) + std::to_string(p + offset);
    } catch (const std::exception&) {
      throw Error("--bind " + control + ": port '" + port + "' is not a number in 1.." +
                  std::to_string(65535 - offset) + " or *");
    }
  }
  if (control.rfind("ipc://", 0) == 0) return control + "." + suffix;
  if (control.rfind("inproc://", 0) == 0) return control + "-" + suffix;
  throw Error("--bind " + control + ": expected tcp://HOST:PORT, ipc://PATH or inproc://NAME");
}
}  // namespace

std::string derive_pose_endpoint(const std::string& control) { return derive_endpoint(control, 1, "pose"); }
std::string derive_stream_endpoint(const std::string& control) { return derive_endpoint(control, 2, "stream"); }

bool is_loopback_endpoint(const std::string& e) {
  auto starts = [&](const char* p) { return e.rfind(p, 0) == 0; };
  return starts("ipc://") || starts("inproc://") || starts("tcp://127.") || starts("tcp://localhost:") ||
         starts("tcp://[::1]:") || starts("tcp://lo:");
}

Server::Server(const Scene& scene, PatientPtr patient, PatientLoader loader, const ServerOptions& options)
    : shared_(std::make_unique<ServerShared>()) {
  if (!patient) throw Error("Server: no patient for scene '" + scene.name + "'");
  control_ = std::make_unique<Control>(*shared_, scene, std::move(patient), std::move(loader), options);
  control_endpoint_ = control_->control_endpoint();
  pose_endpoint_ = control_->pose_endpoint();
}

Server::~Server() { stop(); }

void Server::start() {
  if (started_) return;
  started_ = true;
  const auto t0 = control_->start();
  control_->start_deform();
  try {
    control_->sync_stream();
  } catch (...) {
    control_->stop_deform();
    throw;
  }
  pose_thread_ = std::thread([this, t0] {
    name_this_thread("palpsim-pose");
    if (const int p = control_->pose_fifo()) raise_this_thread(p);
    run_pose_service(control_->pose_socket(), *shared_, t0);
  });
  control_thread_ = std::thread([this] {
    name_this_thread("palpsim-control");
    control_->run();
  });
  // local force model patches, cut off the pose thread (it naps while no session asks)
  patch_thread_ = std::thread([this] {
    name_this_thread("palpsim-patch");
    run_patch_worker(*shared_);
  });
  heap_trimmer_ = std::make_unique<runtime::HeapTrimmer>(1.0, std::size_t(4) << 20, &shared_->heap_trim_requested);
}

void Server::stop() {
  shared_->stop.store(true);
  if (pose_thread_.joinable()) pose_thread_.join();
  if (control_thread_.joinable()) control_thread_.join();
  if (patch_thread_.joinable()) patch_thread_.join();
  heap_trimmer_.reset();
  if (control_) {
    control_->stop_stream();
    control_->stop_deform();
    control_->close();
  }
}

const ContactSlot* Server::contact_slot(std::uint64_t session_id) const {
  if (session_id == 0) return nullptr;
  const SessionSlot& s = shared_->slots[runtime::slot_index(session_id)];
  return s.id.load(std::memory_order_acquire) == session_id ? &s.latest : nullptr;
}

bool Server::deformation_running() const { return control_->deform() != nullptr; }

std::string Server::stream_endpoint() const { return control_->stream_endpoint(); }

bool Server::deformed_volume(std::uint64_t session_id, Volume<float>& out, double timeout_s) const {
  DeformWorker* w = control_->deform();
  return w && w->deformed_volume(session_id, out, timeout_s);
}

std::vector<std::uint64_t> Server::open_sessions() const {
  std::vector<std::uint64_t> ids;
  for (const auto& s : shared_->slots)
    if (const std::uint64_t id = s.id.load(std::memory_order_acquire)) ids.push_back(id);
  return ids;
}

}  // namespace palpsim::net
