// The "cuda" backend's batched steps: sessions ready together stepped by one launch per
// stage for all of them (batch.cu's kernels), and each one's share of the batch's figures.
#include <algorithm>
#include <chrono>
#include <memory>
#include <vector>

#include "cuda/check.h"
#include "cuda/cuda_backend.h"

namespace palpsim::cuda {

bool CudaDeformBackend::begin_batch_impl(const std::vector<DeformBackend*>& group) {
  const int n = int(group.size());
  if (n < 2 || n > kMaxBatch) return false;
  std::vector<CudaDeformBackend*> m;
  unsigned long long max_count = 0;
  for (DeformBackend* b : group) {
    auto* c = dynamic_cast<CudaDeformBackend*>(b);
    if (!c || !deform_batchable(config_, c->config_)) return false;
    m.push_back(c);
    max_count = std::max<unsigned long long>(max_count, (unsigned long long)c->capacity_);
  }
  // the relaxation indexes the VOIs end to end with 32 bits
  if ((unsigned long long)n * max_count >= (1ULL << 32)) return false;
  // this backend's batch resources, unless a member of their last batch has not ended yet
  if (!batch_ || batch_.use_count() > 1) batch_ = std::make_shared<CudaBatch>();
  CudaBatch& bt = *batch_;
  bt.wait();  // the last use of the items is over
  const DeformSettings& s = config_.settings;
  const bool mg = config_.relax && s.relax_method == RelaxMethod::kMultigrid;
  const bool el = config_.relax && s.relax_method == RelaxMethod::kElastic;
  unsigned max_reset = 0, max_voi = 0;
  Vec3i most{0, 0, 0};  // the largest VOI size along each axis
  bool any_chainmail = false;
  // each session's item: its state and where each stage reads, as its own step would
  for (int i = 0; i < n; ++i) {
    CudaDeformBackend& c = *m[i];
    BatchItem& it = bt.host_items[i];
    it = BatchItem{};
    it.geo = c.geometry();
    it.u0 = c.setup_.grabbed_u_vox;
    // 2: ChainMail left out (the grabbed element alone; ChainMailStats::skipped)
    it.chainmail = c.setup_.grabbed_in_bone ? 0 : (c.setup_.skipped ? 2 : 1);
    it.reset_count = unsigned(c.dirty_.count());
    it.b = c.d_;
    it.host_counters = c.host_counters_;
    // reset leaves buffer 0; converged ChainMail leaves its result in both buffers (as its
    // start alone does), capped in the last sweep's; multigrid works in place
    int cur = it.chainmail == 1 ? (s.max_sweeps & 1) : 0;
    it.relax_src = cur;
    if (config_.relax && !mg && !el) cur = (cur + s.relax_iterations) & 1;
    it.invert_src = cur;
    c.cur_ = cur;
    c.field_extra_ = config_.relax ? (mg || el ? -1 : s.relax_iterations) : 0;
    if (el) c.ensure_elastic_buffers();
    if (mg) {
      c.ensure_multigrid_buffers();
      // reusing a G solved on a step that left ChainMail out (so clean, a G): the batch's
      // one reuse launch instead of a solver launch of its own
      if (c.setup_.skipped && c.mg_g_clean_ && multigrid_reuses(it.geo, s.relax_cycles, c.config_.relax_reuse, c.mg_))
        it.mg_g = c.mg_.g;  // mg_g_clean_ stays: the same G, this step left ChainMail out
      it.finger_r2 = c.finger_r2_;  // each session's own (its settings and patient grid)
    }
    c.dirty_ = c.voi_;
    c.prepare_stats(c.setup_);
    max_reset = std::max(max_reset, it.reset_count);
    max_voi = std::max(max_voi, unsigned(c.voi_.count()));
    for (int a = 0; a < 3; ++a) most[a] = std::max(most[a], c.voi_.size[a]);
    any_chainmail = any_chainmail || it.chainmail;
  }
  // the stages, one launch each for all sessions, with an event between stages
  bt.n = n;
  bt.done = false;
  bt.start = std::chrono::steady_clock::now();
  cudaStream_t st = bt.stream;
  PALPSIM_CUDA_CHECK(cudaMemcpyAsync(bt.dev_items, bt.host_items, n * sizeof(BatchItem), cudaMemcpyHostToDevice, st));
  PALPSIM_CUDA_CHECK(cudaEventRecord(bt.ev[0], st));
  launch_reset_batch(bt.dev_items, n, max_reset, st);
  PALPSIM_CUDA_CHECK(cudaEventRecord(bt.ev[1], st));
  if (any_chainmail) launch_chainmail_batch(bt.dev_items, n, limits_, s.max_sweeps, full_shape_, st);
  PALPSIM_CUDA_CHECK(cudaEventRecord(bt.ev[2], st));
  if (el) {
    // each session's elastic solve one cooperative launch (its settings its own), in turn
    // on the whole device, or in lanes side by side with a share of it each; the batch
    // shares the other stages' launches and its one wait
    const int lanes = std::min(n, relax_elastic_lanes());
    if (lanes <= 1) {
      for (int i = 0; i < n; ++i) m[i]->enqueue_elastic(bt.host_items[i].relax_src, st);
    } else {
      PALPSIM_CUDA_CHECK(cudaEventRecord(bt.fork, st));
      for (int l = 0; l < lanes; ++l) PALPSIM_CUDA_CHECK(cudaStreamWaitEvent(bt.lane_stream[l], bt.fork, 0));
      for (int i = 0; i < n; ++i)
        m[i]->enqueue_elastic(bt.host_items[i].relax_src, bt.lane_stream[i % lanes], i % lanes, lanes);
      for (int l = 0; l < lanes; ++l) {
        PALPSIM_CUDA_CHECK(cudaEventRecord(bt.joined[l], bt.lane_stream[l]));
        PALPSIM_CUDA_CHECK(cudaStreamWaitEvent(st, bt.joined[l], 0));
      }
    }
  } else if (mg) {
    // the reusing sessions in one launch; the others' solves in turn, without a wait
    // between them: no batched multigrid solver yet
    bool any_reuse = false;
    for (int i = 0; i < n; ++i) {
      CudaDeformBackend& c = *m[i];
      if (bt.host_items[i].mg_g) {
        any_reuse = true;
        continue;
      }
      c.launch_multigrid(bt.host_items[i].relax_src, *c.mg_shared_, c.full_mg_blocks_, st);
    }
    if (any_reuse)
      launch_multigrid_reuse_batch(bt.dev_items, n, max_voi, float(config_.bone_threshold), float(s.material_width), st);
  } else if (config_.relax) {
    launch_relax_batch(bt.dev_items, n, most, s.relax_iterations, float(s.relax_step), float(config_.bone_threshold),
                       float(s.material_width), full_shape_, st);
  }
  PALPSIM_CUDA_CHECK(cudaEventRecord(bt.ev[3], st));
  if (config_.invert) launch_invert_batch(bt.dev_items, n, max_voi, s.invert_iterations, s.invert_search, st);
  PALPSIM_CUDA_CHECK(cudaEventRecord(bt.ev[4], st));
  // the counters to each session's pinned host copy in one launch; J stays on the device
  // until deformed_brick() asks for it (batch.cu says why)
  launch_gather_batch(bt.dev_items, n, st);
  PALPSIM_CUDA_CHECK(cudaEventRecord(bt.ev[5], st));
  for (CudaDeformBackend* c : m) {
    c->in_batch_ = batch_;
    c->host_j_stale_ = config_.invert;
  }
  return true;
}

DeformStats CudaDeformBackend::end_batched_step() {
  const std::shared_ptr<CudaBatch> bt = std::move(in_batch_);
  bt->wait();
  DeformStats out = step_out_;
  InvertStats inv;
  read_counters(&out.chainmail, &inv, nullptr);
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kMultigrid) take_multigrid_counts(out);
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kElastic)
    out.elastic = elastic_.finish(host_counters_->elastic);
  if (config_.invert) out.take_inversion(inv);
  // this step's share of the batch's stage times (ms)
  const double share = 1.0 / bt->n;
  out.batch = bt->n;
  out.times.reset_ms = bt->stage_ms[0] * share;
  out.times.chainmail_ms = bt->stage_ms[1] * share;
  out.times.relax_ms = bt->stage_ms[2] * share;
  out.times.invert_ms = bt->stage_ms[3] * share;
  out.times.upload_ms = bt->stage_ms[4] * share;
  out.times.total_ms = bt->wall_ms * share;
  return out;
}

}  // namespace palpsim::cuda
