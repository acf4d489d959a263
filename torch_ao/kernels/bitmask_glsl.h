// The "ssilvb_glsl" variant's accumulator (methods/bitmask_glsl.py GLSLAccumulator, hard mode) for walk.h
// with the GLSL step placement and noise: the SSILVB GLSL article's shader per step, its quirks kept
// (the occlusion mask and the light carried across slices, the unnormalised slice axis, the light
// weight 1 - newly / 32, sums over sliceCount + 1 slices divided by sliceCount), and the driver's
// numerics of glsl_numerics="mesa": Mesa's asin polynomial and llvmpipe's dot / length / normalize.
#pragma once

#include "bitmask.h"
#include "lanes_dual.h"

namespace tao {

// Mesa's GLSL asin polynomial (bitmask_glsl.mesa_asin), x in [-1, 1]
template <class F> TAO_FN F mesa_asin(const F& x) {
  const F ax = abs(x);
  const F poly = F(kHalfPi) + ax * (F(kPi / 4.0f - 1.0f) + ax * (F(0.08132463f) + ax * F(-0.02363318f)));
  return sign(x) * (F(kHalfPi) - sqrt(F(1.0f) - ax) * poly);
}

// acos as the shader's driver takes it (Mesa's: pi/2 - its asin polynomial), and its slope as the tensor walk's
// autograd takes it (ops.clamped_gradient: 0 beyond 1 - 1e-6 in magnitude, and Mesa's at 0, where sign(x) is 0)
template <class F> TAO_FN F glsl_acos(bool mesa, const F& x) { return mesa ? F(kHalfPi) - mesa_asin(x) : acos(x); }
template <class F> TAO_FN F glsl_acos_slope(bool mesa, const F& x) {
  const F ax = abs(x);
  F slope;
  if (mesa) {  // -(d/dx mesa_asin) = -(poly / (2 root) - root poly'), root = sqrt(1 - |x|)
    const F root = sqrt(F(1.0f) - ax);
    const F poly = F(kHalfPi) + ax * (F(kPi / 4.0f - 1.0f) + ax * (F(0.08132463f) + ax * F(-0.02363318f)));
    const F dpoly = F(kPi / 4.0f - 1.0f) + ax * (F(2.0f * 0.08132463f) + ax * F(3.0f * -0.02363318f));
    slope = select(ax > F(0.0f), neg(poly / (F(2.0f) * root) - root * dpoly), F(0.0f));
  } else {
    slope = neg(asin_slope(x));
  }
  return select(ax <= F(1.0f - 1e-6f), slope, F(0.0f));
}
template <class F, int N> TAO_FN Dual<F, N> glsl_acos(bool mesa, const Dual<F, N>& x) {
  return Dual<F, N>::chain(glsl_acos(mesa, x.v), glsl_acos_slope(mesa, x.v), x);
}

// The shader's dot / length / normalize as its driver evaluates them (bitmask_glsl.GLSLVectorOps):
// llvmpipe's with exact (each product and sum rounded, dot = (a.y b.y + a.z b.z) + a.x b.x,
// normalize = v (1 / sqrt(dot(v, v)))), else the walk's dot3 / norm3 / normalize3
struct GlslVectorOps {
  bool exact;
  template <class F> TAO_FN F dot(const F* a, const F* b) const {
    return exact ? (a[1] * b[1] + a[2] * b[2]) + a[0] * b[0] : dot3(a, b);
  }
  template <class F> TAO_FN F length(const F* a) const { return exact ? sqrt(dot(a, a)) : norm3(a); }
  template <class F> TAO_FN void normalize(const F* a, F* out) const {
    if (!exact) return normalize3(a, out);
    const F inv = F(1.0f) / sqrt(dot(a, a));
    for (int c = 0; c < 3; ++c) out[c] = a[c] * inv;
  }
};

struct GlslAccumulator {
  int64_t slice_count;  // the shader's sliceCount: the sums' divisor (the walk walks sliceCount + 1)
  ThicknessModel thickness;  // hitThickness at a sample, world units (the shader's one number, or a layer)
  int64_t rounding;
  bool indirect;
  GlslVectorOps gl;

  template <class F> struct Sums {
    typename LaneTraits<F>::I occ = typename LaneTraits<F>::I(0);  // never reset (as written)
    F visibility = F(0.0f), light[3] = {F(0.0f), F(0.0f), F(0.0f)};
  };
  template <class F> struct State {
    typename LaneTraits<F>::I occ;
    F light[3], camera[3], normal[3];
    F n;  // the projected normal's signed angle
  };
  TAO_FN int channels() const { return indirect ? 4 : 1; }

  // _horizon: clamp((acos(c) + n + halfPi) / pi, 0, 1), 0 where acos is NaN (NaN, or with Mesa's numerics
  // |c| > 1; "ieee" takes c clamped to [-1, 1]); Mesa folds acos's pi/2 into the + halfPi: (pi - asin(c)) + n.
  // raw: the value before the clamp where the cosine is not NaN, else -1 (the backward's: a derivative inside
  // [0, 1] only)
  template <class F> TAO_FN F horizon(const F& cosine, const F& n, F* raw = nullptr) const {
    const auto good = gl.exact ? abs(cosine) <= F(1.0f) : cosine == cosine;
    const F c = select(good, gl.exact ? cosine : clamp(cosine, F(-1.0f), F(1.0f)), F(0.0f));
    const F value = gl.exact ? ((F(kPi) - mesa_asin(c)) + n) / F(kPi) : ((acos(c) + n) + F(kHalfPi)) / F(kPi);
    if (raw) *raw = select(good, value, F(-1.0f));
    return select(good, clamp(value, F(0.0f), F(1.0f)), F(0.0f));
  }

  // The slice's camera direction, the pixel's normal (normalised) and its projected normal's signed angle n
  // (any lane type: the backward takes them in the pixel's tangents)
  template <class F>
  TAO_FN void slice_angles(const Pixels<F>& px, const Slice<F>& sl, F* camera, F* normal, F& n) const {
    if (gl.exact) {
      const F minus[3] = {neg(px.P[0]), neg(px.P[1]), neg(px.P[2])};
      gl.normalize(minus, camera);
    } else {
      for (int c = 0; c < 3; ++c) camera[c] = px.V[c];
    }
    gl.normalize(px.N, normal);
    const F direction[3] = {sl.dir_u, sl.dir_v, F(0.0f)};
    const F along = gl.dot(direction, camera);
    F ortho[3], axis[3], proj[3];
    for (int c = 0; c < 3; ++c) ortho[c] = direction[c] - along * camera[c];
    cross(direction, camera, axis);  // not normalised (as written)
    const F na = gl.dot(normal, axis);
    for (int c = 0; c < 3; ++c) proj[c] = normal[c] - axis[c] * na;
    const F cos_n = clamp(gl.dot(proj, camera) / gl.length(proj), F(0.0f), F(1.0f));
    n = sign(gl.dot(ortho, proj)) * glsl_acos(gl.exact, cos_n);
  }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>& px, const Slice<F>& sl, const Sums<F>& sums) const {
    State<F> st;
    st.occ = sums.occ;
    for (int c = 0; c < 3; ++c) st.light[c] = sums.light[c];
    slice_angles(px, sl, st.camera, st.normal, st.n);
    return st;
  }

  // The back horizon of a sample on the pixel's own texel (sampleDistance 0), of thickness t: the direction -camera,
  // so the whole half circle where t > 0; with the driver's roundings dot(normalize(-camera t), camera) is -1 or
  // just below (NaN: 0)
  template <class F> TAO_FN F centre_back(const State<F>& st, const F& t) const {
    if (!gl.exact) return select(t > F(0.0f), F(1.0f), F(0.0f));
    F back[3], dir[3];
    for (int c = 0; c < 3; ++c) back[c] = neg(st.camera[c] * t);
    gl.normalize(back, dir);
    return horizon(gl.dot(dir, st.camera), st.n);
  }

  // A step's direction h = delta / length(delta), thickness t, front and back horizons x, y in [0, 1] (the shader's
  // clamps) and, for the backward, the same before the clamps where they have a derivative (a valid sample off the
  // pixel's own texel, its cosine in [-1, 1]; else -1)
  template <class F> struct Horizons { F h[3], t, x, y, front, back; };
  template <class F> TAO_FN Horizons<F> horizons(const State<F>& st, const Pixels<F>& px, const Sample<F>& smp) const {
    using I = typename LaneTraits<F>::I;
    Horizons<F> hz;
    const F* camera = st.camera;
    hz.t = thickness.at(px, smp);
    F behind[3], back_dir[3];
    unit(smp.delta, hz.h);
    for (int c = 0; c < 3; ++c) behind[c] = smp.delta[c] - camera[c] * hz.t;
    gl.normalize(behind, back_dir);
    // background samples occlude nothing; a sample on the pixel's own texel (sampleDistance 0) has the
    // front horizon 0 (NaN clamped) and the back one of -camera
    const auto centre = ieq(smp.index[0], I(int32_t(px.row * smp.image->W)) + to_int(px.u));
    const auto live = land(smp.valid, lnot(centre));
    const F x = horizon(gl.dot(hz.h, camera), st.n, &hz.front), y = horizon(gl.dot(back_dir, camera), st.n, &hz.back);
    hz.x = select(centre, F(0.0f), select(smp.valid, x, F(1.0f)));
    hz.y = select(smp.valid, y, F(1.0f));
    if (any(centre)) hz.y = select(centre, centre_back(st, thickness.ungrown(px, smp)), hz.y);
    hz.front = select(live, hz.front, F(-1.0f)), hz.back = select(live, hz.back, F(-1.0f));
    return hz;
  }

  // The adjoint of a step's unclamped horizons (horizons' front and back) for d L / d them g_x, g_y (0 where they
  // have no derivative): d L / d its delta and its thickness t, and d L / d the camera direction c added to g_camera.
  // Through acos (glsl_acos_slope; n's part is (g_x + g_y) / pi) to the cosines front = h . c, h = delta / |delta|,
  // and back = b' . c, b' = b / |b|, b = delta - c t, whose gradients are d front / d delta = (c - front h) / |delta|,
  // d front / d c = h, d back / d b = (c - back b') / |b| (b moves with delta, and with c and t by -t and -c), and
  // d back / d c = b' directly
  template <class F>
  TAO_FN void horizons_adjoint(const F* camera, const F* delta, const F& t, const F& g_x, const F& g_y, F* g_delta,
                               F* g_camera, F& g_t) const {
    F h[3], behind[3], back_dir[3];
    unit(delta, h);
    for (int c = 0; c < 3; ++c) behind[c] = delta[c] - camera[c] * t;
    gl.normalize(behind, back_dir);
    const F front = gl.dot(h, camera), back = gl.dot(back_dir, camera);
    const F g_f = g_x * glsl_acos_slope(gl.exact, front) * F(1.0f / kPi);
    const F g_b = g_y * glsl_acos_slope(gl.exact, back) * F(1.0f / kPi);
    // (selected: a sample on the pixel's own texel has delta 0, h and b' NaN)
    const auto on_f = g_f != F(0.0f), on_b = g_b != F(0.0f);
    const F per_f = g_f / gl.length(delta), per_b = g_b / gl.length(behind);
    F g_behind[3];
    for (int c = 0; c < 3; ++c) {
      g_behind[c] = select(on_b, per_b * (camera[c] - back * back_dir[c]), F(0.0f));
      g_delta[c] = select(on_f, per_f * (camera[c] - front * h[c]), F(0.0f)) + g_behind[c];
      g_camera[c] = g_camera[c] + select(on_f, g_f * h[c], F(0.0f)) +
                    select(on_b, g_b * back_dir[c] - g_behind[c] * t, F(0.0f));  // (t is inf off the layer's texels)
    }
    g_t = neg(dot3(g_behind, camera));
  }

  // The light a step sends per unit weight (light_sent's, before its weight)
  template <class F> TAO_FN void step_light(const State<F>& st, const Sample<F>& smp, const F* h, F* sent) const {
    F raw_n[3], light[3];
    for (int c = 0; c < 3; ++c) raw_n[c] = smp.gather(smp.image->normals, c), light[c] = smp.gather(smp.image->light, c);
    light_sent(st.normal, h, raw_n, light, smp.valid, F(1.0f), sent);
  }

  // The sectors a step's horizons cover (the shader's 32-bit mask)
  template <class F> TAO_FN typename LaneTraits<F>::I covered(const Horizons<F>& hz) const {
    return sector_bits(hz.x * F(float(kSectors)), (hz.y - hz.x) * F(float(kSectors)), rounding);
  }

  template <class F>
  TAO_FN void step(State<F>& st, int, const Pixels<F>& px, const Slice<F>&, const Sample<F>& smp) const {
    using I = typename LaneTraits<F>::I;
    const Horizons<F> hz = horizons(st, px, smp);
    const I bits = covered(hz);
    if (indirect) {
      F sent[3];
      step_light(st, smp, hz.h, sent);
      const F w = weight(bits & bnot(st.occ));
      for (int c = 0; c < 3; ++c) st.light[c] = st.light[c] + w * sent[c];
    }
    st.occ = st.occ | bits;
  }

  // h = delta / length(delta): the sample's direction
  template <class F> TAO_FN void unit(const F* delta, F* h) const {
    const F dl = gl.length(delta);
    for (int c = 0; c < 3; ++c) h[c] = delta[c] / dl;
  }

  // the light weight of a step whose sectors `fresh` are newly occluded: 1 - popcount(fresh) / 32
  template <class I> TAO_FN auto weight(const I& fresh) const -> decltype(to_float(popcount(fresh))) {
    using F = decltype(to_float(popcount(fresh)));
    return F(1.0f) - to_float(popcount(fresh)) / F(float(kSectors));
  }

  // The light a step gathers: weight light c1 c2, c1 = clamp(dot(normal, h), 0, 1) (normal: the pixel's,
  // normalised), c2 = clamp(dot(normalize(raw_n), -h), 0, 1) (raw_n: the sender's normal at the tap; 0 from an
  // invalid sample). (walk_grad.h's hard_grad_block runs it in dual lanes.)
  template <class F>
  TAO_FN void light_sent(const F* normal, const F* h, const F* raw_n, const F* light,
                         const typename LaneTraits<F>::M& valid, const F& weight, F* sent) const {
    F sender_n[3], away[3];
    for (int c = 0; c < 3; ++c) away[c] = neg(h[c]);
    gl.normalize(raw_n, sender_n);
    const F c1 = clamp(gl.dot(normal, h), F(0.0f), F(1.0f));
    const F c2 = select(valid, clamp(gl.dot(sender_n, away), F(0.0f), F(1.0f)), F(0.0f));
    for (int c = 0; c < 3; ++c) sent[c] = weight * ((light[c] * c1) * c2);
  }

  template <class F>
  TAO_FN void end_slice(const State<F>& st, const Pixels<F>&, const Slice<F>&, Sums<F>& sums) const {
    sums.occ = st.occ;
    for (int c = 0; c < 3; ++c) sums.light[c] = st.light[c];
    sums.visibility = sums.visibility + (F(1.0f) - to_float(popcount(st.occ)) / F(float(kSectors)));
  }

  // visibility (background 1; up to (sliceCount + 1) / sliceCount, as the shader's), the light (background 0)
  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    const F count = F(float(slice_count));
    out[0] = select(px.live, sums.visibility / count, F(1.0f));
    if (indirect)
      for (int c = 0; c < 3; ++c) out[1 + c] = select(px.live, sums.light[c] / count, F(0.0f));
  }
};

}  // namespace tao
