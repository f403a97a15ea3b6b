#include "net/patch_worker.h"

#include <chrono>
#include <thread>

#include "haptics/patch_cut.h"
#include "runtime/session_table.h"
#include "net/wire_convert.h"
#include "net/wire_limits.h"
#include "palpsim/wire.pb.h"

namespace palpsim::net {
namespace {

namespace v1 = ::palpsim::v1;

// the worker's reused message and the cutting of one patch into it
class PatchCutter {
 public:
  PatchCutter() {
    const std::size_t n = std::size_t(kMaxPatchEdge) * kMaxPatchEdge * kMaxPatchEdge;
    lm_.mutable_body()->reserve(n);
    lm_.mutable_force()->reserve(n * sizeof(float));
    lm_.mutable_grad_force()->reserve(n * sizeof(Vec3f));
  }

  // cuts the patch `q` asks for out of `world`'s patient and serializes it into `out`
  void cut(const runtime::World& world, const runtime::PatchRequest& q, runtime::PatchBytes& out) {
    const Patient& p = *world.patient;
    Vec3i size;
    const Vec3i lo = patch_box(p.grid, q.tip_mm, q.edge, size);
    const std::size_t n = std::size_t(size.x) * size.y * size.z;
    std::string* body = lm_.mutable_body();
    std::string* force = lm_.mutable_force();
    std::string* grad = lm_.mutable_grad_force();
    body->resize(n);
    force->resize(n * sizeof(float));
    grad->resize(n * sizeof(Vec3f));
    // the wire is little-endian, as the hosts palpsim builds for are (PROTOCOL.md)
    gather_patch(p, lo, size, reinterpret_cast<std::uint8_t*>(body->data()), reinterpret_cast<float*>(force->data()),
                 reinterpret_cast<Vec3f*>(grad->data()));
    set_vec(lm_.mutable_origin_mm(), p.grid.to_physical(Vec3(lo)));
    lm_.set_spacing_mm(p.grid.spacing_mm.x);
    lm_.set_stiffness_n_per_mm(q.params.stiffness_n_per_mm);
    lm_.set_friction(q.params.friction);
    lm_.set_max_force_n(q.params.max_force_n);
    lm_.set_max_force_rate_n_per_s(q.params.max_force_rate_n_per_s);
    lm_.set_min_gradient_norm(q.params.min_gradient_norm);
    lm_.set_version(q.version);
    lm_.set_scene_generation(q.generation);
    lm_.set_lo_i(lo.x);
    lm_.set_lo_j(lo.y);
    lm_.set_lo_k(lo.z);
    lm_.set_size_i(size.x);
    lm_.set_size_j(size.y);
    lm_.set_size_k(size.z);
    lm_.set_grid_size_i(p.grid.size.x);
    lm_.set_grid_size_j(p.grid.size.y);
    lm_.set_grid_size_k(p.grid.size.z);
    lm_.mutable_direction()->Clear();
    for (double d : p.grid.direction) lm_.add_direction(d);
    set_vec(lm_.mutable_center_mm(), q.tip_mm);
    lm_.set_server_time_s(q.server_time_s);
    lm_.SerializeToString(&out.bytes);
    out.session_id = q.session_id;
    out.generation = q.generation;
  }

 private:
  v1::LocalForceModel lm_;
};

}  // namespace

void run_patch_worker(runtime::ServerShared& sh) {
  PatchCutter cutter;
  while (!sh.stop.load(std::memory_order_relaxed)) {
    // the current world: once its generation is published here, older ones may be freed
    const runtime::World* world = sh.world.load(std::memory_order_acquire);
    sh.patch_seen_generation.store(world ? world->generation : 0, std::memory_order_release);
    if (!sh.patches_asked.load(std::memory_order_acquire) || !world) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      continue;
    }
    const int used = sh.slots_used.load(std::memory_order_acquire);
    for (int i = 0; i < used; ++i) {
      runtime::SessionSlot& slot = sh.slots[std::size_t(i)];
      // a channel for a slot whose session asked, made here so that the pose thread never allocates
      if (slot.patch_asked.load(std::memory_order_acquire) && !slot.patch_storage) {
        slot.patch_storage = std::make_unique<runtime::PatchChannel>();
        slot.patch_channel.store(slot.patch_storage.get(), std::memory_order_release);
      }
      runtime::PatchChannel* ch = slot.patch_channel.load(std::memory_order_acquire);
      if (!ch || !ch->request.take()) continue;
      const runtime::PatchRequest& q = ch->request.front();
      // a request of another world is stale: the session's next pose asks again
      if (q.generation != world->generation) continue;
      cutter.cut(*world, q, ch->patch.back());
      ch->patch.publish();
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
}

}  // namespace palpsim::net
