// The validating wrapper of DeformBackend, the VOI rule and backend selection by name.
#include "deform/backend.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <tuple>
#include <sstream>

#include "core/error.h"
#include "core/setting_names.h"
#include "deform/cpu_backend.h"
#include "deform/relax_multigrid.h"


namespace palpsim {

namespace {

std::string fmt_vec(const Vec3& v) {
  std::ostringstream s;
  s << "(" << v.x << ", " << v.y << ", " << v.z << ")";
  return s.str();
}

bool finite(const Vec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

}  // namespace

DeformConfig DeformConfig::from_scene(const Scene& scene, const Patient* patient) {
  DeformConfig c;
  c.settings = scene.deform;
  c.bone_threshold = scene.prep.bone_threshold;
  if (!scene.prep.bone_threshold_set && patient && std::isfinite(patient->bone_threshold_hu))
    c.bone_threshold = patient->bone_threshold_hu;
  c.relax = scene.effects.relaxation;
  c.invert = scene.effects.inversion;
  c.elastic_force = scene.haptics.force_model == ForceModel::kElastic;
  // the unit press, for the force model, and whenever the elastic model predicts: a warm
  // start predicted from it needs fewer V-cycles than from the depths' ratio, which more
  // than pays for it (the phantom scene's server bench, the H100: 16 sessions at 95 steps/s
  // each with it, 50 without; bench/results/elastic-server-probes-2026-12-06-h100-d9e7903.txt)
  c.elastic_stiffness = c.elastic_force || (scene.deform.relax_method == RelaxMethod::kElastic &&
                                            scene.deform.elastic.predict);
  return c;
}

float finger_r2(const DeformSettings& s, const Grid& g) {
  const double h = std::min(g.spacing_mm.x, std::min(g.spacing_mm.y, g.spacing_mm.z));
  const double r = s.grab_radius_mm / h;
  return float(r * r);
}

Voi compute_voi(const Vec3i& grid_size, const Vec3i& grabbed, const Vec3i& tip, int edge, bool whole, int margin) {
  Voi v;
  if (whole) {
    v.size = grid_size;
    return v;
  }
  const int m = std::clamp(margin, 0, (edge - 1) / 2);
  for (int a = 0; a < 3; ++a) {
    // centre on the tip
    int lo = tip[a] - edge / 2;
    int hi = lo + edge - 1;
    // shift the least so that the grabbed voxel is inside, m voxels from the faces
    if (grabbed[a] - m < lo) {
      hi -= lo - (grabbed[a] - m);
      lo = grabbed[a] - m;
    } else if (grabbed[a] + m > hi) {
      lo += grabbed[a] + m - hi;
      hi = grabbed[a] + m;
    }
    // clip at the volume border
    lo = std::max(lo, 0);
    hi = std::min(hi, grid_size[a] - 1);
    v.lo[a] = lo;
    v.size[a] = hi - lo + 1;
  }
  return v;
}

void check_elastic_settings(const ElasticSettings& e, const std::string& who) {
  auto bad = [&](const std::string& field, double value, const std::string& rule) {
    std::ostringstream m;
    m << who << ": deform.elastic." << field << " = " << value << " " << rule;
    throw Error(m.str());
  };
  const int n = int(e.modulus.size());
  if (n == 0) throw Error(who + ": deform.elastic.modulus is empty; give at least one point { hu: ... e_kpa: ... }");
  if (n > deform::kElasticMaxTable) {
    std::ostringstream m;
    m << who << ": deform.elastic.modulus has " << n << " points; at most " << deform::kElasticMaxTable;
    throw Error(m.str());
  }
  for (int i = 0; i < n; ++i) {
    const std::string at = "modulus.point[" + std::to_string(i) + "]";
    if (!std::isfinite(e.modulus[i].hu)) bad(at + ".hu", e.modulus[i].hu, "must be finite");
    if (!(e.modulus[i].e_kpa > 0 && e.modulus[i].e_kpa <= 1e7))
      bad(at + ".e_kpa", e.modulus[i].e_kpa, "must be above 0 and at most 1e7 kPa");
    if (i > 0 && !(e.modulus[i].hu > e.modulus[i - 1].hu))
      bad(at + ".hu", e.modulus[i].hu,
          "must be above the point before it (" + std::to_string(e.modulus[i - 1].hu) + "): the table is sorted by hu");
  }
  if (!(e.skin_e_kpa > 0 && e.skin_e_kpa <= 1e7)) bad("skin_e_kpa", e.skin_e_kpa, "must be above 0 and at most 1e7 kPa");
  if (!(e.skin_thickness_mm >= 0 && e.skin_thickness_mm <= 20))
    bad("skin_thickness_mm", e.skin_thickness_mm, "must lie in [0, 20] mm");
  if (!(e.poisson > 0 && e.poisson < 0.5))
    bad("poisson", e.poisson, "must lie in (0, 0.5): 0.5 is incompressible, which linear elasticity cannot hold");
  if (e.max_iterations < 1) bad("max_iterations", e.max_iterations, "must be at least 1");
  if (!(e.tolerance > 0 && e.tolerance < 1)) bad("tolerance", e.tolerance, "must lie in (0, 1)");
  if (e.contact_rounds < 1) bad("contact_rounds", e.contact_rounds, "must be at least 1");
  if (!(e.min_tissue_fraction >= 0 && e.min_tissue_fraction <= 0.95))
    bad("min_tissue_fraction", e.min_tissue_fraction,
        "must lie in [0, 0.95] (0: the press is not stopped short of bone)");
  if (!(e.stiffness_tolerance >= 0 && e.stiffness_tolerance < 1))
    bad("stiffness_tolerance", e.stiffness_tolerance, "must lie in [0, 1) (0: the unit press stops at tolerance)");
  // the Chebyshev degrees: the GPU fuses a smoothing's first step into the pass before it
  // and needs a second; the coefficients' arrays hold kElasticMaxDegree
  const std::string degrees = "must lie in [2, " + std::to_string(deform::kElasticMaxDegree) + "]";
  for (const auto& [name, value] : {std::pair<const char*, int>{"smooth_degree", e.smooth_degree},
                                    {"coarse_smooth_degree", e.coarse_smooth_degree},
                                    {"coarsest_degree", e.coarsest_degree}})
    if (value < 2 || value > deform::kElasticMaxDegree) bad(name, value, degrees);
}

void check_deform_config(const DeformConfig& config, const std::string& who) {
  const DeformSettings& s = config.settings;
  // each setting named as in the scene
  auto bad = [&](const std::string& field, double value, const std::string& rule) {
    std::ostringstream m;
    m << "deform." << field << " = " << value << " " << rule;
    throw Error(who + ": " + m.str());
  };
  if (!(s.min_dist >= 0 && s.min_dist <= 1)) bad("min_dist", s.min_dist, "must lie in [0, 1] voxel");
  if (!(s.max_dist >= 1 && s.max_dist <= 4)) bad("max_dist", s.max_dist, "must lie in [1, 4] voxel");
  if (!(s.max_sheer >= 0 && s.max_sheer <= 4)) bad("max_sheer", s.max_sheer, "must lie in [0, 4] voxel");
  if (!s.whole_volume && !(s.voi_edge >= 3 && s.voi_edge <= 1024))
    bad("voi_edge", s.voi_edge, "must lie in [3, 1024] voxel");
  // the CUDA sweeps keep a flag above the sweep number in their stamps (bit 30)
  if (!(s.max_sweeps >= 1 && s.max_sweeps <= (1 << 24))) bad("max_sweeps", s.max_sweeps, "must lie in [1, 16777216]");
  if (!(s.grab_radius_mm >= 0 && s.grab_radius_mm <= 20)) bad("grab_radius_mm", s.grab_radius_mm, "must lie in [0, 20] mm");
  if (s.grab_radius_mm > 0 && s.relax_method == RelaxMethod::kExplicit)
    bad("grab_radius_mm", s.grab_radius_mm,
        "needs deform.relax_method \"multigrid\" or \"elastic\" (the explicit relaxation grabs one element)");
  if (s.relax_method == RelaxMethod::kElastic) {
    if (!(s.grab_radius_mm > 0))
      bad("grab_radius_mm", s.grab_radius_mm, "must be above 0 with deform.relax_method \"elastic\" (the fingertip sphere's radius)");
    check_elastic_settings(s.elastic, who);
    if (s.untangle) throw Error(who + ": deform.untangle is for the ChainMail family's relaxations; the elastic model's "
                                "folds are counted (DeformStats::elastic.inverted_cells), not moved");
  }
  if (s.relax_iterations < 0) bad("relax_iterations", s.relax_iterations, "must not be negative");
  if (s.relax_cycles < 0 || s.relax_cycles > deform::kMultigridMaxCycles)
    bad("relax_cycles", s.relax_cycles, "must lie in [0, " + std::to_string(deform::kMultigridMaxCycles) + "]");
  if (s.relax_warm_cycles < 0 || s.relax_warm_cycles > deform::kMultigridMaxCycles)
    bad("relax_warm_cycles", s.relax_warm_cycles,
        "must lie in [0, " + std::to_string(deform::kMultigridMaxCycles) + "]");
  if (!(s.relax_step >= 0)) bad("relax_step", s.relax_step, "must not be negative");
  if (s.relax_step > deform::kRelaxStableStep) {
    std::ostringstream m;
    m << "deform.relax_step = " << s.relax_step << " is above the explicit scheme's stable limit "
      << deform::kRelaxStableStep << " (1/6 for six neighbours); use a smaller step and more iterations";
    throw Error(who + ": " + m.str());
  }
  if (!(s.material_width > 0)) bad("material_width", s.material_width, "must be positive (HU)");
  if (s.invert_iterations < 0) bad("invert_iterations", s.invert_iterations, "must not be negative");
  if (!std::isfinite(config.bone_threshold)) bad("bone_threshold", config.bone_threshold, "must be finite");

}

void DeformBackend::require(bool ok, const char* what) const {
  if (!ok) throw Error("deform backend \"" + name_ + "\": " + what);
}

deform::ElasticParams DeformConfig::elastic_params() const {
  const ElasticSettings& e = settings.elastic;
  deform::ElasticParams p;
  deform::ElasticTable& t = p.material.table;
  t.n = int(std::min<std::size_t>(e.modulus.size(), deform::kElasticMaxTable));
  float least = float(e.skin_e_kpa);
  for (int i = 0; i < t.n; ++i) {
    t.hu[i] = float(e.modulus[std::size_t(i)].hu);
    t.e_kpa[i] = float(e.modulus[std::size_t(i)].e_kpa);
    least = std::min(least, t.e_kpa[i]);
  }
  p.material.skin_e_kpa = float(e.skin_e_kpa);
  p.material.skin_mm = float(e.skin_thickness_mm);
  p.material.air_e_kpa = deform::kElasticAirRatio * least;
  p.poisson = e.poisson;
  p.finger_radius_mm = float(settings.grab_radius_mm);
  p.max_iterations = e.max_iterations;
  p.tolerance = float(e.tolerance);
  p.contact_rounds = e.contact_rounds;
  p.predict = e.predict;
  p.stiffness_tolerance = float(e.stiffness_tolerance);
  p.degrees = deform::ElasticDegrees{e.smooth_degree, e.coarse_smooth_degree, e.coarsest_degree};
  p.stiffness = elastic_stiffness;
  p.superpose = elastic_superpose;
  return p;
}

bool DeformBatchKey::operator==(const DeformBatchKey& o) const {
  const auto& [a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11, a12, a13, a14, a15, a16] = *this;
  const auto& [b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15, b16] = o;
  return std::tie(a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11, a12, a13, a14, a15, a16) ==
         std::tie(b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15, b16);
}

std::optional<DeformBatchKey> deform_batch_key(const DeformConfig& config) {
  // every member by name: the session's own ones are left out of the key below
  [[maybe_unused]] const auto& [settings, bone_threshold, relax, invert, relax_reuse, skip_chainmail, voi_hold,
                                elastic_stiffness, elastic_force, elastic_superpose] = config;
  [[maybe_unused]] const auto& [min_dist, max_dist, max_sheer, voi_edge, whole_volume, max_sweeps, relax_method,
                                relax_iterations, relax_step, relax_cycles, relax_warm_cycles, grab_radius_mm,
                                material_width, invert_iterations, untangle, invert_search, backend, elastic] = settings;
  // the session's own: its VOI (voi_edge, whole_volume, voi_hold), its multigrid fingertip
  // (grab_radius_mm: multigrid sessions share the batch's other launches and its one wait,
  // their solves one launch each), the elastic model's settings (elastic,
  // elastic_stiffness, elastic_force, elastic_superpose: each session's solve is one cooperative launch of its own, the
  // batch's other stages shared), its backend; untangling steps alone
  if (relax && untangle) return std::nullopt;
  const deform::ChainMailLimits limits = deform::chainmail_limits(min_dist, max_dist, max_sheer);
  const bool mg = relax_method == RelaxMethod::kMultigrid;
  // in DeformBatchKey's order
  return DeformBatchKey{relax, invert, bone_threshold, relax_method, max_sweeps, relax_iterations, relax_step,
                        material_width, invert_iterations, invert_search, limits.axial_lo, limits.axial_hi,
                        limits.sheer, mg ? relax_cycles : 0, mg ? relax_warm_cycles : 0, mg && relax_reuse,
                        mg && skip_chainmail};
}

bool deform_batchable(const DeformConfig& a, const DeformConfig& b) {
  const std::optional<DeformBatchKey> ka = deform_batch_key(a), kb = deform_batch_key(b);
  return ka && kb && *ka == *kb;
}

void DeformBackend::set_relax_counts(DeformStats& out) const {
  const RelaxMethod method = config_.settings.relax_method;
  const bool mg = method == RelaxMethod::kMultigrid;
  out.relax_iterations = mg || method == RelaxMethod::kElastic ? 0 : config_.settings.relax_iterations;
  out.relax_cycles = mg ? config_.settings.relax_cycles : 0;
}

void DeformBackend::set_multigrid_counts(DeformStats& out, int solves, bool warm, int warm_steps) const {
  out.relax_solves = solves;
  out.relax_warm = warm;
  if (warm) out.relax_cycles = warm_steps;
}

long long DeformBackend::max_voi_count() const {
  const Vec3i& g = patient_->grid.size;
  if (config_.settings.whole_volume) return (long long)g.x * g.y * g.z;
  long long n = 1;
  for (int a = 0; a < 3; ++a) n *= std::min(config_.settings.voi_edge, g[a]);
  return n;
}

void DeformBackend::bind(PatientPtr patient, const DeformConfig& config) {
  require(patient != nullptr, "bind() got no patient");
  const Patient& p = *patient;
  const DeformSettings& s = config.settings;
  const Vec3i& g = p.grid.size;
  require(g.x > 0 && g.y > 0 && g.z > 0, "the patient grid is empty");
  require(p.intensity.grid.same_geometry(p.grid) && p.intensity.data.size() == p.grid.count(),
          "Patient::intensity does not match the patient grid");
  require(p.bone.grid.same_geometry(p.grid) && p.bone.data.size() == p.grid.count(),
          "Patient::bone does not match the patient grid");
  check_deform_config(config, "deform backend \"" + name_ + "\"");
  // the elastic model also reads the body mask (skin and air) and the depth under the skin
  if (config.relax && s.relax_method == RelaxMethod::kElastic) {
    require(p.body.grid.same_geometry(p.grid) && p.body.data.size() == p.grid.count(),
            "deform.relax_method \"elastic\" needs Patient::body (the body mask) on the patient grid");
    require(p.dist_skin_mm.grid.same_geometry(p.grid) && p.dist_skin_mm.data.size() == p.grid.count(),
            "deform.relax_method \"elastic\" needs Patient::dist_skin_mm (the depth under the skin) on the patient grid");
  }

  patient_ = std::move(patient);
  config_ = config;
  limits_ = deform::chainmail_limits(s.min_dist, s.max_dist, s.max_sheer);
  finger_r2_ = finger_r2(s, patient_->grid);
  // a multigrid relaxation that runs (and so overwrites every free element) may do without
  // ChainMail where nothing ChainMail moves is held
  held_blocks_.reset();
  if (config.skip_chainmail && config.relax && s.relax_method == RelaxMethod::kMultigrid && s.relax_cycles > 0)
    held_blocks_ = deform::HeldBlocks::of(patient_, float(config.bone_threshold), float(s.material_width));
  voi_hold_ = config.voi_hold && config.relax && !s.whole_volume &&
              ((config.relax_reuse && s.relax_method == RelaxMethod::kMultigrid && s.relax_cycles > 0) ||
               s.relax_method == RelaxMethod::kElastic);
  voi_margin_ = config.relax && s.relax_method == RelaxMethod::kElastic ? deform::kElasticVoiMarginVox : 0;
  hold_voi_ = Voi{};
  voi_ = Voi{};
  setup_ = ChainMailStats{};
  bound_ = false;
  bind_impl();
  bound_ = true;
  stage_ = 0;
}

ChainMailStats DeformBackend::locate(const DeformContact& c, Vec3i* tip_vox) const {
  if (!finite(c.skin_point_mm)) throw Error("deform: contact skin_point_mm (X) is not finite: " + fmt_vec(c.skin_point_mm));
  if (!finite(c.tip_mm)) throw Error("deform: contact tip_mm (x) is not finite: " + fmt_vec(c.tip_mm));
  const Grid& grid = patient_->grid;
  const Vec3 X = grid.to_index(c.skin_point_mm);
  const Vec3 x = grid.to_index(c.tip_mm);
  // the grabbed element: the voxel nearest X. X must lie in the volume, which reaches half
  // a voxel beyond the border voxels' centres (where the grid cuts the body, the skin point
  // may lie on that outer face); 2e-3 voxel more for the skin search's bisection tolerance
  // (a thousandth of a voxel) and round-off
  constexpr double kFaceTolVox = 2e-3;
  Vec3i e0, t;
  for (int a = 0; a < 3; ++a) {
    if (!(X[a] >= -0.5 - kFaceTolVox && X[a] <= grid.size[a] - 0.5 + kFaceTolVox))
      throw Error("deform: contact skin_point_mm (X) " + fmt_vec(c.skin_point_mm) + " mm lies outside the patient grid");
    e0[a] = std::clamp(int(std::floor(X[a] + 0.5)), 0, grid.size[a] - 1);
    if (!(std::fabs(x[a]) < 1e8)) throw Error("deform: contact tip_mm (x) is far outside the patient grid: " + fmt_vec(c.tip_mm));
    t[a] = int(std::floor(x[a] + 0.5));
  }
  ChainMailStats st;
  st.grabbed_vox = e0;
  st.skin_vox = X;
  st.tip_vox = x;
  st.grabbed_u_vox = Vec3f(float(x.x - e0.x), float(x.y - e0.y), float(x.z - e0.z));
  st.grabbed_in_bone = patient_->bone.data[grid.index(e0.x, e0.y, e0.z)] != 0;
  st.voi = compute_voi(grid.size, e0, t, config_.settings.voi_edge, config_.settings.whole_volume, voi_margin_);
  if (tip_vox) *tip_vox = t;
  return st;
}

ChainMailStats DeformBackend::setup_step(const DeformContact& c) {
  require(bound_, "chainmail() or step() before bind()");
  Vec3i t;
  ChainMailStats st = locate(c, &t);
  const Vec3i& e0 = st.grabbed_vox;
  // a multigrid press keeps its VOI (and so its unit response) while the tip voxel stays
  // within edge / 8 voxels of the one it was placed around and it holds the grabbed voxel
  // (DeformConfig::voi_hold; the elastic model's: as far from its faces as compute_voi
  // puts it, where the face is not the grid's border)
  if (voi_hold_) {
    const int slack = std::max(1, config_.settings.voi_edge / 8);
    const int m = std::clamp(voi_margin_, 0, (config_.settings.voi_edge - 1) / 2);
    const Vec3i& g = patient_->grid.size;
    bool keep = hold_voi_.count() > 0;
    for (int a = 0; a < 3; ++a) {
      const int lo = hold_voi_.lo[a], hi = hold_voi_.lo[a] + hold_voi_.size[a] - 1;
      keep = keep && std::abs(t[a] - hold_tip_[a]) <= slack && e0[a] >= lo + (lo > 0 ? m : 0) &&
             e0[a] <= hi - (hi < g[a] - 1 ? m : 0);
    }
    if (keep) {
      st.voi = hold_voi_;
    } else {
      hold_voi_ = st.voi;
      hold_tip_ = t;
    }
  }
  // the elastic solve sets every element itself (ChainMail's field is not its input)
  st.skipped = (held_blocks_ && !st.grabbed_in_bone && !held_blocks_->any_in(st.voi)) ||
               (config_.relax && config_.settings.relax_method == RelaxMethod::kElastic);
  return st;
}

ChainMailStats DeformBackend::chainmail(const DeformContact& contact) {
  ChainMailStats st = setup_step(contact);
  if (stage_ != 0) reset_impl();
  stage_ = 0;
  voi_ = st.voi;
  setup_ = st;
  chainmail_impl(st);
  stage_ = 1;
  return st;
}

void DeformBackend::relax() {
  require(stage_ >= 1, "relax() before chainmail()");
  relax_impl();
  stage_ = 2;
}

UntangleStats DeformBackend::untangle() {
  require(stage_ >= 1, "untangle() before chainmail()");
  const UntangleStats r = untangle_impl();
  stage_ = 2;
  return r;
}

InvertStats DeformBackend::invert() {
  require(stage_ >= 1, "invert() before chainmail()");
  const InvertStats r = invert_impl();
  stage_ = 3;
  return r;
}

void DeformBackend::upload() {
  require(stage_ >= 3, "upload() before invert()");
  upload_impl();
  stage_ = 4;
}

void DeformBackend::reset() {
  require(bound_, "reset() before bind()");
  if (stage_ != 0) reset_impl();
  forget_impl();
  stage_ = 0;
  hold_voi_ = Voi{};  // the next contact starts a press afresh
}

DeformStats DeformBackend::step(const DeformContact& contact) {
  ChainMailStats st = setup_step(contact);
  // step_impl starts with a reset of whatever the previous step left, timed as a stage
  voi_ = st.voi;
  setup_ = st;
  DeformStats out = step_impl(st);
  stage_ = config_.invert ? 4 : (config_.relax ? 2 : 1);
  return out;
}

void DeformBackend::begin_step(const DeformContact& contact) {
  require(!in_step_, "begin_step() twice without end_step()");
  ChainMailStats st = setup_step(contact);
  voi_ = st.voi;
  setup_ = st;
  in_step_ = true;
  try {
    begin_step_impl(st);
  } catch (...) {
    in_step_ = false;
    throw;
  }
}

DeformStats DeformBackend::end_step() {
  require(in_step_, "end_step() without begin_step()");
  in_step_ = false;
  DeformStats out = end_step_impl();
  stage_ = config_.invert ? 4 : (config_.relax ? 2 : 1);
  return out;
}

std::vector<std::exception_ptr> DeformBackend::begin_steps(const std::vector<DeformBackend*>& backends,
                                                          const std::vector<DeformContact>& contacts) {
  if (backends.size() != contacts.size())
    throw Error("deform: begin_steps() got " + std::to_string(backends.size()) + " backends and " +
                std::to_string(contacts.size()) + " contacts");
  std::vector<std::exception_ptr> errors(backends.size());
  // each contact checked alone: a refused one leaves its backend out
  std::vector<DeformBackend*> group;
  std::vector<std::size_t> at;
  for (std::size_t i = 0; i < backends.size(); ++i) {
    DeformBackend& b = *backends[i];
    try {
      b.require(!b.in_step_, "begin_step() twice without end_step()");
      ChainMailStats st = b.setup_step(contacts[i]);
      b.voi_ = st.voi;
      b.setup_ = st;
      b.in_step_ = true;
      group.push_back(&b);
      at.push_back(i);
    } catch (...) {
      errors[i] = std::current_exception();
    }
  }
  if (group.empty()) return errors;
  // one batch when the backend can; a failed batch fails all of its steps
  if (group.size() > 1) {
    try {
      if (group[0]->begin_batch_impl(group)) return errors;
    } catch (...) {
      for (std::size_t g = 0; g < group.size(); ++g) {
        group[g]->in_step_ = false;
        errors[at[g]] = std::current_exception();
      }
      return errors;
    }
  }
  // otherwise each alone, as begin_step()
  for (std::size_t g = 0; g < group.size(); ++g) {
    try {
      group[g]->begin_step_impl(group[g]->setup_);
    } catch (...) {
      group[g]->in_step_ = false;
      errors[at[g]] = std::current_exception();
    }
  }
  return errors;
}

bool DeformConfig::primes() const {
  return relax && relax_reuse && settings.relax_method == RelaxMethod::kMultigrid && settings.relax_cycles > 0 &&
         settings.relax_warm_cycles > 0;
}

DeformPrime DeformBackend::prime(const DeformContact& expected) {
  require(bound_, "prime() before bind()");
  require(!in_step_, "prime() between begin_step() and end_step()");
  // checked as a step checks its contact, whether or not there is anything to prime
  const ChainMailStats st = locate(expected);
  if (!config_.primes() || st.grabbed_in_bone) return {};
  DeformPrime out = prime_impl(st);
  out.voi = st.voi;
  out.grabbed_vox = st.grabbed_vox;
  return out;
}

bool DeformBackend::unit_response(Vec3i& grabbed_vox) const {
  const deform::MultigridCache* c = bound_ ? multigrid_cache_impl() : nullptr;
  if (!c || !c->ok) return false;
  grabbed_vox = c->lo + c->grabbed;
  return true;
}

void DeformBackend::set_gpu_share(int k) {
  require(!in_step_, "set_gpu_share() between begin_step() and end_step()");
  gpu_share_ = std::max(1, k);
}

std::vector<Vec3f> DeformBackend::displacement() const {
  require(voi_.count() > 0, "displacement() before chainmail()");
  return displacement_impl();
}

void DeformBackend::set_displacement(const std::vector<Vec3f>& u) {
  require(stage_ >= 1, "set_displacement() before chainmail()");
  if ((long long)u.size() != voi_.count()) {
    std::ostringstream m;
    m << "set_displacement() got " << u.size() << " values for a VOI of " << voi_.count();
    throw Error("deform backend \"" + name_ + "\": " + m.str());
  }
  for (const Vec3f& v : u)
    if (!std::isfinite(v.x) || !std::isfinite(v.y) || !std::isfinite(v.z))
      throw Error("deform backend \"" + name_ + "\": set_displacement() got a non-finite displacement");
  set_displacement_impl(u);
  stage_ = 2;
}

const float* DeformBackend::deformed_brick() const {
  require(stage_ >= 4, "deformed_brick() before upload()");
  return deformed_brick_impl();
}

void DeformBackend::compose_deformed(Volume<float>& out) const {
  const Patient& p = *patient_;
  out.grid = p.grid;
  out.data = p.intensity.data;
  if (stage_ < 4) return;
  // copy the brick row by row into its place
  const float* b = deformed_brick_impl();
  for (int k = 0; k < voi_.size.z; ++k)
    for (int j = 0; j < voi_.size.y; ++j)
      std::memcpy(&out.data[p.grid.index(voi_.lo.x, voi_.lo.y + j, voi_.lo.z + k)], b + voi_.index(0, j, k),
                  sizeof(float) * voi_.size.x);
}

bool DeformBackend::copy_brick_to_device(std::unique_ptr<DeviceBytes>& dst) const {
  if (stage_ < 4) return false;
  return copy_brick_to_device_impl(dst);
}

DeformBackendRegistry& deform_backends() {
  static DeformBackendRegistry registry;
  return registry;
}

bool cuda_deform_available(std::string* why) {
  const std::optional<DeformBackendRegistry::Factory> cuda = deform_backends().find(DeformBackendChoice::kCuda);
  if (!cuda) {
    if (why) *why = "this build has no CUDA backend (configured with PALPSIM_CUDA=OFF or without nvcc)";
    return false;
  }
  return cuda->usable(why);
}

std::unique_ptr<DeformBackend> make_deform_backend(DeformBackendChoice choice, std::string* note) {
  if (choice == DeformBackendChoice::kCpu) {
    if (note) *note = "deform backend \"cpu\" (asked for by name)";
    return std::make_unique<CpuDeformBackend>();
  }
  const bool automatic = choice == DeformBackendChoice::kAuto;
  std::string why;
  if (cuda_deform_available(&why)) {
    if (note) *note = "deform backend \"cuda\" (" + std::string(automatic ? "auto: " : "") + why + ")";
    return deform_backends().find(DeformBackendChoice::kCuda)->make();
  }
  if (!automatic) throw Error("deform backend \"cuda\" is unavailable: " + why + "; use \"cpu\" or \"auto\"");
  if (note) *note = "deform backend \"cpu\" (auto: cuda unavailable: " + why + ")";
  return std::make_unique<CpuDeformBackend>();
}

DeformBackendChoice deform_backend_choice(const std::string& name) {
  return setting_by_name<DeformBackendChoice>(name);
}

std::unique_ptr<DeformBackend> make_deform_backend(const std::string& name, std::string* note) {
  return make_deform_backend(deform_backend_choice(name), note);
}

}  // namespace palpsim
