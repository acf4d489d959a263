// The pixels of a row in SIMD lanes: ATen's Vectorized<float> (AVX2 / AVX-512 as torch dispatches,
// SLEEF's vector cos, sin, pow; atan2 our polynomial below), the CPU kernels' lane type. Same names as lanes_scalar.h.
#pragma once

#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>

#include "lanes_scalar.h"

namespace tao {

using Vec = at::vec::Vectorized<float>;
using IVec = at::vec::Vectorized<int32_t>;

template <> struct LaneTraits<Vec> {
  using M = Vec;  // all-ones / all-zeros lanes
  using I = IVec;
  static constexpr int L = Vec::size();
};

inline Vec from_lanes(const float* x, Vec) { return Vec::loadu(x); }
inline void to_lanes(const Vec& x, float* out) { x.store(out); }
inline Vec select(const Vec& m, const Vec& yes, const Vec& no) { return Vec::blendv(no, yes, m); }
inline IVec select(const Vec& m, const IVec& yes, const IVec& no) {
  const IVec mi = at::vec::cast<int32_t>(m);
  return (yes & mi) | (no & (mi ^ IVec(-1)));
}
inline Vec ieq(const IVec& a, const IVec& b) { return at::vec::cast<float>(a == b); }
inline Vec land(const Vec& a, const Vec& b) { return a & b; }
inline Vec lor(const Vec& a, const Vec& b) { return a | b; }
inline Vec lnot(const Vec& a) { return a ^ Vec(at::vec::cast<float>(IVec(-1))); }
inline bool any(const Vec& m) { return m.zero_mask() != (1 << Vec::size()) - 1; }
inline bool lane_on(const Vec& m, int l) { return !((m.zero_mask() >> l) & 1); }
inline uint32_t lane_bits(const Vec& m) { return ~uint32_t(m.zero_mask()) & ((1u << Vec::size()) - 1u); }
inline void store_lanes(const IVec& x, int32_t* out) { x.store(out); }
inline IVec from_lanes(const int32_t* x, IVec) { return IVec::loadu(x); }
// the least and the greatest of the lanes (NaN lanes: either)
inline float reduce_min(const Vec& x) {
  alignas(64) float v[Vec::size()];
  x.store(v);
  float m = v[0];
  for (int l = 1; l < Vec::size(); ++l) m = v[l] < m ? v[l] : m;
  return m;
}
inline float reduce_max(const Vec& x) { return -reduce_min(x.neg()); }
inline Vec neg(const Vec& x) { return x.neg(); }
inline Vec fma(const Vec& a, const Vec& b, const Vec& c) { return at::vec::fmadd(a, b, c); }
inline Vec abs(const Vec& x) { return x.abs(); }
// the lanes whose sign bit is clear (+0 and +NaN included)
inline Vec sign_clear(const Vec& x) { return at::vec::cast<float>(at::vec::cast<int32_t>(x) >= IVec(0)); }
inline Vec sqrt(const Vec& x) { return x.sqrt(); }
inline Vec floor(const Vec& x) { return x.floor(); }
inline Vec ceil(const Vec& x) { return x.ceil(); }
inline Vec rint(const Vec& x) { return x.round(); }  // half to even
// atan2 within 3e-7 rad (measured over 32 M random pairs: 2.96e-7, about an ulp of the result near pi):
// atan(t) = t P(t^2) for t = min(|x|, |y|) / max(|x|, |y|) in [0, 1] (P a degree-8 least-squares fit in
// relative error: |atan(t) - t P(t^2)| <= 1.1e-7 in float32), then the octant. SLEEF's 1-ulp atan2
// (Vectorized::atan2) costs about twice as much, where the walk agrees with its tensor-op specification by
// tolerance anyway. Signed zeros as IEEE's (atan2(+-0, -0) = +-pi); NaN in gives NaN; both infinite gives
// NaN (IEEE: an odd multiple of pi/4), which the walk never takes.
__attribute__((always_inline)) inline Vec atan2(const Vec& y, const Vec& x) {
  constexpr float c[9] = {0.9999998807907104f, -0.33332598209381104f, 0.19985906779766083f, -0.14161229133605957f,
                          0.1049894392490387f, -0.07234849035739899f, 0.03978109732270241f, -0.01440126821398735f,
                          0.0024566997308284044f};
  const Vec ax = x.abs(), ay = y.abs();
  const Vec hi = at::vec::maximum(ax, ay), lo = at::vec::minimum(ax, ay);
  const Vec t = Vec::blendv(lo / hi, Vec(0.0f), hi == Vec(0.0f));
  const Vec s = t * t;
  Vec p(c[8]);
  for (int k = 7; k >= 0; --k) p = at::vec::fmadd(p, s, Vec(c[k]));
  Vec r = t * p;
  r = Vec::blendv(r, Vec(1.57079632679489661923f) - r, ay > ax);
  const Vec x_negative = at::vec::cast<float>(at::vec::cast<int32_t>(x) < IVec(0));  // (its sign bit: -0 too)
  r = Vec::blendv(r, Vec(3.14159265358979323846f) - r, x_negative);
  return r | (y & Vec(-0.0f));  // y's sign (r >= 0)
}
inline Vec acos(const Vec& x) { return x.acos(); }
inline Vec asin(const Vec& x) { return x.asin(); }
inline Vec cos(const Vec& x) { return x.cos(); }
inline Vec sin(const Vec& x) { return x.sin(); }
// (lanes_scalar.h's, in SLEEF's double vectors: 1 ulp of double)
inline void cos_sin_rounded(const Vec& x, Vec& c, Vec& s) {
  using D = at::vec::Vectorized<double>;
  constexpr int L = Vec::size();
  alignas(64) float in[L], out_c[L], out_s[L];
  alignas(64) double wide[L], wide_c[L], wide_s[L];
  x.store(in);
  for (int l = 0; l < L; ++l) wide[l] = double(in[l]);
  for (int k = 0; k < L; k += D::size()) {
    const D v = D::loadu(wide + k);
    v.cos().store(wide_c + k);
    v.sin().store(wide_s + k);
  }
  for (int l = 0; l < L; ++l) out_c[l] = float(wide_c[l]), out_s[l] = float(wide_s[l]);
  c = Vec::loadu(out_c), s = Vec::loadu(out_s);
}
inline Vec pow(const Vec& x, const Vec& y) { return x.pow(y); }
// e^z inline for z in [-87, 87] (2^n stays normal): e^z = 2^n e^r (n = round(z log2 e), r by Cody and Waite's
// two-part ln 2, |r| <= ln 2 / 2, e^r by its degree-6 Taylor polynomial: 1.2e-7 relative). SLEEF's exp is an
// out-of-line call, too slow for the soft union's 64 logistics per step.
__attribute__((always_inline)) inline Vec exp_inline(const Vec& z) {
  const Vec n = (z * Vec(1.44269504088896341f)).round();
  const Vec r = at::vec::fmadd(n, Vec(2.12194440e-4f), at::vec::fmadd(n, Vec(-0.693359375f), z));
  constexpr float c[7] = {1.0f, 1.0f, 1.0f / 2, 1.0f / 6, 1.0f / 24, 1.0f / 120, 1.0f / 720};
  Vec p(c[6]);
  for (int k = 5; k >= 0; --k) p = at::vec::fmadd(p, r, Vec(c[k]));
  const IVec exponent = (at::vec::convert_to_int_of_same_size<float>(n) + IVec(127)) << IVec(23);
  return p * at::vec::cast<float>(exponent);
}
// 1 / (1 + e) for e in [0, 2^126]: the hardware's reciprocal estimate refined by one Newton step (with exp_inline
// in logistic, measured within 3.2e-7 relative), where a division's latency would stall the soft union
__attribute__((always_inline)) inline Vec inverse_one_plus(const Vec& e) {
  const Vec d = Vec(1.0f) + e;
#if defined(CPU_CAPABILITY_AVX512)
  const Vec y(_mm512_rcp14_ps(d));  // 14 bits
#elif defined(CPU_CAPABILITY_AVX2)
  const Vec y(_mm256_rcp_ps(d));  // 12 bits
#else
  return d.reciprocal();
#endif
  return y * at::vec::fmadd(d.neg(), y, Vec(2.0f));
}
// The logistic 1 / (1 + e^-x), x clamped to [-87, 87]
__attribute__((always_inline)) inline Vec logistic(const Vec& x) {
  return inverse_one_plus(exp_inline(at::vec::clamp(x.neg(), Vec(-87.0f), Vec(87.0f))));
}
inline Vec exp(const Vec& x) { return x.exp(); }
// e^x - 1 inline: exp_inline(x) - 1 where |x| >= 1/4 (x clamped to [-87, 87]; |e^x - 1| >= 0.22 there: within 6e-7
// relative), below that its degree-7 Taylor polynomial (within 2e-7). SLEEF's is an out-of-line call, one per step
// of the soft union (its gate, sweeps.expm1_tanh)
inline Vec expm1(const Vec& x) {
  constexpr float c[7] = {1.0f, 1.0f / 2, 1.0f / 6, 1.0f / 24, 1.0f / 120, 1.0f / 720, 1.0f / 5040};
  Vec p(c[6]);
  for (int k = 5; k >= 0; --k) p = at::vec::fmadd(p, x, Vec(c[k]));
  const Vec large = exp_inline(at::vec::clamp(x, Vec(-87.0f), Vec(87.0f))) - Vec(1.0f);
  return select(x.abs() < Vec(0.25f), p * x, large);
}
inline Vec max(const Vec& a, const Vec& b) { return at::vec::maximum(a, b); }
inline Vec min(const Vec& a, const Vec& b) { return at::vec::minimum(a, b); }
inline Vec clamp_min(const Vec& x, const Vec& lo) { return at::vec::clamp_min(x, lo); }
inline Vec clamp_max(const Vec& x, const Vec& hi) { return at::vec::clamp_max(x, hi); }
inline Vec clamp(const Vec& x, const Vec& lo, const Vec& hi) { return at::vec::clamp(x, lo, hi); }
inline Vec rsqrt(const Vec& x) { return x.rsqrt(); }
inline Vec reciprocal(const Vec& x) { return x.reciprocal(); }

inline IVec to_int(const Vec& x) { return at::vec::convert_to_int_of_same_size<float>(x); }
inline Vec to_float(const IVec& x) { return at::vec::convert_to_fp_of_same_size<float>(x); }
inline IVec imin(const IVec& a, const IVec& b) { return at::vec::minimum(a, b); }
inline IVec imax(const IVec& a, const IVec& b) { return at::vec::maximum(a, b); }
inline IVec bnot(const IVec& x) { return x ^ IVec(-1); }
inline IVec low_bits(const IVec& k) { return (IVec(1) << k) - IVec(1); }  // a shift by 32 gives 0: all ones
inline Vec bit(const IVec& mask, int k) { return to_float((mask >> IVec(k)) & IVec(1)); }
// SWAR popcount (arithmetic shifts are safe: the masks clear the smeared sign bits)
inline IVec popcount(const IVec& v) {
  IVec x = v - ((v >> IVec(1)) & IVec(0x55555555));
  x = (x & IVec(0x33333333)) + ((x >> IVec(2)) & IVec(0x33333333));
  x = (x + (x >> IVec(4))) & IVec(0x0F0F0F0F);
  return (x * IVec(0x01010101)) >> IVec(24);
}
inline Vec gather(const float* base, const IVec& index) { return at::vec::gather<4>(base, index); }
// base[2 index] and base[2 index + 1]: both floats of each lane's texel of a two-channel image. With AVX-512 as 64-bit
// elements: two 8-lane gathers where two 16-lane ones would read single floats, measured faster on this project's
// AVX-512 machine (docs/performance.md, "A tap's inverse depth and layer in one read")
inline void gather_pair(const float* base, const IVec& index, Vec& first, Vec& second) {
#if defined(CPU_CAPABILITY_AVX512)
  const __m512i at = index;
  const __m512 p0 = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_castsi512_si256(at), base, 8));
  const __m512 p1 = _mm512_castpd_ps(_mm512_i32gather_pd(_mm512_extracti64x4_epi64(at, 1), base, 8));
  const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
  first = Vec(_mm512_permutex2var_ps(p0, even, p1));
  second = Vec(_mm512_permutex2var_ps(p0, _mm512_add_epi32(even, _mm512_set1_epi32(1)), p1));
#else
  const IVec at = index + index;
  first = gather(base, at), second = gather(base + 1, at);
#endif
}
inline Vec gather_flag(const bool* base, const IVec& index) {
  constexpr int L = Vec::size();
  alignas(64) int32_t at[L];
  alignas(64) float flag[L];
  index.store(at);
  for (int l = 0; l < L; ++l) flag[l] = base[at[l]] ? 1.0f : 0.0f;
  return Vec::loadu(flag) > Vec(0.5f);
}

}  // namespace tao
