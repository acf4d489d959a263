// The backward of the one walk (torch_ao_kernels::walk_backward) for the horizon accumulators of
// horizon.h (GTAO's three variants, HBAO), any fetch but the edge-aware one, either border. Per slice:
//  1. the plain walk (walk.h's walk_slice in plain lanes) records, per lane and side, the steps that
//     changed the accumulator's state (its "takes"; every valid step where acc.blends_every_sample(): UE4's
//     thickness blend): a step that leaves the state as it was is the identity, so only the takes carry
//     gradients. Where a take replaces the state (acc.replaces(): GTAO's
//     exact minimum, HBAO's highest rise), only each side's last take is kept.
//  2. the slice is replayed in dual lanes (lanes_dual.h) through those takes alone (each lane its own step,
//     step_distance in lanes): begin_slice, the takes' samples and steps, end_slice. Tangents 0..6 are the
//     pixel's own position, normal and depth (seeded in Pixels), 7 the accumulator's setting (seed_setting:
//     GTAO's falloff or thickness, HBAO's angle bias), which give its outputs' derivatives with respect to them, the samples' screen positions and bilinear weights included; before every take the
//     state's S components and the sample's delta get fresh tangents, so that the step's local Jacobians
//     d state' / d state (S x S) and d state' / d delta (S x 3) come out of it.
//  3. the outputs' derivatives with respect to the final state, swept back through the takes' Jacobians,
//     give each take's d loss / d delta, chained to its taps: for a bilinear fetch delta = pos - P with
//     pos = q / (sum_k w_k t_k), so d pos / d t_k = pos pos_z w_k; a nearest fetch reads the tap's
//     position itself. Scattered into per-thread images, summed at the end.
// Ties: a step whose candidate equals the state leaves it unchanged, so the earlier sample keeps the
// gradient (the tensor path's torch.minimum splits it between them; tied samples of one texel give both
// the same total).
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

// tangents of the pixel's own P (3), N (3), depth (1) and of the accumulator's setting (seed_setting)
constexpr int kOwn = 8;

inline bool mask_lane(bool m, int) { return m; }
inline bool mask_lane(const Vec& m, int l) { return lane_on(m, l); }
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

// Pass 1's record of a slice: per side and lane the steps that changed the state (the last one alone
// where a take replaces the state)
template <class B, class Acc> struct Takes {
  using State = typename Acc::template State<B>;
  static constexpr int L = LaneTraits<B>::L;
  static constexpr int S = state_size<Acc, B>();
  const Acc& acc;
  const typename LaneTraits<B>::M& live;
  int64_t steps;
  std::vector<float>& step;  // [side][take][lane]: the take's step j
  int count[2][L];

  Takes(const Acc& a, const typename LaneTraits<B>::M& l, int64_t n, std::vector<float>& scratch)
      : acc(a), live(l), steps(n), step(scratch) {
    for (auto& side : count) std::fill(side, side + L, 0);
  }
  int most(int k) const { return *std::max_element(count[k], count[k] + L); }
  float* at(int k, int t) { return step.data() + (k * steps + t) * L; }

  void operator()(int side, int64_t j, const Sample<B>& sample, const State& before, const State& after) {
    auto changed = acc.blends_every_sample() ? sample.valid : B(0.0f) > B(1.0f);
    const B *x = components<const State, const B>(before), *y = components<const State, const B>(after);
    for (int m = 0; m < S; ++m) changed = lor(changed, lnot(x[m] == y[m]));  // (NaN: changed)
    changed = land(changed, live);
    if (!any(changed)) return;
    const int k = side > 0 ? 0 : 1;
    for (int l = 0; l < L; ++l) {
      if (!mask_lane(changed, l)) continue;
      const int t = acc.replaces() ? 0 : count[k][l]++;
      if (acc.replaces()) count[k][l] = 1;
      at(k, t)[l] = float(j);
    }
  }
};

// One take replayed: its step's Jacobians and its fetch (values only)
template <class B, int S> struct Take {
  using I = typename LaneTraits<B>::I;
  B along_state[S][S], along_delta[S][3];  // d state'[m] / d state[m'], d state'[m] / d delta[c]
  I index[4];
  B fu, fv, pos[3];
  typename LaneTraits<B>::M has;
};

template <class B, class Acc>
void grad_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row, int64_t u0, int n,
                const float* const* upstream, int C, const Targets& t, std::vector<float>& take_steps,
                std::vector<Take<B, state_size<Acc, B>()>>& replayed) {
  constexpr int S = state_size<Acc, B>(), kState = kOwn, kDelta = kOwn + S, N = kDelta + 3;
  constexpr int L = LaneTraits<B>::L;
  using D = Dual<B, N>;
  using StateD = typename Acc::template State<D>;
  const Pixels<B> px(cfg, img, row, u0, n);
  if (!any(px.live)) return;
  const Pixels<D> pxd(cfg, img, row, u0, n);
  B g[8];
  {
    float lane[L];
    for (int c = 0; c < C; ++c) {
      for (int l = 0; l < L; ++l) lane[l] = l < n ? upstream[c][row * img.W + u0 + l] : 0.0f;
      g[c] = from_lanes(lane, B(0.0f));
    }
  }
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
  for (int64_t s = 0; s < cfg.slices; ++s) {
    Takes<B, Acc> takes(acc, px.live, cfg.steps, take_steps);
    {
      const Slice<B> sl(cfg, img, px, s);
      typename Acc::template State<B> state = acc.begin_slice(px, sl);
      walk_slice(cfg, img, acc, px, sl, state, takes);
    }
    const Slice<D> sl(cfg, img, pxd, s);
    StateD state = acc.begin_slice(pxd, sl);
    replayed.clear();
    for (int side = 1; side >= (cfg.full_circle ? 1 : -1); side -= 2) {
      const int k = side > 0 ? 0 : 1;
      for (int q = 0, most = takes.most(k); q < most; ++q) {
        float has_lane[L];
        for (int l = 0; l < L; ++l) has_lane[l] = q < takes.count[k][l] ? 1.0f : 0.0f;
        const auto has = from_lanes(has_lane, B(0.0f)) > B(0.5f);
        const D j(select(has, from_lanes(takes.at(k, q), B(0.0f)), B(0.0f)));
        Sample<D> smp(cfg, img, pxd, sl, float(side), step_distance(cfg, sl, pxd.xi, j));
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
        take.fu = smp.fu.v, take.fv = smp.fv.v, take.has = land(has, px.live);
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
      float gl[3][L], pl[3][L], ful[L], fvl[L];
      int32_t il[4][L];
      for (int c = 0; c < 3; ++c) to_lanes(gd[c], gl[c]), to_lanes(take->pos[c], pl[c]);
      to_lanes(take->fu, ful), to_lanes(take->fv, fvl);
      for (int i = 0; i < 4; ++i) store_lanes(take->index[i], il[i]);
      for (int l = 0; l < n; ++l) {
        if (!mask_lane(take->has, l)) continue;
        if (cfg.bilinear) {
          const float fu = ful[l], fv = fvl[l];
          const float weight[4] = {(1.0f - fu) * (1.0f - fv), fu * (1.0f - fv), (1.0f - fu) * fv, fu * fv};
          const float along = (gl[0][l] * pl[0][l] + gl[1][l] * pl[1][l] + gl[2][l] * pl[2][l]) * pl[2][l];
          for (int i = 0; i < 4; ++i) t.tap_inverse[il[i][l]] += along * weight[i];
        } else {
          for (int c = 0; c < 3; ++c) t.tap_positions[3 * il[0][l] + c] += gl[c][l];
        }
      }
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

// The gradients of every row's blocks: SIMD or scalar lanes, a record of the takes per row
template <class Acc>
void grad_frame(const WalkSettings& cfg, const Acc& acc, const Frame& fr, const float* gp, int C, at::Tensor& g_pos,
                at::Tensor& g_nrm, at::Tensor& g_depth, at::Tensor& g_setting, at::Tensor& tap_pos, at::Tensor& tap_inv, bool scalar) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t B = fr.B, plane = fr.H * fr.W;
  torch_ao_rows::for_each_block<L>(B, fr.H, fr.W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n, auto simd) {
    using Lane = std::conditional_t<decltype(simd)::value, Vec, float>;
    thread_local std::vector<float> take_steps;
    thread_local std::vector<Take<Lane, state_size<Acc, Lane>()>> replayed;
    take_steps.resize(size_t(2 * cfg.steps * LaneTraits<Lane>::L));
    const int64_t thread = at::get_thread_num();
    const float* upstream[8];
    for (int c = 0; c < C; ++c) upstream[c] = gp + (b * C + c) * plane;
    const Targets t{g_pos.data_ptr<float>() + 3 * b * plane, g_nrm.data_ptr<float>() + 3 * b * plane,
                    g_depth.data_ptr<float>() + b * plane, g_setting.data_ptr<float>() + b * plane,
                    tap_pos.data_ptr<float>() + (thread * B + b) * 3 * plane,
                    tap_inv.data_ptr<float>() + (thread * B + b) * plane};
    grad_block<Lane>(cfg, fr.image(b), acc, row, u0, n, upstream, C, t, take_steps, replayed);
  });
}

// torch_ao_kernels::walk_backward: the gradients of sum(grad * walk(...)) with respect to the walk's
// positions, normals (B, H, W, 3), inverse depth and depth (B, H, W), and per pixel with respect to the
// accumulator's setting (B, H, W); grad (B, C, H, W); accumulator "gtao" or "hbao" with walk()'s packed settings
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> walk_backward(
    c10::string_view accumulator, const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals,
    const at::Tensor& inverse_depth, const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
    const at::Tensor& ints, const at::Tensor& floats, bool scalar) {
  const std::string name(accumulator);
  TORCH_CHECK(name == "gtao" || name == "hbao", "accumulator: the backward covers gtao and hbao, got ", name);
  const at::Tensor none = at::empty({0}, positions.options());
  const Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, none, none);
  for (auto [x, label] : {std::pair{&grad, "grad"}, {&floats, "floats"}}) check_input(*x, label);
  const int64_t acc_floats = name == "gtao" ? 3 : 2;
  TORCH_CHECK(ints.scalar_type() == at::kLong && ints.is_contiguous() && ints.numel() == kAccInts + 3 &&
                  floats.numel() == kAccFloats + acc_floats, "ints, floats: expected ", name, "'s packed settings");
  const int64_t* i = ints.data_ptr<int64_t>();
  const float* f = floats.data_ptr<float>();
  const WalkSettings cfg = unpack_walk(i, f);
  TORCH_CHECK(!cfg.edge_aware, "fetch: the backward covers the bilinear and nearest fetch, not the edge-aware one");
  const int64_t B = fr.B, H = fr.H, W = fr.W, plane = H * W;
  at::Tensor g_pos = at::zeros({B, H, W, 3}, positions.options()), g_nrm = at::zeros({B, H, W, 3}, positions.options());
  at::Tensor g_depth = at::zeros({B, H, W}, positions.options()), g_setting = at::zeros({B, H, W}, positions.options());
  const int64_t threads = at::get_num_threads();
  at::Tensor tap_pos = at::zeros({threads, B, H, W, 3}, positions.options());
  at::Tensor tap_inv = at::zeros({threads, B, H, W}, positions.options());
  auto run = [&](const auto& acc) {
    const int C = acc.channels();
    TORCH_CHECK(grad.dim() == 4 && grad.size(0) == B && grad.size(1) == C && grad.size(2) == H && grad.size(3) == W,
                "grad: expected (B, ", C, ", H, W)");
    grad_frame(cfg, acc, fr, grad.data_ptr<float>(), C, g_pos, g_nrm, g_depth, g_setting, tap_pos, tap_inv, scalar);
  };
  if (name == "gtao") {
    TORCH_CHECK(i[kAccInts] >= 0 && i[kAccInts] <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
    run(unpack_gtao(i, f));
  } else {
    run(unpack_hbao(i, f));
  }
  // the threads' tap images summed (into the first)
  float *pos = g_pos.data_ptr<float>(), *tp = tap_pos.data_ptr<float>(), *ti = tap_inv.data_ptr<float>();
  const int64_t n_pos = 3 * B * plane, n_inv = B * plane;
  for (int64_t k = 1; k < threads; ++k) {
    for (int64_t q = 0; q < n_pos; ++q) tp[q] += tp[k * n_pos + q];
    for (int64_t q = 0; q < n_inv; ++q) ti[q] += ti[k * n_inv + q];
  }
  for (int64_t q = 0; q < n_pos; ++q) pos[q] += tp[q];
  return {g_pos, g_nrm, tap_inv[0], g_depth, g_setting};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("walk_backward(str accumulator, Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, "
        "Tensor depth, Tensor valid, Tensor intrinsics, Tensor ints, Tensor floats, bool scalar) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("walk_backward", c10::DispatchKey::CPU, TORCH_FN(walk_backward));
}
