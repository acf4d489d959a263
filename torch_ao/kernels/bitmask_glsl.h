// The "ssilvb_glsl" variant's accumulator (methods/bitmask_glsl.py GLSLAccumulator, hard mode) for walk.h
// with the GLSL step placement and noise: the SSILVB GLSL article's shader per step, its quirks kept
// (the occlusion mask and the light carried across slices, the unnormalised slice axis, the light
// weight 1 - newly / 32, sums over sliceCount + 1 slices divided by sliceCount), and the driver's
// numerics of glsl_numerics="mesa": Mesa's asin polynomial and llvmpipe's dot / length / normalize.
#pragma once

#include "bitmask.h"

namespace tao {

// Mesa's GLSL asin polynomial (bitmask_glsl.mesa_asin), x in [-1, 1]
template <class F> TAO_FN F mesa_asin(const F& x) {
  const F ax = abs(x);
  const F poly = F(kHalfPi) + ax * (F(kPi / 4.0f - 1.0f) + ax * (F(0.08132463f) + ax * F(-0.02363318f)));
  return sign(x) * (F(kHalfPi) - sqrt(F(1.0f) - ax) * poly);
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

  // _horizon: clamp((acos(c) + n + halfPi) / pi, 0, 1), 0 where acos is NaN (|c| > 1 or NaN); Mesa folds
  // acos's pi/2 into the + halfPi: (pi - asin(c)) + n
  template <class F> TAO_FN F horizon(const F& cosine, const F& n) const {
    const auto good = abs(cosine) <= F(1.0f);
    const F c = select(good, cosine, F(0.0f));
    const F value = gl.exact ? ((F(kPi) - mesa_asin(c)) + n) / F(kPi) : ((acos(c) + n) + F(kHalfPi)) / F(kPi);
    return select(good, clamp(value, F(0.0f), F(1.0f)), F(0.0f));
  }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>& px, const Slice<F>& sl, const Sums<F>& sums) const {
    State<F> st;
    st.occ = sums.occ;
    for (int c = 0; c < 3; ++c) st.light[c] = sums.light[c];
    if (gl.exact) {
      const F minus[3] = {neg(px.P[0]), neg(px.P[1]), neg(px.P[2])};
      gl.normalize(minus, st.camera);
    } else {
      for (int c = 0; c < 3; ++c) st.camera[c] = px.V[c];
    }
    gl.normalize(px.N, st.normal);
    const F* camera = st.camera;
    const F direction[3] = {sl.dir_u, sl.dir_v, F(0.0f)};
    const F along = gl.dot(direction, camera);
    F ortho[3], axis[3], proj[3];
    for (int c = 0; c < 3; ++c) ortho[c] = direction[c] - along * camera[c];
    cross(direction, camera, axis);  // not normalised (as written)
    const F na = gl.dot(st.normal, axis);
    for (int c = 0; c < 3; ++c) proj[c] = st.normal[c] - axis[c] * na;
    const F cos_n = clamp(gl.dot(proj, camera) / gl.length(proj), F(0.0f), F(1.0f));
    st.n = sign(gl.dot(ortho, proj)) * (gl.exact ? F(kHalfPi) - mesa_asin(cos_n) : acos(cos_n));
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

  template <class F>
  TAO_FN void step(State<F>& st, int, const Pixels<F>& px, const Slice<F>&, const Sample<F>& smp) const {
    using I = typename LaneTraits<F>::I;
    const F* camera = st.camera;
    const F t = thickness.at(px, smp);
    F h[3], behind[3], back_dir[3];
    unit(smp.delta, h);
    for (int c = 0; c < 3; ++c) behind[c] = smp.delta[c] - camera[c] * t;
    gl.normalize(behind, back_dir);
    // background samples occlude nothing; a sample on the pixel's own texel (sampleDistance 0) has the
    // front horizon 0 (NaN clamped) and the back one of -camera
    const auto centre = ieq(smp.index[0], I(int32_t(px.row * smp.image->W)) + to_int(px.u));
    const F x = select(centre, F(0.0f), select(smp.valid, horizon(gl.dot(h, camera), st.n), F(1.0f)));
    F y = select(smp.valid, horizon(gl.dot(back_dir, camera), st.n), F(1.0f));
    if (any(centre)) y = select(centre, centre_back(st, t), y);
    const I bits = sector_bits(x * F(float(kSectors)), (y - x) * F(float(kSectors)), rounding);
    if (indirect) {
      F raw_n[3], light[3], sent[3];
      for (int c = 0; c < 3; ++c) raw_n[c] = smp.gather(smp.image->normals, c), light[c] = smp.gather(smp.image->light, c);
      light_sent(st.normal, h, raw_n, light, smp.valid, weight(bits & bnot(st.occ)), sent);
      for (int c = 0; c < 3; ++c) st.light[c] = st.light[c] + sent[c];
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
