// LoadScene: a scene read, checked and its patient prepared on a loader thread while
// every other request is served, then served from the next request on.
#include "net/control.h"

#include <spdlog/spdlog.h>

#include <cstdio>

#include "core/error.h"
#include "core/thread.h"
#include "deform/backend.h"
#include "net/client_text.h"
#include "net/scene_io.h"

namespace palpsim::net {

void Server::Control::end_load() {
  if (load_ && load_->thread.joinable()) load_->thread.join();
  load_.reset();
}

void Server::Control::load_scene() {
  const auto& r = req_.load_scene();
  if (load_) {
    char b[64];
    std::snprintf(b, sizeof b, "%.1f", std::chrono::duration<double>(Clock::now() - load_->started).count());
    return refuse(v1::ERROR_LOAD_RUNNING, sh_.counters.load_running,
                  "LoadScene: refused: another LoadScene is running (" + load_->what + ", for " + b +
                      " s); send it again when ServerInfo.scene_loading is empty");
  }
  auto l = std::make_unique<Load>();
  l->routing_id.copy(*requester_id_);
  l->req_envelope = requester_req_;
  l->request_id = req_.request_id();
  l->what = r.path().empty() ? std::string("scene text") : client_text(r.path());
  l->started = Clock::now();
  Load* job = l.get();
  l->thread = std::thread([this, job, path = r.path(), text = r.text()] { prepare_world(*job, path, text); });
  load_ = std::move(l);
  deferred_ = true;
}

void Server::Control::prepare_world(Load& l, const std::string& path, const std::string& text) {
  // at the control thread's own priority: a background (SCHED_IDLE or nice 19) loader
  // would starve on a busy host, and a scene load is an operator's request that must end
  name_this_thread("palpsim-load");
  const std::string& what = l.what;
  try {
    if (path.empty() == text.empty())
      throw Error("LoadScene: set exactly one of path or text");
    // no file outside the operator's folders is read or written for a client
    auto allowed = [&](const std::string& p, const std::string& field) {
      const std::string why = paths_.check(p, "LoadScene: " + field);
      if (!why.empty()) throw Error(why);
    };
    // the scene file: a regular file inside them, judged after its links are resolved
    Scene scene = path.empty() ? parse_scene_text(text, "") : load_scene_file(paths_.resolve(path, "LoadScene: path"));
    // its name is the client's string, shown in logs, replies and frames
    scene.name = client_text(scene.name);
    if (!scene.use_phantom) allowed(scene.ct_path, what + ": ct_path");
    if (!scene.prep.cache_dir.empty())
      throw Error("LoadScene: " + what + ": prep.cache_dir is the operator's setting (palpsim-server --cache-dir, "
                  "PALPSIM_CACHE); a client's scene cannot choose the cache folder");
    if (!scene.render.record_dir.empty()) allowed(scene.render.record_dir, what + ": render.record_dir");
    // deformation settings no backend can serve refuse the scene before its patient is made
    if (scene.effects.chainmail) {
      check_deform_config(DeformConfig::from_scene(scene), "LoadScene: " + what);
      std::string why;
      if (scene.deform.backend == DeformBackendChoice::kCuda && !cuda_deform_available(&why))
        throw Error("LoadScene: " + what + ": deform.backend = \"cuda\" is not available here: " + why);
    }
    spdlog::info("loading scene '{}' from {} (poses and control requests keep being served on the old one)",
                 scene.name, what);
    PatientPtr patient = loader_(scene);
    if (!patient) throw Error("LoadScene: " + what + ": the loader returned no patient");
    l.world = make_world(scene, std::move(patient), 0);
  } catch (const std::exception& e) {
    l.error = e.what();
  } catch (...) {
    l.error = "LoadScene: " + what + ": an unknown error";
  }
  (void)load_done_tx_.send(zmq::const_buffer(nullptr, 0), zmq::send_flags::dontwait);
}

void Server::Control::finish_load() {
  zmq::message_t done;
  (void)load_done_rx_.recv(done, zmq::recv_flags::dontwait);
  if (!load_) return;
  const std::unique_ptr<Load> l = std::move(load_);
  l->thread.join();
  rep_.Clear();
  rep_.set_schema_version(v1::VERSION_CURRENT);
  rep_.set_request_id(l->request_id);
  if (!l->world) {
    refuse(v1::ERROR_SCENE_LOAD_FAILED, sh_.counters.scene_load_failures,
           std::string("LoadScene: refused, still serving '") + current_->scene.name + "': " + l->error);
    return send_reply(l->routing_id, l->req_envelope);
  }
  std::unique_ptr<World> next = std::move(l->world);
  next->generation = current_->generation + 1;
  sh_.world.store(next.get(), std::memory_order_release);
  retired_.push_back(std::move(current_));
  current_ = std::move(next);
  sh_.counters.scene_loads.fetch_add(1);
  spdlog::info("now serving scene {} (generation {})", scene_label(current_->scene), current_->generation);
  warn_quota();
  // a running worker picks the new scene up itself; the first scene that asks for
  // deformation starts one (settings were checked above; a failure past them, such as
  // a device out of memory, leaves the scene served with haptics only)
  try {
    start_deform();
  } catch (const std::exception& e) {
    spdlog::error("scene {}: {}; serving haptics only", scene_label(current_->scene), e.what());
  }
  // frames and bricks likewise: a render thread that cannot start leaves the scene without frames
  try {
    sync_stream();
  } catch (const std::exception& e) {
    spdlog::error("scene {}: {}; no frames are served", scene_label(current_->scene), e.what());
  }
  fill_info(rep_.mutable_load_scene()->mutable_server());
  send_reply(l->routing_id, l->req_envelope);
}

}  // namespace palpsim::net
