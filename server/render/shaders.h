// GLSL 4.50 sources of the frame renderer (frame_renderer.cpp). Every pass is one
// full-viewport triangle; fragment shaders work in image pixels with row 0 at the top
// (the framebuffer's texel row 0 is the image's top row, so readback needs no flip).
// Volumes are addressed by continuous patient voxel index (i, j, k), so the grid's
// direction matrix never reaches the shaders.
#pragma once

namespace palpsim::render::shaders {

/// Vertex shader of every pass: one triangle covering the viewport.
constexpr const char* kFullscreenVs = R"GLSL(
#version 450 core
void main() {
  // vertices (-1,-1), (3,-1), (-1,3): the triangle covers the whole viewport
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}
)GLSL";

/// Sampling of the session's volume, shared by the ray caster and the slices: J from the
/// overlay inside the VOI box (air where the undeformed body mask is 0), the CT elsewhere.
/// AIR_HU, SHELL_MAX_HU, SHELL_MASK and OVERLAY are defined before it
/// (frame_renderer.cpp): programs for undeformed sessions (OVERLAY 0) leave the overlay
/// out entirely, since a software rasteriser pays for a branch even where none takes it.
constexpr const char* kSampleGlsl = R"GLSL(
layout(binding = 0) uniform sampler3D u_ct;       // CT (HU), air outside the body mask
layout(binding = 1) uniform sampler3D u_overlay;  // J: texel (i, j, k) = VOI voxel (i, j, k)
layout(binding = 2) uniform sampler3D u_body;     // mask class: 1 body, 128/255 shell, 0 outside
uniform vec3 u_grid_size;          // patient grid (voxels)
uniform bool u_overlay_on;         // the session is deformed: J on the VOI box
uniform vec3 u_voi_lo;             // first VOI voxel (patient index)
uniform vec3 u_voi_size;           // VOI extent (voxels)
uniform vec3 u_overlay_tex_size;   // overlay texture extent (voxels, max_voi)
const float kAirHu = AIR_HU;            // outside the body (frame_renderer.cpp defines these)
const float kShellMaxHu = SHELL_MAX_HU; // the cap of the shell around the body
const float kShellMask = SHELL_MASK;    // the shell's mask class
// J's cap (HU) at a filtered mask class m: air outside, kShellMaxHu on the shell, none
// in the body; linear between, so a deformed surface stays smooth
float cap_hu(float m) {
  return m < kShellMask ? mix(kAirHu, kShellMaxHu, m / kShellMask)
                        : mix(kShellMaxHu, 4096.0, (m - kShellMask) / (1.0 - kShellMask));
}

// true inside the session's VOI box (with the overlay on), grown by `margin` voxels
bool in_voi(vec3 p, float margin) {
#if OVERLAY
  vec3 q = p - u_voi_lo;
  return u_overlay_on && all(greaterThanEqual(q, vec3(-0.5 - margin))) &&
         all(lessThan(q, u_voi_size - 0.5 + margin));
#else
  return false;
#endif
}

// intensity (HU) at the continuous patient voxel index p
float sample_hu(vec3 p) {
#if OVERLAY
  if (in_voi(p, 0.0)) {
    // J inside the box, never filtered with texels beyond it; masked like the CT by
    // the undeformed body mask
    vec3 qc = clamp(p - u_voi_lo, vec3(0.0), u_voi_size - 1.0);
    float j = texture(u_overlay, (qc + 0.5) / u_overlay_tex_size).r;
    return min(j, cap_hu(texture(u_body, (p + 0.5) / u_grid_size).r));
  }
#endif
  return texture(u_ct, (p + 0.5) / u_grid_size).r;
}
)GLSL";

/// The 3D view: perspective rays in voxel-index space, clipped to the body's bounding
/// box, front-to-back compositing through the pre-integrated transfer function with
/// gradient shading, early termination; the tip and proxy spheres hit analytically so
/// they sit at their true depth in the volume (a faint ghost where tissue hides them).
///
/// The march composites unshaded steps and stops at the next step that needs shading (a
/// surface, or an interface the ray crosses); that step is shaded once, outside the
/// march loop, and the march goes on. Software rasterisers (llvmpipe) run every branch
/// of a loop body for all pixels of a SIMD group, so nothing costly may sit inside it.
constexpr const char* kRaycastFs = R"GLSL(
layout(binding = 3) uniform sampler2D u_tf;      // (front, back) HU -> premultiplied RGB, opacity
layout(binding = 4) uniform sampler3D u_blocks;  // per block: the largest HU in it and one voxel around
uniform vec4 u_viewport;    // x0, y0 (row of the view's top), width, height (pixels)
uniform vec3 u_eye;         // camera (voxel index)
uniform vec3 u_fwd;         // view direction (voxel index per unit ray length)
uniform vec3 u_right;       // screen right at the frame edge: fwd + right reaches it
uniform vec3 u_up;          // screen up at the frame edge
uniform vec3 u_box_lo;      // the body's bounding box (voxel index)
uniform vec3 u_box_hi;
uniform vec3 u_spacing;     // mm per voxel along i, j, k
uniform vec3 u_light;       // towards the light, grid axes (unit)
uniform float u_step;       // ray step (voxel)
uniform int u_max_steps;    // most steps of one ray (the box's diagonal in steps, and then some)
uniform float u_block_vox;  // block edge (voxel)
uniform vec3 u_block_count; // blocks per axis
uniform float u_faint_hu;   // intensities below this are faint in the preset (HU)
uniform vec2 u_tf_map;      // HU -> table coordinate: hu * x + y
uniform float u_surface_hu; // where the preset's opaque surfaces lie (HU)
uniform float u_shade_alpha;    // steps at least this opaque are shaded
uniform float u_interface_hu;   // and steps whose intensity changes this much (HU), if not faint
uniform vec2 u_grad_ramp;   // gradient magnitudes (HU/mm) from no shading to full shading
uniform vec4 u_marker[2];   // xyz: sphere centre (voxel index), w: radius (mm), 0 = none
uniform vec3 u_marker_color[2];
uniform vec3 u_bg_top;      // background at the top and bottom of the view
uniform vec3 u_bg_bottom;

const float kOpaque = 0.97;      // early ray termination
const float kShadedMinAlpha = 0.004;  // fainter steps are never shaded

// distance along the ray (voxel) to the marker sphere's front, or 1e30
float sphere_hit(vec3 o, vec3 d, vec4 m) {
  if (m.w <= 0.0) return 1e30;
  vec3 e = (o - m.xyz) * u_spacing, dd = d * u_spacing;  // in mm along the grid axes
  float a = dot(dd, dd), b = dot(e, dd), c = dot(e, e) - m.w * m.w;
  float disc = b * b - a * c;
  if (disc < 0.0) return 1e30;
  float t = (-b - sqrt(disc)) / a;
  return t > 0.0 ? t : 1e30;
}

// Gradient (HU/voxel along i, j, k) of the intensity box-filtered over one voxel: its
// central differences across two voxels, each the mean of four samples half a voxel off
// the axis. Edges then span about three voxels, so a sharp (one-voxel) CT edge neither
// saturates the differences nor shows trilinear facets; the same for CT and J.
vec3 gradient(vec3 p) {
  vec3 g = vec3(0.0);
  for (int n = 0; n < 4; ++n) {
    vec2 o = vec2((n & 1) != 0 ? 0.5 : -0.5, (n & 2) != 0 ? 0.5 : -0.5);
    g.x += sample_hu(p + vec3(1.0, o.x, o.y)) - sample_hu(p + vec3(-1.0, o.x, o.y));
    g.y += sample_hu(p + vec3(o.x, 1.0, o.y)) - sample_hu(p + vec3(o.x, -1.0, o.y));
    g.z += sample_hu(p + vec3(o.x, o.y, 1.0)) - sample_hu(p + vec3(o.x, o.y, -1.0));
  }
  return g * 0.125;
}

// The colour of the ray step from a (sample s_front) to p (sample s), shaded (Blinn-
// Phong, light from the viewer's upper left, two-sided). Where the step enters the
// preset's surface intensity the normal is taken at the crossing, found by a secant
// step, not at p: where the samples fall on a surface then leaves no wood-grain rings.
// Weak gradients (texture, noise) stay unshaded.
vec3 shade(vec4 c, vec3 a, vec3 p, vec3 v, float s_front, float s) {
  vec3 q = p;
  if (s_front < u_surface_hu && s >= u_surface_hu) {
    q = mix(a, p, (u_surface_hu - s_front) / (s - s_front));
    float sq = sample_hu(q);  // one secant step more, on the bracketing side
    if (sq < u_surface_hu) q = mix(q, p, (u_surface_hu - sq) / max(s - sq, 1e-3));
    else q = mix(a, q, (u_surface_hu - s_front) / max(sq - s_front, 1e-3));
  }
  vec3 g = gradient(q) / u_spacing;  // HU/mm along the grid axes
  float gm = length(g);
  if (gm <= 1e-3) return c.rgb;
  vec3 n = -g / gm;
  float w = smoothstep(u_grad_ramp.x, u_grad_ramp.y, gm);
  float diff = abs(dot(n, u_light));
  float spec = pow(abs(dot(n, normalize(u_light + v))), 28.0);
  return c.rgb * mix(1.0, 0.28 + 0.72 * diff, w) + vec3(0.28 * w * spec * c.a);
}

// the colour of the pixel whose centre is at `frag_coord` (image pixels, row 0 at the top)
vec4 ray_color(vec2 frag_coord) {
  // the ray through this pixel, in voxel-index space
  vec2 px = frag_coord - u_viewport.xy;
  vec2 ndc = vec2(2.0 * px.x / u_viewport.z - 1.0, 1.0 - 2.0 * px.y / u_viewport.w);
  vec3 d = normalize(u_fwd + ndc.x * u_right + ndc.y * u_up);
  vec3 v = normalize(-d * u_spacing);  // towards the eye, grid axes
  vec3 bg = mix(u_bg_top, u_bg_bottom, px.y / u_viewport.w);

  // where it is inside the body's bounding box (slab test)
  // (a zero direction component: "never" along that axis, no NaN)
  vec3 inv = mix(1.0 / d, vec3(1e30), lessThan(abs(d), vec3(1e-12)));
  vec3 ta = (u_box_lo - u_eye) * inv, tb = (u_box_hi - u_eye) * inv;
  vec3 tmin = min(ta, tb), tmax = max(ta, tb);
  float t_in = max(max(tmin.x, tmin.y), max(tmin.z, 0.0));
  float t_out = min(min(tmax.x, tmax.y), tmax.z);

  // the nearest marker on the ray
  float t_mark = 1e30;
  int mark = -1;
  for (int n = 0; n < 2; ++n) {
    float t = sphere_hit(u_eye, d, u_marker[n]);
    if (t < t_mark) { t_mark = t; mark = n; }
  }

  // front-to-back compositing up to the box's far side or the marker
  vec4 acc = vec4(0.0);
  float t_end = min(t_out, t_mark);
  if (t_in < t_end) {
    float t = t_in;
    float s_front = sample_hu(u_eye + t * d);
    vec3 exit_side = step(vec3(0.0), d);  // 1 where the ray leaves a block by its upper face
    int budget = u_max_steps;             // a bound on the march, whatever the numbers do
    for (;;) {
      // march: composite unshaded steps up to the next one to be shaded. A block whose
      // intensities (and one voxel around) are all faint in the preset is crossed in one
      // step; near the deformed box (its J is not in the block bounds) never.
      vec4 c = vec4(0.0);
      vec3 a = vec3(0.0), p = vec3(0.0);
      float s = 0.0;
      bool to_shade = false;
      for (;;) {
        if (--budget < 0) break;
        a = u_eye + t * d;
        vec3 bc = clamp(floor((a + 0.5) / u_block_vox), vec3(0.0), u_block_count - 1.0);
        vec3 te = ((bc + exit_side) * u_block_vox - 0.5 - u_eye) * inv;
        bool faint = texelFetch(u_blocks, ivec3(bc), 0).r < u_faint_hu && !in_voi(a, u_block_vox);
        float dt = faint ? max(min(min(te.x, te.y), te.z) - t, 0.0) + 0.05 : u_step;
        t += dt;
        if (t > t_end) break;
        p = u_eye + t * d;
        s = sample_hu(p);
        c = texture(u_tf, vec2(s_front, s) * u_tf_map.x + u_tf_map.y);
        // a long step: the opacity of (dt / u_step) table steps
        float k = dt / u_step;
        float ak = 1.0 - pow(max(1.0 - c.a, 0.0), k);
        c = c.a > 0.0 ? vec4(c.rgb * (ak / c.a), ak) : vec4(0.0);
        to_shade = !faint && c.a > kShadedMinAlpha && (c.a >= u_shade_alpha || abs(s - s_front) >= u_interface_hu);
        if (to_shade) break;
        acc += (1.0 - acc.a) * c;
        s_front = s;
        if (acc.a > kOpaque) break;
      }
      if (!to_shade) break;
      // the step that needs shading, once
      c.rgb = shade(c, a, p, v, s_front, s);
      acc += (1.0 - acc.a) * c;
      s_front = s;
      if (acc.a > kOpaque) break;
    }
  }

  // the marker: opaque where the ray reaches it, a faint ghost where tissue hides it
  if (mark >= 0 && t_mark < 1e29) {
    vec3 n = normalize((u_eye + t_mark * d - u_marker[mark].xyz) * u_spacing);
    vec3 col = u_marker_color[mark] * (0.35 + 0.65 * max(dot(n, u_light), 0.0)) +
               vec3(0.35 * pow(max(dot(n, normalize(u_light + v)), 0.0), 24.0));
    if (acc.a <= kOpaque) acc += (1.0 - acc.a) * vec4(col, 1.0);
    else acc.rgb = mix(acc.rgb, col, 0.35);
  }
  return vec4(acc.rgb + (1.0 - acc.a) * bg, 1.0);
}

// Why two entry points: a data-centre GPU (H100, H200) runs fragment shaders on its few
// graphics-capable multiprocessors only and compute shaders on all of them, so the compute
// ray cast is several times faster there; llvmpipe runs the fragment shader faster than
// the compute one.
#ifdef RAY_COMPUTE
// one invocation per pixel of the rectangle u_rect (x0, y0 of its top row, width, height)
layout(local_size_x = 8, local_size_y = 8) in;
layout(rgba8, binding = 0) uniform writeonly image2D u_frame;
uniform ivec4 u_rect;
void main() {
  ivec2 g = ivec2(gl_GlobalInvocationID.xy);
  if (g.x >= u_rect.z || g.y >= u_rect.w) return;
  ivec2 pixel = u_rect.xy + g;
  imageStore(u_frame, pixel, ray_color(vec2(pixel) + 0.5));
}
#else
// one fragment per pixel of the viewport (and scissor)
out vec4 frag;
void main() { frag = ray_color(gl_FragCoord.xy); }
#endif
)GLSL";

/// One slice: a plane of the patient grid through the centre, in an intensity window.
constexpr const char* kSliceFs = R"GLSL(
uniform vec4 u_viewport;  // x0, y0 (row of the slice's top), edge, edge (pixels)
uniform vec3 u_center;    // slice centre (voxel index)
uniform vec3 u_right;     // voxel index per pixel to the right
uniform vec3 u_down;      // voxel index per pixel down
uniform vec2 u_window;    // lowest HU shown, 1 / window width (1/HU)
out vec4 frag;
void main() {
  vec2 px = gl_FragCoord.xy - u_viewport.xy - 0.5 * u_viewport.zw;  // pixels from the centre
  vec3 p = u_center + px.x * u_right + px.y * u_down;
  float g = 0.0;  // black outside the grid
  if (all(greaterThanEqual(p, vec3(-0.5))) && all(lessThanEqual(p, u_grid_size - 0.5)))
    g = clamp((sample_hu(p) - u_window.x) * u_window.y, 0.0, 1.0);
  frag = vec4(vec3(g), 1.0);
}
)GLSL";

/// The slices' overlays, blended over the right column: a coloured frame per slice, the
/// lines where the other two planes cut it (with a gap at the centre), tip and proxy dots.
constexpr const char* kCompositeFs = R"GLSL(
uniform vec4 u_viewport;        // the column: x0, y0, width, height (pixels)
uniform float u_edge;           // slice edge (pixels)
uniform vec3 u_frame_color[3];  // axial, coronal, sagittal
uniform vec3 u_vline_color[3];  // the plane seen as the vertical line in each slice
uniform vec3 u_hline_color[3];  // the plane seen as the horizontal line
uniform vec2 u_cut[3];          // where the cut lines cross (pixels from the slice's top left)
uniform vec4 u_dot[6];          // tip, proxy per slice: xy pixel, z radius (0 = none), w unused
uniform vec3 u_dot_color[2];    // tip, proxy
out vec4 frag;

// a colour with coverage a over c (premultiplied)
void over(inout vec4 c, vec3 rgb, float a) { c = vec4(rgb * a, a) + (1.0 - a) * c; }

void main() {
  vec2 q = gl_FragCoord.xy - u_viewport.xy;
  int s = int(q.y / u_edge);
  if (s > 2) discard;
  vec2 l = q - vec2(0.0, float(s) * u_edge);  // pixel centre from the slice's top left
  vec4 c = vec4(0.0);
  // cut lines, 1 pixel, leaving the centre free
  vec2 dc = abs(l - u_cut[s]);
  float gap = max(10.0, u_edge * 0.06);
  if (dc.x < 0.5 && dc.y > gap) over(c, u_vline_color[s], 0.6);
  if (dc.y < 0.5 && dc.x > gap) over(c, u_hline_color[s], 0.6);
  // tip and proxy dots: filled, with a dark rim, antialiased
  for (int m = 1; m >= 0; --m) {
    vec4 d = u_dot[2 * s + m];
    if (d.z <= 0.0) continue;
    float r = length(l - d.xy);
    over(c, vec3(0.0), 0.8 * clamp(d.z + 1.5 - r, 0.0, 1.0));
    over(c, u_dot_color[m], clamp(d.z + 0.5 - r, 0.0, 1.0));
  }
  // the frame, 2 pixels
  float edge = min(min(l.x, l.y), min(u_edge - l.x, u_edge - l.y));
  if (edge < 2.0) over(c, u_frame_color[s], 1.0);
  if (c.a <= 0.0) discard;
  frag = c;  // premultiplied: blended with (ONE, ONE_MINUS_SRC_ALPHA)
}
)GLSL";

/// The orientation triad in the 3D view's corner: the patient's L (red), P (green) and
/// S (blue) axes as the camera sees them.
constexpr const char* kTriadFs = R"GLSL(
uniform vec4 u_viewport;      // x0, y0, edge, edge (pixels)
uniform vec3 u_axis[3];       // xy: axis end from the centre (pixels, y down), z: depth (towards viewer > 0)
uniform vec3 u_axis_color[3];
out vec4 frag;
void main() {
  vec2 p = gl_FragCoord.xy - u_viewport.xy - 0.5 * u_viewport.zw;
  vec4 c = vec4(0.0);
  float best = -1e9;
  for (int n = 0; n < 3; ++n) {
    // distance to the segment from the centre to the axis end; the nearer axis on top
    vec2 e = u_axis[n].xy;
    float h = clamp(dot(p, e) / max(dot(e, e), 1e-6), 0.0, 1.0);
    float a = clamp(2.0 - length(p - e * h), 0.0, 1.0);
    if (a > 0.0 && u_axis[n].z > best) {
      best = u_axis[n].z;
      c = vec4(u_axis_color[n] * a, a);
    }
  }
  if (c.a <= 0.0) discard;
  frag = c;  // premultiplied
}
)GLSL";

}  // namespace palpsim::render::shaders
