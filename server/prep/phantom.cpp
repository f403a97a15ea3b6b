// The built-in procedural phantom: closed-form shapes (phantom.h gives the layout)
// and their rasterization into HU with partial volume at every boundary.
#include "prep/phantom.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <sstream>
#include <thread>

#include "core/error.h"

namespace palpsim {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kInf = std::numeric_limits<double>::infinity();

// the volume: origin and extent (mm), see phantom.h
const Vec3 kOrigin{-170, -145, -110};
const Vec3 kExtent{340, 270, 220};

// torso cross-section (elliptic cylinder along z) and its layers (mm)
constexpr double kBodyA = 155, kBodyB = 110;    // skin ellipse semi-axes along x, y
constexpr double kSkinThickness = 2;            // dermis
constexpr double kFatA = 137, kFatB = 96;       // inner edge of the subcutaneous fat
constexpr double kCavityY = -30, kCavityA = 112, kCavityB = 58;  // abdominal cavity
constexpr double kCanalY = 31, kCanalR = 8.5;   // spinal canal (circle)
constexpr double kPsoasX = 38, kPsoasY = 0, kPsoasA = 13, kPsoasB = 16;

// CT table: a rounded rectangle in x-y, infinite along z
constexpr double kTableY = -127, kTableHalfX = 165, kTableHalfY = 13, kTableRound = 3;
constexpr double kTableShell = 3;

double clamp01(double v) { return v < 0 ? 0 : (v > 1 ? 1 : v); }
double lerp(double a, double b, double t) { return a + (b - a) * t; }

// distance from (y0, y1) >= 0 to the ellipse with semi-axes e0 >= e1 > 0 (Eberly's
// robust bisection, "Distance from a Point to an Ellipse", exact to rounding)
double ellipse_distance_q1(double e0, double e1, double y0, double y1) {
  if (y1 > 0) {
    if (y0 > 0) {
      const double z0 = y0 / e0, z1 = y1 / e1;
      double g = z0 * z0 + z1 * z1 - 1;
      if (g == 0) return 0;
      const double r0 = (e0 / e1) * (e0 / e1);
      const double n0 = r0 * z0;
      double s0 = z1 - 1, s1 = g < 0 ? 0 : std::hypot(n0, z1) - 1, s = 0;
      for (int it = 0; it < 256; ++it) {
        s = 0.5 * (s0 + s1);
        if (s == s0 || s == s1) break;
        const double a = n0 / (s + r0), b = z1 / (s + 1);
        g = a * a + b * b - 1;
        if (g > 0) s0 = s;
        else if (g < 0) s1 = s;
        else break;
      }
      const double x0 = r0 * y0 / (s + r0), x1 = y1 / (s + 1);
      return std::hypot(x0 - y0, x1 - y1);
    }
    return std::abs(y1 - e1);
  }
  const double numer0 = e0 * y0, denom0 = e0 * e0 - e1 * e1;
  if (numer0 < denom0) {
    const double xde0 = numer0 / denom0;
    const double x0 = e0 * xde0, x1 = e1 * std::sqrt(std::max(0.0, 1 - xde0 * xde0));
    return std::hypot(x0 - y0, x1);
  }
  return std::abs(y0 - e0);
}

// exact signed distance to an axis-aligned ellipse with semi-axes a (x) and b (y)
double ellipse_sdf(double x, double y, double a, double b) {
  x = std::abs(x);
  y = std::abs(y);
  if (a < b) {
    std::swap(a, b);
    std::swap(x, y);
  }
  const double d = ellipse_distance_q1(a, b, x, y);
  return (x / a) * (x / a) + (y / b) * (y / b) < 1 ? -d : d;
}

// exact signed distance to a rounded rectangle (half sizes hx, hy include the rounding r)
double round_rect_sdf(double x, double y, double hx, double hy, double r) {
  const double qx = std::abs(x) - hx + r, qy = std::abs(y) - hy + r;
  return std::hypot(std::max(qx, 0.0), std::max(qy, 0.0)) + std::min(std::max(qx, qy), 0.0) - r;
}

/// Axis-aligned bounding box; distance() is a lower bound of the distance to what it holds.
struct Aabb {
  Vec3 lo{kInf, kInf, kInf}, hi{-kInf, -kInf, -kInf};
  double distance(const Vec3& p) const {
    const double dx = std::max({lo.x - p.x, 0.0, p.x - hi.x});
    const double dy = std::max({lo.y - p.y, 0.0, p.y - hi.y});
    const double dz = std::max({lo.z - p.z, 0.0, p.z - hi.z});
    return std::sqrt(dx * dx + dy * dy + dz * dz);
  }
};

Vec3 normalized(const Vec3& v) { return v / norm(v); }

}  // namespace

/// One solid with an exact signed distance: capsule, oriented rounded box, or an
/// elliptic slab (ellipse in x-y extruded along z) with rounded edges.
struct Solid {
  enum Kind { kCapsule, kRoundBox, kEllipseSlab } kind = kCapsule;
  Vec3 a, b;              // capsule: segment ends (mm)
  Vec3 c;                 // box / slab: centre (mm)
  Vec3 u{1, 0, 0}, v{0, 1, 0}, w{0, 0, 1};  // box: orthonormal axes
  Vec3 e;                 // box: half extents of the inner box; slab: (ax, ay, hz) before rounding
  double r = 0;           // capsule radius; box and slab rounding (mm)
  double cortex_mm = 0;   // bone: cortical shell thickness
  double interior_hu = 0; // bone: HU inside the shell; disc: HU
  Aabb box;

  double sdf(const Vec3& p) const {
    switch (kind) {
      case kCapsule: {
        const Vec3 ab = b - a, ap = p - a;
        const double t = std::clamp(dot(ap, ab) / dot(ab, ab), 0.0, 1.0);
        return norm(ap - ab * t) - r;
      }
      case kRoundBox: {
        const Vec3 d = p - c;
        const double qx = std::abs(dot(d, u)) - e.x, qy = std::abs(dot(d, v)) - e.y, qz = std::abs(dot(d, w)) - e.z;
        const Vec3 m{std::max(qx, 0.0), std::max(qy, 0.0), std::max(qz, 0.0)};
        return norm(m) + std::min(std::max(qx, std::max(qy, qz)), 0.0) - r;
      }
      case kEllipseSlab: {
        const double q2 = ellipse_sdf(p.x - c.x, p.y - c.y, e.x, e.y);
        const double dz = std::abs(p.z - c.z) - e.z;
        return std::hypot(std::max(q2, 0.0), std::max(dz, 0.0)) + std::min(std::max(q2, dz), 0.0) - r;
      }
    }
    return kInf;
  }

  static Solid capsule(const Vec3& a, const Vec3& b, double r) {
    Solid s;
    s.kind = kCapsule;
    s.a = a;
    s.b = b;
    s.r = r;
    s.box.lo = {std::min(a.x, b.x) - r, std::min(a.y, b.y) - r, std::min(a.z, b.z) - r};
    s.box.hi = {std::max(a.x, b.x) + r, std::max(a.y, b.y) + r, std::max(a.z, b.z) + r};
    return s;
  }
  // u must be a unit vector; v is made orthonormal to it from `v_hint`
  static Solid round_box(const Vec3& c, const Vec3& u, const Vec3& v_hint, const Vec3& half, double r) {
    Solid s;
    s.kind = kRoundBox;
    s.c = c;
    s.u = normalized(u);
    s.v = normalized(v_hint - s.u * dot(v_hint, s.u));
    s.w = cross(s.u, s.v);
    s.e = half;
    s.r = r;
    const Vec3 ext{std::abs(s.u.x) * half.x + std::abs(s.v.x) * half.y + std::abs(s.w.x) * half.z + r,
                   std::abs(s.u.y) * half.x + std::abs(s.v.y) * half.y + std::abs(s.w.y) * half.z + r,
                   std::abs(s.u.z) * half.x + std::abs(s.v.z) * half.y + std::abs(s.w.z) * half.z + r};
    s.box.lo = c - ext;
    s.box.hi = c + ext;
    return s;
  }
  static Solid ellipse_slab(const Vec3& c, double ax, double ay, double hz, double r) {
    Solid s;
    s.kind = kEllipseSlab;
    s.c = c;
    s.e = {ax, ay, hz};
    s.r = r;
    s.box.lo = c - Vec3{ax + r, ay + r, hz + r};
    s.box.hi = c + Vec3{ax + r, ay + r, hz + r};
    return s;
  }
};

/// A bowel loop: a capsule with a 3 mm wall; its lumen holds fluid, and gas above
/// `gas_level_y` (the patient is prone, so gas rises towards +y).
struct BowelLoop {
  Solid outer;            // capsule to the outer wall surface
  Solid lumen;            // capsule to the inner wall surface
  double gas_level_y = kInf;
};

/// Everything the phantom is made of.
struct PhantomShapes {
  std::vector<Solid> bones;
  struct Group {
    std::size_t begin, end;  // a range of `bones` (one vertebra, one rib, one ilium)
    Aabb box;                // holds all of them
  };
  std::vector<Group> groups;
  std::vector<Solid> discs;
  std::vector<BowelLoop> loops;
  std::vector<PhantomLandmark> landmarks;
};

namespace {

// a bone solid with its shell and interior
Solid bone(Solid s, double cortex_mm, double interior_hu) {
  s.cortex_mm = cortex_mm;
  s.interior_hu = interior_hu;
  return s;
}

// one vertebral level
struct Level {
  const char* name;
  double z;             // centre of the body (mm)
  double ax, ay, hz;    // body ellipse semi-axes and half height before the 2 mm rounding
  double tip_y;         // posterior-most point of the spinous process (mm)
  double tilt_deg;      // spinous process slopes down towards its tip
  double tp_x;          // transverse process reach (mm from the midline), 0 = none
  double tp_r;          // transverse process radius
  double body_interior_hu;
};

// Catmull-Rom spline through `pts`, `n` samples per span, ends included
std::vector<Vec3> catmull_rom(const std::vector<Vec3>& pts, int n) {
  std::vector<Vec3> out;
  for (std::size_t s = 0; s + 1 < pts.size(); ++s) {
    const Vec3 p0 = pts[s == 0 ? 0 : s - 1], p1 = pts[s], p2 = pts[s + 1];
    const Vec3 p3 = pts[std::min(s + 2, pts.size() - 1)];
    for (int i = 0; i < n; ++i) {
      const double t = double(i) / n, t2 = t * t, t3 = t2 * t;
      out.push_back((p1 * 2.0 + (p2 - p0) * t + (p0 * 2.0 - p1 * 5.0 + p2 * 4.0 - p3) * t2 +
                     (p1 * 3.0 - p0 - p2 * 3.0 + p3) * t3) * 0.5);
    }
  }
  out.push_back(pts.back());
  return out;
}

// closes the group of bones added since the last call (for the distance queries)
void end_group(PhantomShapes& s) {
  PhantomShapes::Group g{s.groups.empty() ? 0 : s.groups.back().end, s.bones.size(), {}};
  for (std::size_t i = g.begin; i < g.end; ++i) {
    const Aabb& b = s.bones[i].box;
    g.box.lo = {std::min(g.box.lo.x, b.lo.x), std::min(g.box.lo.y, b.lo.y), std::min(g.box.lo.z, b.lo.z)};
    g.box.hi = {std::max(g.box.hi.x, b.hi.x), std::max(g.box.hi.y, b.hi.y), std::max(g.box.hi.z, b.hi.z)};
  }
  if (g.end > g.begin) s.groups.push_back(g);
}

// vertebral bodies: centre y and rounding (mm)
constexpr double kBodyY = 6, kBodyRound = 2;

// spine: T12, L1-L5 and the top of S1 (cut by the volume; its interior is above the
// bone threshold because a cut body cannot be hole-filled)
const Level kLevels[] = {
    {"T12", 96, 17, 12.5, 9.5, 82, 18, 28, 3.5, phantom_hu::kCancellousVertebra},
    {"L1", 62, 18, 13, 10.5, 83, 12, 36, 3.5, phantom_hu::kCancellousVertebra},
    {"L2", 28, 19, 13.5, 10.5, 85, 10, 40, 3.5, phantom_hu::kCancellousVertebra},
    {"L3", -6, 20, 14, 10.5, 86, 8, 46, 3.5, phantom_hu::kCancellousVertebra},
    {"L4", -40, 21, 14, 10.5, 84, 8, 42, 3.5, phantom_hu::kCancellousVertebra},
    {"L5", -74, 22, 14.5, 10.5, 79, 5, 40, 5.0, phantom_hu::kCancellousVertebra},
    {"S1", -108, 23, 15, 10, 72, 0, 0, 0, phantom_hu::kCancellous},
};

// one vertebra's bones and landmarks, closed as one group
void add_vertebra(PhantomShapes& s, const Level& l) {
  namespace hu = phantom_hu;
  // vertebral body: 2 mm cortex around the cancellous interior
  s.bones.push_back(bone(Solid::ellipse_slab({0, kBodyY, l.z}, l.ax, l.ay, l.hz, kBodyRound), 2.0,
                         l.body_interior_hu));
  s.landmarks.push_back({std::string("vertebral_body_") + l.name, {0, kBodyY, l.z}});
  // pedicles, lateral to the canal
  for (double sx : {-1.0, 1.0})
    s.bones.push_back(bone(Solid::round_box({sx * 14, 30, l.z + 1}, {0, 1, 0}, {1, 0, 0}, {8, 2, 4}, 2.5), 1.5,
                           hu::kCancellous));
  // laminae: plates from the pedicles to the midline, the canal's roof
  for (double sx : {-1.0, 1.0}) {
    const Vec3 from{sx * 14, 40, l.z}, to{0, 47, l.z};
    s.bones.push_back(bone(Solid::round_box((from + to) * 0.5, to - from, {0, 0, 1},
                                            {norm(to - from) * 0.5, 6.5, 1.5}, 2.5),
                           1.5, hu::kCancellous));
  }
  // spinous process: a rounded plate from the laminae backwards, sloping down
  // by tilt; its posterior-most point lies at y = tip_y
  {
    const double th = l.tilt_deg * kPi / 180, r = 2, hx = 2, hz = 7;
    const Vec3 u{0, std::cos(th), -std::sin(th)}, w{0, std::sin(th), std::cos(th)};
    const Vec3 start{0, 44, l.z};
    // solve start.y + 2 hl cos(th) + hz sin(th) + r = tip_y for the half length hl
    const double hl = (l.tip_y - start.y - hz * std::sin(th) - r) / (2 * std::cos(th));
    const Vec3 c = start + u * hl;
    s.bones.push_back(bone(Solid::round_box(c, u, {1, 0, 0}, {hl, hx, hz}, r), 1.5, hu::kCancellous));
    const Vec3 corner = c + u * hl + w * hz;
    s.landmarks.push_back({std::string("spinous_tip_") + l.name, {0, corner.y + r, corner.z}});
  }
  // transverse processes
  if (l.tp_x > 0)
    for (double sx : {-1.0, 1.0})
      s.bones.push_back(
          bone(Solid::capsule({sx * 14, 32, l.z}, {sx * l.tp_x, 36, l.z + 1}, l.tp_r), 1.5, hu::kCancellous));
  end_group(s);
}

// intervertebral discs between consecutive bodies, overlapping the endplates by 1 mm
void add_discs(PhantomShapes& s) {
  for (std::size_t i = 0; i + 1 < std::size(kLevels); ++i) {
    const Level& up = kLevels[i];
    const Level& lo = kLevels[i + 1];
    const double top = up.z - up.hz - kBodyRound + 1, bottom = lo.z + lo.hz + kBodyRound - 1;
    Solid d = Solid::ellipse_slab({0, kBodyY, 0.5 * (top + bottom)}, 0.5 * (up.ax + lo.ax) + 1,
                                  0.5 * (up.ay + lo.ay) + 1, 0.5 * (top - bottom) - 1, 1);
    d.interior_hu = phantom_hu::kDisc;
    s.discs.push_back(d);
  }
}

// ribs 10-12: from the costovertebral joint round the posterior and lateral body
// wall on an ellipse (128 x 84 mm), sloping down; capsules of a constant radius; one
// group and one landmark per rib
void add_ribs(PhantomShapes& s) {
  struct Rib {
    int n;
    double head_z, tip_z, tip_deg, radius, landmark_deg;
  };
  const Rib ribs[] = {{10, 164, 84, -25, 5, -10}, {11, 130, 62, -10, 5, 20}, {12, 96, 52, 15, 4.5, 30}};
  for (const Rib& rb : ribs)
    for (double sx : {-1.0, 1.0}) {
      std::vector<Vec3> pts{{sx * 24, 30, rb.head_z}};
      const double phi0 = 65, step = 5;
      const int n = int(std::lround((phi0 - rb.tip_deg) / step));
      for (int i = 0; i <= n; ++i) {
        const double phi = (phi0 - i * step) * kPi / 180, t = double(i) / n;
        pts.push_back({sx * 128 * std::cos(phi), 84 * std::sin(phi), lerp(rb.head_z - 6, rb.tip_z, t)});
      }
      for (std::size_t i = 0; i + 1 < pts.size(); ++i)
        s.bones.push_back(bone(Solid::capsule(pts[i], pts[i + 1], rb.radius), 1.5, phantom_hu::kCancellous));
      end_group(s);
      // landmark: the rib's outer surface (facing the skin) at the vertex nearest to
      // landmark_deg, a place inside the volume where the rib is palpable
      const int iv = 1 + int(std::lround((phi0 - rb.landmark_deg) / step));
      const Vec3 vtx = pts[iv], t = normalized(pts[iv + 1] - pts[iv - 1]);
      const Vec3 radial = normalized(Vec3{vtx.x / (128.0 * 128.0), vtx.y / (84.0 * 84.0), 0});
      const Vec3 out = normalized(radial - t * dot(radial, t));
      s.landmarks.push_back({"rib" + std::to_string(rb.n) + (sx > 0 ? "_left" : "_right"), vtx + out * rb.radius});
    }
}

// iliac wings: the crest is a chain of capsules along a spline from the posterior
// superior iliac spine round the flank to the anterior superior spine; a plate
// hangs from each crest segment down beyond the volume; one group per wing
void add_iliac_wings(PhantomShapes& s) {
  for (double sx : {-1.0, 1.0}) {
    const std::vector<Vec3> ctrl{{sx * 38, 62, -92}, {sx * 75, 64, -62}, {sx * 110, 42, -46},
                                 {sx * 128, 6, -40}, {sx * 126, -28, -48}, {sx * 118, -45, -70}};
    const std::vector<Vec3> crest = catmull_rom(ctrl, 6);
    constexpr double kCrestR = 6, kPlateHalf = 4, kPlateRound = 1, kPlateDepth = 160;
    std::size_t top = 0;
    for (std::size_t i = 0; i < crest.size(); ++i) {
      if (crest[i].z > crest[top].z) top = i;
      if (i + 1 == crest.size()) break;
      const Vec3 a = crest[i], b = crest[i + 1];
      s.bones.push_back(bone(Solid::capsule(a, b, kCrestR), 2.0, phantom_hu::kCancellous));
      // the plate: vertical, along the segment's horizontal direction, thickness across
      // it; its top edge at the segment's lower end stays inside the crest capsule
      // because consecutive crest points differ by less than the capsule radius in z
      const Vec3 u = normalized(Vec3{b.x - a.x, b.y - a.y, 0});
      const Vec3 v{-u.y, u.x, 0};
      const double top_z = std::min(a.z, b.z);
      const Vec3 c{0.5 * (a.x + b.x), 0.5 * (a.y + b.y), top_z - kPlateDepth * 0.5};
      const double len = std::hypot(b.x - a.x, b.y - a.y);
      s.bones.push_back(bone(Solid::round_box(c, u, v,
                                              {len * 0.5 + 2, kPlateHalf - kPlateRound,
                                               kPlateDepth * 0.5 - kPlateRound},
                                              kPlateRound),
                             2.0, phantom_hu::kCancellous));
    }
    end_group(s);
    s.landmarks.push_back({sx > 0 ? "iliac_crest_top_left" : "iliac_crest_top_right", crest[top] + Vec3{0, 0, kCrestR}});
  }
}

// bowel: colon and small-bowel loops inside the abdominal cavity; gas above the level
void add_bowel(PhantomShapes& s) {
  struct Loop {
    Vec3 a, b;
    double r;
    double gas_fraction;  // 0 = fluid only; else the gas fills the top (posterior) part
  };
  const Loop loops[] = {
      {{-60, -50, 70}, {60, -50, 70}, 15, 0.7},     // transverse colon
      {{-85, -30, -60}, {-85, -30, 40}, 17, 0.6},   // ascending colon (patient's right)
      {{88, -20, -50}, {88, -20, 50}, 14, 0.5},     // descending colon (patient's left)
      {{-30, -70, -30}, {20, -65, -20}, 12, 0.4},   // small bowel
      {{10, -40, -60}, {40, -65, -50}, 11, 0.0},
      {{-40, -45, 20}, {-10, -70, 35}, 11, 0.5},
      {{30, -35, 10}, {60, -55, -10}, 12, 0.0},
  };
  constexpr double kWall = 3;
  for (const Loop& l : loops) {
    BowelLoop b;
    b.outer = Solid::capsule(l.a, l.b, l.r);
    b.lumen = Solid::capsule(l.a, l.b, l.r - kWall);
    // gas above a horizontal level: the lumen's top y minus the gas fraction of its diameter
    const double top_y = std::max(l.a.y, l.b.y) + (l.r - kWall);
    b.gas_level_y = l.gas_fraction > 0 ? top_y - l.gas_fraction * 2 * (l.r - kWall) : kInf;
    s.loops.push_back(b);
  }
}

std::shared_ptr<PhantomShapes> build_shapes() {
  auto s = std::make_shared<PhantomShapes>();
  for (const Level& l : kLevels) add_vertebra(*s, l);
  add_discs(*s);
  add_ribs(*s);
  add_iliac_wings(*s);
  // every bone belongs to one group (bone_signed_distance_mm relies on it)
  if (s->groups.empty() || s->groups.back().end != s->bones.size() || s->groups.size() > 64)
    throw Error("phantom: internal error: the bone groups do not cover the bones");
  add_bowel(*s);
  return s;
}

// z-invariant tissue of the column at (x, y): air, table, skin, fat, muscle, cavity, psoas, canal
double column_hu(double x, double y, double h) {
  namespace hu = phantom_hu;
  const auto ramp = [h](double d) { return clamp01(0.5 - d / h); };
  double v = hu::kAir;
  // CT table: carbon shell with a foam core
  const double d_table = round_rect_sdf(x, y - kTableY, kTableHalfX, kTableHalfY, kTableRound);
  if (d_table < h) {
    v = lerp(v, hu::kTableShell, ramp(d_table));
    const double d_core =
        round_rect_sdf(x, y - kTableY, kTableHalfX - kTableShell, kTableHalfY - kTableShell, kTableRound - 2);
    v = lerp(v, hu::kTableCore, ramp(d_core));
  }
  const double d_skin = ellipse_sdf(x, y, kBodyA, kBodyB);
  if (d_skin >= h) return v;
  v = lerp(v, hu::kSkin, ramp(d_skin));
  v = lerp(v, hu::kFat, ramp(d_skin + kSkinThickness));
  const double d_fat = ellipse_sdf(x, y, kFatA, kFatB);
  if (d_fat >= h) return v;
  v = lerp(v, hu::kMuscle, ramp(d_fat));
  v = lerp(v, hu::kViscera, ramp(ellipse_sdf(x, y - kCavityY, kCavityA, kCavityB)));
  const double d_psoas = std::min(ellipse_sdf(x - kPsoasX, y - kPsoasY, kPsoasA, kPsoasB),
                                  ellipse_sdf(x + kPsoasX, y - kPsoasY, kPsoasA, kPsoasB));
  v = lerp(v, hu::kMuscle, ramp(d_psoas));
  v = lerp(v, hu::kCanal, ramp(std::hypot(x, y - kCanalY) - kCanalR));
  return v;
}

// texture in [-1, 1) from a fixed hash of the voxel index (splitmix64)
double texture(std::uint64_t index) {
  std::uint64_t z = index + 0x9E3779B97F4A7C15ull;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  z ^= z >> 31;
  return double(z >> 11) * (2.0 / 9007199254740992.0) - 1.0;
}

}  // namespace

/// Rasterizes the shapes slice by slice (friend of PhantomGeometry).
struct PhantomRasterizer {
  static void run(const PhantomGeometry& geometry, Volume<float>& out);
};

void PhantomRasterizer::run(const PhantomGeometry& geometry, Volume<float>& out) {
  namespace hu = phantom_hu;
  const PhantomShapes& s = *geometry.shapes_;
  const Grid& g = out.grid;
  const double h = g.spacing_mm.x;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  const auto ramp = [h](double d) { return clamp01(0.5 - d / h); };

  // the z-invariant columns, once
  std::vector<float> columns(std::size_t(nx) * ny);
  for (int j = 0; j < ny; ++j)
    for (int i = 0; i < nx; ++i) {
      const Vec3 p = g.to_physical({double(i), double(j), 0});
      columns[std::size_t(j) * nx + i] = float(column_hu(p.x, p.y, h));
    }

  // slices in parallel; every voxel depends on its index only, so the result is the
  // same for any number of threads
  const auto work = [&](int k0, int step) {
    std::vector<const Solid*> bones_z, discs_z, bones_y, discs_y;
    std::vector<const BowelLoop*> loops_z, loops_y;
    for (int k = k0; k < nz; k += step) {
      const double z = g.origin_mm.z + k * h;
      // shapes whose box (widened by a voxel) meets this slice
      const auto in_z = [&](const Aabb& b) { return z >= b.lo.z - h && z <= b.hi.z + h; };
      bones_z.clear();
      discs_z.clear();
      loops_z.clear();
      for (const Solid& b : s.bones) if (in_z(b.box)) bones_z.push_back(&b);
      for (const Solid& d : s.discs) if (in_z(d.box)) discs_z.push_back(&d);
      for (const BowelLoop& l : s.loops) if (in_z(l.outer.box)) loops_z.push_back(&l);
      for (int j = 0; j < ny; ++j) {
        const double y = g.origin_mm.y + j * h;
        const auto in_y = [&](const Aabb& b) { return y >= b.lo.y - h && y <= b.hi.y + h; };
        bones_y.clear();
        discs_y.clear();
        loops_y.clear();
        for (const Solid* b : bones_z) if (in_y(b->box)) bones_y.push_back(b);
        for (const Solid* d : discs_z) if (in_y(d->box)) discs_y.push_back(d);
        for (const BowelLoop* l : loops_z) if (in_y(l->outer.box)) loops_y.push_back(l);
        for (int i = 0; i < nx; ++i) {
          const Vec3 p{g.origin_mm.x + i * h, y, z};
          double v = columns[std::size_t(j) * nx + i];
          // bowel loops: wall, then fluid with gas above the level
          for (const BowelLoop* l : loops_y) {
            const double d_out = l->outer.sdf(p);
            if (d_out >= 0.5 * h) continue;
            v = lerp(v, hu::kBowelWall, ramp(d_out));
            const double content = lerp(hu::kBowelFluid, hu::kAir, ramp(l->gas_level_y - p.y));
            v = lerp(v, content, ramp(l->lumen.sdf(p)));
          }
          // discs
          for (const Solid* d : discs_y) {
            if (p.x < d->box.lo.x - h || p.x > d->box.hi.x + h) continue;
            const double dd = d->sdf(p);
            if (dd < 0.5 * h) v = lerp(v, d->interior_hu, ramp(dd));
          }
          // bone: the union's distance, cortex and the interior of the deepest shape
          double best = kInf;
          const Solid* deepest = nullptr;
          for (const Solid* b : bones_y) {
            if (p.x < b->box.lo.x - h || p.x > b->box.hi.x + h) continue;
            const double db = b->sdf(p);
            if (db < best) {
              best = db;
              deepest = b;
            }
          }
          if (deepest && best < 0.5 * h) {
            v = lerp(v, hu::kCortical, ramp(best));
            v = lerp(v, deepest->interior_hu, ramp(best + deepest->cortex_mm));
          }
          // texture on tissue, fading out towards pure air and gas
          const std::size_t idx = g.index(i, j, k);
          v += hu::kTextureAmplitude * texture(idx) * clamp01((v - hu::kAir) / 100.0);
          out.data[idx] = float(v);
        }
      }
    }
  };
  const int threads = int(std::clamp(std::thread::hardware_concurrency(), 1u, 8u));
  std::vector<std::thread> pool;
  for (int t = 1; t < threads; ++t) pool.emplace_back(work, t, threads);
  work(0, threads);
  for (auto& t : pool) t.join();
}

PhantomGeometry::PhantomGeometry() {
  static const std::shared_ptr<const PhantomShapes> shared = build_shapes();
  shapes_ = shared;
}

double PhantomGeometry::skin_signed_distance_mm(const Vec3& p_mm) const {
  return ellipse_sdf(p_mm.x, p_mm.y, kBodyA, kBodyB);
}

double PhantomGeometry::bone_signed_distance_mm(const Vec3& p_mm) const {
  // groups nearest first, so that farther groups are skipped by their boxes
  const auto& groups = shapes_->groups;
  constexpr std::size_t kMaxGroups = 64;
  std::pair<double, std::size_t> order[kMaxGroups];
  const std::size_t n = std::min(groups.size(), kMaxGroups);
  for (std::size_t g = 0; g < n; ++g) order[g] = {groups[g].box.distance(p_mm), g};
  std::sort(order, order + n);
  double best = kInf;
  for (std::size_t o = 0; o < n && order[o].first < best; ++o) {
    const PhantomShapes::Group& g = groups[order[o].second];
    for (std::size_t i = g.begin; i < g.end; ++i)
      if (shapes_->bones[i].box.distance(p_mm) < best) best = std::min(best, shapes_->bones[i].sdf(p_mm));
  }
  return best;
}

bool PhantomGeometry::in_table(const Vec3& p_mm) const {
  return round_rect_sdf(p_mm.x, p_mm.y - kTableY, kTableHalfX, kTableHalfY, kTableRound) < 0;
}

bool PhantomGeometry::in_bowel_gas(const Vec3& p_mm) const {
  for (const BowelLoop& l : shapes_->loops)
    if (p_mm.y > l.gas_level_y && l.lumen.sdf(p_mm) < 0) return true;
  return false;
}

const std::vector<PhantomLandmark>& PhantomGeometry::landmarks() const { return shapes_->landmarks; }

Vec3 PhantomGeometry::landmark(const std::string& name) const {
  for (const PhantomLandmark& l : shapes_->landmarks)
    if (l.name == name) return l.p_mm;
  throw Error("phantom: no landmark called '" + name + "'");
}

Grid phantom_grid(double voxel_mm) {
  if (!(voxel_mm >= 0.25 && voxel_mm <= 4.0)) {
    std::ostringstream msg;
    msg << "phantom.voxel_mm = " << voxel_mm << ": must be between 0.25 and 4 mm";
    throw Error(msg.str());
  }
  Grid g;
  g.spacing_mm = {voxel_mm, voxel_mm, voxel_mm};
  g.origin_mm = kOrigin;
  // the small epsilon keeps exact divisions (340 / 0.5) from losing a voxel to rounding
  g.size = {int(std::floor(kExtent.x / voxel_mm + 1e-9)) + 1, int(std::floor(kExtent.y / voxel_mm + 1e-9)) + 1,
            int(std::floor(kExtent.z / voxel_mm + 1e-9)) + 1};
  return g;
}

PhantomCt make_phantom(double voxel_mm) {
  PhantomCt ct;
  ct.hu = Volume<float>(phantom_grid(voxel_mm), phantom_hu::kAir);
  PhantomRasterizer::run(ct.geometry, ct.hu);
  return ct;
}

}  // namespace palpsim
