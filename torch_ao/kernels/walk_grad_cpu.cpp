// The backward of the one walk (torch_ao_kernels::walk_backward) for the horizon accumulators of
// horizon.h (GTAO's three variants, HBAO), any fetch, either border. Per slice:
//  1. the forward (torch_ao_kernels::walk_record: walk.h's walk_slice in plain lanes with the Takes visitor)
//     records, per pixel and side, the steps that changed the accumulator's state (its "takes", a bit per
//     step; every valid step where acc.blends_every_sample(): UE4's thickness blend): a step that leaves the
//     state as it was is the identity, so only the takes carry gradients. Where a take replaces the state
//     (acc.replaces(): GTAO's exact minimum, HBAO's highest rise), only each side's last take is kept.
//  2. the backward replays the slice in dual lanes (lanes_dual.h) through those takes alone (each lane its
//     own step, step_distance in lanes): begin_slice, the takes' samples and steps, end_slice. Tangents 0..6
//     are the pixel's own position, normal and depth (seeded in Pixels), 7 the accumulator's setting
//     (seed_setting: GTAO's falloff or thickness, HBAO's angle bias), which give its outputs' derivatives
//     with respect to them, the samples' screen positions and bilinear weights included (Pixels and Slice
//     in those 8 alone, widened); before every take the state's S components and the sample's delta get
//     fresh tangents, so that the step's local Jacobians d state' / d state (S x S) and d state' / d delta
//     (S x 3) come out of it.
//  3. the outputs' derivatives with respect to the final state, swept back through the takes' Jacobians,
//     give each take's d loss / d delta, chained to its taps: for a bilinear fetch delta = pos - P with
//     pos = q / (sum_k w_k t_k), so d pos / d t_k = pos pos_z w_k; a nearest fetch reads the tap's
//     position itself. The edge-aware fetch is the bilinear one whose taps across a depth edge are four
//     copies of the nearest: their weights sum to 1 on that texel, and the interpolation's d / d (fu, fv)
//     is 0 (the cell flags, like every comparison, have no derivative). Scattered into per-thread images,
//     summed at the end.
// Ties: a step whose candidate equals the state leaves it unchanged, so the earlier sample keeps the
// gradient (the tensor path's torch.minimum splits it between them; tied samples of one texel give both
// the same total).
// The soft / straight-through bitmask walk's backward (torch_ao_kernels::soft_backward) is soft.h's
// SoftAdjoint over the same walk: value lanes with the pixel and its slices in dual lanes (tangents 0..6),
// each step's d / d delta scattered to its taps as above.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/select.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <string>
#include <tuple>
#include <vector>

#include "lanes_simd.h"
#include "lanes_dual.h"
#include "frame_cpu.h"
#include "packed.h"
#include "rows_cpu.h"

namespace {

using namespace tao;

// tangents of the pixel's own P (3), N (3), depth (1) (seed_pixel) and of the accumulator's setting
// (seed_setting: the horizon accumulators')
constexpr int kPixel = 7, kOwn = kPixel + 1;

inline bool mask_lane(bool m, int) { return m; }
inline bool mask_lane(const Vec& m, int l) { return lane_on(m, l); }
// a lane mask as bits (lane l: bit l)
inline uint32_t lane_bits(bool m) { return m ? 1u : 0u; }
inline uint32_t lane_bits(const Vec& m) { return ~uint32_t(m.zero_mask()) & ((1u << Vec::size()) - 1u); }
inline void store_lanes(uint32_t x, int32_t* out) { out[0] = int32_t(x); }
inline void store_lanes(const IVec& x, int32_t* out) { x.store(out); }

// An accumulator's state as its S components (its State is an aggregate of lane values)
template <class Acc, class F> constexpr int state_size() {
  static_assert(sizeof(typename Acc::template State<F>) % sizeof(F) == 0, "State: lane values only");
  return int(sizeof(typename Acc::template State<F>) / sizeof(F));
}
template <class State, class F> F* components(State& s) { return reinterpret_cast<F*>(&s); }

// Where the gradients go: the pixel's own (written once per pixel) and the taps' (this thread's images)
struct Targets {
  float *positions, *normals, *depth, *setting;  // own: (H, W, 3), (H, W, 3), (H, W), (H, W) of image b
  float *tap_positions, *tap_inverse;  // scattered: (H, W, 3), (H, W) of image b, this thread's
};

// The record of a slice (the forward's visitor): per side and lane the steps that changed the state (the
// last one alone where a take replaces the state), as bits: step j is bit j % 64 of word j / 64
template <class B, class Acc> struct Takes {
  static constexpr bool kBefore = true;
  using State = typename Acc::template State<B>;
  static constexpr int L = LaneTraits<B>::L;
  static constexpr int S = state_size<Acc, B>();
  const Acc& acc;
  const typename LaneTraits<B>::M& live;
  int64_t words;
  uint64_t* bits;  // [side][lane][word]

  Takes(const Acc& a, const typename LaneTraits<B>::M& l, int64_t w, uint64_t* scratch)
      : acc(a), live(l), words(w), bits(scratch) {
    std::fill(bits, bits + 2 * L * words, uint64_t(0));
  }
  uint64_t* of(int k, int l) { return bits + (k * L + l) * words; }

  void operator()(int side, int64_t j, const Sample<B>& sample, const State& before, const State& after) {
    auto changed = acc.blends_every_sample() ? sample.valid : B(0.0f) > B(1.0f);
    const B *x = components<const State, const B>(before), *y = components<const State, const B>(after);
    for (int m = 0; m < S; ++m) changed = lor(changed, lnot(x[m] == y[m]));  // (NaN: changed)
    const int k = side > 0 ? 0 : 1;
    for (uint32_t lanes = lane_bits(land(changed, live)); lanes; lanes &= lanes - 1) {
      uint64_t* b = of(k, __builtin_ctz(lanes));
      if (acc.replaces()) std::fill(b, b + words, uint64_t(0));
      b[j / 64] |= uint64_t(1) << (j % 64);
    }
  }
};

// The words of a record per (pixel, slice, side)
inline int64_t take_words(const WalkSettings& cfg) { return (cfg.steps + 63) / 64; }

// One take replayed: its step's Jacobians and its fetch (values only)
template <class B, int S> struct Take {
  using I = typename LaneTraits<B>::I;
  B along_state[S][S], along_delta[S][3];  // d state'[m] / d state[m'], d state'[m] / d delta[c]
  I index[4];
  B fu, fv, pos[3];
  typename LaneTraits<B>::M has;
};

// d L / d delta of a sample (g_delta) scattered to its fetch's taps, on the lanes in `on` of the first n: a
// bilinear fetch's four inverse depths (d pos / d t_k = pos pos_z w_k, pos the fetched position, w_k the
// weights of fu, fv), a nearest fetch's position (index[0])
template <class B>
void scatter_taps(bool bilinear, int n, const Targets& t, const B* g_delta, const B* pos, const B& fu, const B& fv,
                  const typename LaneTraits<B>::I* index, const typename LaneTraits<B>::M& on) {
  if (!any(on)) return;
  constexpr int L = LaneTraits<B>::L;
  float gl[3][L], pl[3][L], ful[L], fvl[L];
  int32_t il[4][L];
  for (int c = 0; c < 3; ++c) to_lanes(g_delta[c], gl[c]), to_lanes(pos[c], pl[c]);
  to_lanes(fu, ful), to_lanes(fv, fvl);
  for (int i = 0; i < 4; ++i) store_lanes(index[i], il[i]);
  for (int l = 0; l < n; ++l) {
    if (!mask_lane(on, l)) continue;
    if (bilinear) {
      const float u = ful[l], v = fvl[l];
      const float weight[4] = {(1.0f - u) * (1.0f - v), u * (1.0f - v), (1.0f - u) * v, u * v};
      const float along = (gl[0][l] * pl[0][l] + gl[1][l] * pl[1][l] + gl[2][l] * pl[2][l]) * pl[2][l];
      for (int i = 0; i < 4; ++i) t.tap_inverse[il[i][l]] += along * weight[i];
    } else {
      for (int c = 0; c < 3; ++c) t.tap_positions[3 * il[0][l] + c] += gl[c][l];
    }
  }
}

// A slice's record read back (the forward's Takes, image b's from record): per side, the lanes' takes in
// order as each lane's step j, step[k][q][l], count[k][l] of them
template <int L> struct Replay {
  std::vector<float>& step;  // [side][take][lane]
  int64_t steps;
  int count[2][L];

  Replay(std::vector<float>& scratch, int64_t n) : step(scratch), steps(n) {}
  float* at(int k, int q) { return step.data() + (k * steps + q) * L; }
  int most(int k) const { return *std::max_element(count[k], count[k] + L); }
  // the record of slice s of the n pixels from p (words per side and pixel)
  void read(const int64_t* record, int64_t p, int n, int64_t slices, int64_t s, int64_t words) {
    for (int k = 0; k < 2; ++k) {
      for (int l = 0; l < L; ++l) {
        int q = 0;
        if (l < n) {
          const auto* b = reinterpret_cast<const uint64_t*>(record) + (((p + l) * slices + s) * 2 + k) * words;
          for (int64_t w = 0; w < words; ++w)
            for (uint64_t x = b[w]; x; x &= x - 1) at(k, q++)[l] = float(64 * w + __builtin_ctzll(x));
        }
        count[k][l] = q;
      }
    }
  }
};

template <class B, class Acc>
void grad_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row, int64_t u0, int n,
                const float* const* upstream, int C, const int64_t* record, const Targets& t,
                std::vector<float>& take_steps, std::vector<Take<B, state_size<Acc, B>()>>& replayed) {
  constexpr int S = state_size<Acc, B>(), kState = kOwn, kDelta = kOwn + S, N = kDelta + 3;
  constexpr int L = LaneTraits<B>::L;
  using D = Dual<B, N>;
  using StateD = typename Acc::template State<D>;
  B g[8];
  {
    float lane[L];
    bool none = true;
    for (int c = 0; c < C; ++c) {
      for (int l = 0; l < L; ++l) {
        lane[l] = l < n ? upstream[c][row * img.W + u0 + l] : 0.0f;
        none = none && lane[l] == 0.0f;
      }
      g[c] = from_lanes(lane, B(0.0f));
    }
    if (none) return;  // (no gradient flows: the outputs' zeros stand)
  }
  // the pixel and its slices in the own tangents alone, widened for the takes' state and delta tangents
  using Own = Dual<B, kOwn>;
  const auto wide = [](const Own& x) { return widen<N>(x); };
  const Pixels<Own> px_own(cfg, img, row, u0, n);
  if (!any(px_own.live)) return;
  const Pixels<D> pxd(px_own, wide);
  B own[kOwn];
  for (int k = 0; k < kOwn; ++k) own[k] = B(0.0f);
  // fresh tangents on the state's components (and none on a delta)
  auto reseed = [&](StateD& st) {
    D* x = components<StateD, D>(st);
    for (int m = 0; m < S; ++m) {
      for (int q = kState; q < N; ++q) x[m].d[q] = B(0.0f);
      x[m].d[kState + m] = B(1.0f);
    }
  };
  Replay<L> takes(take_steps, cfg.steps);
  for (int64_t s = 0; s < cfg.slices; ++s) {
    takes.read(record, row * img.W + u0, n, cfg.slices, s, take_words(cfg));
    const Slice<D> sl(Slice<Own>(cfg, img, px_own, s), wide);
    StateD state = acc.begin_slice(pxd, sl);
    replayed.clear();
    for (int side = 1; side >= (cfg.full_circle ? 1 : -1); side -= 2) {
      const int k = side > 0 ? 0 : 1;
      const D xi = step_noise(cfg, pxd, sl, side);
      for (int q = 0, most = takes.most(k); q < most; ++q) {
        float has_lane[L];
        for (int l = 0; l < L; ++l) has_lane[l] = q < takes.count[k][l] ? 1.0f : 0.0f;
        const auto has = from_lanes(has_lane, B(0.0f)) > B(0.5f);
        const D j(select(has, from_lanes(takes.at(k, q), B(0.0f)), B(0.0f)));
        Sample<D> smp(cfg, img, pxd, sl, float(side), step_distance(cfg, sl, xi, j));
        smp.valid = land(smp.valid, has);  // (a lane without this take: an invalid sample, the identity)
        for (int c = 0; c < 3; ++c) smp.delta[c].d[kDelta + c] = B(1.0f);
        reseed(state);
        acc.step(state, side, pxd, sl, smp);
        Take<B, S> take;
        const D* x = components<StateD, D>(state);
        for (int m = 0; m < S; ++m) {
          for (int q2 = 0; q2 < S; ++q2) take.along_state[m][q2] = x[m].d[kState + q2];
          for (int c = 0; c < 3; ++c) take.along_delta[m][c] = x[m].d[kDelta + c];
        }
        for (int i = 0; i < 4; ++i) take.index[i] = smp.index[i];
        take.fu = smp.fu.v, take.fv = smp.fv.v, take.has = land(has, pxd.live);
        for (int c = 0; c < 3; ++c) take.pos[c] = smp.delta[c].v + pxd.P[c].v;
        replayed.push_back(take);
      }
    }
    reseed(state);  // tangents kState.. now probe the final state
    typename Acc::template Sums<D> part;
    acc.end_slice(state, pxd, sl, part);
    D outs[8];
    acc.finish(part, pxd, outs);  // linear in the sums: the slice's share of the outputs
    for (int k = 0; k < kOwn; ++k)
      for (int c = 0; c < C; ++c) own[k] = own[k] + g[c] * outs[c].d[k];
    B adjoint[S];  // d loss / d state after the take being swept
    for (int m = 0; m < S; ++m) {
      adjoint[m] = B(0.0f);
      for (int c = 0; c < C; ++c) adjoint[m] = adjoint[m] + g[c] * outs[c].d[kState + m];
    }
    for (auto take = replayed.rbegin(); take != replayed.rend(); ++take) {
      B gd[3];
      for (int c = 0; c < 3; ++c) {
        gd[c] = B(0.0f);
        for (int m = 0; m < S; ++m) gd[c] = gd[c] + adjoint[m] * take->along_delta[m][c];
      }
      B before[S];
      for (int q = 0; q < S; ++q) {
        before[q] = B(0.0f);
        for (int m = 0; m < S; ++m) before[q] = before[q] + adjoint[m] * take->along_state[m][q];
      }
      std::copy(before, before + S, adjoint);
      scatter_taps(cfg.bilinear, n, t, gd, take->pos, take->fu, take->fv, take->index, take->has);
    }
  }
  float ol[kOwn][L];
  for (int k = 0; k < kOwn; ++k) to_lanes(own[k], ol[k]);
  for (int l = 0; l < n; ++l) {
    const int64_t p = row * img.W + u0 + l;
    for (int c = 0; c < 3; ++c) t.positions[3 * p + c] = ol[c][l], t.normals[3 * p + c] = ol[3 + c][l];
    t.depth[p] = ol[6][l], t.setting[p] = ol[7][l];
  }
}

void check_input(const at::Tensor& x, const char* name) {
  TORCH_CHECK(x.scalar_type() == at::kFloat && x.is_contiguous() && x.device().is_cpu(), name,
              ": expected contiguous float32 on the CPU");
}

// Where a backward's gradients go: the pixels' own (positions, normals, depth, the accumulator's setting)
// and the taps' (per thread)
struct Gradients {
  at::Tensor positions, normals, depth, setting, tap_positions, tap_inverse;

  Gradients(const at::Tensor& like, int64_t B, int64_t H, int64_t W) {
    const int64_t threads = at::get_num_threads();
    positions = at::zeros({B, H, W, 3}, like.options()), normals = at::zeros({B, H, W, 3}, like.options());
    depth = at::zeros({B, H, W}, like.options()), setting = at::zeros({B, H, W}, like.options());
    tap_positions = at::zeros({threads, B, H, W, 3}, like.options());
    tap_inverse = at::zeros({threads, B, H, W}, like.options());
  }
  Targets targets(int64_t b, int64_t B, int64_t plane, int64_t thread) {
    return Targets{positions.data_ptr<float>() + 3 * b * plane, normals.data_ptr<float>() + 3 * b * plane,
                   depth.data_ptr<float>() + b * plane, setting.data_ptr<float>() + b * plane,
                   tap_positions.data_ptr<float>() + (thread * B + b) * 3 * plane,
                   tap_inverse.data_ptr<float>() + (thread * B + b) * plane};
  }
  // the threads' tap images summed: the taps' positions into the pixels' own; the inverse depth's image
  at::Tensor reduce() {
    float *pos = positions.data_ptr<float>(), *tp = tap_positions.data_ptr<float>(), *ti = tap_inverse.data_ptr<float>();
    const int64_t threads = tap_positions.size(0), n_pos = positions.numel(), n_inv = depth.numel();
    for (int64_t k = 1; k < threads; ++k) {
      for (int64_t q = 0; q < n_pos; ++q) tp[q] += tp[k * n_pos + q];
      for (int64_t q = 0; q < n_inv; ++q) ti[q] += ti[k * n_inv + q];
    }
    for (int64_t q = 0; q < n_pos; ++q) pos[q] += tp[q];
    return tap_inverse[0];
  }
};

// A backward's packed settings: n_ints and n_floats of the accumulator's after the walk's
void check_settings(const at::Tensor& ints, const at::Tensor& floats, int64_t n_ints, int64_t n_floats,
                    const char* name) {
  check_input(floats, "floats");
  TORCH_CHECK(ints.scalar_type() == at::kLong && ints.is_contiguous() && ints.numel() == kAccInts + n_ints &&
                  floats.numel() == kAccFloats + n_floats, "ints, floats: expected ", name, "'s packed settings");
}

// The upstream gradient: (B, C, H, W) of positions' B, H, W
void check_grad(const at::Tensor& grad, const at::Tensor& positions, int C) {
  check_input(grad, "grad");
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2);
  TORCH_CHECK(grad.dim() == 4 && grad.size(0) == B && grad.size(1) == C && grad.size(2) == H && grad.size(3) == W,
              "grad: expected (B, ", C, ", H, W)");
}

// The walk of every row's blocks (SIMD or scalar lanes) with the Takes visitor: the outputs (B, C, H, W), as
// the walk's, and the record (B, H, W, slices, 2, take_words) of every pixel's takes
template <class Acc>
void record_frame(const WalkSettings& cfg, const Acc& acc, const Frame& fr, float* dst, int64_t* record, bool scalar) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t H = fr.H, W = fr.W, words = take_words(cfg);
  const int C = acc.channels();
  torch_ao_rows::for_each_block<L>(fr.B, H, W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n, auto simd) {
    using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
    constexpr int LL = LaneTraits<Lane>::L;
    thread_local std::vector<uint64_t> bits;
    bits.resize(size_t(2 * LL * words));
    const Image img = fr.image(b);
    const Pixels<Lane> px(cfg, img, row, u0, n);
    typename Acc::template Sums<Lane> sums;
    auto* out = reinterpret_cast<uint64_t*>(record) + ((b * H + row) * W + u0) * cfg.slices * 2 * words;
    for (int64_t s = 0; s < cfg.slices; ++s) {
      Takes<Lane, Acc> takes(acc, px.live, words, bits.data());
      if (any(px.live)) {
        const Slice<Lane> sl(cfg, img, px, s);
        typename Acc::template State<Lane> state = acc.begin_slice(px, sl);
        walk_slice(cfg, img, acc, px, sl, state, takes);
        acc.end_slice(state, px, sl, sums);
      }
      for (int l = 0; l < n; ++l)
        for (int k = 0; k < 2; ++k) std::copy(takes.of(k, l), takes.of(k, l) + words, out + ((l * cfg.slices + s) * 2 + k) * words);
    }
    Lane values[8];
    acc.finish(sums, px, values);
    alignas(64) float lanes[LL];
    for (int c = 0; c < C; ++c) {
      to_lanes(values[c], lanes);
      std::copy(lanes, lanes + n, dst + ((b * C + c) * H + row) * W + u0);
    }
  });
}

// The gradients of every row's blocks: SIMD or scalar lanes, the forward's record of the takes
template <class Acc>
void grad_frame(const WalkSettings& cfg, const Acc& acc, const Frame& fr, const float* gp, int C, const int64_t* record,
                Gradients& out, bool scalar) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t B = fr.B, plane = fr.H * fr.W, per_image = plane * cfg.slices * 2 * take_words(cfg);
  torch_ao_rows::for_each_block<L>(B, fr.H, fr.W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n, auto simd) {
    using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
    thread_local std::vector<float> take_steps;
    thread_local std::vector<Take<Lane, state_size<Acc, Lane>()>> replayed;
    take_steps.resize(size_t(2 * cfg.steps * LaneTraits<Lane>::L));
    const float* upstream[8];
    for (int c = 0; c < C; ++c) upstream[c] = gp + (b * C + c) * plane;
    grad_block<Lane>(cfg, fr.image(b), acc, row, u0, n, upstream, C, record + b * per_image,
                     out.targets(b, B, plane, at::get_thread_num()), take_steps, replayed);
  });
}

// The horizon accumulator `name` ("gtao", "hbao") of the packed settings, to fn
template <class Fn> void with_horizon(const std::string& name, const int64_t* i, const float* f, const Fn& fn) {
  if (name == "gtao") {
    TORCH_CHECK(i[kAccInts] >= 0 && i[kAccInts] <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
    fn(unpack_gtao(i, f));
  } else {
    fn(unpack_hbao(i, f));
  }
}

// The edge-aware fetch reads the cell flags (walk.h's Image::cells)
void check_cells(const WalkSettings& cfg, const Frame& fr) {
  TORCH_CHECK(!cfg.edge_aware || fr.cells, "cells: the edge-aware fetch needs the cell flags (B, H, W)");
}

// The walk's settings of a horizon accumulator's call (walk_record, walk_backward)
WalkSettings horizon_settings(const std::string& name, const at::Tensor& ints, const at::Tensor& floats) {
  TORCH_CHECK(name == "gtao" || name == "hbao", "accumulator: the backward covers gtao and hbao, got ", name);
  check_settings(ints, floats, 3, name == "gtao" ? 3 : 2, name.c_str());
  const WalkSettings cfg = unpack_walk(ints.data_ptr<int64_t>(), floats.data_ptr<float>());
  return cfg;
}

// torch_ao_kernels::walk_record: the walk (torch_ao_kernels::walk's outputs (B, channels, H, W)) of a horizon
// accumulator ("gtao", "hbao"), and the record of its takes (B, H, W, slices, 2, words) int64, for
// walk_backward
std::tuple<at::Tensor, at::Tensor> walk_record(c10::string_view accumulator, const at::Tensor& positions,
                                               const at::Tensor& normals, const at::Tensor& inverse_depth,
                                               const at::Tensor& depth, const at::Tensor& valid,
                                               const at::Tensor& intrinsics, const at::Tensor& cells,
                                               const at::Tensor& ints, const at::Tensor& floats, int64_t channels,
                                               bool scalar) {
  const std::string name(accumulator);
  const WalkSettings cfg = horizon_settings(name, ints, floats);
  const at::Tensor none = at::empty({0}, positions.options());
  const Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, cells, none);
  check_cells(cfg, fr);
  at::Tensor out = at::empty({fr.B, channels, fr.H, fr.W}, positions.options());
  at::Tensor record = at::empty({fr.B, fr.H, fr.W, cfg.slices, 2, take_words(cfg)}, ints.options());
  with_horizon(name, ints.data_ptr<int64_t>(), floats.data_ptr<float>(), [&](const auto& acc) {
    TORCH_CHECK(acc.channels() == channels, "channels: expected ", acc.channels());
    record_frame(cfg, acc, fr, out.data_ptr<float>(), record.data_ptr<int64_t>(), scalar);
  });
  return {out, record};
}

// torch_ao_kernels::walk_backward: the gradients of sum(grad * walk(...)) with respect to the walk's
// positions, normals (B, H, W, 3), inverse depth and depth (B, H, W), and per pixel with respect to the
// accumulator's setting (B, H, W); grad (B, C, H, W); accumulator "gtao" or "hbao" with walk()'s packed
// settings; cells: the edge-aware fetch's cell flags (B, H, W), else empty; record: walk_record's of the
// same call
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> walk_backward(
    c10::string_view accumulator, const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals,
    const at::Tensor& inverse_depth, const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
    const at::Tensor& cells, const at::Tensor& ints, const at::Tensor& floats, const at::Tensor& record, bool scalar) {
  const std::string name(accumulator);
  const WalkSettings cfg = horizon_settings(name, ints, floats);
  const at::Tensor none = at::empty({0}, positions.options());
  const Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, cells, none);
  check_cells(cfg, fr);
  TORCH_CHECK(record.scalar_type() == at::kLong && record.is_contiguous() &&
                  record.sizes() == at::IntArrayRef({fr.B, fr.H, fr.W, cfg.slices, 2, take_words(cfg)}),
              "record: expected walk_record's (B, H, W, slices, 2, words) of the same call");
  Gradients out(positions, fr.B, fr.H, fr.W);
  with_horizon(name, ints.data_ptr<int64_t>(), floats.data_ptr<float>(), [&](const auto& acc) {
    check_grad(grad, positions, acc.channels());
    grad_frame(cfg, acc, fr, grad.data_ptr<float>(), acc.channels(), record.data_ptr<int64_t>(), out, scalar);
  });
  at::Tensor g_inv = out.reduce();
  return {out.positions, out.normals, g_inv, out.depth, out.setting};
}

// The soft backward's sink (soft.h's end_slice_adjoint): a step's d L / d delta to its kept fetch's taps
template <class B> struct TapSink {
  bool bilinear;
  int n;
  const Targets& t;

  template <class State> void scatter(const B* g_delta, const State& st, int m, const typename LaneTraits<B>::M& on) {
    const B pos[3] = {st.pos[0][m], st.pos[1][m], st.pos[2][m]};
    const typename LaneTraits<B>::I index[4] = {st.index[0][m], st.index[1][m], st.index[2][m], st.index[3][m]};
    scatter_taps(bilinear, n, t, g_delta, pos, st.fu[m], st.fv[m], index, on);
  }
};

// The soft backward of the n <= L pixels of a row from u0: the walk with SoftAdjoint's slices (the pixels and
// slices also in dual lanes: tangents on the pixel's own P, N, depth); the pixel's own gradients and
// d L / d thickness written per pixel
template <class B>
void soft_grad_block(const WalkSettings& cfg, const Image& img, const SoftAccumulator<true, true>& acc, int64_t row,
                     int64_t u0, int n, const float* upstream, const Targets& t) {
  using D = Dual<B, kPixel>;
  constexpr int L = LaneTraits<B>::L;
  float lane[L];
  for (int l = 0; l < L; ++l) lane[l] = l < n ? upstream[row * img.W + u0 + l] : 0.0f;
  const B g = from_lanes(lane, B(0.0f));
  TapSink<B> sink{cfg.bilinear, n, t};
  const Pixels<D> pd(cfg, img, row, u0, n);
  const SoftAdjoint<B, D, TapSink<B>> adjoint{acc, img, pd, g / acc.denominator<B>(img, row, u0, n), sink};
  B outs[8];
  walk_block(cfg, img, adjoint, row, u0, n, outs);
  float ol[8][L];
  for (int k = 0; k < 8; ++k) to_lanes(g * outs[k], ol[k]);
  for (int l = 0; l < n; ++l) {
    const int64_t p = row * img.W + u0 + l;
    for (int c = 0; c < 3; ++c) t.positions[3 * p + c] = ol[c][l], t.normals[3 * p + c] = ol[3 + c][l];
    t.depth[p] = ol[6][l];
    t.setting[p] = ol[7][l];  // d L / d thickness
  }
}

// torch_ao_kernels::soft_backward: the gradients of sum(grad * visibility) of the soft / straight-through
// walk ("soft"'s packed settings) with respect to its positions, normals (B, H, W, 3), inverse depth and
// depth (B, H, W), and each pixel's share of the thickness' (B, H, W); grad (B, 1, H, W); cells: the
// edge-aware fetch's cell flags (B, H, W), else empty
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> soft_backward(
    const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
    const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& cells,
    const at::Tensor& ints, const at::Tensor& floats, bool scalar) {
  const at::Tensor none = at::empty({0}, positions.options());
  const Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, cells, none);
  check_settings(ints, floats, 3, 3, "soft");
  check_grad(grad, positions, 1);
  const int64_t* i = ints.data_ptr<int64_t>();
  const float* f = floats.data_ptr<float>();
  const WalkSettings cfg = unpack_walk(i, f);
  check_cells(cfg, fr);
  TORCH_CHECK(f[kAccFloats + 2] > 0, "tau: expected > 0");
  TORCH_CHECK(cfg.steps <= kSoftMaxSteps / 2, "steps: the soft union holds at most ", kSoftMaxSteps / 2, " per side");
  TORCH_CHECK(cfg.placement == Steps::power && !cfg.full_circle, "soft_backward: the power step placement, one half circle");
  const SoftAccumulator<true, true> acc = unpack_soft<true, true>(i, f);
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2), plane = H * W;
  Gradients out(positions, B, H, W);
  const float* gp = grad.data_ptr<float>();
  constexpr int L = LaneTraits<Vec>::L;
  torch_ao_rows::for_each_block<L>(B, H, W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n, auto simd) {
    using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
    soft_grad_block<Lane>(cfg, fr.image(b), acc, row, u0, n, gp + b * plane, out.targets(b, B, plane, at::get_thread_num()));
  });
  at::Tensor g_inv = out.reduce();
  return {out.positions, out.normals, g_inv, out.depth, out.setting};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("walk_record(str accumulator, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor cells, Tensor ints, Tensor floats, int channels, bool scalar) "
        "-> (Tensor, Tensor)");
  m.impl("walk_record", c10::DispatchKey::CPU, TORCH_FN(walk_record));
  m.def("walk_backward(str accumulator, Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, "
        "Tensor depth, Tensor valid, Tensor intrinsics, Tensor cells, Tensor ints, Tensor floats, Tensor record, "
        "bool scalar) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("walk_backward", c10::DispatchKey::CPU, TORCH_FN(walk_backward));
  m.def("soft_backward(Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor cells, Tensor ints, Tensor floats, bool scalar) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("soft_backward", c10::DispatchKey::CPU, TORCH_FN(soft_backward));
}
