// The elastic model (deform.relax_method = "elastic"), host side: the cell matrix, the
// settings the solvers take, what a solve reports, and the CPU reference solver. The
// per-node math both backends compile is in elastic_math.h, which says what is solved.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/patient.h"
#include "core/vec3.h"
#include "deform/deform_math.h"
#include "deform/elastic_math.h"

namespace palpsim::deform {

/// The elastic model's VOI holds the grabbed voxel (X's, on the skin under the finger) this
/// many voxels from its faces (compute_voi's margin): its faces are held at rest, and a
/// press deeper than half the VOI's edge, which centres on the tip, would otherwise hold
/// the skin layer under the finger on a face, pressing nothing. Two: the skin's node and
/// the one outside it are off the face.
constexpr int kElasticVoiMarginVox = 2;

/// The 24 x 24 stiffness of one box cell with edges `h_mm` (mm) for E = 1 kPa and
/// Poisson ratio `nu`, by selective reduced integration (mu part 2x2x2 Gauss points, lambda
/// part the centre), row-major, rows and columns 3 corner + component (elastic_corner()
/// order): N per mm of displacement. Computed in double, stored in float.
std::array<float, 576> elastic_element(const Vec3& h_mm, double nu);

/// elastic_element()'s corner-0 row block, base[9 d + 3 i + j] = k(i, 3 d + j): the 72
/// entries from which ElasticCellBase (elastic_math.h) reads every other, as the CUDA
/// kernels keep the matrix.
std::array<float, 72> elastic_element_base(const std::array<float, 576>& k);

/// The elastic model's settings as the solvers take them (from deform.elastic and
/// deform.grab_radius_mm; DeformConfig holds them as a scene gave them).
struct ElasticParams {
  ElasticMaterial material;
  double poisson = 0.45;
  float finger_radius_mm = 5;   // the fingertip sphere's radius
  int max_iterations = 60;      // CG steps per contact round at most
  float tolerance = 1e-3f;      // relative residual at which a round stops
  int contact_rounds = 4;       // contact set updates per step at most
  bool predict = true;          // predict a warm step's start from the last press (elastic_prediction)
  /// The unit press's own tolerance; 0: `tolerance`, and the force is the contact nodes'
  /// reactions summed. Above 0 the force and stiffness come from the unit press by
  /// reciprocity (elastic_math.h), accurate to the product of the two solves' errors.
  float stiffness_tolerance = 0.01f;
  ElasticDegrees degrees;       // the V-cycle's Chebyshev degrees
  bool stiffness = false;       // also solve the unit press for the contact's stiffness (haptics.force_model "elastic")
  bool superpose = true;        // a step whose press moved along n alone may superpose (elastic_superposes)

  /// The relative residual the unit press is solved to: stiffness_tolerance, or
  /// `tolerance` where that is 0.
  float unit_tolerance() const { return stiffness_tolerance > 0 ? stiffness_tolerance : tolerance; }
};

/// What one elastic step did and found.
struct ElasticRun {
  bool contact = false;          // the fingertip pressed the skin (depth above 0 and skin nodes under it)
  int contact_nodes = 0;         // skin nodes held on the sphere at the end
  int rounds = 0;                // contact rounds run
  bool contact_settled = true;   // the last round changed no node's contact (false: contact_rounds ran out)
  int iterations = 0;            // CG steps over all rounds (the unit press not counted)
  double residual = 0;           // the last round's relative residual
  bool converged = true;         // every round reached the tolerance within max_iterations
  bool warm = false;             // started from the last step's field
  Vec3 force_n{0, 0, 0};         // the tissue's force on the finger (N, along the grid axes)
  double stiffness_n_per_mm = 0; // d(force along -n) / d(tip depth along n), the contact set held (N/mm); 0 unless asked
  int stiffness_iterations = 0;  // CG steps of the unit press
  double depth_mm = 0;           // the tip's depth along n below the skin point X (mm)
  Vec3 normal{0, 0, 0};          // n: the press direction, unit, along the grid axes
  long long inverted_cells = 0;  // cells whose deformation folds (det(I + grad u) <= 0 somewhere in them)
  ElasticPredict prediction = ElasticPredict::kNone;  // how the warm start predicted this press (elastic_prediction)
  bool superposed = false;       // the last press plus the unit press times the tip's move along n: no solve (elastic_superposes)
};

/// What a superposed step adds to (elastic_superposes), which both backends' solvers keep
/// from step to step: whether the last step solved, converged and settled (or superposed on
/// such a one), the tip's moves along n superposed since (mm), and that step's push along n
/// (N), stiffness (N/mm) and relative residual.
struct ElasticSuperposeState {
  bool last_solved = false;
  double superposed_mm = 0;
  double last_push_n = 0, last_stiffness = 0, last_residual = 0;

  /// Whether a step predicted by `pred`, pressing `depth_mm` along an n at cosine `unit_cos`
  /// from the unit press's, may superpose with settings `prm` (the host's part of
  /// elastic_superposes; the step's start must also leave the contact set as it was).
  bool allows(const ElasticPrediction& pred, float unit_cos, double depth_mm, const ElasticParams& prm) const {
    return prm.superpose && prm.stiffness &&
           elastic_superposes(pred, unit_cos, last_solved, superposed_mm, depth_mm, prm.tolerance, prm.unit_tolerance());
  }
  /// The push along n (N) that a superposed step of prediction factor `factor` reaches.
  double superposed_push(float factor) const { return last_push_n + double(factor) * last_stiffness; }
  /// Keeps what the step just run (`run`, its prediction's factor `factor`) leaves the next.
  void after(const ElasticRun& run, float factor) {
    if (!run.contact) {
      last_solved = false;
      return;
    }
    last_push_n = -dot(run.force_n, run.normal);
    if (run.superposed) {
      superposed_mm += std::fabs(double(factor));
      return;
    }
    last_solved = run.converged && run.contact_settled && run.contact_nodes > 0;
    superposed_mm = 0;
    last_stiffness = run.stiffness_n_per_mm;
    last_residual = run.residual;
  }
};

/// The CPU elastic solver's buffers for one session, sized for the largest VOI (grown on
/// first use: a scene without the elastic model allocates none of them). Fields in mm.
struct ElasticCpu {
  // level 0: solution, the unit press, CG's vectors, flags and cell moduli, the rest
  // positions' pushes (mm along n; < 0: not under the sphere) of skin nodes
  std::vector<Vec3f> u, u_unit, r, z, p, q, ku;
  std::vector<std::uint8_t> flags;
  std::vector<float> cell_e;
  std::vector<float> push;
  // the last step's reactions (N along n) at its contact nodes, of the press and of the unit
  // press: a step predicted from the unit press leaves out the nodes they have pulled
  // (elastic_predicted_pull)
  std::vector<float> react_press, react_unit;
  // every level's inverse Jacobi diagonal (level 0 first, then the coarse ones at
  // plan.offset[l] + count0), and the coarse levels' flags, moduli, correction, right-hand
  // side and residual
  std::vector<Vec3f> inv_diag;
  std::vector<std::uint8_t> c_flags;
  std::vector<float> c_e;
  std::vector<Vec3f> c_x, c_f, c_r, res0;
  std::vector<Vec3f> cheb_d, c_d;       // the smoother's step, level 0 and the coarse levels
  float lmax[kElasticMaxLevels] = {};   // every level's largest eigenvalue of D^-1 K
  std::vector<Vec3f> tmp_u;             // the last field while the VOI moves
  std::vector<std::uint8_t> tmp_flags;  // the last flags while the VOI moves
  ElasticPlan plan;
  std::array<float, 576> k{};     // the cell matrix for E = 1 kPa at level 0
  Voi voi;                        // the VOI the moduli, static flags and diagonals are set for
  double poisson = -1;            // ... and the Poisson ratio and material (material_key) they were made with
  std::uint64_t material_key = 0;
  bool have_u = false;            // u holds the last step's field on `voi` (a warm start)
  bool have_unit = false;         // u_unit holds the unit press of the current contact set
  Vec3f unit_normal{0, 0, 0};     // ... along this n
  ElasticLastPress last_press;    // the last step's press, for the warm start's prediction
  ElasticSuperposeState superpose;  // what a superposed step adds to
  ElasticDegrees degrees;         // the V-cycle's Chebyshev degrees (the step's params)
};

/// A fingerprint of a material (its bytes): the set-up is redone when it changes.
std::uint64_t material_key(const ElasticMaterial& m);

/// Sets the buffers up for `voi`: the cell matrix (grid spacing and params.poisson), the
/// cell moduli, the static flags (held: bone and the VOI's faces; body; skin) and every
/// level's Jacobi diagonal; no contact, no field kept (u is not touched).
void elastic_set_up_cpu(const Patient& p, const Voi& voi, const ElasticParams& params, ElasticCpu& s);

/// What one conjugate-gradient solve did.
struct ElasticSolve {
  int iterations = 0;     // CG steps
  double residual = 0;    // |residual| over that of the constrained values alone (free parts at 0)
  bool converged = true;  // it reached the tolerance
};

/// Solves K u = 0 on the free components of `u` (on s.voi, mm) with the flags as they are:
/// held nodes keep their value in u, contact nodes their part along `n` (unit); the other
/// components start from u. Conjugate gradients preconditioned by the V-cycle, to
/// `tolerance` or `max_iterations` steps.
ElasticSolve elastic_solve_cpu(ElasticCpu& s, const Vec3f& n, Vec3f* u, int max_iterations, float tolerance);

/// y = Pi K x on level 0 (Pi: the flags' projection along `n`), the operator conjugate
/// gradients solve with; for tests (symmetry, definiteness).
void elastic_operator_cpu(ElasticCpu& s, const Vec3f& n, const Vec3f* x, Vec3f* y);
/// z = B r: one V-cycle from level 0, the preconditioner; for tests. Uses s.r and s.z.
void elastic_precondition_cpu(ElasticCpu& s, const Vec3f& n, const Vec3f* r, Vec3f* z);

/// (K u) at VOI-local node (i, j, k) (N): the force that holds it where u has it.
Vec3f elastic_node_force_cpu(const ElasticCpu& s, const Vec3f* u, int i, int j, int k);

/// The elastic step on the CPU: the fingertip (a sphere of radius params.finger_radius_mm
/// whose deepest point is the tip x, pressing along n from X to x) on the skin of the VOI
/// st.voi, bone and the VOI's faces held, solved from the last step's field. Writes the
/// displacement (voxel, along the grid axes) of the VOI's elements into `u_vox` (VOI-local,
/// i fastest) and returns what it did. `skin_vox`, `tip_vox`: X and x as continuous patient
/// voxel indices.
ElasticRun relax_elastic_cpu(const Patient& p, const Voi& voi, const Vec3& skin_vox, const Vec3& tip_vox,
                             const ElasticParams& params, ElasticCpu& s, Vec3f* u_vox);

/// Whether the tip x (a continuous patient voxel index) lies inside the skin: the body mask
/// C, trilinear, above 1/2 there (the skin is its 1/2 level, where the haptic path puts X).
/// A tip outside presses nothing, whatever the skin point.
bool elastic_tip_inside(const Patient& p, const Vec3& tip_vox);

/// The cells of a VOI's field `u_vox` (voxel, VOI-local, i fastest) whose deformation folds:
/// det(I + grad u) <= 0 at a corner or the centre (deform_math.h's cell_min_det), among the
/// cells with a moved corner (ElasticRun::inverted_cells).
long long elastic_inverted_cells(const Voi& voi, const Vec3f* u_vox);

/// The bytes an ElasticCpu holds (capacities).
std::size_t elastic_cpu_bytes(const ElasticCpu& s);

}  // namespace palpsim::deform
