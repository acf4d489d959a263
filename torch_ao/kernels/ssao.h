// The accumulators of torch_ao/methods/ue4_ssao.py (WedgeAccumulator: UE4's WedgeNoNormal of each symmetric
// pair of samples, Steps::wedge), torch_ao/methods/pssao.py (PSSAOAccumulator: the largest sample
// occlusion per direction, Steps::pixels) and torch_ao/methods/ssao.py (HemisphereAccumulator: Crytek's SSAO
// over the normal-oriented hemisphere kernel, Steps::hemisphere), for walk.h. Like horizon.h's, the first two
// finish into per-pixel sums over slices (0 on background) that the modules' own Python finish turns into the
// visibility; the hemisphere's finishes into the visibility. Their backward is walk_grad.h's grad_block, which
// replays every step (seed_setting: UE4's fade distance, flat-surface bias and softness, PSSAO's distance bias,
// SSAO's bias and softness).
#pragma once

#include "walk.h"

namespace tao {

// WedgeAccumulator: per direction the running (x, y) of acc = lerp(acc, (max(acc.x, x), 1), Weight)
struct WedgeAccumulator {
  static constexpr bool kPairedSides = true;  // step_pair: both sides of step j together (walk_pairs)
  static constexpr bool kScreenOnly = true;   // (walked_slice: the slice's projected normal is not read)
  float fade_distance;      // D of the halo weight, clamped to 1e-30 (world units)
  float flat_surface_bias;  // world units
  float flat_softness;      // > 0: the logistic blend of the flat-surface test
  bool accurate_angle;      // acos(cos) / pi instead of UE4's (1 - cos) 0.45

  template <class F> struct State { F x, y; };
  template <class F> struct Sums { F num = F(0.0f), den = F(0.0f); };
  TAO_FN int channels() const { return 2; }
  TAO_FN int settings() const { return 3; }  // fade_distance, flat_surface_bias, flat_softness (seed_setting)

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>&) const {
    return State<F>{F(0.0f), F(0.0f)};
  }

  template <class F>
  TAO_FN void step_pair(State<F>& st, const Pixels<F>& px, const Slice<F>&, const Sample<F>& plus,
                        const Sample<F>& minus) const {
    const F* dl = plus.delta;
    const F* dr = minus.delta;
    const F denom = sqrt(clamp_min(dot3(dl, dl) * dot3(dr, dr), F(1e-30f)));
    const F cos_lr = clamp(dot3(dl, dr) / denom, F(-1.0f), F(1.0f));
    F norm_angle = accurate_angle ? acos(clamp(cos_lr, F(float(-1 + 1e-7)), F(float(1 - 1e-7)))) / F(kPi)
                                  : clamp((F(1.0f) - cos_lr) * F(0.45f), F(0.0f), F(1.0f));
    // zc - zL, zc - zR: the samples' depths -(P + delta).z (an invalid sample's delta is -V, as the tensor
    // path's position P - V)
    const F left = px.depth + (px.P[2] + dl[2]), right = px.depth + (px.P[2] + dr[2]);
    const F bias = seed_setting(F(flat_surface_bias), 1), one = F(1.0f);
    if (flat_softness > 0) {
      const F flat = logistic((bias - (left + right)) / seed_setting(F(flat_softness), 2));
      norm_angle = norm_angle + flat * (one - norm_angle);
    } else {
      norm_angle = select(left + right < bias, one, norm_angle);
    }
    const F D = seed_setting(F(fade_distance));
    F weight = clamp(one - left / D, F(0.0f), one) * clamp(one - right / D, F(0.0f), one);
    weight = select(land(plus.valid, minus.valid), weight, F(0.0f));
    const F x = (one - norm_angle) / (weight + F(0.001f));
    st.x = st.x + weight * (max(st.x, x) - st.x);
    st.y = st.y + weight * (one - st.y);
  }

  template <class F> TAO_FN void end_slice(const State<F>& st, const Pixels<F>&, const Slice<F>&, Sums<F>& sums) const {
    const F occluded = F(1.0f) - st.x;
    sums.num = sums.num + (occluded * occluded) * st.y;
    sums.den = sums.den + st.y;
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    out[0] = select(px.live, sums.num, F(0.0f));
    out[1] = select(px.live, sums.den, F(0.0f));
  }
};

// PSSAOAccumulator: per direction the largest occlusion a / (1 + a), a = max(n . d, 0) / (bias + |d|), of its
// samples in the image, and how many there are (the gist's toInclude)
struct PSSAOAccumulator {
  float distance_bias;  // world units: the gist's 1.0 in a /= 1.0 + distance

  template <class F> struct State { F best, count; };
  template <class F> struct Sums { F sum = F(0.0f), count = F(0.0f), dirs = F(0.0f); };
  TAO_FN int channels() const { return 3; }
  TAO_FN int settings() const { return 1; }  // distance_bias (seed_setting)
  // a step that raises the maximum replaces it (walk_grad.h's takes): only the slice's highest sample carries a
  // gradient; the count of samples inside the image changes at every step but has none, so the takes follow
  // best alone (kTakeComponents: the state's first)
  TAO_FN bool replaces() const { return true; }
  TAO_FN bool blends_every_sample() const { return false; }
  // a slice without a take had no sample in the image (the first one always raises the maximum): it adds 0
  TAO_FN bool untaken_slice_constant() const { return true; }
  static constexpr int kTakeComponents = 1;
  static constexpr bool kScreenOnly = true;  // (walked_slice: the slice's projected normal is not read)

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>&) const {
    return State<F>{F(-100000.0f), F(0.0f)};
  }

  template <class F>
  TAO_FN void step(State<F>& st, int, const Pixels<F>& px, const Slice<F>&, const Sample<F>& smp) const {
    const auto inside = smp.inside();
    F a = clamp_min(dot3(px.N, smp.delta), F(0.0f));
    a = a / (seed_setting(F(distance_bias)) + norm3(smp.delta));
    const F occ = select(smp.valid, a / (F(1.0f) + a), F(0.0f));
    st.best = select(inside, max(st.best, occ), st.best);
    st.count = st.count + select(inside, F(1.0f), F(0.0f));
  }

  template <class F> TAO_FN void end_slice(const State<F>& st, const Pixels<F>&, const Slice<F>&, Sums<F>& sums) const {
    const auto has = st.count > F(0.0f);
    sums.sum = sums.sum + select(has, st.best, F(0.0f));
    sums.count = sums.count + st.count;
    sums.dirs = sums.dirs + select(has, F(1.0f), F(0.0f));
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    out[0] = select(px.live, sums.sum, F(0.0f));
    out[1] = select(px.live, sums.count, F(0.0f));
    out[2] = select(px.live, sums.dirs, F(0.0f));
  }
};

// HemisphereAccumulator: kernel_occlusion's visibility 1 - (1/K) sum_k occluded_k rangeCheck_k over the K kernel
// points S_k (walk_points; a single slice)
struct HemisphereAccumulator {
  static constexpr bool kKernelPoints = true;
  float radius;    // world units (the walk's)
  float bias;      // world units: S is occluded when the surface is this much in front of it
  float softness;  // > 0: the logistic of this width instead of the step
  int64_t samples;

  template <class F> struct State { F occlusion; };
  template <class F> struct Sums { F occlusion = F(0.0f); };
  TAO_FN int channels() const { return 1; }
  TAO_FN int settings() const { return 2; }  // bias, softness (seed_setting)

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>&) const { return State<F>{F(0.0f)}; }

  template <class F>
  TAO_FN void step_point(State<F>& st, const Pixels<F>& px, const F* S, const Sample<F>& smp) const {
    using V = typename ValueOf<F>::type;
    const F z_point = neg(S[2]), z_buffer = neg(px.P[2] + smp.delta[2]), one = F(1.0f);
    const F diff = z_point - z_buffer - seed_setting(F(bias), 0);
    const F occluded = softness > 0 ? logistic(diff / seed_setting(F(softness), 1))
                                    : select(diff >= F(0.0f), one, F(0.0f));
    const F x = clamp(F(radius) / clamp_min(abs(px.depth - z_buffer), F(1e-12f * radius)), F(0.0f), one);
    const F range_check = x * x * (F(3.0f) - F(2.0f) * x);
    // (a point behind the camera: its projection's depth was clamped)
    const auto counts = land(smp.valid, value(z_point) > value(px.depth) * V(1e-6f));
    st.occlusion = st.occlusion + select(counts, occluded * range_check, F(0.0f));
  }

  template <class F> TAO_FN void end_slice(const State<F>& st, const Pixels<F>&, const Slice<F>&, Sums<F>& sums) const {
    sums.occlusion = sums.occlusion + st.occlusion;
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    out[0] = select(px.live, F(1.0f) - sums.occlusion / F(float(samples)), F(1.0f));
  }
};

}  // namespace tao
