// The walk of torch_ao.walk compiled: one source for every backend. Written against the lane names of
// lanes_scalar.h / lanes_simd.h, so the same code runs L pixels of a row in SIMD lanes on the CPU
// (F = Vectorized<float>), one pixel per lane set on the CPU (F = float, what CI runs of the CUDA
// build) and one pixel per thread on CUDA (F = float under NVRTC).
//
// The names follow torch_ao/walk (GTAO's Algorithm 1 in walk.py): Pixels is Frame's queries, Slice
// is slice_geometry, step_distance is SlicePattern.step_offsets, Sample is fetch_sample + Sample's
// valid/delta, walk_block is march's loop. An accumulator (horizon.h, bitmask.h) says what a method
// keeps: its State per slice and Sums over slices, and the output channels it finishes them into:
//   State begin_slice(px, sl); void step(State&, int side, px, sl, sample);
//   void end_slice(const State&, px, sl, Sums&); void finish(const Sums&, px, F out[channels]).
// Sums start at zero; finish gives every lane its value, background lanes included (select on px.live).
// An accumulator whose state carries across slices (the GLSL shader's occlusion mask) takes the sums so
// far instead: State begin_slice(px, sl, const Sums&). One that takes step j of both sides together (ssao.h's
// UE4 wedge pairs: kPairedSides) has void step_pair(State&, px, sl, plus, minus) instead of step (walk_pairs).
#pragma once

#include "lanes_scalar.h"
#include "slopes.h"

// The CUDA build comes in two forms (launch.py compiles each on first use). The lean one, which a call runs unless
// it needs one of the options below, leaves them out: each costs registers in every CUDA walk, used or not. The full
// one (TAO_FULL_WALK) has them: slices drawn by the projected normal's density in the bitmask family's accumulators
// (kSectorsWeighSlices), a position buffer read between texels (Sample::position_taps) and the soft accumulators'
// segment geometry (SoftAccumulator::kSegments). The CPU build has everything.
#if defined(__CUDACC_RTC__) && !defined(TAO_FULL_WALK)
#define TAO_LEAN_WALK 1
#else
#define TAO_LEAN_WALK 0
#endif

namespace tao {

constexpr bool kLeanWalk = TAO_LEAN_WALK;

constexpr float kPi = 3.14159265358979323846f;
constexpr float kEdgeMinRatio = 1.02f;  // walk.fetch.EDGE_MIN_RATIO
constexpr float kHalfPi = 1.57079632679489661923f;
constexpr float kMinOffset = 1e-5f;  // walk.sample.MIN_OFFSET
constexpr float kNearestTie = 1.0f / 512.0f;  // walk.fetch.NEAREST_TIE: the nearest texel is floor(x + 0.5 - it)

template <class F> TAO_HOT F dot3(const F* a, const F* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
template <class F> TAO_HOT F norm3(const F* a) { return sqrt(dot3(a, a)); }
template <class F> TAO_HOT F norm2(const F& x, const F& y) { return sqrt(x * x + y * y); }
template <class F> TAO_HOT void cross(const F* a, const F* b, F* out) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

// Sample.along_view and along_tangent of a sample at delta from a pixel at view-space z pixel_z: delta . V, and
// side delta . T taken as +0 (no gradient) within kMinOffset of the pixel's depth -pixel_z (walk.sample's
// slice_coordinates: a sample off the slice, in the plane of V and the slice's normal, would otherwise occlude the
// half of the hemisphere its rounding picks). The test reads values alone (reverse lanes record no node for it).
template <class G, class D>
TAO_HOT void slice_coordinates(int side, const G* delta, const G* V, const G* T, const D& pixel_z, G& along_view,
                               G& along_tangent) {
  using Plain = typename ValueOf<G>::type;
  along_view = dot3(delta, V);
  const G tangent = G(float(side)) * dot3(delta, T);
  const auto off_slice = abs(value(tangent)) <= neg(Plain(value(pixel_z))) * Plain(kMinOffset);
  along_tangent = select(off_slice, G(0.0f), tangent);
}
// Sample.angle: atan2(along_tangent, along_view) of slice_coordinates, the sample's angle from V toward its side
template <class G, class D>
TAO_HOT G slice_angle(int side, const G* delta, const G* V, const G* T, const D& pixel_z) {
  G along_view, along_tangent;
  slice_coordinates(side, delta, V, T, pixel_z, along_view, along_tangent);
  return atan2(along_tangent, along_view);
}
// The slopes of atan2(along_tangent, along_view) (slice_angle's, sample_angles' front and back) with respect to
// along_view and to delta . T: atan2_slopes', the tangent coordinate's times the side (along_tangent = side delta . T).
// None to delta . T off the slice, where slice_coordinates takes along_tangent as a constant 0.
template <class F>
TAO_HOT void slice_angle_slopes(int side, const F& along_view, const F& along_tangent, F& by_view, F& by_tangent) {
  F by_along_tangent;
  atan2_slopes(along_tangent, along_view, by_along_tangent, by_view);
  by_tangent = select(along_tangent == F(0.0f), F(0.0f), F(float(side)) * by_along_tangent);
}

// F.normalize(x, eps=1e-12)
template <class F> TAO_HOT void normalize3(const F* x, F* out) {
  const F len = clamp_min(norm3(x), F(1e-12f));
  for (int c = 0; c < 3; ++c) out[c] = x[c] / len;
}
// N lanes values left uninitialised (ATen's Vectorized zeroes itself on construction: the per-step arrays
// of every slice would be cleared for nothing)
template <class F, int N> struct LaneArray {
  alignas(F) unsigned char bytes[N * sizeof(F)];
  TAO_FN F& operator[](int i) { return reinterpret_cast<F*>(bytes)[i]; }
  TAO_FN const F& operator[](int i) const { return reinterpret_cast<const F*>(bytes)[i]; }
};

// The walk's derivatives' seed on a pixel's own inputs: nothing for plain lanes (lanes_dual.h's for duals)
template <class F> TAO_FN void seed_pixel(F*, F*, F&) {}
// and on an accumulator's differentiable setting k (its settings(): GTAO's falloff or thickness, HBAO's angle
// bias; UE4 SSAO's three lengths), and on the camera's intrinsic k (fx, fy, cx, cy: lanes_rev.h's)
template <class F> TAO_FN F seed_setting(const F& x, int = 0) { return x; }
template <class F> TAO_FN F seed_camera(const F& x, int) { return x; }
template <class F> TAO_FN F lerp(const F& a, const F& b, const F& w) { return a + w * (b - a); }
// torch.sign (0 for 0 and NaN)
template <class F> TAO_HOT F sign(const F& x) { return select(x > F(0.0f), F(1.0f), select(x < F(0.0f), F(-1.0f), F(0.0f))); }
// HDRP's GTAOFastAcos / UE4's acosFast (torch_ao.ops.fast_acos) of x, given root = sqrt(1 - |x|)
template <class F> TAO_FN F fast_acos_of_root(const F& x, const F& root) {
  const F res = (F(-0.156583f) * abs(x) + F(kHalfPi)) * root;
  return select(x >= F(0.0f), res, F(kPi) - res);
}

template <class F> TAO_FN F fast_acos(const F& x) {
  const auto inside = abs(x) < F(1.0f);
  return fast_acos_of_root(x, select(inside, sqrt(select(inside, F(1.0f) - abs(x), F(1.0f))), F(0.0f)));
}

// Jimenez's interleaved gradient noise, in double as torch_ao.walk.interleaved_gradient_noise
TAO_FN float ign(float u, float v, int64_t seed) {
  const double x = double(u) + 5.588238 * double(seed), y = double(v) + 5.588238 * double(seed);
  const double s = 0.06711056 * x + 0.00583715 * y;
  const double g = 52.9829189 * (s - double(int64_t(s)));
  return float(g - double(int64_t(g)));
}

// The 64x64 Hilbert curve's index of pixel (u, v) modulo 64 (torch_ao.walk.hilbert_index, XeGTAO's HilbertIndex)
TAO_FN int64_t hilbert_index(int64_t u, int64_t v) {
  int64_t x = ((u % 64) + 64) % 64, y = ((v % 64) + 64) % 64, index = 0;
  for (int64_t level = 32; level > 0; level /= 2) {
    const int64_t rx = (x & level) > 0, ry = (y & level) > 0;
    index += level * level * ((3 * rx) ^ ry);
    if (ry == 0) {
      if (rx == 1) x = 63 - x, y = 63 - y;
      const int64_t t = x;
      x = y, y = t;
    }
  }
  return index;
}

// Value k (0: the slice rotation, 1: the step offset) of torch_ao.walk.hilbert_r2_noise, in double as there
TAO_FN float hilbert_r2(int64_t u, int64_t v, int64_t seed, int k) {
  const double i = double(hilbert_index(u, v) + 288 * seed);
  const double x = 0.5 + i * (k == 0 ? 0.75487766624669276005 : 0.5698402909980532659114);
  return float(x - double(int64_t(x)));
}

// Float rounded to float16 and back (round half to even), |x| < 65520: the GLSL mediump evaluation
TAO_FN float half_round(float x) {
  if (fabsf(x) < 6.103515625e-05f) return rintf(x * 16777216.0f) / 16777216.0f;  // float16 subnormals: 2^-24 steps
  uint32_t bits = float_bits(x);
  bits += 0xfffu + ((bits >> 13) & 1u);  // 13 mantissa bits dropped, to nearest even
  return bits_float(bits & ~0x1fffu);
}

// The SSILVB GLSL shader's randf(int(gl_FragCoord.x), int(gl_FragCoord.y)) - 0.5 at column u, GL row
// y_gl (from the bottom), in float32 or, mediump, each operation in float16 (bitmask_glsl.glsl_jitter)
TAO_FN float glsl_jitter(float u, float y_gl, bool mediump) {
  if (!mediump) {
    const float s = 0.06711056f * u + 0.00583715f * y_gl;
    const float g = 52.9829189f * (s - floorf(s));
    return (g - floorf(g)) - 0.5f;
  }
  const float x = half_round(u), y = half_round(y_gl);
  const float a = half_round(half_round(0.06711056f) * x), b = half_round(half_round(0.00583715f) * y);
  const float s = half_round(a + b), inner = half_round(s - floorf(s));
  const float g = half_round(half_round(52.9829189f) * inner);
  return half_round(g - floorf(g)) - 0.5f;
}

// Step placement (SlicePattern.step_offsets, ShaderStepPattern's, the GLSL shader's: GLSLPattern, UE4 SSAO's
// WedgePattern, PSSAOPattern's integer pixel offsets, read from the walk's table, or SSAO's hemisphere kernel:
// 3-D points around the normal, read from the table and projected, walk_points)
enum class Steps : int64_t { power = 0, hdrp = 1, ue4 = 2, glsl = 3, wedge = 4, pixels = 5, hemisphere = 6 };
// The noise of the slice angles and steps (launch.NOISES): Jimenez's interleaved gradient noise (ign),
// XeGTAO's R2 sequence along a Hilbert curve (hilbert_r2: SlicePattern._noise), or the GLSL shader's one
// jitter for both (glsl_jitter, in float32 or float16)
enum class Noise : int64_t { ign = 0, hilbert_r2 = 1, glsl = 2, glsl_mediump = 3 };

struct WalkSettings {
  int64_t slices, steps;
  float radius;         // world units: the walk's radius (search_scale included)
  float step_power, min_step_px;
  float max_radius_px;  // <= 0: none
  bool jitter, bilinear, drop, full_circle, screen_azimuth;
  bool stagger;  // the step offset shifted per half-slice (SlicePattern.step_noise)
  // the slices drawn by the projected normal's density (SlicePattern's slice_sampling="projected_normal": around V,
  // over the half circle), each weighted by Slice::weight
  bool projected_normal;
  int64_t seed;
  Steps placement;
  Noise noise;
  bool edge_aware;     // bilinear taps, or the nearest one where their cell is not one surface
  bool sphere_extent;  // the steps over the screen extent of the radius' sphere (intervals.sphere_stretch)
  // the positions are the depth unprojected (a G-buffer without a position buffer): a nearest fetch reads the
  // depth alone and unprojects it (the same arithmetic as the positions', a third of the bytes)
  bool unprojected;
  // Steps::wedge: per slice its screen angle and length (a UE4 sample set; null: slices evenly spaced, length
  // 1); Steps::pixels: per slice and step (du, dv), at 2 (s steps + j); Steps::hemisphere: per step its kernel
  // point (x, y, z) in the unit hemisphere z > 0 (z along the normal), at 3 j; else null
  const float* table;
};

// One image of the batch, channel-last: intrinsics in pixels, positions and normals (H, W, 3), the
// inverse depth and the depth (both NaN where invalid: a texel's validity travels with it), validity (H, W),
// the light (H, W, 3) or null; for the edge-aware fetch, per texel whether the 2x2 cell it is the
// top-left of is one surface (walk.fetch.continuous_cell_image: 1 or 0), and the back-face thickness
// layer (H, W) of thickness.BackfaceThickness, or null
struct Image {
  int64_t H, W;
  float fx, fy, cx, cy;
  const float *positions, *normals, *inverse, *depth, *light;
  const bool* valid;
  const float *cells, *backface;
  // What a bilinear fetch reads at its taps, where the CPU operators prepared it (frame_cpu.h's fetch_texels; else
  // null, and inverse and cells are read): the inverse depth, negative where cells is 0 if cells_in_sign (cells is
  // then not read: a gather fewer a sample), interleaved with backface (H, W, 2) if texels_layer (both of a tap's
  // floats in one 64-bit gather lane)
  const float* texels = nullptr;
  bool texels_layer = false, cells_in_sign = false;
};

// The view-space position of screen point (u, v) at depth d (camera.unproject: kornia's unprojection in OpenCV's
// axes, then y and z flipped): ((u - cx) / fx d, -(v - cy) / fy d, -d)
template <class F> TAO_FN void unproject(const Image& img, const F& u, const F& v, const F& d, F* pos) {
  pos[0] = ((u - F(img.cx)) / F(img.fx)) * d;
  pos[1] = (neg(v - F(img.cy)) / F(img.fy)) * d;
  pos[2] = neg(d);
}

// The pixels of a row a block's lanes hold: the n <= L columns from u0 on, or the n columns of cols (a gathered
// block); column(l) of a lane from n on: u0 + l, or the last column (its pixel's data is the last lane's)
struct RowLanes {
  int64_t row, u0;
  int n;
  const int64_t* cols = nullptr;
  TAO_FN int64_t column(int l) const { return cols ? cols[l < n ? l : n - 1] : u0 + l; }
  TAO_FN int64_t pixel(int64_t W, int l) const { return row * W + column(l < n ? l : n - 1); }
};

// L pixels of a row (Frame's queries): P, N, V = normalize(-P), depth (and its inverse), u, v, the step
// noise xi (with the GLSL noise the shader's jitter, its slice angles' too), the basis e1 = normalize(cross(+Y, V)),
// e2 = cross(V, e1) around V (0 where the slices' tangents come from their screen angles), and the slice rotation's
// noise (SlicePattern._noise: 0 without jitter), of the pixels of a row RowLanes says. Lanes past the row's end
// (past n) repeat its last pixel and are not live.
template <class F> struct Pixels {
  using M = typename LaneTraits<F>::M;
  static constexpr int L = LaneTraits<F>::L;
  F P[3], N[3], V[3], e1[3], e2[3], depth, inverse_depth, distance, u, v, xi;  // distance: |P|
  float rotation[L];
  M live;
  int64_t row;

  TAO_FN Pixels(const WalkSettings& cfg, const Image& img, int64_t row_, int64_t u0_, int n)
      : Pixels(cfg, img, RowLanes{row_, u0_, n}) {}
  TAO_FN Pixels(const WalkSettings& cfg, const Image& img, const RowLanes& lanes) : row(lanes.row) {
    const int n = lanes.n;
    float lane[10][L];
    for (int l = 0; l < L; ++l) {
      const int64_t p = lanes.pixel(img.W, l);
      for (int c = 0; c < 3; ++c) {
        lane[c][l] = img.positions[3 * p + c];
        lane[3 + c][l] = img.normals[3 * p + c];
      }
      lane[6][l] = img.valid[p] ? img.depth[p] : 1.0f;  // (GBuffer.safe_depth)
      const int64_t col = lanes.column(l);
      lane[7][l] = float(col);
      lane[8][l] = l < n && img.valid[p] ? 1.0f : 0.0f;
    }
    // the noise, a loop of its own (the interleaved gradient noise's then vectorises, its double arithmetic included)
    if (cfg.noise == Noise::glsl || cfg.noise == Noise::glsl_mediump) {  // one jitter, no rotation of its own
      for (int l = 0; l < L; ++l) {
        lane[9][l] = cfg.jitter ? glsl_jitter(lane[7][l], float(img.H - 1 - row), cfg.noise == Noise::glsl_mediump) : 0.0f;
        rotation[l] = 0.0f;
      }
    } else if (!cfg.jitter) {
      for (int l = 0; l < L; ++l) lane[9][l] = 0.5f, rotation[l] = 0.0f;
    } else if (cfg.noise == Noise::hilbert_r2) {
      for (int l = 0; l < L; ++l) {
        const int64_t col = lanes.column(l);
        lane[9][l] = hilbert_r2(col, row, cfg.seed, 1), rotation[l] = hilbert_r2(col, row, cfg.seed, 0);
      }
    } else {
      for (int l = 0; l < L; ++l) {
        lane[9][l] = ign(lane[7][l] + 37.0f, float(row) + 59.0f, cfg.seed + 1);
        rotation[l] = ign(lane[7][l], float(row), cfg.seed);
      }
    }
    const F like(0.0f);
    for (int c = 0; c < 3; ++c) {
      P[c] = from_lanes(lane[c], like);
      N[c] = from_lanes(lane[3 + c], like);
    }
    depth = from_lanes(lane[6], like);
    seed_pixel(P, N, depth);
    inverse_depth = F(1.0f) / depth;
    u = from_lanes(lane[7], like);
    v = F(float(row));
    live = from_lanes(lane[8], like) > F(0.5f);
    xi = from_lanes(lane[9], like);
    distance = norm3(P);
    for (int c = 0; c < 3; ++c) V[c] = neg(P[c]) / clamp_min(distance, F(1e-12f));  // (normalize3(-P): |-P| = |P|)
    if (cfg.screen_azimuth) {  // (a slice's tangent from its screen angle: no basis around V)
      for (int c = 0; c < 3; ++c) e1[c] = e2[c] = F(0.0f);
    } else {
      const F c1[3] = {V[2], F(0.0f), neg(V[0])};  // cross(+Y, V)
      normalize3(c1, e1);
      cross(V, e1, e2);
    }
  }

  // the same pixels in another lane type, each value through to(x) (walk_grad_cpu.cpp: into a dual with more tangents)
  template <class G, class To>
  TAO_FN Pixels(const Pixels<G>& o, const To& to)
      : depth(to(o.depth)), inverse_depth(to(o.inverse_depth)), distance(to(o.distance)), u(to(o.u)), v(to(o.v)),
        xi(to(o.xi)), live(o.live), row(o.row) {
    for (int c = 0; c < 3; ++c)
      P[c] = to(o.P[c]), N[c] = to(o.N[c]), V[c] = to(o.V[c]), e1[c] = to(o.e1[c]), e2[c] = to(o.e2[c]);
    for (int l = 0; l < L; ++l) rotation[l] = o.rotation[l];
  }
};

// patterns.projected_normal_azimuths: the view azimuth psi in [0, pi) at the quantile u of the density p proportional
// to GTAO's unoccluded slice integral |n_p| (cos g + g sin g) = n.V + atan2(n.T, n.V) n.T (tabulated in
// kDensityBins equal bins, each at least 1e-4), and psi's estimator weight 1 / (pi p(psi)) into weight
constexpr int kDensityBins = 32;  // patterns.PROJECTED_NORMAL_BINS
// the bins' centres' cos and sin, (k + 1/2) pi / kDensityBins
TAO_CONST float kDensityCos[kDensityBins] = {0.998795456f, 0.98917651f, 0.970031253f, 0.941544065f, 0.903989293f, 0.85772861f, 0.803207531f, 0.740951125f, 0.671558955f, 0.595699304f, 0.514102744f, 0.427555093f, 0.336889853f, 0.24298018f, 0.146730474f, 0.0490676743f, -0.0490676743f, -0.146730474f, -0.24298018f, -0.336889853f, -0.427555093f, -0.514102744f, -0.595699304f, -0.671558955f, -0.740951125f, -0.803207531f, -0.85772861f, -0.903989293f, -0.941544065f, -0.970031253f, -0.98917651f, -0.998795456f};
TAO_CONST float kDensitySin[kDensityBins] = {0.0490676743f, 0.146730474f, 0.24298018f, 0.336889853f, 0.427555093f, 0.514102744f, 0.595699304f, 0.671558955f, 0.740951125f, 0.803207531f, 0.85772861f, 0.903989293f, 0.941544065f, 0.970031253f, 0.98917651f, 0.998795456f, 0.998795456f, 0.98917651f, 0.970031253f, 0.941544065f, 0.903989293f, 0.85772861f, 0.803207531f, 0.740951125f, 0.671558955f, 0.595699304f, 0.514102744f, 0.427555093f, 0.336889853f, 0.24298018f, 0.146730474f, 0.0490676743f};
template <class F> TAO_FN F density_bin(const F& nv, const F& n1, const F& n2, int k) {
  const F along = n1 * F(kDensityCos[k]) + n2 * F(kDensitySin[k]);  // n.T at the bin's centre
  return clamp_min(nv + atan2(along, nv) * along, F(1e-4f));
}
// The azimuth and weight of the normal's components n.V, n.e1, n.e2 (projected_normal_azimuth's; walk_grad.h's
// reverse lanes record it as two nodes of three parents). Two passes over the bins (the quantile needs their sum
// first): the CPU's keeps them from the first; a CUDA thread computes them again (32 kept spill its registers)
#ifdef __CUDACC_RTC__
constexpr bool kKeepDensityBins = false;
#else
constexpr bool kKeepDensityBins = true;
#endif
template <class F> TAO_FN F density_azimuth(const F& nv, const F& n1, const F& n2, const F& u, F& weight) {
  F kept[kKeepDensityBins ? kDensityBins : 1], total(0.0f);
  for (int k = 0; k < kDensityBins; ++k) {
    const F w = density_bin(nv, n1, n2, k);
    if (kKeepDensityBins) kept[k] = w;
    total = total + w;
  }
  // the first bin whose running sum exceeds the target (searchsorted, right), else the last
  const F target = u * total;
  F sum(0.0f), index(0.0f), chosen(1.0f), before(0.0f);
  typename LaneTraits<F>::M found = F(0.0f) > F(1.0f);
  for (int k = 0; k < kDensityBins; ++k) {
    const F w = kKeepDensityBins ? kept[k] : density_bin(nv, n1, n2, k), below = sum;
    sum = sum + w;
    const auto take = k + 1 < kDensityBins ? land(sum > target, lnot(found)) : lnot(found);
    index = select(take, F(float(k)), index), chosen = select(take, w, chosen), before = select(take, below, before);
    found = lor(found, take);
  }
  weight = total / (F(float(kDensityBins)) * chosen);
  return (index + clamp((target - before) / chosen, F(0.0f), F(1.0f))) * F(kPi / float(kDensityBins));
}
template <class F> TAO_FN F projected_normal_azimuth(const Pixels<F>& px, const F& u, F& weight) {
  return density_azimuth(dot3(px.N, px.V), dot3(px.N, px.e1), dot3(px.N, px.e2), u, weight);
}

// slice_geometry: the slice tangent T, the projected normal's length, its angle gamma
// from V (with cos and sin), and the walk's screen direction and extent (SlicePattern.radius_px, span)
// (with the GLSL placement only the screen direction and T: the shader places its steps from the
// direction and measures its own angles; without normal, the walk's alone: length, gamma and its sine 0, its
// cosine 1)
template <class F> struct Slice {
  F T[3], length, gamma, cos_gamma, sin_gamma, unit_u, unit_v, radius_px, span;
  F weight;  // the slice's estimator weight: 1, or with projected_normal 1 / (pi p) of its azimuth's density
  F screen_length;  // pixels per world unit along T (|du, dv|: unit_u, unit_v are du, dv over it)
  F dir_u, dir_v;  // the slice's screen angle's cos and sin
  int64_t index;

  TAO_FN explicit Slice(int64_t s) : weight(1.0f), index(s) {}  // no geometry (walked_slice: the hemisphere's kernel points)
  // (azimuth: the view azimuth where the slice's is drawn, walked_slice's; its weight is set by the caller)
  TAO_FN Slice(const WalkSettings& cfg, const Image& img, const Pixels<F>& px, int64_t s, bool normal = true,
               const F* azimuth = nullptr)
      : weight(1.0f), index(s) {
    F angle;
    if (cfg.placement == Steps::glsl) {  // GLSLPattern: 2 pi / (sliceCount - 1) (s + jitter) + pi, sliceCount = slices - 1
      angle = F(2.0f * kPi / float(cfg.slices - 2)) * (F(float(s)) + px.xi) + F(kPi);
    } else if (cfg.placement == Steps::wedge) {  // WedgePattern: the direction's angle + 2 pi a
      float lane[LaneTraits<F>::L];
      const float base = cfg.table ? cfg.table[2 * s] : float(double(s) * 3.14159265358979323846 / double(cfg.slices));
      for (int l = 0; l < LaneTraits<F>::L; ++l) lane[l] = 2.0f * kPi * px.rotation[l] + base;
      angle = from_lanes(lane, F(0.0f));
    } else if (azimuth) {
      angle = *azimuth;
    } else {  // SlicePattern.slice_tangent: angle (s + a) * span / slices, a the pixel's rotation noise
      float lane[LaneTraits<F>::L];
      const float step = (cfg.full_circle ? 2.0f : 1.0f) * kPi / float(cfg.slices);
      for (int l = 0; l < LaneTraits<F>::L; ++l) lane[l] = (px.rotation[l] + float(s)) * step;
      angle = from_lanes(lane, F(0.0f));
    }
    F cs, sn;
    if (cfg.placement == Steps::glsl) {  // (the shader's directions pick texels: as torch's and llvmpipe's, 1 ulp matters)
      cos_sin_rounded(angle, cs, sn);
    } else if (azimuth) {
      cs = cos(angle), sn = sin(angle);
    } else {  // (a constant: in value lanes, where dual or reverse lanes would take each one's sin and cos)
      const auto plain = value(angle);
      cs = F(cos(plain)), sn = F(sin(plain));
    }
    dir_u = cs, dir_v = sn;
    if (cfg.screen_azimuth) {  // tangent_from_screen_angle: (cos, sin, 0) made orthogonal to V
      const F d[3] = {cs, sn, F(0.0f)};
      const F along = cs * px.V[0] + sn * px.V[1];  // d . V
      F t[3];
      for (int c = 0; c < 3; ++c) t[c] = d[c] - along * px.V[c];
      normalize3(t, T);
    } else {  // tangent_from_view_azimuth
      for (int c = 0; c < 3; ++c) T[c] = cs * px.e1[c] + sn * px.e2[c];
    }
    if (cfg.placement == Steps::glsl) return;
    if (normal) {
      // the normal projected into the slice plane (N less its part along the plane's normal T x V): x V + y T
      const F x = dot3(px.N, px.V), y = dot3(px.N, T);
      length = norm2(x, y);
      gamma = atan2(y, x);
      const auto flat = length > F(1e-30f);  // atan2(0, 0) = 0: cos 1, sin 0
      cos_gamma = select(flat, x / clamp_min(length, F(1e-30f)), F(1.0f));
      sin_gamma = select(flat, y / clamp_min(length, F(1e-30f)), F(0.0f));
    } else {
      length = gamma = sin_gamma = F(0.0f), cos_gamma = F(1.0f);
    }
    // screen motion (pixels per world unit along +T) of the projection (fx x/d + cx, -fy y/d + cy)
    const F du = (seed_camera(F(img.fx), 0) * (T[0] + (px.P[0] * T[2]) / px.depth)) / px.depth;
    const F dv = (neg(seed_camera(F(img.fy), 1)) * (T[1] + (px.P[1] * T[2]) / px.depth)) / px.depth;
    const F len = norm2(du, dv);
    screen_length = len;
    unit_u = du / clamp_min(len, F(1e-12f));
    unit_v = dv / clamp_min(len, F(1e-12f));
    radius_px = F(cfg.radius) * len;
    if (cfg.sphere_extent) {  // 1 / sqrt(1 - (R / |P|)^2), at most 10 (intervals.sphere_stretch)
      const F ratio = F(cfg.radius) / px.distance;
      radius_px = radius_px * rsqrt(clamp_min(F(1.0f) - ratio * ratio, F(1.0f / 100.0f)));
    }
    if (cfg.placement == Steps::power) {
      if (cfg.max_radius_px > 0) radius_px = clamp_max(radius_px, F(cfg.max_radius_px));
      span = clamp_min(radius_px - F(cfg.min_step_px), F(0.0f));
    } else if (cfg.placement == Steps::wedge || cfg.placement == Steps::pixels) {  // the direction's length
      if (cfg.placement == Steps::wedge && cfg.table) radius_px = radius_px * F(cfg.table[2 * s + 1]);
      span = radius_px;
    } else {  // ShaderStepPattern: R_px clamped to [steps, max_radius_px], dt = R_px / (steps + 1)
      const F steps = F(float(cfg.steps));
      radius_px = clamp_min(radius_px, steps);
      if (cfg.max_radius_px > 0)
        radius_px = clamp_max(radius_px, F(cfg.max_radius_px > float(cfg.steps) ? cfg.max_radius_px : float(cfg.steps)));
      span = radius_px / F(float(cfg.steps + 1));
    }
  }

  // the same slice in another lane type, each value through to(x) (as Pixels')
  template <class G, class To>
  TAO_FN Slice(const Slice<G>& o, const To& to)
      : length(to(o.length)), gamma(to(o.gamma)), cos_gamma(to(o.cos_gamma)), sin_gamma(to(o.sin_gamma)),
        unit_u(to(o.unit_u)), unit_v(to(o.unit_v)), radius_px(to(o.radius_px)), span(to(o.span)), weight(to(o.weight)),
        screen_length(to(o.screen_length)), dir_u(to(o.dir_u)),
        dir_v(to(o.dir_v)), index(o.index) {
    for (int c = 0; c < 3; ++c) T[c] = to(o.T[c]);
  }
};

// SlicePattern.step_noise: the pixel's step offset xi, with stagger frac(xi + (s + [side < 0] / 2) / slices)
// (staggered_offset; the shift in double, as Python's float)
template <class F> TAO_FN F step_noise(const WalkSettings& cfg, const Pixels<F>& px, const Slice<F>& sl, int side) {
  if (!cfg.stagger) return px.xi;
  const F x = px.xi + F(float((double(sl.index) + (side < 0 ? 0.5 : 0.0)) / double(cfg.slices)));
  return x - floor(x);
}

// The distance in pixels of step j from the pixel (SlicePattern.step_offsets / ShaderStepPattern) for the
// step offset xi (step_noise); j in lanes (each lane its own step), or one step for every lane
template <class F> TAO_FN F step_distance(const WalkSettings& cfg, const Slice<F>& sl, const F& xi, const F& j) {
  if (cfg.placement == Steps::hdrp) return ((j + F(1.0f)) + xi) * sl.span;
  if (cfg.placement == Steps::ue4) return clamp_min((j + xi) * sl.span, j + F(1.0f));
  if (cfg.placement == Steps::wedge) return ((j + F(1.0f)) / F(float(cfg.steps))) * sl.span;  // (j + 1) / steps R_px
  F frac = (j + xi) / F(float(cfg.steps));
  if (cfg.step_power == 2.0f) {
    frac = frac * frac;
  } else if (cfg.step_power != 1.0f) {
    frac = pow(frac, F(cfg.step_power));
  }
  return F(cfg.min_step_px) + sl.span * frac;
}
template <class F> TAO_FN F step_distance(const WalkSettings& cfg, const Slice<F>& sl, const F& xi, int64_t j) {
  return step_distance(cfg, sl, xi, F(float(j)));
}

// The screen position (along_u, along_v) dist pixels from the pixel along the slice's side
template <class F> TAO_FN F along_u(const Pixels<F>& px, const Slice<F>& sl, float side, const F& dist) {
  return px.u + dist * (sl.unit_u * F(side));
}
template <class F> TAO_FN F along_v(const Pixels<F>& px, const Slice<F>& sl, float side, const F& dist) {
  return px.v + dist * (sl.unit_v * F(side));
}

// Where the steps j (each lane its own: a backward's replayed takes) of a slice's side sample, in screen pixels
// (su, sv), for the side's step offset xi (step_noise): step_distance along the slice's screen direction, or
// PSSAOPattern.pixel_offset from the table (not the GLSL placement, whose accumulators record no takes)
template <class F>
TAO_FN void step_screen(const WalkSettings& cfg, const Image&, const Pixels<F>& px, const Slice<F>& sl, float side,
                        const F& xi, const F& j, F& su, F& sv) {
  if (cfg.placement == Steps::pixels) {
    constexpr int L = LaneTraits<F>::L;
    int32_t step[L];
    float off_u[L], off_v[L];
    store_lanes(to_int(value(j)), step);
    for (int l = 0; l < L; ++l) {
      const float* o = cfg.table + 2 * (sl.index * cfg.steps + step[l]);
      off_u[l] = o[0], off_v[l] = o[1];
    }
    su = px.u + from_lanes(off_u, F(0.0f)), sv = px.v + from_lanes(off_v, F(0.0f));
    return;
  }
  const F dist = step_distance(cfg, sl, xi, j);
  su = along_u(px, sl, side, dist), sv = along_v(px, sl, side, dist);
}

// Where step j of a slice's side samples (one step for every lane: the walk's), as above, or GLSLPattern's texel:
// uv = fragUV - ((j + jitter) / sampleCount + 0.01) sampleScale (cos, sin) (aspect H / W on x),
// sampleScale = -radius P[0][0] / position.z, P[0][0] = 2 fx / W, the nearest texel floor(uv * size)
// clamped to the image (GL rows from the bottom; sampleCount = steps - 1)
template <class F>
TAO_FN void step_screen(const WalkSettings& cfg, const Image& img, const Pixels<F>& px, const Slice<F>& sl, float side,
                        const F& xi, int64_t j, F& su, F& sv) {
  if (cfg.placement == Steps::pixels) {  // (the table's one entry for every lane)
    const float* o = cfg.table + 2 * (sl.index * cfg.steps + j);
    su = px.u + F(o[0]), sv = px.v + F(o[1]);
    return;
  }
  if (cfg.placement != Steps::glsl) return step_screen(cfg, img, px, sl, side, xi, F(float(j)), su, sv);
  const float Wf = float(img.W), Hf = float(img.H);
  const F scale = F(-cfg.radius * (2.0f * img.fx / Wf)) / px.P[2];
  const F frag_u = (px.u + F(0.5f)) / F(Wf), frag_v = ((F(Hf - 1.0f) - px.v) + F(0.5f)) / F(Hf);
  const F f = ((F(float(j)) + xi) / F(float(cfg.steps - 1)) + F(0.01f)) * scale;
  const F uv_u = frag_u - (f * sl.dir_u) * F(Hf / Wf), uv_v = frag_v - f * sl.dir_v;
  su = clamp(floor(uv_u * F(Wf)), F(0.0f), F(Wf - 1.0f));
  sv = F(Hf - 1.0f) - clamp(floor(uv_v * F(Hf)), F(0.0f), F(Hf - 1.0f));
}

// The lanes whose four taps are one texel
template <class F> TAO_FN typename LaneTraits<F>::M equal_taps(const typename LaneTraits<F>::I* index) {
  return land(land(ieq(index[1], index[0]), ieq(index[2], index[0])), ieq(index[3], index[0]));
}

// One sample (fetch_sample and Sample): the fetch at screen (su, sv): the nearest texel, or the
// perspective-correct bilinear footprint of four taps (walk.fetch.bilinear_taps: inverse depth
// interpolated, then unprojected), delta = position - P where valid, else -V (away from the camera: it
// never occludes). valid drops background taps, the border (drop) and the centre texel.
template <class F> struct Sample {
  using M = typename LaneTraits<F>::M;
  using I = typename LaneTraits<F>::I;
  F delta[3];
  M valid;
  I index[4];  // the taps' texels (index[0] only for a nearest fetch), to read other buffers
  F fu, fv;
  F su, sv;  // where it samples, in screen pixels
  // a bilinear fetch's d (the interpolated inverse depth) / d su and d sv, for fetch_motion (0 for a nearest fetch)
  F inverse_su, inverse_sv;
  // the back-face layer at the taps where this sample's fetch read it with the inverse depth (Image::texels_layer)
  F layer;
  bool has_layer = false;
  bool bilinear;
  // a bilinear read of a position buffer (position_taps; the CPU's only), and whether its fetch is edge-aware
  bool reads_positions = false, edge_aware = false;
  const Image* image;

  // channel c of a (H, W, channels) image at the sample's taps (Sample.gather)
  TAO_FN F gather(const float* image, int c, int channels = 3) const {
    const I n = I(channels);
    if (!bilinear) return tao::gather(image + c, index[0] * n);
    const F t0 = tao::gather(image + c, index[0] * n), t1 = tao::gather(image + c, index[1] * n);
    const F t2 = tao::gather(image + c, index[2] * n), t3 = tao::gather(image + c, index[3] * n);
    return lerp(lerp(t0, t1, fu), lerp(t2, t3, fu), fv);
  }

  // A position buffer read between texels (Footprint.position): its four taps' positions interpolated
  // perspective-correctly (p / depth and 1 / depth bilinearly, then divided; each tap's depth its own -z); the
  // edge-aware fetch's four equal taps (its nearest copies) give the tap's depth unprojected at the clamped (su, sv),
  // as the depth fetch does. The CPU's only, out of line (inline, GTAO's forward took 4 % longer): inline in every
  // CUDA walk it took 6-23 more registers a thread (a quarter less occupancy in six of them), out of line it moved
  // them both ways, for a read that engines' position buffers alone need. Its motion: position_motion; its
  // backward: walk_grad.h's scatter_position_taps.
  TAO_COLD void position_taps(const Image& img, const F& su_c, const F& sv_c, F* pos) const {
    const I three = I(3);
    F inverse[4];
    for (int k = 0; k < 4; ++k) inverse[k] = F(-1.0f) / F(tao::gather(img.positions + 2, index[k] * three));
    const F denominator = lerp(lerp(inverse[0], inverse[1], fu), lerp(inverse[2], inverse[3], fu), fv);
    for (int c = 0; c < 3; ++c) {  // (a component's taps at a time)
      const F top = lerp(F(tao::gather(img.positions + c, index[0] * three)) * inverse[0],
                         F(tao::gather(img.positions + c, index[1] * three)) * inverse[1], fu);
      const F bottom = lerp(F(tao::gather(img.positions + c, index[2] * three)) * inverse[2],
                            F(tao::gather(img.positions + c, index[3] * three)) * inverse[3], fu);
      pos[c] = lerp(top, bottom, fv) / denominator;
    }
    const auto single = one_texel();
    if (any(single)) {
      F tile[3];
      unproject(img, su_c, sv_c, neg(F(tao::gather(img.positions + 2, index[0] * three))), tile);
      for (int c = 0; c < 3; ++c) pos[c] = select(single, tile[c], pos[c]);
    }
  }
  // the lanes whose position_taps read is the edge-aware fetch's one texel, unprojected at (su, sv)
  TAO_FN M one_texel() const { return edge_aware ? equal_taps<F>(index) : F(0.0f) > F(1.0f); }
  // d position_taps / d su and d sv (fu and fv move with them; the one texel's unprojection moves inside the
  // image), for fetch_motion
  TAO_COLD void position_motion(F* d_su, F* d_sv) const {
    const Image& img = *image;
    const I three = I(3);
    F inverse[4];
    for (int k = 0; k < 4; ++k) inverse[k] = F(-1.0f) / F(tao::gather(img.positions + 2, index[k] * three));
    const F top = lerp(inverse[0], inverse[1], fu), bottom = lerp(inverse[2], inverse[3], fu);
    const F denominator = lerp(top, bottom, fv);
    const F den_u = lerp(inverse[1] - inverse[0], inverse[3] - inverse[2], fv), den_v = bottom - top;
    for (int c = 0; c < 3; ++c) {
      F a[4];
      for (int k = 0; k < 4; ++k) a[k] = F(tao::gather(img.positions + c, index[k] * three)) * inverse[k];
      const F upper = lerp(a[0], a[1], fu), lower = lerp(a[2], a[3], fu);
      const F pos = lerp(upper, lower, fv) / denominator;
      d_su[c] = (lerp(a[1] - a[0], a[3] - a[2], fv) - pos * den_u) / denominator;
      d_sv[c] = (lower - upper - pos * den_v) / denominator;
    }
    const auto single = one_texel();
    if (any(single)) {
      const F depth = F(1.0f) / inverse[0];  // (-z)
      const auto u_inside = clamp(su, F(0.0f), F(float(img.W - 1))) == su;
      const auto v_inside = clamp(sv, F(0.0f), F(float(img.H - 1))) == sv;
      const F dxh = select(u_inside, depth * F(1.0f / img.fx), F(0.0f));
      const F dyh = select(v_inside, depth * F(-1.0f / img.fy), F(0.0f));
      for (int c = 0; c < 3; ++c) {
        d_su[c] = select(single, c == 0 ? dxh : F(0.0f), d_su[c]);
        d_sv[c] = select(single, c == 1 ? dyh : F(0.0f), d_sv[c]);
      }
    }
  }

  // d gather(image, c, channels) / d su and d sv: the taps' weights moving (0 for a nearest fetch)
  TAO_FN void gather_slope(const float* image, int c, int channels, F& d_su, F& d_sv) const {
    if (!bilinear) {
      d_su = d_sv = F(0.0f);
      return;
    }
    const I n = I(channels);
    const F t0 = tao::gather(image + c, index[0] * n), t1 = tao::gather(image + c, index[1] * n);
    const F t2 = tao::gather(image + c, index[2] * n), t3 = tao::gather(image + c, index[3] * n);
    d_su = lerp(t1 - t0, t3 - t2, fv), d_sv = lerp(t2, t3, fu) - lerp(t0, t1, fu);
  }

  // whether the screen position lies in the image, pixel centres [0, W-1] x [0, H-1] (Sample.inside)
  TAO_FN M inside() const {
    return land(land(su >= F(0.0f), su <= F(float(image->W - 1))), land(sv >= F(0.0f), sv <= F(float(image->H - 1))));
  }

  // a kept sample's taps alone (index, fu, fv: a backward reading other buffers there; its delta and screen
  // position are not set)
  TAO_FN Sample(const Image& img, bool bilinear, const I* taps, const F& fu, const F& fv, const M& valid)
      : valid(valid), fu(fu), fv(fv), bilinear(bilinear), image(&img) {
    for (int k = 0; k < 4; ++k) index[k] = taps[k];
  }

  // the same sample in another lane type, each value through to(x) (as Pixels')
  template <class G, class To>
  TAO_FN Sample(const Sample<G>& o, const To& to)
      : valid(o.valid), fu(to(o.fu)), fv(to(o.fv)), su(to(o.su)), sv(to(o.sv)), inverse_su(to(o.inverse_su)),
        inverse_sv(to(o.inverse_sv)), bilinear(o.bilinear), reads_positions(o.reads_positions),
        edge_aware(o.edge_aware), image(o.image) {
    for (int c = 0; c < 3; ++c) delta[c] = to(o.delta[c]);
    for (int k = 0; k < 4; ++k) index[k] = o.index[k];
  }

  // the sample dist pixels from the pixel along the slice's side
  TAO_FN Sample(const WalkSettings& cfg, const Image& img, const Pixels<F>& px, const Slice<F>& sl, float side,
                const F& dist)
      : Sample(cfg, img, px, along_u(px, sl, side, dist), along_v(px, sl, side, dist)) {}

  // the sample at screen (su, sv)
  TAO_HOT Sample(const WalkSettings& cfg, const Image& img, const Pixels<F>& px, const F& su, const F& sv)
      : su(su), sv(sv) {
    const F Wf = F(float(img.W)), Hf = F(float(img.H));
    const I zero = I(0), Wi = I(int32_t(img.W)), Wlast = I(int32_t(img.W - 1)), Hlast = I(int32_t(img.H - 1)), one = I(1);
    F pos[3];
    bilinear = cfg.bilinear;
    image = &img;
    auto own = F(0.0f) > F(1.0f);  // (edge-aware fetch: the pixel's own texel)
    if (cfg.bilinear) {
      const F fu0 = floor(su), fv0 = floor(sv);
      fu = su - fu0, fv = sv - fv0;
      const I iu = to_int(clamp(fu0, F(-1.0f), Wf)), iv = to_int(clamp(fv0, F(-1.0f), Hf));
      const I c0 = imin(imax(iu, zero), Wlast), c1 = imin(imax(iu + one, zero), Wlast);
      const I r0 = imin(imax(iv, zero), Hlast) * Wi, r1 = imin(imax(iv + one, zero), Hlast) * Wi;
      index[0] = r0 + c0, index[1] = r0 + c1, index[2] = r1 + c0, index[3] = r1 + c1;
      using P = typename ValueOf<F>::type;
      F t0, t1, t2, t3;
      P b0, b1, b2, b3;  // (the layer's taps, where read with the inverse depth)
      if (!img.texels_layer) {
        const float* inverse = img.texels ? img.texels : img.inverse;
        t0 = tao::gather(inverse, index[0]), t1 = tao::gather(inverse, index[1]);
        t2 = tao::gather(inverse, index[2]), t3 = tao::gather(inverse, index[3]);
      } else {
        P i0, i1, i2, i3;
        gather_pair(img.texels, index[0], i0, b0), gather_pair(img.texels, index[1], i1, b1);
        gather_pair(img.texels, index[2], i2, b2), gather_pair(img.texels, index[3], i3, b3);
        t0 = i0, t1 = i1, t2 = i2, t3 = i3;
        has_layer = true;
      }
      if (cfg.edge_aware) {
        // edge_aware_taps: the four taps where their cell is one surface (a footprint clamped at the
        // border, whose taps repeat, by the ratio rule alone), else four copies of the nearest tap
        const auto proper = land(lnot(ieq(index[1], index[0])), lnot(ieq(index[2], index[0])));
        const bool all_proper = !any(lnot(proper));
        auto smooth = img.cells_in_sign ? sign_clear(value(t0)) : tao::gather(img.cells, index[0]) > F(0.5f);
        if (img.cells_in_sign) t0 = abs(t0), t1 = abs(t1), t2 = abs(t2), t3 = abs(t3);
        if (!all_proper) {
          const F lo = min(min(t0, t1), min(t2, t3)), hi = max(max(t0, t1), max(t2, t3));
          smooth = select(proper, smooth, land(lo > F(0.0f), hi <= F(kEdgeMinRatio) * lo));  // (NaN taps: never)
        }
        // (where every lane's footprint is four distinct taps of one surface, nothing changes: most steps)
        if (!all_proper || any(lnot(smooth))) {
          const auto right = fu >= F(0.5f + kNearestTie), down = fv >= F(0.5f + kNearestTie);
          const I nearest = select(down, select(right, index[3], index[2]), select(right, index[1], index[0]));
          const F t_near = select(down, select(right, t3, t2), select(right, t1, t0));
          for (int k = 0; k < 4; ++k) index[k] = select(smooth, index[k], nearest);
          t0 = select(smooth, t0, t_near), t1 = select(smooth, t1, t_near);
          t2 = select(smooth, t2, t_near), t3 = select(smooth, t3, t_near);
          if (has_layer) {
            const P b_near = select(down, select(right, b3, b2), select(right, b1, b0));
            b0 = select(smooth, b0, b_near), b1 = select(smooth, b1, b_near);
            b2 = select(smooth, b2, b_near), b3 = select(smooth, b3, b_near);
          }
          // four copies of the pixel's own texel (its nearest, or a footprint clamped onto it at the border):
          // no occluder, as the nearest fetch's centre texel (Footprint.on_own_texel)
          const I own_index = I(int32_t(px.row * img.W)) + to_int(px.u);
          own = land(land(ieq(index[0], own_index), ieq(index[1], own_index)),
                     land(ieq(index[2], own_index), ieq(index[3], own_index)));
        }
      }
      if (has_layer) layer = lerp(lerp(F(b0), F(b1), fu), lerp(F(b2), F(b3), fu), fv);
      valid = land(land(t0 == t0, t1 == t1), land(t2 == t2, t3 == t3));  // invalid texels hold NaN
      if (cfg.drop)
        valid = land(valid, land(land(fu0 >= F(0.0f), fu0 + F(1.0f) < Wf), land(fv0 >= F(0.0f), fv0 + F(1.0f) < Hf)));
      const F top = lerp(t0, t1, fu), bottom = lerp(t2, t3, fu);
      inverse_su = lerp(t1 - t0, t3 - t2, fv), inverse_sv = bottom - top;
      const F depth = reciprocal(lerp(top, bottom, fv));
      const F su_c = clamp(su, F(0.0f), Wf - F(1.0f)), sv_c = clamp(sv, F(0.0f), Hf - F(1.0f));
#if !TAO_LEAN_WALK
      if (!cfg.unprojected) {
        reads_positions = true, edge_aware = cfg.edge_aware;
        position_taps(img, su_c, sv_c, pos);
      } else
#endif
      {
        unproject(img, su_c, sv_c, depth, pos);
      }
    } else {
      const F fu0 = floor(su + F(0.5f - kNearestTie)), fv0 = floor(sv + F(0.5f - kNearestTie));
      fu = fv = inverse_su = inverse_sv = F(0.0f);
      const I iu = imin(imax(to_int(clamp(fu0, F(-1.0f), Wf)), zero), Wlast);
      const I iv = imin(imax(to_int(clamp(fv0, F(-1.0f), Hf)), zero), Hlast);
      index[0] = iv * Wi + iu;
      index[1] = index[2] = index[3] = index[0];
      if (cfg.unprojected) {  // GBuffer.positions' unprojection of the texel's depth, bit for bit
        const F depth = tao::gather(img.depth, index[0]);
        valid = depth == depth;  // (invalid texels hold NaN)
        unproject(img, to_float(iu), to_float(iv), depth, pos);
      } else {
        valid = gather_flag(img.valid, index[0]);  // (as the inverse depth's NaN: 4x fewer bytes to fetch)
        for (int c = 0; c < 3; ++c) pos[c] = tao::gather(img.positions + c, index[0] * I(3));
      }
      if (cfg.drop) valid = land(valid, land(land(fu0 >= F(0.0f), fu0 < Wf), land(fv0 >= F(0.0f), fv0 < Hf)));
    }
    for (int c = 0; c < 3; ++c) delta[c] = pos[c] - px.P[c];
    // a sample on the centre texel, or within float rounding of the pixel's own position (Sample's MIN_OFFSET),
    // would occlude in a direction made of noise: it never occludes
    F rel[3];
    for (int c = 0; c < 3; ++c) rel[c] = delta[c] * px.inverse_depth;
    valid = land(valid, dot3(rel, rel) > F(kMinOffset * kMinOffset));
    if (cfg.edge_aware) valid = land(valid, lnot(own));
    for (int c = 0; c < 3; ++c) delta[c] = select(valid, delta[c], neg(px.V[c]));
  }
};

// The hand-written backwards' adjoint of a slice's step placement (along_u, along_v over step_distance's power
// placement) from each step's d L / d (su, sv): d L / d the slice's unit_u, unit_v and span; and on to the
// intrinsics through the slice's screen motion (du, dv) = (fx a, -fy b) / depth, whose direction the unit is and
// whose length len sets the span = clamp_min(min(R len stretch, max_radius_px) - min_step_px, 0)
template <class F> struct PlacementAdjoint {
  F unit_u = F(0.0f), unit_v = F(0.0f), span = F(0.0f);

  // the step dist pixels out on side: (su, sv) = (u, v) + side dist (unit_u, unit_v), dist = min_step_px + span frac
  TAO_FN void add(const WalkSettings& cfg, const Slice<F>& sl, float side, const F& dist, const F& g_su, const F& g_sv) {
    const F gu = g_su * F(side), gv = g_sv * F(side);
    unit_u = unit_u + gu * dist, unit_v = unit_v + gv * dist;
    const F frac = (dist - F(cfg.min_step_px)) / select(sl.span > F(0.0f), sl.span, F(1.0f));
    span = span + (gu * sl.unit_u + gv * sl.unit_v) * frac;
  }
  // d L / d fx, fy added to g_cam[0], g_cam[1]
  TAO_FN void camera(const WalkSettings& cfg, const Image& img, const Slice<F>& sl, F* g_cam) const {
    const F len = sl.screen_length, inv = reciprocal(clamp_min(len, F(1e-12f)));
    const F uu = sl.unit_u, uv = sl.unit_v;
    F along_len = sl.radius_px * inv;  // d span / d len where no clamp holds
    if (cfg.max_radius_px > 0) along_len = select(sl.radius_px < F(cfg.max_radius_px), along_len, F(0.0f));
    along_len = select(sl.radius_px - F(cfg.min_step_px) >= F(0.0f), along_len, F(0.0f));
    const auto moving = len > F(1e-12f);
    const F g_len = span * along_len;
    const F g_du = select(moving, (unit_u * (F(1.0f) - uu * uu) - unit_v * uu * uv) * inv, F(0.0f)) + g_len * uu;
    const F g_dv = select(moving, (unit_v * (F(1.0f) - uv * uv) - unit_u * uu * uv) * inv, F(0.0f)) + g_len * uv;
    g_cam[0] = g_cam[0] + g_du * (uu * len) / F(img.fx);  // d du / d fx = du / fx
    g_cam[1] = g_cam[1] + g_dv * (uv * len) / F(img.fy);
  }
};

// d pos[c] / d its focal length and centre (c = 0: fx, cx; 1: fy, cy) of a bilinear fetch's position
// ((su - cx) / fx, -(sv - cy) / fy, -1) depth
template <class F>
TAO_FN void unprojection_partials(const Image& img, const F* pos, int c, F& d_focal, F& d_centre) {
  const F focal = F(c == 0 ? img.fx : img.fy);
  d_focal = neg(pos[c]) / focal;
  d_centre = F(c == 0 ? 1.0f : -1.0f) * pos[2] / focal;  // (depth = -pos[2])
}

// The lanes of a bilinear fetch (taps index) whose position is an unprojection at (su, sv), so moves with the
// intrinsics: every lane of a depth read; of a position buffer's (Sample::position_taps), the edge-aware fetch's one
// texel
template <class F>
TAO_FN typename LaneTraits<F>::M unprojected_lanes(const WalkSettings& cfg, const typename LaneTraits<F>::I* index) {
  const auto none = F(0.0f) > F(1.0f);
  if (cfg.unprojected) return lnot(none);
  return cfg.edge_aware ? equal_taps<F>(index) : none;
}

// d L / d fx, fy, cx, cy of a bilinear fetch's position (taps index) from d L / d the position g_pos, on the lanes
// `on` where it is an unprojection (unprojected_lanes), added to g_cam
template <class F>
TAO_FN void unprojection_camera(const WalkSettings& cfg, const Image& img, const typename LaneTraits<F>::I* index,
                                const F* pos, const F* g_pos, const typename LaneTraits<F>::M& on, F* g_cam) {
  const auto moving = land(on, unprojected_lanes<F>(cfg, index));
  for (int c = 0; c < 2; ++c) {
    F d_focal, d_centre;
    unprojection_partials(img, pos, c, d_focal, d_centre);
    g_cam[c] = g_cam[c] + select(moving, g_pos[c] * d_focal, F(0.0f));
    g_cam[2 + c] = g_cam[2 + c] + select(moving, g_pos[c] * d_centre, F(0.0f));
  }
}

// A walk's sample at screen (su, sv): Sample's fetch (walk_grad.h's reverse lanes overload it: the fetched
// position a leaf of their tape, its taps kept for the backward's scatter)
template <class F>
TAO_HOT Sample<F> fetch_sample(const WalkSettings& cfg, const Image& img, const Pixels<F>& px, const F& su, const F& sv) {
  return Sample<F>(cfg, img, px, su, sv);
}

// acc.begin_slice(px, sl, sums) where the accumulator takes the sums so far, else acc.begin_slice(px, sl)
template <class Acc, class F, class S>
TAO_FN auto begin_slice_of(const Acc& acc, const Pixels<F>& px, const Slice<F>& sl, const S& sums, int)
    -> decltype(acc.begin_slice(px, sl, sums)) {
  return acc.begin_slice(px, sl, sums);
}
template <class Acc, class F, class S>
TAO_FN auto begin_slice_of(const Acc& acc, const Pixels<F>& px, const Slice<F>& sl, const S&, long)
    -> decltype(acc.begin_slice(px, sl)) {
  return acc.begin_slice(px, sl);
}

// Whether an accumulator takes step j of both sides together (Acc::kPairedSides: walk_pairs)
template <class Acc, class = void> struct PairedSides {
  static constexpr bool value = false;
};
template <class Acc> struct PairedSides<Acc, decltype(void(Acc::kPairedSides))> {
  static constexpr bool value = Acc::kPairedSides;
};

// Nothing to do after a step (walk_slice's visitor of the plain walk)
struct NoVisit {
  static constexpr bool kBefore = false;  // (a visitor that reads the state before the step says so)
  template <class... T> TAO_FN void operator()(const T&...) const {}
};

// One slice of GTAO's Algorithm 1 (march's loop): for each side (one with full_circle), each step; after
// each step visit(side, j, sample, state before the step, state after it) (where Visit::kBefore; else the
// state after it twice)
template <class F, class Acc, class Visit>
TAO_FN void walk_slice(const WalkSettings& cfg, const Image& img, const Acc& acc, const Pixels<F>& px,
                       const Slice<F>& sl, typename Acc::template State<F>& state, Visit& visit) {
  for (int side = 1; side >= (cfg.full_circle ? 1 : -1); side -= 2) {  // for each side
    const F xi = step_noise(cfg, px, sl, side);
    for (int64_t j = 0; j < cfg.steps; ++j) {  // for each sample
      F su, sv;
      step_screen(cfg, img, px, sl, float(side), xi, j, su, sv);
      const Sample<F> sample = fetch_sample(cfg, img, px, su, sv);
      if constexpr (Visit::kBefore) {  // (a copy of the state per step only for a visitor that reads it)
        const typename Acc::template State<F> before = state;
        acc.step(state, side, px, sl, sample);
        visit(side, j, sample, before, state);
      } else {
        acc.step(state, side, px, sl, sample);
        visit(side, j, sample, state, state);
      }
    }
  }
}

// SSAO's tangent frame around the pixel's normal N (methods/ssao.py's _tangent_frame): the screen direction
// r = (cos, sin, 0) of the pixel's rotation 2 pi a (a its noise, 0 without jitter) made orthogonal to N, or +Z
// made so where r is within 1e-3 of N's direction; t normalized, b = cross(N, t)
template <class F> struct TangentFrame {
  F t[3], b[3];

  TAO_FN explicit TangentFrame(const Pixels<F>& px) {
    float lane[LaneTraits<F>::L];
    for (int l = 0; l < LaneTraits<F>::L; ++l) lane[l] = 2.0f * kPi * px.rotation[l];
    const F alpha = from_lanes(lane, F(0.0f));
    const F r[3] = {cos(alpha), sin(alpha), F(0.0f)};
    const F along = dot3(r, px.N);
    F ortho[3], ortho_z[3];
    for (int c = 0; c < 3; ++c) ortho[c] = r[c] - px.N[c] * along;
    for (int c = 0; c < 3; ++c) ortho_z[c] = (c == 2 ? F(1.0f) : F(0.0f)) - px.N[c] * px.N[2];
    const auto apart = norm3(ortho) > F(1e-3f);
    F chosen[3];
    for (int c = 0; c < 3; ++c) chosen[c] = select(apart, ortho[c], ortho_z[c]);
    normalize3(chosen, t);
    cross(px.N, t, b);
  }
};

// Kernel point j of the hemisphere placement (methods/ssao.py's kernel_points): the table's (x, y, z) times the
// radius, in the pixel's tangent frame (z along N), around its position
template <class F>
TAO_FN void kernel_point(const WalkSettings& cfg, const Pixels<F>& px, const TangentFrame<F>& frame, int64_t j, F* S) {
  const float* k = cfg.table + 3 * j;
  const F x = F(k[0] * cfg.radius), y = F(k[1] * cfg.radius), z = F(k[2] * cfg.radius);
  for (int c = 0; c < 3; ++c) S[c] = px.P[c] + x * frame.t[c] + y * frame.b[c] + z * px.N[c];
}

// Where the view-space point S projects, in screen pixels (camera.view_to_pixels), its depth -S.z clamped to
// 1e-6 of the pixel's (a point behind the camera: kernel_occlusion's, which then occludes nothing)
template <class F>
TAO_FN void project_point(const Image& img, const Pixels<F>& px, const F* S, F& su, F& sv) {
  using V = typename ValueOf<F>::type;
  const F d = clamp_min(neg(S[2]), F(value(px.depth) * V(1e-6f)));
  su = (S[0] / d) * seed_camera(F(img.fx), 0) + seed_camera(F(img.cx), 2);
  sv = (neg(S[1]) / d) * seed_camera(F(img.fy), 1) + seed_camera(F(img.cy), 3);
}

// Whether an accumulator takes the hemisphere placement's kernel points (Acc::kKernelPoints: walk_points)
template <class Acc, class = void> struct KernelPoints {
  static constexpr bool value = false;
};
template <class Acc> struct KernelPoints<Acc, decltype(void(Acc::kKernelPoints))> {
  static constexpr bool value = Acc::kKernelPoints;
};

// Whether the bitmask family's sector accumulators weigh their slices (and so take slices drawn by the projected
// normal's density): not in the lean CUDA build. There the draw cost registers in every call, drawn or not (ptxas,
// sm_90: tao_walk_exact_gradients 167 -> 172 registers and 19 % -> 12 % occupancy, tao_walk_bitmask's spill
// 60 -> 152 bytes, tao_walk_soft's 0 -> 32). (GTAO's walks have it in both.)
constexpr bool kSectorsWeighSlices = !kLeanWalk;
// x weighed by slice sl's estimator weight where kSectorsWeighSlices (else x: no arithmetic in the lean CUDA build)
template <class F, class G> TAO_FN G weighed(const Slice<F>& sl, const G& x) {
  if constexpr (kSectorsWeighSlices) return G(sl.weight) * x;
  else return x;
}
// Whether this walk's sector accumulators take slices drawn by the projected normal's density (whose weights the
// backwards then differentiate)
TAO_FN bool sectors_drawn(const WalkSettings& cfg) { return kSectorsWeighSlices && cfg.projected_normal; }
// kWeighsSlices says an accumulator weighs each slice's sums by Slice::weight (horizon.h's GTAO, bitmask.h's and
// soft.h's sector accumulators), so that its walk may draw the slices' azimuths by the projected normal's density
// (WalkSettings::projected_normal)
template <class Acc, class = void> struct WeighsSlices {
  static constexpr bool value = false;
};
template <class Acc> struct WeighsSlices<Acc, decltype(void(Acc::kWeighsSlices))> {
  static constexpr bool value = Acc::kWeighsSlices;
};

// Whether an accumulator reads the slice's projected normal (its length, its angle gamma): all but those whose
// kScreenOnly says they read the slice's screen direction and extent alone (UE4 SSAO's wedges, PSSAO), whose
// walk leaves the normal's arithmetic out (and their backward's tape its nodes)
template <class Acc, class = void> struct ReadsSliceNormal {
  static constexpr bool value = true;
};
template <class Acc> struct ReadsSliceNormal<Acc, decltype(void(Acc::kScreenOnly))> {
  static constexpr bool value = !Acc::kScreenOnly;
};

// Slice s of the walk as Acc takes it: its geometry (without the projected normal where Acc reads none), or none
// for an accumulator of kernel points (walk_points); where Acc weighs its slices and the walk draws them by the
// projected normal's density, at the azimuth of quantile (s + a) / slices (SlicePattern.slice_direction) with its
// weight
template <class Acc, class F>
TAO_FN Slice<F> walked_slice(const WalkSettings& cfg, const Image& img, const Pixels<F>& px, int64_t s) {
  if constexpr (KernelPoints<Acc>::value) {
    return Slice<F>(s);
  } else {
    if constexpr (WeighsSlices<Acc>::value) {
      if (cfg.projected_normal) {
        float lane[LaneTraits<F>::L];
        for (int l = 0; l < LaneTraits<F>::L; ++l) lane[l] = (px.rotation[l] + float(s)) / float(cfg.slices);
        F weight;
        const F azimuth = projected_normal_azimuth(px, from_lanes(lane, F(0.0f)), weight);
        Slice<F> sl(cfg, img, px, s, ReadsSliceNormal<Acc>::value, &azimuth);
        sl.weight = weight;
        return sl;
      }
    }
    return Slice<F>(cfg, img, px, s, ReadsSliceNormal<Acc>::value);
  }
}

// The hemisphere placement's one slice (SSAO's kernel_occlusion): each of the steps kernel points projected and
// fetched there, acc.step_point(state, px, S, sample)
template <class F, class Acc>
TAO_FN void walk_points(const WalkSettings& cfg, const Image& img, const Acc& acc, const Pixels<F>& px,
                        typename Acc::template State<F>& state) {
  const TangentFrame<F> frame(px);
  for (int64_t j = 0; j < cfg.steps; ++j) {
    F S[3], su, sv;
    kernel_point(cfg, px, frame, j, S);
    project_point(img, px, S, su, sv);
    const Sample<F> sample = fetch_sample(cfg, img, px, su, sv);
    acc.step_point(state, px, S, sample);
  }
}

// One slice of a paired accumulator (march's paired_sides: SliceAccumulator.paired_sides, UE4 SSAO's
// symmetric pairs): step j of side +1 and of side -1 taken together, acc.step_pair(state, px, sl, plus, minus)
template <class F, class Acc>
TAO_FN void walk_pairs(const WalkSettings& cfg, const Image& img, const Acc& acc, const Pixels<F>& px,
                       const Slice<F>& sl, typename Acc::template State<F>& state) {
  const F xi_plus = step_noise(cfg, px, sl, 1), xi_minus = step_noise(cfg, px, sl, -1);
  for (int64_t j = 0; j < cfg.steps; ++j) {
    F su, sv;
    step_screen(cfg, img, px, sl, 1.0f, xi_plus, j, su, sv);
    const Sample<F> plus = fetch_sample(cfg, img, px, su, sv);
    step_screen(cfg, img, px, sl, -1.0f, xi_minus, j, su, sv);
    const Sample<F> minus = fetch_sample(cfg, img, px, su, sv);
    acc.step_pair(state, px, sl, plus, minus);
  }
}

// GTAO's Algorithm 1 for the n <= L pixels of a row from column u0: every slice's walk (walk_slice);
// out[c] receives channel c of every lane.
template <class F, class Acc>
TAO_FN void walk_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row, int64_t u0, int n,
                       F* out) {
  const Pixels<F> px(cfg, img, row, u0, n);
  typename Acc::template Sums<F> sums;
  if (any(px.live)) {
    NoVisit none;
    for (int64_t s = 0; s < cfg.slices; ++s) {  // for each slice
      const Slice<F> sl = walked_slice<Acc>(cfg, img, px, s);
      typename Acc::template State<F> state = begin_slice_of(acc, px, sl, sums, 0);
      if constexpr (PairedSides<Acc>::value) {
        walk_pairs(cfg, img, acc, px, sl, state);
      } else if constexpr (KernelPoints<Acc>::value) {
        walk_points(cfg, img, acc, px, state);
      } else {
        walk_slice(cfg, img, acc, px, sl, state, none);
      }
      acc.end_slice(state, px, sl, sums);
    }
  }
  acc.finish(sums, px, out);
}

}  // namespace tao
