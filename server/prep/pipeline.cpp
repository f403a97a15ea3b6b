#include "prep/pipeline.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>
#include <utility>
#include <sstream>
#include <vector>

#include "core/error.h"
#include "prep/contrast.h"
#include "prep/distance.h"
#include "prep/flood.h"

namespace palpsim {

double patient_spacing_mm(const Grid& input, double requested_mm) {
  if (requested_mm > 0) return requested_mm;
  const double smallest = std::min({input.spacing_mm.x, input.spacing_mm.y, input.spacing_mm.z});
  return std::clamp(smallest, 0.5, 2.0);
}

Grid isotropic_grid(const Grid& input, double spacing_mm) {
  Grid g = input;  // same origin (voxel 0's centre) and direction
  g.spacing_mm = {spacing_mm, spacing_mm, spacing_mm};
  const auto cover = [&](int n, double sp) {
    // voxel centres from 0 to the last input centre, with a tolerance for rounding
    return int(std::floor((n - 1) * sp / spacing_mm + 1e-6)) + 1;
  };
  g.size = {cover(input.size.x, input.spacing_mm.x), cover(input.size.y, input.spacing_mm.y),
            cover(input.size.z, input.spacing_mm.z)};
  return g;
}

std::size_t estimate_prep_bytes(const Grid& input, const Grid& patient) {
  // input: ITK's float buffer and our copy; patient: intensity 4, body 1, bone 1,
  // A 4, B 4, F 4, grad F 12 bytes, plus about 4 bytes of labels and masks while
  // the masks are built
  return input.count() * 8 + patient.count() * 34;
}

Volume<float> resample_linear(const Volume<float>& in, const Grid& out, float outside_value, int threads) {
  Volume<float> r(out);
  const Grid& gi = in.grid;
  const int nx = gi.size.x, ny = gi.size.y, nz = gi.size.z;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;
  const double eps = 1e-4;  // voxels: accept rounding at the input's last centre
  parallel_for(std::size_t(out.size.y) * out.size.z, threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t row = b; row < e; ++row) {
      const int j = int(row % out.size.y), k = int(row / out.size.y);
      for (int i = 0; i < out.size.x; ++i) {
        const Vec3 c = gi.to_index(out.to_physical(Vec3{double(i), double(j), double(k)}));
        float& dst = r.data[out.index(i, j, k)];
        if (c.x < -eps || c.y < -eps || c.z < -eps || c.x > nx - 1 + eps || c.y > ny - 1 + eps ||
            c.z > nz - 1 + eps) {
          dst = outside_value;
          continue;
        }
        // trilinear weights with the upper corner clamped at the last voxel
        const int i0 = std::clamp(int(std::floor(c.x)), 0, nx - 1), j0 = std::clamp(int(std::floor(c.y)), 0, ny - 1),
                  k0 = std::clamp(int(std::floor(c.z)), 0, nz - 1);
        const int i1 = std::min(i0 + 1, nx - 1), j1 = std::min(j0 + 1, ny - 1), k1 = std::min(k0 + 1, nz - 1);
        const double fx = std::clamp(c.x - i0, 0.0, 1.0), fy = std::clamp(c.y - j0, 0.0, 1.0),
                     fz = std::clamp(c.z - k0, 0.0, 1.0);
        const float* d = in.data.data();
        const auto v = [&](int ii, int jj, int kk) { return double(d[kk * sxy + jj * sx + ii]); };
        const double c00 = v(i0, j0, k0) * (1 - fx) + v(i1, j0, k0) * fx;
        const double c10 = v(i0, j1, k0) * (1 - fx) + v(i1, j1, k0) * fx;
        const double c01 = v(i0, j0, k1) * (1 - fx) + v(i1, j0, k1) * fx;
        const double c11 = v(i0, j1, k1) * (1 - fx) + v(i1, j1, k1) * fx;
        dst = float((c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz);
      }
    }
  });
  return r;
}

int grid_axis_along(const Grid& g, int physical) {
  // column a of the direction is grid axis a in physical space
  int best = physical;
  double best_abs = -1;
  for (int a = 0; a < 3; ++a) {
    const double s = std::abs(g.direction[3 * physical + a]);
    if (s > best_abs) best_abs = s, best = a;
  }
  return best;
}

std::size_t count_nonzero(const Volume<std::uint8_t>& m) {
  return std::size_t(std::count_if(m.data.begin(), m.data.end(), [](std::uint8_t v) { return v != 0; }));
}

namespace {

// union-find over provisional labels
struct DisjointSet {
  std::vector<std::uint32_t> parent;
  std::uint32_t make() {
    parent.push_back(std::uint32_t(parent.size()));
    return parent.back();
  }
  std::uint32_t find(std::uint32_t a) {
    while (parent[a] != a) a = parent[a] = parent[parent[a]];
    return a;
  }
  void unite(std::uint32_t a, std::uint32_t b) {
    a = find(a), b = find(b);
    if (a != b) parent[std::max(a, b)] = std::min(a, b);
  }
};

// 6-connected components of the voxels where (mask != 0) == value: labels 1..n
// (0 elsewhere), sizes[l] voxels and border[l] whether it touches the volume's border
struct Components {
  std::vector<std::uint32_t> label;
  std::vector<std::size_t> size;
  std::vector<bool> border;
};

Components label_components(const Volume<std::uint8_t>& mask, bool value) {
  const Grid& g = mask.grid;
  const int nx = g.size.x, ny = g.size.y, nz = g.size.z;
  const std::size_t sx = std::size_t(nx), sxy = std::size_t(nx) * ny;
  Components c;
  c.label.assign(g.count(), 0);
  DisjointSet ds;
  ds.make();  // label 0 = background
  // pass 1: provisional labels from the -i, -j, -k neighbours
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const std::size_t idx = k * sxy + j * sx + i;
        if ((mask.data[idx] != 0) != value) continue;
        const std::uint32_t a = i > 0 ? c.label[idx - 1] : 0, b = j > 0 ? c.label[idx - sx] : 0,
                            d = k > 0 ? c.label[idx - sxy] : 0;
        std::uint32_t l = 0;
        for (std::uint32_t n : {a, b, d})
          if (n && (!l || n < l)) l = n;
        if (!l) l = ds.make();
        for (std::uint32_t n : {a, b, d})
          if (n && n != l) ds.unite(l, n);
        c.label[idx] = l;
      }
  // pass 2: resolve to dense final labels, count sizes, note border contact
  std::vector<std::uint32_t> dense(ds.parent.size(), 0);
  std::uint32_t n = 0;
  for (std::uint32_t l = 1; l < ds.parent.size(); ++l) {
    const std::uint32_t r = ds.find(l);
    if (r == l) dense[l] = ++n;
  }
  for (std::uint32_t l = 1; l < ds.parent.size(); ++l) dense[l] = dense[ds.find(l)];
  c.size.assign(n + 1, 0);
  c.border.assign(n + 1, false);
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i) {
        const std::size_t idx = k * sxy + j * sx + i;
        std::uint32_t& l = c.label[idx];
        if (!l) continue;
        l = dense[l];
        ++c.size[l];
        if (i == 0 || j == 0 || k == 0 || i == nx - 1 || j == ny - 1 || k == nz - 1) c.border[l] = true;
      }
  return c;
}

}  // namespace

int remove_small_components(Volume<std::uint8_t>& mask, std::size_t min_voxels) {
  const Components c = label_components(mask, true);
  int kept = 0;
  for (std::size_t l = 1; l < c.size.size(); ++l) kept += c.size[l] >= min_voxels;
  for (std::size_t i = 0; i < mask.data.size(); ++i)
    if (c.label[i] && c.size[c.label[i]] < min_voxels) mask.data[i] = 0;
  return kept;
}

std::uint32_t component_labels(const Volume<std::uint8_t>& mask, std::vector<std::uint32_t>& labels) {
  Components c = label_components(mask, true);
  labels = std::move(c.label);
  return std::uint32_t(c.size.size() - 1);
}

std::vector<std::size_t> component_sizes(const Volume<std::uint8_t>& mask) {
  std::vector<std::size_t> sizes = label_components(mask, true).size;
  if (!sizes.empty()) sizes.erase(sizes.begin());  // label 0: the background
  std::sort(sizes.rbegin(), sizes.rend());
  return sizes;
}

void fill_holes_3d(Volume<std::uint8_t>& mask) {
  const Components c = label_components(mask, false);
  for (std::size_t i = 0; i < mask.data.size(); ++i)
    if (c.label[i] && !c.border[c.label[i]]) mask.data[i] = 1;
}

void fill_holes_per_slice(Volume<std::uint8_t>& mask, int axis, std::size_t max_hole_pixels,
                          const HoleFilter& accept) {
  const Grid& g = mask.grid;
  const int n[3] = {g.size.x, g.size.y, g.size.z};
  const std::size_t stride[3] = {1, std::size_t(g.size.x), std::size_t(g.size.x) * g.size.y};
  const int u = axis == 0 ? 1 : 0, v = axis == 2 ? 1 : 2;  // the slice's two in-plane axes
  const int nu = n[u], nv = n[v];
  parallel_for(std::size_t(n[axis]), 0, [&](std::size_t b, std::size_t e) {
    std::vector<std::uint8_t> seen(std::size_t(nu) * nv);
    std::vector<int> queue;
    std::vector<std::size_t> hole;
    queue.reserve(std::size_t(nu) * nv);
    for (std::size_t s = b; s < e; ++s) {
      const std::size_t base = s * stride[axis];
      const auto at = [&](int a, int c) -> std::uint8_t& { return mask.data[base + a * stride[u] + c * stride[v]]; };
      std::fill(seen.begin(), seen.end(), 0);
      queue.clear();
      // seed: background pixels on the slice's border
      const auto seed = [&](int a, int c) {
        const int p = c * nu + a;
        if (!seen[p] && !at(a, c)) seen[p] = 1, queue.push_back(p);
      };
      for (int a = 0; a < nu; ++a) seed(a, 0), seed(a, nv - 1);
      for (int c = 0; c < nv; ++c) seed(0, c), seed(nu - 1, c);
      // flood the background reachable from the border (4-connected)
      flood_4(queue, 0, nu, nv, seed);
      // everything else in the slice is inside: fill each hole up to the size limit
      for (int c0 = 0; c0 < nv; ++c0)
        for (int a0 = 0; a0 < nu; ++a0) {
          if (seen[c0 * nu + a0] || at(a0, c0)) continue;
          const std::size_t first = queue.size();
          seed(a0, c0);
          flood_4(queue, first, nu, nv, seed);
          if (queue.size() - first > max_hole_pixels) continue;
          if (accept) {
            hole.clear();
            for (std::size_t q = first; q < queue.size(); ++q)
              hole.push_back(base + (queue[q] % nu) * stride[u] + (queue[q] / nu) * stride[v]);
            if (!accept(hole)) continue;
          }
          for (std::size_t q = first; q < queue.size(); ++q) at(queue[q] % nu, queue[q] / nu) = 1;
        }
    }
  });
}

Volume<std::uint8_t> body_mask(const Volume<float>& image, double air_threshold, double opening_mm,
                               double min_part_ml, int threads) {
  const Grid& g = image.grid;
  const double h = std::min({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
  const double voxel_ml = g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z / 1000.0;

  // tissue candidates: not air
  Volume<std::uint8_t> cand(g);
  parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) cand.data[i] = image.data[i] >= air_threshold;
  });

  // erode by the opening radius: the thick core of the body; thin shells vanish
  Volume<std::uint8_t> core(g);
  {
    const Volume<float> d2 = squared_distance_mm2(cand, false, threads);
    const float r2 = float(opening_mm * opening_mm);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) core.data[i] = d2.data[i] > r2;
    });
  }

  // keep the largest core part and every part of at least min_part_ml (arms)
  {
    const Components c = label_components(core, true);
    std::size_t largest = 0;
    for (std::size_t l = 1; l < c.size.size(); ++l) largest = std::max(largest, c.size[l]);
    const std::size_t min_voxels = std::size_t(std::ceil(min_part_ml / voxel_ml));
    for (std::size_t i = 0; i < core.data.size(); ++i) {
      const std::uint32_t l = c.label[i];
      if (l && c.size[l] != largest && c.size[l] < min_voxels) core.data[i] = 0;
    }
  }

  // dilate back (the opening) plus 1.5 voxels, within the candidates
  Volume<std::uint8_t> body(g);
  {
    const Volume<float> d2 = squared_distance_mm2(core, true, threads);
    const double reach = opening_mm + 1.5 * h;
    const float r2 = float(reach * reach);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) body.data[i] = cand.data[i] && d2.data[i] <= r2;
    });
  }

  // gas enclosed within an axial slice is inside (bowel, lungs, cut airways)
  fill_holes_per_slice(body, axial_axis(g));
  return body;
}

namespace {

// morphological closing with a ball of radius r_mm (dilate, then erode; both exact
// through distance maps); voxels outside the volume count as neither
Volume<std::uint8_t> closing(const Volume<std::uint8_t>& m, double r_mm, int threads) {
  const Grid& g = m.grid;
  if (r_mm <= 0 || count_nonzero(m) == 0) return m;
  const float r2 = float(r_mm * r_mm);
  Volume<std::uint8_t> dilated(g);
  {
    const Volume<float> d2 = squared_distance_mm2(m, true, threads);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) dilated.data[i] = d2.data[i] <= r2;
    });
  }
  const Volume<float> d2 = squared_distance_mm2(dilated, false, threads);
  Volume<std::uint8_t> closed(g);
  parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) closed.data[i] = m.data[i] || d2.data[i] > r2;
  });
  return closed;
}

}  // namespace

double cancellous_level(const PrepSettings& prep) {
  return prep.air_threshold + 0.8 * (prep.bone_threshold - prep.air_threshold);
}

namespace {

// the sub-volume [lo, lo + size) of v, on a grid placed where it lies in v's
template <typename T>
Volume<T> crop(const Volume<T>& v, Vec3i lo, Vec3i size) {
  Grid g = v.grid;
  g.origin_mm = v.grid.to_physical(Vec3{double(lo.x), double(lo.y), double(lo.z)});
  g.size = size;
  Volume<T> c(g);
  for (int k = 0; k < size.z; ++k)
    for (int j = 0; j < size.y; ++j) {
      const T* src = &v.data[v.grid.index(lo.x, lo.y + j, lo.z + k)];
      std::copy(src, src + size.x, &c.data[g.index(0, j, k)]);
    }
  return c;
}

// the body voxels at or above t.thin_seed that are no thin seed: within kThinSeedClearMm
// of a contrast-filled region (find_contrast_regions before there is a bone mask or a
// column), or within sqrt(2) kThinSeedHalfWidthMm and a voxel of a voxel of theirs
// farther than kThinSeedHalfWidthMm from any darker one (a thick bright part: a vessel's
// lumen)
Volume<std::uint8_t> not_thin_seeds(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                    const BoneThresholds& t, int threads) {
  const Grid& g = image.grid;
  const double h = std::max({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
  Volume<std::uint8_t> out(g, 0);
  const auto near = [&](const Volume<std::uint8_t>& m, double r_mm) {
    const Volume<float> d2 = squared_distance_mm2(m, true, threads);
    const float r2 = float(r_mm * r_mm);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) out.data[i] |= d2.data[i] <= r2;
    });
  };
  Volume<std::uint8_t> regions;
  if (!find_contrast_regions(image, body, Volume<std::uint8_t>(g, 0), t, SpineColumn{}, &regions, threads).empty())
    near(regions, kThinSeedClearMm);
  Volume<std::uint8_t> core(g);
  parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) core.data[i] = body.data[i] && image.data[i] >= t.thin_seed;
  });
  {
    const Volume<float> d2 = squared_distance_mm2(core, false, threads);
    const float r2 = float(kThinSeedHalfWidthMm * kThinSeedHalfWidthMm);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) core.data[i] = d2.data[i] > r2;
    });
  }
  // the core's reach: sqrt(2) half widths (a square lumen's corners) and a voxel
  if (count_nonzero(core) > 0) near(core, std::sqrt(2.0) * kThinSeedHalfWidthMm + h);
  return out;
}

// the hysteresis on a volume already cropped to the seeds and the growth's reach:
// candidates (body voxels at or above t.low) within t.grow_mm of a seed (at or above
// t.high, or at or above t.thin_seed in thin ridges apart from contrast), in 6-connected
// components holding a seed
Volume<std::uint8_t> hysteresis(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                const BoneThresholds& t, int threads) {
  const Grid& g = image.grid;
  Volume<std::uint8_t> raw(g), seed(g);
  parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      raw.data[i] = body.data[i] && image.data[i] >= t.low;
      seed.data[i] = raw.data[i] && image.data[i] >= t.high;
    }
  });
  if (!(t.high > t.low)) return raw;
  // lower seeds in thin ridges (a rib's cortex blurred by partial volume), not in thick
  // bright parts or beside contrast-filled regions
  if (t.thin_seed < t.high) {
    const Volume<std::uint8_t> excluded = not_thin_seeds(image, body, t, threads);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i)
        seed.data[i] |= raw.data[i] && image.data[i] >= t.thin_seed && !excluded.data[i];
    });
  }
  if (t.grow_mm > 0) {
    const Volume<float> d2 = squared_distance_mm2(seed, true, threads);
    const float r2 = float(t.grow_mm * t.grow_mm);
    parallel_for(g.count(), threads, [&](std::size_t b, std::size_t e) {
      for (std::size_t i = b; i < e; ++i) raw.data[i] &= d2.data[i] <= r2;
    });
  }
  const Components c = label_components(raw, true);
  std::vector<std::uint8_t> seeded(c.size.size(), 0);
  for (std::size_t i = 0; i < raw.data.size(); ++i)
    if (seed.data[i]) seeded[c.label[i]] = 1;
  for (std::size_t i = 0; i < raw.data.size(); ++i) raw.data[i] = c.label[i] && seeded[c.label[i]];
  return raw;
}

// the rest of bone_mask on a volume already cropped to the hysteresis result `raw`
// and a margin beyond every closing's reach
Volume<std::uint8_t> bone_mask_cropped(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                       const Volume<std::uint8_t>& raw, const BoneThresholds& t,
                                       const PrepSettings& prep, double fill_closing_mm, int threads) {
  const Grid& g = image.grid;
  // closing joins nearby bone (a blurred cortex, thin processes)
  Volume<std::uint8_t> bone = closing(raw, prep.bone_closing_mm, threads);
  for (std::size_t i = 0; i < bone.data.size(); ++i) bone.data[i] &= body.data[i];

  // cavities enclosed by bone are bone (cancellous interior, marrow): enclosed in
  // 3D, or (a cortex blurred by thick slices has gaps) enclosed within a slice of
  // any orientation after a wider closing, no larger than kMaxBoneHoleMm2, and
  // with a mean value at least the cancellous level (the spinal canal, the discs,
  // the pelvis and the thorax are enclosed too, but hold CSF, soft tissue or air)
  if (prep.bone_fill_holes) {
    fill_holes_3d(bone);
    const double wide_mm = std::max(fill_closing_mm, prep.bone_closing_mm);
    const Volume<std::uint8_t> wide = wide_mm > prep.bone_closing_mm ? closing(raw, wide_mm, threads) : bone;
    const std::size_t max_pixels = std::size_t(kMaxBoneHoleMm2 / (g.spacing_mm.x * g.spacing_mm.x));
    const auto dense_from = [&](double level) -> HoleFilter {
      return [&image, level](const std::vector<std::size_t>& vox) {
        double sum = 0;
        for (std::size_t i : vox) sum += image.data[i];
        return sum / double(vox.size()) >= level;
      };
    };
    const HoleFilter dense = dense_from(t.cancellous), dense_axial = dense_from(t.cancellous_axial);
    const int axial = axial_axis(g);
    // soft tissue that an axial slice's cavity leaves open voxel by voxel (a disc)
    const auto disc = [&](std::size_t i) { return image.data[i] >= t.disc_lo && image.data[i] < t.disc_hi; };
    // two rounds: what one orientation fills can close a cavity in another
    Volume<std::uint8_t> cavity(g), grown = wide;
    for (int round = 0; round < 2; ++round) {
      for (int axis = 0; axis < 3; ++axis) {
        Volume<std::uint8_t> filled = grown;
        fill_holes_per_slice(filled, axis, max_pixels, axis == axial ? dense_axial : dense);
        for (std::size_t i = 0; i < cavity.data.size(); ++i)
          cavity.data[i] |= filled.data[i] && !wide.data[i] && !(axis == axial && disc(i));
      }
      for (std::size_t i = 0; i < cavity.data.size(); ++i) grown.data[i] = wide.data[i] | cavity.data[i];
    }
    {
      // enclosed in 3D by what the slices filled: but the disc voxels the axial fill left
      Volume<std::uint8_t> filled = grown;
      fill_holes_3d(filled);
      for (std::size_t i = 0; i < cavity.data.size(); ++i)
        cavity.data[i] |= filled.data[i] && !wide.data[i] && (grown.data[i] || !disc(i));
    }
    // the cavities, and the wide closing's voxels beside them (the gaps in their
    // cortex; not its bridges elsewhere, e.g. between spinous processes)
    if (count_nonzero(cavity) > 0) {
      const double reach = wide_mm + g.spacing_mm.x;
      const float r2 = float(reach * reach);
      const Volume<float> d2 = squared_distance_mm2(cavity, true, threads);
      for (std::size_t i = 0; i < bone.data.size(); ++i)
        if (body.data[i] && (cavity.data[i] || (wide.data[i] && d2.data[i] <= r2))) bone.data[i] = 1;
    }
  }

  // small components: vessels with contrast, calcifications, noise; not a piece
  // within kBonePieceGapMm of a larger one (a rib broken by partial volume)
  const double voxel_ml = g.spacing_mm.x * g.spacing_mm.y * g.spacing_mm.z / 1000.0;
  const std::size_t min_voxels = std::size_t(std::ceil(prep.bone_min_volume_ml / voxel_ml));
  std::vector<std::uint32_t> label;
  const std::uint32_t n = component_labels(bone, label);
  std::vector<std::size_t> size(n + 1, 0);
  for (std::uint32_t l : label) ++size[l];
  Volume<std::uint8_t> large(g);
  for (std::size_t i = 0; i < label.size(); ++i) large.data[i] = label[i] && size[label[i]] >= min_voxels;
  std::vector<std::uint8_t> keep(n + 1, 0);
  for (std::uint32_t l = 1; l <= n; ++l) keep[l] = size[l] >= min_voxels;
  if (count_nonzero(large) > 0) {
    const Volume<float> d2 = squared_distance_mm2(large, true, threads);
    const float r2 = float(kBonePieceGapMm * kBonePieceGapMm);
    for (std::size_t i = 0; i < label.size(); ++i)
      if (label[i] && d2.data[i] <= r2) keep[label[i]] = 1;
  }
  for (std::size_t i = 0; i < label.size(); ++i) bone.data[i] = keep[label[i]];
  return bone;
}

}  // namespace

BoneThresholds choose_bone_thresholds(const Volume<float>& image, const Volume<std::uint8_t>& body,
                                      const PrepSettings& prep) {
  BoneThresholds t;
  // an explicit threshold wins: a plain threshold, the cancellous level from it
  if (prep.bone_threshold_set) {
    t.low = t.high = t.thin_seed = prep.bone_threshold;
    t.cancellous = t.cancellous_axial = cancellous_level(prep);
    t.reason = "prep.bone_threshold set (scene or palpsim-prep --bone-threshold)";
    return t;
  }
  t.automatic = true;

  // histogram of the body's voxels, 1 HU bins from -1024 to 3071 HU
  constexpr int kLo = -1024, kBins = 4096;
  std::vector<double> hist(kBins, 0.0);
  std::size_t n = 0;
  for (std::size_t i = 0; i < image.data.size(); ++i) {
    if (!body.data[i]) continue;
    const float v = image.data[i];
    if (!(v >= kLo && v < kLo + kBins)) continue;
    hist[std::size_t(int(std::floor(v)) - kLo)] += 1;
    ++n;
  }
  if (n == 0) throw Error("choose_bone_thresholds: the body mask is empty or holds no value in -1024..3071 HU");

  // smoothed with a 21 HU box (integer-valued CTs leave every other bin empty after rescaling)
  std::vector<double> smooth(kBins, 0.0);
  {
    double run = 0;
    for (int b = 0; b < kBins + 10; ++b) {
      if (b < kBins) run += hist[std::size_t(b)];
      if (b >= 21) run -= hist[std::size_t(b - 21)];
      if (b >= 10 && b - 10 < kBins) smooth[std::size_t(b - 10)] = run / 21.0;
    }
  }

  // the soft-tissue peak: the mode between -50 and 150 HU (fat lies below, bone above)
  int mode = -50 - kLo;
  for (int b = -50 - kLo; b <= 150 - kLo; ++b)
    if (smooth[std::size_t(b)] > smooth[std::size_t(mode)]) mode = b;
  const double peak = smooth[std::size_t(mode)];
  std::ostringstream why;
  if (peak < 1e-3 * double(n) / 21.0) {
    // no soft tissue to speak of (a phantom of bone in air, a non-CT image): the default
    t.low = t.high = t.thin_seed = PrepSettings{}.bone_threshold;
    t.cancellous = t.cancellous_axial = cancellous_level(PrepSettings{});
    why << "automatic: the body's histogram has no soft-tissue peak between -50 and 150 HU, so the default "
        << t.low << " HU is used as a plain threshold";
    t.reason = why.str();
    return t;
  }
  // its spread: the upper half width at half height (the lower side mixes with fat)
  int up = mode;
  while (up + 1 < kBins && smooth[std::size_t(up)] >= 0.5 * peak) ++up;
  const double mu = mode + kLo, sigma = (up - mode) / 1.1774;
  t.soft_tissue_hu = mu;
  t.soft_tissue_sigma_hu = sigma;

  // low: 100 HU or 3 sigma above soft tissue, within the bounds; seeds twice as far
  // above soft tissue (cortical bone), thin seeds 1.5 times as far; cavities filled
  // from halfway up, within bounds
  t.low = std::clamp(mu + std::max(100.0, 3 * sigma), kAutoBoneLowMinHu, kAutoBoneLowMaxHu);
  t.high = std::max(kAutoBoneSeedMinHu, mu + 2 * (t.low - mu));
  t.thin_seed = std::min(t.high, mu + kThinSeedSpan * (t.low - mu));
  t.cancellous = std::clamp(mu + 0.5 * (t.low - mu), kAutoCancellousMinHu, kAutoCancellousMaxHu);
  t.cancellous_axial = t.cancellous - kAxialCancellousDropHu;
  t.disc_lo = mu - kDiscBandBelow * sigma;
  t.disc_hi = mu + kDiscBandAbove * sigma;
  t.grow_mm = kAutoBoneGrowMm;
  why << "automatic from the body's histogram: soft-tissue peak " << mu << " HU, spread " << std::lround(sigma)
      << " HU; bone from " << std::lround(t.low) << " HU (soft tissue + max(100, 3 spread), kept within "
      << kAutoBoneLowMinHu << ".." << kAutoBoneLowMaxHu << " HU) where joined within " << t.grow_mm
      << " mm to seeds from " << std::lround(t.high) << " HU (cortex), or from " << std::lround(t.thin_seed)
      << " HU in thin ridges away from contrast-filled regions (a rib's cortex blurred by partial volume); small "
      << "pieces within "
      << kBonePieceGapMm << " mm of larger bone kept; cavities enclosed by bone filled from a mean of "
      << std::lround(t.cancellous) << " HU (" << std::lround(t.cancellous_axial) << " HU in axial slices, their "
      << std::lround(t.disc_lo) << ".." << std::lround(t.disc_hi) << " HU voxels left open: discs)";
  t.reason = why.str();
  return t;
}

Volume<std::uint8_t> bone_mask(const Volume<float>& image, const Volume<std::uint8_t>& body,
                               const PrepSettings& prep, double fill_closing_mm, int threads) {
  return bone_mask(image, body, choose_bone_thresholds(image, body, prep), prep, fill_closing_mm, threads);
}

Volume<std::uint8_t> bone_mask(const Volume<float>& image, const Volume<std::uint8_t>& body,
                               const BoneThresholds& t, const PrepSettings& prep, double fill_closing_mm,
                               int threads) {
  const Grid& g = image.grid;
  Volume<std::uint8_t> bone(g);
  const double h_min = std::min({g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z});
  // the bounding box of the voxels where `pred` holds, grown by m voxels and clipped;
  // false when there is none
  const auto box = [&](auto&& pred, int m, Vec3i& lo, Vec3i& size) {
    Vec3i hi{-1, -1, -1};
    lo = {g.size.x, g.size.y, g.size.z};
    for (int k = 0; k < g.size.z; ++k)
      for (int j = 0; j < g.size.y; ++j)
        for (int i = 0; i < g.size.x; ++i) {
          if (!pred(g.index(i, j, k))) continue;
          lo = {std::min(lo.x, i), std::min(lo.y, j), std::min(lo.z, k)};
          hi = {std::max(hi.x, i), std::max(hi.y, j), std::max(hi.z, k)};
        }
    if (hi.x < 0) return false;
    lo = {std::max(lo.x - m, 0), std::max(lo.y - m, 0), std::max(lo.z - m, 0)};
    hi = {std::min(hi.x + m, g.size.x - 1), std::min(hi.y + m, g.size.y - 1), std::min(hi.z + m, g.size.z - 1)};
    size = {hi.x - lo.x + 1, hi.y - lo.y + 1, hi.z - lo.z + 1};
    return true;
  };
  // copies a cropped mask back into a whole-volume one at lo
  const auto paste = [&](const Volume<std::uint8_t>& part, Vec3i lo, Volume<std::uint8_t>& whole) {
    for (int k = 0; k < part.grid.size.z; ++k)
      for (int j = 0; j < part.grid.size.y; ++j)
        std::copy_n(&part.data[part.grid.index(0, j, k)], part.grid.size.x,
                    &whole.data[g.index(lo.x, lo.y + j, lo.z + k)]);
  };

  // stage 1, the hysteresis, on the seeds' box plus the growth's reach (every bone
  // voxel is joined to a seed; unlimited growth needs the whole volume)
  Vec3i lo, size;
  const bool unlimited = t.high > t.low && t.grow_mm <= 0;
  const int m1 = unlimited ? std::max({g.size.x, g.size.y, g.size.z}) : int(std::ceil(t.grow_mm / h_min)) + 2;
  const double seed_min = std::min(t.high, t.thin_seed);
  if (!box([&](std::size_t i) { return body.data[i] && image.data[i] >= seed_min; }, m1, lo, size)) return bone;
  Volume<std::uint8_t> raw(g);
  paste(hysteresis(crop(image, lo, size), crop(body, lo, size), t, threads), lo, raw);

  // stage 2 on the hysteresis result's box plus a margin beyond every closing's
  // reach: outside it nothing can become bone, and background at the box's edge is
  // connected to the volume's border exactly when it is in the whole volume, so the
  // result is the same as on the whole volume
  const double reach_mm = std::max(fill_closing_mm, prep.bone_closing_mm) + 2 * g.spacing_mm.x;
  if (!box([&](std::size_t i) { return raw.data[i] != 0; }, int(std::ceil(reach_mm / h_min)) + 2, lo, size))
    return bone;
  paste(bone_mask_cropped(crop(image, lo, size), crop(body, lo, size), crop(raw, lo, size), t, prep,
                          fill_closing_mm, threads),
        lo, bone);
  return bone;
}

Volume<float> force_image(const Patient& p, const ForceImageSettings& f, int threads) {
  Volume<float> F(p.grid);
  parallel_for(p.grid.count(), threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t i = b; i < e; ++i) {
      const double C = p.body.data[i] ? 1.0 : 0.0;
      const double A = p.dist_bone_mm.data[i];
      // A = +inf (no bone) makes the first term 0
      const double bone_term = std::isfinite(A) ? f.alpha * C / (f.beta + A) : 0.0;
      F.data[i] = float(bone_term + f.gamma * p.dist_skin_mm.data[i]);
    }
  });
  return F;
}

Volume<Vec3f> gradient_physical(const Volume<float>& f, int threads) {
  const Grid& g = f.grid;
  Volume<Vec3f> grad(g);
  const int n[3] = {g.size.x, g.size.y, g.size.z};
  const double h[3] = {g.spacing_mm.x, g.spacing_mm.y, g.spacing_mm.z};
  const std::size_t stride[3] = {1, std::size_t(g.size.x), std::size_t(g.size.x) * g.size.y};
  parallel_for(std::size_t(g.size.y) * g.size.z, threads, [&](std::size_t b, std::size_t e) {
    for (std::size_t row = b; row < e; ++row) {
      const int j = int(row % g.size.y), k = int(row / g.size.y);
      for (int i = 0; i < g.size.x; ++i) {
        const int ijk[3] = {i, j, k};
        const std::size_t idx = g.index(i, j, k);
        Vec3 ga;
        for (int a = 0; a < 3; ++a) {
          // central difference inside, one-sided at the border
          const bool lo = ijk[a] > 0, hi = ijk[a] < n[a] - 1;
          const double fm = lo ? f.data[idx - stride[a]] : f.data[idx];
          const double fp = hi ? f.data[idx + stride[a]] : f.data[idx];
          const int steps = int(lo) + int(hi);
          ga[a] = steps ? (fp - fm) / (steps * h[a]) : 0.0;
        }
        grad.data[idx] = Vec3f(g.axes_to_physical(ga));
      }
    }
  });
  return grad;
}

}  // namespace palpsim
