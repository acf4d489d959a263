// The soft and straight-through visibility-bitmask accumulator of torch_ao.BitmaskAO's "default" variant
// (mode="soft" / "straight_through") for walk.h: per slice, each step's interval (s, w) in sector units
// (the same float operations as BitmaskAccumulator, so that the straight-through forward's coverage is
// the hard one bit for bit), then the soft union of torch_ao.sectors.soft_union per sector k,
//     a = sigmoid((k + 1 - s) / tau),  b = sigmoid((w + F(s) - delta - k) / tau),  g = tanh(w / tau)
//     P_{m+1} = P_m - a b g P_m           (P_0 = 1; a step with w < 0 is empty)
// F the smooth floor sum_{m=1..32} sigmoid((s - m) / tau) (over a window of W <= 8 integers around s
// where tau is small: sweeps.floor_window_width), and the visibility sum_slices sum_k P_k omega_k / den
// (omega = 1/32, den = slices; or the cosine weights, den = their sum).
//
// With gradients, two more channels: d visibility / d radius and d visibility / d thickness of the pixel
// (the caller multiplies by the upstream gradient and sums). Each slice keeps its steps' intervals and
// runs soft_union's reverse scan per sector,
//     S_M = omega,  Y_m = a b P_m S_{m+1},  S_m = S_{m+1} - a b g S_{m+1},
// whose three sums per step give d/ds, d/dw (soft_union.py derives them); SectorInterval's atan2
// derivatives give the thickness's gradient, and the fetch's derivative along the step (su, sv move with
// the radius through the step placement) the radius's. Straight-through: the hard coverage's visibility
// with these (the soft union's) gradients.
#pragma once

#include "bitmask.h"

namespace tao {

constexpr float kSoftClamp = 30.0f;  // logistic arguments are clamped to +-30 (sectors.sweeps.CLAMP)
constexpr float kSoftTiny = 1e-30f;  // visibilities at or below are flushed to 0 (sweeps.TINY)
constexpr int kSoftWindowMax = 8;    // sweeps.WINDOW_MAX
constexpr int kSoftMaxSteps = 64;    // both sides' steps of a slice: steps <= 32

// N lanes values left uninitialised (ATen's Vectorized zeroes itself on construction: the per-step arrays
// of every slice would be cleared for nothing)
template <class F, int N> struct LaneArray {
  alignas(F) unsigned char bytes[N * sizeof(F)];
  TAO_FN F& operator[](int i) { return reinterpret_cast<F*>(bytes)[i]; }
  TAO_FN const F& operator[](int i) const { return reinterpret_cast<const F*>(bytes)[i]; }
};

template <class F> TAO_FN F soft_sigmoid(const F& x) {
  return reciprocal(F(1.0f) + exp(neg(clamp(x, F(-kSoftClamp), F(kSoftClamp)))));
}

// One step's soft coverage: a[k], b[k], the gate tanh(w / tau) (0 where empty), F'(s)
template <class F> struct SoftCoverage {
  LaneArray<F, kSectors> a, b;
  F gate, slope;
};

// kGradients: the two derivative channels too (a separate instantiation: the forward keeps no step arrays)
template <bool kGradients> struct SoftAccumulator {
  WalkSettings walk;  // the step placement (the radius' gradient moves the steps)
  float thickness, epsilon, tau, delta;  // delta: sectors.rule.rounding_offset
  int64_t rounding;
  int reach, window;  // the smooth floor's window (windowed: tau <= 0.1), sweeps.floor_window_width
  bool windowed, cosine, straight_through;
  static constexpr int kKept = kGradients ? kSoftMaxSteps : 1;  // steps kept per slice

  template <class F> struct State {
    using I = typename LaneTraits<F>::I;
    I occ;  // straight-through: the hard coverage
    F shift;
    LaneArray<F, kSectors> omega, P;
    int n;
    // with gradients: each step's interval, its angles' coordinates and their derivatives along the radius
    LaneArray<F, kKept> s, w, av, at, dav, dat;
  };
  template <class F> struct Sums { F num = F(0.0f), den = F(0.0f), radius = F(0.0f), thickness = F(0.0f); };
  TAO_FN int channels() const { return kGradients ? 3 : 1; }

  template <class F> TAO_FN void coverage(const F& s, const F& w, SoftCoverage<F>& cv) const {
    const float inv_tau = float(1.0 / double(tau));
    const F wc = clamp_min(w, F(0.0f));  // an empty step: zero width, zero gate
    const F t = expm1(wc * F(inv_tau) * F(-2.0f));  // sweeps.expm1_tanh
    cv.gate = neg(t / (t + F(2.0f)));
    const F start_arg = s * F(-inv_tau);
    for (int k = 0; k < kSectors; ++k) cv.a[k] = soft_sigmoid(F(float(k + 1) * inv_tau) + start_arg);
    F floor_s = F(0.0f), slope = F(0.0f);
    if (windowed) {
      const F lo = clamp(floor(s) - F(float(reach - 1)), F(1.0f), F(float(kSectors - window + 1)));
      const F z = (s - lo) * F(inv_tau);
      for (int i = 0; i < window; ++i) {
        const F x = soft_sigmoid(z - F(float(i) * inv_tau));
        floor_s = floor_s + x;
        slope = slope + (F(1.0f) - x) * x;
      }
      floor_s = floor_s + (lo - F(1.0f));
    } else {
      for (int k = 0; k < kSectors; ++k) {
        const F not_a = F(1.0f) - cv.a[k];
        floor_s = floor_s + not_a;
        slope = slope + not_a * cv.a[k];
      }
    }
    cv.slope = slope * F(inv_tau);
    const F end_arg = (wc + F(1.0f - delta) + floor_s) * F(inv_tau);
    for (int k = 0; k < kSectors; ++k) cv.b[k] = soft_sigmoid(end_arg - F(float(k + 1) * inv_tau));
  }

  // P <- P - a b g P over the sectors (P_m kept in before, if given)
  template <class F> TAO_FN void cover(const F& s, const F& w, F* P, F* before) const {
    SoftCoverage<F> cv;
    coverage(s, w, cv);
    for (int k = 0; k < kSectors; ++k) {
      if (before) before[k] = P[k];
      const F c = cv.b[k] * cv.a[k] * cv.gate;
      P[k] = P[k] - c * P[k];
      P[k] = select(P[k] > F(kSoftTiny), P[k], F(0.0f));
    }
  }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>& sl) const {
    State<F> st;
    st.occ = typename LaneTraits<F>::I(0);
    st.shift = (F(kHalfPi) - sl.gamma) / F(kPi);
    st.n = 0;
    for (int k = 0; k < kSectors; ++k) st.P[k] = F(1.0f), st.omega[k] = F(1.0f / kSectors);
    if (cosine) cosine_sector_weights(sl, st.omega);
    return st;
  }

  template <class F>
  TAO_FN void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    const F scale = F(float(side) / kPi);
    const F av = dot3(smp.delta, px.V), at = F(float(side)) * dot3(smp.delta, sl.T);
    const F front = clamp(fma(atan2(at, av), scale, st.shift), F(0.0f), F(1.0f));
    const F back = clamp(fma(atan2(at, av - F(thickness)), scale, st.shift), F(0.0f), F(1.0f));
    const F lo = side > 0 ? front : back, hi = side > 0 ? back : front;
    const F s = lo * F(float(kSectors));
    F w = (hi - lo) * F(float(kSectors));
    if (epsilon > 0) w = w - F(epsilon);
    w = select(px.live, w, F(-1.0f));  // lanes past the row or on the background: empty
    if (straight_through) st.occ = st.occ | sector_bits(s, w, rounding);
    if (!kGradients) {
      if (!straight_through && any(w >= F(0.0f))) cover(s, w, &st.P[0], static_cast<F*>(nullptr));
      return;
    }
    const int m = st.n++;
    st.s[m] = s, st.w[m] = w, st.av[m] = av, st.at[m] = at;
    // the sample's motion along the radius: dist' = frac span', span = radius_px - min_step_px (>= 0)
    F d_pos[3] = {F(0.0f), F(0.0f), F(0.0f)};
    if (smp.bilinear && any(w >= F(0.0f))) {  // (an empty step has no gradient)
      const int64_t j = m % walk.steps;
      const F reach_px = sl.radius_px - F(walk.min_step_px);
      const F span_slope = select(reach_px >= F(0.0f), sl.radius_px / F(walk.radius), F(0.0f));
      const F dist = step_distance(walk, sl, step_noise(walk, px, sl, side), j);  // min_step_px + span frac
      const F dd = span_slope * ((dist - F(walk.min_step_px)) / select(sl.span > F(0.0f), sl.span, F(1.0f)));
      const F su = px.u + dist * (sl.unit_u * F(float(side))), sv = px.v + dist * (sl.unit_v * F(float(side)));
      const F dsu = dd * sl.unit_u * F(float(side)), dsv = dd * sl.unit_v * F(float(side));
      const Image& img = *smp.image;
      const F t0 = gather(img.inverse, smp.index[0]), t1 = gather(img.inverse, smp.index[1]);
      const F t2 = gather(img.inverse, smp.index[2]), t3 = gather(img.inverse, smp.index[3]);
      const F depth = reciprocal(lerp(lerp(t0, t1, smp.fu), lerp(t2, t3, smp.fu), smp.fv));
      const F dS = lerp(t1 - t0, t3 - t2, smp.fv) * dsu + (lerp(t2, t3, smp.fu) - lerp(t0, t1, smp.fu)) * dsv;
      const F ddepth = neg(depth * depth * dS);
      const F Wl = F(float(img.W - 1)), Hl = F(float(img.H - 1));
      const F su_c = clamp(su, F(0.0f), Wl), sv_c = clamp(sv, F(0.0f), Hl);
      const F xh = (su_c - F(img.cx)) / F(img.fx), yh = neg(sv_c - F(img.cy)) / F(img.fy);
      const F dxh = select(su_c == su, dsu / F(img.fx), F(0.0f)), dyh = select(sv_c == sv, dsv / F(-img.fy), F(0.0f));
      d_pos[0] = select(smp.valid, ddepth * xh + depth * dxh, F(0.0f));
      d_pos[1] = select(smp.valid, ddepth * yh + depth * dyh, F(0.0f));
      d_pos[2] = select(smp.valid, neg(ddepth), F(0.0f));
    }  // the nearest texel does not move with the radius
    st.dav[m] = dot3(d_pos, px.V);
    st.dat[m] = F(float(side)) * dot3(d_pos, sl.T);
  }

  template <class F>
  TAO_FN void end_slice(State<F>& st, const Pixels<F>& px, const Slice<F>&, Sums<F>& sums) const {
    const int M = st.n;
    LaneArray<F, kKept * kSectors> before;  // P_m of each step (with gradients): before[m * 32 + k]
    if (kGradients)
      for (int m = 0; m < M; ++m)
        if (any(st.w[m] >= F(0.0f))) cover(st.s[m], st.w[m], &st.P[0], &before[m * kSectors]);
    F visible = F(0.0f);
    for (int k = 0; k < kSectors; ++k) {
      const F free = straight_through ? F(1.0f) - bit(st.occ, k) : st.P[k];
      visible = visible + free * st.omega[k];
      if (cosine) sums.den = sums.den + st.omega[k];
    }
    sums.num = sums.num + visible;
    if (!kGradients) return;
    const float inv_tau = float(1.0 / double(tau));
    F S[kSectors];
    for (int k = 0; k < kSectors; ++k) S[k] = st.omega[k];
    for (int m = M - 1; m >= 0; --m) {  // the reverse scan
      const auto live = st.w[m] >= F(0.0f);
      if (!any(live)) continue;
      SoftCoverage<F> cv;
      coverage(st.s[m], st.w[m], cv);
      F sum_y = F(0.0f), sum_ya = F(0.0f), sum_yb = F(0.0f);
      for (int k = 0; k < kSectors; ++k) {
        const F ab = cv.a[k] * cv.b[k];
        const F y = ab * before[m * kSectors + k] * S[k];  // Y = a b P_m S_{m+1}
        sum_y = sum_y + y;
        sum_ya = sum_ya + y * cv.a[k];
        sum_yb = sum_yb + y * cv.b[k];
        S[k] = S[k] - ab * cv.gate * S[k];
      }
      const F g = cv.gate, not_b = sum_y - sum_yb;
      // dL/dw = -(g' sum Y + g / tau sum Y (1 - b)), g' = (1 - g^2) / tau;
      // dL/ds = -(g / tau) (F' sum Y (1 - b) - sum Y (1 - a))
      const F gw = select(live, ((g * g - F(1.0f)) * sum_y - g * not_b) * F(inv_tau), F(0.0f));
      const F gs = select(live, (not_b * cv.slope - sum_y + sum_ya) * g * F(-inv_tau), F(0.0f));
      // SectorInterval.backward: s = 32 lo, w = 32 (hi - lo) - epsilon, the clamps pass inside [0, 1]
      const int side = m < walk.steps ? 1 : -1;
      const F scale = F(float(side) / kPi);
      const F av = st.av[m], at = st.at[m], bv = av - F(thickness);
      const F front = fma(atan2(at, av), scale, st.shift), back = fma(atan2(at, bv), scale, st.shift);
      const F g_lo = (gs - gw) * F(float(kSectors)), g_hi = gw * F(float(kSectors));
      F g_f = side > 0 ? g_lo : g_hi, g_b = side > 0 ? g_hi : g_lo;
      g_f = select(land(front >= F(0.0f), front <= F(1.0f)), g_f, F(0.0f));
      g_b = select(land(back >= F(0.0f), back <= F(1.0f)), g_b, F(0.0f));
      // theta = atan2(y, x): d theta = (x dy - y dx) / (x^2 + y^2)
      const F inv_f = g_f * scale / fma(av, av, at * at);
      const F inv_b = g_b * scale / fma(bv, bv, at * at);
      const F g_at = av * inv_f + bv * inv_b, g_av = neg((inv_f + inv_b) * at);
      sums.thickness = sums.thickness + select(px.live, at * inv_b, F(0.0f));
      sums.radius = sums.radius + select(px.live, g_av * st.dav[m] + g_at * st.dat[m], F(0.0f));
    }
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    const F den = cosine ? clamp_min(sums.den, F(1e-30f)) : F(float(walk.slices));
    out[0] = select(px.live, sums.num / den, F(1.0f));
    if (kGradients) {
      out[1] = select(px.live, sums.radius / den, F(0.0f));
      out[2] = select(px.live, sums.thickness / den, F(0.0f));
    }
  }
};

}  // namespace tao
