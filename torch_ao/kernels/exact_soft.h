// The "exact" variant's accumulator with its derivatives (BitmaskAO(variant="exact") in soft,
// straight-through or hard mode, whose exact union is differentiable as it is: the modes are one walk) for
// walk.h: bitmask.h's ExactAccumulator walked in dual lanes Dual<F, 3> whose tangents are the derivatives
// with respect to the radius, the thickness model's offset and its scale (the back-face model's
// thickness_scale, LinearThickness' slope), and with kGrowth a fourth, its growth's (a model with a growth; the
// others do not carry its tangent). Channels: the visibility (ExactAccumulator's, value for value), then d visibility
// / d radius, d thickness, d thickness_scale (, d thickness_growth) of the pixel (the caller multiplies by the
// upstream gradient and sums).
//
// A sample's tangents: along the radius its fetched position moves with the step (dist = min_step_px +
// span frac, span from radius_px: soft.h's step_motion and fetch_motion), and so do a layer read at its
// taps and its depth (a first tap's read is piecewise constant); the thickness t = (scale * value + offset) (1 +
// growth |delta|), |delta| moving with the fetch too. ExactAccumulator::interval then carries them
// through the back point, the clip to the sphere (whose radius has tangent 1 along the radius), the atan2s
// and clamps, and union_measure through the sort and the running reach (at a tie max passes the first
// operand's: torch's maximum splits it, which only a measure-zero set of frames sees).
#pragma once

#include "lanes_dual.h"
#include "soft.h"

namespace tao {

template <bool kGrowth> struct ExactGradAccumulator {
  ExactAccumulator exact;
  WalkSettings walk;  // the step placement (the radius moves the steps)
  static constexpr int kTangents = kGrowth ? 4 : 3;  // radius, the thickness' offset, its scale (, its growth)
  static constexpr bool kWeighsSlices = kSectorsWeighSlices;  // (ExactAccumulator::add_slice weighs each slice)

  template <class F> using D = Dual<F, kTangents>;
  template <class F> struct State {
    F shift;
    LaneArray<D<F>, kMaxIntervals> lo, hi;
    int n;
  };
  template <class F> struct Sums {
    D<F> num;
    F den = F(0.0f);
  };
  TAO_FN int channels() const { return 1 + kTangents; }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>& sl) const {
    State<F> st;
    st.shift = edge_shift(sl);
    st.n = 0;
    return st;
  }

  template <class F>
  TAO_FN void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    const ThicknessModel& model = exact.thickness;
    D<F> delta[3];
    for (int c = 0; c < 3; ++c) delta[c] = D<F>(smp.delta[c]);
    D<F> t(model.at(px, smp));
    // t = base factor: base = scale value + offset, factor = 1 + growth |delta|
    const F value = model.read != ThicknessRead::constant ? model.value(px, smp) : F(0.0f);
    F factor = F(1.0f), length = F(0.0f);
    if constexpr (kGrowth) {  // (a parameter: its tangent is wanted at growth 0 too)
      factor = model.growth_factor(smp.delta, length);
      t.d[3] = (F(model.scale) * value + F(model.offset)) * length;
    }
    t.d[1] = factor, t.d[2] = value * factor;
    if (smp.bilinear && any(smp.valid)) {  // (the nearest texel does not move with the radius)
      const int64_t j = st.n % walk.steps;
      const F dist = step_distance(walk, sl, step_noise(walk, px, sl, side), j);
      const F su = along_u(px, sl, float(side), dist), sv = along_v(px, sl, float(side), dist);
      F d_su[3], d_sv[3], dsu, dsv;
      fetch_motion(smp, px.P, su, sv, d_su, d_sv);
      step_motion(walk, px, sl, float(side), dist, dsu, dsv);
      F d_pos[3];
      for (int c = 0; c < 3; ++c) delta[c].d[0] = d_pos[c] = d_su[c] * dsu + d_sv[c] * dsv;
      t.d[0] = F(model.scale) * model.motion(smp, d_pos, dsu, dsv);
      if constexpr (kGrowth) t.d[0] = model.grown_motion(t.d[0], smp.delta, d_pos, t.v);
    }
    D<F> radius(F(exact.radius));
    radius.d[0] = F(1.0f);
    exact.interval(side, px, sl, st.shift, delta, t, radius, smp.valid, st.lo[st.n], st.hi[st.n]);
    ++st.n;
  }

  template <class F>
  TAO_FN void end_slice(State<F>& st, const Pixels<F>&, const Slice<F>& sl, Sums<F>& sums) const {
    exact.add_slice(exact.union_measure(&st.lo[0], &st.hi[0], st.n, sl), sl, sums.num, sums.den);
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    exact.finish(typename ExactAccumulator::template Sums<F>{sums.num.v, sums.den}, px, out);
    const F den = exact.cosine ? clamp_min(sums.den, F(1e-30f)) : F(float(exact.slices));
    for (int k = 0; k < kTangents; ++k) out[1 + k] = select(px.live, sums.num.d[k] / den, F(0.0f));
  }
};

}  // namespace tao
