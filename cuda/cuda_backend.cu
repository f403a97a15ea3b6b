// The "cuda" backend: device state, reset, stage calls and the timed step.
#include "cuda/cuda_backend.h"

#include <algorithm>
#include <chrono>
#include <cstring>

#include "cuda/check.h"
#include "cuda/register_backends.h"

namespace palpsim::cuda {

namespace {

// the undeformed state on the first n elements of every buffer, and zero counters,
// in one launch: nine cudaMemsetAsync calls cost ~45 us at any VOI size (one launch
// each, DEVICE.md's 3.3 us floor plus their gaps), this costs one launch
__global__ void reset_kernel(unsigned n, DeviceBuffers b) {
  reset_elements(n, b, blockIdx.x * blockDim.x + threadIdx.x, gridDim.x * blockDim.x);
}

}  // namespace

CudaDeviceBytes::CudaDeviceBytes(std::size_t bytes) : size_(bytes) {
  PALPSIM_CUDA_CHECK(cudaMalloc(&ptr_, bytes));
}

CudaDeviceBytes::~CudaDeviceBytes() {
  // errors are ignored here: a destructor must not throw
  cudaFree(ptr_);
}

std::unique_ptr<DeformBackend> make_cuda_deform_backend() { return std::make_unique<CudaDeformBackend>(); }

bool cuda_device_usable(std::string* why) {
  int n = 0;
  const cudaError_t e = cudaGetDeviceCount(&n);
  if (e != cudaSuccess || n == 0) {
    if (why)
      *why = e != cudaSuccess ? std::string("no CUDA device (") + cudaGetErrorString(e) + ")" : "no CUDA device found";
    cudaGetLastError();  // clear the sticky-free error so later calls start clean
    return false;
  }
  cudaDeviceProp prop{};
  if (cudaGetDeviceProperties(&prop, 0) != cudaSuccess) {
    if (why) *why = "cudaGetDeviceProperties failed";
    return false;
  }
  if (why) *why = std::string("device 0: ") + prop.name;
  return true;
}

void register_deform_backend() {
  deform_backends().add(DeformBackendChoice::kCuda, {cuda_device_usable, make_cuda_deform_backend});
}

CudaDeformBackend::CudaDeformBackend() : DeformBackend("cuda") {}

CudaDeformBackend::~CudaDeformBackend() { release(); }

void CudaDeformBackend::release() {
  // errors are ignored here: a destructor must not throw
  in_batch_.reset();      // a batch still in flight is waited for by its last holder
  batch_.reset();
  patient_copy_.reset();  // the shared patient copy: freed with its last holder
  for (auto& buf : d_.u)
    for (float*& c : buf) cudaFree(c);
  for (int*& s : d_.stamp) cudaFree(s);
  cudaFree(d_.j);
  cudaFree(d_.relax_w);
  cudaFree(d_.search_queue);
  cudaFree(d_.search_slot);
  cudaFree(d_.search_candidates);
  cudaFree(d_.cell_folded);
  cudaFree(d_.untangle_flags);
  for (float*& c : d_.untangle_new) cudaFree(c);
  cudaFree(d_.counters);
  // the session's own multigrid buffers; the scratch goes with its last holder
  for (void* q : {(void*)mg_.g, (void*)mg_.g_last, (void*)mg_.flags}) cudaFree(q);
  mg_ = MultigridBuffers{};
  mg_shared_.reset();
  mg_own_.reset();
  // the elastic model's own buffers; its scratch and the body copy go with their last holders
  elastic_.release();
  el_shared_.reset();
  el_lane_.reset();
  body_copy_.reset();
  cudaFreeHost(host_counters_);
  cudaFreeHost(host_j_);
  for (cudaEvent_t& e : ev_)
    if (e) cudaEventDestroy(e);
  if (stream_) cudaStreamDestroy(stream_);
  d_ = DeviceBuffers{};
  host_counters_ = nullptr;
  host_j_ = nullptr;
  stream_ = nullptr;
  for (cudaEvent_t& e : ev_) e = nullptr;
  capacity_ = 0;
}

void CudaDeformBackend::bind_impl() {
  release();
  const Patient& p = *patient_;
  const std::size_t nvol = p.grid.count();
  capacity_ = max_voi_count();
  if (capacity_ >= (1LL << 31))
    throw Error("deform backend \"cuda\": a VOI of " + std::to_string(capacity_) +
                " voxels is too large (the kernels index VOIs with 32 bits; use a smaller deform.voi_edge)");
  const std::size_t n = std::size_t(capacity_);
  PALPSIM_CUDA_CHECK(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
  for (cudaEvent_t& e : ev_) PALPSIM_CUDA_CHECK(cudaEventCreate(&e));
  // the patient: one device copy shared with every other session bound to it
  patient_copy_ = DevicePatient::acquire(patient_);
  d_.intensity = patient_copy_->intensity();
  d_.bone = patient_copy_->bone();
  // VOI-sized state, undeformed. The fills go on this backend's own stream, which the
  // first step's kernels follow: cudaMemset() would run on the legacy default stream, which
  // a non-blocking stream does not wait for, and returns before a device fill is done, so
  // the first ChainMail could read stamps and counters not yet set (a "did not converge
  // ..., 0 elements moved" line)
  for (auto& buf : d_.u)
    for (float*& c : buf) {
      PALPSIM_CUDA_CHECK(cudaMalloc(&c, n * sizeof(float)));
      PALPSIM_CUDA_CHECK(cudaMemsetAsync(c, 0, n * sizeof(float), stream_));
    }
  for (int*& s : d_.stamp) {
    PALPSIM_CUDA_CHECK(cudaMalloc(&s, n * sizeof(int)));
    PALPSIM_CUDA_CHECK(cudaMemsetAsync(s, 0xff, n * sizeof(int), stream_));  // -1: never moved
  }
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.j, n * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.counters, sizeof(Counters)));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(d_.counters, 0, sizeof(Counters), stream_));
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
  PALPSIM_CUDA_CHECK(cudaMallocHost(&host_counters_, sizeof(Counters)));
  PALPSIM_CUDA_CHECK(cudaMallocHost(&host_j_, n * sizeof(float)));
  std::memset(host_counters_, 0, sizeof(Counters));
  full_shape_ = shape_ = persistent_launch_shape();
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kMultigrid) ensure_multigrid_buffers();
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kExplicit) ensure_relax_buffers();
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kElastic) ensure_elastic_buffers();
  if (config_.relax && config_.settings.untangle) ensure_untangle_buffers();
  // the inversion's search queue, slot map and the scatter's list, only for scenes that
  // ask for the search: the queue a 32nd of the VOI (a fold's searched voxels are a few
  // hundred to a few thousand at VOI 64), at least 2048, the list four cells a queued
  // voxel (about nine are found for each, and few voxels are queued at once); voxels
  // beyond the queue are searched in place, and a full list sends the queue to the rings
  // (invert.cu)
  if (config_.invert && config_.settings.invert_search) {
    d_.search_capacity = unsigned(std::max<long long>(2048, capacity_ / 32));
    d_.candidate_capacity = 4 * d_.search_capacity;
    PALPSIM_CUDA_CHECK(cudaMalloc(&d_.search_queue, std::size_t(d_.search_capacity) * sizeof(InvertQueued)));
    PALPSIM_CUDA_CHECK(cudaMalloc(&d_.search_slot, n * sizeof(int)));
    PALPSIM_CUDA_CHECK(
        cudaMalloc(&d_.search_candidates, std::size_t(d_.candidate_capacity) * sizeof(InvertCandidate)));
  }
  dirty_ = Voi{};
  cur_ = 0;
  field_extra_ = 0;
}

void CudaDeformBackend::ensure_relax_buffers() {
  // the explicit relaxation's weights, only for scenes (or callers of relax()) that relax
  if (d_.relax_w) return;
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.relax_w, std::size_t(capacity_) * sizeof(float)));
}

void CudaDeformBackend::ensure_untangle_buffers() {
  // only for scenes (or callers of untangle()) that ask for it: a stage not asked for holds nothing
  if (d_.untangle_flags) return;
  const std::size_t n = std::size_t(capacity_);
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.cell_folded, n));
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.untangle_flags, n));
  for (float*& c : d_.untangle_new) PALPSIM_CUDA_CHECK(cudaMalloc(&c, n * sizeof(float)));
}

void CudaDeformBackend::ensure_multigrid_buffers() {
  if (mg_.capacity > 0) return;
  // the largest coarse levels: the largest VOI with every level's origin at 0
  Vec3i most;
  for (int a = 0; a < 3; ++a)
    most[a] = config_.settings.whole_volume ? patient_->grid.size[a] : std::min(config_.settings.voi_edge, patient_->grid.size[a]);
  const long long nc = std::max(1LL, deform::multigrid_plan(most, Vec3i{0, 0, 0}).coarse_count);
  const std::size_t n = std::size_t(capacity_);
  // the session's own: its unit response, the last one, the flags; the scratch is shared
  for (float** v : {&mg_.g, &mg_.g_last}) PALPSIM_CUDA_CHECK(cudaMalloc(v, n * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&mg_.flags, 3 * sizeof(int)));
  mg_shared_ = MultigridScratch::shared(capacity_, nc);
  mg_shared_->lend_to(mg_);
  // on this backend's stream, waited for (a legacy-stream cudaMemset races the steps' stream; see bind)
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(mg_.flags, 0, 3 * sizeof(int), stream_));
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
  mg_.capacity = capacity_;
  mg_.coarse_capacity = nc;
  full_mg_blocks_ = mg_blocks_ = relax_multigrid_blocks();
}

void CudaDeformBackend::ensure_elastic_buffers() {
  if (elastic_.bound()) return;
  body_copy_ = DeviceBody::acquire(patient_);
  // the largest VOI along each axis (compute_voi clips at the border)
  Vec3i most;
  for (int a = 0; a < 3; ++a)
    most[a] = config_.settings.whole_volume ? patient_->grid.size[a] : std::min(config_.settings.voi_edge, patient_->grid.size[a]);
  elastic_.bind(*patient_, config_.elastic_params(), most);
  el_shared_ = ElasticScratch::shared(elastic_.capacity(), elastic_.coarse_capacity());
  el_blocks_ = relax_elastic_blocks();
}


DeformMemory CudaDeformBackend::memory_impl() const {
  // what bind_impl allocated: both displacement fields and both sweep stamps serve
  // ChainMail (relaxation ping-pongs between the same two fields); J and its pinned host
  // copy serve the inversion, but are allocated whatever the scene asks. The patient
  // copy is shared with the other sessions on it, so it is counted apart.
  const std::size_t n = std::size_t(capacity_);
  DeformMemory m;
  m.chainmail_bytes = sizeof(d_.u) / sizeof(float*) * n * sizeof(float) +
                      sizeof(d_.stamp) / sizeof(int*) * n * sizeof(int) + 2 * sizeof(Counters);
  // untangling's flags and sweep buffer, when it was asked for
  if (d_.untangle_flags) m.relax_bytes = 2 * n + sizeof(d_.untangle_new) / sizeof(float*) * n * sizeof(float);
  // the explicit relaxation's weights, when it was asked for
  if (d_.relax_w) m.relax_bytes += n * sizeof(float);
  m.invert_bytes = 2 * n * sizeof(float) + std::size_t(d_.search_capacity) * sizeof(InvertQueued) +
                   (d_.search_slot ? n * sizeof(int) : 0) +
                   std::size_t(d_.candidate_capacity) * sizeof(InvertCandidate);
  m.shared_patient_bytes = patient_copy_ ? patient_copy_->bytes() : 0;
  // multigrid: the session's two unit responses and flags, a scratch of its own while steps
  // run side by side; the shared scratch once per server
  if (mg_.capacity > 0) m.relax_bytes += 2 * std::size_t(mg_.capacity) * sizeof(float) + 3 * sizeof(int);
  if (mg_own_) m.relax_bytes += mg_own_->bytes();
  if (mg_shared_) m.shared_scratch_bytes = mg_shared_->bytes();
  // elastic: the session's field, flags and moduli of every level (and the unit press), a
  // scratch of its own while steps run side by side; the shared scratch once per server,
  // the body copy once per patient
  m.relax_bytes += elastic_.bytes();
  if (el_shared_) m.shared_scratch_bytes += el_shared_->bytes();
  // and the lanes' scratches (lanes 1 and up, all alive while sessions batch in lanes)
  if (el_lane_) m.shared_scratch_bytes += el_lane_->bytes() * std::size_t(relax_elastic_lanes() - 1);
  if (body_copy_) m.shared_patient_bytes += body_copy_->bytes();
  return m;
}

bool CudaDeformBackend::launch_multigrid_for(const StepGeometry& g, int src, MultigridScratch& scratch, int blocks,
                                             cudaStream_t stream, bool prime) {
  const DeformSettings& s = config_.settings;
  scratch.lend_to(mg_);
  const MultigridScratch::Turn turn(scratch, stream);
  return launch_relax_multigrid(g, src, s.relax_cycles, s.relax_warm_cycles, float(config_.bone_threshold),
                                float(s.material_width), finger_r2_, prime || config_.relax_reuse, d_, mg_, blocks,
                                stream, prime);
}

void CudaDeformBackend::launch_multigrid(int src, MultigridScratch& scratch, int blocks, cudaStream_t stream) {
  launch_multigrid_for(geometry(), src, scratch, blocks, stream, false);
  mg_g_clean_ = setup_.skipped;
}

DeformPrime CudaDeformBackend::prime_impl(const ChainMailStats& expected) {
  const DeformSettings& s = config_.settings;
  ensure_multigrid_buffers();
  StepGeometry g;
  g.voi = expected.voi;
  g.volume_size = patient_->grid.size;
  g.grabbed = expected.grabbed_vox - expected.voi.lo;
  if (multigrid_reuses(g, s.relax_cycles, true, mg_)) return {};  // held already
  launch_shape_for_share();  // this pass's share of the device, as a step takes it
  // on the session's stream, in the scratch's turn, as a step's solve
  DeformPrime out;
  out.warm = launch_multigrid_for(g, cur_, step_multigrid_scratch(), mg_blocks_, stream_, true);
  out.solved = true;
  out.steps = out.warm ? mg_.warm_steps : s.relax_cycles;  // (bind checks relax_cycles <= kMultigridMaxCycles)
  mg_g_clean_ = true;  // a prime solves G alone
  return out;
}

void CudaDeformBackend::take_multigrid_counts(DeformStats& out) {
  set_multigrid_counts(out, host_counters_->relax_solves, host_counters_->relax_warm != 0, mg_.warm_steps);
  // three solves left no G (the device knew it): nothing to start a prime from, as on the cpu
  if (host_counters_->relax_solves == 3) mg_.cache = deform::MultigridCache{};
}

void CudaDeformBackend::wait_impl() { PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_)); }

MultigridScratch& CudaDeformBackend::own_multigrid_scratch() {
  if (!mg_own_) mg_own_ = std::make_shared<MultigridScratch>(mg_.capacity, mg_.coarse_capacity);
  return *mg_own_;
}

StepGeometry CudaDeformBackend::geometry() const {
  StepGeometry g;
  g.voi = voi_;
  g.volume_size = patient_->grid.size;
  g.grabbed = setup_.grabbed_vox - voi_.lo;
  return g;
}

void CudaDeformBackend::enqueue_reset() {
  // zero the part of the buffers the last VOI used, and the counters
  const unsigned n = unsigned(dirty_.count());
  const unsigned threads = 256;
  const unsigned blocks = std::max(1u, std::min((n + threads - 1) / threads, unsigned(4 * shape_.relax_blocks)));
  reset_kernel<<<blocks, threads, 0, stream_>>>(n, d_);
  PALPSIM_CUDA_CHECK(cudaGetLastError());
  dirty_ = Voi{};
  cur_ = 0;
  field_extra_ = 0;
}

void CudaDeformBackend::enqueue_chainmail() {
  dirty_ = voi_;
  field_extra_ = 0;  // the field reaches as far as ChainMail's sweeps
  if (setup_.grabbed_in_bone) return;  // nothing moves
  if (setup_.skipped) {
    // the multigrid relaxation needs the grabbed element alone (both buffers hold it)
    launch_chainmail_start(geometry(), setup_.grabbed_u_vox, d_, stream_);
    return;
  }
  launch_chainmail(geometry(), setup_.grabbed_u_vox, limits_, config_.settings.max_sweeps, d_, shape_, stream_);
  // converged: both buffers hold the result; capped: the last sweep's buffer does
  cur_ = config_.settings.max_sweeps & 1;
}

void CudaDeformBackend::enqueue_elastic(int buffer, cudaStream_t stream, int lane, int lanes) {
  ensure_elastic_buffers();
  const ElasticPatient ep{patient_copy_->intensity(), patient_copy_->bone(), body_copy_->body(),
                          body_copy_->dist_skin_mm()};
  // lane 0 solves in the scratch every session shares; another lane in that lane's
  // (held while this session was last in that lane)
  if (lane > 0 && (!el_lane_ || el_lane_->lane != lane))
    el_lane_ = ElasticScratch::shared(elastic_.capacity(), elastic_.coarse_capacity(), lane);
  ElasticScratch& scratch = lane > 0 ? *el_lane_ : *el_shared_;
  elastic_.enqueue(*patient_, ep, voi_, setup_.skin_vox, setup_.tip_vox, scratch, std::max(1, el_blocks_ / lanes),
                   d_.u[buffer], &d_.counters->elastic, stream);
}

void CudaDeformBackend::enqueue_relax() {
  const DeformSettings& s = config_.settings;
  if (s.relax_method == RelaxMethod::kElastic) {
    // every element of the VOI into the current buffer, which the reset and ChainMail's
    // start left at 0 but for the grabbed element; with other steps in flight beside it, in
    // a scratch of its own
    enqueue_elastic(cur_, stream_);
    field_extra_ = -1;
    return;
  }
  if (s.relax_method == RelaxMethod::kMultigrid) {
    // in place on the current buffer; with other steps in flight beside it, in a scratch
    // of its own
    ensure_multigrid_buffers();
    launch_multigrid(cur_, step_multigrid_scratch(), mg_blocks_, stream_);
    field_extra_ = -1;  // the steady state is nonzero wherever the grabbed element is felt
    return;
  }
  ensure_relax_buffers();
  launch_relax(geometry(), cur_, field_extra_, s.relax_iterations, float(s.relax_step), float(config_.bone_threshold),
               float(s.material_width), d_, shape_, stream_);
  cur_ = (cur_ + s.relax_iterations) & 1;
  if (field_extra_ >= 0) field_extra_ = std::min(field_extra_ + s.relax_iterations, 1 << 24);
}

void CudaDeformBackend::enqueue_untangle() {
  ensure_untangle_buffers();
  field_extra_ = -1;
  if (!setup_.grabbed_in_bone) launch_untangle(geometry(), cur_, d_, shape_, stream_);
}

void CudaDeformBackend::enqueue_invert() {
  launch_invert(geometry(), cur_, config_.settings.invert_iterations, config_.settings.invert_search, d_, stream_);
}

void CudaDeformBackend::enqueue_upload() {
  PALPSIM_CUDA_CHECK(cudaMemcpyAsync(host_j_, d_.j, std::size_t(voi_.count()) * sizeof(float),
                                     cudaMemcpyDeviceToHost, stream_));
}

void CudaDeformBackend::finish(ChainMailStats* stats, InvertStats* inv, UntangleStats* unt) {
  PALPSIM_CUDA_CHECK(cudaMemcpyAsync(host_counters_, d_.counters, sizeof(Counters), cudaMemcpyDeviceToHost, stream_));
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
  read_counters(stats, inv, unt);
}

void CudaDeformBackend::read_counters(ChainMailStats* stats, InvertStats* inv, UntangleStats* unt) {
  if (stats && !stats->grabbed_in_bone) {
    stats->sweeps = host_counters_->sweeps;
    stats->moved = (long long)host_counters_->moved_total;
    stats->converged = host_counters_->converged != 0;
  }
  if (inv) {
    float r;
    std::memcpy(&r, &host_counters_->residual_bits, sizeof r);
    inv->max_residual_vox = r;
    inv->unresolved = (long long)host_counters_->unresolved;
    float c;
    std::memcpy(&c, &host_counters_->change_bits, sizeof c);
    inv->max_change = c;
    inv->nonfinite = (long long)host_counters_->nonfinite;
    inv->searched = (long long)host_counters_->search_queued;
    inv->scattered = (long long)host_counters_->search_scattered;
  }
  if (unt && !setup_.grabbed_in_bone) {
    const Counters& c = *host_counters_;
    const bool reverted = c.untangle_reverted != 0;
    *unt = UntangleStats{c.untangle_folded[0], c.untangle_folded[reverted ? 0 : c.untangle_rounds], c.untangle_rounds,
                         c.untangle_sweeps, (long long)c.untangle_moved, reverted};
  }
}

void CudaDeformBackend::reset_impl() {
  enqueue_reset();
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
}

void CudaDeformBackend::chainmail_impl(ChainMailStats& st) {
  st.sweeps = 0;
  st.moved = 0;
  st.converged = true;
  // the wrapper has reset a previous deformation; the counters start at zero
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(d_.counters, 0, sizeof(Counters), stream_));
  enqueue_chainmail();
  finish(&st, nullptr);
}

void CudaDeformBackend::relax_impl() {
  enqueue_relax();
  if (config_.settings.relax_method != RelaxMethod::kElastic) {
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
    return;
  }
  // the elastic solve's counts, for what its next step starts from
  finish(nullptr, nullptr);
  elastic_.finish(host_counters_->elastic);
}

void CudaDeformBackend::forget_impl() { elastic_.forget(); }

UntangleStats CudaDeformBackend::untangle_impl() {
  UntangleStats r;
  enqueue_untangle();
  finish(nullptr, nullptr, &r);
  return r;
}

InvertStats CudaDeformBackend::invert_impl() {
  InvertStats r;
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->residual_bits, 0, sizeof(unsigned), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->unresolved, 0, sizeof(unsigned long long), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->change_bits, 0, sizeof(unsigned), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->nonfinite, 0, sizeof(unsigned long long), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->search_queued, 0, sizeof(unsigned), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->search_candidates, 0, sizeof(unsigned), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->search_spill, 0, sizeof(int), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->search_scattered, 0, sizeof(unsigned), stream_));
  PALPSIM_CUDA_CHECK(cudaMemsetAsync(&d_.counters->search_bounds, 0, sizeof(ScatterBounds), stream_));
  enqueue_invert();
  finish(nullptr, &r);
  return r;
}

const float* CudaDeformBackend::deformed_brick_impl() const {
  // a batched step's J reaches the host only when read (batch.cu says why)
  if (host_j_stale_) {
    PALPSIM_CUDA_CHECK(cudaMemcpyAsync(host_j_, d_.j, std::size_t(voi_.count()) * sizeof(float), cudaMemcpyDeviceToHost,
                                       stream_));
    PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
    host_j_stale_ = false;
  }
  return host_j_;
}

void CudaDeformBackend::upload_impl() {
  host_j_stale_ = false;
  enqueue_upload();
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
}

DeformStats CudaDeformBackend::step_impl(const ChainMailStats& setup) {
  begin_step_impl(setup);
  return end_step_impl();
}

void CudaDeformBackend::prepare_stats(const ChainMailStats& setup) {
  DeformStats& out = step_out_;
  out = DeformStats{};
  out.chainmail = setup;
  out.chainmail.sweeps = 0;
  out.chainmail.moved = 0;
  out.chainmail.converged = true;
  if (config_.relax) set_relax_counts(out);
}

void CudaDeformBackend::begin_step_impl(const ChainMailStats& setup) {
  // every stage is enqueued on one stream with an event between stages; end_step_impl()
  // waits once, then reads the stage times from the events
  in_batch_.reset();
  host_j_stale_ = false;  // the upload below copies J
  step_start_ = std::chrono::steady_clock::now();
  launch_shape_for_share();
  prepare_stats(setup);
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[0], stream_));
  enqueue_reset();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[1], stream_));
  enqueue_chainmail();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[2], stream_));
  if (config_.relax) enqueue_relax();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[3], stream_));
  if (config_.relax && config_.settings.untangle) enqueue_untangle();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[4], stream_));
  if (config_.invert) enqueue_invert();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[5], stream_));
  if (config_.invert) enqueue_upload();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[6], stream_));
}

DeformStats CudaDeformBackend::end_step_impl() {
  if (in_batch_) return end_batched_step();
  DeformStats out = step_out_;
  const bool untangle = config_.relax && config_.settings.untangle;
  InvertStats inv;
  finish(&out.chainmail, &inv, untangle ? &out.untangle : nullptr);
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kMultigrid) take_multigrid_counts(out);
  if (config_.relax && config_.settings.relax_method == RelaxMethod::kElastic)
    out.elastic = elastic_.finish(host_counters_->elastic);
  if (config_.invert) out.take_inversion(inv);
  // stage times from the events (ms)
  float ms[6];
  for (int s = 0; s < 6; ++s) PALPSIM_CUDA_CHECK(cudaEventElapsedTime(&ms[s], ev_[s], ev_[s + 1]));
  out.times.reset_ms = ms[0];
  out.times.chainmail_ms = ms[1];
  out.times.relax_ms = ms[2];
  out.times.untangle_ms = ms[3];
  out.times.invert_ms = ms[4];
  out.times.upload_ms = ms[5];
  out.times.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - step_start_).count();
  return out;
}

void CudaDeformBackend::launch_shape_for_share() {
  // each persistent kernel takes 1/gpu_share_ of what fits on the device (at least one
  // block), so that that many sessions' cooperative grids are resident together
  shape_ = full_shape_;
  shape_.chainmail_blocks = std::max(1, full_shape_.chainmail_blocks / gpu_share_);
  shape_.relax_blocks = std::max(1, full_shape_.relax_blocks / gpu_share_);
  mg_blocks_ = std::max(1, full_mg_blocks_ / gpu_share_);
  // the elastic step keeps the whole device (el_blocks_) whatever the share: sessions step
  // in turn on every multiprocessor with one shared scratch (ElasticScratch::Turn), which
  // gives each more steps than 1/share of the device side by side (a step is a chain of
  // grid barriers whose cost hardly shrinks with fewer blocks) and no scratch of its own
}

bool CudaDeformBackend::copy_brick_to_device_impl(std::unique_ptr<DeviceBytes>& dst) const {
  // d_.j holds J on the VOI since invert() (upload() only copied it to the host). The
  // destination is sized for the largest VOI, so a session allocates it once.
  const std::size_t bytes = std::size_t(voi_.count()) * sizeof(float);
  if (!dst || dst->size() < bytes)
    dst = std::make_unique<CudaDeviceBytes>(std::max(bytes, std::size_t(capacity_) * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMemcpyAsync(dst->data(), d_.j, bytes, cudaMemcpyDeviceToDevice, stream_));
  // Called on the deformation worker thread; the render thread later reads dst on its
  // own stream. Waiting here makes the copy complete (and visible to every stream of
  // the device) before the worker hands dst over, so no cross-stream event is needed.
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
  return true;
}

std::vector<Vec3f> CudaDeformBackend::displacement_impl() const {
  const std::size_t n = std::size_t(voi_.count());
  std::vector<float> c[3];
  for (int a = 0; a < 3; ++a) {
    c[a].resize(n);
    PALPSIM_CUDA_CHECK(cudaMemcpyAsync(c[a].data(), d_.u[cur_][a], n * sizeof(float), cudaMemcpyDeviceToHost, stream_));
  }
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
  std::vector<Vec3f> u(n);
  for (std::size_t e = 0; e < n; ++e) u[e] = Vec3f{c[0][e], c[1][e], c[2][e]};
  return u;
}

void CudaDeformBackend::set_displacement_impl(const std::vector<Vec3f>& u) {
  field_extra_ = -1;  // any field
  const std::size_t n = u.size();
  std::vector<float> c[3];
  for (int a = 0; a < 3; ++a) {
    c[a].resize(n);
    for (std::size_t e = 0; e < n; ++e) c[a][e] = u[e][a];
    PALPSIM_CUDA_CHECK(cudaMemcpyAsync(d_.u[cur_][a], c[a].data(), n * sizeof(float), cudaMemcpyHostToDevice, stream_));
  }
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
}

}  // namespace palpsim::cuda
