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
#include "bitmask.h"

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
using tao::kSectors;

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

inline Vec load_lanes(const float* lanes) { return Vec::loadu(lanes); }
using tao::bit;
using tao::popcount;
using tao::to_float;
inline Int operator~(const Int& x) { return x ^ Int(-1); }

using tao::sector_bits;  // bitmask.h: the sector rule

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
  m.def("glsl_walk(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor radius_scale, Tensor light, int slices, int steps, float thickness, bool jitter, "
        "int numerics, int rounding, bool indirect) -> (Tensor, Tensor)");
  m.impl("glsl_walk", c10::DispatchKey::CPU, TORCH_FN(glsl_walk));
}
