// The walk of torch_ao.walk (slice directions, jitter, step placement, fetch, border) for the fused CPU
// kernels: one pixel's walk in registers, SIMD across the pixels of a row (ATen's Vectorized<float>,
// whose atan2/pow are the SLEEF functions torch's own CPU kernels call), rows over torch's threads.
//
// The float arithmetic repeats the tensor path's operation by operation: where a torch CPU kernel
// fuses a multiply and an add (cross products, addcmul, lerp, the tail of a 2-/3-element norm) this
// code calls fma, and nowhere else (the kernels are built with -ffp-contract=off); torch's unary
// functions that call MKL's vector math on this build (cos, sin, asin, sqrt) are MKL's here too. The
// names follow torch_ao/walk (GTAO's Algorithm 1 in walk.py): Pixels is Frame's queries, Slice is
// slice_geometry, step_distance is SlicePattern.step_offsets, Sample is fetch_sample + Sample's
// valid/delta, walk<Accumulator> is the walk's loop.
#pragma once

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <ATen/ops/empty.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "mkl_vml.h"  // torch.cos/torch.sin on a build with MKL call its vector math; so do the kernels
#include "lanes_simd.h"
#include "rows_cpu.h"
#include "walk.h"

namespace torch_ao_walk {

using torch_ao_rows::for_each_row;
using torch_ao_rows::over_rows;

using Vec = at::vec::Vectorized<float>;
using Int = at::vec::Vectorized<int32_t>;
constexpr int L = Vec::size();

inline Vec fma(const Vec& a, const Vec& b, const Vec& c) { return at::vec::fmadd(a, b, c); }
inline Vec dot3(const Vec* a, const Vec* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }
// torch's norm over a last dimension shorter than a vector: an fma chain, then sqrt
inline Vec norm3(const Vec* a) { return fma(a[2], a[2], fma(a[1], a[1], a[0] * a[0])).sqrt(); }
inline Vec norm2(const Vec& a, const Vec& b) { return fma(b, b, a * a).sqrt(); }
inline Vec select(const Vec& mask, const Vec& yes, const Vec& no) { return Vec::blendv(no, yes, mask); }
// torch.sign (0 for 0 and NaN)
inline Vec sign(const Vec& x) {
  return select(x > Vec(0.0f), Vec(1.0f), select(x < Vec(0.0f), Vec(-1.0f), Vec(0.0f)));
}
// torch's cross(a, b) as its CPU kernel evaluates it
inline void cross(const Vec* a, const Vec* b, Vec* out) {
  out[0] = fma(a[1], b[2], (a[2] * b[1]).neg());
  out[1] = fma(a[2], b[0], (a[0] * b[2]).neg());
  out[2] = fma(a[0], b[1], (a[1] * b[0]).neg());
}
// F.normalize(x, eps=1e-12)
inline void normalize3(const Vec* x, Vec* out) {
  const Vec len = at::vec::clamp_min(norm3(x), Vec(1e-12f));
  for (int c = 0; c < 3; ++c) out[c] = x[c] / len;
}
// torch.lerp: start + w (end - start) for |w| < 0.5, else end - (1 - w) (end - start), both fused
inline Vec lerp(const Vec& start, const Vec& end, const Vec& w) {
  Vec small = w.abs() < Vec(0.5f);
  return fma(select(small, w, w - Vec(1.0f)), end - start, select(small, start, end));
}
inline Int to_int(const Vec& x) { return at::vec::convert_to_int_of_same_size<float>(x); }

// cos and sin of n * L floats, through MKL's vector math where torch.cos/torch.sin use it
inline void cos_sin(const Vec* x, int n, Vec* cosine, Vec* sine) {
#ifdef TORCH_AO_MKL_VML
  constexpr long long mode = kVmlMode;
  alignas(64) float in[8 * L], out[8 * L];
  for (int i = 0; i < n; ++i) x[i].store(in + i * L);
  if (cosine != nullptr) {
    vmsCos(n * L, in, out, mode);
    for (int i = 0; i < n; ++i) cosine[i] = Vec::loadu(out + i * L);
  }
  if (sine != nullptr) {
    vmsSin(n * L, in, out, mode);
    for (int i = 0; i < n; ++i) sine[i] = Vec::loadu(out + i * L);
  }
#else
  for (int i = 0; i < n; ++i) {
    if (cosine != nullptr) cosine[i] = x[i].cos();
    if (sine != nullptr) sine[i] = x[i].sin();
  }
#endif
}

#ifdef TORCH_AO_MKL_VML
// one VML function on L floats
inline Vec vml(void (*fn)(int, const float*, float*, long long), const Vec& x) {
  alignas(64) float in[L], out[L];
  x.store(in);
  fn(L, in, out, kVmlMode);
  return Vec::loadu(out);
}
#endif

// torch.asin, torch.sqrt: MKL's vector math where torch calls it (its sqrt is accurate to 1 ulp, not
// always the IEEE root that torch's norms and Vec::sqrt give), else SLEEF / the instruction
#ifdef TORCH_AO_MKL_VML
inline Vec asin(const Vec& x) { return vml(vmsAsin, x); }
inline Vec sqrt(const Vec& x) { return vml(vmsSqrt, x); }
#else
inline Vec asin(const Vec& x) { return x.asin(); }
inline Vec sqrt(const Vec& x) { return x.sqrt(); }
#endif

// the noise, the step placement and the walk's settings: walk.h's
using tao::ign;
using tao::Steps;
using tao::WalkSettings;

// One image of the batch: its intrinsics, inverse depth (NaN where invalid), positions (H, W, 3).
struct Image {
  int64_t H, W;
  float fx, fy, cx, cy;
  const float* inverse;
  const float* positions;
};

// The cos and sin of every pixel's slice angles along a row, one vector-math call per row (torch
// evaluates them over all pixels at once): SlicePattern.slice_tangent's (s + a) * span / slices.
struct SliceAngles {
  int64_t stride;
  std::vector<float> cosine, sine;

  SliceAngles(const WalkSettings& cfg, int64_t row, int64_t W) : stride((W + L - 1) / L * L) {
    const int64_t S = cfg.slices;
    const float step = float((cfg.full_circle ? 2.0 : 1.0) * M_PI / double(S));
    std::vector<float> angle(S * stride);
    cosine.resize(angle.size());
    sine.resize(angle.size());
    for (int64_t u = 0; u < stride; ++u) {
      const float a = cfg.jitter ? ign(float(u), float(row), cfg.seed) : 0.0f;
      for (int64_t s = 0; s < S; ++s) angle[s * stride + u] = (a + float(s)) * step;
    }
#ifdef TORCH_AO_MKL_VML
    constexpr long long mode = kVmlMode;
    vmsCos(int(angle.size()), angle.data(), cosine.data(), mode);
    vmsSin(int(angle.size()), angle.data(), sine.data(), mode);
#else
    for (size_t i = 0; i < angle.size(); i += L) {
      Vec x = Vec::loadu(angle.data() + i);
      x.cos().store(cosine.data() + i);
      x.sin().store(sine.data() + i);
    }
#endif
  }
  Vec cos(int64_t s, int64_t u0) const { return Vec::loadu(cosine.data() + s * stride + u0); }
  Vec sin(int64_t s, int64_t u0) const { return Vec::loadu(sine.data() + s * stride + u0); }
};

// L pixels of a row (Frame's queries): P, N, V = normalize(-P), depth, u, v, the step noise xi, and
// the basis e1 = normalize(cross(+Y, V)), e2 = cross(V, e1) around V. Lanes past the row's end repeat
// its last pixel and are not live.
struct Pixels {
  int n;      // lanes inside the row
  bool any;   // whether a lane is live
  Vec P[3], N[3], V[3], e1[3], e2[3], depth, u, v, xi, live;

  Pixels(const WalkSettings& cfg, const Image& img, const float* normals, const float* depth_plane, const bool* valid,
         int64_t row, int64_t u0) {
    const int64_t W = img.W;
    n = int(std::min<int64_t>(L, W - u0));
    alignas(64) float lane[10][L];
    any = false;
    for (int l = 0; l < L; ++l) {
      const int64_t p = row * W + u0 + std::min(l, n - 1);
      const bool ok = l < n && valid[p];
      any |= ok;
      for (int c = 0; c < 3; ++c) {
        lane[c][l] = img.positions[3 * p + c];
        lane[3 + c][l] = normals[3 * p + c];
      }
      lane[6][l] = depth_plane[p];
      lane[7][l] = float(u0 + l);
      lane[8][l] = ok ? 1.0f : 0.0f;
      lane[9][l] = cfg.jitter ? ign(float(u0 + l) + 37.0f, float(row) + 59.0f, cfg.seed + 1) : 0.5f;
    }
    if (!any) return;
    for (int c = 0; c < 3; ++c) {
      P[c] = Vec::loadu(lane[c]);
      N[c] = Vec::loadu(lane[3 + c]);
    }
    depth = Vec::loadu(lane[6]);
    u = Vec::loadu(lane[7]);
    v = Vec(float(row));
    live = Vec::loadu(lane[8]) > Vec(0.5f);
    xi = Vec::loadu(lane[9]);
    const Vec minus[3] = {P[0].neg(), P[1].neg(), P[2].neg()};
    normalize3(minus, V);
    if (!cfg.screen_azimuth) {
      const Vec c1[3] = {V[2], Vec(0.0f), V[0].neg()};  // cross(+Y, V)
      normalize3(c1, e1);
      cross(V, e1, e2);
    }
  }
};

// slice_geometry: the slice tangent T, its plane's axis, the projected normal's length and angle
// gamma from V, and the walk's screen direction and extent (SlicePattern.radius_px and the span).
struct Slice {
  Vec T[3], axis[3], length, gamma, unit_u, unit_v, radius_px, span;

  Slice(const WalkSettings& cfg, const Image& img, const Pixels& px, const Vec& cs, const Vec& sn) {
    if (cfg.screen_azimuth) {  // tangent_from_screen_angle: (cos, sin, 0) made orthogonal to V
      const Vec d[3] = {cs, sn, Vec(0.0f)};
      const Vec along = dot3(d, px.V);
      Vec t[3];
      for (int c = 0; c < 3; ++c) t[c] = d[c] - along * px.V[c];
      normalize3(t, T);
    } else {  // tangent_from_view_azimuth
      for (int c = 0; c < 3; ++c) T[c] = cs * px.e1[c] + sn * px.e2[c];
    }
    cross(T, px.V, axis);
    const Vec nd = dot3(px.N, axis);
    Vec np[3];
    for (int c = 0; c < 3; ++c) np[c] = px.N[c] - axis[c] * nd;
    length = norm3(np);
    gamma = dot3(np, T).atan2(dot3(np, px.V));
    // screen motion (pixels per world unit along +T) of the projection (fx x/d + cx, -fy y/d + cy)
    const Vec du = (Vec(img.fx) * (T[0] + (px.P[0] * T[2]) / px.depth)) / px.depth;
    const Vec dv = (Vec(-img.fy) * (T[1] + (px.P[1] * T[2]) / px.depth)) / px.depth;
    const Vec len = norm2(du, dv);
    unit_u = du / at::vec::clamp_min(len, Vec(1e-12f));
    unit_v = dv / at::vec::clamp_min(len, Vec(1e-12f));
    radius_px = Vec(cfg.radius) * len;
    if (cfg.placement == Steps::power) {
      if (cfg.max_radius_px > 0) radius_px = at::vec::clamp_max(radius_px, Vec(cfg.max_radius_px));
      span = at::vec::clamp_min(radius_px - Vec(cfg.min_step_px), Vec(0.0f));
    } else {  // ShaderStepPattern: R_px clamped to [steps, max_radius_px], dt = R_px / (steps + 1)
      const Vec steps = Vec(float(cfg.steps));
      radius_px = at::vec::clamp_min(radius_px, steps);
      if (cfg.max_radius_px > 0) radius_px = at::vec::clamp_max(radius_px, Vec(std::max(cfg.max_radius_px, float(cfg.steps))));
      span = radius_px / Vec(float(cfg.steps + 1));
    }
  }
};

// The distance in pixels of step j from the pixel (SlicePattern.step_offsets / ShaderStepPattern)
inline Vec step_distance(const WalkSettings& cfg, const Slice& sl, const Vec& xi, int64_t j) {
  if (cfg.placement == Steps::hdrp) return (Vec(float(j + 1)) + xi) * sl.span;
  if (cfg.placement == Steps::ue4) return at::vec::clamp_min((Vec(float(j)) + xi) * sl.span, Vec(float(j + 1)));
  Vec frac = (Vec(float(j)) + xi) / Vec(float(cfg.steps));
  if (cfg.step_power == 2.0f) {
    frac = frac * frac;
  } else if (cfg.step_power != 1.0f) {
    frac = frac.pow(Vec(cfg.step_power));
  }
  return Vec(cfg.min_step_px) + sl.span * frac;
}

// One sample (fetch_sample and Sample): delta = position - P where valid, else -V (away from the
// camera: it never occludes); valid drops background taps, the border (drop) and the centre texel.
// The perspective-correct bilinear footprint of samples at screen (su, sv) (torch_ao.walk.fetch.bilinear_taps):
// the top-left texel (fu0, fv0), the fractions (fu, fv), the four taps' inverse depths t0..t3 of the
// (W x H) image `inverse_depth` (rows and columns clamped to the image), whether all four are valid
// (an invalid texel holds NaN), and the four texels' indices (to read other images at the same taps).
struct BilinearTaps {
  Vec fu0, fv0, fu, fv, t0, t1, t2, t3, ok;
  Int index[4];
};

inline BilinearTaps bilinear_taps(const float* inverse_depth, const Vec& su, const Vec& sv, int64_t W, int64_t H) {
  const Int zero = Int(0), one = Int(1), Wi = Int(int32_t(W)), Wlast = Int(int32_t(W - 1)), Hlast = Int(int32_t(H - 1));
  BilinearTaps tap;
  tap.fu0 = su.floor();
  tap.fv0 = sv.floor();
  tap.fu = su - tap.fu0;
  tap.fv = sv - tap.fv0;
  const Int iu = at::vec::convert_to_int_of_same_size<float>(at::vec::clamp(tap.fu0, Vec(-1.0f), Vec(float(W))));
  const Int iv = at::vec::convert_to_int_of_same_size<float>(at::vec::clamp(tap.fv0, Vec(-1.0f), Vec(float(H))));
  const Int c0 = at::vec::clamp(iu, zero, Wlast), c1 = at::vec::clamp(iu + one, zero, Wlast);
  const Int r0 = at::vec::clamp(iv, zero, Hlast) * Wi, r1 = at::vec::clamp(iv + one, zero, Hlast) * Wi;
  tap.index[0] = r0 + c0, tap.index[1] = r0 + c1, tap.index[2] = r1 + c0, tap.index[3] = r1 + c1;
  tap.t0 = at::vec::gather<4>(inverse_depth, tap.index[0]);
  tap.t1 = at::vec::gather<4>(inverse_depth, tap.index[1]);
  tap.t2 = at::vec::gather<4>(inverse_depth, tap.index[2]);
  tap.t3 = at::vec::gather<4>(inverse_depth, tap.index[3]);
  tap.ok = (tap.t0 == tap.t0) & (tap.t1 == tap.t1) & (tap.t2 == tap.t2) & (tap.t3 == tap.t3);
  return tap;
}

struct Sample {
  Vec delta[3], valid;

  Sample(const WalkSettings& cfg, const Image& img, const Pixels& px, const Slice& sl, const Vec& side, const Vec& dist) {
    const Int zero_i = Int(0), Wi = Int(int32_t(img.W));
    const Int Wlast = Int(int32_t(img.W - 1)), Hlast = Int(int32_t(img.H - 1));
    const Vec Wf = Vec(float(img.W)), Hf = Vec(float(img.H));
    const Vec su = px.u + dist * (sl.unit_u * side), sv = px.v + dist * (sl.unit_v * side);
    Vec pos[3];
    if (cfg.bilinear) {
      const BilinearTaps tap = bilinear_taps(img.inverse, su, sv, img.W, img.H);
      const Vec &fu0 = tap.fu0, &fv0 = tap.fv0;
      valid = tap.ok;  // invalid texels hold NaN: a sample is valid when its four taps are
      if (cfg.drop) {
        valid = valid & (fu0 >= Vec(0.0f)) & (fu0 + Vec(1.0f) < Wf) & (fv0 >= Vec(0.0f)) & (fv0 + Vec(1.0f) < Hf);
      }
      const Vec depth = lerp(lerp(tap.t0, tap.t1, tap.fu), lerp(tap.t2, tap.t3, tap.fu), tap.fv).reciprocal();
      const Vec su_c = at::vec::clamp(su, Vec(0.0f), Wf - Vec(1.0f)), sv_c = at::vec::clamp(sv, Vec(0.0f), Hf - Vec(1.0f));
      pos[0] = ((su_c - Vec(img.cx)) / Vec(img.fx)) * depth;
      pos[1] = ((sv_c - Vec(img.cy)).neg() / Vec(img.fy)) * depth;
      pos[2] = depth.neg();
    } else {
      const Vec fu0 = (su + Vec(0.5f)).floor(), fv0 = (sv + Vec(0.5f)).floor();
      const Int iu = at::vec::clamp(to_int(at::vec::clamp(fu0, Vec(-1.0f), Wf)), zero_i, Wlast);
      const Int iv = at::vec::clamp(to_int(at::vec::clamp(fv0, Vec(-1.0f), Hf)), zero_i, Hlast);
      const Int texel = iv * Wi + iu, at3 = texel * Int(3);
      const Vec t = at::vec::gather<4>(img.inverse, texel);
      valid = t == t;
      if (cfg.drop) valid = valid & (fu0 >= Vec(0.0f)) & (fu0 < Wf) & (fv0 >= Vec(0.0f)) & (fv0 < Hf);
      for (int c = 0; c < 3; ++c) pos[c] = at::vec::gather<4>(img.positions + c, at3);
    }
    for (int c = 0; c < 3; ++c) delta[c] = pos[c] - px.P[c];
    // a sample on the centre texel (or a degenerate one) would give 0/0 angles: it never occludes
    valid = valid & (dot3(delta, delta) > Vec(1e-20f) * (px.depth * px.depth));
    for (int c = 0; c < 3; ++c) delta[c] = select(valid, delta[c], px.V[c].neg());
  }
};

}  // namespace torch_ao_walk
