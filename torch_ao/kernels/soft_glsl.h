// The "ssilvb_glsl" variant in soft and straight-through mode (methods/bitmask_glsl.py GLSLAccumulator with
// mode="soft" / "straight_through") for walk.h: the shader's walk, horizons and light (bitmask_glsl.h's
// GlslAccumulator) with soft.h's union of each step's interval (s, w) = (32 x, 32 (y - x)), whose per-sector visible
// share P is carried across slices as the shader carries its mask (P starts at 1 in the first slice, and each later
// slice where the one before it ended):
//     visibility = sum_slices sum_k P_k / 32 / sliceCount,
//     light = sum_steps (1 - newly_m) light_m / sliceCount,   newly_m = sum_k a b g P_mk / 32
// (the shader's light weight 1 - newly / 32). Straight-through: the hard masks' values (GlslAccumulator's), and in
// the backward the soft union's gradients, each slice's P starting at the hard mask carried into it (what
// sector_union's straight-through p0 is). The backward is walk_grad.h's soft_grad_block of this accumulator.
#pragma once

#include "bitmask_glsl.h"
#include "soft.h"

namespace tao {

constexpr int kGlslMaxSlices = 17;  // the backward keeps each slice's start: sliceCount <= 16

// Union: soft.h's SoftAccumulator, for its union (tau, delta, the smooth floor's window, straight_through: cover,
// sweep, reverse_scan) and, in the backward, its State's kept steps
template <class Union> struct GlslSoftAccumulator {
  GlslAccumulator shader;  // slice_count, thickness, rounding, indirect, the driver's numerics
  Union soft;

  template <class F> struct Sums {
    typename GlslAccumulator::template Sums<F> shader;  // (straight-through's hard mask, the visibility, the light)
    LaneArray<F, kSectors> P;  // soft: each sector's visible share where the last slice ended
  };
  template <class F> struct State {
    typename GlslAccumulator::template State<F> shader;
    LaneArray<F, kSectors> P, omega;  // (omega: the light's uniform sector weights, 1 / 32)
  };
  TAO_FN int channels() const { return shader.channels(); }

  // A step's interval in sector units (w < 0: empty, on lanes past the row or on the background too)
  template <class F>
  TAO_FN void interval(const typename GlslAccumulator::template Horizons<F>& hz, const Pixels<F>& px, F& s, F& w) const {
    s = hz.x * F(float(kSectors));
    w = select(px.live, (hz.y - hz.x) * F(float(kSectors)), F(-1.0f));
  }

  // The slice's start: P where the last slice ended (1 in the first), or straight-through's hard mask as shares
  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>& px, const Slice<F>& sl, const Sums<F>& sums) const {
    State<F> st;
    st.shader = shader.begin_slice(px, sl, sums.shader);
    for (int k = 0; k < kSectors; ++k) {
      st.P[k] = soft.straight_through ? F(1.0f) - bit(sums.shader.occ, k) : sl.index == 0 ? F(1.0f) : sums.P[k];
      st.omega[k] = F(1.0f / kSectors);
    }
    return st;
  }

  template <class F>
  TAO_FN void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    if (soft.straight_through) return shader.step(st.shader, side, px, sl, smp);
    const typename GlslAccumulator::template Horizons<F> hz = shader.horizons(st.shader, px, smp);
    F s, w, newly = F(0.0f);
    interval(hz, px, s, w);
    const auto live = w >= F(0.0f);  // (an empty step, or a NaN interval, newly occludes nothing: sector_union's)
    if (any(live))
      newly = select(live, soft.cover(s, w, &st.P[0], static_cast<F*>(nullptr), static_cast<SoftCoverage<F>*>(nullptr),
                                      shader.indirect ? &st.omega[0] : static_cast<const F*>(nullptr)), F(0.0f));
    if (shader.indirect) {
      F sent[3];
      shader.step_light(st.shader, smp, hz.h, sent);
      for (int c = 0; c < 3; ++c) st.shader.light[c] = st.shader.light[c] + (F(1.0f) - newly) * sent[c];
    }
  }

  template <class F> TAO_FN void end_slice(const State<F>& st, const Pixels<F>& px, const Slice<F>& sl, Sums<F>& sums) const {
    if (soft.straight_through) return shader.end_slice(st.shader, px, sl, sums.shader);
    F share = F(0.0f);
    for (int k = 0; k < kSectors; ++k) share = share + st.P[k], sums.P[k] = st.P[k];
    for (int c = 0; c < 3; ++c) sums.shader.light[c] = st.shader.light[c];
    sums.shader.visibility = sums.shader.visibility + share * F(1.0f / kSectors);
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    shader.finish(sums.shader, px, out);
  }
};

// The backward's walk of one slice (walk_slice's accumulator): each step kept in the union's State (its interval,
// unclamped horizons, thickness, fetch) with, with indirect light, its gain -light_weight . its light (the shader
// weighs the light by 1 - newly) and, straight-through, the share its hard sectors newly occlude
template <class B, class Union> struct GlslSoftSteps {
  const GlslSoftAccumulator<Union>& acc;
  const B* light_weight;  // d L / d the light sum, or null without indirect light

  template <class G> struct State {
    typename Union::template State<G> kept;
    typename GlslAccumulator::template State<G> shader;  // (occ: straight-through's hard mask)
  };
  TAO_FN void step(State<B>& st, int, const Pixels<B>& px, const Slice<B>&, const Sample<B>& smp) const {
    auto& kept = st.kept;
    const int m = kept.n++;
    const typename GlslAccumulator::template Horizons<B> hz = acc.shader.horizons(st.shader, px, smp);
    acc.interval(hz, px, kept.s[m], kept.w[m]);
    kept.front[m] = hz.front, kept.back[m] = hz.back, kept.t[m] = hz.t, kept.tv[m] = acc.shader.thickness.value(px, smp);
    for (int c = 0; c < 3; ++c) kept.delta[c][m] = smp.delta[c], kept.pos[c][m] = smp.delta[c] + px.P[c];
    for (int i = 0; i < 4; ++i) kept.index[i][m] = smp.index[i];
    kept.fu[m] = smp.fu, kept.fv[m] = smp.fv, kept.valid[m] = smp.valid;
    if (acc.soft.straight_through) {
      const typename LaneTraits<B>::I bits = acc.shader.covered(hz);
      kept.hard_newly[m] = B(1.0f) - acc.shader.weight(bits & bnot(st.shader.occ));
      st.shader.occ = st.shader.occ | bits;
    }
    if (light_weight) {
      B sent[3];
      acc.shader.step_light(st.shader, smp, hz.h, sent);
      kept.gain[m] = select(px.live, neg(dot3(light_weight, sent)), B(0.0f));
    }
  }
};

// The thickness model and whether light is sent, of either soft accumulator's backward (walk_cuda.cu's entries)
template <bool kGradients, bool kAdjoint, int kMostSteps>
TAO_FN const ThicknessModel& soft_thickness(const SoftAccumulator<kGradients, kAdjoint, kMostSteps>& acc) {
  return acc.thickness;
}
template <class Union> TAO_FN const ThicknessModel& soft_thickness(const GlslSoftAccumulator<Union>& acc) {
  return acc.shader.thickness;
}
template <bool kGradients, bool kAdjoint, int kMostSteps>
TAO_FN bool soft_indirect(const SoftAccumulator<kGradients, kAdjoint, kMostSteps>& acc) { return acc.indirect; }
template <class Union> TAO_FN bool soft_indirect(const GlslSoftAccumulator<Union>& acc) { return acc.shader.indirect; }

}  // namespace tao
