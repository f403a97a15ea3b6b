// The deformation backend: ChainMail, relaxation, inversion and reset of one
// session's volume of interest, with a CPU reference ("cpu", server/deform/) and a
// CUDA implementation ("cuda", cuda/), chosen by name at run time. The public
// methods are non-virtual: they validate and keep the call order, then call the
// virtual *_impl of the backend (tiny-cuda-nn's object.h pattern).
#pragma once

#include <exception>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/backend_registry.h"
#include "core/device_bytes.h"
#include "core/patient.h"
#include "core/scene.h"
#include "core/vec3.h"
#include "deform/deform_math.h"
#include "deform/held_blocks.h"
#include "deform/relax_elastic.h"

namespace palpsim {

namespace deform {
struct MultigridCache;  // relax_multigrid.h
}

using deform::Voi;

/// What one deformation step needs from the haptic path (the paper's X and x);
/// the fields match haptics' Contact so the server copies them over.
struct DeformContact {
  Vec3 skin_point_mm{0, 0, 0};  // X: undeformed position of the first moved element (mm, LPS)
  Vec3 tip_mm{0, 0, 0};         // x: its deformed position, the device tip (mm, LPS)
};

/// Deformation settings of a scene plus what they depend on outside Deform{}.
struct DeformConfig {
  DeformSettings settings;     // ChainMail restrictions, VOI, sweep cap, relaxation, inversion
  double bone_threshold = 200; // the material function's step, in Patient::intensity units (HU)
  bool relax = true;           // run the relaxation stage (scene effect "relaxation")
  bool invert = true;          // produce the deformed image J (scene effect "inversion")
  /// Multigrid relaxation reuses its unit response while the VOI and the grabbed element
  /// stay (exact: relax_multigrid.h), and starts a new one from it (deform.relax_warm_cycles);
  /// false solves every step from zero with relax_cycles steps (benchmarks time both).
  bool relax_reuse = true;
  /// Multigrid steps leave ChainMail out where its field cannot change their result: the
  /// VOI holds no element that relaxation would hold and ChainMail could move
  /// (deform::HeldBlocks), so the steady state is u = d G whatever ChainMail did (exact:
  /// relax_multigrid.h). false runs ChainMail every step (tests compare both).
  bool skip_chainmail = true;
  /// Multigrid steps that reuse their unit response keep their VOI while the tip voxel
  /// stays within deform.voi_edge / 8 voxels (along each axis) of the one it was placed
  /// around and it holds the grabbed voxel, so that a press reuses G over several voxels of
  /// tip motion instead of solving at each. G then moves when the VOI re-centres, by 2.5%
  /// RMS and at most 1.1e-3 of the grabbed displacement (VOI 64 moved 8 voxels; measured,
  /// server/deform/README.md), where today's rule moves it 0.5% at every voxel. false: the
  /// VOI follows the tip every step (the paper's rule; the warm-start tests and benches).
  bool voi_hold = true;
  /// The elastic model also solves the unit press for the contact's stiffness each step
  /// (ElasticRun::stiffness_n_per_mm), which haptics.force_model "elastic" renders and from
  /// which the next step's start is predicted (deform::ElasticPredict::kUnit).
  bool elastic_stiffness = false;
  /// The deformation worker hands each elastic step's local force model to the haptic
  /// thread (haptics.force_model "elastic").
  bool elastic_force = false;
  /// An elastic step whose press moved along n alone, leaving the contact set as it was,
  /// superposes the unit press on the last press instead of solving
  /// (deform::elastic_superposes); false: every step solves (the tests and benches that
  /// compare the two).
  bool elastic_superpose = true;

  /// The elastic model's settings as its solvers take them (deform.elastic,
  /// deform.grab_radius_mm; the stiffness as elastic_stiffness says).
  deform::ElasticParams elastic_params() const;

  /// Whether DeformBackend::prime() can solve anything ahead of a contact: relaxation by
  /// multigrid with reuse and warm starts (relax_cycles and relax_warm_cycles above 0).
  bool primes() const;

  /// The configuration a scene asks for: Deform{}, prep's bone threshold and the effects.
  /// The scene's settings; the material function's bone threshold is the scene's
  /// prep.bone_threshold where the scene sets one, else the one prep chose for `patient`
  /// (Patient::bone_threshold_hu), so that relaxation steps at the bone mask's own edge.
  static DeformConfig from_scene(const Scene& scene, const Patient* patient = nullptr);
};

/// The settings that sessions stepped together in one batch must share: the batched
/// kernels take them once for all (cuda/, CudaDeformBackend::begin_batch_impl). Built by
/// deform_batch_key() alone; operator== names every member, so that a member added here
/// fails to compile until it is compared.
struct DeformBatchKey {
  bool relax = false;
  bool invert = false;
  double bone_threshold = 0;     // HU
  RelaxMethod relax_method = RelaxMethod::kExplicit;
  int max_sweeps = 0;
  int relax_iterations = 0;
  double relax_step = 0;
  double material_width = 0;     // HU
  int invert_iterations = 0;
  bool invert_search = false;
  float axial_lo = 0, axial_hi = 0, sheer = 0;  // ChainMail's limits (voxel; deform::chainmail_limits)
  // multigrid's (0 and false with the other methods)
  int relax_cycles = 0;
  int relax_warm_cycles = 0;
  bool relax_reuse = false;
  bool skip_chainmail = false;

  /// True when every member is equal.
  bool operator==(const DeformBatchKey& o) const;
  /// Not operator==.
  bool operator!=(const DeformBatchKey& o) const { return !(*this == o); }
};

/// The batch key of a configuration, or nothing where its steps cannot share launches:
/// the elastic model (one cooperative solve a session) and untangling (no batched kernel).
/// Lists every DeformConfig and DeformSettings member, so that a new one fails to compile
/// until it is put in the key or said to be the session's own.
std::optional<DeformBatchKey> deform_batch_key(const DeformConfig& config);

/// Whether sessions configured by `a` and `b` can be stepped in one batch (equal keys).
bool deform_batchable(const DeformConfig& a, const DeformConfig& b);

/// What ChainMail did in one step.
struct ChainMailStats {
  Voi voi;                   // the box it worked in (patient voxel indices)
  Vec3i grabbed_vox{0, 0, 0};// the first moved element (patient voxel index nearest X)
  Vec3 skin_vox{0, 0, 0};    // X as a continuous patient voxel index
  Vec3 tip_vox{0, 0, 0};     // x as a continuous patient voxel index
  Vec3f grabbed_u_vox;       // its displacement (voxel): x - grabbed voxel
  bool grabbed_in_bone = false;  // X lies in bone: nothing moves
  int sweeps = 0;            // Jacobi sweeps run, the last one quiet when converged
  long long moved = 0;       // elements that moved, the first element not counted
  bool converged = true;     // a quiet sweep came within deform.max_sweeps
  /// Not run: a multigrid step whose result does not depend on ChainMail's field
  /// (DeformConfig::skip_chainmail), or an elastic one (its solve sets every element);
  /// the grabbed element alone is at x.
  bool skipped = false;
};

/// Wall time of each stage of one step (ms). upload: making J's VOI readable on the
/// host; reset: returning the previous step's state to undeformed. A step of a batch
/// (DeformBackend::begin_steps) gets the batch's times divided by its sessions: its
/// share, so that the times of a server's steps add up to the GPU's.
struct DeformTimes {
  double reset_ms = 0;
  double chainmail_ms = 0;
  double relax_ms = 0;
  double untangle_ms = 0;  // 0 without untangling
  double invert_ms = 0;
  double upload_ms = 0;
  double total_ms = 0;
};

/// What the inversion left: its worst residual and how many voxels it did not resolve.
struct InvertStats {
  double max_residual_vox = 0;  // max |p + u(p) - y| over the VOI (voxel)
  long long unresolved = 0;     // VOI voxels with a residual above deform::kInvertResolvedVox
  double max_change = 0;        // max |J - I| over the VOI's finite J (Patient::intensity units, HU)
  long long nonfinite = 0;      // VOI voxels whose J is NaN or Inf (a broken step)
  long long searched = 0;       // voxels Newton left above deform::kInvertSearchVox, taken to the cell search (deform.invert_search)
  long long scattered = 0;      // of those, decided on the search's pass 0 without walking all rings (invert_scatter.h)
};

/// What untangling did: the folded cells (cell_min_det() <= deform::kUntangleFoldDet,
/// eight soft corners) before and after, and its work.
struct UntangleStats {
  long long folded_before = 0;  // folded cells of the relaxed field
  long long folded_after = 0;   // folded cells left (0: det(I + grad u) > kUntangleFoldDet in every cell)
  int rounds = 0;               // rounds of sweeps run (0: nothing was folded)
  int sweeps = 0;               // Jacobi sweeps over all rounds, each round's quiet one included
  long long moved = 0;          // elements it moved
  bool reverted = false;        // it ended with more folds than it found and restored the relaxed field
};

/// Memory a backend holds for its session (host and device bytes), by the stage that
/// needs it, so the server can show that a stage the scene did not ask for costs nothing.
struct DeformMemory {
  std::size_t chainmail_bytes = 0;  // displacement field and sweep bookkeeping
  std::size_t relax_bytes = 0;      // relaxation's and untangling's own buffers (cuda explicit relaxation: none, it reuses ChainMail's two fields)
  std::size_t invert_bytes = 0;     // J on the VOI (cuda: also its pinned host copy)
  /// The patient's device copy (cuda: I and the bone mask), shared by every session on
  /// that patient: not the session's own, so not in total(); a server counts it once.
  std::size_t shared_patient_bytes = 0;
  /// Solver scratch shared by the sessions whose solves run one after another (cuda
  /// multigrid: residuals, directions, coarse levels): not in total(); a server counts it once.
  std::size_t shared_scratch_bytes = 0;
  /// The session's own memory.
  std::size_t total() const { return chainmail_bytes + relax_bytes + invert_bytes; }
};

/// What one whole step did and cost.
struct DeformStats {
  ChainMailStats chainmail;
  int relax_iterations = 0;          // explicit steps run; 0 when relaxation is off or multigrid
  int relax_cycles = 0;              // multigrid V-cycles run; 0 when relaxation is off or explicit
  /// Scalar multigrid solves run (relax_multigrid.h): 1 for a fresh unit response, 0 when
  /// the kept one was reused, 3 when a held element other than the grabbed one had moved.
  int relax_solves = 0;
  /// The multigrid solve started from the last step's unit response (the tip entered a
  /// neighbouring voxel) and ran deform.relax_warm_cycles steps (relax_cycles says so).
  bool relax_warm = false;
  double invert_residual_vox = 0;    // max |p + u(p) - y| over the VOI (voxel); 0 without inversion
  long long invert_unresolved = 0;   // VOI voxels with a residual above deform::kInvertResolvedVox
  long long invert_searched = 0;     // VOI voxels Newton left to the cell search (0 without deform.invert_search)
  double invert_max_change = 0;      // max |J - I| over the VOI (HU); 0 without inversion
  long long invert_nonfinite = 0;    // VOI voxels whose J is NaN or Inf; 0 without inversion
  UntangleStats untangle;            // all 0 when untangling is off
  deform::ElasticRun elastic;        // the elastic model's solve, contact and force (relax_method "elastic"; all 0 otherwise)
  DeformTimes times;
  int batch = 1;                     // sessions stepped by the same launches (DeformBackend::begin_steps); 1: alone

  /// Takes the inversion's figures into the step's (every backend's step, batched or not).
  void take_inversion(const InvertStats& inv) {
    invert_residual_vox = inv.max_residual_vox;
    invert_unresolved = inv.unresolved;
    invert_searched = inv.searched;
    invert_max_change = inv.max_change;
    invert_nonfinite = inv.nonfinite;
  }
};

/// What DeformBackend::prime() did.
struct DeformPrime {
  bool solved = false;        // a unit response was solved (false: nothing to prime, or held already)
  bool warm = false;          // it started from the last G (cuda: the host offered it, and the device takes it
                              // unless that field is no G; the host knows after a step's three solves only)
  int steps = 0;              // CG steps it ran: deform.relax_cycles from zero, the warm steps otherwise
  Voi voi;                    // the VOI it was solved on (patient voxel indices)
  Vec3i grabbed_vox{0, 0, 0}; // and the grabbed element (patient voxel index)
};

/// One session's deformation state on one backend. bind() once, then step() per
/// contact (or the stages one by one, as the tests do). Not thread-safe: one worker
/// thread owns it.
class DeformBackend {
 public:
  virtual ~DeformBackend() = default;
  DeformBackend(const DeformBackend&) = delete;
  DeformBackend& operator=(const DeformBackend&) = delete;

  /// "cpu" or "cuda".
  const std::string& name() const { return name_; }

  /// Validates the patient and configuration and allocates the state; refuses a
  /// relax_step above the explicit scheme's stable limit (1/6) with the limit in the message.
  void bind(PatientPtr patient, const DeformConfig& config);

  /// Returns the previous step's state to undeformed, then runs ChainMail from the
  /// contact: the element nearest X goes to x and the others follow.
  ChainMailStats chainmail(const DeformContact& contact);
  /// Relaxes the displacement field: deform.relax_iterations explicit steps, or
  /// deform.relax_cycles multigrid V-cycles towards their steady state (deform.relax_method).
  void relax();
  /// Untangles the folds of the displacement field (deform_math.h, untangle_pull): the
  /// corners of folded cells, and the elements behind them that it moves, keep a spacing
  /// beyond their neighbour towards the grabbed element; bone and the grabbed element stay.
  UntangleStats untangle();
  /// Computes the deformed image J on the VOI; returns the inversion's residuals.
  InvertStats invert();
  /// Makes J's VOI readable through deformed_brick() (a device-to-host copy on "cuda").
  void upload();
  /// Returns displacements to zero and J to I: the undeformed state.
  void reset();

  /// All stages in order, timed: reset, ChainMail, relax, untangle (deform.untangle, with
  /// relaxation) and invert as configured, upload.
  DeformStats step(const DeformContact& contact);
  /// step() in two halves, so that one thread can overlap the steps of several sessions
  /// on one GPU: begin_step() enqueues the stages without waiting where the backend can
  /// (cuda: on the session's own stream; cpu: runs the whole step), end_step() waits and
  /// returns what step() would. Nothing else may be called on the backend in between.
  void begin_step(const DeformContact& contact);
  DeformStats end_step();
  /// begin_step() of several sessions at once, batched where their backend can: cuda
  /// steps them all with one launch per stage (cuda/batch.cu says why) when they share
  /// the settings; otherwise, and on cpu, each begins alone. Each backend's end_step()
  /// then returns what its own step() would, to the bit. A backend whose contact is
  /// refused, or whose step could not be begun, is not in a step: its error is at its
  /// index in the result (nullptr: begun), and the others go on.
  static std::vector<std::exception_ptr> begin_steps(const std::vector<DeformBackend*>& backends,
                                                     const std::vector<DeformContact>& contacts);
  /// Solves, ahead of time, the multigrid relaxation's unit response G for a contact
  /// expected soon (the tip approaching the skin: X where it will touch, x there too), and
  /// keeps it as the last one, so that the contact's first step starts warm (one or two
  /// steps) or reuses it, instead of solving from zero (deform.relax_cycles steps).
  /// Nothing else changes: the deformation in place,
  /// J, the held VOI and the stage stay, so the server calls it between a session's steps
  /// while the tip is outside the body. Does nothing (solved false) unless the scene
  /// relaxes by multigrid with reuse and warm starts (DeformConfig::relax_reuse,
  /// deform.relax_warm_cycles > 0), or where X lies in bone or G is held already. On cuda
  /// the solve is enqueued on the session's stream and not waited for. Throws
  /// palpsim::Error as step() does for a non-finite contact or X outside the grid.
  DeformPrime prime(const DeformContact& expected);
  /// Waits until the work the backend has enqueued and not waited for is done (cuda: a
  /// prime's solve; cpu: nothing is ever left), for benches that time a step apart from
  /// the prime before it.
  void wait() { wait_impl(); }
  /// Whether the backend holds a multigrid unit response, the one the next warm start or
  /// prime begins from, and if so the grabbed element it was solved for (patient voxel),
  /// into `grabbed_vox`: how far a new guess of the contact is from it.
  bool unit_response(Vec3i& grabbed_vox) const;

  /// Lets each persistent kernel of this backend take 1/k of the device's co-resident
  /// blocks (cuda; cpu ignores it), so that k sessions' steps fit on the GPU side by
  /// side: a cooperative launch needs all its blocks resident, and k grids of 1/k always
  /// fit together. 1 (the default): every kernel may fill the device.
  void set_gpu_share(int k);

  /// The VOI of the latest ChainMail (empty before the first one).
  const Voi& voi() const { return voi_; }
  /// The VOI's displacement field (voxel, along the grid axes), local index i fastest.
  std::vector<Vec3f> displacement() const;
  /// Replaces the VOI's displacement field, e.g. to feed both backends the same input
  /// in tests; `u` holds voi().count() values.
  void set_displacement(const std::vector<Vec3f>& u);
  /// J on the VOI after upload() (voi().count() values, i fastest); J = I outside it.
  /// Valid until the next stage call.
  const float* deformed_brick() const;
  /// Writes the whole deformed image: `out` = I, with the uploaded VOI brick of J.
  void compose_deformed(Volume<float>& out) const;
  /// Copies J of the VOI, as uploaded, into device memory for the renderer (CUDA-GL
  /// interop): `dst` is (re)allocated when missing or too small and holds voi().count()
  /// floats afterwards, the copy finished. False, touching nothing, for a backend that
  /// keeps no J on a GPU (cpu) or before upload().
  bool copy_brick_to_device(std::unique_ptr<DeviceBytes>& dst) const;

  /// The memory the state holds now, by stage (0 before bind()).
  DeformMemory memory() const { return bound_ ? memory_impl() : DeformMemory{}; }

  /// The bound patient and configuration.
  const Patient& patient() const { return *patient_; }
  const DeformConfig& config() const { return config_; }

 protected:
  explicit DeformBackend(std::string name) : name_(std::move(name)) {}

  // the backend's work; arguments are validated and the call order is kept
  virtual void bind_impl() = 0;
  virtual void chainmail_impl(ChainMailStats& stats) = 0;  // stats has voi and grabbed set
  virtual void relax_impl() = 0;
  virtual UntangleStats untangle_impl() = 0;
  virtual InvertStats invert_impl() = 0;
  virtual void upload_impl() = 0;
  virtual void reset_impl() = 0;
  // reset(): also forgets what warm starts keep from step to step (the elastic field), so
  // that the next press starts from rest
  virtual void forget_impl() {}
  virtual DeformStats step_impl(const ChainMailStats& setup) = 0;  // resets first
  // the halves of step_impl; by default the whole step runs in the first
  virtual void begin_step_impl(const ChainMailStats& setup) { pending_ = step_impl(setup); }
  virtual DeformStats end_step_impl() { return pending_; }
  // begins the steps of `group` (this one first; each has voi_ and setup_ set) with
  // batched launches and returns true, or returns false having begun nothing
  virtual bool begin_batch_impl(const std::vector<DeformBackend*>& /*group*/) { return false; }
  // solves G for `expected` (voi and grabbed element set; not in bone) and keeps it; the
  // state of the deformation untouched
  virtual DeformPrime prime_impl(const ChainMailStats& expected) = 0;
  virtual void wait_impl() {}
  // what the backend's kept unit response was solved for (null: no multigrid state)
  virtual const deform::MultigridCache* multigrid_cache_impl() const { return nullptr; }
  virtual std::vector<Vec3f> displacement_impl() const = 0;
  virtual void set_displacement_impl(const std::vector<Vec3f>& u) = 0;
  virtual const float* deformed_brick_impl() const = 0;
  virtual bool copy_brick_to_device_impl(std::unique_ptr<DeviceBytes>&) const { return false; }
  virtual DeformMemory memory_impl() const = 0;

  /// Writes the relaxation's counts (iterations or cycles, by deform.relax_method) into `out`.
  void set_relax_counts(DeformStats& out) const;
  /// Writes a multigrid relaxation's solves and start into `out` (after set_relax_counts):
  /// a warm start ran `warm_steps` (deform.relax_warm_cycles, one more after a far move).
  void set_multigrid_counts(DeformStats& out, int solves, bool warm, int warm_steps) const;

  /// Largest VOI the state holds (voxels): deform.voi_edge^3, or the whole volume.
  long long max_voi_count() const;

  PatientPtr patient_;
  DeformConfig config_;
  Voi voi_;                   // VOI of the latest ChainMail
  ChainMailStats setup_;      // grabbed element and VOI of the latest ChainMail
  deform::ChainMailLimits limits_;
  /// Where the patient may hold elements outside bone (multigrid scenes with
  /// DeformConfig::skip_chainmail; null otherwise): steps whose VOI has none skip ChainMail.
  std::shared_ptr<const deform::HeldBlocks> held_blocks_;
  float finger_r2_ = 0;       // finger_r2() of the bound settings and patient (voxel^2)
  bool voi_hold_ = false;     // DeformConfig::voi_hold applies (multigrid relaxation that reuses, elastic)
  int voi_margin_ = 0;        // compute_voi's margin around the grabbed voxel (voxel; the elastic model's)
  Voi hold_voi_;              // the VOI held since bind() or reset() (empty: none) ...
  Vec3i hold_tip_{0, 0, 0};   // ... and the tip voxel it was placed around
  int gpu_share_ = 1;         // set_gpu_share(): the 1/k of the device each persistent kernel may take
  DeformStats pending_;       // the default begin_step_impl()'s result, returned by end_step_impl()

 private:
  ChainMailStats setup_step(const DeformContact& contact);
  // the grabbed element, its displacement and the VOI of a contact (no VOI hold, no skip);
  // the tip voxel into *tip_vox when given
  ChainMailStats locate(const DeformContact& contact, Vec3i* tip_vox = nullptr) const;
  void require(bool ok, const char* what) const;

  std::string name_;
  bool bound_ = false;
  bool in_step_ = false;      // between begin_step() and end_step()
  int stage_ = 0;             // 0 undeformed, 1 chainmail, 2 relaxed, 3 inverted, 4 uploaded
};

/// The VOI of a step: a cube of edge `edge` centred on the tip voxel, shifted the
/// least so that it holds the grabbed voxel at least `margin` voxels (at most (edge - 1) /
/// 2) from its faces, then clipped at the volume border; the whole grid when `whole`. Both
/// backends use it; the elastic model asks for deform::kElasticVoiMarginVox.
Voi compute_voi(const Vec3i& grid_size, const Vec3i& grabbed, const Vec3i& tip, int edge, bool whole, int margin = 0);

/// The fingertip's radius squared in voxels^2 on grid `g` (deform.grab_radius_mm over the
/// smallest voxel edge; 0: the grabbed element alone), as the multigrid solvers test it.
float finger_r2(const DeformSettings& s, const Grid& g);

/// Checks deformation settings that every backend needs (ranges, the relaxation step's
/// stable limit) without a patient or a device, so a scene can be refused before it is
/// served; throws palpsim::Error starting with `who` and naming the scene field.
void check_deform_config(const DeformConfig& config, const std::string& who);

/// Checks the elastic model's settings (deform.elastic): a table of 1 to kElasticMaxTable
/// points sorted by hu with moduli above 0, a skin modulus above 0, Poisson's ratio in
/// (0, 0.5); throws palpsim::Error starting with `who` and naming the field.
void check_elastic_settings(const ElasticSettings& elastic, const std::string& who);

/// The deformation backends outside server/deform, by the deform.backend value that asks
/// for them: cuda/ registers "cuda" (register_linked_backends(), core/linked_backends.h).
using DeformBackendRegistry = BackendRegistry<DeformBackend, DeformBackendChoice>;

/// The one registry make_deform_backend() and cuda_deform_available() look "cuda" up in.
DeformBackendRegistry& deform_backends();

/// Makes the backend a scene's deform.backend asks for: cpu, cuda, or auto (cuda where a
/// device and a CUDA build exist, else cpu). An unavailable cuda throws palpsim::Error
/// saying why; `note`, when given, says what was chosen and why.
std::unique_ptr<DeformBackend> make_deform_backend(DeformBackendChoice choice, std::string* note = nullptr);

/// The deform.backend a name spells ("auto", "cpu" or "cuda", core/setting_names.h), for
/// benchmarks and tests that take a backend from the command line; an unknown name
/// throws palpsim::Error listing the allowed ones.
DeformBackendChoice deform_backend_choice(const std::string& name);

/// make_deform_backend() by the setting's name (deform_backend_choice()).
std::unique_ptr<DeformBackend> make_deform_backend(const std::string& name, std::string* note = nullptr);

/// True when a "cuda" backend is registered (a CUDA build) and a CUDA device can be
/// used; otherwise `why` says what is missing.
bool cuda_deform_available(std::string* why = nullptr);

}  // namespace palpsim
