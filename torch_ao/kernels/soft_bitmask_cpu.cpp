// Soft and straight-through visibility-bitmask AO (the "default" variant of torch_ao.BitmaskAO,
// mode="soft" / "straight_through"), forward and backward, one pixel's whole walk in registers: SIMD
// across the pixels of a row (ATen's Vectorized<float>), rows over torch's intra-op threads.
//
// The forward is the tensor path's soft visibility: per slice, each step's interval (s, w) in sector
// units (the same float operations as the hard kernel and the tensor walk, so that the straight-through
// forward's 0/1 coverage is the hard one bit for bit), then the soft union of torch_ao.sectors.soft_union
// per sector k,
//     a = sigmoid((k + 1 - s) / tau),  b = sigmoid((w + F(s) - delta - k) / tau),  g = tanh(w / tau)
//     P_{m+1} = P_m - a b g P_m           (P_0 = 1; a step with w < 0 is empty)
// and the visibility sum_slices sum_k P_k omega_k / den (omega = 1/32, den = slices; or the cosine
// weights, den = their sum).
//
// The backward recomputes the walk per pixel (nothing is stored per sample between the passes; that is
// what bounds memory) and runs soft_union's reverse scan per sector,
//     S_M = dL/dP_M,  Y_m = a b P_m S_{m+1},  S_m = S_{m+1} - c_m S_{m+1},
// then its three sums per step give dL/ds, dL/dw (soft_union.py derives them), SectorInterval's
// atan2 derivatives give the thickness's and the two in-slice coordinates' gradients, and the fetch's
// derivative along the step (su, sv move with the radius) gives the radius's. Returned: the gradients of
// the scalar radius and thickness (summed per row in double, then over rows in order).
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "walk_cpu.h"

#include <atomic>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <vector>

#include "mkl_vml.h"

namespace soft_bitmask {
namespace {

using torch_ao_walk::Int;
using torch_ao_walk::L;
using torch_ao_walk::Vec;
constexpr int K = 32;             // sectors
constexpr float kClamp = 30.0f;   // logistic arguments are clamped to +-30 (torch_ao.sectors.sweeps.CLAMP)
constexpr float kTiny = 1e-30f;   // visibilities at or below are flushed to 0 (sweeps.TINY)
constexpr int kWindowMax = 8;     // sweeps.WINDOW_MAX
// The forward marks, per chunk of kChunk pixels of a row, slice and step, whether any pixel's interval is
// not empty (one byte per kChunk samples); the backward walks only those steps (an empty one covers
// nothing and has no gradient). kChunk is a multiple of every build's vector width.
constexpr int kChunk = 16;
static_assert(kChunk % L == 0, "a chunk holds whole vectors");

// cos/sin as torch.cos/torch.sin compute them on this build (MKL's vector math, else SLEEF)
void cos_sin(const float* x, float* c, float* s, int64_t n) {
#ifdef TORCH_AO_MKL_VML
  if (c) vmsCos(int(n), x, c, kVmlMode);
  if (s) vmsSin(int(n), x, s, kVmlMode);
#else
  for (int64_t i = 0; i < n; i += L) {
    const int m = int(std::min<int64_t>(L, n - i));
    Vec v = Vec::loadu(x + i, m);
    if (c) v.cos().store(c + i, m);
    if (s) v.sin().store(s + i, m);
  }
#endif
}

struct Config {
  int64_t slices, steps, seed, rounding;  // rounding: 0 ceil, 1 round (half to even), 2 floor
  float radius, thickness, step_power, min_step_px, epsilon, tau, delta;
  bool jitter, bilinear, drop, cosine, hard_forward;
  // the soft floor's window (tau <= 0.1): reach and width in sectors, as sweeps.floor_window_width
  int reach, window;
  bool windowed;
};

struct Inputs {
  const float *positions, *normals, *inverse_depth, *depth, *intrinsics;
  const bool* valid;
  int64_t H, W;
};

// the float helpers that repeat torch's CPU kernels, and the jitter noise (walk_cpu.h)
using torch_ao_walk::dot3;
using torch_ao_walk::fma;
using torch_ao_walk::ign;
using torch_ao_walk::lerp;
using torch_ao_walk::norm3;
using torch_ao_walk::over_rows;
using torch_ao_walk::select;
using torch_ao_walk::to_int;
inline Vec sigmoid(const Vec& x) {  // torch.sigmoid's vectorised form, argument clamped as the sweeps do
  return (Vec(1.0f) + at::vec::clamp(x, Vec(-kClamp), Vec(kClamp)).neg().exp()).reciprocal();
}
inline bool any_lane(const Vec& mask) { return mask.zero_mask() != (1 << L) - 1; }
inline double lane_sum(const Vec& x) {
  alignas(64) float v[L];
  x.store(v);
  double total = 0;
  for (int l = 0; l < L; ++l) total += v[l];
  return total;
}

// ---------------------------------------------------------------- the pixel and its slice
struct Pixel {  // L pixels of one row
  Vec P[3], N[3], V[3], e1[3], e2[3], d, u, v, live, xi, depth_floor;
};

// the lanes u0 .. u0 + n - 1 of row `row` of image b; returns whether any is a valid pixel
bool load_pixel(const Config& cfg, const Inputs& in, int64_t b, int64_t row, int64_t u0, int n, Pixel& px) {
  const int64_t plane = b * in.H * in.W;
  alignas(64) float lane[10][L];
  bool any = false;
  for (int l = 0; l < L; ++l) {
    const int64_t p = plane + row * in.W + u0 + std::min(l, n - 1);
    const bool live = l < n && in.valid[p];
    any |= live;
    for (int c = 0; c < 3; ++c) {
      lane[c][l] = in.positions[3 * p + c];
      lane[3 + c][l] = in.normals[3 * p + c];
    }
    lane[6][l] = in.depth[p];
    lane[7][l] = float(u0 + l);
    lane[8][l] = live ? 1.0f : 0.0f;
    lane[9][l] = cfg.jitter ? ign(float(u0 + l) + 37.0f, float(row) + 59.0f, cfg.seed + 1) : 0.5f;
  }
  for (int c = 0; c < 3; ++c) {
    px.P[c] = Vec::loadu(lane[c]);
    px.N[c] = Vec::loadu(lane[3 + c]);
  }
  px.d = Vec::loadu(lane[6]);
  px.u = Vec::loadu(lane[7]);
  px.v = Vec(float(row));
  px.live = Vec::loadu(lane[8]) > Vec(0.5f);
  px.xi = Vec::loadu(lane[9]);
  // V = normalize(-P); e1 = normalize(cross(+Y, V)); e2 = cross(V, e1) (patterns.tangent_from_view_azimuth)
  Vec minus[3] = {px.P[0].neg(), px.P[1].neg(), px.P[2].neg()};
  Vec len = at::vec::clamp_min(norm3(minus), Vec(1e-12f));
  for (int c = 0; c < 3; ++c) px.V[c] = minus[c] / len;
  Vec c1[3] = {px.V[2], Vec(0.0f), px.V[0].neg()};
  Vec len1 = at::vec::clamp_min(norm3(c1), Vec(1e-12f));
  for (int c = 0; c < 3; ++c) px.e1[c] = c1[c] / len1;
  const Vec* V = px.V;
  const Vec* e1 = px.e1;
  px.e2[0] = fma(V[1], e1[2], (V[2] * e1[1]).neg());
  px.e2[1] = fma(V[2], e1[0], (V[0] * e1[2]).neg());
  px.e2[2] = fma(V[0], e1[1], (V[1] * e1[0]).neg());
  px.depth_floor = Vec(1e-20f) * (px.d * px.d);
  return any;
}

struct Slice {  // walk.slice_geometry and the step placement of patterns.SlicePattern
  Vec T[3], shift, length, unit_u, unit_v, len, span, span_slope;  // span_slope: d span / d radius
};

void slice_frame(const Config& cfg, const Pixel& px, const Vec& cs, const Vec& sn, float fx, float fy, Slice& sl,
                 Vec* omega) {
  Vec axis[3], np[3];
  for (int c = 0; c < 3; ++c) sl.T[c] = cs * px.e1[c] + sn * px.e2[c];
  const Vec* T = sl.T;
  const Vec* V = px.V;
  axis[0] = fma(T[1], V[2], (T[2] * V[1]).neg());
  axis[1] = fma(T[2], V[0], (T[0] * V[2]).neg());
  axis[2] = fma(T[0], V[1], (T[1] * V[0]).neg());
  const Vec nd = dot3(px.N, axis);
  for (int c = 0; c < 3; ++c) np[c] = px.N[c] - axis[c] * nd;
  const Vec gamma = dot3(np, T).atan2(dot3(np, V));
  sl.shift = (Vec(float(M_PI / 2)) - gamma) / Vec(float(M_PI));
  const Vec du = (Vec(fx) * (T[0] + (px.P[0] * T[2]) / px.d)) / px.d;
  const Vec dv = (Vec(-fy) * (T[1] + (px.P[1] * T[2]) / px.d)) / px.d;
  sl.len = fma(dv, dv, du * du).sqrt();
  const Vec safe = at::vec::clamp_min(sl.len, Vec(1e-12f));
  sl.unit_u = du / safe;
  sl.unit_v = dv / safe;
  const Vec reach = Vec(cfg.radius) * sl.len - Vec(cfg.min_step_px);
  sl.span = at::vec::clamp_min(reach, Vec(0.0f));
  sl.span_slope = select(reach >= Vec(0.0f), sl.len, Vec(0.0f));  // clamp_min passes the gradient at >= 0
  if (!omega) return;
  if (!cfg.cosine) {
    for (int k = 0; k < K; ++k) omega[k] = Vec(1.0f / K);
    return;
  }
  // methods.bitmask_common.cosine_sector_weights: omega_k = |n_p| max(H(e_{k+1}) - H(e_k), 0) with the
  // sector edges e_k = gamma - pi/2 + pi k / 32 and H(t) = sign(t) (F(t) - F(0)),
  // F(t) = -cos(2 t - gamma) / 4 + t sin(gamma) / 2 (ops.arc_measure). No trigonometry: n_p lies in the
  // slice plane, so (cos gamma, sin gamma) = (n_p . V, n_p . T) / |n_p|, and 2 e_k - gamma =
  // gamma - pi + pi k / 16 gives -cos(2 e_k - gamma) = cos gamma cos(pi k / 16) - sin gamma sin(pi k / 16).
  sl.length = norm3(np);
  const Vec flat = sl.length == Vec(0.0f);  // (gamma = atan2(0, 0) = 0 there)
  const Vec inv_length = select(flat, Vec(0.0f), Vec(1.0f) / sl.length);
  const Vec cos_g = select(flat, Vec(1.0f), dot3(np, V) * inv_length), sin_g = dot3(np, T) * inv_length;
  const Vec F0 = cos_g.neg() / Vec(4.0f);
  const Vec base = gamma - Vec(float(M_PI / 2));
  static const std::vector<float> rotation = [] {  // cos(pi k / 16), sin(pi k / 16)
    std::vector<float> r(2 * (K + 1));
    for (int k = 0; k <= K; ++k) {
      r[2 * k] = float(std::cos(M_PI * k / 16.0));
      r[2 * k + 1] = float(std::sin(M_PI * k / 16.0));
    }
    return r;
  }();
  Vec previous;
  for (int k = 0; k <= K; ++k) {
    const Vec t = base + Vec(float(M_PI) * float(k) / float(K));
    const Vec F = (cos_g * Vec(rotation[2 * k]) - sin_g * Vec(rotation[2 * k + 1])) / Vec(4.0f) + (t * sin_g) / Vec(2.0f);
    const Vec sign = select(t > Vec(0.0f), Vec(1.0f), select(t < Vec(0.0f), Vec(-1.0f), Vec(0.0f)));
    const Vec H = sign * (F - F0);
    if (k > 0) omega[k - 1] = at::vec::clamp_min(H - previous, Vec(0.0f)) * sl.length;
    previous = H;
  }
}

// ---------------------------------------------------------------- one step: sample and interval
struct Step {
  Vec s, w;             // interval start and width, sector units (w < 0: empty)
  Vec av, at;           // delta . V and side * delta . T
  Vec front, back;      // unclamped unit positions of the front and back angles
  Vec dav, dat;         // their derivatives along the radius (the step moves with it); backward only
  int side;
};

void sample_step(const Config& cfg, const Inputs& in, int64_t b, const Pixel& px, const Slice& sl, int side,
                 int64_t j, bool slopes, Step& st) {
  const float* K4 = in.intrinsics + 4 * b;
  const float fx = K4[0], fy = K4[1], cx = K4[2], cy = K4[3];
  const int64_t plane = b * in.H * in.W;
  const float* inv = in.inverse_depth + plane;
  const float* pos = in.positions + 3 * plane;
  const Int zero_i(0), one_i(1), Wi(int32_t(in.W)), Wlast(int32_t(in.W - 1)), Hlast(int32_t(in.H - 1));
  const Vec Wf = Vec(float(in.W)), Hf = Vec(float(in.H));
  const Vec sgn = Vec(float(side));
  const Vec su_dir = sl.unit_u * sgn, sv_dir = sl.unit_v * sgn;
  Vec frac = (Vec(float(j)) + px.xi) / Vec(float(cfg.steps));
  if (cfg.step_power == 2.0f) {
    frac = frac * frac;
  } else if (cfg.step_power != 1.0f) {
    frac = frac.pow(Vec(cfg.step_power));
  }
  const Vec dist = Vec(cfg.min_step_px) + sl.span * frac;
  const Vec su = px.u + dist * su_dir, sv = px.v + dist * sv_dir;
  Vec at_s[3], ok, d_at[3];  // the sample's position (and its derivative along the radius)
  if (cfg.bilinear) {
    const torch_ao_walk::BilinearTaps tap = torch_ao_walk::bilinear_taps(inv, su, sv, in.W, in.H);
    const Vec &fu0 = tap.fu0, &fv0 = tap.fv0, &fu = tap.fu, &fv = tap.fv, &t0 = tap.t0, &t1 = tap.t1, &t2 = tap.t2,
              &t3 = tap.t3;
    ok = tap.ok;  // invalid texels hold NaN
    if (cfg.drop) ok = ok & (fu0 >= Vec(0.0f)) & (fu0 + Vec(1.0f) < Wf) & (fv0 >= Vec(0.0f)) & (fv0 + Vec(1.0f) < Hf);
    const Vec depth_s = lerp(lerp(t0, t1, fu), lerp(t2, t3, fu), fv).reciprocal();
    const Vec su_c = at::vec::clamp(su, Vec(0.0f), Vec(float(in.W - 1)));
    const Vec sv_c = at::vec::clamp(sv, Vec(0.0f), Vec(float(in.H - 1)));
    const Vec xh = (su_c - Vec(cx)) / Vec(fx), yh = (sv_c - Vec(cy)).neg() / Vec(fy);
    at_s[0] = xh * depth_s;
    at_s[1] = yh * depth_s;
    at_s[2] = depth_s.neg();
    if (slopes) {
      // su, sv move by dist' (su_dir, sv_dir) per unit of radius, dist' = frac span'; the depth's
      // inverse is bilinear in (fu, fv) = (su, sv) - floor, and the unprojection clamps (su, sv)
      const Vec dd = sl.span_slope * frac;
      const Vec dsu = dd * su_dir, dsv = dd * sv_dir;
      const Vec dS = lerp(t1 - t0, t3 - t2, fv) * dsu + (lerp(t2, t3, fu) - lerp(t0, t1, fu)) * dsv;
      const Vec ddepth = (depth_s * depth_s * dS).neg();
      const Vec dxh = select(su_c == su, dsu / Vec(fx), Vec(0.0f)), dyh = select(sv_c == sv, dsv / Vec(-fy), Vec(0.0f));
      d_at[0] = ddepth * xh + depth_s * dxh;
      d_at[1] = ddepth * yh + depth_s * dyh;
      d_at[2] = ddepth.neg();
    }
  } else {
    const Vec fu0 = (su + Vec(0.5f)).floor(), fv0 = (sv + Vec(0.5f)).floor();
    const Int iu = at::vec::clamp(to_int(at::vec::clamp(fu0, Vec(-1.0f), Wf)), zero_i, Wlast);
    const Int iv = at::vec::clamp(to_int(at::vec::clamp(fv0, Vec(-1.0f), Hf)), zero_i, Hlast);
    const Int texel = iv * Wi + iu;
    const Vec t = at::vec::gather<4>(inv, texel);
    ok = t == t;
    if (cfg.drop) ok = ok & (fu0 >= Vec(0.0f)) & (fu0 < Wf) & (fv0 >= Vec(0.0f)) & (fv0 < Hf);
    for (int c = 0; c < 3; ++c) {
      at_s[c] = at::vec::gather<4>(pos + c, texel * Int(3));
      d_at[c] = Vec(0.0f);  // the nearest texel does not move with the radius
    }
  }
  Vec delta[3];
  for (int c = 0; c < 3; ++c) delta[c] = at_s[c] - px.P[c];
  ok = ok & (dot3(delta, delta) > px.depth_floor);  // a sample on the centre texel never occludes
  for (int c = 0; c < 3; ++c) delta[c] = select(ok, delta[c], px.V[c].neg());
  st.side = side;
  st.av = dot3(delta, px.V);
  st.at = sgn * dot3(delta, sl.T);
  if (slopes) {
    for (int c = 0; c < 3; ++c) d_at[c] = select(ok, d_at[c], Vec(0.0f));
    st.dav = dot3(d_at, px.V);
    st.dat = sgn * dot3(d_at, sl.T);
  }
  // methods.bitmask._sector_interval: front and back angles across the hemisphere, clamped, in sectors
  const Vec scale = Vec(float(side / M_PI));
  st.front = fma(st.at.atan2(st.av), scale, sl.shift);
  st.back = fma(st.at.atan2(st.av - Vec(cfg.thickness)), scale, sl.shift);
  const Vec xf = at::vec::clamp(st.front, Vec(0.0f), Vec(1.0f)), xb = at::vec::clamp(st.back, Vec(0.0f), Vec(1.0f));
  const Vec lo = side > 0 ? xf : xb, hi = side > 0 ? xb : xf;
  st.s = lo * Vec(float(K));
  st.w = (hi - lo) * Vec(float(K));
  if (cfg.epsilon > 0) st.w = st.w - Vec(cfg.epsilon);
  st.w = select(px.live, st.w, Vec(-1.0f));  // lanes past the row or on the background: empty
}

// ---------------------------------------------------------------- the soft coverage of one step
struct Coverage {
  Vec a[K], b[K];     // sigmoid((k + 1 - s) / tau), sigmoid((w + F(s) - delta - k) / tau)
  Vec gate, slope;    // tanh(w / tau) (0 where empty), F'(s)
  Vec live;           // w >= 0
};

void coverage(const Config& cfg, const Vec& s, const Vec& w, Coverage& cv) {
  const float inv_tau = float(1.0 / double(cfg.tau));
  cv.live = w >= Vec(0.0f);
  const Vec wc = at::vec::clamp_min(w, Vec(0.0f));  // an empty step: zero width, zero gate
  const Vec t = (wc * Vec(inv_tau) * Vec(-2.0f)).expm1();  // sweeps.expm1_tanh
  cv.gate = (t / (t + Vec(2.0f))).neg();
  const Vec start_arg = s * Vec(-inv_tau);
  for (int k = 0; k < K; ++k) cv.a[k] = sigmoid(Vec(float(k + 1) * inv_tau) + start_arg);
  // the smooth floor F(s) = sum_{m=1..32} sigmoid((s - m) / tau) and F'(s) tau (sweeps: two paths)
  Vec F(0.0f), slope(0.0f);
  if (cfg.windowed) {
    const Vec lo = at::vec::clamp(s.floor() - Vec(float(cfg.reach - 1)), Vec(1.0f), Vec(float(K - cfg.window + 1)));
    const Vec z = (s - lo) * Vec(inv_tau);
    for (int i = 0; i < cfg.window; ++i) {
      const Vec x = sigmoid(z - Vec(float(i) * inv_tau));
      F = F + x;
      slope = slope + (Vec(1.0f) - x) * x;
    }
    F = F + (lo - Vec(1.0f));
  } else {
    for (int k = 0; k < K; ++k) {
      const Vec not_a = Vec(1.0f) - cv.a[k];
      F = F + not_a;
      slope = slope + not_a * cv.a[k];
    }
  }
  cv.slope = slope * Vec(inv_tau);
  const Vec end_arg = (wc + Vec(1.0f - cfg.delta) + F) * Vec(inv_tau);
  for (int k = 0; k < K; ++k) cv.b[k] = sigmoid(end_arg - Vec(float(k + 1) * inv_tau));
}

// the hard sector rule of one step on 32-bit lanes (sectors.rule.hard_mask): bits [k0, k0 + count)
Int hard_bits(const Config& cfg, const Step& st) {
  const Vec sectors = Vec(float(K));
  const Vec w = st.w;
  const Vec count = cfg.rounding == 0 ? w.ceil() : cfg.rounding == 1 ? w.round() : w.floor();
  const Int one(1), k0 = to_int(at::vec::clamp(st.s.floor(), Vec(0.0f), sectors));
  const Int k1 = at::vec::minimum(k0 + to_int(at::vec::clamp(count, Vec(0.0f), sectors)), Int(K));
  return ((one << k1) - one) & (((one << k0) - one) ^ Int(-1));
}

// the visible share sum_k P_k omega_k of one slice after its M steps
Vec slice_forward(const Config& cfg, const Step* steps, int64_t M, const Vec* omega, Coverage& cv) {
  if (cfg.hard_forward) {  // straight-through: the hard coverage on float visibility
    Int occ(0);
    for (int64_t m = 0; m < M; ++m) occ = occ | hard_bits(cfg, steps[m]);
    alignas(64) int32_t bits[L];
    occ.store(bits);
    Vec total(0.0f);
    for (int k = 0; k < K; ++k) {
      alignas(64) float free[L];
      for (int l = 0; l < L; ++l) free[l] = (bits[l] >> k) & 1 ? 0.0f : 1.0f;
      total = total + Vec::loadu(free) * omega[k];
    }
    return total;
  }
  Vec P[K];
  for (int k = 0; k < K; ++k) P[k] = Vec(1.0f);
  for (int64_t m = 0; m < M; ++m) {
    if (!any_lane(steps[m].w >= Vec(0.0f))) continue;  // every lane empty: covers nothing
    coverage(cfg, steps[m].s, steps[m].w, cv);
    for (int k = 0; k < K; ++k) {
      const Vec c = cv.b[k] * cv.a[k] * cv.gate;
      P[k] = P[k] - c * P[k];
      P[k] = select(P[k] > Vec(kTiny), P[k], Vec(0.0f));
    }
  }
  Vec total(0.0f);
  for (int k = 0; k < K; ++k) total = total + P[k] * omega[k];
  return total;
}

// soft_union's backward for one slice: gradients (ds, dw) of its M steps given grad[k] = dL/dvisible_k
struct Tables {
  std::vector<Coverage> cover;  // per step
  std::vector<Vec> before;      // P_m, per step and sector
};

void slice_backward(const Config& cfg, const Step* steps, int64_t M, const Vec* grad, Tables& tab, Vec* gs, Vec* gw) {
  const float inv_tau = float(1.0 / double(cfg.tau));
  Vec P[K], S[K];
  for (int k = 0; k < K; ++k) P[k] = Vec(1.0f);
  std::vector<char> live(M);
  for (int64_t m = 0; m < M; ++m) {  // the forward sweep, keeping a, b and P_m
    live[m] = any_lane(steps[m].w >= Vec(0.0f));
    if (!live[m]) continue;
    Coverage& cv = tab.cover[m];
    coverage(cfg, steps[m].s, steps[m].w, cv);
    Vec* before = tab.before.data() + m * K;
    for (int k = 0; k < K; ++k) {
      before[k] = P[k];
      const Vec c = cv.b[k] * cv.a[k] * cv.gate;
      P[k] = P[k] - c * P[k];
      P[k] = select(P[k] > Vec(kTiny), P[k], Vec(0.0f));
    }
  }
  for (int k = 0; k < K; ++k) S[k] = grad[k];
  for (int64_t m = M - 1; m >= 0; --m) {  // the reverse scan
    gs[m] = gw[m] = Vec(0.0f);
    if (!live[m]) continue;
    const Coverage& cv = tab.cover[m];
    const Vec* before = tab.before.data() + m * K;
    Vec sum_y(0.0f), sum_ya(0.0f), sum_yb(0.0f);
    for (int k = 0; k < K; ++k) {
      const Vec ab = cv.a[k] * cv.b[k];
      const Vec y = ab * before[k] * S[k];  // Y = a b P_m S_{m+1}
      sum_y = sum_y + y;
      sum_ya = sum_ya + y * cv.a[k];
      sum_yb = sum_yb + y * cv.b[k];
      S[k] = S[k] - ab * cv.gate * S[k];
    }
    const Vec g = cv.gate, not_b = sum_y - sum_yb;
    // dL/dw = -(g' sum Y + g / tau sum Y (1 - b)), g' = (1 - g^2) / tau; dL/ds = -(g / tau) (F' sum Y (1 - b) - sum Y (1 - a))
    gw[m] = select(cv.live, ((g * g - Vec(1.0f)) * sum_y - g * not_b) * Vec(inv_tau), Vec(0.0f));
    gs[m] = select(cv.live, (not_b * cv.slope - sum_y + sum_ya) * g * Vec(-inv_tau), Vec(0.0f));
  }
}

// ---------------------------------------------------------------- a row
struct Row {
  const Config& cfg;
  const Inputs& in;
  int64_t b, row;
  std::vector<float> cosine, sine;  // the slice angles' cos/sin per pixel of the row, slice-major
  int64_t stride;

  Row(const Config& c, const Inputs& i, int64_t b_, int64_t r) : cfg(c), in(i), b(b_), row(r) {
    const int64_t S = cfg.slices;
    stride = (in.W + L - 1) / L * L;
    std::vector<float> angle(S * stride);
    const float slice_step = float(M_PI / double(S));
    for (int64_t u = 0; u < stride; ++u) {
      const float a = cfg.jitter ? ign(float(u), float(row), cfg.seed) : 0.0f;
      for (int64_t s = 0; s < S; ++s) angle[s * stride + u] = (a + float(s)) * slice_step;
    }
    cosine.resize(angle.size());
    sine.resize(angle.size());
    cos_sin(angle.data(), cosine.data(), sine.data(), int64_t(angle.size()));
  }

  void slice(const Pixel& px, int64_t u0, int64_t s, Slice& sl, Vec* omega) const {
    const float* K4 = in.intrinsics + 4 * b;
    slice_frame(cfg, px, Vec::loadu(cosine.data() + s * stride + u0), Vec::loadu(sine.data() + s * stride + u0),
                K4[0], K4[1], sl, omega);
  }

  // step m of a slice: steps 0 .. steps - 1 on side +1, then those of side -1 (the tensor walk's order)
  void sample(const Pixel& px, const Slice& sl, int64_t m, bool slopes, Step& st) const {
    const bool plus = m < cfg.steps;
    sample_step(cfg, in, b, px, sl, plus ? 1 : -1, plus ? m : m - cfg.steps, slopes, st);
  }

  // the live marks of the chunk holding pixel u0: (slices, 2 steps) bytes
  uint8_t* marks(uint8_t* live, int64_t u0) const {
    const int64_t chunks = (in.W + kChunk - 1) / kChunk;
    return live + ((b * in.H + row) * chunks + u0 / kChunk) * cfg.slices * 2 * cfg.steps;
  }

  void forward(float* out, uint8_t* live) const {
    const int64_t M = 2 * cfg.steps;
    std::vector<Step> steps(M);
    Coverage cv;
    Vec omega[K];
    Slice sl;
    for (int64_t u0 = 0; u0 < in.W; u0 += L) {
      const int n = int(std::min<int64_t>(L, in.W - u0));
      Pixel px;
      float* dst = out + (b * in.H + row) * in.W + u0;
      if (!load_pixel(cfg, in, b, row, u0, n, px)) {
        for (int l = 0; l < n; ++l) dst[l] = 1.0f;
        continue;
      }
      Vec num(0.0f), den(0.0f);
      uint8_t* mark = marks(live, u0);
      for (int64_t s = 0; s < cfg.slices; ++s) {
        slice(px, u0, s, sl, omega);
        for (int64_t m = 0; m < M; ++m) {
          sample(px, sl, m, false, steps[m]);
          mark[s * M + m] |= any_lane(steps[m].w >= Vec(0.0f));
        }
        num = num + slice_forward(cfg, steps.data(), M, omega, cv);
        if (cfg.cosine) {
          Vec total(0.0f);
          for (int k = 0; k < K; ++k) total = total + omega[k];
          den = den + total;
        }
      }
      den = cfg.cosine ? at::vec::clamp_min(den, Vec(1e-30f)) : Vec(float(cfg.slices));
      const Vec vis = select(px.live, num / den, Vec(1.0f));
      vis.store(dst, n);
    }
  }

  // adds (dL/dradius, dL/dthickness) of this row to sums[0], sums[1]
  void backward(const float* grad_out, const uint8_t* live, double* sums) const {
    const int64_t M = 2 * cfg.steps, S = cfg.slices;
    std::vector<Step> steps(M);
    std::vector<Vec> omega(S * K), gs(M), gw(M);
    Tables tab{std::vector<Coverage>(M), std::vector<Vec>(M * K)};
    Vec grad[K];
    Slice sl;
    for (int64_t u0 = 0; u0 < in.W; u0 += L) {
      const int n = int(std::min<int64_t>(L, in.W - u0));
      Pixel px;
      if (!load_pixel(cfg, in, b, row, u0, n, px)) continue;
      // dL/dvisible_k = dL/dvis omega_k / den: the weights of every slice first, for den
      Vec den = Vec(float(S));
      if (cfg.cosine) {
        den = Vec(0.0f);
        for (int64_t s = 0; s < S; ++s) {
          slice(px, u0, s, sl, omega.data() + s * K);
          for (int k = 0; k < K; ++k) den = den + omega[s * K + k];
        }
        den = at::vec::clamp_min(den, Vec(1e-30f));
      }
      const Vec upstream = select(px.live, Vec::loadu(grad_out + (b * in.H + row) * in.W + u0, n) / den, Vec(0.0f));
      if (!any_lane(upstream != Vec(0.0f))) continue;
      Vec g_radius(0.0f), g_thickness(0.0f);
      const uint8_t* mark = marks(const_cast<uint8_t*>(live), u0);
      for (int64_t s = 0; s < S; ++s) {
        int64_t count = 0;  // the slice's live steps, in order
        for (int64_t m = 0; m < M; ++m) count += mark[s * M + m];
        if (count == 0) continue;
        slice(px, u0, s, sl, cfg.cosine ? nullptr : omega.data());
        for (int k = 0; k < K; ++k) grad[k] = upstream * (cfg.cosine ? omega[s * K + k] : omega[k]);
        count = 0;
        for (int64_t m = 0; m < M; ++m)
          if (mark[s * M + m]) sample(px, sl, m, true, steps[count++]);
        slice_backward(cfg, steps.data(), count, grad, tab, gs.data(), gw.data());
        for (int64_t m = 0; m < count; ++m) {
          const Step& st = steps[m];
          // SectorInterval.backward: s = 32 lo, w = 32 (hi - lo) - epsilon, clamps pass inside [0, 1]
          const Vec g_lo = (gs[m] - gw[m]) * Vec(float(K)), g_hi = gw[m] * Vec(float(K));
          Vec g_f = st.side > 0 ? g_lo : g_hi, g_b = st.side > 0 ? g_hi : g_lo;
          g_f = select((st.front >= Vec(0.0f)) & (st.front <= Vec(1.0f)), g_f, Vec(0.0f));
          g_b = select((st.back >= Vec(0.0f)) & (st.back <= Vec(1.0f)), g_b, Vec(0.0f));
          // theta = atan2(y, x): d theta = (x dy - y dx) / (x^2 + y^2)
          const Vec scale = Vec(float(st.side / M_PI));
          const Vec bv = st.av - Vec(cfg.thickness);
          const Vec inv_f = g_f * scale / fma(st.av, st.av, st.at * st.at);
          const Vec inv_b = g_b * scale / fma(bv, bv, st.at * st.at);
          const Vec g_at = st.av * inv_f + bv * inv_b, g_av = ((inv_f + inv_b) * st.at).neg();
          g_thickness = g_thickness + select(px.live, st.at * inv_b, Vec(0.0f));
          g_radius = g_radius + select(px.live, g_av * st.dav + g_at * st.dat, Vec(0.0f));
        }
      }
      sums[0] += lane_sum(g_radius);
      sums[1] += lane_sum(g_thickness);
    }
  }
};

Config make_config(int64_t slices, int64_t steps, const at::Tensor& radius, const at::Tensor& thickness,
                   double step_power, double min_step_px, bool jitter, int64_t seed, bool bilinear, bool drop,
                   int64_t rounding, double epsilon, double tau, bool cosine, bool hard_forward) {
  TORCH_CHECK(radius.numel() == 1 && thickness.numel() == 1, "radius, thickness: expected scalars");
  TORCH_CHECK(tau > 0, "tau: expected > 0");
  Config cfg{};
  cfg.slices = slices;
  cfg.steps = steps;
  cfg.seed = seed;
  cfg.rounding = rounding;
  cfg.radius = radius.item<float>();
  cfg.thickness = thickness.item<float>();
  cfg.step_power = float(step_power);
  cfg.min_step_px = float(min_step_px);
  cfg.epsilon = float(epsilon);
  cfg.tau = float(tau);
  cfg.delta = rounding == 0 ? 0.0f : rounding == 1 ? 0.5f : 1.0f;  // sectors.rule.rounding_offset
  cfg.jitter = jitter;
  cfg.bilinear = bilinear;
  cfg.drop = drop;
  cfg.cosine = cosine;
  cfg.hard_forward = hard_forward;
  cfg.reach = int(std::ceil(double(kClamp) * tau)) + 1;
  cfg.window = std::min(2 * cfg.reach, K);
  cfg.windowed = cfg.window <= kWindowMax;
  return cfg;
}

Inputs make_inputs(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                   const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics) {
  TORCH_CHECK(positions.dim() == 4 && positions.size(3) == 3, "positions: expected (B, H, W, 3)");
  for (const at::Tensor* t : {&positions, &normals, &inverse_depth, &depth, &intrinsics})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous(), "expected contiguous float32 inputs");
  TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous(), "valid: expected contiguous bool");
  return Inputs{positions.data_ptr<float>(), normals.data_ptr<float>(), inverse_depth.data_ptr<float>(),
                depth.data_ptr<float>(), intrinsics.data_ptr<float>(), valid.data_ptr<bool>(), positions.size(1),
                positions.size(2)};
}

std::tuple<at::Tensor, at::Tensor> soft_bitmask(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                        const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
                        const at::Tensor& radius, const at::Tensor& thickness, int64_t slices, int64_t steps,
                        double step_power, double min_step_px, bool jitter, int64_t seed, bool bilinear, bool drop,
                        int64_t rounding, double epsilon, double tau, bool cosine, bool hard_forward) {
  const Config cfg = make_config(slices, steps, radius, thickness, step_power, min_step_px, jitter, seed, bilinear,
                                 drop, rounding, epsilon, tau, cosine, hard_forward);
  const Inputs in = make_inputs(positions, normals, inverse_depth, depth, valid, intrinsics);
  const int64_t B = positions.size(0);
  at::Tensor out = at::empty({B, 1, in.H, in.W}, positions.options());
  at::Tensor live = at::zeros({B, in.H, (in.W + kChunk - 1) / kChunk, slices, 2 * steps}, positions.options().dtype(at::kByte));
  float* o = out.data_ptr<float>();
  uint8_t* marks = live.data_ptr<uint8_t>();
  over_rows(B * in.H, [&](int64_t r) { Row(cfg, in, r / in.H, r % in.H).forward(o, marks); });
  return {out, live};
}

std::tuple<at::Tensor, at::Tensor> soft_bitmask_backward(
    const at::Tensor& grad, const at::Tensor& live, const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
    const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& radius,
    const at::Tensor& thickness, int64_t slices, int64_t steps, double step_power, double min_step_px, bool jitter,
    int64_t seed, bool bilinear, bool drop, int64_t rounding, double epsilon, double tau, bool cosine) {
  const Config cfg = make_config(slices, steps, radius, thickness, step_power, min_step_px, jitter, seed, bilinear,
                                 drop, rounding, epsilon, tau, cosine, false);
  const Inputs in = make_inputs(positions, normals, inverse_depth, depth, valid, intrinsics);
  const at::Tensor g = grad.to(at::kFloat).contiguous();
  TORCH_CHECK(g.numel() == positions.size(0) * in.H * in.W, "grad: expected (B, 1, H, W)");
  const int64_t rows = positions.size(0) * in.H;
  std::vector<double> per_row(2 * rows, 0.0);  // summed in row order below: the same result on any thread count
  TORCH_CHECK(live.scalar_type() == at::kByte && live.is_contiguous() &&
              live.numel() == rows * ((in.W + kChunk - 1) / kChunk) * slices * 2 * steps, "live: expected the forward's marks");
  const float* go = g.data_ptr<float>();
  const uint8_t* marks = live.data_ptr<uint8_t>();
  over_rows(rows, [&](int64_t r) { Row(cfg, in, r / in.H, r % in.H).backward(go, marks, per_row.data() + 2 * r); });
  double total[2] = {0.0, 0.0};
  for (int64_t r = 0; r < rows; ++r) {
    total[0] += per_row[2 * r];
    total[1] += per_row[2 * r + 1];
  }
  return {at::full({}, total[0], radius.options()), at::full({}, total[1], thickness.options())};
}

}  // namespace
}  // namespace soft_bitmask

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("soft_bitmask(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor radius, Tensor thickness, int slices, int steps, float step_power, "
        "float min_step_px, bool jitter, int seed, bool bilinear, bool drop, int rounding, float epsilon, float tau, "
        "bool cosine, bool hard_forward) -> (Tensor, Tensor)");
  m.def("soft_bitmask_backward(Tensor grad, Tensor live, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, "
        "Tensor valid, Tensor intrinsics, Tensor radius, Tensor thickness, int slices, int steps, float step_power, "
        "float min_step_px, bool jitter, int seed, bool bilinear, bool drop, int rounding, float epsilon, float tau, "
        "bool cosine) -> (Tensor, Tensor)");
  m.impl("soft_bitmask", c10::DispatchKey::CPU, TORCH_FN(soft_bitmask::soft_bitmask));
  m.impl("soft_bitmask_backward", c10::DispatchKey::CPU, TORCH_FN(soft_bitmask::soft_bitmask_backward));
}
