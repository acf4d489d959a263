// The backward of the one walk for GTAO's exact variant (torch_ao_kernels::walk_backward): the walk of
// walk.h run once more in dual lanes (lanes_dual.h), which gives
//  - each pixel's outputs' derivatives with respect to its own position, normal and depth (tangents
//    0..6, seeded in Pixels), the sample positions' and bilinear weights' dependence on them included;
//  - per slice and side, the derivatives with respect to the horizon's winning sample's offset delta
//    (tangents 7..9, seeded on every sample: the horizon is a minimum, so the tangents that survive are
//    the winner's; each side's horizon keeps its own, taken out before the slice's integral, which then
//    runs with tangents 7 and 8 on the two horizons). They are chained to the winner's taps: for a
//    bilinear fetch delta = pos - P with pos = q / (sum_k w_k t_k), so d pos / d t_k = pos pos_z w_k; a
//    nearest fetch reads the tap's position itself. Scattered into per-thread images, summed at the end.
// The outputs' upstream gradient is read per pixel before the walk, so nothing per sample is stored.
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

#include "lanes_simd.h"
#include "lanes_dual.h"
#include "frame_cpu.h"
#include "packed.h"
#include "rows_cpu.h"

namespace {

using namespace tao;

constexpr int kOwn = 7;                  // tangents of the pixel's own P (3), N (3), depth (1)
constexpr int kTangents = kOwn + 3;      // and of a side's winning sample's delta

inline bool mask_lane(bool m, int) { return m; }
inline bool mask_lane(const Vec& m, int l) { return lane_on(m, l); }
inline void store_lanes(uint32_t x, int32_t* out) { out[0] = int32_t(x); }
inline void store_lanes(const IVec& x, int32_t* out) { x.store(out); }

// Where the gradients go: the pixel's own (written once per pixel) and the taps' (this thread's images)
struct Targets {
  float *positions, *normals, *depth;  // own: (H, W, 3), (H, W, 3), (H, W) of image b
  float *tap_positions, *tap_inverse;  // scattered: (H, W, 3), (H, W) of image b, this thread's
};

// The horizon's winner on one side: its taps and weights, its position (values only)
template <class B> struct Winner {
  using M = typename LaneTraits<B>::M;
  using I = typename LaneTraits<B>::I;
  I index[4];
  B fu, fv, pos[3];
  M has;
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

template <class B, class Acc>
void grad_block(const WalkSettings& cfg, const Image& img, const Acc& acc, int64_t row, int64_t u0, int n,
                const float* const* upstream, int C, const Targets& t) {
  using D = Dual<B, kTangents>;
  using M = typename LaneTraits<B>::M;
  constexpr int L = LaneTraits<B>::L;
  const Pixels<D> px(cfg, img, row, u0, n);
  if (!any(px.live)) return;
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
  const M none = B(0.0f) > B(1.0f);
  for (int64_t s = 0; s < cfg.slices; ++s) {
    const Slice<D> sl(cfg, img, px, s);
    typename Acc::template State<D> state = acc.begin_slice(px, sl);
    Winner<B> win[2];
    for (int k = 0; k < 2; ++k) {
      win[k].has = none;
      for (int i = 0; i < 4; ++i) win[k].index[i] = typename LaneTraits<B>::I(0);
      win[k].fu = win[k].fv = B(0.0f);
      for (int c = 0; c < 3; ++c) win[k].pos[c] = B(0.0f);
    }
    for (int side = 1; side >= (cfg.full_circle ? 1 : -1); side -= 2) {
      const int k = side > 0 ? 0 : 1;
      Winner<B>& w = win[k];
      for (int64_t j = 0; j < cfg.steps; ++j) {
        Sample<D> smp(cfg, img, px, sl, float(side), step_distance(cfg, sl, px.xi, j));
        for (int c = 0; c < 3; ++c) smp.delta[c].d[kOwn + c] = B(1.0f);
        const B before = state.best[k].v;
        acc.step(state, side, px, sl, smp);
        const M took = state.best[k].v < before;
        for (int i = 0; i < 4; ++i) w.index[i] = select(took, smp.index[i], w.index[i]);
        w.fu = select(took, smp.fu.v, w.fu), w.fv = select(took, smp.fv.v, w.fv);
        for (int c = 0; c < 3; ++c) w.pos[c] = select(took, smp.delta[c].v + px.P[c].v, w.pos[c]);
        w.has = lor(w.has, took);
      }
    }
    B along_delta[2][3];  // d best[k] / d delta of its winner; then tangents kOwn + k probe best[k]
    for (int k = 0; k < 2; ++k)
      for (int c = 0; c < 3; ++c) along_delta[k][c] = state.best[k].d[kOwn + c], state.best[k].d[kOwn + c] = B(0.0f);
    state.best[0].d[kOwn] = state.best[1].d[kOwn + 1] = B(1.0f);
    typename Acc::template Sums<D> part;
    acc.end_slice(state, px, sl, part);
    D outs[8];
    acc.finish(part, px, outs);  // linear in the sums: the slice's share of the outputs
    for (int k = 0; k < kOwn; ++k)
      for (int c = 0; c < C; ++c) own[k] = own[k] + g[c] * outs[c].d[k];
    for (int k = 0; k < 2; ++k) {  // the winners' taps
      B gd[3];
      B along_best = B(0.0f);
      for (int ch = 0; ch < C; ++ch) along_best = along_best + g[ch] * outs[ch].d[kOwn + k];
      for (int c = 0; c < 3; ++c) gd[c] = along_best * along_delta[k][c];
      const Winner<B>& w = win[k];
      scatter_taps(cfg.bilinear, n, t, gd, w.pos, w.fu, w.fv, w.index, land(w.has, px.live));
    }
  }
  float ol[kOwn][L];
  for (int k = 0; k < kOwn; ++k) to_lanes(own[k], ol[k]);
  for (int l = 0; l < n; ++l) {
    const int64_t p = row * img.W + u0 + l;
    for (int c = 0; c < 3; ++c) t.positions[3 * p + c] = ol[c][l], t.normals[3 * p + c] = ol[3 + c][l];
    t.depth[p] = ol[6][l];
  }
}

void check_input(const at::Tensor& x, const char* name) {
  TORCH_CHECK(x.scalar_type() == at::kFloat && x.is_contiguous() && x.device().is_cpu(), name,
              ": expected contiguous float32 on the CPU");
}

// Where a backward's gradients go: the pixels' own (positions, normals, depth) and the taps' (per thread)
struct Gradients {
  at::Tensor positions, normals, depth, tap_positions, tap_inverse;

  Gradients(const at::Tensor& like, int64_t B, int64_t H, int64_t W) {
    const int64_t threads = at::get_num_threads();
    positions = at::zeros({B, H, W, 3}, like.options()), normals = at::zeros({B, H, W, 3}, like.options());
    depth = at::zeros({B, H, W}, like.options());
    tap_positions = at::zeros({threads, B, H, W, 3}, like.options());
    tap_inverse = at::zeros({threads, B, H, W}, like.options());
  }
  Targets targets(int64_t b, int64_t B, int64_t plane, int64_t thread) {
    return Targets{positions.data_ptr<float>() + 3 * b * plane, normals.data_ptr<float>() + 3 * b * plane,
                   depth.data_ptr<float>() + b * plane,
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

// torch_ao_kernels::walk_backward: the gradients of sum(grad * walk(...)) with respect to the walk's
// positions, normals (B, H, W, 3), inverse depth and depth (B, H, W); grad (B, C, H, W)
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> walk_backward(
    c10::string_view accumulator, const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals,
    const at::Tensor& inverse_depth, const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
    const at::Tensor& ints, const at::Tensor& floats, bool scalar) {
  TORCH_CHECK(std::string(accumulator) == "gtao", "accumulator: the backward covers gtao, got ", std::string(accumulator));
  const at::Tensor none = at::empty({0}, positions.options());
  const Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, none, none);
  check_settings(ints, floats, 3, 3, "gtao");
  const int64_t* i = ints.data_ptr<int64_t>();
  const float* f = floats.data_ptr<float>();
  const WalkSettings cfg = unpack_walk(i, f);
  const GTAOAccumulator acc = unpack_gtao(i, f);
  TORCH_CHECK(acc.variant == GTAOVariant::exact, "variant: the backward covers the exact variant");
  TORCH_CHECK(!cfg.edge_aware && !cfg.full_circle, "the backward covers the bilinear and nearest fetch, one half circle");
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2), plane = H * W;
  const int C = acc.channels();
  check_grad(grad, positions, C);
  Gradients out(positions, B, H, W);
  const float* gp = grad.data_ptr<float>();
  torch_ao_rows::for_each_row(B, H, [&](int64_t b, int64_t row) {
    const Image img = fr.image(b);
    const float* upstream[8];
    for (int c = 0; c < C; ++c) upstream[c] = gp + (b * C + c) * plane;
    const Targets t = out.targets(b, B, plane, at::get_thread_num());
    if (scalar) {
      for (int64_t u = 0; u < W; ++u) grad_block<float>(cfg, img, acc, row, u, 1, upstream, C, t);
      return;
    }
    constexpr int L = LaneTraits<Vec>::L;
    for (int64_t u0 = 0; u0 < W; u0 += L)
      grad_block<Vec>(cfg, img, acc, row, u0, int(std::min<int64_t>(L, W - u0)), upstream, C, t);
  });
  at::Tensor g_inv = out.reduce();
  return {out.positions, out.normals, g_inv, out.depth};
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
                     int64_t u0, int n, const float* upstream, const Targets& t, float* g_thickness) {
  using D = Dual<B, kOwn>;
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
    g_thickness[p] = ol[7][l];
  }
}

// torch_ao_kernels::soft_backward: the gradients of sum(grad * visibility) of the soft / straight-through
// walk ("soft"'s packed settings) with respect to its positions, normals (B, H, W, 3), inverse depth and
// depth (B, H, W), and each pixel's share of the thickness' (B, H, W); grad (B, 1, H, W)
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> soft_backward(
    const at::Tensor& grad, const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
    const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& ints,
    const at::Tensor& floats, bool scalar) {
  const at::Tensor none = at::empty({0}, positions.options());
  const Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, none, none, none);
  check_settings(ints, floats, 3, 3, "soft");
  check_grad(grad, positions, 1);
  const int64_t* i = ints.data_ptr<int64_t>();
  const float* f = floats.data_ptr<float>();
  const WalkSettings cfg = unpack_walk(i, f);
  TORCH_CHECK(f[kAccFloats + 2] > 0, "tau: expected > 0");
  TORCH_CHECK(cfg.steps <= kSoftMaxSteps / 2, "steps: the soft union holds at most ", kSoftMaxSteps / 2, " per side");
  TORCH_CHECK(cfg.placement == Steps::power && !cfg.edge_aware && !cfg.full_circle,
              "soft_backward: the power step placement, the bilinear or nearest fetch, one half circle");
  const SoftAccumulator<true, true> acc = unpack_soft<true, true>(i, f);
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2), plane = H * W;
  Gradients out(positions, B, H, W);
  at::Tensor g_thickness = at::zeros({B, H, W}, positions.options());
  const float* gp = grad.data_ptr<float>();
  torch_ao_rows::for_each_row(B, H, [&](int64_t b, int64_t row) {
    const Image img = fr.image(b);
    const Targets t = out.targets(b, B, plane, at::get_thread_num());
    float* gt = g_thickness.data_ptr<float>() + b * plane;
    if (scalar) {
      for (int64_t u = 0; u < W; ++u) soft_grad_block<float>(cfg, img, acc, row, u, 1, gp + b * plane, t, gt);
      return;
    }
    constexpr int L = LaneTraits<Vec>::L;
    for (int64_t u0 = 0; u0 < W; u0 += L)
      soft_grad_block<Vec>(cfg, img, acc, row, u0, int(std::min<int64_t>(L, W - u0)), gp + b * plane, t, gt);
  });
  at::Tensor g_inv = out.reduce();
  return {out.positions, out.normals, g_inv, out.depth, g_thickness};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("walk_backward(str accumulator, Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, "
        "Tensor depth, Tensor valid, Tensor intrinsics, Tensor ints, Tensor floats, bool scalar) "
        "-> (Tensor, Tensor, Tensor, Tensor)");
  m.impl("walk_backward", c10::DispatchKey::CPU, TORCH_FN(walk_backward));
  m.def("soft_backward(Tensor grad, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor ints, Tensor floats, bool scalar) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor)");
  m.impl("soft_backward", c10::DispatchKey::CPU, TORCH_FN(soft_backward));
}
