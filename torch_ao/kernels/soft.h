// The soft and straight-through visibility-bitmask accumulator of torch_ao.BitmaskAO's "default" and "hdrp"
// variants (mode="soft" / "straight_through") for walk.h: per slice (in the variant's frame, bitmask.h's
// slice_frame), each step's interval (s, w) in sector units (BitmaskAccumulator's sample_angles and
// sample_interval, so that the straight-through forward's coverage is the hard one bit for bit), then the soft union of torch_ao.sectors.soft_union per sector k,
//     a = sigmoid((k + 1 - s) / tau),  b = sigmoid((w + F(s) - delta - k) / tau),  g = tanh(w / tau)
//     P_{m+1} = P_m - a b g P_m           (P_0 = 1; a step with w < 0 is empty)
// F the smooth floor sum_{m=1..32} sigmoid((s - m) / tau) (over a window of W <= 8 integers around s
// where tau is small: sweeps.floor_window_width), and the visibility sum_slices sum_k P_k omega_k / den
// (omega = 1/32, den = slices; or the cosine weights, den = their sum). With indirect, also the light
// sum_slices sum_m newly_m light_m / den, newly_m = sum_k omega_k a b g P_m (soft_union's; straight-through: the hard
// sectors' share) and light_m the sample's light times bitmask.h's light_factor; with bent, the bent normal's sum
// sum_slices sum_k P_k omega_k (cos phi_k V + sin phi_k T) (bitmask.h's bent_axes; its direction is taken in torch).
//
// The thickness at a sample is bitmask.h's ThicknessModel (thickness.ThicknessLayer: scale * value + offset).
// With gradients, three more channels: d visibility / d radius, d thickness (the model's offset) and d its
// scale of the pixel, and with a growth (t times 1 + growth |delta|) a fourth, d growth (the caller multiplies by
// the upstream gradient and sums). Each slice keeps its steps' intervals and runs soft_union's reverse scan per
// sector,
//     S_M = omega,  Y_m = a b P_m S_{m+1},  S_m = S_{m+1} - a b g S_{m+1},
// whose three sums per step give d/ds, d/dw (soft_union.py derives them), so d / d its front and back angles;
// sample_angles_adjoint (atan2's derivatives, or HDRP's fast_acos(ViewCosine)'s) gives the thickness's gradient,
// and the fetch's derivative along the step (su, sv move with
// the radius through the step placement, and so does a layer's read) the radius's. Straight-through: the hard coverage's visibility
// with these (the soft union's) gradients.
//
// The backward of the G-buffer (SoftAdjoint, kAdjoint: walk_grad_cpu.cpp's soft_backward) walks again in
// value lanes keeping each step's fetch, runs the same reverse scan seeded by the outputs' upstream gradients
// (d loss / d each sector's free share: the visibility's, and the bent normal sum's through phi_k's direction;
// with indirect light each step's gain, the light's upstream gradient dotted with its light, soft_union's gn),
// and chains each step's d loss / d s,
// d w by hand: through the angles (sample_angles_adjoint) to d / d delta and d / d its thickness (scattered to
// the fetch's taps by the caller's sink: the position's, and the layer's where the model
// reads one; the linear model's value is the fetched position's depth) and on to the slice's quantities (V, T, P, the screen direction, the
// span, gamma: HDRP's through hdrp_slice_angle), whose tangents on the pixel's own P, N, depth come from the pixel and slice walked in dual
// lanes (lanes_dual.h); the cosine weights carry their own tangents.
#pragma once

#include "bitmask.h"
#include "lanes_dual.h"

namespace tao {

constexpr float kSoftClamp = 30.0f;  // logistic arguments are clamped to +-30 (sectors.sweeps.CLAMP)
constexpr float kSoftTiny = 1e-30f;  // visibilities at or below are flushed to 0 (sweeps.TINY)
constexpr int kSoftWindowMax = 8;    // sweeps.WINDOW_MAX
constexpr int kSoftMaxSteps = 64;    // both sides' steps of a slice: steps <= 32
constexpr int kSoftShortSteps = 16;  // ... of a short slice (a CUDA backward's: walk_cuda.cu)
// a step's sectors whose a b is below logistic(-kSoftSkip) = 2e-9 for every lane are left out of its sweep
// and reverse scan (below the interval a ~ 0, above it b ~ 0): at tau = 0.25, 5 sectors either side of it
constexpr float kSoftSkip = 20.0f;
constexpr int kSoftRunMax = 8;  // sigmoid_run: an exp at least every 8 terms
constexpr float kSoftExpLow = 9.35762297e-14f, kSoftExpHigh = 1.06864746e13f;  // e^-30, e^30 (kSoftClamp)

// One step's soft coverage: a[k], b[k] for the sectors k0 <= k < k1 where they overlap (kSoftSkip), the gate
// tanh(w / tau) (0 where empty), F'(s)
template <class F> struct SoftCoverage {
  LaneArray<F, kSectors> a, b;
  F gate, slope;
  int k0, k1;
};

// d position / d su and d sv of a sample's bilinear fetch at (su, sv) (perspective-correct depth, the
// clamped unprojection; 0 where the sample is not valid), P the pixel's position. The position is
// (xh, yh, -1) z with z = 1 / i, i the interpolated inverse depth: d position / d su = -z (d i / d su) position
// + z (d xh / d su, 0, 0), and likewise for sv.
template <class F>
TAO_FN void fetch_motion(const Sample<F>& smp, const F* P, const F& su, const F& sv, F* d_su, F* d_sv) {
  const Image& img = *smp.image;
#if !TAO_LEAN_WALK
  if (smp.reads_positions) {  // (a position buffer's taps: Sample::position_motion)
    smp.position_motion(d_su, d_sv);
    for (int c = 0; c < 3; ++c)
      d_su[c] = select(smp.valid, d_su[c], F(0.0f)), d_sv[c] = select(smp.valid, d_sv[c], F(0.0f));
    return;
  }
#endif
  F pos[3];
  for (int c = 0; c < 3; ++c) pos[c] = smp.delta[c] + P[c];
  const F depth = neg(pos[2]);
  const F k_u = neg(depth * smp.inverse_su), k_v = neg(depth * smp.inverse_sv);
  const auto u_inside = clamp(su, F(0.0f), F(float(img.W - 1))) == su;
  const auto v_inside = clamp(sv, F(0.0f), F(float(img.H - 1))) == sv;
  const F dxh = select(u_inside, depth * F(1.0f / img.fx), F(0.0f));
  const F dyh = select(v_inside, depth * F(-1.0f / img.fy), F(0.0f));
  for (int c = 0; c < 3; ++c) {
    d_su[c] = select(smp.valid, k_u * pos[c] + (c == 0 ? dxh : F(0.0f)), F(0.0f));
    d_sv[c] = select(smp.valid, k_v * pos[c] + (c == 1 ? dyh : F(0.0f)), F(0.0f));
  }
}

// d su / d radius and d sv / d radius of the step dist pixels out on a slice's side (SlicePattern.step_offsets,
// the power placement: dist = min_step_px + span frac, span = clamp_min(radius_px - min_step_px, 0),
// radius_px = R |ppu|, with the sphere's extent times intervals.sphere_stretch, clamped to max_radius_px)
template <class F>
TAO_FN void step_motion(const WalkSettings& walk, const Pixels<F>& px, const Slice<F>& sl, float side, const F& dist,
                        F& dsu, F& dsv) {
  F slope = sl.radius_px / F(walk.radius);  // d radius_px / d R
  if (walk.sphere_extent) {  // stretch = rsqrt(clamp_min(q, 1/100)), q = 1 - r^2, r = R / |P|: d (R stretch) / dR = stretch (1 + r^2 / q)
    const F ratio = F(walk.radius) / px.distance;
    const F square = ratio * ratio, q = F(1.0f) - square;
    slope = slope * select(q >= F(1.0f / 100.0f), F(1.0f) + square / q, F(1.0f));
  }
  if (walk.max_radius_px > 0) slope = select(sl.radius_px < F(walk.max_radius_px), slope, F(0.0f));
  const F reach_px = sl.radius_px - F(walk.min_step_px);
  const F span_slope = select(reach_px >= F(0.0f), slope, F(0.0f));
  const F dd = span_slope * ((dist - F(walk.min_step_px)) / select(sl.span > F(0.0f), sl.span, F(1.0f)));
  dsu = dd * sl.unit_u * F(side), dsv = dd * sl.unit_v * F(side);
}

// bitmask.h's segment_angles' adjoint, in dual lanes (14 tangents: delta, V, T, the pixel's P, t, the radius): of L
// with d L / d front = g_front and d L / d back = g_back, d L / d delta, V, T and the pixel's P (through its depth
// and |P| alone: delta's share is the caller's) added to g_delta, g_V, g_T and g_P, d L / d the radius (the clip's)
// to g_radius, and d L / d t returned
template <class F>
TAO_FN F segment_angles_adjoint(bool along_ray, bool clip, int side, const F* P, const F* delta, const F* V,
                                const F* T, const F& t, const F& radius, const F& g_front, const F& g_back, F* g_delta,
                                F* g_V, F* g_T, F* g_P, F& g_radius) {
  using D = Dual<F, 14>;
  D d[3], v[3], w[3], p[3], thickness(t), r(radius);
  for (int c = 0; c < 3; ++c) {
    d[c] = D(delta[c]), v[c] = D(V[c]), w[c] = D(T[c]), p[c] = D(P[c]);
    d[c].d[c] = F(1.0f), v[c].d[3 + c] = F(1.0f), w[c].d[6 + c] = F(1.0f), p[c].d[9 + c] = F(1.0f);
  }
  thickness.d[12] = F(1.0f), r.d[13] = F(1.0f);
  D seg[4], front, back;
  segment_of(along_ray, side, d, v, w, norm3(p), p[2], thickness, seg);
  auto live = F(0.0f) <= F(1.0f);
  segment_end_angles<F>(clip, seg, r, live, front, back);
  const auto along = [&](int k) { return g_front * front.d[k] + g_back * back.d[k]; };
  for (int c = 0; c < 3; ++c) {
    g_delta[c] = g_delta[c] + along(c), g_V[c] = g_V[c] + along(3 + c), g_T[c] = g_T[c] + along(6 + c);
    g_P[c] = g_P[c] + along(9 + c);
  }
  g_radius = g_radius + along(13);
  return along(12);
}

// kGradients: the two derivative channels too (a separate instantiation: the forward keeps no step arrays);
// kAdjoint (with kGradients): the backward's, which keeps each step's fetch for end_slice_adjoint
template <bool kGradients, bool kAdjoint = false, int kMostSteps = kSoftMaxSteps> struct SoftAccumulator {
  WalkSettings walk;  // the step placement (the radius' gradient moves the steps)
  ThicknessModel thickness;  // world units along the view ray
  float epsilon, tau, delta;  // delta: sectors.rule.rounding_offset
  int64_t rounding;
  int reach, window;  // the smooth floor's window (windowed: tau <= 0.1), sweeps.floor_window_width
  // sigmoid_run's: an exp every run terms at x clamped to +-run_bound, then products by run_ratio = e^(-1 / tau)
  // (soft_window)
  int run;
  float run_bound, run_ratio;
  bool windowed, cosine, straight_through;
  static constexpr bool kWeighsSlices = kSectorsWeighSlices;  // (end_slice weighs a slice drawn by a density)
  // whether the thickness model has a growth (ThicknessModel::growth, then a parameter: its gradient is wanted at
  // growth 0 too)
  bool grows = false;
  // the indirect light and the bent normal's sum too (not with kGradients: their settings' gradients are the
  // backward's)
  bool indirect, bent;
  SectorAngles angles;  // the variant's rule (bitmask.h's sample_angles, in slice_frame's frame)
  // the exact variant's segment geometry with plane angles (bitmask.h's segment_angles): the back point along the
  // sample's camera ray, the segment clipped to the walk's radius' sphere. Not in the lean CUDA build (kSegments):
  // its soft walks, already at 245-249 registers, would spill them.
  bool along_ray = false, clip = false;
  static constexpr bool kSegments = !kLeanWalk;
  TAO_FN bool segments() const { return kSegments && (along_ray || clip) && angles == SectorAngles::plane; }

  // A step's front and back angles (sample_angles, or segment_angles: live loses a segment that misses the sphere)
  template <class F>
  TAO_FN void step_angles(int side, const Pixels<F>& px, const Slice<F>& sl, const F* delta, const F& t,
                          typename LaneTraits<F>::M& live, F& front, F& back) const {
    if constexpr (kSegments) {
      if (segments()) return segment_angles(along_ray, clip, side, px, sl, delta, t, F(walk.radius), live, front, back);
    }
    sample_angles(angles, side, delta, px.V, sl.T, px.P[2], t, front, back);
  }
  // step_angles' adjoint (T: the frame's tangent): d L / d delta, V, T added to g_delta, g_V, g_T, and with the
  // segment geometry d L / d the pixel's P (through its depth and |P|: delta's share is the caller's) to g_P and the
  // clip's d L / d radius to g_radius; d L / d t returned
  template <class F>
  TAO_FN F step_angles_adjoint(int side, const Pixels<F>& px, const F* T, const F* delta, const F& t, const F& g_front,
                               const F& g_back, F* g_delta, F* g_V, F* g_T, F* g_P, F& g_radius) const {
    if constexpr (kSegments) {
      if (segments())
        return segment_angles_adjoint(along_ray, clip, side, px.P, delta, px.V, T, t, F(walk.radius), g_front, g_back,
                                      g_delta, g_V, g_T, g_P, g_radius);
    }
    return sample_angles_adjoint(angles, side, delta, px.V, T, px.P[2], t, g_front, g_back, g_delta, g_V, g_T);
  }
  static constexpr int kKept = kGradients ? kMostSteps : 1;  // steps kept per slice
  // whether the sweep keeps each step's coverage for the reverse scan (64 logistics a step, else computed again):
  // the CPU's do (a slice's are L2-resident), a CUDA thread's forward recomputes them (its local memory is
  // global memory)
#ifdef __CUDACC_RTC__
  static constexpr bool kKeepCoverage = kAdjoint;
#else
  static constexpr bool kKeepCoverage = kGradients;
#endif

  template <class F> struct State {
    using I = typename LaneTraits<F>::I;
    using M = typename LaneTraits<F>::M;
    static constexpr int kFetches = kAdjoint ? kKept : 1;  // the backward's: each step's fetch
    I occ;  // straight-through: the hard coverage
    F shift;
    LaneArray<F, kSectors> omega, P;
    int n;
    // with gradients: each step's interval, its front and back positions (before their clamps), its thickness t,
    // the value its scale multiplies and its delta; without kAdjoint, d delta / d radius and d t / d radius (the
    // sample's motion as the radius moves the step)
    LaneArray<F, kKept> s, w, front, back, t, tv, delta[3];
    LaneArray<F, kAdjoint ? 1 : kKept> radial[3], radial_t;
    // the backward: each step's taps, bilinear weights, fetched position, validity, distance in
    // pixels, d position / d su, d sv and d / d su, d sv of a layer's read (ThicknessModel::layer_slope)
    LaneArray<F, kFetches> fu, fv, pos[3], dist, d_su[3], d_sv[3], dv_su, dv_sv;
    LaneArray<I, kFetches> index[4];
    LaneArray<M, kFetches> valid;
    LaneArray<SoftCoverage<F>, kKeepCoverage ? kKept : 1> coverages;  // the sweep's, for the reverse scan
    F light[3];  // the forward's indirect light: what the slice's steps send
    // the backward's with indirect light: each step's d L / d the share it newly occludes (SoftAdjoint::step), and
    // in straight-through mode that (hard) share
    LaneArray<F, kFetches> gain, hard_newly;
  };
  template <class F> struct Sums {
    F num = F(0.0f), den = F(0.0f), radius = F(0.0f), thickness = F(0.0f), scale = F(0.0f), growth = F(0.0f);
    // the forward's: the light the steps send (with indirect), the visible sectors' direction sum (with bent)
    F light[3] = {F(0.0f), F(0.0f), F(0.0f)}, bent[3] = {F(0.0f), F(0.0f), F(0.0f)};
    // the backward's: d L / d fx, fy, cx, cy (values only), and d L / d the pixel's own inputs but through the
    // visibility (tangents only)
    F camera[4] = {F(0.0f), F(0.0f), F(0.0f), F(0.0f)};
    F loss = F(0.0f);
    F lit = F(0.0f);  // the backward's sum of each step's gain times its newly occluded share (values only)
  };
  // d visibility / d of one step's s and w, of its front and back angles, of the slice's shift; the share it newly
  // occludes (with gains)
  template <class B> struct StepAdjoint { B s, w, front, back, shift, newly; };
  // the visibility, the indirect light, the bent normal's sum
  TAO_FN int outputs() const { return 1 + (indirect ? 3 : 0) + (bent ? 3 : 0); }
  TAO_FN int channels() const { return kGradients && !kAdjoint ? 4 + grows : outputs(); }

  // d L / d t of a kept step at delta (g_thickness; t = base (1 + growth |delta|), ThicknessModel::at) onto its
  // model's parameters in sums: the offset's (d t / d offset = the factor), the scale's (times the value) and the
  // growth's (base |delta|); with g_delta, the growth's share of d L / d delta added (d |delta| / d delta = delta /
  // |delta|). d L / d the base returned. (None where g_thickness is 0: a background texel's layer is inf.)
  template <class F, class G>
  TAO_FN F thickness_adjoint(const F& g_thickness, const F* delta, const F& t, const F& value, const Pixels<F>& px,
                             Sums<G>& sums, F* g_delta = nullptr) const {
    const F g_base = grows ? growth_adjoint(g_thickness, delta, t, px, sums, g_delta) : g_thickness;
    const F g_t = select(px.live, g_base, F(0.0f));
    sums.thickness = sums.thickness + G(g_t);
    sums.scale = sums.scale + G(select(g_t != F(0.0f), g_t * value, F(0.0f)));
    return g_base;
  }
  // thickness_adjoint's growth: its gradient into sums, its share of d L / d delta into g_delta (if given); d L / d
  // the base returned
  template <class F, class G>
  TAO_COLD F growth_adjoint(const F& g_thickness, const F* delta, const F& t, const Pixels<F>& px, Sums<G>& sums,
                            F* g_delta) const {
    F length;
    const F factor = thickness.growth_factor(delta, length), base = t / factor;
    const auto on = g_thickness != F(0.0f);
    sums.growth = sums.growth + G(select(land(on, px.live), g_thickness * base * length, F(0.0f)));
    if (g_delta) {
      const F per = select(on, g_thickness * base * F(thickness.growth) / clamp_min(length, F(1e-30f)), F(0.0f));
      for (int c = 0; c < 3; ++c) g_delta[c] = g_delta[c] + per * delta[c];
    }
    return g_thickness * factor;
  }

  // out(j, logistic(x_j)), x_j = x0 + j / tau clamped to +-kSoftClamp (sectors.sweeps), for j = 0 .. n - 1:
  // a step's sector logistics are such a run. e^-x_j is a running product, e^-x_(j-1) e^(-1 / tau), from the exp
  // of the run's first term a at x_a clamped to +-run_bound (= kSoftClamp + (run - 1) / tau: where that clamp
  // acts, the whole run is at the clamp of +-kSoftClamp; the products stay normal floats: soft_window); each
  // e^-x_j is then clamped as x_j is. One exp a run and a multiply a term, where each term took an exp (within
  // 1e-6 relative of e^-x_j: at most 7 products)
  template <class F, class Out> TAO_FN void sigmoid_run(const F& x0, int n, const Out& out) const {
    const float inv_tau = float(1.0 / double(tau));
    F e = F(0.0f);
    for (int j = 0, r = 0; j < n; ++j, r = r + 1 < run ? r + 1 : 0) {
      e = r == 0 ? exp_inline(clamp(neg(x0) - F(float(j) * inv_tau), F(-run_bound), F(run_bound))) : e * F(run_ratio);
      out(j, inverse_one_plus(clamp(e, F(kSoftExpLow), F(kSoftExpHigh))));
    }
  }

  template <class F> TAO_FN void coverage(const F& s, const F& w, SoftCoverage<F>& cv) const {
    const float inv_tau = float(1.0 / double(tau));
    const F wc = clamp_min(w, F(0.0f));  // an empty step: zero width, zero gate
    const F t = expm1(wc * F(inv_tau) * F(-2.0f));  // sweeps.expm1_tanh
    cv.gate = neg(t / (t + F(2.0f)));
    // the sectors where some live lane's a b can exceed logistic(-kSoftSkip), margin = kSoftSkip tau: a < 2e-9
    // below s - 1 - margin, b < 2e-9 above s + w + 2 + margin (the smooth floor F(s) < s + 1/2 + tau ln 2, under
    // s + 2 wherever the margin leaves a sector out: tau < 32 / kSoftSkip)
    const auto live = w >= F(0.0f);
    const float margin = kSoftSkip * tau;
    const float first = reduce_min(select(live, s, F(float(kSectors)))) - 1.0f - margin;
    const float last = reduce_max(select(live, s + wc, F(0.0f))) + 2.0f + margin;
    cv.k0 = first > 0.0f ? (first < float(kSectors) ? int(first) : kSectors) : 0;  // (NaN: every sector)
    cv.k1 = last < float(kSectors) ? (last > float(cv.k0) ? int(last) + 1 : cv.k0) : kSectors;
    // a_k = logistic((k + 1 - s) / tau)
    sigmoid_run((F(float(cv.k0 + 1)) - s) * F(inv_tau), cv.k1 - cv.k0, [&](int j, const F& a) { cv.a[cv.k0 + j] = a; });
    F floor_s = F(0.0f), slope = F(0.0f);
    if (windowed) {  // sum_i x_i, x_i = logistic((s - lo - i) / tau), from the last i
      const F lo = clamp(floor(s) - F(float(reach - 1)), F(1.0f), F(float(kSectors - window + 1)));
      sigmoid_run((s - lo - F(float(window - 1))) * F(inv_tau), window, [&](int, const F& x) {
        floor_s = floor_s + x;
        slope = slope + logistic_slope(x);
      });
      floor_s = floor_s + (lo - F(1.0f));
    } else {  // (each sector below k0 adds 1 - a = 1, each from k1 on 0)
      floor_s = F(float(cv.k0));
      for (int k = cv.k0; k < cv.k1; ++k) {
        // (logistic_slope(a), written out so that 1 - a serves the floor too: with the call, the soft backward
        // measured 4 % slower, 97-100 ms against 102-105)
        const F not_a = F(1.0f) - cv.a[k];
        floor_s = floor_s + not_a;
        slope = slope + not_a * cv.a[k];
      }
    }
    cv.slope = slope * F(inv_tau);
    // b_k = logistic((w + 1 - delta + F(s) - (k + 1)) / tau), from the last k
    sigmoid_run((wc + F(1.0f - delta) + floor_s - F(float(cv.k1))) * F(inv_tau), cv.k1 - cv.k0,
                [&](int j, const F& b) { cv.b[cv.k1 - 1 - j] = b; });
  }

  // P <- P - a b g P over the sectors (P_m kept in before, if given; the coverage in keep, if given); with
  // weights, the share the step newly occludes, sum_k weights_k a b g P_k (soft_union's newly), else 0
  template <class B>
  TAO_FN B cover(const B& s, const B& w, B* P, B* before, SoftCoverage<B>* keep = nullptr,
                 const B* weights = nullptr) const {
    SoftCoverage<B> local;
    SoftCoverage<B>& cv = keep ? *keep : local;
    coverage(s, w, cv);
    B newly = B(0.0f);
    for (int k = cv.k0; k < cv.k1; ++k) {
      if (before) before[k] = P[k];
      const B c = cv.b[k] * cv.a[k] * cv.gate;
      if (weights) newly = newly + weights[k] * (c * P[k]);
      P[k] = P[k] - c * P[k];
      P[k] = select(P[k] > B(kSoftTiny), P[k], B(0.0f));
    }
    return newly;
  }

  // The light a sample sends per unit of the share it newly occludes: its light times light_factor
  template <class F> TAO_FN void sample_light(const Pixels<F>& px, const Sample<F>& smp, F* light) const {
    F sender_n[3];
    for (int c = 0; c < 3; ++c) sender_n[c] = smp.gather(smp.image->normals, c);
    const F factor = light_factor(smp.delta, sender_n, px.N, smp.valid, cosine);
    for (int c = 0; c < 3; ++c) light[c] = smp.gather(smp.image->light, c) * factor;
  }

  // The forward's light: newly times what the sample sends (sample_light) added on the lanes in sends (read only where
  // some lane sends)
  template <class F>
  TAO_FN void send_light(State<F>& st, const Pixels<F>& px, const Sample<F>& smp, const typename LaneTraits<F>::M& sends,
                         const F& newly) const {
    if (!any(sends)) return;
    F light[3];
    sample_light(px, smp, light);
    for (int c = 0; c < 3; ++c) st.light[c] = st.light[c] + select(sends, newly * light[c], F(0.0f));
  }

  // The share of the hemisphere the sectors `fresh` cover (their weights' sum)
  template <class F> TAO_FN F newly_share(const State<F>& st, const typename LaneTraits<F>::I& fresh) const {
    F newly = F(0.0f);
    for (int k = 0; k < kSectors; ++k) newly = newly + bit(fresh, k) * st.omega[k];
    return newly;
  }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>& walked) const {
    const Slice<F> sl = slice_frame(angles, walked);
    State<F> st;
    st.occ = typename LaneTraits<F>::I(0);
    st.shift = edge_shift(sl);
    st.n = 0;
    for (int c = 0; c < 3; ++c) st.light[c] = F(0.0f);
    for (int k = 0; k < kSectors; ++k) st.P[k] = F(1.0f), st.omega[k] = F(1.0f / kSectors);
    if (cosine) cosine_sector_weights(sl, st.omega);
    return st;
  }

  template <class F>
  TAO_FN void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    const int turn = sector_turn(angles, side);
    const F scale = F(float(turn) / kPi), t = thickness.at(px, smp);
    F front_angle, back_angle, s, w;
    // (lanes past the row or on the background, and with the segment geometry invalid samples and segments that miss
    // the sphere, as DefaultAccumulator.interval: empty)
    auto live = segments() ? land(px.live, smp.valid) : px.live;
    step_angles(side, px, sl, smp.delta, t, live, front_angle, back_angle);
    const F front = fma(front_angle, scale, st.shift), back = fma(back_angle, scale, st.shift);
    sample_interval(turn, front, back, epsilon, s, w);
    w = select(live, w, F(-1.0f));
    if (straight_through) {
      const typename LaneTraits<F>::I bits = sector_bits(s, w, rounding);
      if (indirect && (kAdjoint || !kGradients)) {  // (the hard share: straight-through's values)
        const typename LaneTraits<F>::I fresh = bits & bnot(st.occ);
        const F newly = newly_share(st, fresh);
        if (kAdjoint) st.hard_newly[st.n] = newly;
        // (only a non-empty interval gathers light; none is read where no lane occludes anything new)
        const auto sends = land(w >= F(0.0f), lnot(ieq(fresh, typename LaneTraits<F>::I(0))));
        if (!kGradients) send_light(st, px, smp, sends, newly);
      }
      st.occ = st.occ | bits;
    }
    if (!kGradients) {
      if (!straight_through && any(w >= F(0.0f))) {
        const F newly = cover(s, w, &st.P[0], static_cast<F*>(nullptr), static_cast<SoftCoverage<F>*>(nullptr),
                              indirect ? &st.omega[0] : static_cast<const F*>(nullptr));
        if (indirect) send_light(st, px, smp, land(w >= F(0.0f), newly > F(0.0f)), newly);
      }
      return;
    }
    const int m = st.n++;
    st.s[m] = s, st.w[m] = w, st.front[m] = front, st.back[m] = back, st.t[m] = t, st.tv[m] = thickness.value(px, smp);
    for (int c = 0; c < 3; ++c) st.delta[c][m] = smp.delta[c];
    F d_su[3] = {F(0.0f), F(0.0f), F(0.0f)}, d_sv[3] = {F(0.0f), F(0.0f), F(0.0f)};
    const F dist = step_distance(walk, sl, step_noise(walk, px, sl, side), m % walk.steps);
    const bool moves = smp.bilinear && any(w >= F(0.0f));  // (an empty step has no gradient; the nearest texel does not move)
    if (moves) {
      const F su = along_u(px, sl, float(side), dist), sv = along_v(px, sl, float(side), dist);
      fetch_motion(smp, px.P, su, sv, d_su, d_sv);
    }
    if (kAdjoint) {  // the backward: the fetch, for the pixel's and the taps' gradients (end_slice_adjoint)
      for (int c = 0; c < 3; ++c) {
        st.pos[c][m] = smp.delta[c] + px.P[c];
        st.d_su[c][m] = d_su[c], st.d_sv[c][m] = d_sv[c];
      }
      for (int i = 0; i < 4; ++i) st.index[i][m] = smp.index[i];
      st.fu[m] = smp.fu, st.fv[m] = smp.fv, st.valid[m] = smp.valid, st.dist[m] = dist;
      st.dv_su[m] = F(0.0f), st.dv_sv[m] = F(0.0f);
      if (moves) thickness.layer_slope(smp, st.dv_su[m], st.dv_sv[m]);
      return;
    }
    // the sample's motion along the radius: dist' = frac span', span = radius_px - min_step_px (>= 0)
    F d_pos[3] = {F(0.0f), F(0.0f), F(0.0f)}, dt = F(0.0f);
    if (moves) {
      F dsu, dsv;
      step_motion(walk, px, sl, float(side), dist, dsu, dsv);
      for (int c = 0; c < 3; ++c) d_pos[c] = d_su[c] * dsu + d_sv[c] * dsv;
      dt = F(thickness.scale) * thickness.motion(smp, d_pos, dsu, dsv);
      if (grows) dt = thickness.grown_motion(dt, smp.delta, d_pos, t);
    }
    for (int c = 0; c < 3; ++c) st.radial[c][m] = d_pos[c];
    st.radial_t[m] = dt;
  }

  // With gradients: the slice's union over its kept steps, P_m before each step kept in before[m * 32 + k]
  template <class F> TAO_FN void sweep(State<F>& st, F* before) const {
    for (int m = 0; m < st.n; ++m)
      if (any(st.w[m] >= F(0.0f)))
        cover(st.s[m], st.w[m], &st.P[0], &before[m * kSectors], kKeepCoverage ? &st.coverages[m] : nullptr);
  }

  // The slice's visible share sum_k free_k omega_k (the weights' sum added to *den with cosine weights); omega:
  // st.omega, or the same weights with tangents (G: their lane type)
  template <class F, class Weights, class G, class W = F>
  TAO_FN G visible(const State<F>& st, const Weights& omega, G* den, const Slice<W>* walked = nullptr) const {
    G share = G(0.0f), weight = G(0.0f);
    for (int k = 0; k < kSectors; ++k) {
      share = share + G(free_share(st, k)) * omega[k];
      if (cosine) weight = weight + omega[k];
    }
    // (the slice's weights summed as its share is: every free share <= 1, so the share <= the weight and the
    // visibility <= 1 after rounding, as the tensor path's per-slice sums; walked: the slice whose weight it takes)
    if (cosine) *den = *den + (walked ? weighed(*walked, weight) : weight);
    return share;
  }

  // sector k's free share: 1 - the union's soft coverage, or the hard one's in straight-through mode
  template <class F> TAO_FN F free_share(const State<F>& st, int k) const {
    return straight_through ? F(1.0f) - bit(st.occ, k) : st.P[k];
  }

  // The slice's bent-normal sum (bent_axes of the free shares times omega) into bent, in the frame's V and T (of
  // the walked slice's T: frame_tangent) at its angle fa
  template <class F, class Weights, class G>
  TAO_FN void slice_bent(const State<F>& st, const Weights& omega, const G* V, const G* walked_T, const FrameAngle<G>& fa,
                         G* bent) const {
    G along_v, along_t;
    bent_axes([&](int k) { return G(free_share(st, k)) * omega[k]; }, fa.cos_gamma, fa.sin_gamma, along_v, along_t);
    for (int c = 0; c < 3; ++c) bent[c] = along_v * V[c] + along_t * frame_tangent(angles, walked_T[c]);
  }

  // soft_union's reverse scan over the slice's kept steps (after sweep) from seed(k) (d the loss / d sector k's
  // free share): fn(m, StepAdjoint) for each step with a live lane, last to first. With gains (st.gain: d the
  // loss / d each step's newly occluded share, soft_union's gn), D_m = S_{m+1} - gn_m omega takes S's place, each
  // step's share joins its adjoint, and, with E, E_k gains sum_m gn_m c_mk P_mk (d the loss / d omega_k); with start,
  // start_k receives S_0k (d the loss / d the slice's initial share of sector k: soft_union's dL/dp0)
  template <class F, class Seed, class Fn>
  TAO_FN void reverse_scan(const State<F>& st, const F* before, const Seed& seed, const Fn& fn, bool gains = false,
                           F* E = nullptr, F* start = nullptr) const {
    const float inv_tau = float(1.0 / double(tau));
    F S[kSectors];
    for (int k = 0; k < kSectors; ++k) S[k] = seed(k);
    for (int m = st.n - 1; m >= 0; --m) {
      const auto live = st.w[m] >= F(0.0f);
      if (!any(live)) continue;
      SoftCoverage<F> local;
      if (!kKeepCoverage) coverage(st.s[m], st.w[m], local);
      const SoftCoverage<F>& cv = kKeepCoverage ? st.coverages[m] : local;
      F sum_y = F(0.0f), sum_ya = F(0.0f), sum_yb = F(0.0f), newly = F(0.0f);
      const F gain = gains ? st.gain[m] : F(0.0f);
      for (int k = cv.k0; k < cv.k1; ++k) {
        const F ab = cv.a[k] * cv.b[k], P = before[m * kSectors + k];
        const F D = gains ? S[k] - gain * st.omega[k] : S[k];
        const F y = ab * P * D;  // Y = a b P_m D_m
        sum_y = sum_y + y;
        sum_ya = sum_ya + y * cv.a[k];
        sum_yb = sum_yb + y * cv.b[k];
        if (gains) {
          const F covered = ab * cv.gate * P;  // c_mk P_mk
          newly = newly + st.omega[k] * covered;
          if (E) E[k] = E[k] + gain * covered;
        }
        S[k] = S[k] - ab * cv.gate * D;
      }
      const F g = cv.gate, not_b = sum_y - sum_yb;
      StepAdjoint<F> adj;
      adj.newly = select(live, newly, F(0.0f));  // (a dead lane's interval, empty or NaN, occludes nothing)
      // dL/dw = -(g' sum Y + g / tau sum Y (1 - b)), g' = (1 - g^2) / tau;
      // dL/ds = -(g / tau) (F' sum Y (1 - b) - sum Y (1 - a))
      adj.w = select(live, ((g * g - F(1.0f)) * sum_y - g * not_b) * F(inv_tau), F(0.0f));
      adj.s = select(live, (not_b * cv.slope - sum_y + sum_ya) * g * F(-inv_tau), F(0.0f));
      // SectorInterval.backward: s = 32 lo, w = 32 (hi - lo) - epsilon, the clamps pass inside [0, 1]
      const int turn = sector_turn(angles, m < walk.steps ? 1 : -1);
      const F g_lo = (adj.s - adj.w) * F(float(kSectors)), g_hi = adj.w * F(float(kSectors));
      const F front = st.front[m], back = st.back[m];
      const F g_f = select(land(front >= F(0.0f), front <= F(1.0f)), turn > 0 ? g_lo : g_hi, F(0.0f));
      const F g_b = select(land(back >= F(0.0f), back <= F(1.0f)), turn > 0 ? g_hi : g_lo, F(0.0f));
      adj.front = g_f * F(float(turn) / kPi), adj.back = g_b * F(float(turn) / kPi), adj.shift = g_f + g_b;
      fn(m, adj);
    }
    if (start)
      for (int k = 0; k < kSectors; ++k) start[k] = S[k];
  }

  template <class F>
  TAO_FN void end_slice(State<F>& st, const Pixels<F>& px, const Slice<F>& walked, Sums<F>& sums) const {
    LaneArray<F, kKept * kSectors> before;  // P_m of each step (with gradients)
    if (kGradients) sweep(st, &before[0]);
    // (every sum weighs by the slice's Slice::weight: 1 but for slices drawn by a density; the parameters'
    // derivatives too, through the reverse scan's seed)
    sums.num = sums.num + weighed(walked, visible(st, st.omega, &sums.den, &walked));
    if (indirect && !kGradients)
      for (int c = 0; c < 3; ++c) sums.light[c] = sums.light[c] + weighed(walked, st.light[c]);
    if (bent && !kGradients) {
      F part[3];
      slice_bent(st, st.omega, px.V, walked.T, frame_angle(angles, walked), part);
      for (int c = 0; c < 3; ++c) sums.bent[c] = sums.bent[c] + weighed(walked, part[c]);
    }
    if (!kGradients) return;
    // d visibility / d delta and t of each step (sample_angles_adjoint), then along the radius' motion of both
    const auto seed = [&](int k) { return weighed(walked, st.omega[k]); };
    reverse_scan(st, &before[0], seed, [&](int m, const StepAdjoint<F>& g) {
      const F delta[3] = {st.delta[0][m], st.delta[1][m], st.delta[2][m]};
      F g_delta[3] = {F(0.0f), F(0.0f), F(0.0f)}, unused_V[3] = {F(0.0f), F(0.0f), F(0.0f)};
      F unused_T[3] = {F(0.0f), F(0.0f), F(0.0f)}, unused_P[3] = {F(0.0f), F(0.0f), F(0.0f)}, g_clip = F(0.0f);
      const F g_thickness = step_angles_adjoint(m < walk.steps ? 1 : -1, px, walked.T, delta, st.t[m], g.front,
                                                g.back, g_delta, unused_V, unused_T, unused_P, g_clip);
      thickness_adjoint(g_thickness, delta, st.t[m], st.tv[m], px, sums);
      const F radial[3] = {st.radial[0][m], st.radial[1][m], st.radial[2][m]};
      // (the steps' motion along the radius, and the clip's sphere's own)
      sums.radius = sums.radius +
                    select(px.live, fma(g_thickness, st.radial_t[m], dot3(g_delta, radial)) + g_clip, F(0.0f));
    });
  }

  // The backward's slice (kAdjoint), for the loss L = weight num + light_weight . (the light the steps send) +
  // bent_weight . (the bent normal's sum) (weight, light_weight: d L / d the visibility, d L / d the indirect light,
  // over the denominator; bent_weight: d L / d the bent normal's sum; null without those outputs): the reverse scan
  // from d L / d each sector's free share (and each step's gain, SoftAdjoint::step's) gives d L / d delta of each
  // step (the light's replay, light_adjoint, adds its own), which goes to sink.scatter(g_delta, st,
  // m, lanes), which chains it to the step's taps; the same adjoints chained by hand through the step (delta =
  // pos(su, sv) - P or -V, su = u + side dist unit_u, dist = min_step_px + span frac, the angles by
  // sample_angles_adjoint, the shift) to the slice's quantities, whose tangents on the pixel's own inputs (pd, sd:
  // the pixel and slice in dual lanes; the variant's frame from sd) sums.loss gains. sums.num gains the slice's
  // visible share (its value; sums.den the weights with their tangents), and sums.loss the tangents of its weights
  // and frame through the share times weight and through the bent-normal sum times bent_weight. With camera
  // (the image whose intrinsics want gradients), also d L / d fx, fy, cx, cy into sums.camera: through the slice's
  // screen motion (du, dv) = (fx a, -fy b) / depth (its direction unit_u, unit_v and the span from its length) and
  // a bilinear fetch's unprojection ((su - cx) / fx, -(sv - cy) / fy) depth
  template <class F, class D, class Sink>
  TAO_FN void end_slice_adjoint(State<F>& st, const Pixels<F>& px, const Slice<F>& sl, const Pixels<D>& pd,
                                const Slice<D>& sd, Sums<D>& sums, const F& weight, const F* light_weight,
                                const F* bent_weight, Sink& sink, const Image& img, const Image* camera = nullptr) const {
    LaneArray<F, kKept * kSectors> before;
    sweep(st, &before[0]);
    // A slice drawn by the projected normal's density counts by its weight (sd.weight, 1 for the others): the
    // slice's part of L is w U, so every adjoint below is w times U's, and w's tangents add U dw (unweighted: U)
    const F w = weighed(sl, F(1.0f)), weight_w = weight * w;
    const F *light_w = light_weight, *bent_w = bent_weight;
    F light_scaled[3], bent_scaled[3];
    if (sectors_drawn(walk)) {
      for (int c = 0; c < 3; ++c) {
        if (light_weight) light_scaled[c] = light_weight[c] * w;
        if (bent_weight) bent_scaled[c] = bent_weight[c] * w;
      }
      light_w = light_weight ? light_scaled : nullptr, bent_w = bent_weight ? bent_scaled : nullptr;
    }
    const FrameAngle<D> frame = frame_angle(angles, sd);  // (the shift's and the weights' gamma, with tangents)
    LaneArray<D, kSectors> omega;  // cosine weights with their tangents (uniform ones have none: st.omega)
    if (cosine) {
      for (int k = 0; k < kSectors; ++k) omega[k] = D(1.0f / kSectors);
      cosine_sector_weights(frame, sd.length, omega);
    }
    // (its tangents, times weight, are the loss's through num)
    const D share = cosine ? visible(st, omega, &sums.den, &sd) : D(visible(st, st.omega, static_cast<F*>(nullptr)));
    sums.num = sums.num + D(w * share.v);
    sums.loss = sums.loss + D(weight_w) * share;
    F unweighted = weight * share.v;
    // d L / d each sector's free share: the visibility's weight omega_k, and with bent normals omega_k times the
    // upstream gradient's components along the sector centre's direction
    F g_v = F(0.0f), g_t = F(0.0f);
    if (bent_weight) {  // (the sum's own tangents, through its weights and frame, times the upstream gradient)
      D part[3];
      if (cosine)
        slice_bent(st, omega, pd.V, sd.T, frame, part);
      else
        slice_bent(st, st.omega, pd.V, sd.T, frame, part);
      for (int c = 0; c < 3; ++c) {
        sums.loss = sums.loss + D(bent_w[c]) * part[c];
        unweighted = unweighted + bent_weight[c] * part[c].v;
        g_v = g_v + bent_w[c] * px.V[c], g_t = g_t + bent_w[c] * frame_tangent(angles, sl.T[c]);
      }
    }
    const F cos_gamma = frame.cos_gamma.v, sin_gamma = frame.sin_gamma.v;
    const auto seed = [&](int k) {
      if (!bent_weight) return weight_w * st.omega[k];
      F v, t;
      sector_centre(k, cos_gamma, sin_gamma, v, t);
      return st.omega[k] * (weight_w + g_v * v + g_t * t);
    };
    const F lit_before = sums.lit.v;  // (the slice's light part of L, its gains w times U's, is what it adds)
    F g_V[3] = {F(0.0f), F(0.0f), F(0.0f)}, g_T[3] = {F(0.0f), F(0.0f), F(0.0f)}, g_P[3] = {F(0.0f), F(0.0f), F(0.0f)};
    F g_N[3] = {F(0.0f), F(0.0f), F(0.0f)};  // (indirect light's: the pixel's normal faces the samples)
    F g_shift = F(0.0f);
    PlacementAdjoint<F> placement;
    F g_cam[4] = {F(0.0f), F(0.0f), F(0.0f), F(0.0f)};  // d L / d fx, fy, cx, cy (with camera)
    LaneArray<F, kSectors> g_omega;  // (indirect light with cosine weights: d L / d omega through the steps' shares)
    if (light_weight && cosine)
      for (int k = 0; k < kSectors; ++k) g_omega[k] = F(0.0f);
    reverse_scan(st, &before[0], seed, [&](int m, const StepAdjoint<F>& g) {
      const F delta[3] = {st.delta[0][m], st.delta[1][m], st.delta[2][m]};
      const auto valid = st.valid[m];
      F g_delta[3] = {F(0.0f), F(0.0f), F(0.0f)};  // (the angles' parts of g_V, g_T, g_P join them here)
      F unused_radius = F(0.0f);  // (the radius': Euler's identity, soft_bitmask.py)
      const F g_thickness = step_angles_adjoint(m < walk.steps ? 1 : -1, px, sl.T, delta, st.t[m], g.front, g.back,
                                                g_delta, g_V, g_T, g_P, unused_radius);
      // d L / d the value the scale multiplies (the offset's, the scale's and the growth's into sums)
      const F g_value = thickness_adjoint(g_thickness, delta, st.t[m], st.tv[m], px, sums, g_delta) *
                        F(thickness.scale);
      if (thickness.read == ThicknessRead::depth) {  // value = -(delta_z + P_z): the fetched position's depth
        g_delta[2] = g_delta[2] - g_value;
        g_P[2] = g_P[2] - g_value;  // (with g_P's -g_delta below: none of it on the pixel's own P)
      }
      // the fetch moves with (su, sv): its position, and a layer's read there
      F g_su = g_delta[0] * st.d_su[0][m] + g_delta[1] * st.d_su[1][m] + g_delta[2] * st.d_su[2][m] +
               g_value * st.dv_su[m];
      F g_sv = g_delta[0] * st.d_sv[0][m] + g_delta[1] * st.d_sv[1][m] + g_delta[2] * st.d_sv[2][m] +
               g_value * st.dv_sv[m];
      if (light_weight) {  // the light it sends (sample_light, times the share it newly occludes)
        const F newly = straight_through ? st.hard_newly[m] : g.newly;
        sums.lit.v = sums.lit.v + st.gain[m] * newly;
        const typename LaneTraits<F>::I taps[4] = {st.index[0][m], st.index[1][m], st.index[2][m], st.index[3][m]};
        const Sample<F> smp(img, walk.bilinear, taps, st.fu[m], st.fv[m], valid);
        F g_light_delta[3];
        light_adjoint(px, smp, delta, newly, light_w, g_light_delta, g_N, g_su, g_sv, sink, st, m,
                      land(px.live, valid));
        for (int c = 0; c < 3; ++c) g_delta[c] = g_delta[c] + g_light_delta[c];
        const F d_su[3] = {st.d_su[0][m], st.d_su[1][m], st.d_su[2][m]}, d_sv[3] = {st.d_sv[0][m], st.d_sv[1][m], st.d_sv[2][m]};
        g_su = g_su + dot3(g_light_delta, d_su), g_sv = g_sv + dot3(g_light_delta, d_sv);
      }
      for (int c = 0; c < 3; ++c) {
        g_V[c] = g_V[c] - select(valid, F(0.0f), g_delta[c]);
        g_P[c] = g_P[c] - select(valid, g_delta[c], F(0.0f));
      }
      placement.add(walk, sl, m < walk.steps ? 1.0f : -1.0f, st.dist[m], g_su, g_sv);
      g_shift = g_shift + g.shift;
      if (camera && walk.bilinear) {
        const F pos[3] = {st.pos[0][m], st.pos[1][m], st.pos[2][m]};
        const typename LaneTraits<F>::I index[4] = {st.index[0][m], st.index[1][m], st.index[2][m], st.index[3][m]};
        unprojection_camera(walk, *camera, index, pos, g_delta, land(px.live, valid), g_cam);
      }
      // (g_value: read by the layer's taps, scattered where the model reads a layer)
      sink.scatter(g_delta, st, m, land(px.live, valid), thickness.reads_layer() ? &g_value : nullptr);
    }, light_weight != nullptr, light_weight && cosine ? &g_omega[0] : nullptr);
    if (light_weight && cosine) {  // (the weights' tangents through the shares the steps newly occlude)
      D through = D(0.0f);
      for (int k = 0; k < kSectors; ++k) through = through + D(g_omega[k]) * omega[k];
      sums.loss = sums.loss + through;
    }
    if (sectors_drawn(walk)) {  // U dw (w > 0: the density's bins are at least 1e-4)
      if (light_weight) unweighted = unweighted + (sums.lit.v - lit_before) / w;
      sums.loss = sums.loss + D(unweighted) * (sd.weight - D(sd.weight.v));
    }
    if (camera) {
      placement.camera(walk, *camera, sl, g_cam);
      for (int k = 0; k < 4; ++k) sums.camera[k].v = sums.camera[k].v + select(px.live, g_cam[k], F(0.0f));
    }
    D along = D(placement.unit_u) * sd.unit_u + D(placement.unit_v) * sd.unit_v + D(placement.span) * sd.span +
              D(g_shift) * ((D(kHalfPi) - frame.gamma) / D(kPi));
    for (int c = 0; c < 3; ++c) along = along + D(g_V[c]) * pd.V[c] + D(g_T[c]) * sd.T[c] + D(g_P[c]) * pd.P[c];
    if (light_weight)
      for (int c = 0; c < 3; ++c) along = along + D(g_N[c]) * pd.N[c];
    sums.loss = sums.loss + (along - D(along.v));  // (its tangents only)
  }

  // The adjoint of a kept step's light (sample_light times newly: its share), for d L / d the light = light_weight:
  // d L / d its delta into g_delta; d L / d the pixel's normal added to g_N; d L / d its sender's normal and light
  // scattered to its taps (sink.scatter_light, on the lanes in on), and their reads' motion with the screen position
  // added to g_su, g_sv
  template <class F, class Sink>
  TAO_FN void light_adjoint(const Pixels<F>& px, const Sample<F>& smp, const F* delta, const F& newly,
                            const F* light_weight, F* g_delta, F* g_N, F& g_su, F& g_sv, Sink& sink,
                            const State<F>& st, int m, const typename LaneTraits<F>::M& on) const {
    using L = Dual<F, 9>;  // tangents: delta, the sender's normal, the pixel's normal
    L d[3], sender_n[3], N[3];
    F light[3];
    for (int c = 0; c < 3; ++c) {
      d[c] = L(delta[c]), sender_n[c] = L(smp.gather(smp.image->normals, c)), N[c] = L(px.N[c]);
      d[c].d[c] = F(1.0f), sender_n[c].d[3 + c] = F(1.0f), N[c].d[6 + c] = F(1.0f);
      light[c] = smp.gather(smp.image->light, c);
    }
    const L factor = light_factor(d, sender_n, N, smp.valid, cosine);
    F g_factor = F(0.0f), g_light[3], g_sender[3];
    for (int c = 0; c < 3; ++c) {
      const F per = light_weight[c] * newly;  // d L / d the light it sends, channel c
      g_factor = g_factor + per * light[c];
      g_light[c] = per * factor.v;
    }
    for (int c = 0; c < 3; ++c) {
      g_delta[c] = g_factor * factor.d[c];
      g_sender[c] = g_factor * factor.d[3 + c];
      g_N[c] = g_N[c] + select(px.live, g_factor * factor.d[6 + c], F(0.0f));
      F n_su, n_sv, l_su, l_sv;
      smp.gather_slope(smp.image->normals, c, 3, n_su, n_sv);
      smp.gather_slope(smp.image->light, c, 3, l_su, l_sv);
      g_su = g_su + g_sender[c] * n_su + g_light[c] * l_su;
      g_sv = g_sv + g_sender[c] * n_sv + g_light[c] * l_sv;
    }
    sink.scatter_light(g_sender, g_light, st, m, on);
  }

  // The visibility's denominator at the pixels of walk_block(row, u0, n): the slices, or the cosine
  // weights' sum over them
  template <class F> TAO_FN F denominator(const Image& img, int64_t row, int64_t u0, int n) const {
    if (!cosine) return F(float(walk.slices));
    const Pixels<F> px(walk, img, row, u0, n);
    F den = F(0.0f);
    for (int64_t s = 0; s < walk.slices; ++s) {
      const Slice<F> sl = walked_slice<SoftAccumulator>(walk, img, px, s);
      LaneArray<F, kSectors> omega;
      cosine_sector_weights(slice_frame(angles, sl), omega);
      F sum = F(0.0f);
      for (int k = 0; k < kSectors; ++k) sum = sum + omega[k];
      den = den + weighed(sl, sum);  // (as visible sums a slice's weights)
    }
    return clamp_min(den, F(1e-30f));
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    const F den = cosine ? clamp_min(sums.den, F(1e-30f)) : F(float(walk.slices));
    out[0] = select(px.live, sums.num / den, F(1.0f));
    if (kGradients && !kAdjoint) {
      out[1] = select(px.live, sums.radius / den, F(0.0f));
      out[2] = select(px.live, sums.thickness / den, F(0.0f));
      out[3] = select(px.live, sums.scale / den, F(0.0f));
      if (grows) out[4] = select(px.live, sums.growth / den, F(0.0f));
      return;
    }
    int c0 = 1;
    if (indirect) {
      for (int c = 0; c < 3; ++c) out[c0 + c] = select(px.live, sums.light[c] / den, F(0.0f));
      c0 += 3;
    }
    if (bent)  // (its direction is taken in torch: soft_bitmask.bent_normal)
      for (int c = 0; c < 3; ++c) out[c0 + c] = select(px.live, sums.bent[c], F(0.0f));
  }
};

// The backward's accumulator (walk_block's interface) over value lanes F: SoftAccumulator<true, true>'s
// slices ended by end_slice_adjoint into sink, with the pixels pd in dual lanes D (tangents on their own
// P, N, depth) and each slice's in D; sums in D. The loss is upstream times the visibility, plus light_upstream
// (with indirect light; else null) dotted with the indirect light, plus bent_upstream (with bent normals; else null)
// dotted with the bent normal's sum; weight and light_weight: upstream and light_upstream over the denominator.
// finish writes d L / d the pixel's own 7, d L / d the thickness' offset, d its scale and d its growth, then (with
// camera; else zeros) d L / d fx, fy, cx, cy.
template <class F, class D, class Sink, int kMostSteps = kSoftMaxSteps> struct SoftAdjoint {
  using Acc = SoftAccumulator<true, true, kMostSteps>;
  const Acc& acc;
  const Image& img;
  const Pixels<D>& pd;
  F upstream, weight;
  const F *light_weight, *bent_upstream;
  Sink& sink;
  bool camera;  // d L / d the intrinsics too (4 more channels)
  mutable int64_t slice = 0;
  static constexpr bool kWeighsSlices = kSectorsWeighSlices;  // (end_slice_adjoint weighs a slice drawn by a density)
  template <class G> struct State {
    typename Acc::template State<G> base;
    Slice<D> sd;
  };
  template <class G> using Sums = typename Acc::template Sums<D>;
  TAO_FN int channels() const { return 14; }
  TAO_FN State<F> begin_slice(const Pixels<F>& px, const Slice<F>& sl) const {
    // (the lean CUDA build, which draws no slice by a density, builds it in place: through walked_slice's return
    // ptxas spilled twice the bytes in tao_soft_backward)
    if constexpr (!kSectorsWeighSlices) return State<F>{acc.begin_slice(px, sl), Slice<D>(acc.walk, img, pd, slice++)};
    return State<F>{acc.begin_slice(px, sl), walked_slice<Acc>(acc.walk, img, pd, slice++)};
  }
  TAO_FN void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    acc.step(st.base, side, px, sl, smp);
    const int m = st.base.n - 1;
    // d L / d the share the step newly occludes: its light's (the reverse scan's gain; a step with no live lane is
    // not scanned)
    if (light_weight && any(st.base.w[m] >= F(0.0f))) {
      F light[3];
      acc.sample_light(px, smp, light);
      st.base.gain[m] = select(px.live, weighed(sl, dot3(light_weight, light)), F(0.0f));
    }
  }
  TAO_FN void end_slice(State<F>& st, const Pixels<F>& px, const Slice<F>& sl, Sums<F>& sums) const {
    acc.end_slice_adjoint(st.base, px, sl, pd, st.sd, sums, weight, light_weight, bent_upstream, sink, img,
                          camera ? &img : nullptr);
  }
  TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    const D den = acc.cosine ? clamp_min(sums.den, D(1e-30f)) : D(float(acc.walk.slices));
    const F inv = F(1.0f) / den.v;
    // d L / d (1 / den): the visibility's numerator and the light's sum (lit: over the denominator)
    const F through_den = upstream * sums.num.v + sums.lit.v * den.v;
    for (int k = 0; k < 7; ++k) {
      // d (1 / den) = -d den / den^2, as two products: den^2 underflows where den is clamped at 1e-30 (its tangent
      // 0 there: 0 / 0 would be NaN)
      const F d_inv = neg(den.d[k] * inv) * inv;
      out[k] = select(px.live, through_den * d_inv + sums.loss.d[k], F(0.0f));
    }
    out[7] = sums.thickness.v, out[8] = sums.scale.v, out[9] = sums.growth.v;
    for (int k = 0; k < 4; ++k) out[10 + k] = sums.camera[k].v;
  }
};

}  // namespace tao
