// The horizon accumulators of torch_ao/methods/gtao.py (GTAO's three variants: a horizon per side, then
// the clamped arc integral of torch_ao.ops.arc_integral) and torch_ao/methods/hbao.py, for walk.h.
// They finish into the per-pixel sums over slices (0 on background) that the modules' own Python
// finish turns into outputs, so normalisation, final power and multi-bounce have one definition.
#pragma once

#include "walk.h"

namespace tao {

// torch_ao.ops.arc_integral over [h1, h2] around the projected normal's angle n: both halves of
// 1/4 (-cos(2h - n) + cos n + 2 h sin n)
template <class F> TAO_FN F arc_integral(const F& h1, const F& h2, const F& n, const F& cos_n, const F& sin_n) {
  const F two = F(2.0f);
  return F(0.25f) * ((neg(cos(two * h1 - n)) + cos_n + two * h1 * sin_n) + (neg(cos(two * h2 - n)) + cos_n + two * h2 * sin_n));
}

template <class F> struct Rev;  // (lanes_rev.h, where a backward includes it)
// arc_integral in reverse lanes: its value in the value lanes, its derivatives with respect to h1, h2, n, cos_n
// and sin_n in two nodes of the tape, where its arithmetic makes fourteen: d / d h_k = (sin(2 h_k - n) + sin n) / 2,
// d / d n = -(sin(2 h1 - n) + sin(2 h2 - n)) / 4, d / d cos n = 1 / 2, d / d sin n = (h1 + h2) / 2
template <class B>
TAO_FN Rev<B> arc_integral(const Rev<B>& h1, const Rev<B>& h2, const Rev<B>& n, const Rev<B>& cos_n,
                           const Rev<B>& sin_n) {
  const B two(2.0f), half(0.5f), s1 = sin(two * h1.v - n.v), s2 = sin(two * h2.v - n.v);
  const B value = arc_integral(h1.v, h2.v, n.v, cos_n.v, sin_n.v);
  const Rev<B> along_h = Rev<B>::link(value, h1, half * (s1 + sin_n.v), h2, half * (s2 + sin_n.v), n,
                                      B(-0.25f) * (s1 + s2));
  return Rev<B>::link(value, along_h, B(1.0f), cos_n, half, sin_n, half * (h1.v + h2.v));
}

enum class GTAOVariant : int64_t { exact = 0, hdrp = 1, ue4 = 2 };
constexpr float kUE4Epsilon = 1e-4f;  // ue4's rsqrt(|d|^2 + 1e-4), world units squared

struct GTAOAccumulator {
  GTAOVariant variant;
  float radius;     // world units: where samples stop counting (not the walk's radius)
  float falloff;    // exact: falloff_range * radius clamped to 1e-12; <= 0: a hard cut
  float thickness;  // ue4: the thickness heuristic
  bool projected_normal_weight, bent;
  // its sums weighed by Slice::weight: its walk may draw the slices by the projected normal's density (walked_slice)
  static constexpr bool kWeighsSlices = true;

  template <class F> struct State { F best[2]; };  // [0]: side +1, [1]: side -1
  static constexpr bool kStatePerSide = true;  // (a step changes its side's alone: Takes compares that one)
  template <class F> struct Sums { F vis = F(0.0f), free = F(0.0f), bent[3] = {F(0.0f), F(0.0f), F(0.0f)}; };
  TAO_FN int channels() const { return bent ? 5 : 2; }
  // falloff (exact), or thickness and the length epsilon (ue4) (seed_setting): ue4's epsilon is an area, which
  // breaks the walk's scale invariance unless its gradient joins Euler's identity (walk_grad.py)
  TAO_FN int settings() const { return variant == GTAOVariant::ue4 ? 2 : 1; }
  // whether a step that changes a side's state replaces it (the state after depends on the slice and the
  // sample alone): the exact variant's minimum; the shaders' updates blend the sample into the horizon
  TAO_FN bool replaces() const { return variant == GTAOVariant::exact; }
  // whether every valid sample's step carries a derivative, even one that leaves the state's value as it
  // was (ue4's thickness blend: at thickness 1 its value stays, its derivative in the thickness does not)
  TAO_FN bool blends_every_sample() const { return variant == GTAOVariant::ue4; }
  // whether a slice whose steps took nothing adds a constant to the outputs (its backward replays nothing): not
  // here, where each side's horizon starts at the slice's own hemisphere edge
  TAO_FN bool untaken_slice_constant() const { return false; }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>& sl) const {
    if (variant == GTAOVariant::exact)  // the smallest angle from V per side, from the hemisphere boundary
      return State<F>{{F(kHalfPi) + sl.gamma, F(kHalfPi) - sl.gamma}};
    return State<F>{{F(-1.0f), F(-1.0f)}};  // the shaders' largest horizon cosine, from cos(pi)
  }

  template <class F>
  TAO_FN void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    F& best = st.best[side > 0 ? 0 : 1];
    const F R = F(radius);
    if (variant == GTAOVariant::exact) {
      const F theta = clamp(slice_angle(side, smp.delta, px.V, sl.T, px.P[2]), F(0.0f), F(kPi));
      const F distance = norm3(smp.delta);
      F w = falloff > 0 ? clamp((R - distance) / seed_setting(F(falloff)), F(0.0f), F(1.0f))
                        : select(distance < R, F(1.0f), F(0.0f));
      w = select(smp.valid, w, F(0.0f));
      const F bound = F(kHalfPi) + F(float(side)) * sl.gamma;
      best = min(best, bound + w * (theta - bound));
    } else if (variant == GTAOVariant::hdrp) {  // UpdateHorizon
      const F distance = norm3(smp.delta);
      const F cand = dot3(smp.delta, px.V) / clamp_min(distance, F(1e-30f));
      const F falloff_w = clamp(F(1.0f) - (distance * distance) / (R * R), F(0.0f), F(1.0f));
      const F upd = select(cand > best, best + falloff_w * (cand - best), best);
      best = select(smp.valid, upd, best);
    } else {  // SearchForLargestAngleDual
      const F len_sq = dot3(smp.delta, smp.delta);
      F ang = dot3(smp.delta, px.V) * rsqrt(len_sq + seed_setting(F(kUE4Epsilon), 1));
      const F falloff_w = clamp(len_sq * (F(2.0f) / (R * R)), F(0.0f), F(1.0f));
      ang = ang + falloff_w * (best - ang);
      const F upd = select(ang > best, ang, ang + seed_setting(F(thickness)) * (best - ang));
      best = select(smp.valid, upd, best);
    }
  }

  template <class F>
  TAO_FN void end_slice(const State<F>& st, const Pixels<F>& px, const Slice<F>& sl, Sums<F>& sums) const {
    // the horizons h1 <= 0 <= h2, the projected normal's angle n, its cos and sin, the slice's weight
    F h1, h2, n, cos_n, sin_n, weight;
    const F length = sl.length, one = F(1.0f), minus_one = F(-1.0f);
    auto degenerate = length < F(0.0f);
    if (variant == GTAOVariant::exact) {
      h1 = neg(st.best[1]), h2 = st.best[0], n = sl.gamma, cos_n = sl.cos_gamma, sin_n = sl.sin_gamma, weight = length;
    } else {
      h1 = neg(fast_acos(clamp(st.best[1], minus_one, one)));
      h2 = fast_acos(clamp(st.best[0], minus_one, one));
      if (variant == GTAOVariant::hdrp) {
        cos_n = clamp(sl.cos_gamma, minus_one, one);
        n = sign(sl.sin_gamma) * fast_acos(cos_n);
        sin_n = sin(n);
        weight = projected_normal_weight ? length : one;
        degenerate = length < F(1e-6f);
      } else {  // ComputeInnerIntegral, with its own |n_p| + 1e-6
        const F Lp = length + F(1e-6f);
        const F cos_ang = (length * sl.sin_gamma) / Lp;
        n = F(kHalfPi) - fast_acos(clamp(cos_ang, minus_one, one));
        cos_n = (length * sl.cos_gamma) / Lp, sin_n = cos_ang, weight = Lp;
      }
    }
    const F lo = n - F(kHalfPi), hi = n + F(kHalfPi);
    h1 = max(h1, lo);  // n + max(h1 - n, -pi/2)
    h2 = min(h2, hi);  // n + min(h2 - n, pi/2)
    F integral = weight * arc_integral(h1, h2, n, cos_n, sin_n);
    F free_integral = weight * arc_integral(lo, hi, n, cos_n, sin_n);
    if (variant == GTAOVariant::hdrp) {  // AnyIsNaN(...) ? 1
      integral = select(degenerate, one, integral);
      free_integral = select(degenerate, one, free_integral);
    }
    // (a slice drawn by a density counts by its estimator weight, as the tensor walk's march weighs every output)
    sums.vis = sums.vis + sl.weight * integral;
    sums.free = sums.free + sl.weight * free_integral;
    if (bent) {  // bent_vector(h1, h2, n), times |n_p|, in the slice's (V, T) frame
      const F h[2] = {h2, h1}, cn = cos(n), sn = sin(n), three = F(3.0f);
      F fc[2], fs[2];
      for (int k = 0; k < 2; ++k) {
        const F ch = cos(h[k]), sh = sin(h[k]);
        const F c3 = ch * ch * ch, s3 = sh * sh * sh;
        fc[k] = (neg(c3) * cn + s3 * sn) / three;
        fs[k] = (s3 * cn) / three + sn * (c3 / three - ch);
      }
      const F along_v = (fc[0] + fc[1]) + (F(2.0f) * cn) / three;
      const F along_t = (fs[0] + fs[1]) + (F(4.0f) * sn) / three;
      const F scale = sl.weight * length;
      for (int k = 0; k < 3; ++k) sums.bent[k] = sums.bent[k] + scale * (along_v * px.V[k] + along_t * sl.T[k]);
    }
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    out[0] = select(px.live, sums.vis, F(0.0f));
    out[1] = select(px.live, sums.free, F(0.0f));
    if (bent)
      for (int c = 0; c < 3; ++c) out[2 + c] = select(px.live, sums.bent[c], F(0.0f));
  }
};

// HBAOAccumulator (torch_ao/methods/hbao.py): per direction, the running horizon sin h above the
// tangent's sin t and its weighted rise
struct HBAOAccumulator {
  float radius, angle_bias;
  bool quadratic, incremental, view_elevation;

  // a step changes the state exactly where the horizon rises (its sine's change marks the takes, walk_grad.h)
  template <class F> struct State { F sin_h, sin_t, ao, w; };
  static constexpr int kTakeComponents = 1;
  template <class F> struct Sums { F ao = F(0.0f); };
  TAO_FN int channels() const { return 1; }
  TAO_FN int settings() const { return 1; }  // angle_bias (seed_setting)
  // whether a step that changes the state replaces it: the highest sample's rise alone (max), not the
  // incremental sum of every rise
  TAO_FN bool replaces() const { return !incremental; }
  TAO_FN bool blends_every_sample() const { return false; }
  // a slice without a rise adds 0, whatever the pixel (its sum and weight stay 0): its backward replays nothing
  TAO_FN bool untaken_slice_constant() const { return true; }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>& px, const Slice<F>& sl) const {
    F t;
    if (view_elevation) {  // the hemisphere boundary on side +1 sits at angle pi/2 + gamma from V
      t = neg(sl.gamma);
    } else {  // the elevation of the tangent cos(b) V + sin(b) T, b = pi/2 + gamma, above the image plane
      // cos(pi/2 + gamma) = -sin(gamma), sin(pi/2 + gamma) = cos(gamma)
      const F z = neg(sl.sin_gamma) * px.V[2] + sl.cos_gamma * sl.T[2];
      t = asin(clamp(z, F(float(-1 + 1e-7)), F(float(1 - 1e-7))));
    }
    const F sin_t = sin(clamp_max(t + seed_setting(F(angle_bias)), F(kHalfPi)));
    return State<F>{sin_t, sin_t, F(0.0f), F(0.0f)};
  }

  template <class F>
  TAO_FN void step(State<F>& st, int, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    const F distance = norm3(smp.delta);
    const F sin_s = view_elevation ? cos(atan2(dot3(smp.delta, sl.T), dot3(smp.delta, px.V)))
                                   : smp.delta[2] / clamp_min(distance, F(1e-30f));
    const F r = distance / F(radius > 1e-30f ? radius : 1e-30f);
    const F w = clamp_min(quadratic ? F(1.0f) - r * r : F(1.0f) - r, F(0.0f));
    const auto rise = land(land(smp.valid, r < F(1.0f)), sin_s > st.sin_h);
    if (incremental) {
      st.ao = select(rise, st.ao + w * (sin_s - st.sin_h), st.ao);
    } else {
      st.w = select(rise, w, st.w);
    }
    st.sin_h = select(rise, sin_s, st.sin_h);
  }

  template <class F>
  TAO_FN void end_slice(const State<F>& st, const Pixels<F>&, const Slice<F>&, Sums<F>& sums) const {
    sums.ao = sums.ao + (incremental ? st.ao : st.w * (st.sin_h - st.sin_t));
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    out[0] = select(px.live, sums.ao, F(0.0f));
  }
};

}  // namespace tao
