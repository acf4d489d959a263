// The backwards of the one walk, written against the lane type as walk.h is: the CPU operators
// (walk_grad_cpu.cpp, SIMD and scalar lanes, rows over torch's threads) and the CUDA kernels (walk_cuda.cu, one
// pixel a thread) run them. The soft / straight-through bitmask walk's (soft_grad_block) is soft.h's
// SoftAdjoint over the walk: value lanes with the pixel and its slices in dual lanes (tangents 0..6), each
// step's d / d delta scattered to its taps by scatter_taps (TapSink). The exact union's (exact_grad_block) and the
// hard sector walk's (hard_record_block, hard_grad_block) are described where they are defined. The horizon
// accumulators' (horizon.h: GTAO's three variants, HBAO; ssao.h's PSSAO; any fetch, either border), per slice:
//  1. the forward (record_block: walk.h's walk_slice in plain lanes with the Takes visitor) records, per pixel
//     and side, the steps that changed the accumulator's state (its "takes", a bit per step; every valid step
//     where acc.blends_every_sample(): UE4's thickness blend): a step that leaves the state as it was is the
//     identity, so only the takes carry gradients. Where a take replaces the state (acc.replaces(): GTAO's
//     exact minimum, HBAO's highest rise, PSSAO's maximum), only each side's last take is kept.
//  2. the backward (grad_block) replays the slice in reverse lanes (lanes_rev.h: the walk records its
//     arithmetic on a tape) through those takes alone (each lane its own step, step_screen in lanes):
//     begin_slice, the takes' samples (fetch_sample: each fetched position a node) and steps, end_slice and
//     finish. The pixel's own position, normal and depth are leaves (seed_pixel), recorded once per block
//     before its slices; the accumulator's settings (seed_setting: GTAO's falloff or thickness, HBAO's angle
//     bias) and, where asked, the intrinsics (seed_camera) a leaf each per slice. Where a slice without takes
//     adds a constant to the outputs (acc.untaken_slice_constant(): HBAO, PSSAO), a slice no lane of the block
//     took a step in is not replayed, and a block with no take at all not even its pixel; the CPU's SIMD lanes
//     may gather a row's pixels that took steps in a slice into full blocks (grad_lanes, walk_grad_cpu.cpp).
//  3. the upstream gradients seeded on the slice's outputs and swept back over the slice's nodes give d loss /
//     d each take's fetched position, chained to its taps: for a bilinear fetch pos = q / (sum_k w_k t_k), so
//     d pos / d t_k = pos pos_z w_k; a nearest fetch reads the tap's position itself. The edge-aware fetch is
//     the bilinear one whose taps across a depth edge are four copies of the nearest: their weights sum to 1
//     on that texel, and the interpolation's d / d (fu, fv) is 0 (the cell flags, like every comparison, have
//     no derivative). Scattered with scatter_add: into each CPU thread's own images, atomically into one
//     image on CUDA. The slice's nodes are then dropped; after the last slice the pixel's nodes are swept,
//     which gives its own gradients.
// Ties: a step whose candidate equals the state leaves it unchanged, so the earlier sample keeps the gradient
// (the tensor path's torch.minimum splits it between them; tied samples of one texel give both the same total).
#pragma once

#include "lanes_dual.h"
#include "lanes_rev.h"
#include "packed.h"

namespace tao {

// walk.h's density_azimuth in dual lanes of its three inputs (the normal's components n . V, n . e1, n . e2; u is a
// constant), for the backwards to chain to theirs: its 32 bins' atan2s carried in 3 tangents
template <class F>
TAO_FN Dual<F, 3> density_azimuth_in_three(const F& nv, const F& n1, const F& n2, const F& u, Dual<F, 3>& weight) {
  using D = Dual<F, 3>;
  D in[3] = {D(nv), D(n1), D(n2)};
  for (int k = 0; k < 3; ++k) in[k].d[k] = F(1.0f);
  return density_azimuth<D>(in[0], in[1], in[2], D(u), weight);
}
// in reverse lanes: recorded as the azimuth's and the weight's nodes of three parents alone, instead of its 64 bins'
// few hundred
template <class F>
TAO_FN Rev<F> density_azimuth(const Rev<F>& nv, const Rev<F>& n1, const Rev<F>& n2, const Rev<F>& u, Rev<F>& weight) {
  Dual<F, 3> w;
  const Dual<F, 3> psi = density_azimuth_in_three(nv.v, n1.v, n2.v, u.v, w);
  weight = Rev<F>::link(w.v, nv, w.d[0], n1, w.d[1], n2, w.d[2]);
  return Rev<F>::link(psi.v, nv, psi.d[0], n1, psi.d[1], n2, psi.d[2]);
}
// in dual lanes of N tangents: chained from the 3 to their N
template <class F, int N>
TAO_FN Dual<F, N> density_azimuth(const Dual<F, N>& nv, const Dual<F, N>& n1, const Dual<F, N>& n2, const Dual<F, N>& u,
                                  Dual<F, N>& weight) {
  Dual<F, 3> w;
  const Dual<F, 3> psi = density_azimuth_in_three(nv.v, n1.v, n2.v, u.v, w);
  const auto chained = [&](const Dual<F, 3>& x) {
    Dual<F, N> r(x.v);
    for (int k = 0; k < N; ++k) r.d[k] = x.d[0] * nv.d[k] + x.d[1] * n1.d[k] + x.d[2] * n2.d[k];
    return r;
  };
  weight = chained(w);
  return chained(psi);
}

// tangents of the pixel's own P (3), N (3), depth (1) (seed_pixel) and of the accumulator's setting
// (seed_setting: the horizon accumulators')
constexpr int kPixel = 7;
// the most steps per side of a CUDA thread's backward (its record and replay are fixed arrays)
#ifndef TAO_GRAD_MAX_STEPS
#define TAO_GRAD_MAX_STEPS 32
#endif
constexpr int kGradMaxSteps = TAO_GRAD_MAX_STEPS;

// An accumulator's state as its S components (its State is an aggregate of lane values)
template <class Acc, class F> TAO_FN constexpr int state_size() {
  static_assert(sizeof(typename Acc::template State<F>) % sizeof(F) == 0, "State: lane values only");
  return int(sizeof(typename Acc::template State<F>) / sizeof(F));
}
template <class State, class F> TAO_FN F* components(State& s) { return reinterpret_cast<F*>(&s); }
// How many of the state's first components decide whether a step took (changed it): Acc::kTakeComponents where
// the rest change only with them (HBAO's sum and weight, with its horizon) or carry no derivative (PSSAO's
// count), else all
template <class Acc, class F, class = void> struct TakeComponents {
  static constexpr int value = state_size<Acc, F>();
};
template <class Acc, class F> struct TakeComponents<Acc, F, decltype(void(Acc::kTakeComponents))> {
  static constexpr int value = Acc::kTakeComponents;
};
// Whether the state is one component per side, which a step of that side alone changes (Acc::kStatePerSide: GTAO's
// horizons), so that a take compares that one
template <class Acc, class = void> struct StatePerSide {
  static constexpr bool value = false;
};
template <class Acc> struct StatePerSide<Acc, decltype(void(Acc::kStatePerSide))> {
  static constexpr bool value = Acc::kStatePerSide;
};

// Where the gradients go: the pixel's own (written once per pixel) and the taps' (scatter_add)
struct Targets {
  float *positions, *normals, *depth, *setting;  // own: (H, W, 3), (H, W, 3), (H, W), (H, W) of image b
  float *tap_positions, *tap_inverse;  // scattered: (H, W, 3), (H, W) of image b
  float* tap_layer = nullptr;          // scattered: the thickness layer's (H, W) of image b, where it is read
  float *tap_normals = nullptr, *tap_light = nullptr;  // scattered: (H, W, 3) of image b (a sender's normal, light)
  float* camera = nullptr;  // own: (H, W, 4) of image b, d L / d fx, fy, cx, cy (where asked for)
  int settings = 1;         // the setting's values per pixel: (H, W, settings) where more than one
  // a position buffer (H, W, 3) of image b the bilinear fetch read between taps (Sample::position_taps; the CPU's),
  // whose taps' positions its gradient goes to (tap_positions), and whether the fetch is edge-aware; else null
  const float* read_positions = nullptr;
  bool read_edge_aware = false;
};

// The bilinear weights of fu = u, fv = v at the four taps (u0 v0, u1 v0, u0 v1, u1 v1)
TAO_FN void bilinear_weights(float u, float v, float* weight) {
  weight[0] = (1.0f - u) * (1.0f - v), weight[1] = u * (1.0f - v), weight[2] = (1.0f - u) * v, weight[3] = u * v;
}

// The adjoint of Sample.gather: g (channels lanes: d L / d the value gathered) into image (H, W, channels) at
// the sample's taps (bilinear: weighted as fu, fv weight them; else index[0]), on the lanes in `on` of the first n
template <class B>
TAO_FN void scatter_gather(bool bilinear, int n, float* image, int channels, const B* g, const B& fu, const B& fv,
                           const typename LaneTraits<B>::I* index, const typename LaneTraits<B>::M& on) {
  if (!any(on)) return;
  constexpr int L = LaneTraits<B>::L;
  float gl[3][L], ful[L], fvl[L];
  int32_t il[4][L];
  for (int c = 0; c < channels; ++c) to_lanes(g[c], gl[c]);
  to_lanes(fu, ful), to_lanes(fv, fvl);
  for (int i = 0; i < 4; ++i) store_lanes(index[i], il[i]);
  for (uint32_t lanes = lane_bits(on) & low_bits(uint32_t(n)); lanes; lanes &= lanes - 1) {
    const int l = lowest_bit(lanes);  // (the lanes on, in order: no branch a lane, which their data mispredicted)
    float weight[4];
    bilinear_weights(ful[l], fvl[l], weight);
    for (int c = 0; c < channels; ++c) {
      if (bilinear) {
        for (int i = 0; i < 4; ++i) scatter_add(image + channels * il[i][l] + c, gl[c][l] * weight[i]);
      } else {
        scatter_add(image + channels * il[0][l] + c, gl[c][l]);
      }
    }
  }
}

// A pixel's record of its takes: bit (2 s + k) steps + j set where step j of slice s, side k (0: +1, 1: -1) took,
// in take_words(cfg) words
TAO_FN int64_t take_words(const WalkSettings& cfg) { return (cfg.slices * 2 * cfg.steps + 63) / 64; }
// The bits [lo, hi) of words, each word's share masked, to fn(word index, bits) (an empty share skipped)
template <class Fn> TAO_FN void for_each_word(const uint64_t* words, int64_t lo, int64_t hi, const Fn& fn) {
  for (int64_t w = lo / 64; 64 * w < hi; ++w) {
    uint64_t x = words[w];
    if (64 * w < lo) x &= ~uint64_t(0) << (lo - 64 * w);
    if (hi < 64 * w + 64) x &= (uint64_t(1) << (hi - 64 * w)) - 1;
    if (x) fn(w, x);
  }
}
// Whether pixel p of a record took a step in slice `only` (-1: in any slice)
TAO_FN bool took_steps(const WalkSettings& cfg, const int64_t* record, int64_t p, int64_t only = -1) {
  const int64_t per_slice = 2 * cfg.steps, words = take_words(cfg);
  const uint64_t* x = reinterpret_cast<const uint64_t*>(record) + p * words;
  if (words == 1) {  // (slices 2 steps <= 64: every slice's bits in one word)
    if (only < 0 || per_slice == 64) return x[0] != 0;
    return (x[0] >> (only * per_slice)) & ((uint64_t(1) << per_slice) - 1);
  }
  const int64_t lo = only < 0 ? 0 : only * per_slice, hi = only < 0 ? cfg.slices * per_slice : lo + per_slice;
  bool any = false;
  for_each_word(x, lo, hi, [&](int64_t, uint64_t) { any = true; });
  return any;
}

// The pixels' own gradients of the lanes' n pixels (own: d L / d P (3), N (3), depth) added into t (zeros, or a
// gathered block's earlier slices'), and with setting its per-pixel d L / d the accumulator's t.settings settings,
// with camera d L / d the intrinsics
template <class B>
TAO_FN void write_own(const Targets& t, int64_t W, const RowLanes& lanes, const B* own, const B* setting = nullptr,
                      const B* camera = nullptr) {
  constexpr int L = LaneTraits<B>::L;
  constexpr int kMost = Tape<B>::kSettings;
  float ol[kPixel + kMost + 4][L];
  for (int k = 0; k < kPixel; ++k) to_lanes(own[k], ol[k]);
  if (setting)
    for (int k = 0; k < t.settings; ++k) to_lanes(setting[k], ol[kPixel + k]);
  if (camera)
    for (int k = 0; k < 4; ++k) to_lanes(camera[k], ol[kPixel + kMost + k]);
  for (int l = 0; l < lanes.n; ++l) {
    const int64_t p = lanes.pixel(W, l);
    for (int c = 0; c < 3; ++c) t.positions[3 * p + c] += ol[c][l], t.normals[3 * p + c] += ol[3 + c][l];
    t.depth[p] += ol[6][l];
    if (setting)
      for (int k = 0; k < t.settings; ++k) t.setting[t.settings * p + k] += ol[kPixel + k][l];
    if (camera)
      for (int k = 0; k < 4; ++k) t.camera[4 * p + k] += ol[kPixel + kMost + k][l];
  }
}
// (the n <= L pixels of a row from u0)
template <class B>
TAO_FN void write_own(const Targets& t, int64_t W, int64_t row, int64_t u0, int n, const B* own,
                      const B* setting = nullptr, const B* camera = nullptr) {
  write_own(t, W, RowLanes{row, u0, n}, own, setting, camera);
}

// The record of a slice (the forward's visitor): per side and lane the steps that changed the state (the
// last one alone where a take replaces the state), as the bits of the lane's pixel's record (take_words)
template <class B, class Acc> struct Takes {
  static constexpr bool kBefore = true;
  using State = typename Acc::template State<B>;
  static constexpr int S = TakeComponents<Acc, B>::value;
  using I = typename LaneTraits<B>::I;
  const Acc& acc;
  const typename LaneTraits<B>::M& live;
  int64_t words, steps, slice;
  uint64_t* record;  // the lanes' pixels' words, zeroed before the first slice (past n: not live, never marked)
  I last[2] = {I(-1), I(-1)};  // (where a take replaces the state: per side the last take's step, -1: none)
  // (where a slice's bits fit one word, 2 steps <= 64: per lane bit k steps + j, kept here until end_slice, so
  // that a CUDA thread sets them in a register, not in memory at every take)
  uint64_t pending[LaneTraits<B>::L] = {};

  TAO_FN Takes(const Acc& a, const typename LaneTraits<B>::M& l, const WalkSettings& cfg, int64_t s, uint64_t* r)
      : acc(a), live(l), words(take_words(cfg)), steps(cfg.steps), slice(s), record(r) {}
  TAO_FN void mark(int k, int l, int64_t j) {  // (step j of side k taken by lane l)
    if (2 * steps <= 64) {
      pending[l] |= uint64_t(1) << (k * steps + j);
      return;
    }
    const int64_t bit = (2 * slice + k) * steps + j;
    record[l * words + bit / 64] |= uint64_t(1) << (bit % 64);
  }

  TAO_FN void operator()(int side, int64_t j, const Sample<B>& sample, const State& before, const State& after) {
    auto changed = acc.blends_every_sample() ? sample.valid : B(0.0f) > B(1.0f);
    const B *x = components<const State, const B>(before), *y = components<const State, const B>(after);
    const int k = side > 0 ? 0 : 1;
    if constexpr (StatePerSide<Acc>::value) {
      changed = lor(changed, lnot(x[k] == y[k]));  // (NaN: changed)
    } else {
      for (int m = 0; m < S; ++m) changed = lor(changed, lnot(x[m] == y[m]));
    }
    if (acc.replaces()) {  // (the last change alone counts: kept in lanes, its bit set by end_slice on live lanes)
      last[k] = select(changed, I(int32_t(j)), last[k]);
      return;
    }
    for (uint32_t lanes = lane_bits(land(changed, live)); lanes; lanes &= lanes - 1) mark(k, lowest_bit(lanes), j);
  }
  // the slice walked: where a take replaces the state, each side's last take's bit; the slice's bits kept in
  // pending into the record (bit 2 slice steps on, across two words where it crosses one)
  TAO_FN void end_slice() {
    if (acc.replaces()) {
      const uint32_t on = lane_bits(live);
      for (int k = 0; k < 2; ++k) {
        int32_t step[LaneTraits<B>::L];
        store_lanes(last[k], step);
        for (int l = 0; l < LaneTraits<B>::L; ++l) {
          const uint32_t took = uint32_t(step[l] >= 0) & (on >> l) & 1u;
          if (2 * steps <= 64) {  // (a 0 bit where the lane took none: no branch on its data, which mispredicted)
            pending[l] |= uint64_t(took) << ((k * steps + step[l]) & 63);
          } else if (took) {
            mark(k, l, step[l]);
          }
        }
      }
    }
    if (2 * steps > 64) return;
    const int64_t first = 2 * slice * steps, w = first / 64, shift = first % 64;
    for (int l = 0; l < LaneTraits<B>::L; ++l) {
      if (pending[l] == 0) continue;
      record[l * words + w] |= pending[l] << shift;
      if (shift + 2 * steps > 64) record[l * words + w + 1] |= pending[l] >> (64 - shift);
    }
  }
};

// The forward of the n <= L pixels of a row from u0 with the Takes visitor: the outputs' lanes in values, and
// the pixels' records (take_words each) at record
template <class B, class Acc>
TAO_FN void record_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row, int64_t u0, int n,
                         uint64_t* record, B* values) {
  const Pixels<B> px(cfg, img, row, u0, n);
  for (int64_t i = 0; i < n * take_words(cfg); ++i) record[i] = 0;
  typename Acc::template Sums<B> sums;
  if (any(px.live)) {
    for (int64_t s = 0; s < cfg.slices; ++s) {
      Takes<B, Acc> takes(acc, px.live, cfg, s, record);
      const Slice<B> sl = walked_slice<Acc>(cfg, img, px, s);
      typename Acc::template State<B> state = acc.begin_slice(px, sl);
      walk_slice(cfg, img, acc, px, sl, state, takes);
      takes.end_slice();
      acc.end_slice(state, px, sl, sums);
    }
  }
  acc.finish(sums, px, values);
}

#if !TAO_LEAN_WALK
// Sample::position_taps' adjoint: d L / d the position read (g) into its four taps' positions (t.tap_positions), on
// the lanes `on` of the first n. With W_k = w_k / depth_k (w_k the weights of fu, fv; 1 / depth_k = -1 / z_k) and
// pos = sum W_k p_k / sum W_k: d pos / d p_k = W_k / sum W_k, and through the tap's depth d pos / d z_k adds
// w_k (p_k - pos) / (z_k^2 sum W_k). The edge-aware fetch's one texel is its depth unprojected: d pos / d z = pos / z.
template <class B>
TAO_FN void scatter_position_taps(int n, const Targets& t, const B* g, const B* pos, const B& fu, const B& fv,
                                  const typename LaneTraits<B>::I* index, const typename LaneTraits<B>::M& on) {
  if (!any(on)) return;
  constexpr int L = LaneTraits<B>::L;
  float gl[3][L], pl[3][L], ful[L], fvl[L];
  int32_t il[4][L];
  for (int c = 0; c < 3; ++c) to_lanes(g[c], gl[c]), to_lanes(pos[c], pl[c]);
  to_lanes(fu, ful), to_lanes(fv, fvl);
  for (int i = 0; i < 4; ++i) store_lanes(index[i], il[i]);
  for (uint32_t lanes = lane_bits(on) & low_bits(uint32_t(n)); lanes; lanes &= lanes - 1) {
    const int l = lowest_bit(lanes);  // (the lanes on, in order)
    const float* tap[4];
    for (int k = 0; k < 4; ++k) tap[k] = t.read_positions + 3 * il[k][l];
    const float gp[3] = {gl[0][l], gl[1][l], gl[2][l]}, p[3] = {pl[0][l], pl[1][l], pl[2][l]};
    if (t.read_edge_aware && il[1][l] == il[0][l] && il[2][l] == il[0][l] && il[3][l] == il[0][l]) {
      scatter_add(t.tap_positions + 3 * il[0][l] + 2, (gp[0] * p[0] + gp[1] * p[1] + gp[2] * p[2]) / tap[0][2]);
      continue;
    }
    float weight[4], inverse[4], total = 0.0f;
    bilinear_weights(ful[l], fvl[l], weight);
    for (int k = 0; k < 4; ++k) inverse[k] = -1.0f / tap[k][2], total += weight[k] * inverse[k];
    for (int k = 0; k < 4; ++k) {
      const float share = weight[k] * inverse[k] / total;
      const float along = gp[0] * (tap[k][0] - p[0]) + gp[1] * (tap[k][1] - p[1]) + gp[2] * (tap[k][2] - p[2]);
      for (int c = 0; c < 2; ++c) scatter_add(t.tap_positions + 3 * il[k][l] + c, share * gp[c]);
      scatter_add(t.tap_positions + 3 * il[k][l] + 2, share * gp[2] + share * inverse[k] * along);
    }
  }
}
#endif

// d L / d delta of a sample (g_delta) scattered to its fetch's taps, on the lanes in `on` of the first n: a
// bilinear fetch's four inverse depths (d pos / d t_k = pos pos_z w_k, pos the fetched position, w_k the
// weights of fu, fv), or where it read a position buffer (t.read_positions) its four taps' positions
// (scatter_position_taps), a nearest fetch's position (index[0]); with g_layer, d L / d the thickness layer's value
// at the sample to the layer's taps (layer_bilinear: its four, weighted w_k, as Sample.gather reads it; else
// index[0]: a nearest fetch's or a first tap's read)
template <class B>
TAO_FN void scatter_taps(bool bilinear, int n, const Targets& t, const B* g_delta, const B* pos, const B& fu,
                         const B& fv, const typename LaneTraits<B>::I* index, const typename LaneTraits<B>::M& on,
                         const B* g_layer = nullptr, bool layer_bilinear = false) {
  if (bilinear && t.read_positions) {
#if !TAO_LEAN_WALK
    scatter_position_taps(n, t, g_delta, pos, fu, fv, index, on);
#endif
  } else if (bilinear) {  // the interpolated inverse depth's d L / d t = (d L / d pos . pos) pos_z
    const B along = dot3(g_delta, pos) * pos[2];
    scatter_gather(true, n, t.tap_inverse, 1, &along, fu, fv, index, on);
  } else {
    scatter_gather(false, n, t.tap_positions, 3, g_delta, fu, fv, index, on);
  }
  if (g_layer) scatter_gather(layer_bilinear, n, t.tap_layer, 1, g_layer, fu, fv, index, on);
}

// A slice's record read back (the forward's Takes, image b's from record): per side, the lanes' takes in
// order as each lane's step j, at(k, q)[l], count[k][l] of them; step: 2 steps L floats of scratch
template <int L> struct Replay {
  float* step;  // [side][take][lane]
  int64_t steps;
  int count[2][L];

  TAO_FN Replay(float* scratch, int64_t n_steps) : step(scratch), steps(n_steps) {}
  TAO_FN float* at(int k, int q) { return step + (k * steps + q) * L; }
  TAO_FN int most(int k) const {
    int m = count[k][0];
    for (int l = 1; l < L; ++l) m = count[k][l] > m ? count[k][l] : m;
    return m;
  }
  // the record of slice s of the lanes' pixels in image W wide (words per pixel)
  TAO_FN void read(const int64_t* record, const RowLanes& lanes, int64_t W, int64_t s, int64_t words) {
    const uint64_t mask = steps < 64 ? (uint64_t(1) << steps) - 1 : ~uint64_t(0);
    for (int l = 0; l < L; ++l) {
      count[0][l] = count[1][l] = 0;
      if (l >= lanes.n) continue;
      const uint64_t* x = reinterpret_cast<const uint64_t*>(record) + lanes.pixel(W, l) * words;
      for (int k = 0; k < 2; ++k) {
        const int64_t lo = (2 * s + k) * steps;
        int q = 0;
        if (words == 1) {  // (every slice's bits in one word: lo < 64)
          // the first take without a branch on whether there is one (a take that replaces the state leaves at most
          // one a side, and a loop over the bits mispredicted its end); a lane without takes writes an unread 63
          uint64_t b = (x[0] >> lo) & mask;
          q = popcount(b);
          at(k, 0)[l] = float(lowest_bit(b | (uint64_t(1) << 63)));
          int i = 1;
          for (b &= b - 1; b; b &= b - 1) at(k, i++)[l] = float(lowest_bit(b));
        } else {
          for_each_word(x, lo, lo + steps, [&](int64_t w, uint64_t b) {
            for (; b; b &= b - 1) at(k, q++)[l] = float(64 * w + lowest_bit(b) - lo);
          });
        }
        count[k][l] = q;
      }
    }
  }
};

// A backward's replayed fetch at screen (su, sv): fetched in plain lanes, with its position's d / d su and d / d sv
// (soft.h's fetch_motion: a bilinear fetch's; a nearest one's texel does not move). The dual and the reverse
// lanes' replayed samples (replayed_sample, fetch_sample) are made of it.
template <class B> struct MovingFetch {
  Sample<B> plain;
  B d_su[3], d_sv[3];

  TAO_FN MovingFetch(const WalkSettings& cfg, const Image& img, const Pixels<B>& px, const B& su, const B& sv)
      : plain(cfg, img, px, su, sv) {
    for (int c = 0; c < 3; ++c) d_su[c] = B(0.0f), d_sv[c] = B(0.0f);
    if (cfg.bilinear) fetch_motion(plain, px.P, su, sv, d_su, d_sv);
  }
};

// A replayed sample in dual lanes D whose first kPixel tangents are the pixel's own (those of px_own and sl_own,
// Dual<B, kPixel>; the rest zero), dist (own tangents) pixels along the slice's side: fetched in plain lanes (px: the
// pixel's values), its offset's own tangents chained through where it samples (soft.h's fetch_motion: a bilinear
// fetch's d position / d su, d sv; a nearest one's texel does not move) and the pixel's own position, and fu, fv
// carrying su, sv's (a layer read at the taps moves with them). The same sample as Sample<Dual>'s, at a fraction
// of its dual arithmetic.
// d_su, d_sv (optional): the fetched position's d / d su, d sv.
template <class D, class B, class Own>
TAO_FN Sample<D> replayed_sample(const WalkSettings& cfg, const Image& img, const Pixels<B>& px,
                                 const Pixels<Own>& px_own, const Slice<Own>& sl_own, float side, const Own& dist,
                                 B* d_su_out = nullptr, B* d_sv_out = nullptr) {
  const Own su = along_u(px_own, sl_own, side, dist), sv = along_v(px_own, sl_own, side, dist);
  const MovingFetch<B> fetch(cfg, img, px, su.v, sv.v);
  Sample<D> smp(fetch.plain, [](const B& x) { return D(x); });
  for (int k = 0; k < kPixel; ++k) {
    for (int c = 0; c < 3; ++c)
      smp.delta[c].d[k] = fetch.d_su[c] * su.d[k] + fetch.d_sv[c] * sv.d[k] - px_own.P[c].d[k];
    if (cfg.bilinear) smp.fu.d[k] = su.d[k], smp.fv.d[k] = sv.d[k];
  }
  for (int c = 0; c < 3; ++c) {
    if (d_su_out) d_su_out[c] = fetch.d_su[c];
    if (d_sv_out) d_sv_out[c] = fetch.d_sv[c];
  }
  return smp;
}

// A replayed fetch: its position's nodes on the tape, and where its taps are
template <class B> struct TapedTake {
  int32_t ids[3];
  typename LaneTraits<B>::I index[4];
  B fu, fv, pos[3];
  typename LaneTraits<B>::M has;
};

// A replay's fetches (Tape::fetches): the pixels' values they read and, in order, what each fetched (at most
// capacity: one more overwrites the last and overflows the tape)
template <class B> struct TapedFetches {
  const Pixels<B>* px;
  TapedTake<B>* taken;
  int32_t capacity;
  int n;
};

// walk.h's fetch_sample in reverse lanes (R = Rev<B>), the replay's: fetched in plain lanes, the fetched
// position a node per component, moving as the fetch moves with the screen position (soft.h's fetch_motion: a
// bilinear fetch's d position / d su, d sv, and its unprojection's d / d the intrinsics where the tape asks; a
// nearest one's texel does not move: a leaf, its position the buffer's), less the pixel's own position (an
// invalid sample's delta is -V, as Sample's); fu, fv carry su, sv's derivatives (a layer read at the taps moves
// with them). The same sample as Sample<R>'s, the fetch's arithmetic kept off the tape; the position's nodes (their
// adjoints: d L / d the position read) and taps appended to the tape's fetches.
template <class B>
TAO_FN Sample<Rev<B>> fetch_sample(const WalkSettings& cfg, const Image& img, const Pixels<Rev<B>>& pr,
                                   const Rev<B>& su, const Rev<B>& sv) {
  using R = Rev<B>;
  Tape<B>* tape = current_tape<B>();
  TapedFetches<B>& fetches = *static_cast<TapedFetches<B>*>(tape->fetches);
  if (fetches.n == fetches.capacity) tape->overflow = true, --fetches.n;  // (the block's gradients unwritten)
  TapedTake<B>& take = fetches.taken[fetches.n++];
  const MovingFetch<B> fetch(cfg, img, *fetches.px, su.v, sv.v);
  const Sample<B>& plain = fetch.plain;
  const B* d_su = fetch.d_su;
  const B* d_sv = fetch.d_sv;
  Sample<R> smp(plain, [](const B& x) { return R(x); });
  if (cfg.bilinear) smp.fu = R::link(plain.fu, su, B(1.0f)), smp.fv = R::link(plain.fv, sv, B(1.0f));
  for (int c = 0; c < 3; ++c) take.pos[c] = plain.delta[c] + fetches.px->P[c];
  const B one(1.0f), zero(0.0f);
  const B in = select(plain.valid, one, zero), out = select(plain.valid, zero, neg(one));
  for (int c = 0; c < 3; ++c) {
    // the fetched position: a node of the screen position (its first node: the take's, whose adjoint is
    // d L / d the position read), or where it does not move (a nearest fetch, or a screen position made of
    // constants) a leaf
    R moved = cfg.bilinear ? R::link(take.pos[c], su, d_su[c], sv, d_sv[c]) : R(take.pos[c]);
    if (moved.id < 0) moved = R(take.pos[c], tape->leaf(), tape);
    take.ids[c] = moved.id;
    if (cfg.bilinear && c < 2 && tape->camera) {  // the unprojection's intrinsics (where it is one)
      B d_focal, d_centre;
      unprojection_partials(img, take.pos, c, d_focal, d_centre);
      const auto unprojected = unprojected_lanes<B>(cfg, plain.index);
      d_focal = select(unprojected, d_focal, zero), d_centre = select(unprojected, d_centre, zero);
      const R f = seed_camera(R(B(c == 0 ? img.fx : img.fy)), c);
      const R centre = seed_camera(R(B(c == 0 ? img.cx : img.cy)), 2 + c);
      moved = R::link(take.pos[c], moved, one, f, d_focal);
      moved = R::link(take.pos[c], moved, one, centre, d_centre);
    }
    // delta: the position less the pixel's where valid, else -V (Sample's), in one node (moved is the last made)
    smp.delta[c] = R::link(select(plain.valid, plain.delta[c], neg(pr.V[c].v)), moved, in, pr.P[c], neg(in), pr.V[c],
                           out);
  }
  for (int i = 0; i < 4; ++i) take.index[i] = plain.index[i];
  take.fu = plain.fu, take.fv = plain.fv, take.has = land(plain.valid, pr.live);
  return smp;
}

// walk.h's slice_angle in reverse lanes: its value the value lanes', its partial derivatives with respect to delta,
// T and V (nine, of slice_angle_slopes) in a chain of five nodes, where the two dot products and atan2 make seven
template <class B, class D>
TAO_FN Rev<B> slice_angle(int side, const Rev<B>* delta, const Rev<B>* V, const Rev<B>* T, const D& pixel_z) {
  using R = Rev<B>;
  B d[3], v[3], t[3], along_view, along_tangent, by_view, by_tangent;
  for (int c = 0; c < 3; ++c) d[c] = delta[c].v, v[c] = V[c].v, t[c] = T[c].v;
  slice_coordinates(side, d, v, t, value(pixel_z), along_view, along_tangent);
  const B theta = atan2(along_tangent, along_view), one(1.0f);
  slice_angle_slopes(side, along_view, along_tangent, by_view, by_tangent);
  B by_delta[3];
  for (int c = 0; c < 3; ++c) by_delta[c] = by_tangent * t[c] + by_view * v[c];
  R chain = R::link(theta, delta[0], by_delta[0], delta[1], by_delta[1]);
  chain = R::link(theta, chain, one, delta[2], by_delta[2], T[0], by_tangent * d[0]);
  chain = R::link(theta, chain, one, T[1], by_tangent * d[1], T[2], by_tangent * d[2]);
  chain = R::link(theta, chain, one, V[0], by_view * d[0], V[1], by_view * d[1]);
  return R::link(theta, chain, one, V[2], by_view * d[2]);
}

// Whether an accumulator's forward records its takes (record_block; the horizon accumulators': replaces()),
// so that its backward replays those alone; else the backward replays every step of the walk
template <class Acc, class = void> struct RecordsTakes {
  static constexpr bool value = false;
};
template <class Acc> struct RecordsTakes<Acc, decltype(void(&Acc::replaces))> {
  static constexpr bool value = true;
};

// The most fetches one slice of a horizon backward replays: where a take replaces the state (acc.replaces()), each
// side's last take alone, else every step of each side; a slice has one side with full_circle (HBAO's directions,
// SSAO's points) but for walk_pairs' (UE4 SSAO), which fetches both at every step. The caller sizes a replay's
// scratch by it (walk_grad.py's replayed_fetches chooses the same number on the host)
template <class Acc> TAO_FN int64_t replayed_fetches(const Acc& acc, const WalkSettings& cfg) {
  const int64_t sides = PairedSides<Acc>::value || !cfg.full_circle ? 2 : 1;
  if constexpr (RecordsTakes<Acc>::value) {
    if (acc.replaces()) return sides;
  }
  return sides * cfg.steps;
}

// The tape's nodes for a horizon backward's block: the pixel (Pixels<Rev>), then one slice at a time (its
// geometry, begin and end, its takes: at most replayed_fetches'). At 3 x 1..16 (every variant, fetch and azimuth;
// the count follows the code, not the values) the pixel makes at most 46, a slice at most 211 besides its takes, a take at
// most 46; a slice whose azimuth the projected normal's density draws about 25 more (counted: the normal's three
// components, the azimuth's and weight's nodes of density_azimuth, the slice's tangent and its weight's products);
// with room to spare (tests/test_kernels_walk_grad.py runs the most steps a CUDA thread takes)
constexpr int32_t kTapePixel = 64, kTapeSlice = 280, kTapeTake = 60, kTapeDensity = 40;
TAO_FN constexpr int32_t tape_capacity(int64_t fetches) {  // (fetches: a slice's, replayed_fetches')
  return kTapePixel + kTapeSlice + kTapeDensity + int32_t(fetches) * kTapeTake;
}

// The backward of the lanes' pixels: upstream[c] the gradient of output channel c (H, W), record the forward's
// (image b's), t where the gradients go (added to it); of every slice, or of slice `only` alone (>= 0: a gathered
// block's); scratch: take_steps 2 steps L floats, taken max_fetches takes, tape of tape_capacity(max_fetches) nodes,
// max_fetches at least replayed_fetches(acc, cfg) (overflow: the gradients are not written and tape.overflow
// says so)
template <class B, class Acc>
TAO_FN void grad_lanes(const WalkSettings& cfg, const Image& img, const Acc& acc, const RowLanes& lanes, int64_t only,
                       const float* const* upstream, int C, const int64_t* record, const Targets& t,
                       float* take_steps, TapedTake<B>* taken, int32_t max_fetches, Tape<B>& tape) {
  using R = Rev<B>;
  constexpr int L = LaneTraits<B>::L;
  const int n = lanes.n;
  B g[8];
  {
    float lane[L];
    bool none = true;
    for (int c = 0; c < C; ++c) {
      for (int l = 0; l < L; ++l) {
        lane[l] = l < n ? upstream[c][lanes.pixel(img.W, l)] : 0.0f;
        none = none && lane[l] == 0.0f;
      }
      g[c] = from_lanes(lane, B(0.0f));
    }
    if (none) return;  // (no gradient flows: the outputs' zeros stand)
  }
  // (pixels whose slices took nothing, where that leaves the outputs constant: none flows either)
  if constexpr (RecordsTakes<Acc>::value) {
    bool any_taken = !acc.untaken_slice_constant();
    for (int l = 0; l < n && !any_taken; ++l)
      any_taken = took_steps(cfg, record, lanes.pixel(img.W, l), only);
    if (!any_taken) return;
  }
  current_tape<B>() = &tape;
  tape.cut(0);
  tape.camera = t.camera != nullptr;
  const Pixels<R> px(cfg, img, lanes);
  if (!any(px.live) || tape.overflow) return;
  const Pixels<B> px_values(px, [](const R& x) { return x.v; });
  TapedFetches<B> fetches{&px_values, taken, max_fetches, 0};
  tape.fetches = &fetches;
  const int32_t pixel_nodes = tape.n;
  B setting[Tape<B>::kSettings], camera[4];
  for (int k = 0; k < Tape<B>::kSettings; ++k) setting[k] = B(0.0f);
  for (int k = 0; k < 4; ++k) camera[k] = B(0.0f);
  Replay<L> takes(take_steps, cfg.steps);
  for (int64_t s = only < 0 ? 0 : only; s < (only < 0 ? cfg.slices : only + 1); ++s) {
    if constexpr (RecordsTakes<Acc>::value) {
      takes.read(record, lanes, img.W, s, take_words(cfg));
      if (acc.untaken_slice_constant() && takes.most(0) == 0 && takes.most(1) == 0) continue;
    }
    const Slice<R> sl = walked_slice<Acc>(cfg, img, px, s);
    typename Acc::template State<R> state = acc.begin_slice(px, sl);
    fetches.n = 0;
    if constexpr (RecordsTakes<Acc>::value) {  // the recorded takes alone
      for (int side = 1; side >= (cfg.full_circle ? 1 : -1); side -= 2) {
        const int k = side > 0 ? 0 : 1;
        const R xi = step_noise(cfg, px, sl, side);
        for (int q = 0, most = takes.most(k); q < most; ++q) {
          float has_lane[L];
          for (int l = 0; l < L; ++l) has_lane[l] = q < takes.count[k][l] ? 1.0f : 0.0f;
          const auto has = from_lanes(has_lane, B(0.0f)) > B(0.5f);
          R su, sv;
          step_screen(cfg, img, px, sl, float(side), xi, R(select(has, from_lanes(takes.at(k, q), B(0.0f)), B(0.0f))),
                      su, sv);
          Sample<R> smp = fetch_sample(cfg, img, px, su, sv);
          smp.valid = land(smp.valid, has);  // (a lane without this take: an invalid sample, the identity)
          taken[fetches.n - 1].has = land(taken[fetches.n - 1].has, has);
          acc.step(state, side, px, sl, smp);
        }
      }
    } else if constexpr (PairedSides<Acc>::value) {
      walk_pairs(cfg, img, acc, px, sl, state);
    } else if constexpr (KernelPoints<Acc>::value) {
      walk_points(cfg, img, acc, px, state);
    } else {
      NoVisit none;
      walk_slice(cfg, img, acc, px, sl, state, none);
    }
    typename Acc::template Sums<R> part;
    acc.end_slice(state, px, sl, part);
    R outs[8];
    acc.finish(part, px, outs);  // linear in the sums: the slice's share of the outputs
    if (tape.overflow) return;
    for (int c = 0; c < C; ++c) tape.seed(outs[c].id, g[c] * outs[c].scale);
    tape.sweep(pixel_nodes);
    for (int k = 0; k < acc.settings(); ++k)
      setting[k] = setting[k] + tape.parameter_adjoint(Tape<B>::kSetting + k, pixel_nodes);
    for (int k = 0; k < 4; ++k) camera[k] = camera[k] + tape.parameter_adjoint(Tape<B>::kCamera + k, pixel_nodes);
    for (int r = 0; r < fetches.n; ++r) {
      const TapedTake<B>& take = taken[r];
      const B gd[3] = {tape.adjoint[take.ids[0]], tape.adjoint[take.ids[1]], tape.adjoint[take.ids[2]]};
      scatter_taps(cfg.bilinear, n, t, gd, take.pos, take.fu, take.fv, take.index, take.has);
    }
    tape.cut(pixel_nodes);
  }
  tape.sweep(0);
  B own[kPixel];
  for (int k = 0; k < kPixel; ++k) own[k] = tape.adjoint[tape.own[k]];
  write_own(t, img.W, lanes, own, setting, t.camera ? camera : nullptr);
}
// (the n <= L pixels of a row from u0, every slice)
template <class B, class Acc>
TAO_FN void grad_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row, int64_t u0, int n,
                       const float* const* upstream, int C, const int64_t* record, const Targets& t,
                       float* take_steps, TapedTake<B>* taken, int32_t max_fetches, Tape<B>& tape) {
  grad_lanes(cfg, img, acc, RowLanes{row, u0, n}, -1, upstream, C, record, t, take_steps, taken, max_fetches, tape);
}

// The soft backward's sink (soft.h's end_slice_adjoint): a step's d L / d delta to its kept fetch's taps
template <class B> struct TapSink {
  bool bilinear, layer_bilinear;  // the fetch's; the layer's read (ThicknessModel::value: bilinear, or the first tap)
  int n;
  const Targets& t;

  template <class State>
  TAO_FN void scatter(const B* g_delta, const State& st, int m, const typename LaneTraits<B>::M& on,
                      const B* g_layer = nullptr) {
    const B pos[3] = {st.pos[0][m], st.pos[1][m], st.pos[2][m]};
    const typename LaneTraits<B>::I index[4] = {st.index[0][m], st.index[1][m], st.index[2][m], st.index[3][m]};
    scatter_taps(bilinear, n, t, g_delta, pos, st.fu[m], st.fv[m], index, on, g_layer, layer_bilinear);
  }
  // d L / d a kept step's sender normal and light (3 each) to its taps' (indirect light)
  template <class State>
  TAO_FN void scatter_light(const B* g_normal, const B* g_light, const State& st, int m,
                            const typename LaneTraits<B>::M& on) {
    const typename LaneTraits<B>::I index[4] = {st.index[0][m], st.index[1][m], st.index[2][m], st.index[3][m]};
    scatter_gather(bilinear, n, t.tap_normals, 3, g_normal, st.fu[m], st.fv[m], index, on);
    scatter_gather(bilinear, n, t.tap_light, 3, g_light, st.fu[m], st.fv[m], index, on);
  }
};

// The soft backward of the n <= L pixels of a row from u0: the walk with SoftAdjoint's slices (the pixels and
// slices also in dual lanes: tangents on the pixel's own P, N, depth); the pixel's own gradients and
// d L / d the thickness' offset, scale and growth written per pixel (t.settings == 3) and, where t.camera, d L / d the
// intrinsics; the layer's to its taps
template <class B, int kMostSteps>
TAO_FN void soft_grad_block(const WalkSettings& cfg, const Image& img, const SoftAccumulator<true, true, kMostSteps>& acc,
                            int64_t row, int64_t u0, int n, const float* upstream, const Targets& t) {
  using D = Dual<B, kPixel>;
  // d L / d the visibility, then d L / d the indirect light (with indirect) and the bent normal's sum (with bent)
  B g[8];
  if (!upstream_lanes(img, row, u0, n, upstream, acc.outputs(), g)) return;  // (the outputs' zeros stand)
  TapSink<B> sink{cfg.bilinear, cfg.bilinear && acc.thickness.read == ThicknessRead::layer, n, t};
  const Pixels<D> pd(cfg, img, row, u0, n);
  const B den = acc.template denominator<B>(img, row, u0, n);
  B light_weight[3];
  for (int c = 0; c < 3; ++c) light_weight[c] = acc.indirect ? g[1 + c] / den : B(0.0f);
  const SoftAdjoint<B, D, TapSink<B>, kMostSteps> adjoint{acc, img, pd, g[0], g[0] / den,
                                                          acc.indirect ? light_weight : nullptr,
                                                          acc.bent ? &g[acc.indirect ? 4 : 1] : nullptr, sink,
                                                          t.camera != nullptr};
  B own[14];
  walk_block(cfg, img, adjoint, row, u0, n, own);
  // (the settings: d L / d the offset, the scale, the growth; where asked, d L / d the intrinsics)
  write_own(t, img.W, row, u0, n, own, &own[kPixel], t.camera ? &own[kPixel + 3] : nullptr);
}

// The exact union's backward (bitmask.h's ExactAccumulator: variant="exact" in every mode) of the n <= L pixels
// of a row from u0: d L / d the G-buffer for L = sum(upstream * visibility). The union is a sort and a running
// maximum, so its adjoint is written out rather than carried in tangents (one set per interval would not fit).
// Per slice:
//  1. the forward's intervals, in value lanes (walk_slice with the accumulator: the forward's decisions);
//  2. the union's adjoint: the intervals sorted by start with their indices, union_measure's sweep
//     (a_j = max(lo_j, reach_j), b_j = max(hi_j, reach_j), reach_j+1 = b_j) run back from the last interval:
//     d covered / d lo_i, d hi_i of each interval i (max passes its first operand at a tie, as the dual walk
//     of exact_soft.h does); measure's d / d a, d / d b and its dependence on the slice with the ends held come
//     from one evaluation in Dual<B, 9> (the pixel's own 7 tangents, then a, b);
//  3. each interval with a non-zero adjoint replayed: its segment (ExactAccumulator::segment) in Dual<B, 11> (the
//     pixel's own 7, the sample's delta 3, the thickness layer's value at the sample 1), the clip and the angles
//     (segment_interval) in tangents of the segment's 4 values and the shift, chained: its ends' own tangents join the slice's covered measure,
//     a dual in the own tangents taken through add_slice and finish (the pixel's own gradients); its delta's
//     and layer value's, times d L / d covered (finish's per_covered: the same for every slice), go to its taps.
// An interval of zero width has no tangents (empty, dead, or clamped at an end of the hemisphere): skipped.
constexpr int kExactDelta = kPixel, kExactLayer = kPixel + 3, kExactTangents = kPixel + 4;

template <class B>
TAO_FN void exact_grad_block(const WalkSettings& cfg, const Image& img, const ExactAccumulator& acc, int64_t row,
                             int64_t u0, int n, const float* upstream, const Targets& t) {
  constexpr int L = LaneTraits<B>::L;
  using Own = Dual<B, kPixel>;
  using Ends = Dual<B, kPixel + 2>;
  using D = Dual<B, kExactTangents>;
  using Local = Dual<B, 5>;  // an interval's segment (4) and shift
  using M = typename LaneTraits<B>::M;
  float lane[L];
  bool none = true;
  for (int l = 0; l < L; ++l) {
    lane[l] = l < n ? upstream[row * img.W + u0 + l] : 0.0f;
    none = none && lane[l] == 0.0f;
  }
  if (none) return;  // (no gradient flows: the outputs' zeros stand)
  const B g = from_lanes(lane, B(0.0f));
  const Pixels<B> px(cfg, img, row, u0, n);
  if (!any(px.live)) return;
  const Pixels<Own> px_own(cfg, img, row, u0, n);
  const auto wide = [](const Own& x) { return widen<kExactTangents>(x); };
  const auto with_ends = [](const Own& x) { return widen<kPixel + 2>(x); };
  const Pixels<D> pxd(px_own, wide);
  B den(0.0f);  // the slices' whole measure (cosine weights), for finish's d visibility / d covered
  if (acc.cosine) {
    B num(0.0f);
    for (int64_t s = 0; s < cfg.slices; ++s)
      acc.add_slice(B(0.0f), walked_slice<ExactAccumulator>(cfg, img, px, s), num, den);
  }
  const B per_covered = g * acc.per_covered(den);  // d L / d a slice's covered measure
  const bool layer_read = acc.thickness.reads_layer();
  const bool layer_bilinear = cfg.bilinear && acc.thickness.read == ThicknessRead::layer;
  typename ExactAccumulator::template Sums<Own> sums;
  LaneArray<B, kMaxIntervals> order, reach;
  float g_lo[kMaxIntervals][L], g_hi[kMaxIntervals][L];
  B g_cam[4] = {B(0.0f), B(0.0f), B(0.0f), B(0.0f)};  // d L / d fx, fy, cx, cy (where t.camera)
  for (int64_t s = 0; s < cfg.slices; ++s) {
    // 1. the forward's intervals (a slice drawn by the projected normal's density weighs its covered measure: its
    // taps' adjoints by the weight's value, the pixel's own tangents through add_slice's product with sl_own's)
    const Slice<Own> sl_own = walked_slice<ExactAccumulator>(cfg, img, px_own, s);
    const Slice<B> sl(sl_own, [](const Own& x) { return x.v; });  // (the same values: a dual's are its lanes')
    const B per_slice = weighed(sl, per_covered);
    typename ExactAccumulator::template State<B> st = acc.begin_slice(px, sl);
    NoVisit visit;
    walk_slice(cfg, img, acc, px, sl, st, visit);
    const int m = st.n;
    // 2. the union's adjoint
    for (int i = 0; i < m; ++i) order[i] = B(float(i));
    acc.sort_by_start(&st.lo[0], &st.hi[0], m, [&](const M& swap, int a, int b) {
      const B first = select(swap, order[b], order[a]);
      order[b] = select(swap, order[a], order[b]), order[a] = first;
    });
    B r(0.0f);
    for (int j = 0; j < m; ++j) reach[j] = r, r = max(st.hi[j], r);
    const Slice<Ends> sl_ends(sl_own, with_ends);
    Own covered;
    B g_reach(0.0f);  // d covered / d reach_j+1
    for (int j = m - 1; j >= 0; --j) {
      const auto take_lo = lnot(reach[j] > st.lo[j]), take_hi = lnot(reach[j] > st.hi[j]);
      const auto open = st.hi[j] > st.lo[j];
      // an interval within the reach (hi < reach) or of zero width measures nothing: it passes the reach's
      // adjoint on (at or beyond the reach, an empty one takes it into its constant end), no measure to differentiate
      if (!any(land(open, take_hi))) {
        g_reach = select(take_lo, B(0.0f), g_reach);
        to_lanes(order[j], lane);
        for (int l = 0; l < L; ++l) g_lo[int(lane[l])][l] = 0.0f, g_hi[int(lane[l])][l] = 0.0f;
        continue;
      }
      Ends a(max(st.lo[j], reach[j])), b(max(st.hi[j], reach[j]));
      a.d[kPixel] = B(1.0f), b.d[kPixel + 1] = B(1.0f);
      const Ends part = acc.measure(a, b, sl_ends);
      covered.v = covered.v + part.v;
      for (int k = 0; k < kPixel; ++k) covered.d[k] = covered.d[k] + part.d[k];
      const B ga = part.d[kPixel], gb = part.d[kPixel + 1] + g_reach;
      g_reach = select(take_lo, B(0.0f), ga) + select(take_hi, B(0.0f), gb);
      float gl[L], gh[L], il[L];
      to_lanes(select(land(open, take_lo), ga, B(0.0f)), gl), to_lanes(select(land(open, take_hi), gb, B(0.0f)), gh);
      to_lanes(order[j], il);
      for (int l = 0; l < L; ++l) g_lo[int(il[l])][l] = gl[l], g_hi[int(il[l])][l] = gh[l];
    }
    // 3. the intervals with an adjoint, replayed
    const Slice<D> sld(sl_own, wide);
    const Own shift = edge_shift(sl_own);
    PlacementAdjoint<B> placement;  // (where t.camera)
    for (int side = 1; side >= -1; side -= 2) {
      const Own xi = step_noise(cfg, px_own, sl_own, side);
      for (int64_t j = 0; j < cfg.steps; ++j) {
        const int i = int((side > 0 ? 0 : cfg.steps) + j);  // (walk_slice's order)
        const B glo = from_lanes(g_lo[i], B(0.0f)), ghi = from_lanes(g_hi[i], B(0.0f));
        if (!any(lor(lnot(glo == B(0.0f)), lnot(ghi == B(0.0f))))) continue;
        const Own dist = step_distance(cfg, sl_own, xi, j);
        B d_su[3], d_sv[3];
        Sample<D> smp = replayed_sample<D>(cfg, img, px, px_own, sl_own, float(side), dist, d_su, d_sv);
        for (int c = 0; c < 3; ++c) smp.delta[c].d[kExactDelta + c] = B(1.0f);
        D thickness = acc.thickness.at(pxd, smp);  // (its growth's tangents through delta's)
        if (layer_read) {  // d t / d the layer's value: the scale, times the growth's factor
          thickness.d[kExactLayer] = B(acc.thickness.scale);
          if (acc.thickness.growth != 0.0f) {
            const B delta[3] = {smp.delta[0].v, smp.delta[1].v, smp.delta[2].v};
            B length;
            thickness.d[kExactLayer] = thickness.d[kExactLayer] * acc.thickness.growth_factor(delta, length);
          }
        }
        D seg[4];
        acc.segment(side, pxd, sld, smp.delta, thickness, seg);
        // the interval from its segment and the shift in tangents of their own (5, where the 11 would carry the
        // clip and the atan2s), contracted with the ends' adjoints, then chained to the 11
        Local local[4], lo, hi;
        for (int q = 0; q < 4; ++q) local[q] = Local(seg[q].v), local[q].d[q] = B(1.0f);
        Local shift_local(shift.v);
        shift_local.d[4] = B(1.0f);
        acc.segment_interval(side, local, shift_local, Local(B(acc.radius)), smp.valid, lo, hi);
        B w[5], along[kExactTangents];
        for (int q = 0; q < 5; ++q) w[q] = glo * lo.d[q] + ghi * hi.d[q];
        for (int k = 0; k < kExactTangents; ++k) {
          along[k] = w[0] * seg[0].d[k] + w[1] * seg[1].d[k] + w[2] * seg[2].d[k] + w[3] * seg[3].d[k];
          if (k < kPixel) along[k] = along[k] + w[4] * shift.d[k];
        }
        for (int k = 0; k < kPixel; ++k) covered.d[k] = covered.d[k] + along[k];
        B gd[3], pos[3];
        for (int c = 0; c < 3; ++c) gd[c] = per_slice * along[kExactDelta + c], pos[c] = smp.delta[c].v + pxd.P[c].v;
        const B g_layer = per_slice * along[kExactLayer];
        const auto on = land(smp.valid, px.live);
        if (t.camera) {  // the intrinsics: the fetch's unprojection, and where it samples (the slice's placement)
          if (cfg.bilinear) unprojection_camera(cfg, img, smp.index, pos, gd, on, g_cam);
          B layer_su, layer_sv;
          acc.thickness.layer_slope(Sample<B>(smp, [](const D& x) { return x.v; }), layer_su, layer_sv);
          const B g_su = gd[0] * d_su[0] + gd[1] * d_su[1] + gd[2] * d_su[2] + g_layer * layer_su;
          const B g_sv = gd[0] * d_sv[0] + gd[1] * d_sv[1] + gd[2] * d_sv[2] + g_layer * layer_sv;
          placement.add(cfg, sl, float(side), dist.v, select(on, g_su, B(0.0f)), select(on, g_sv, B(0.0f)));
        }
        scatter_taps(cfg.bilinear, n, t, gd, pos, smp.fu.v, smp.fv.v, smp.index, on,
                     layer_read ? &g_layer : nullptr, layer_bilinear);
      }
    }
    if (t.camera) placement.camera(cfg, img, sl, g_cam);
    acc.add_slice(covered, sl_own, sums.num, sums.den);
  }
  Own vis;
  acc.finish(sums, px_own, &vis);
  B own[kPixel];
  for (int k = 0; k < kPixel; ++k) own[k] = g * vis.d[k];
  for (int k = 0; k < 4; ++k) g_cam[k] = select(px.live, g_cam[k], B(0.0f));
  write_own(t, img.W, row, u0, n, own, static_cast<const B*>(nullptr), t.camera ? g_cam : nullptr);
}

// The sectors each step of a slice newly occludes (walk_slice's visitor): fresh[i] of step i in walk_slice's
// order (side +1's steps, then side -1's)
template <class B> struct FreshSectors {
  static constexpr bool kBefore = true;
  using State = typename BitmaskAccumulator::template State<B>;
  typename LaneTraits<B>::I* fresh;
  int64_t steps;
  TAO_FN void operator()(int side, int64_t j, const Sample<B>&, const State& before, const State& after) {
    fresh[(side > 0 ? 0 : steps) + j] = after.occ & bnot(before.occ);
  }
};

// The hard sector walk's forward with its record: each slice's occupied sectors, one word per pixel and slice
// at record + (pixel * slices + slice) (image b's; pixel = row * W + u0 + lane), so that the backward ends the
// slices without walking them again; the outputs' lanes in values
// (Acc: BitmaskAccumulator, or GlslAccumulator, whose mask is carried across slices: its record is the mask after
// each slice, the next slice's start)
template <class B, class Acc>
TAO_FN void hard_record_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row,
                              int64_t u0, int n, int32_t* record, B* values) {
  constexpr int L = LaneTraits<B>::L;
  const Pixels<B> px(cfg, img, row, u0, n);
  typename Acc::template Sums<B> sums;
  const bool live = any(px.live);
  for (int64_t s = 0; s < cfg.slices; ++s) {
    int32_t occ[L] = {};
    if (live) {
      const Slice<B> sl = walked_slice<Acc>(cfg, img, px, s);
      typename Acc::template State<B> st = begin_slice_of(acc, px, sl, sums, 0);
      NoVisit visit;
      walk_slice(cfg, img, acc, px, sl, st, visit);
      acc.end_slice(st, px, sl, sums);
      store_lanes(st.occ, occ);
    }
    for (int l = 0; l < n; ++l) record[((row * img.W + u0 + l) * cfg.slices) + s] = occ[l];
  }
  acc.finish(sums, px, values);
}

// The upstream gradients of the n <= L pixels of a row from u0 in lanes, g[c] of channel c of upstream (C, H, W);
// false where all are zero (no gradient flows)
template <class B>
TAO_FN bool upstream_lanes(const Image& img, int64_t row, int64_t u0, int n, const float* upstream, int C, B* g) {
  constexpr int L = LaneTraits<B>::L;
  const int64_t plane = img.H * img.W;
  bool none = true;
  for (int c = 0; c < C; ++c) {
    float lane[L];
    for (int l = 0; l < L; ++l) {
      lane[l] = l < n ? upstream[c * plane + row * img.W + u0 + l] : 0.0f;
      none = none && lane[l] == 0.0f;
    }
    g[c] = from_lanes(lane, B(0.0f));
  }
  return !none;
}

// The hard sector walk's backward (bitmask.h's BitmaskAccumulator in hard mode, visibility and bent normals) of
// the n <= L pixels of a row from u0: d L / d the pixel's own position, normal and depth for L = sum over the C
// outputs of upstream[c] * output c; record: hard_record_block's (image b's). Hard masks have no derivative, but
// what weights them has: the cosine weights and the bent normals' directions follow the slice (its projected
// normal, its tangent). So each slice is ended again with the recorded sectors in the 2 tangents of the slice's
// gamma and length, which its weights follow, chained to the pixel's own position, normal and depth (Dual<B, 7>,
// with the bent normal's view vector and tangent); no tap gets a gradient. Either variant's angles: begin_slice
// and end_slice take the walked slice's frame to the variant's (HDRP's gamma of the walked one) in those tangents.
template <class B>
TAO_FN void hard_grad_block(const WalkSettings& cfg, const Image& img, const BitmaskAccumulator& acc, int64_t row,
                            int64_t u0, int n, const float* upstream, const int32_t* record, const Targets& t) {
  constexpr int L = LaneTraits<B>::L;
  using Own = Dual<B, kPixel>;
  using I = typename LaneTraits<B>::I;
  const int C = acc.channels();
  B g[8];
  if (!upstream_lanes(img, row, u0, n, upstream, C, g)) return;  // (no gradient flows: the outputs' zeros stand)
  const Pixels<B> px(cfg, img, row, u0, n);
  if (!any(px.live)) {  // background alone: its bent normal is its own normal (finish's), which takes the upstream's
    if (acc.bent) {
      B own[kPixel];
      for (int k = 0; k < kPixel; ++k) own[k] = k >= 3 && k < 6 ? g[C - 6 + k] : B(0.0f);
      write_own(t, img.W, row, u0, n, own);
    }
    return;
  }
  const Pixels<Own> px_own(cfg, img, row, u0, n);
  // indirect light: each newly occluding step replayed in Dual<B, 16> (the pixel's own 7, the sample's offset 3,
  // the sender's normal 3 and light 3, both gathered at its taps)
  constexpr int kDelta = kPixel, kSender = kPixel + 3, kLight = kPixel + 6, N = kPixel + 9;
  using D = Dual<B, N>;
  B per_light[3];  // d L / d a slice's light sum
  if (acc.indirect) {
    typename BitmaskAccumulator::template Sums<B> whole;  // (den: the slices' whole weight)
    for (int64_t s = 0; s < cfg.slices; ++s) {
      const Slice<B> sl = walked_slice<BitmaskAccumulator>(cfg, img, px, s);
      acc.end_slice(acc.begin_slice(px, sl), px, sl, whole);
    }
    for (int c = 0; c < 3; ++c) per_light[c] = select(px.live, g[1 + c] * acc.per_light(whole.den), B(0.0f));
  }
  LaneArray<I, kMaxIntervals> fresh;
  B g_cam[4] = {B(0.0f), B(0.0f), B(0.0f), B(0.0f)};  // d L / d fx, fy, cx, cy (indirect light, where t.camera)
  using Two = Dual<B, 2>;  // a slice's gamma and length
  const auto constant = [](const B& x) { return Two(x); };
  Pixels<Two> px_axes(px, constant);
  for (int c = 0; c < 3; ++c) px_axes.V[c] = Two(B(c == 0 ? 1.0f : 0.0f));
  typename BitmaskAccumulator::template Sums<Own> sums;
  for (int64_t s = 0; s < cfg.slices; ++s) {
    int32_t words[L] = {};
    for (int l = 0; l < n; ++l) words[l] = record[(row * img.W + u0 + l) * cfg.slices + s];
    const I occ = from_lanes(words, I(0));
    const Slice<Own> sl_own = walked_slice<BitmaskAccumulator>(cfg, img, px_own, s);
    const Slice<B> sl(sl_own, [](const Own& x) { return x.v; });  // (the same values: a dual's are its lanes')
    // the slice's weights follow its gamma and length alone: its end in their 2 tangents, chained to the 7; a slice
    // drawn by the projected normal's density ended unweighed, its sums then times its weight in the 7 (weighted)
    Slice<Two> sl_two(sl, constant);
    sl_two.gamma.d[0] = B(1.0f), sl_two.cos_gamma.d[0] = neg(sl.sin_gamma), sl_two.sin_gamma.d[0] = sl.cos_gamma;
    sl_two.length.d[1] = B(1.0f);
    sl_two.weight = Two(B(1.0f));
    // end_slice's bent normal is along_v V + along_t T: with V and T the first two axes it gives along_v and
    // along_t, which are then chained and multiplied by V and T in the own tangents
    for (int c = 0; c < 3; ++c) sl_two.T[c] = Two(B(c == 1 ? 1.0f : 0.0f));
    typename BitmaskAccumulator::template State<Two> ended = acc.begin_slice(px_axes, sl_two);
    ended.occ = occ;
    typename BitmaskAccumulator::template Sums<Two> part;
    acc.end_slice(ended, px_axes, sl_two, part);
    const auto chained = [&](const Two& x) {
      Own r(x.v);
      for (int k = 0; k < kPixel; ++k) r.d[k] = x.d[0] * sl_own.gamma.d[k] + x.d[1] * sl_own.length.d[k];
      return r;
    };
    const auto weighted = [&](const Two& x) {
      return sectors_drawn(cfg) ? chained(x) * sl_own.weight : chained(x);
    };
    sums.visible = sums.visible + weighted(part.visible);
    sums.num = sums.num + weighted(part.num), sums.den = sums.den + weighted(part.den);
    if (acc.bent) {
      const Own along_v = weighted(part.bent[0]), along_t = weighted(part.bent[1]);
      for (int c = 0; c < 3; ++c) sums.bent[c] = sums.bent[c] + along_v * px_own.V[c] + along_t * sl_own.T[c];
    }
    if (!acc.indirect) continue;
    // the light: the slice walked again for the sectors each step newly occludes, those steps replayed
    const Pixels<D> pxd(px_own, [](const Own& x) { return widen<N>(x); });
    typename BitmaskAccumulator::template State<B> st = acc.begin_slice(px, sl);
    FreshSectors<B> visit{&fresh[0], cfg.steps};
    walk_slice(cfg, img, acc, px, sl, st, visit);
    B slice_light[3];  // d L / d this slice's light sum (weighed as the slice is)
    for (int c = 0; c < 3; ++c) slice_light[c] = weighed(sl, per_light[c]);
    PlacementAdjoint<B> placement;  // (where t.camera)
    for (int side = 1; side >= -1; side -= 2) {
      const Own xi = step_noise(cfg, px_own, sl_own, side);
      for (int64_t j = 0; j < cfg.steps; ++j) {
        const I step_fresh = fresh[int((side > 0 ? 0 : cfg.steps) + j)];
        if (!any(lnot(ieq(step_fresh, I(0))))) continue;
        const Own dist = step_distance(cfg, sl_own, xi, j);
        B d_su[3], d_sv[3];
        Sample<D> smp = replayed_sample<D>(cfg, img, px, px_own, sl_own, float(side), dist, d_su, d_sv);
        D sender_n[3], light[3], sent[3];
        for (int c = 0; c < 3; ++c) {
          smp.delta[c].d[kDelta + c] = B(1.0f);
          sender_n[c] = smp.gather(img.normals, c), sender_n[c].d[kSender + c] = B(1.0f);
          light[c] = smp.gather(img.light, c), light[c].d[kLight + c] = B(1.0f);
        }
        acc.light_sent(pxd, smp, widen<N>(chained(acc.newly_occluded(ended, step_fresh))), sender_n, light, sent);
        B gd[3], gn[3], gl[3], pos[3];
        for (int q = 0; q < 3; ++q) {
          gd[q] = gn[q] = gl[q] = B(0.0f);
          for (int c = 0; c < 3; ++c) {
            gd[q] = gd[q] + slice_light[c] * sent[c].d[kDelta + q];
            gn[q] = gn[q] + slice_light[c] * sent[c].d[kSender + q];
            gl[q] = gl[q] + slice_light[c] * sent[c].d[kLight + q];
          }
          pos[q] = smp.delta[q].v + px.P[q];
        }
        for (int c = 0; c < 3; ++c) {  // its own tangents: through the light sums, finish's division
          Own own(sent[c].v);
          for (int k = 0; k < kPixel; ++k) own.d[k] = sent[c].d[k];
          sums.light[c] = sums.light[c] + (sectors_drawn(cfg) ? own * sl_own.weight : own);
        }
        const auto on = land(smp.valid, px.live);
        if (t.camera) {  // the intrinsics: the fetch's unprojection, and where it samples (its position, the
          // sender's normal and light all move with it)
          if (cfg.bilinear) unprojection_camera(cfg, img, smp.index, pos, gd, on, g_cam);
          const Sample<B> plain(smp, [](const D& x) { return x.v; });
          B g_su = gd[0] * d_su[0] + gd[1] * d_su[1] + gd[2] * d_su[2], g_sv = gd[0] * d_sv[0] + gd[1] * d_sv[1] + gd[2] * d_sv[2];
          for (int c = 0; c < 3; ++c) {
            B n_su, n_sv, l_su, l_sv;
            plain.gather_slope(img.normals, c, 3, n_su, n_sv);
            plain.gather_slope(img.light, c, 3, l_su, l_sv);
            g_su = g_su + gn[c] * n_su + gl[c] * l_su, g_sv = g_sv + gn[c] * n_sv + gl[c] * l_sv;
          }
          placement.add(cfg, sl, float(side), dist.v, select(on, g_su, B(0.0f)), select(on, g_sv, B(0.0f)));
        }
        scatter_taps(cfg.bilinear, n, t, gd, pos, smp.fu.v, smp.fv.v, smp.index, on);
        scatter_gather(cfg.bilinear, n, t.tap_normals, 3, gn, smp.fu.v, smp.fv.v, smp.index, on);
        scatter_gather(cfg.bilinear, n, t.tap_light, 3, gl, smp.fu.v, smp.fv.v, smp.index, on);
      }
    }
    if (t.camera) placement.camera(cfg, img, sl, g_cam);
  }
  Own outs[8];
  acc.finish(sums, px_own, outs);
  B own[kPixel];
  for (int k = 0; k < kPixel; ++k) {
    own[k] = B(0.0f);
    for (int c = 0; c < C; ++c) own[k] = own[k] + g[c] * outs[c].d[k];
  }
  for (int k = 0; k < 4; ++k) g_cam[k] = select(px.live, g_cam[k], B(0.0f));
  write_own(t, img.W, row, u0, n, own, static_cast<const B*>(nullptr), t.camera ? g_cam : nullptr);
}

// d L / d (the pixel's normal N, the sample's delta, the sender's normal and light at its tap) of the light a step
// sends with weight (GlslAccumulator::light_sent: weight light c1 c2, c1 = clamp(normal . h, 0, 1), c2 = clamp(s . -h,
// 0, 1), h = delta / |delta|, s the sender's normal normalised; normal = N / |N|, the pixel's, normal_length = |N|) for
// d L / d the light = per_light, into g (0 off the lanes on); its taps' scattered to the sender's normal and light.
// By hand: d u / d v = (I - u u^T) / |v| for each u = v / |v|, the clamps passing inside [0, 1]
template <class B>
TAO_FN void glsl_light_grads(const GlslAccumulator& acc, const B* normal, const B& normal_length, const Sample<B>& smp,
                             const B* delta, const B& weight, const B* per_light, const typename LaneTraits<B>::M& on,
                             int n, const Targets& t, B* g) {
  B h[3], away[3], raw[3], sender[3], light[3];
  acc.unit(delta, h);
  for (int c = 0; c < 3; ++c) {
    away[c] = neg(h[c]);
    raw[c] = smp.gather(smp.image->normals, c), light[c] = smp.gather(smp.image->light, c);
  }
  acc.gl.normalize(raw, sender);
  const B d1 = acc.gl.dot(normal, h), d2 = acc.gl.dot(sender, away);
  const B c1 = clamp(d1, B(0.0f), B(1.0f)), c2 = select(smp.valid, clamp(d2, B(0.0f), B(1.0f)), B(0.0f));
  const B along = per_light[0] * light[0] + per_light[1] * light[1] + per_light[2] * light[2];  // d L / d (c1 c2) / weight
  const B g1 = select(land(d1 >= B(0.0f), d1 <= B(1.0f)), along * weight * c2, B(0.0f));
  const B g2 = select(land(smp.valid, land(d2 >= B(0.0f), d2 <= B(1.0f))), along * weight * c1, B(0.0f));
  B g_normal[3], g_sender[3], g_h[3];
  for (int c = 0; c < 3; ++c) {
    g_normal[c] = g1 * h[c], g_sender[c] = neg(g2 * h[c]), g_h[c] = g1 * normal[c] - g2 * sender[c];
    g[9 + c] = per_light[c] * ((weight * c1) * c2);
  }
  const B f_normal = dot3(g_normal, normal), f_sender = dot3(g_sender, sender), f_h = dot3(g_h, h);
  const B inv_normal = B(1.0f) / normal_length, inv_raw = B(1.0f) / acc.gl.length(raw);
  const B inv_delta = B(1.0f) / acc.gl.length(delta);
  // (selected: where a factor has no gradient its vector may be degenerate, a zero normal or offset)
  const auto on_1 = g1 != B(0.0f), on_2 = g2 != B(0.0f), on_h = lor(on_1, on_2);
  for (int c = 0; c < 3; ++c) {
    g[c] = select(on_1, (g_normal[c] - f_normal * normal[c]) * inv_normal, B(0.0f));
    g[3 + c] = select(on_h, (g_h[c] - f_h * h[c]) * inv_delta, B(0.0f));
    g[6 + c] = select(on_2, (g_sender[c] - f_sender * sender[c]) * inv_raw, B(0.0f));
  }
  for (int k = 0; k < 12; ++k) g[k] = select(on, g[k], B(0.0f));
  scatter_gather(false, n, t.tap_normals, 3, g + 6, smp.fu, smp.fv, smp.index, on);
  scatter_gather(false, n, t.tap_light, 3, g + 9, smp.fu, smp.fv, smp.index, on);
}

// The "ssilvb_glsl" variant's hard backward (hard_grad_block of bitmask_glsl.h's GlslAccumulator, indirect light) of the n <= L pixels
// of a row from u0: d L / d its light, for L = sum over its 4 outputs of upstream[c] * output c; record:
// hard_record_block's (image b's: the carried mask after each slice). The masks, and so each step's weight, have no
// derivative, and the shader's texels (floored) do not move: each slice is walked again from its recorded start,
// and each valid step's light_sent differentiated (glsl_light_grads: to the pixel's own normal, the sample's offset,
// the sender's normal and light at its tap): d L / d the pixel's normal and position (-the offset's) are its own,
// the tap's position, normal and light scattered (nearest fetch: index[0]). No depth, intrinsics or radius
// gradient of its own (the positions carry them, through walk_inputs).
template <class B> struct GlslLightAdjoint {
  static constexpr bool kBefore = true;
  using State = typename GlslAccumulator::template State<B>;
  const GlslAccumulator& acc;
  const Pixels<B>& px;
  const B* normal;       // normalize(N)
  B normal_length;       // |N|
  const B* per_light;    // d L / d the light sums
  const Targets& t;
  int n;
  B* own;                // d L / d P (3), N (3)

  TAO_FN void operator()(int, int64_t, const Sample<B>& smp, const State& before, const State& after) {
    const auto on = land(smp.valid, px.live);
    if (!any(on)) return;
    B g[12];
    glsl_light_grads(acc, normal, normal_length, smp, smp.delta, acc.weight(after.occ & bnot(before.occ)), per_light,
                     on, n, t, g);
    for (int c = 0; c < 3; ++c) own[c] = own[c] - g[3 + c], own[3 + c] = own[3 + c] + g[c];
    scatter_taps(false, n, t, g + 3, smp.delta, smp.fu, smp.fv, smp.index, on);
  }
};

template <class B>
TAO_FN void hard_grad_block(const WalkSettings& cfg, const Image& img, const GlslAccumulator& acc, int64_t row,
                            int64_t u0, int n, const float* upstream, const int32_t* record, const Targets& t) {
  constexpr int L = LaneTraits<B>::L;
  using I = typename LaneTraits<B>::I;
  B g[8];
  if (!acc.indirect || !upstream_lanes(img, row, u0, n, upstream, acc.channels(), g)) return;
  const Pixels<B> px(cfg, img, row, u0, n);
  if (!any(px.live)) return;
  B per_light[3];
  for (int c = 0; c < 3; ++c) per_light[c] = select(px.live, g[1 + c] / B(float(acc.slice_count)), B(0.0f));
  B normal[3];
  acc.gl.normalize(px.N, normal);
  B own[kPixel];
  for (int k = 0; k < kPixel; ++k) own[k] = B(0.0f);
  GlslLightAdjoint<B> visit{acc, px, normal, acc.gl.length(px.N), per_light, t, n, own};
  typename GlslAccumulator::template Sums<B> sums;
  for (int64_t s = 0; s < cfg.slices; ++s) {
    int32_t words[L] = {};
    if (s > 0)
      for (int l = 0; l < n; ++l) words[l] = record[(row * img.W + u0 + l) * cfg.slices + s - 1];
    sums.occ = from_lanes(words, I(0));
    const Slice<B> sl(cfg, img, px, s);
    typename GlslAccumulator::template State<B> st = acc.begin_slice(px, sl, sums);
    walk_slice(cfg, img, acc, px, sl, st, visit);
  }
  write_own(t, img.W, row, u0, n, own);
}

// The "ssilvb_glsl" variant's soft / straight-through backward (soft_glsl.h's GlslSoftAccumulator) of the n <= L
// pixels of a row from u0, for L = sum over its outputs of upstream[c] * output c. Its union carries each sector's
// visible share across slices, so d L / d a slice's end is its own visibility's (1 / 32 a sector) plus what the later
// slices owe their start (soft_union's dL/dp0). So the forward runs first, keeping each slice's start (P, or the hard
// mask as shares), then the slices last to first: each walked again keeping its steps (GlslSoftSteps), swept from its
// start, scanned back from that seed (soft.h's reverse_scan, with each step's gain), which leaves its own start's debt
// for the slice before it. Each step's d L / d its unclamped horizons goes through horizons_adjoint to its delta
// (scattered to its tap; the pixel's own P the opposite), its thickness (the offset's and scale's sums per pixel, the
// layer's tap, or a depth read's) and the camera direction; the slices' n through (g_x + g_y) / pi. The camera
// direction's and each slice's n's tangents on the pixel's own P, N, depth come from slice_angles in dual lanes. With
// indirect light each step's light (weight 1 - newly: the scan's soft share, or the hard one) is replayed as the hard
// backward's (glsl_light_grads). No intrinsics or radius gradient of its own: the shader's texels are floored.
template <class B, int kMostSteps>
TAO_FN void soft_grad_block(const WalkSettings& cfg, const Image& img,
                            const GlslSoftAccumulator<SoftAccumulator<true, true, kMostSteps>>& acc, int64_t row,
                            int64_t u0, int n, const float* upstream, const Targets& t) {
  using Union = SoftAccumulator<true, true, kMostSteps>;
  using Steps = GlslSoftSteps<B, Union>;
  using D = Dual<B, kPixel>;
  B g[4];
  if (!upstream_lanes(img, row, u0, n, upstream, acc.channels(), g)) return;
  const Pixels<B> px(cfg, img, row, u0, n);
  if (!any(px.live)) return;
  const B count = B(float(acc.shader.slice_count));
  const B per_share = select(px.live, g[0] / count, B(0.0f)) * B(1.0f / kSectors);  // d L / d a share at a slice's end
  B light_weight[3];
  for (int c = 0; c < 3; ++c) light_weight[c] = acc.shader.indirect ? select(px.live, g[1 + c] / count, B(0.0f)) : B(0.0f);
  // 1. the forward (without its light), keeping each slice's start (and the hard mask carried into it)
  LaneArray<B, kGlslMaxSlices * kSectors> starts;
  LaneArray<typename LaneTraits<B>::I, kGlslMaxSlices> masks;
  {
    GlslSoftAccumulator<Union> unlit = acc;
    unlit.shader.indirect = false;
    typename GlslSoftAccumulator<Union>::template Sums<B> sums;
    NoVisit none;
    for (int64_t s = 0; s < cfg.slices; ++s) {
      const Slice<B> sl(cfg, img, px, s);
      typename GlslSoftAccumulator<Union>::template State<B> st = unlit.begin_slice(px, sl, sums);
      for (int k = 0; k < kSectors; ++k) starts[s * kSectors + k] = st.P[k];
      masks[s] = st.shader.occ;
      if (s + 1 == cfg.slices) break;
      walk_slice(cfg, img, unlit, px, sl, st, none);
      unlit.end_slice(st, px, sl, sums);
    }
  }
  // 2. the slices last to first
  const Steps steps{acc, acc.shader.indirect ? light_weight : nullptr};
  TapSink<B> sink{false, false, n, t};
  B normal[3];  // (indirect light's: the pixel's normal normalised)
  acc.shader.gl.normalize(px.N, normal);
  const B normal_length = acc.shader.gl.length(px.N);
  B owed[kSectors], own[kPixel], g_camera[3] = {B(0.0f), B(0.0f), B(0.0f)}, setting[3] = {B(0.0f), B(0.0f), B(0.0f)};
  for (int k = 0; k < kSectors; ++k) owed[k] = B(0.0f);
  for (int k = 0; k < kPixel; ++k) own[k] = B(0.0f);
  const Pixels<D> pd(cfg, img, row, u0, n);
  D along = D(0.0f);  // (its tangents: through the camera direction and the slices' n)
  for (int64_t s = cfg.slices - 1; s >= 0; --s) {
    const Slice<B> sl(cfg, img, px, s);
    typename Steps::template State<B> st;
    typename GlslAccumulator::template Sums<B> carried;
    carried.occ = masks[s];
    st.shader = acc.shader.begin_slice(px, sl, carried);
    st.kept.n = 0;
    for (int k = 0; k < kSectors; ++k) st.kept.P[k] = starts[s * kSectors + k], st.kept.omega[k] = B(1.0f / kSectors);
    NoVisit none;
    walk_slice(cfg, img, steps, px, sl, st, none);
    LaneArray<B, kMostSteps * kSectors> before;
    acc.soft.sweep(st.kept, &before[0]);
    B g_n = B(0.0f);
    const auto& kept = st.kept;
    const auto seed = [&](int k) { return per_share + owed[k]; };
    acc.soft.reverse_scan(kept, &before[0], seed, [&](int m, const typename Union::template StepAdjoint<B>& adj) {
      // d L / d the unclamped horizons (the scan's angles are theirs over pi: the interval's turn is +1)
      const B g_x = adj.front * B(kPi), g_y = adj.back * B(kPi);
      const B delta[3] = {kept.delta[0][m], kept.delta[1][m], kept.delta[2][m]};
      const auto on = land(px.live, kept.valid[m]);
      B g_delta[3], g_t;
      acc.shader.horizons_adjoint(st.shader.camera, delta, kept.t[m], g_x, g_y, g_delta, g_camera, g_t);
      g_n = g_n + (g_x + g_y) * B(1.0f / kPi);
      g_t = select(px.live, g_t, B(0.0f));
      // (the offset's, the scale's and the growth's; the growth's share of d L / d delta)
      typename Union::template Sums<B> part;
      const B g_base = acc.soft.thickness_adjoint(g_t, delta, kept.t[m], kept.tv[m], px, part, g_delta);
      setting[0] = setting[0] + part.thickness, setting[1] = setting[1] + part.scale;
      setting[2] = setting[2] + part.growth;
      B g_value = g_base * B(acc.shader.thickness.scale);  // d L / d the value the scale multiplies
      if (acc.shader.thickness.read == ThicknessRead::depth) {  // value = -(delta_z + P_z): the tap's depth
        g_delta[2] = g_delta[2] - g_value;
        own[2] = own[2] - g_value;  // (with own's -g_delta below: none of it on the pixel's own P)
      }
      if (acc.shader.indirect && any(on)) {  // the light it sends, weighed by 1 - the share it newly occludes
        const typename LaneTraits<B>::I taps[4] = {kept.index[0][m], kept.index[1][m], kept.index[2][m], kept.index[3][m]};
        const Sample<B> smp(img, false, taps, kept.fu[m], kept.fv[m], kept.valid[m]);
        const B newly = acc.soft.straight_through ? kept.hard_newly[m] : adj.newly;
        B gl[12];
        glsl_light_grads(acc.shader, normal, normal_length, smp, delta, B(1.0f) - newly, light_weight, on, n, t, gl);
        for (int c = 0; c < 3; ++c) own[3 + c] = own[3 + c] + gl[c], g_delta[c] = g_delta[c] + gl[3 + c];
      }
      for (int c = 0; c < 3; ++c) {
        g_delta[c] = select(on, g_delta[c], B(0.0f));
        own[c] = own[c] - g_delta[c];
      }
      sink.scatter(g_delta, kept, m, on, acc.shader.thickness.reads_layer() ? &g_value : nullptr);
    }, acc.shader.indirect, static_cast<B*>(nullptr), owed);
    const Slice<D> sd(cfg, img, pd, s);
    D camera[3], normal_d[3], angle;
    acc.shader.slice_angles(pd, sd, camera, normal_d, angle);
    // (selected: a pixel whose n is NaN, its projected normal of zero length, has NaN intervals, which are empty
    // steps, as the tensor path's, and no gradient)
    along = along + select(land(px.live, g_n != B(0.0f)), D(g_n) * angle, D(0.0f));
    if (s == 0)
      for (int c = 0; c < 3; ++c)
        along = along + select(land(px.live, g_camera[c] != B(0.0f)), D(g_camera[c]) * camera[c], D(0.0f));
  }
  for (int k = 0; k < kPixel; ++k) own[k] = select(px.live, own[k] + along.d[k], B(0.0f));
  write_own(t, img.W, row, u0, n, own, setting);
}

// Pixel p (of B H W) of a CUDA thread: its forward into out (B, C, H, W) and its takes into record
// (B, H, W, take_words), at most kGradMaxSteps steps per side
template <class Acc>
TAO_FN void record_pixel(const WalkSettings& cfg, const Acc& acc, const Frame& fr, float* out, int64_t* record,
                         int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  float values[8];
  record_block(cfg, fr.image(b), acc, row, u, 1, reinterpret_cast<uint64_t*>(record) + p * take_words(cfg), values);
  const int C = acc.channels();
  for (int c = 0; c < C; ++c) out[((b * C + c) * fr.H + row) * fr.W + u] = values[c];
}

// Into t, image b's position buffer where a bilinear fetch reads one between texels (Targets::read_positions: its
// taps' positions take the gradient, in tap_positions), for a CUDA thread's backward (none in the lean build, whose
// walk reads the depth there)
TAO_FN void read_position_buffer(Targets& t, const WalkSettings& cfg, const Frame& fr, int64_t b) {
  if constexpr (!kLeanWalk) {
    if (cfg.bilinear && !cfg.unprojected)
      t.read_positions = fr.positions + 3 * b * fr.H * fr.W, t.read_edge_aware = cfg.edge_aware;
  }
}

// Pixel p's backward (a CUDA thread): grad (B, C, H, W); the gradients of image b at its own pixel (positions,
// normals (B, H, W, 3), depth (B, H, W), settings (B, H, W, acc.settings()), and where camera is not null
// d L / d fx, fy, cx, cy (B, H, W, 4)) and scattered to its taps (tap_positions (B, H, W, 3), tap_inverse
// (B, H, W), atomically). Its replay's scratch is sized for kFetches fetches a slice (replayed_fetches: where the
// call's need more, the pixel's position gradient is NaN): the driver reserves a thread's local memory for every
// thread the GPU can hold, so a tape for the most steps would cost gigabytes of device memory on every call
template <class Acc, int kFetches>
TAO_FN void grad_pixel(const WalkSettings& cfg, const Acc& acc, const Frame& fr, const float* grad,
                       const int64_t* record, float* positions, float* normals, float* depth, float* setting,
                       float* tap_positions, float* tap_inverse, float* camera, int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  const int C = acc.channels();
  const float* upstream[8];
  for (int c = 0; c < C; ++c) upstream[c] = grad + (b * C + c) * plane;
  Targets t{positions + 3 * b * plane, normals + 3 * b * plane, depth + b * plane,
            setting + acc.settings() * b * plane, tap_positions + 3 * b * plane, tap_inverse + b * plane};
  read_position_buffer(t, cfg, fr, b);
  t.camera = camera ? camera + 4 * b * plane : nullptr;
  t.settings = acc.settings();
  float take_steps[2 * kGradMaxSteps];
  TapedTake<float> taken[kFetches];
  constexpr int32_t capacity = tape_capacity(kFetches);
  float partials[Tape<float>::partials_size(capacity)], adjoints[Tape<float>::adjoints_size(capacity)];
  int32_t parents[Tape<float>::parents_size(capacity)];
  Tape<float> tape(partials, parents, adjoints, capacity);
  const int64_t per_image = RecordsTakes<Acc>::value ? plane * take_words(cfg) : 0;
  if (replayed_fetches(acc, cfg) > kFetches)
    tape.overflow = true;  // (the host chose a kernel too small for the call)
  else
    grad_block<float>(cfg, fr.image(b), acc, row, u, 1, upstream, C, record + b * per_image, t, take_steps, taken,
                      kFetches, tape);
  if (tape.overflow) {  // (NaN rather than a silently partial gradient)
    const float nan = bits_float(0x7fc00000u);
    for (int c = 0; c < 3; ++c) t.positions[3 * (row * fr.W + u) + c] = nan;
  }
}

// Pixel p's soft backward (a CUDA thread): grad (B, 1, H, W); its own gradients (positions, normals, depth,
// d L / d the thickness' offset, scale and growth: thickness (B, H, W, 3), and where camera d L / d the intrinsics:
// (B, H, W, 4)) and its steps' taps' (positions, inverse depth, the layer's where the model reads one;
// atomically) as grad_pixel's
template <class Acc>
TAO_FN void soft_grad_pixel(const WalkSettings& cfg, const Acc& acc, const Frame& fr,
                            const float* grad, float* positions, float* normals, float* depth, float* thickness,
                            float* tap_positions, float* tap_inverse, float* tap_layer, float* tap_normals,
                            float* tap_light, float* camera, int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  Targets t{positions + 3 * b * plane, normals + 3 * b * plane, depth + b * plane, thickness + 3 * b * plane,
            tap_positions + 3 * b * plane, tap_inverse + b * plane, tap_layer ? tap_layer + b * plane : nullptr,
            tap_normals ? tap_normals + 3 * b * plane : nullptr, tap_light ? tap_light + 3 * b * plane : nullptr,
            camera ? camera + 4 * b * plane : nullptr, 3};
  read_position_buffer(t, cfg, fr, b);
  soft_grad_block<float>(cfg, fr.image(b), acc, row, u, 1, grad + b * acc.channels() * plane, t);
}

// Pixel p's exact-union backward (a CUDA thread): grad (B, 1, H, W); its own gradients (positions, normals,
// depth; where camera, d L / d the intrinsics (B, H, W, 4)) and its intervals' taps' (positions, inverse depth,
// the thickness layer's where it is read; atomically)
TAO_FN void exact_grad_pixel(const WalkSettings& cfg, const ExactAccumulator& acc, const Frame& fr, const float* grad,
                             float* positions, float* normals, float* depth, float* tap_positions, float* tap_inverse,
                             float* tap_layer, float* camera, int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  Targets t{positions + 3 * b * plane, normals + 3 * b * plane, depth + b * plane, nullptr,
            tap_positions + 3 * b * plane, tap_inverse + b * plane, tap_layer ? tap_layer + b * plane : nullptr,
            nullptr, nullptr, camera ? camera + 4 * b * plane : nullptr};
  read_position_buffer(t, cfg, fr, b);
  exact_grad_block<float>(cfg, fr.image(b), acc, row, u, 1, grad + b * plane, t);
}

// Pixel p's hard sector forward with its record (a CUDA thread): its outputs into out (B, C, H, W), its slices'
// occupied sectors into record (B, H, W, slices)
template <class Acc>
TAO_FN void hard_record_pixel(const WalkSettings& cfg, const Acc& acc, const Frame& fr, float* out, int32_t* record,
                              int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  float values[8];
  hard_record_block<float>(cfg, fr.image(b), acc, row, u, 1, record + b * plane * cfg.slices, values);
  const int C = acc.channels();
  for (int c = 0; c < C; ++c) out[((b * C + c) * fr.H + row) * fr.W + u] = values[c];
}

// Pixel p's hard sector backward (a CUDA thread): grad (B, C, H, W), record hard_record_pixel's; its own gradients
// (positions, normals, depth) and, with indirect light, its steps' taps' (positions, inverse depth, the senders'
// normals and light; atomically); where camera, its d L / d the intrinsics (B, H, W, 4: indirect light's)
template <class Acc>
TAO_FN void hard_grad_pixel(const WalkSettings& cfg, const Acc& acc, const Frame& fr, const float* grad,
                            const int32_t* record, float* positions, float* normals, float* depth, float* tap_positions,
                            float* tap_inverse, float* tap_normals, float* tap_light, float* camera, int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  Targets t{positions + 3 * b * plane, normals + 3 * b * plane, depth + b * plane, nullptr,
            tap_positions + 3 * b * plane, tap_inverse + b * plane, nullptr,
            acc.indirect ? tap_normals + 3 * b * plane : nullptr, acc.indirect ? tap_light + 3 * b * plane : nullptr,
            camera ? camera + 4 * b * plane : nullptr};
  read_position_buffer(t, cfg, fr, b);
  hard_grad_block<float>(cfg, fr.image(b), acc, row, u, 1, grad + b * acc.channels() * plane,
                         record + b * plane * cfg.slices, t);
}

}  // namespace tao
