// The "cuda" backend: device state, reset, stage calls and the timed step.
#include "cuda/cuda_backend.h"

#include <algorithm>
#include <chrono>
#include <cstring>

#include "cuda/check.h"

namespace palpsim::cuda {

namespace {

// the undeformed state on the first n elements of every buffer, and zero counters,
// in one launch: nine cudaMemsetAsync calls cost ~45 us at any VOI size (one launch
// each, DEVICE.md's 3.3 us floor plus their gaps), this costs one launch
__global__ void reset_kernel(unsigned n, DeviceBuffers b) {
  const unsigned t0 = blockIdx.x * blockDim.x + threadIdx.x, stride = gridDim.x * blockDim.x;
  for (unsigned e = t0; e < n; e += stride) {
    for (int p = 0; p < 2; ++p) {
      b.u[p][0][e] = 0.0f;
      b.u[p][1][e] = 0.0f;
      b.u[p][2][e] = 0.0f;
      b.stamp[p][e] = -1;
    }
  }
  if (t0 == 0) *b.counters = Counters{};
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

CudaDeformBackend::CudaDeformBackend() : DeformBackend("cuda") {}

CudaDeformBackend::~CudaDeformBackend() { release(); }

void CudaDeformBackend::release() {
  // errors are ignored here: a destructor must not throw
  cudaFree(const_cast<float*>(d_.intensity));
  cudaFree(const_cast<std::uint8_t*>(d_.bone));
  for (auto& buf : d_.u)
    for (float*& c : buf) cudaFree(c);
  for (int*& s : d_.stamp) cudaFree(s);
  cudaFree(d_.j);
  cudaFree(d_.cell_folded);
  cudaFree(d_.untangle_flags);
  for (float*& c : d_.untangle_new) cudaFree(c);
  cudaFree(d_.counters);
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
  // the patient, once per session
  float* intensity = nullptr;
  std::uint8_t* bone = nullptr;
  PALPSIM_CUDA_CHECK(cudaMalloc(&intensity, nvol * sizeof(float)));
  d_.intensity = intensity;
  PALPSIM_CUDA_CHECK(cudaMalloc(&bone, nvol));
  d_.bone = bone;
  PALPSIM_CUDA_CHECK(cudaMemcpy(intensity, p.intensity.data.data(), nvol * sizeof(float), cudaMemcpyHostToDevice));
  PALPSIM_CUDA_CHECK(cudaMemcpy(bone, p.bone.data.data(), nvol, cudaMemcpyHostToDevice));
  // VOI-sized state, undeformed
  for (auto& buf : d_.u)
    for (float*& c : buf) {
      PALPSIM_CUDA_CHECK(cudaMalloc(&c, n * sizeof(float)));
      PALPSIM_CUDA_CHECK(cudaMemset(c, 0, n * sizeof(float)));
    }
  for (int*& s : d_.stamp) {
    PALPSIM_CUDA_CHECK(cudaMalloc(&s, n * sizeof(int)));
    PALPSIM_CUDA_CHECK(cudaMemset(s, 0xff, n * sizeof(int)));  // -1: never moved
  }
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.j, n * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.cell_folded, n));
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.untangle_flags, n));
  for (float*& c : d_.untangle_new) PALPSIM_CUDA_CHECK(cudaMalloc(&c, n * sizeof(float)));
  PALPSIM_CUDA_CHECK(cudaMalloc(&d_.counters, sizeof(Counters)));
  PALPSIM_CUDA_CHECK(cudaMemset(d_.counters, 0, sizeof(Counters)));
  PALPSIM_CUDA_CHECK(cudaMallocHost(&host_counters_, sizeof(Counters)));
  PALPSIM_CUDA_CHECK(cudaMallocHost(&host_j_, n * sizeof(float)));
  std::memset(host_counters_, 0, sizeof(Counters));
  shape_ = persistent_launch_shape();
  dirty_ = Voi{};
  cur_ = 0;
}

DeformMemory CudaDeformBackend::memory_impl() const {
  // what bind_impl allocated: the patient copy, both displacement fields and both sweep
  // stamps serve ChainMail (relaxation ping-pongs between the same two fields); J and
  // its pinned host copy serve the inversion, but are allocated whatever the scene asks
  const std::size_t n = std::size_t(capacity_);
  const std::size_t nvol = patient_->grid.count();
  DeformMemory m;
  m.chainmail_bytes = nvol * (sizeof(float) + sizeof(std::uint8_t)) + sizeof(d_.u) / sizeof(float*) * n * sizeof(float) +
                      sizeof(d_.stamp) / sizeof(int*) * n * sizeof(int) + 2 * sizeof(Counters);
  m.relax_bytes = 2 * n + sizeof(d_.untangle_new) / sizeof(float*) * n * sizeof(float);  // untangling's flags and sweep buffer
  m.invert_bytes = 2 * n * sizeof(float);
  return m;
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
}

void CudaDeformBackend::enqueue_chainmail() {
  dirty_ = voi_;
  if (setup_.grabbed_in_bone) return;  // nothing moves
  launch_chainmail(geometry(), setup_.grabbed_u_vox, limits_, config_.settings.max_sweeps, d_, shape_, stream_);
  // converged: both buffers hold the result; capped: the last sweep's buffer does
  cur_ = config_.settings.max_sweeps & 1;
}

void CudaDeformBackend::enqueue_relax() {
  const DeformSettings& s = config_.settings;
  launch_relax(geometry(), cur_, s.relax_iterations, float(s.relax_step), float(config_.bone_threshold),
               float(s.material_width), d_, shape_, stream_);
  cur_ = (cur_ + s.relax_iterations) & 1;
}

void CudaDeformBackend::enqueue_untangle() {
  if (!setup_.grabbed_in_bone) launch_untangle(geometry(), cur_, d_, shape_, stream_);
}

void CudaDeformBackend::enqueue_invert() {
  launch_invert(geometry(), cur_, config_.settings.invert_iterations, d_, stream_);
}

void CudaDeformBackend::enqueue_upload() {
  PALPSIM_CUDA_CHECK(cudaMemcpyAsync(host_j_, d_.j, std::size_t(voi_.count()) * sizeof(float),
                                     cudaMemcpyDeviceToHost, stream_));
}

void CudaDeformBackend::finish(ChainMailStats* stats, InvertStats* inv, UntangleStats* unt) {
  PALPSIM_CUDA_CHECK(cudaMemcpyAsync(host_counters_, d_.counters, sizeof(Counters), cudaMemcpyDeviceToHost, stream_));
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
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
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
}

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
  enqueue_invert();
  finish(nullptr, &r);
  return r;
}

void CudaDeformBackend::upload_impl() {
  enqueue_upload();
  PALPSIM_CUDA_CHECK(cudaStreamSynchronize(stream_));
}

DeformStats CudaDeformBackend::step_impl(const ChainMailStats& setup) {
  // every stage is enqueued on one stream with an event between stages; the host
  // waits once, at the end, then reads the stage times from the events
  const auto t0 = std::chrono::steady_clock::now();
  DeformStats out;
  out.chainmail = setup;
  out.chainmail.sweeps = 0;
  out.chainmail.moved = 0;
  out.chainmail.converged = true;
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[0], stream_));
  enqueue_reset();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[1], stream_));
  enqueue_chainmail();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[2], stream_));
  if (config_.relax) {
    enqueue_relax();
    out.relax_iterations = config_.settings.relax_iterations;
  }
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[3], stream_));
  const bool untangle = config_.relax && config_.settings.untangle;
  if (untangle) enqueue_untangle();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[4], stream_));
  if (config_.invert) enqueue_invert();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[5], stream_));
  if (config_.invert) enqueue_upload();
  PALPSIM_CUDA_CHECK(cudaEventRecord(ev_[6], stream_));
  InvertStats inv;
  finish(&out.chainmail, &inv, untangle ? &out.untangle : nullptr);
  if (config_.invert) {
    out.invert_residual_vox = inv.max_residual_vox;
    out.invert_unresolved = inv.unresolved;
  }
  // stage times from the events (ms)
  float ms[6];
  for (int s = 0; s < 6; ++s) PALPSIM_CUDA_CHECK(cudaEventElapsedTime(&ms[s], ev_[s], ev_[s + 1]));
  out.times.reset_ms = ms[0];
  out.times.chainmail_ms = ms[1];
  out.times.relax_ms = ms[2];
  out.times.untangle_ms = ms[3];
  out.times.invert_ms = ms[4];
  out.times.upload_ms = ms[5];
  out.times.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return out;
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
