// Hard visibility-bitmask walks of torch_ao.BitmaskAO, one pixel's whole walk in registers, SIMD across
// the pixels of a row (ATen's Vectorized<float>: the same SLEEF atan2 as torch's own CPU kernels, MKL's
// vector math where torch calls it) and rows spread over torch's intra-op threads:
//
// * walk_row: the "default" variant (methods/bitmask.py DefaultAccumulator) with uniform or cosine
//   sector weights (methods/bitmask_common.py), and optionally its indirect light and bent normals;
// * walk_row_glsl: the "ssilvb_glsl" variant (methods/bitmask_glsl.py), the SSILVB GLSL article's shader,
//   AO and indirect light.
//
// Both repeat the tensor path's float arithmetic operation by operation, so that the 32-bit masks come
// out the same: where a torch CPU kernel fuses a multiply and an add (cross products, addcmul, lerp,
// the tail of a 2-/3-element norm) this code calls fma, and nowhere else (built with
// -ffp-contract=off); sums over the 32 sectors follow torch's reduction order (sum32). See
// torch_ao/kernels/bitmask.py for the inputs; docs/performance.md for the measured agreement.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <ATen/ops/empty.h>
#include <c10/util/Half.h>
#include <torch/library.h>

#include <atomic>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <vector>

#include "mkl_vml.h"  // torch.cos/sin/acos on a build with MKL call its vector math; so does this
#include "walk_cpu.h"

namespace {

using torch_ao_walk::Int;
using torch_ao_walk::L;
using torch_ao_walk::Vec;
// the float helpers that repeat torch's CPU kernels (walk_cpu.h)
using torch_ao_walk::cross;
using torch_ao_walk::dot3;
using torch_ao_walk::fma;
using torch_ao_walk::ign;
using torch_ao_walk::lerp;
using torch_ao_walk::norm2;
using torch_ao_walk::norm3;
using torch_ao_walk::over_rows;
using torch_ao_walk::select;
using torch_ao_walk::sign;
using torch_ao_walk::to_int;
constexpr int kSectors = 32;

// torch's sum over a contiguous last dimension of 32 floats, lane by lane (each x[k] holds sector k of
// L pixels): SumKernel (dispatched at 8-float vectors, also on AVX-512 CPUs, as measured) adds sectors
// k, k + 8, k + 16, k + 24 in one accumulator lane, then its 8 lanes in order
constexpr int kSumWidth = 8;
inline Vec sum32(const Vec* x) {
  Vec total = x[0] + x[kSumWidth] + x[2 * kSumWidth] + x[3 * kSumWidth];
  for (int k = 1; k < kSumWidth; ++k) total = total + (((x[k] + x[k + kSumWidth]) + x[k + 2 * kSumWidth]) + x[k + 3 * kSumWidth]);
  return total;
}

// torch's row_sum (SumKernel's cascade) of n values x[0], x[stride], ..., lane by lane: four interleaved
// partial sums over groups of 4 values (in blocks of 16 groups, each block's sum added to a second level),
// the leftover values added to the first partial sum, then the four summed in order (n < 4 * 65536)
inline Vec row_sum(const Vec* x, int64_t n, int64_t stride) {
  constexpr int64_t block = 16;  // multi_row_sum's level step while rows < 2^16
  const int64_t rows = n / 4;
  Vec level0[4], level1[4];
  for (int k = 0; k < 4; ++k) level0[k] = level1[k] = Vec(0.0f);
  int64_t i = 0;
  for (; i + block <= rows;) {
    for (int64_t j = 0; j < block; ++j, ++i)
      for (int k = 0; k < 4; ++k) level0[k] = level0[k] + x[(4 * i + k) * stride];
    for (int k = 0; k < 4; ++k) level1[k] = level1[k] + level0[k], level0[k] = Vec(0.0f);
  }
  for (; i < rows; ++i)
    for (int k = 0; k < 4; ++k) level0[k] = level0[k] + x[(4 * i + k) * stride];
  for (int k = 0; k < 4; ++k) level0[k] = level0[k] + level1[k];
  for (int64_t r = rows * 4; r < n; ++r) level0[0] = level0[0] + x[r * stride];
  return ((level0[0] + level0[1]) + level0[2]) + level0[3];
}

// array_cos/sin/acos: n floats (a multiple of L) through the function torch.cos/sin/acos use, MKL's
// vector math where torch has it, else SLEEF's
#ifdef TORCH_AO_MKL_VML
#define TORCH_AO_ARRAY_FN(fn, mkl) \
  inline void array_##fn(int64_t n, const float* a, float* r) { mkl(int(n), a, r, kVmlMode); }
#else
#define TORCH_AO_ARRAY_FN(fn, mkl) \
  inline void array_##fn(int64_t n, const float* a, float* r) { \
    for (int64_t i = 0; i < n; i += L) Vec::loadu(a + i).fn().store(r + i); \
  }
#endif
TORCH_AO_ARRAY_FN(cos, vmsCos)
TORCH_AO_ARRAY_FN(sin, vmsSin)
TORCH_AO_ARRAY_FN(acos, vmsAcos)
#undef TORCH_AO_ARRAY_FN

// torch.atan2 evaluates SLEEF's vector atan2 over runs of 2 vectors and the C library's atan2f on the
// last (n mod 32) elements of a tensor: lanes with ``scalar`` set take the latter
inline Vec atan2_as_torch(const Vec& y, const Vec& x, const Vec& scalar, bool any_scalar) {
  const Vec vector = y.atan2(x);
  if (!any_scalar || scalar.zero_mask() == (1 << L) - 1) return vector;
  alignas(64) float ys[L], xs[L], out[L], flags[L];
  y.store(ys), x.store(xs), vector.store(out), scalar.store(flags);
  for (int l = 0; l < L; ++l)
    if (flags[l] != 0.0f) out[l] = std::atan2(ys[l], xs[l]);
  return Vec::loadu(out);
}

inline Vec load_lanes(const float* lanes) { return Vec::loadu(lanes); }
inline Vec to_float(const Int& x) { return at::vec::convert_to_fp_of_same_size<float>(x); }
inline Int operator~(const Int& x) { return x ^ Int(-1); }
inline Vec bit(const Int& mask, int k) { return to_float((mask >> Int(k)) & Int(1)); }

// popcount of 32-bit lanes, SWAR (arithmetic shifts are safe here: the masks clear the smeared sign bits)
inline Int popcount(const Int& v) {
  Int x = v - ((v >> Int(1)) & Int(0x55555555));
  x = (x & Int(0x33333333)) + ((x >> Int(2)) & Int(0x33333333));
  x = (x + (x >> Int(4))) & Int(0x0F0F0F0F);
  return (x * Int(0x01010101)) >> Int(24);
}

// sectors.hard_mask: bits [floor(s), floor(s) + count) of 32 (bits past 31 are shifted out), count the
// interval's width w rounded (0 ceil, 1 round half to even, 2 floor), both clamped to [0, 32]
inline Int sector_bits(const Vec& s, const Vec& w, int64_t rounding) {
  const Vec sectors = Vec(float(kSectors));
  const Vec count = rounding == 0 ? w.ceil() : rounding == 1 ? w.round() : w.floor();
  const Int k0 = to_int(at::vec::clamp(s.floor(), Vec(0.0f), sectors));
  const Int k1 = at::vec::minimum(k0 + to_int(at::vec::clamp(count, Vec(0.0f), sectors)), Int(kSectors));
  // (1 << k) - 1 for k = 32 is all ones: a vector shift by 32 gives 0
  return ((Int(1) << k1) - Int(1)) & ~((Int(1) << k0) - Int(1));
}

// Channels 0..3 of the 4-float records base[4 i] at the lanes' indices i: one 16-byte load per lane and a
// transpose (the hardware gather of single floats is several times slower on this CPU: measured)
inline void gather_records(const float* base, const Int& index, Vec* out) {
#if defined(CPU_CAPABILITY_AVX512)
  static_assert(L == 16, "AVX-512: 16 lanes");
  alignas(64) int32_t at[L];
  index.store(at);
  __m512 v[4];
  for (int j = 0; j < 4; ++j) {  // v[j] holds the records of lanes j, 4 + j, 8 + j, 12 + j
    __m512 r = _mm512_castps128_ps512(_mm_loadu_ps(base + 4 * int64_t(at[j])));
    r = _mm512_insertf32x4(r, _mm_loadu_ps(base + 4 * int64_t(at[4 + j])), 1);
    r = _mm512_insertf32x4(r, _mm_loadu_ps(base + 4 * int64_t(at[8 + j])), 2);
    v[j] = _mm512_insertf32x4(r, _mm_loadu_ps(base + 4 * int64_t(at[12 + j])), 3);
  }
  const __m512 t0 = _mm512_unpacklo_ps(v[0], v[1]), t1 = _mm512_unpackhi_ps(v[0], v[1]);
  const __m512 t2 = _mm512_unpacklo_ps(v[2], v[3]), t3 = _mm512_unpackhi_ps(v[2], v[3]);
  out[0] = _mm512_shuffle_ps(t0, t2, 0x44), out[1] = _mm512_shuffle_ps(t0, t2, 0xEE);
  out[2] = _mm512_shuffle_ps(t1, t3, 0x44), out[3] = _mm512_shuffle_ps(t1, t3, 0xEE);
#else
  for (int c = 0; c < 4; ++c) out[c] = at::vec::gather<4>(base + c, index * Int(4));
#endif
}

// Where a sample reads the frame: the nearest texel, or four bilinear taps and their fractions
struct Taps {
  Int index[4];  // texel indices within the image (only index[0] for a nearest fetch)
  Vec fu, fv;
  bool bilinear;
  // value of channel c of a (H, W, stride) channel-last image at the taps (Sample.gather)
  Vec gather(const float* image, int c, int stride = 3) const {
    const Int step(stride);
    if (!bilinear) return at::vec::gather<4>(image + c, index[0] * step);
    const Vec t0 = at::vec::gather<4>(image + c, index[0] * step), t1 = at::vec::gather<4>(image + c, index[1] * step);
    const Vec t2 = at::vec::gather<4>(image + c, index[2] * step), t3 = at::vec::gather<4>(image + c, index[3] * step);
    return lerp(lerp(t0, t1, fu), lerp(t2, t3, fu), fv);
  }
};

// One image of the frame, channel-last: what a row's walk reads
struct Image {
  // positions, normals and light (may be null) hold `stride` floats per texel: 3, or 4 with the inverse
  // depth as the positions' fourth (a nearest fetch then reads a texel with one record load)
  const float *positions, *normals, *inverse_depth, *depth, *light;
  int stride;
  const bool* valid;
  const int32_t* scalar_from;  // per pixel: the first step whose atan2 is torch's scalar one (steps: none)
  const bool* scalar_gamma;    // per pixel: whether its projected normal's atan2 is
  float fx, fy, cx, cy;
  int64_t H, W;
};

// The walk's fetch (walk/fetch.py Footprint, Sample): the sample's position at screen (su, sv), whether
// it is valid (its texels are, and with drop it lies inside), and the taps for other buffers
inline void fetch(const Image& im, const Vec& su, const Vec& sv, bool bilinear, bool drop, Vec* pos, Vec& ok, Taps& taps) {
  const Vec Wf(float(im.W)), Hf(float(im.H)), Wmax(float(im.W - 1)), Hmax(float(im.H - 1));
  const Int Wi(int32_t(im.W)), Wlast(int32_t(im.W - 1)), Hlast(int32_t(im.H - 1)), zero(0);
  taps.bilinear = bilinear;
  if (bilinear) {
    const torch_ao_walk::BilinearTaps tap = torch_ao_walk::bilinear_taps(im.inverse_depth, su, sv, im.W, im.H);
    const Vec &fu0 = tap.fu0, &fv0 = tap.fv0;
    taps.fu = tap.fu, taps.fv = tap.fv;
    for (int k = 0; k < 4; ++k) taps.index[k] = tap.index[k];
    ok = tap.ok;  // invalid texels hold NaN: a sample is valid when its four taps are
    if (drop) ok = ok & (fu0 >= Vec(0.0f)) & (fu0 + Vec(1.0f) < Wf) & (fv0 >= Vec(0.0f)) & (fv0 + Vec(1.0f) < Hf);
    const Vec depth_s = lerp(lerp(tap.t0, tap.t1, taps.fu), lerp(tap.t2, tap.t3, taps.fu), taps.fv).reciprocal();
    const Vec su_c = at::vec::clamp(su, Vec(0.0f), Wmax), sv_c = at::vec::clamp(sv, Vec(0.0f), Hmax);
    pos[0] = ((su_c - Vec(im.cx)) / Vec(im.fx)) * depth_s;
    pos[1] = ((sv_c - Vec(im.cy)).neg() / Vec(im.fy)) * depth_s;
    pos[2] = depth_s.neg();
  } else {
    const Vec fu0 = (su + Vec(0.5f)).floor(), fv0 = (sv + Vec(0.5f)).floor();
    const Int iu = at::vec::clamp(to_int(at::vec::clamp(fu0, Vec(-1.0f), Wf)), zero, Wlast);
    const Int iv = at::vec::clamp(to_int(at::vec::clamp(fv0, Vec(-1.0f), Hf)), zero, Hlast);
    taps.index[0] = iv * Wi + iu;
    Vec t;
    if (im.stride == 4) {
      Vec record[4];
      gather_records(im.positions, taps.index[0], record);
      for (int c = 0; c < 3; ++c) pos[c] = record[c];
      t = record[3];
    } else {
      t = at::vec::gather<4>(im.inverse_depth, taps.index[0]);
      for (int c = 0; c < 3; ++c) pos[c] = taps.gather(im.positions, c);
    }
    ok = t == t;
    if (drop) ok = ok & (fu0 >= Vec(0.0f)) & (fu0 < Wf) & (fv0 >= Vec(0.0f)) & (fv0 < Hf);
  }
}

// A block of up to L pixels of one row: the lanes' inputs (lanes past the row's end repeat its last pixel)
struct Block {
  int n;      // real pixels in the block
  bool any;   // whether any lane is a valid pixel
  Vec P[3], N[3], V[3], d, u, v, live;
  Vec scalar_from, scalar_gamma;  // (as Image's, for the lanes)
  bool any_scalar;                // whether any lane has a scalar atan2
};

inline Block load_block(const Image& im, int64_t row, int64_t u0) {
  Block blk;
  blk.n = int(std::min<int64_t>(L, im.W - u0));
  alignas(64) float lane[10][L];
  blk.any = false;
  blk.any_scalar = false;
  for (int l = 0; l < L; ++l) {
    const int64_t p = row * im.W + u0 + std::min(l, blk.n - 1);
    const bool live = l < blk.n && im.valid[p];
    blk.any |= live;
    for (int c = 0; c < 3; ++c) {
      lane[c][l] = im.positions[im.stride * p + c];
      lane[3 + c][l] = im.normals[im.stride * p + c];
    }
    lane[6][l] = im.depth[p];
    lane[7][l] = live ? 1.0f : 0.0f;
    lane[8][l] = im.scalar_from ? float(im.scalar_from[p]) : 1e9f;
    lane[9][l] = im.scalar_gamma && im.scalar_gamma[p] ? 1.0f : 0.0f;
    blk.any_scalar |= live && im.scalar_from && (im.scalar_from[p] < (1 << 20) || im.scalar_gamma[p]);
  }
  blk.scalar_from = load_lanes(lane[8]);
  blk.scalar_gamma = load_lanes(lane[9]);
  for (int c = 0; c < 3; ++c) {
    blk.P[c] = load_lanes(lane[c]);
    blk.N[c] = load_lanes(lane[3 + c]);
  }
  blk.d = load_lanes(lane[6]);
  blk.live = load_lanes(lane[7]) > Vec(0.5f);
  blk.u = Vec::arange(float(u0), 1.0f);
  blk.v = Vec(float(row));
  // V = normalize(-P) (F.normalize)
  Vec minus[3] = {blk.P[0].neg(), blk.P[1].neg(), blk.P[2].neg()};
  const Vec len = at::vec::clamp_min(norm3(minus), Vec(1e-12f));
  for (int c = 0; c < 3; ++c) blk.V[c] = minus[c] / len;
  return blk;
}

inline void store_lanes(const Vec& x, int n, float* out, int64_t stride = 1) {
  alignas(64) float result[L];
  x.store(result);
  for (int l = 0; l < n; ++l) out[l * stride] = result[l];
}

// ====================================================================================== "default" variant

struct Settings {
  int64_t slices, steps;
  float radius, thickness, step_power, min_step_px, epsilon;
  bool jitter, bilinear, drop;
  int64_t seed, rounding;  // rounding: 0 ceil, 1 round (half to even), 2 floor
  bool cosine, indirect, bent;
};

struct Outputs {
  float *vis, *indirect, *bent;  // one image's (H,W), (3,H,W) or null, (3,H,W) or null
};

// cosine_sector_weights: each sector's share |n_p| int cos(theta - gamma) |sin theta| over the sector,
// H(theta) = sign(theta) (F(theta) - F(0)), F(t) = -cos(2t - gamma) / 4 + t sin(gamma) / 2 (ops.arc_measure)
void cosine_weights(const Vec& gamma, const Vec& length, Vec* omega, float* scratch) {
  float* arg = scratch;                        // (34, L): 2 edge_k - gamma, then 2 * 0 - gamma
  float* cosine = scratch + 34 * L;            // (34, L)
  float* sine = scratch + 68 * L;              // (1, L) sin(gamma)
  float* gamma_lanes = scratch + 69 * L;
  Vec edge[kSectors + 1];
  const Vec start = gamma - Vec(float(M_PI / 2));
  for (int k = 0; k <= kSectors; ++k) {
    edge[k] = start + Vec((float(M_PI) * float(k)) / float(kSectors));
    (Vec(2.0f) * edge[k] - gamma).store(arg + k * L);
  }
  (Vec(2.0f) * Vec(0.0f) - gamma).store(arg + 33 * L);
  array_cos(34 * L, arg, cosine);
  gamma.store(gamma_lanes);
  array_sin(L, gamma_lanes, sine);
  const Vec sin_gamma = Vec::loadu(sine);
  const Vec F0 = Vec::loadu(cosine + 33 * L).neg() / Vec(4.0f) + (Vec(0.0f) * sin_gamma) / Vec(2.0f);
  Vec H_prev;
  for (int k = 0; k <= kSectors; ++k) {
    const Vec F = Vec::loadu(cosine + k * L).neg() / Vec(4.0f) + (edge[k] * sin_gamma) / Vec(2.0f);
    const Vec H = sign(edge[k]) * (F - F0);
    if (k > 0) omega[k - 1] = at::vec::clamp_min(H - H_prev, Vec(0.0f)) * length;
    H_prev = H;
  }
}

void walk_row(const Settings& cfg, const Image& im, int64_t row, const Outputs& out) {
  const int64_t H = im.H, W = im.W;
  const float slice_step = float(M_PI / double(cfg.slices));
  const Vec half_pi = Vec(float(M_PI / 2)), pi = Vec(float(M_PI)), sectors = Vec(32.0f);
  // cos and sin of every pixel's slice angles, one call per row (torch evaluates them over all pixels)
  const int64_t S = cfg.slices, row_stride = (W + L - 1) / L * L;
  std::vector<float> angle(S * row_stride), cosine(S * row_stride), sine(S * row_stride);
  for (int64_t u = 0; u < row_stride; ++u) {
    const float a = cfg.jitter ? ign(float(u), float(row), cfg.seed) : 0.0f;
    for (int64_t s = 0; s < S; ++s) angle[s * row_stride + u] = (a + float(s)) * slice_step;
  }
  array_cos(angle.size(), angle.data(), cosine.data());
  array_sin(angle.size(), angle.data(), sine.data());
  const bool weights_needed = cfg.cosine || cfg.bent;
  std::vector<float> scratch(weights_needed ? 70 * L : 0), phi(cfg.bent ? 2 * kSectors * L : 0),
      trig(cfg.bent ? 2 * kSectors * L : 0);
  std::vector<Vec> step_light(cfg.indirect ? 3 * 2 * cfg.steps : 0);
  for (int64_t u0 = 0; u0 < W; u0 += L) {
    const Block blk = load_block(im, row, u0);
    const int n = blk.n;
    const int64_t at = row * W + u0;  // this block's first pixel in the image
    if (!blk.any) {
      for (int l = 0; l < n; ++l) {
        out.vis[at + l] = 1.0f;
        for (int c = 0; c < 3; ++c) {
          if (cfg.indirect) out.indirect[c * H * W + at + l] = 0.0f;
          if (cfg.bent) out.bent[c * H * W + at + l] = im.normals[3 * (at + l) + c];
        }
      }
      continue;
    }
    const Vec *P = blk.P, *N = blk.N, *V = blk.V;
    const Vec &d = blk.d, &u = blk.u, &v = blk.v;
    alignas(64) float noise[L];
    for (int l = 0; l < L; ++l) noise[l] = cfg.jitter ? ign(float(u0 + l) + 37.0f, float(row) + 59.0f, cfg.seed + 1) : 0.5f;
    const Vec xi = load_lanes(noise);
    // e1 = normalize(cross(+Y, V)) = normalize((V_z, 0, -V_x)); e2 = cross(V, e1)
    Vec e1[3], e2[3];
    {
      Vec c1[3] = {V[2], Vec(0.0f), V[0].neg()};
      Vec len1 = at::vec::clamp_min(norm3(c1), Vec(1e-12f));
      for (int c = 0; c < 3; ++c) e1[c] = c1[c] / len1;
      cross(V, e1, e2);
    }
    const Vec depth_floor = Vec(1e-20f) * (d * d);
    Vec visible = Vec(0.0f);  // uniform: unoccluded sectors summed over slices (exact small integers)
    Vec vis_num(0.0f), vis_den(0.0f), indirect[3] = {Vec(0.0f), Vec(0.0f), Vec(0.0f)}, bent[3] = {Vec(0.0f), Vec(0.0f), Vec(0.0f)};
    for (int64_t s = 0; s < cfg.slices; ++s) {
      // slice: its tangent T, the projected normal's angle gamma and length, the sector weights
      const Vec cs = Vec::loadu(cosine.data() + s * row_stride + u0), sn = Vec::loadu(sine.data() + s * row_stride + u0);
      Vec T[3], axis[3], np[3];
      for (int c = 0; c < 3; ++c) T[c] = cs * e1[c] + sn * e2[c];
      cross(T, V, axis);
      const Vec nd = dot3(N, axis);
      for (int c = 0; c < 3; ++c) np[c] = N[c] - axis[c] * nd;
      const Vec gamma = atan2_as_torch(dot3(np, T), dot3(np, V), blk.scalar_gamma != Vec(0.0f), blk.any_scalar);
      const Vec shift = (half_pi - gamma) / pi;
      Vec omega[kSectors];
      if (cfg.cosine) {
        cosine_weights(gamma, norm3(np), omega, scratch.data());
      } else {
        for (int k = 0; k < kSectors; ++k) omega[k] = Vec(1.0f / kSectors);
      }
      // screen motion (pixels per world unit along +T) of the projection (fx x/d + cx, -fy y/d + cy)
      const Vec du = (Vec(im.fx) * (T[0] + (P[0] * T[2]) / d)) / d;
      const Vec dv = (Vec(-im.fy) * (T[1] + (P[1] * T[2]) / d)) / d;
      const Vec len = norm2(du, dv);
      const Vec unit_u = du / at::vec::clamp_min(len, Vec(1e-12f)), unit_v = dv / at::vec::clamp_min(len, Vec(1e-12f));
      const Vec span = at::vec::clamp_min(Vec(cfg.radius) * len - Vec(cfg.min_step_px), Vec(0.0f));
      Int occ = Int(0);
      int64_t sent = 0;  // steps so far; step_light[3 step + c]: the step's newly occluded share x light
      for (int side = 1; side >= -1; side -= 2) {
        const Vec sgn = Vec(float(side)), scale = Vec(float(side / M_PI));
        const Vec su_dir = unit_u * sgn, sv_dir = unit_v * sgn;
        for (int64_t j = 0; j < cfg.steps; ++j) {
          // sample: the step's screen position, its fetch and its occluded interval
          Vec frac = (Vec(float(j)) + xi) / Vec(float(cfg.steps));
          if (cfg.step_power == 2.0f) {
            frac = frac * frac;
          } else if (cfg.step_power != 1.0f) {
            frac = frac.pow(Vec(cfg.step_power));
          }
          const Vec dist = Vec(cfg.min_step_px) + span * frac;
          const Vec su = u + dist * su_dir, sv = v + dist * sv_dir;
          Vec pos_s[3], sample_ok;
          Taps taps;
          fetch(im, su, sv, cfg.bilinear, cfg.drop, pos_s, sample_ok, taps);
          Vec delta[3];
          for (int c = 0; c < 3; ++c) delta[c] = pos_s[c] - P[c];
          // a sample on the centre texel (or a degenerate one) would give 0/0 angles: it never occludes
          sample_ok = sample_ok & (dot3(delta, delta) > depth_floor);
          for (int c = 0; c < 3; ++c) delta[c] = select(sample_ok, delta[c], V[c].neg());
          const Vec along_view = dot3(delta, V);
          const Vec along_tangent = sgn * dot3(delta, T);
          const Vec scalar = Vec(float(j)) >= blk.scalar_from;
          const Vec front = fma(atan2_as_torch(along_tangent, along_view, scalar, blk.any_scalar), scale, shift);
          const Vec back = fma(atan2_as_torch(along_tangent, along_view - Vec(cfg.thickness), scalar, blk.any_scalar),
                               scale, shift);
          const Vec xf = at::vec::clamp(front, Vec(0.0f), Vec(1.0f)), xb = at::vec::clamp(back, Vec(0.0f), Vec(1.0f));
          const Vec lo = side > 0 ? xf : xb, hi = side > 0 ? xb : xf;
          Vec width = (hi - lo) * sectors;
          if (cfg.epsilon > 0) width = width - Vec(cfg.epsilon);
          const Int bits = sector_bits(lo * sectors, width, cfg.rounding);
          if (cfg.indirect) {
            // the light this step sends (SectorAccumulator.step), times the share of sectors it newly occludes
            const Int fresh = bits & ~occ;
            Vec newly;
            if (cfg.cosine) {
              Vec x[kSectors];
              for (int k = 0; k < kSectors; ++k) x[k] = bit(fresh, k) * omega[k];
              newly = sum32(x);
            } else {
              newly = to_float(popcount(fresh)) * Vec(1.0f / kSectors);
            }
            const Vec distance = at::vec::clamp_min(norm3(delta), Vec(1e-30f));
            Vec ldir[3], away[3], sender_n[3];
            for (int c = 0; c < 3; ++c) {
              ldir[c] = delta[c] / distance;
              away[c] = ldir[c].neg();
              sender_n[c] = taps.gather(im.normals, c);
            }
            Vec factor = at::vec::clamp(dot3(sender_n, away), Vec(0.0f), Vec(1.0f)) * select(sample_ok, Vec(1.0f), Vec(0.0f));
            if (!cfg.cosine) factor = factor * at::vec::clamp(dot3(N, ldir), Vec(0.0f), Vec(1.0f));
            const Vec sends = width >= Vec(0.0f);  // only a non-empty interval gathers light
            for (int c = 0; c < 3; ++c) {
              const Vec light = select(sends, taps.gather(im.light, c) * factor, Vec(0.0f));
              step_light[3 * sent + c] = newly * light;
            }
          }
          occ = occ | bits;
          ++sent;
        }
      }
      // finish the slice: its visible sectors, their weights, the light, the bent normal
      if (!weights_needed) {
        visible = visible + to_float(Int(kSectors) - popcount(occ));
      } else {
        Vec wv[kSectors];
        for (int k = 0; k < kSectors; ++k) wv[k] = (Vec(1.0f) - bit(occ, k)) * omega[k];
        const Vec num = sum32(wv);
        if (cfg.cosine) {
          vis_num = s == 0 ? num : vis_num + num;
          const Vec den = sum32(omega);
          vis_den = s == 0 ? den : vis_den + den;
        } else {
          visible = visible + to_float(Int(kSectors) - popcount(occ));
        }
        if (cfg.bent) {
          // sector_centres: (gamma - pi/2) + pi (k + 1/2) / 32
          const Vec start = gamma - Vec(float(M_PI / 2));
          for (int k = 0; k < kSectors; ++k)
            (start + Vec((float(M_PI) * (float(k) + 0.5f)) / float(kSectors))).store(phi.data() + k * L);
          array_cos(kSectors * L, phi.data(), trig.data());
          array_sin(kSectors * L, phi.data(), trig.data() + kSectors * L);
          Vec xc[kSectors], xs[kSectors];
          for (int k = 0; k < kSectors; ++k) {
            xc[k] = wv[k] * Vec::loadu(trig.data() + k * L);
            xs[k] = wv[k] * Vec::loadu(trig.data() + (kSectors + k) * L);
          }
          const Vec along_v = sum32(xc), along_t = sum32(xs);
          for (int c = 0; c < 3; ++c) {
            const Vec b = along_v * V[c] + along_t * T[c];
            bent[c] = s == 0 ? b : bent[c] + b;
          }
        }
      }
      if (cfg.indirect)
        for (int c = 0; c < 3; ++c) {
          // (newly x light).sum(0) over the slice's steps: the product is laid out step-fastest per channel
          const Vec light = row_sum(step_light.data() + c, sent, 3);
          indirect[c] = s == 0 ? light : indirect[c] + light;
        }
    }
    // finish: average over slices (uniform) or divide by the cosine weights' total
    Vec den;
    Vec vis;
    if (cfg.cosine) {
      den = at::vec::clamp_min(vis_den, Vec(1e-30f));
      vis = vis_num / den;
    } else {
      den = Vec(float(cfg.slices));
      vis = (visible * Vec(1.0f / 32.0f)) / den;
    }
    const Vec live = blk.live;
    store_lanes(select(live, vis, Vec(1.0f)), n, out.vis + at);
    if (cfg.indirect)
      for (int c = 0; c < 3; ++c) store_lanes(select(live, indirect[c] / den, Vec(0.0f)), n, out.indirect + c * H * W + at);
    if (cfg.bent) {
      // F.normalize where the sum is not ~0, else the pixel's normal
      const Vec nb = norm3(bent);
      const Vec has = nb > Vec(1e-12f), scale = at::vec::clamp_min(nb, Vec(1e-12f));
      for (int c = 0; c < 3; ++c) store_lanes(select(live & has, bent[c] / scale, N[c]), n, out.bent + c * H * W + at);
    }
  }
}

// ====================================================================================== "ssilvb_glsl" variant

struct GlslSettings {
  int64_t slices, steps;  // the shader's sliceCount, sampleCount: it walks slices + 1 and steps + 1
  float thickness;
  bool jitter, indirect;
  int64_t numerics, rounding;  // numerics: 0 ieee, 1 mesa, 2 mesa_mediump
};

// The driver's dot / length / normalize (bitmask_glsl.GLSLVectorOps): llvmpipe's ("mesa") or torch's ("ieee")
struct GlslOps {
  bool exact;
  Vec dot(const Vec* a, const Vec* b) const { return exact ? (a[1] * b[1] + a[2] * b[2]) + a[0] * b[0] : dot3(a, b); }
  Vec length(const Vec* a) const { return exact ? dot(a, a).sqrt() : norm3(a); }
  void normalize(const Vec* a, Vec* out) const {
    if (exact) {
      const Vec inv = Vec(1.0f) / dot(a, a).sqrt();
      for (int c = 0; c < 3; ++c) out[c] = a[c] * inv;
    } else {
      const Vec len = at::vec::clamp_min(norm3(a), Vec(1e-12f));
      for (int c = 0; c < 3; ++c) out[c] = a[c] / len;
    }
  }
};

// Mesa's GLSL asin polynomial (bitmask_glsl.mesa_asin), x in [-1, 1]
inline Vec mesa_asin(const Vec& x) {
  const Vec half_pi(float(M_PI / 2)), quarter_pi_m1(float(M_PI / 4) - 1.0f);
  const Vec ax = x.abs();
  const Vec poly = half_pi + ax * (quarter_pi_m1 + ax * (Vec(0.08132463f) + ax * Vec(-0.02363318f)));
  return sign(x) * (half_pi - (Vec(1.0f) - ax).sqrt() * poly);
}

inline float half_round(float x) { return float(c10::Half(x)); }

// randf(int(gl_FragCoord.x), int(gl_FragCoord.y)) - 0.5 (bitmask_glsl.glsl_jitter): float32, or float16 per op
inline float glsl_jitter(float u, float y_gl, bool mediump) {
  if (!mediump) {
    const float a = 0.06711056f * u, b = 0.00583715f * y_gl;
    const float s = a + b, inner = s - std::floor(s);
    const float g = 52.9829189f * inner;
    return (g - std::floor(g)) - 0.5f;
  }
  const float x = half_round(u), y = half_round(y_gl);
  const float a = half_round(half_round(0.06711056f) * x), b = half_round(half_round(0.00583715f) * y);
  const float s = half_round(a + b), inner = half_round(s - std::floor(s));
  const float g = half_round(half_round(52.9829189f) * inner);
  return half_round(g - std::floor(g)) - 0.5f;
}

void walk_row_glsl(const GlslSettings& cfg, const Image& im, int64_t row, float radius_scale, float* vis_out,
                   float* light_out) {
  const int64_t H = im.H, W = im.W, S = cfg.slices + 1, J = cfg.steps + 1;
  const GlslOps gl{cfg.numerics != 0};
  const float pi_f = 3.14159265359f, two_pi = 2.0f * pi_f, half_pi_f = 0.5f * pi_f;
  const float rotation = two_pi / float(double(cfg.slices) - 1.0);
  const Vec pi(pi_f), half_pi(half_pi_f), t(cfg.thickness);
  const int64_t row_stride = (W + L - 1) / L * L;
  // the slice directions (cos phi, sin phi), phi = rotation (s + jitter) + pi, one call per row
  std::vector<float> jitter(row_stride), angle(S * row_stride), cosine(S * row_stride), sine(S * row_stride);
  const float y_gl = float(H - 1) - float(row);
  for (int64_t u = 0; u < row_stride; ++u) {
    jitter[u] = cfg.jitter ? glsl_jitter(float(u), y_gl, cfg.numerics == 2) : 0.0f;
    for (int64_t s = 0; s < S; ++s) angle[s * row_stride + u] = rotation * (float(s) + jitter[u]) + pi_f;
  }
  array_cos(angle.size(), angle.data(), cosine.data());
  array_sin(angle.size(), angle.data(), sine.data());
  // per step of a slice: the front and back cosines (then their acos), the sample's state
  std::vector<float> cosines(2 * J * L), clean(2 * J * L), angles(2 * J * L), n_in(L), n_out(L);
  std::vector<Vec> horizon(3 * J), sample_ok(J), centre(J);
  std::vector<Taps> taps(J);
  const Vec aspect(float(H) / float(W)), count(float(cfg.steps));
  for (int64_t u0 = 0; u0 < W; u0 += L) {
    const Block blk = load_block(im, row, u0);
    const int n = blk.n;
    if (!blk.any) {
      for (int l = 0; l < n; ++l) vis_out[row * W + u0 + l] = 1.0f;
      if (light_out)
        for (int c = 0; c < 3; ++c)
          for (int l = 0; l < n; ++l) light_out[c * H * W + row * W + u0 + l] = 0.0f;
      continue;
    }
    const Vec *P = blk.P, *V = blk.V;
    const Vec &u = blk.u, &v = blk.v;
    Vec camera[3], normal[3];
    if (gl.exact) {
      const Vec minus[3] = {P[0].neg(), P[1].neg(), P[2].neg()};
      gl.normalize(minus, camera);
    } else {
      for (int c = 0; c < 3; ++c) camera[c] = V[c];
    }
    gl.normalize(blk.N, normal);
    const Vec jit = Vec::loadu(jitter.data() + u0);
    const Vec scale = Vec(radius_scale) / P[2];  // sampleScale = -radius P[0][0] / position.z
    const Vec frag_u = (u + Vec(0.5f)) / Vec(float(W)), frag_v = ((Vec(float(H - 1)) - v) + Vec(0.5f)) / Vec(float(H));
    const Vec depth_floor = Vec(1e-20f) * (blk.d * blk.d);
    const Vec sectors = Vec(float(kSectors));
    Int occ(0);  // not reset across slices (as written)
    Vec visibility(0.0f), lighting[3] = {Vec(0.0f), Vec(0.0f), Vec(0.0f)};
    for (int64_t s = 0; s < S; ++s) {
      // slice: direction, projected normal, its angle n
      const Vec ox = Vec::loadu(cosine.data() + s * row_stride + u0), oy = Vec::loadu(sine.data() + s * row_stride + u0);
      const Vec direction[3] = {ox, oy, Vec(0.0f)};
      const Vec dc = gl.dot(direction, camera);
      Vec ortho[3], axis[3], proj[3];
      for (int c = 0; c < 3; ++c) ortho[c] = direction[c] - dc * camera[c];
      cross(direction, camera, axis);  // not normalised (as written)
      const Vec na = gl.dot(normal, axis);
      for (int c = 0; c < 3; ++c) proj[c] = normal[c] - axis[c] * na;
      const Vec sign_n = sign(gl.dot(ortho, proj));
      const Vec cos_n = at::vec::clamp(gl.dot(proj, camera) / gl.length(proj), Vec(0.0f), Vec(1.0f));
      Vec n_angle;
      if (gl.exact) {
        n_angle = sign_n * (half_pi - mesa_asin(cos_n));
      } else {
        cos_n.store(n_in.data());
        array_acos(L, n_in.data(), n_out.data());
        n_angle = sign_n * Vec::loadu(n_out.data());
      }
      // samples: one side, steps + 1 nearest texels
      for (int64_t j = 0; j < J; ++j) {
        const Vec step = ((Vec(float(j)) + jit) / count) + Vec(0.01f);
        const Vec f = step * scale;
        const Vec uv_u = frag_u - (f * ox) * aspect, uv_v = frag_v - (f * oy) * Vec(1.0f);
        const Vec tx = at::vec::clamp((uv_u * Vec(float(W))).floor(), Vec(0.0f), Vec(float(W - 1)));
        const Vec ty = at::vec::clamp((uv_v * Vec(float(H))).floor(), Vec(0.0f), Vec(float(H - 1)));
        const Vec off_u = tx - u, off_v = (Vec(float(H - 1)) - ty) - v;
        centre[j] = (off_u == Vec(0.0f)) & (off_v == Vec(0.0f));
        Vec pos_s[3], ok, delta[3];
        fetch(im, u + off_u, v + off_v, false, false, pos_s, ok, taps[j]);
        for (int c = 0; c < 3; ++c) delta[c] = pos_s[c] - P[c];
        ok = ok & (dot3(delta, delta) > depth_floor);
        for (int c = 0; c < 3; ++c) delta[c] = select(ok, delta[c], V[c].neg());
        sample_ok[j] = ok;
        const Vec dl = gl.length(delta);
        Vec* h = &horizon[3 * j];
        for (int c = 0; c < 3; ++c) h[c] = delta[c] / dl;
        Vec behind[3], back_dir[3];
        for (int c = 0; c < 3; ++c) behind[c] = delta[c] - camera[c] * t;
        gl.normalize(behind, back_dir);
        gl.dot(h, camera).store(cosines.data() + 2 * j * L);
        gl.dot(back_dir, camera).store(cosines.data() + (2 * j + 1) * L);
      }
      // _horizon: clamp((acos(c) + n + halfPi) / pi, 0, 1), 0 where acos is NaN (|c| > 1 or NaN)
      if (!gl.exact) {
        for (int64_t i = 0; i < 2 * J; ++i) {
          const Vec c = Vec::loadu(cosines.data() + i * L);
          select(c.abs() <= Vec(1.0f), c, Vec(0.0f)).store(clean.data() + i * L);
        }
        array_acos(2 * J * L, clean.data(), angles.data());
      }
      auto horizon_of = [&](const Vec& raw, int64_t i) {
        const Vec good = raw.abs() <= Vec(1.0f);
        const Vec c = select(good, raw, Vec(0.0f));
        const Vec value = gl.exact ? ((pi - mesa_asin(c)) + n_angle) / pi
                                   : ((Vec::loadu(angles.data() + i * L) + n_angle) + half_pi) / pi;
        return select(good, at::vec::clamp(value, Vec(0.0f), Vec(1.0f)), Vec(0.0f));
      };
      Vec centre_back;
      if (gl.exact) {  // a centre-texel sample's back direction: normalize(-camera t)
        Vec minus[3], dir[3];
        for (int c = 0; c < 3; ++c) minus[c] = (camera[c] * t).neg();
        gl.normalize(minus, dir);
        const Vec raw = gl.dot(dir, camera);
        const Vec good = raw.abs() <= Vec(1.0f);
        const Vec value = ((pi - mesa_asin(select(good, raw, Vec(0.0f)))) + n_angle) / pi;
        centre_back = select(good, at::vec::clamp(value, Vec(0.0f), Vec(1.0f)), Vec(0.0f));
      } else {
        centre_back = Vec(cfg.thickness > 0 ? 1.0f : 0.0f);
      }
      for (int64_t j = 0; j < J; ++j) {
        Vec x = horizon_of(Vec::loadu(cosines.data() + 2 * j * L), 2 * j);
        Vec y = horizon_of(Vec::loadu(cosines.data() + (2 * j + 1) * L), 2 * j + 1);
        x = select(sample_ok[j], x, Vec(1.0f));
        y = select(sample_ok[j], y, Vec(1.0f));
        x = select(centre[j], Vec(0.0f), x);
        y = select(centre[j], centre_back, y);
        const Int bits = sector_bits(x * sectors, (y - x) * sectors, cfg.rounding);
        if (cfg.indirect) {
          const Vec* h = &horizon[3 * j];
          Vec raw_n[4], light[4], sample_n[3], away[3];
          gather_records(im.normals, taps[j].index[0], raw_n);
          gather_records(im.light, taps[j].index[0], light);
          for (int c = 0; c < 3; ++c) away[c] = h[c].neg();
          gl.normalize(raw_n, sample_n);
          const Vec c1 = at::vec::clamp(gl.dot(normal, h), Vec(0.0f), Vec(1.0f));
          const Vec c2 = at::vec::clamp(gl.dot(sample_n, away), Vec(0.0f), Vec(1.0f)) *
                         select(sample_ok[j], Vec(1.0f), Vec(0.0f));
          const Vec newly = to_float(popcount(bits & ~occ));
          const Vec weight = Vec(1.0f) - newly / sectors;
          for (int c = 0; c < 3; ++c) lighting[c] = lighting[c] + weight * ((light[c] * c1) * c2);
        }
        occ = occ | bits;
      }
      visibility = visibility + (Vec(1.0f) - to_float(popcount(occ)) / sectors);
    }
    const Vec live = blk.live, slices = Vec(float(cfg.slices));
    store_lanes(select(live, visibility / slices, Vec(1.0f)), n, vis_out + row * W + u0);
    if (light_out)
      for (int c = 0; c < 3; ++c)
        store_lanes(select(live, lighting[c] / slices, Vec(0.0f)), n, light_out + c * H * W + row * W + u0);
  }
}

// ====================================================================================== the ops

void check_inputs(std::initializer_list<const at::Tensor*> floats, const at::Tensor& valid) {
  for (const at::Tensor* t : floats)
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous(), "expected contiguous float32 inputs");
  TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous(), "valid: expected contiguous bool");
}

Image image_of(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
               const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor* light,
               int64_t b, const at::Tensor* scalar_from = nullptr, const at::Tensor* scalar_gamma = nullptr) {
  const int64_t H = positions.size(1), W = positions.size(2), plane = b * H * W, stride = positions.size(3);
  TORCH_CHECK(normals.size(3) == stride && (!light || light->size(3) == stride), "expected channel-last inputs of one width");
  const float* K = intrinsics.data_ptr<float>() + 4 * b;
  return Image{positions.data_ptr<float>() + stride * plane, normals.data_ptr<float>() + stride * plane,
               inverse_depth.data_ptr<float>() + plane, depth.data_ptr<float>() + plane,
               light ? light->data_ptr<float>() + stride * plane : nullptr, int(stride), valid.data_ptr<bool>() + plane,
               scalar_from ? scalar_from->data_ptr<int32_t>() + plane : nullptr,
               scalar_gamma ? scalar_gamma->data_ptr<bool>() + plane : nullptr, K[0], K[1], K[2], K[3], H, W};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> bitmask_walk(
    const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth, const at::Tensor& depth,
    const at::Tensor& valid, const at::Tensor& intrinsics, const at::Tensor& light, const at::Tensor& scalar_from,
    const at::Tensor& scalar_gamma, int64_t slices, int64_t steps, double radius, double thickness, double step_power, double min_step_px, bool jitter, int64_t seed, bool bilinear,
    bool drop, int64_t rounding, double epsilon, bool cosine, bool indirect, bool bent) {
  TORCH_CHECK(positions.dim() == 4 && positions.size(3) == 3, "positions: expected (B, H, W, 3)");
  check_inputs({&positions, &normals, &inverse_depth, &depth, &intrinsics}, valid);
  if (indirect) check_inputs({&light}, valid);
  TORCH_CHECK(scalar_from.scalar_type() == at::kInt && scalar_from.is_contiguous() && scalar_gamma.scalar_type() == at::kBool &&
              scalar_gamma.is_contiguous(), "scalar_from, scalar_gamma: expected contiguous int32 and bool maps");
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2);
  Settings cfg{slices, steps, float(radius), float(thickness), float(step_power), float(min_step_px),
               float(epsilon), jitter, bilinear, drop, seed, rounding, cosine, indirect, bent};
  at::Tensor vis = at::empty({B, 1, H, W}, positions.options());
  at::Tensor ind = at::empty({indirect ? B : 0, 3, H, W}, positions.options());
  at::Tensor bn = at::empty({bent ? B : 0, 3, H, W}, positions.options());
  over_rows(B * H, [&](int64_t r) {
    const int64_t b = r / H;
    const Image im = image_of(positions, normals, inverse_depth, depth, valid, intrinsics, indirect ? &light : nullptr, b,
                              &scalar_from, &scalar_gamma);
    const Outputs out{vis.data_ptr<float>() + b * H * W, indirect ? ind.data_ptr<float>() + b * 3 * H * W : nullptr,
                      bent ? bn.data_ptr<float>() + b * 3 * H * W : nullptr};
    walk_row(cfg, im, r % H, out);
  });
  return {vis, ind, bn};
}

std::tuple<at::Tensor, at::Tensor> glsl_walk(const at::Tensor& positions, const at::Tensor& normals,
                                             const at::Tensor& inverse_depth, const at::Tensor& depth,
                                             const at::Tensor& valid, const at::Tensor& intrinsics,
                                             const at::Tensor& radius_scale, const at::Tensor& light, int64_t slices,
                                             int64_t steps, double thickness, bool jitter, int64_t numerics,
                                             int64_t rounding, bool indirect) {
  TORCH_CHECK(positions.dim() == 4, "positions: expected (B, H, W, 4)");
  TORCH_CHECK(slices >= 2 && steps >= 1, "slices >= 2 and steps >= 1 expected");
  TORCH_CHECK(positions.size(3) == 4, "positions: expected (B, H, W, 4) records (x, y, z, inverse depth)");
  check_inputs({&positions, &normals, &inverse_depth, &depth, &intrinsics, &radius_scale}, valid);
  if (indirect) check_inputs({&light}, valid);
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2);
  GlslSettings cfg{slices, steps, float(thickness), jitter, indirect, numerics, rounding};
  at::Tensor vis = at::empty({B, 1, H, W}, positions.options());
  at::Tensor ind = at::empty({indirect ? B : 0, 3, H, W}, positions.options());
  const float* scale = radius_scale.data_ptr<float>();
  over_rows(B * H, [&](int64_t r) {
    const int64_t b = r / H;
    const Image im = image_of(positions, normals, inverse_depth, depth, valid, intrinsics, indirect ? &light : nullptr, b);
    walk_row_glsl(cfg, im, r % H, scale[b], vis.data_ptr<float>() + b * H * W,
                  indirect ? ind.data_ptr<float>() + b * 3 * H * W : nullptr);
  });
  return {vis, ind};
}

}  // namespace

TORCH_LIBRARY(torch_ao_kernels, m) {
  m.def("bitmask_walk(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor light, Tensor scalar_from, Tensor scalar_gamma, int slices, int steps, float radius, float thickness, float step_power, "
        "float min_step_px, bool jitter, int seed, bool bilinear, bool drop, int rounding, float epsilon, "
        "bool cosine, bool indirect, bool bent) -> (Tensor, Tensor, Tensor)");
  m.def("glsl_walk(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor radius_scale, Tensor light, int slices, int steps, float thickness, bool jitter, "
        "int numerics, int rounding, bool indirect) -> (Tensor, Tensor)");
  m.impl("bitmask_walk", c10::DispatchKey::CPU, TORCH_FN(bitmask_walk));
  m.impl("glsl_walk", c10::DispatchKey::CPU, TORCH_FN(glsl_walk));
}
