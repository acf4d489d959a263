// One pixel per lane set: the lane type of the CUDA kernel (one thread per pixel, compiled at run time
// by NVRTC) and of the CPU build of the same walk that CI runs (lanes="scalar"). The walk (walk.h) is
// written against the names defined here and in lanes_simd.h, nothing else.
#pragma once

// TAO_COLD: a branch that rarely runs (out of line on the CPU, where its code inside a hot loop costs the loop's
// registers; inline on CUDA, where a call would put its arguments in local memory). TAO_HOT: a step's own work (its
// fetch, its sector angles, an accumulator's step) and the dual and reverse lanes' arithmetic (a dual's operation
// is a few vector operations, a reverse node a few stores), always inlined on the CPU, where a call per use returned
// its values through memory and loaded its constants again (docs/kernel-notes.md)
#ifdef __CUDACC_RTC__
#define TAO_FN __device__ __forceinline__
#define TAO_COLD TAO_FN
#define TAO_HOT TAO_FN
#define TAO_CONST static __device__ const
typedef int int32_t;
typedef unsigned int uint32_t;
typedef long long int64_t;
typedef unsigned long long uint64_t;
#else
#define TAO_FN inline
#define TAO_COLD __attribute__((noinline, cold))
#define TAO_HOT inline __attribute__((always_inline))
#define TAO_CONST static constexpr
#include <cmath>
#include <cstdint>
#include <cstring>
#endif

namespace tao {

template <class F> struct LaneTraits;

// The value lanes of a lane type and whether it carries tangents (lanes_dual.h's Dual<F, N>: F's and N
// tangents); value(x) its value lanes
template <class F> struct ValueOf {
  using type = F;
  static constexpr bool dual = false;
};
template <class F> TAO_FN const F& value(const F& x) { return x; }

template <> struct LaneTraits<float> {
  using M = bool;      // a lane mask
  using I = uint32_t;  // integer lanes (sector masks, texel indices)
  static constexpr int L = 1;
};

TAO_FN float from_lanes(const float* x, float) { return x[0]; }
TAO_FN void to_lanes(float x, float* out) { out[0] = x; }
TAO_FN float select(bool m, float yes, float no) { return m ? yes : no; }
TAO_FN uint32_t select(bool m, uint32_t yes, uint32_t no) { return m ? yes : no; }
TAO_FN bool select(bool m, bool yes, bool no) { return m ? yes : no; }
TAO_FN bool ieq(uint32_t a, uint32_t b) { return a == b; }  // integer lanes equal: a lane mask
TAO_FN bool land(bool a, bool b) { return a && b; }
TAO_FN bool lor(bool a, bool b) { return a || b; }
TAO_FN bool lnot(bool a) { return !a; }
TAO_FN bool any(bool m) { return m; }
TAO_FN bool lane_on(bool m, int) { return m; }
TAO_FN uint32_t lane_bits(bool m) { return m ? 1u : 0u; }  // a lane mask as bits (lane l: bit l)
TAO_FN void store_lanes(uint32_t x, int32_t* out) { out[0] = int32_t(x); }
TAO_FN uint32_t from_lanes(const int32_t* x, uint32_t) { return uint32_t(x[0]); }
TAO_FN float reduce_min(float x) { return x; }  // over the lanes
TAO_FN float reduce_max(float x) { return x; }
TAO_FN float neg(float x) { return -x; }
TAO_FN float fma(float a, float b, float c) { return fmaf(a, b, c); }
TAO_FN float abs(float x) { return fabsf(x); }
TAO_FN float sqrt(float x) { return sqrtf(x); }
TAO_FN float floor(float x) { return floorf(x); }
TAO_FN float ceil(float x) { return ceilf(x); }
TAO_FN float rint(float x) { return rintf(x); }  // half to even
TAO_FN float atan2(float y, float x) { return atan2f(y, x); }
TAO_FN float acos(float x) { return acosf(x); }
TAO_FN float asin(float x) { return asinf(x); }
TAO_FN float cos(float x) { return cosf(x); }
TAO_FN float sin(float x) { return sinf(x); }
// cos and sin correctly rounded (from double: but for double rounding, which needs the value within a double
// ulp of a float midpoint), as torch's float32 cos and sin on an MKL build
TAO_FN void cos_sin_rounded(float x, float& c, float& s) {
  c = float(::cos(double(x)));
  s = float(::sin(double(x)));
}
TAO_FN float pow(float x, float y) { return powf(x, y); }
TAO_FN float exp(float x) { return expf(x); }
TAO_FN float logistic(float x) { return 1.0f / (1.0f + expf(-x)); }  // 1 / (1 + e^-x)
TAO_FN float exp_inline(float x) { return expf(x); }            // e^x (lanes_simd.h's is inline)
TAO_FN float inverse_one_plus(float e) { return 1.0f / (1.0f + e); }  // 1 / (1 + e)
TAO_FN float expm1(float x) { return expm1f(x); }
// NaN-propagating like ATen's maximum/minimum, which the SIMD lanes use
TAO_FN float max(float a, float b) { return (a != a || b != b) ? a + b : (a > b ? a : b); }
TAO_FN float min(float a, float b) { return (a != a || b != b) ? a + b : (a < b ? a : b); }
TAO_FN float clamp_min(float x, float lo) { return x < lo ? lo : x; }
TAO_FN float clamp_max(float x, float hi) { return x > hi ? hi : x; }
TAO_FN float clamp(float x, float lo, float hi) { return clamp_max(clamp_min(x, lo), hi); }
TAO_FN float rsqrt(float x) { return 1.0f / sqrtf(x); }
TAO_FN float reciprocal(float x) { return 1.0f / x; }

TAO_FN uint32_t to_int(float x) { return uint32_t(int32_t(x)); }  // truncation, x in int range
TAO_FN float to_float(uint32_t x) { return float(int32_t(x)); }
TAO_FN uint32_t imin(uint32_t a, uint32_t b) { return int32_t(a) < int32_t(b) ? a : b; }
TAO_FN uint32_t imax(uint32_t a, uint32_t b) { return int32_t(a) > int32_t(b) ? a : b; }
TAO_FN uint32_t bnot(uint32_t x) { return ~x; }
TAO_FN uint32_t low_bits(uint32_t k) { return k >= 32u ? 0xffffffffu : (1u << k) - 1u; }  // k in [0, 32]
TAO_FN float bit(uint32_t mask, int k) { return float((mask >> k) & 1u); }
// set bits, and the lowest set bit's index (of x != 0)
#ifdef __CUDACC_RTC__
TAO_FN uint32_t popcount(uint32_t x) { return uint32_t(__popc(x)); }
TAO_FN int popcount(uint64_t x) { return __popcll((unsigned long long)x); }
TAO_FN int lowest_bit(uint32_t x) { return __ffs(int(x)) - 1; }
TAO_FN int lowest_bit(uint64_t x) { return __ffsll((long long)x) - 1; }
#else
TAO_FN uint32_t popcount(uint32_t x) { return uint32_t(__builtin_popcount(x)); }
TAO_FN int popcount(uint64_t x) { return __builtin_popcountll(x); }
TAO_FN int lowest_bit(uint32_t x) { return __builtin_ctz(x); }
TAO_FN int lowest_bit(uint64_t x) { return __builtin_ctzll(x); }
#endif
TAO_FN float gather(const float* base, uint32_t index) { return base[index]; }
// both floats of texel index of a two-channel image (lanes_simd.h's)
TAO_FN void gather_pair(const float* base, uint32_t index, float& first, float& second) {
  first = base[2 * index], second = base[2 * index + 1];
}
// *to += x, by one thread at a time (on the CPU each thread adds into its own image; CUDA threads share one)
#ifdef __CUDACC_RTC__
TAO_FN void scatter_add(float* to, float x) { atomicAdd(to, x); }
#else
TAO_FN void scatter_add(float* to, float x) { *to += x; }
#endif
TAO_FN bool gather_flag(const bool* base, uint32_t index) { return base[index]; }
// a float's bits and back
#ifdef __CUDACC_RTC__
TAO_FN uint32_t float_bits(float x) { return __float_as_uint(x); }
TAO_FN float bits_float(uint32_t b) { return __uint_as_float(b); }
#else
TAO_FN uint32_t float_bits(float x) {
  uint32_t b;
  std::memcpy(&b, &x, sizeof b);
  return b;
}
TAO_FN float bits_float(uint32_t b) {
  float x;
  std::memcpy(&x, &b, sizeof x);
  return x;
}
#endif
TAO_FN bool sign_clear(float x) { return (float_bits(x) >> 31) == 0u; }  // (+0 and +NaN included)

}  // namespace tao
