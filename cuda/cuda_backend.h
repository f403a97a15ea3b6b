// The "cuda" deformation backend: the state of one session on the GPU and the
// stages around the kernels of chainmail.cu, relax.cu and invert.cu.
#pragma once

#include <cuda_runtime.h>

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>

#include "core/device_bytes.h"
#include "cuda/batch.h"
#include "cuda/device_patient.h"
#include "cuda/kernels.h"
#include "cuda/relax_elastic.h"
#include "cuda/shared_scratch.h"
#include "deform/backend.h"

namespace palpsim::cuda {

/// A block of device memory from cudaMalloc (on the calling thread's current device),
/// freed by cudaFree in the destructor; the DeviceBytes the cuda backend hands J over in.
class CudaDeviceBytes final : public DeviceBytes {
 public:
  /// Allocates `bytes` bytes; throws palpsim::Error naming cudaMalloc when it fails.
  explicit CudaDeviceBytes(std::size_t bytes);
  ~CudaDeviceBytes() override;
  CudaDeviceBytes(const CudaDeviceBytes&) = delete;
  CudaDeviceBytes& operator=(const CudaDeviceBytes&) = delete;

  void* data() override { return ptr_; }
  const void* data() const override { return ptr_; }
  std::size_t size() const override { return size_; }

 private:
  void* ptr_ = nullptr;
  std::size_t size_ = 0;
};

/// The multigrid solver's scratch for VOIs of up to `capacity` elements and coarse levels
/// of up to `coarse_capacity` nodes: level 0's residuals, directions, correction and held
/// mask, the coarse levels, the dot sums. Nothing in it outlives a launch (the held mask
/// and the sums are made anew by each), so sessions whose solves run one after another may
/// share one (their launches take turns: Turn); what a session keeps (its unit responses,
/// flags) stays in its own buffers.
struct MultigridScratch {
  /// Held around a launch that uses the scratch (ScratchTurn).
  using Turn = ScratchTurn<MultigridScratch>;

  MultigridScratch(long long capacity, long long coarse_capacity);
  ~MultigridScratch();
  MultigridScratch(const MultigridScratch&) = delete;
  MultigridScratch& operator=(const MultigridScratch&) = delete;
  /// The scratch shared on the current device for these capacities: the one alive, or a new one.
  static std::shared_ptr<MultigridScratch> shared(long long capacity, long long coarse_capacity);
  /// Points `m`'s scratch fields at this scratch.
  void lend_to(MultigridBuffers& m) const;
  /// Device bytes held.
  std::size_t bytes() const;

  long long capacity, coarse_capacity;
  int device = 0;
  float *r[2] = {nullptr, nullptr}, *z = nullptr, *p[2] = {nullptr, nullptr}, *q = nullptr, *res = nullptr;
  float *cx = nullptr, *cf = nullptr, *cres = nullptr;
  std::uint8_t *held = nullptr, *cheld = nullptr;
  double* dots = nullptr;
  cudaEvent_t done = nullptr;  // recorded after the last launch that used the scratch
  std::mutex mu;               // one Turn at a time
};

/// The CUDA backend. The patient's intensity and bone mask live on the device once
/// for all sessions bound to that patient (DevicePatient); displacement, sweep stamps and J are VOI-sized device buffers. A
/// step is one stream of device work with one synchronisation at its end; the steps of
/// several sessions with the same settings may share one launch per stage instead
/// (DeformBackend::begin_steps, batch.cu).
class CudaDeformBackend final : public DeformBackend {
 public:
  CudaDeformBackend();
  ~CudaDeformBackend() override;

 protected:
  void bind_impl() override;
  DeformPrime prime_impl(const ChainMailStats& expected) override;
  const deform::MultigridCache* multigrid_cache_impl() const override { return &mg_.cache; }
  void wait_impl() override;
  void chainmail_impl(ChainMailStats& stats) override;
  void relax_impl() override;
  UntangleStats untangle_impl() override;
  InvertStats invert_impl() override;
  void upload_impl() override;
  void reset_impl() override;
  void forget_impl() override;
  DeformStats step_impl(const ChainMailStats& setup) override;
  void begin_step_impl(const ChainMailStats& setup) override;
  DeformStats end_step_impl() override;
  bool begin_batch_impl(const std::vector<DeformBackend*>& group) override;
  std::vector<Vec3f> displacement_impl() const override;
  void set_displacement_impl(const std::vector<Vec3f>& u) override;
  const float* deformed_brick_impl() const override;
  bool copy_brick_to_device_impl(std::unique_ptr<DeviceBytes>& dst) const override;
  DeformMemory memory_impl() const override;

 private:
  void release();
  // the launch shapes of this step from the device's and set_gpu_share()
  void launch_shape_for_share();
  // allocates the multigrid relaxation's buffers once (deform.relax_method "multigrid")
  void ensure_multigrid_buffers();
  // allocates the explicit relaxation's weights once (deform.relax_method "explicit")
  void ensure_relax_buffers();
  // allocates untangling's buffers once (deform.untangle, or a call of untangle())
  void ensure_untangle_buffers();
  // allocates the elastic model's buffers and the patient's body copy once (deform.relax_method "elastic")
  void ensure_elastic_buffers();
  StepGeometry geometry() const;
  // enqueue one stage on the stream
  void enqueue_reset();
  void enqueue_chainmail();
  void enqueue_relax();
  // the elastic solve of this step into displacement buffer `buffer`, on `stream` (its own
  // step's or a batch's), in batch lane `lane` of `lanes` (relax_elastic_lanes())
  void enqueue_elastic(int buffer, cudaStream_t stream, int lane = 0, int lanes = 1);
  void enqueue_untangle();
  void enqueue_invert();
  void enqueue_upload();
  // wait for the stream and read the counters
  void finish(ChainMailStats* stats, InvertStats* inv, UntangleStats* unt = nullptr);
  // read the counters the device wrote into host_counters_
  void read_counters(ChainMailStats* stats, InvertStats* inv, UntangleStats* unt);
  // begin_step_impl()'s part of the stats, before any stage
  void prepare_stats(const ChainMailStats& setup);
  // end_step_impl() of a step begun in a batch
  DeformStats end_batched_step();

  std::shared_ptr<const DevicePatient> patient_copy_;  // I and the bone mask, shared
  DeviceBuffers d_;
  MultigridBuffers mg_;                // empty unless the scene relaxes by multigrid
  /// The multigrid solver's scratch: shared by the device's sessions of this VOI size
  /// (their solves run one after another: alone, or in turn within a batch), or this
  /// session's own while steps run side by side (set_gpu_share() above 1)
  std::shared_ptr<MultigridScratch> mg_shared_, mg_own_;
  MultigridScratch& own_multigrid_scratch();  // mg_own_, made on first use
  // the scratch a solve of this session's own takes: the shared one, or with other steps in
  // flight beside it (set_gpu_share() above 1) its own
  MultigridScratch& step_multigrid_scratch() { return gpu_share_ > 1 ? own_multigrid_scratch() : *mg_shared_; }
  // this step's multigrid solver (or reuse) from displacement buffer `src`, on `scratch`
  // in its turn, `blocks` cooperative blocks on `stream`
  void launch_multigrid(int src, MultigridScratch& scratch, int blocks, cudaStream_t stream);
  // the multigrid solver for geometry `g` on `scratch` in its turn (launch_relax_multigrid;
  // `prime`: G alone); returns whether it starts from the kept field
  bool launch_multigrid_for(const StepGeometry& g, int src, MultigridScratch& scratch, int blocks, cudaStream_t stream,
                            bool prime);
  // a finished multigrid step's solves and start, from the counters read back, into `out`;
  // forgets the kept G where the step solved three components (none kept)
  void take_multigrid_counts(DeformStats& out);
  /// The elastic model (relax_elastic.cu): the session's solver, the patient's body mask
  /// and B on the device (shared with the other sessions on it), the solver's scratch
  /// (shared, or this session's own while steps run side by side, as the multigrid's)
  ElasticSolver elastic_;
  std::shared_ptr<const DeviceBody> body_copy_;
  std::shared_ptr<ElasticScratch> el_shared_;
  std::shared_ptr<ElasticScratch> el_lane_;  // the batch lane's scratch this session last solved in (lane 1 and up)
  int el_blocks_ = 0;                  // cooperative blocks of the elastic kernels: all that fit on the device
  bool mg_g_clean_ = false;  // the kept unit response was solved on a step that left ChainMail out (so it is a G)
  int mg_blocks_ = 0;                  // cooperative blocks of the multigrid kernel, this step
  int full_mg_blocks_ = 0;             // ... that fit on the device
  LaunchShape shape_;                  // persistent kernels' blocks, this step (launch_shape_for_share)
  LaunchShape full_shape_;             // ... that fit on the device
  DeformStats step_out_;               // begin_step_impl()'s part of the step's stats
  std::chrono::steady_clock::time_point step_start_;
  cudaStream_t stream_ = nullptr;
  cudaEvent_t ev_[7] = {};
  Counters* host_counters_ = nullptr;  // pinned
  float* host_j_ = nullptr;            // pinned, J's VOI after upload
  mutable bool host_j_stale_ = false;  // a batched step left J on the device only: deformed_brick() copies it
  long long capacity_ = 0;             // elements per VOI buffer
  Voi dirty_;                          // VOI whose buffers hold a deformation
  int cur_ = 0;                        // displacement buffer holding the current field
  int field_extra_ = 0;                // BatchItem::relax_extra of the current field (-1: unknown extent)
  std::shared_ptr<CudaBatch> batch_;     // the launches' resources when this backend leads a batch, kept for the next
  std::shared_ptr<CudaBatch> in_batch_;  // the batch this backend's step is in, until end_step()
};

}  // namespace palpsim::cuda
