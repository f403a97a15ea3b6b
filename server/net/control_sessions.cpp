// The sessions' control requests: OpenSession, CloseSession, ResetSession, SetParameter.
#include "net/control.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "net/client_text.h"
#include "net/pose_service.h"
#include "palpsim/scene.pb.h"
#include "palpsim/options.pb.h"

namespace palpsim::net {

int Server::Control::open_count() const {
  int n = 0;
  for (const auto& s : sh_.slots) n += s.id.load(std::memory_order_relaxed) != 0;
  return n;
}

void Server::Control::open() {
  // one client holds at most its quota, so that it cannot take every session
  int mine = 0;
  for (int i = 0; i < sh_.slots_used.load(std::memory_order_relaxed); ++i)
    mine += sh_.slots[i].id.load(std::memory_order_relaxed) != 0 && sh_.slots[i].owner == requester_;
  if (mine >= opt_.max_sessions_per_client)
    return refuse(v1::ERROR_SESSION_QUOTA, sh_.counters.session_quota,
                  "OpenSession: this client (its " + std::string(requester_kind()) + ") already holds " +
                      std::to_string(mine) + " sessions, the most one client may hold open at once "
                      "(palpsim-server --max-sessions-per-client); close one first");
  const int limit = std::min(world().scene.server.max_sessions, kMaxSlots);
  SessionSlot* free_slot = nullptr;
  int index = 0;
  for (int i = 0; i < kMaxSlots && !free_slot; ++i)
    if (sh_.slots[i].id.load(std::memory_order_relaxed) == 0) {
      free_slot = &sh_.slots[i];
      index = i;
    }
  if (!free_slot || open_count() >= limit)
    return refuse(v1::ERROR_TOO_MANY_SESSIONS, sh_.counters.too_many_sessions,
                  "OpenSession: all " + std::to_string(limit) + " sessions (scene server.max_sessions) are open");
  // a fresh id: high bits from the OS's random source, so that a client that knows
  // its own ids learns nothing of anyone else's (a counter through a fixed mix could
  // be inverted and stepped); the slot index in the low bits; never 0, and never the
  // id this slot had last (a late message of that session cannot reach the new one)
  std::uint64_t id = 0;
  while (id == 0 || id == last_id_[std::size_t(index)])
    id = (((std::uint64_t(random_()) << 32) | random_()) << kSlotBits) | std::uint64_t(index);
  last_id_[std::size_t(index)] = id;
  SessionSlot& s = *free_slot;
  s.set_params(world().scene.haptics);
  s.poses = 0;
  s.errors = 0;
  s.last_seq = 0;
  s.clamps = 0;
  s.local_models_sent = 0;
  s.local_poses = 0;
  s.elastic_counters.clear();
  s.passivity_counters.clear();
  s.renders_locally = false;
  s.contact = false;
  s.depth_mm = 0;
  s.client_name = client_text(req_.open().client_name());
  s.owner = requester_;
  s.set_owner_key(requester_key_.empty() ? nullptr : requester_key_.c_str());
  const std::int64_t now = ns_since(start_);
  s.last_seen_ns.store(now);
  s.last_used_ns.store(now);
  opened_order_[index] = ++id_counter_opened_;
  if (index >= sh_.slots_used.load(std::memory_order_relaxed))
    sh_.slots_used.store(index + 1, std::memory_order_release);
  s.id.store(id, std::memory_order_release);  // publishes the slot to the pose thread
  sh_.counters.sessions_opened.fetch_add(1);
  auto* o = rep_.mutable_open();
  o->set_session_id(id);
  o->set_pose_endpoint(pose_endpoint_);
  fill_params(o->mutable_params(), world().scene.haptics);
  fill_info(o->mutable_server());
  spdlog::info("session {} opened ({}), {} open", hex_id(id), s.client_name.empty() ? "unnamed" : s.client_name,
               open_count());
}

std::string Server::Control::deform_summary(std::uint64_t id) const {
  DeformSessionReport r;
  if (!deform_ || !deform_->session_report(id, r)) return "";
  const double k = r.steps ? 1.0 / double(r.steps) : 0.0;
  char b[320];
  std::snprintf(b, sizeof b,
                "; deformation (%s): %llu steps, mean %.2f ms (chainmail %.2f, relax %.2f, invert %.2f), %llu "
                "contacts dropped, %llu non-converged, %llu failures",
                r.backend.empty() ? "no contact" : r.backend.c_str(), (unsigned long long)r.steps, r.sum.total_ms * k,
                r.sum.chainmail_ms * k, r.sum.relax_ms * k, r.sum.invert_ms * k,
                (unsigned long long)r.contacts_dropped, (unsigned long long)r.non_converged,
                (unsigned long long)r.failures);
  return b;
}

void Server::Control::close_session() {
  const std::uint64_t id = req_.close().session_id();
  SessionSlot* s = session_or_refuse(id, "CloseSession.session_id");
  if (!s) return;
  const std::string deformation = deform_summary(id);
  free_session(*s);
  sh_.counters.sessions_closed.fetch_add(1);
  auto* c = rep_.mutable_close();
  c->set_session_id(id);
  c->set_poses(s->poses.load());
  spdlog::info("session {} closed after {} poses{}", hex_id(id), s->poses.load(), deformation);
}

void Server::Control::reset() {
  const std::uint64_t id = req_.reset().session_id();
  SessionSlot* s = session_or_refuse(id, "ResetSession.session_id");
  if (!s) return;
  s->reset_requests.fetch_add(1, std::memory_order_release);
  rep_.mutable_reset()->set_session_id(id);
}

void Server::Control::set_parameter() {
  const auto& r = req_.set_parameter();
  SessionSlot* s = session_or_refuse(r.session_id(), "SetParameter.session_id");
  if (!s) return;
  // names and ranges come from the scene schema's Haptics message
  const auto* field = v1::Haptics::descriptor()->FindFieldByName(r.name());
  if (!field || field->cpp_type() != google::protobuf::FieldDescriptor::CPPTYPE_DOUBLE)
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter,
                  "SetParameter.name: '" + client_text(r.name()) +
                      "' is not a haptics parameter (stiffness_n_per_mm, friction, max_force_n, "
                      "max_force_rate_n_per_s, min_gradient_norm)");
  const auto& o = field->options();
  const double lo = o.GetExtension(v1::min), hi = o.GetExtension(v1::max), v = r.value();
  if (!std::isfinite(v) || v < lo || v > hi) {
    char b[256];
    std::snprintf(b, sizeof b, "SetParameter.value: %s = %g is outside [%g, %g] %s", field->name().c_str(), v, lo, hi,
                  o.GetExtension(v1::unit).c_str());
    return refuse(v1::ERROR_BAD_PARAMETER, sh_.counters.bad_parameter, b);
  }
  HapticsSettings p = s->params();
  if (r.name() == "stiffness_n_per_mm") p.stiffness_n_per_mm = v;
  else if (r.name() == "friction") p.friction = v;
  else if (r.name() == "max_force_n") p.max_force_n = v;
  else if (r.name() == "max_force_rate_n_per_s") p.max_force_rate_n_per_s = v;
  else if (r.name() == "min_gradient_norm") p.min_gradient_norm = v;
  s->set_params(p);
  auto* out = rep_.mutable_set_parameter();
  out->set_session_id(r.session_id());
  fill_params(out->mutable_params(), p);
}

}  // namespace palpsim::net
