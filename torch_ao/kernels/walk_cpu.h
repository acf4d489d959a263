// The float helpers of the two CPU kernels not yet on the one walk (walk.h): the soft / straight-through
// kernel and the ssilvb_glsl one, which still reproduce the tensor path's float operations.
//
// The float arithmetic repeats the tensor path's operation by operation: where a torch CPU kernel
// fuses a multiply and an add (cross products, addcmul, lerp, the tail of a 2-/3-element norm) this
// code calls fma, and nowhere else (the kernels are built with -ffp-contract=off); torch's unary
// functions that call MKL's vector math on this build (cos, sin, asin, sqrt) are MKL's here too.
#pragma once

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <ATen/ops/empty.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "mkl_vml.h"  // torch.cos/torch.sin on a build with MKL call its vector math; so do the kernels
#include "lanes_simd.h"
#include "rows_cpu.h"
#include "walk.h"

namespace torch_ao_walk {

using torch_ao_rows::for_each_row;
using torch_ao_rows::over_rows;

using Vec = at::vec::Vectorized<float>;
using Int = at::vec::Vectorized<int32_t>;
constexpr int L = Vec::size();

inline Vec fma(const Vec& a, const Vec& b, const Vec& c) { return at::vec::fmadd(a, b, c); }
inline Vec dot3(const Vec* a, const Vec* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }
// torch's norm over a last dimension shorter than a vector: an fma chain, then sqrt
inline Vec norm3(const Vec* a) { return fma(a[2], a[2], fma(a[1], a[1], a[0] * a[0])).sqrt(); }
inline Vec norm2(const Vec& a, const Vec& b) { return fma(b, b, a * a).sqrt(); }
inline Vec select(const Vec& mask, const Vec& yes, const Vec& no) { return Vec::blendv(no, yes, mask); }
// torch.sign (0 for 0 and NaN)
inline Vec sign(const Vec& x) {
  return select(x > Vec(0.0f), Vec(1.0f), select(x < Vec(0.0f), Vec(-1.0f), Vec(0.0f)));
}
// torch's cross(a, b) as its CPU kernel evaluates it
inline void cross(const Vec* a, const Vec* b, Vec* out) {
  out[0] = fma(a[1], b[2], (a[2] * b[1]).neg());
  out[1] = fma(a[2], b[0], (a[0] * b[2]).neg());
  out[2] = fma(a[0], b[1], (a[1] * b[0]).neg());
}
// F.normalize(x, eps=1e-12)
inline void normalize3(const Vec* x, Vec* out) {
  const Vec len = at::vec::clamp_min(norm3(x), Vec(1e-12f));
  for (int c = 0; c < 3; ++c) out[c] = x[c] / len;
}
// torch.lerp: start + w (end - start) for |w| < 0.5, else end - (1 - w) (end - start), both fused
inline Vec lerp(const Vec& start, const Vec& end, const Vec& w) {
  Vec small = w.abs() < Vec(0.5f);
  return fma(select(small, w, w - Vec(1.0f)), end - start, select(small, start, end));
}
inline Int to_int(const Vec& x) { return at::vec::convert_to_int_of_same_size<float>(x); }

// cos and sin of n * L floats, through MKL's vector math where torch.cos/torch.sin use it
inline void cos_sin(const Vec* x, int n, Vec* cosine, Vec* sine) {
#ifdef TORCH_AO_MKL_VML
  constexpr long long mode = kVmlMode;
  alignas(64) float in[8 * L], out[8 * L];
  for (int i = 0; i < n; ++i) x[i].store(in + i * L);
  if (cosine != nullptr) {
    vmsCos(n * L, in, out, mode);
    for (int i = 0; i < n; ++i) cosine[i] = Vec::loadu(out + i * L);
  }
  if (sine != nullptr) {
    vmsSin(n * L, in, out, mode);
    for (int i = 0; i < n; ++i) sine[i] = Vec::loadu(out + i * L);
  }
#else
  for (int i = 0; i < n; ++i) {
    if (cosine != nullptr) cosine[i] = x[i].cos();
    if (sine != nullptr) sine[i] = x[i].sin();
  }
#endif
}

#ifdef TORCH_AO_MKL_VML
// one VML function on L floats
inline Vec vml(void (*fn)(int, const float*, float*, long long), const Vec& x) {
  alignas(64) float in[L], out[L];
  x.store(in);
  fn(L, in, out, kVmlMode);
  return Vec::loadu(out);
}
#endif

// torch.asin, torch.sqrt: MKL's vector math where torch calls it (its sqrt is accurate to 1 ulp, not
// always the IEEE root that torch's norms and Vec::sqrt give), else SLEEF / the instruction
#ifdef TORCH_AO_MKL_VML
inline Vec asin(const Vec& x) { return vml(vmsAsin, x); }
inline Vec sqrt(const Vec& x) { return vml(vmsSqrt, x); }
#else
inline Vec asin(const Vec& x) { return x.asin(); }
inline Vec sqrt(const Vec& x) { return x.sqrt(); }
#endif

// the noise: walk.h's
using tao::ign;

// The perspective-correct bilinear footprint of samples at screen (su, sv) (torch_ao.walk.fetch.bilinear_taps):
// the top-left texel (fu0, fv0), the fractions (fu, fv), the four taps' inverse depths t0..t3 of the
// (W x H) image `inverse_depth` (rows and columns clamped to the image), whether all four are valid
// (an invalid texel holds NaN), and the four texels' indices (to read other images at the same taps).
struct BilinearTaps {
  Vec fu0, fv0, fu, fv, t0, t1, t2, t3, ok;
  Int index[4];
};

inline BilinearTaps bilinear_taps(const float* inverse_depth, const Vec& su, const Vec& sv, int64_t W, int64_t H) {
  const Int zero = Int(0), one = Int(1), Wi = Int(int32_t(W)), Wlast = Int(int32_t(W - 1)), Hlast = Int(int32_t(H - 1));
  BilinearTaps tap;
  tap.fu0 = su.floor();
  tap.fv0 = sv.floor();
  tap.fu = su - tap.fu0;
  tap.fv = sv - tap.fv0;
  const Int iu = at::vec::convert_to_int_of_same_size<float>(at::vec::clamp(tap.fu0, Vec(-1.0f), Vec(float(W))));
  const Int iv = at::vec::convert_to_int_of_same_size<float>(at::vec::clamp(tap.fv0, Vec(-1.0f), Vec(float(H))));
  const Int c0 = at::vec::clamp(iu, zero, Wlast), c1 = at::vec::clamp(iu + one, zero, Wlast);
  const Int r0 = at::vec::clamp(iv, zero, Hlast) * Wi, r1 = at::vec::clamp(iv + one, zero, Hlast) * Wi;
  tap.index[0] = r0 + c0, tap.index[1] = r0 + c1, tap.index[2] = r1 + c0, tap.index[3] = r1 + c1;
  tap.t0 = at::vec::gather<4>(inverse_depth, tap.index[0]);
  tap.t1 = at::vec::gather<4>(inverse_depth, tap.index[1]);
  tap.t2 = at::vec::gather<4>(inverse_depth, tap.index[2]);
  tap.t3 = at::vec::gather<4>(inverse_depth, tap.index[3]);
  tap.ok = (tap.t0 == tap.t0) & (tap.t1 == tap.t1) & (tap.t2 == tap.t2) & (tap.t3 == tap.t3);
  return tap;
}


}  // namespace torch_ao_walk
