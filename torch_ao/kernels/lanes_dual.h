// Forward-mode dual numbers over any lane type of lanes_scalar.h / lanes_simd.h: Dual<F, N> carries a
// value and its derivatives along N tangents, lane by lane, so the one walk (walk.h) run with
// F = Dual<Vec, N> (or Dual<float, N>) gives its outputs' derivatives with respect to whatever the caller
// seeds (seed_pixel: the pixel's own position, normal and depth; seed_setting: an accumulator's setting).
//
// Every operation's value is the value lanes' own (a quotient divides, an fma is fused), so that a walk replayed
// in duals samples the texels, and drops the samples, that its forward did.
//
// Derivatives at non-differentiable points follow torch's autograd of the tensor path: floor, rint and
// comparisons have none; clamp passes the gradient where lo <= x <= hi; min / max pass the chosen
// operand's (ties: the first). pow differentiates its base only (the walk's exponents are settings).
#pragma once

#include "lanes_scalar.h"
#include "slopes.h"

namespace tao {

template <class F, int N> struct Dual {
  using M = typename LaneTraits<F>::M;
  F v;
  F d[N];

  TAO_HOT Dual() : v(0.0f) {
    for (int k = 0; k < N; ++k) d[k] = F(0.0f);
  }
  TAO_HOT Dual(const F& x) : v(x) {  // a constant (float converts through F)
    for (int k = 0; k < N; ++k) d[k] = F(0.0f);
  }

  // a value with derivative a * x.d + b * y.d
  static TAO_HOT Dual chain(const F& value, const F& a, const Dual& x) {
    Dual r(value);
    for (int k = 0; k < N; ++k) r.d[k] = a * x.d[k];
    return r;
  }
  static TAO_HOT Dual chain(const F& value, const F& a, const Dual& x, const F& b, const Dual& y) {
    Dual r(value);
    for (int k = 0; k < N; ++k) r.d[k] = a * x.d[k] + b * y.d[k];
    return r;
  }

  friend TAO_HOT Dual operator+(const Dual& a, const Dual& b) {
    Dual r(a.v + b.v);
    for (int k = 0; k < N; ++k) r.d[k] = a.d[k] + b.d[k];
    return r;
  }
  friend TAO_HOT Dual operator-(const Dual& a, const Dual& b) {
    Dual r(a.v - b.v);
    for (int k = 0; k < N; ++k) r.d[k] = a.d[k] - b.d[k];
    return r;
  }
  friend TAO_HOT Dual operator*(const Dual& a, const Dual& b) { return chain(a.v * b.v, b.v, a, a.v, b); }
  friend TAO_HOT Dual operator/(const Dual& a, const Dual& b) {
    const F inv = F(1.0f) / b.v, q = a.v / b.v;
    return chain(q, inv, a, neg(q * inv), b);
  }
  friend TAO_HOT M operator<(const Dual& a, const Dual& b) { return a.v < b.v; }
  friend TAO_HOT M operator>(const Dual& a, const Dual& b) { return a.v > b.v; }
  friend TAO_HOT M operator<=(const Dual& a, const Dual& b) { return a.v <= b.v; }
  friend TAO_HOT M operator>=(const Dual& a, const Dual& b) { return a.v >= b.v; }
  friend TAO_HOT M operator==(const Dual& a, const Dual& b) { return a.v == b.v; }
};

// x with M >= N tangents: its own, then zeros
template <int M, class F, int N> TAO_HOT Dual<F, M> widen(const Dual<F, N>& x) {
  static_assert(M >= N, "widen: to at least as many tangents");
  Dual<F, M> r(x.v);
  for (int k = 0; k < N; ++k) r.d[k] = x.d[k];
  return r;
}

template <class F, int N> struct LaneTraits<Dual<F, N>> {
  using M = typename LaneTraits<F>::M;
  using I = typename LaneTraits<F>::I;
  static constexpr int L = LaneTraits<F>::L;
};

template <class F, int N> struct ValueOf<Dual<F, N>> {
  using type = F;
  static constexpr bool dual = true;
};
template <class F, int N> TAO_HOT const F& value(const Dual<F, N>& x) { return x.v; }

template <class F, int N> TAO_HOT Dual<F, N> from_lanes(const float* x, const Dual<F, N>&) {
  return Dual<F, N>(from_lanes(x, F(0.0f)));
}
template <class F, int N>
TAO_HOT Dual<F, N> select(const typename LaneTraits<F>::M& m, const Dual<F, N>& yes, const Dual<F, N>& no) {
  Dual<F, N> r(select(m, yes.v, no.v));
  for (int k = 0; k < N; ++k) r.d[k] = select(m, yes.d[k], no.d[k]);
  return r;
}
template <class F, int N> TAO_HOT Dual<F, N> neg(const Dual<F, N>& x) {
  Dual<F, N> r(neg(x.v));
  for (int k = 0; k < N; ++k) r.d[k] = neg(x.d[k]);
  return r;
}
template <class F, int N> TAO_HOT Dual<F, N> fma(const Dual<F, N>& a, const Dual<F, N>& b, const Dual<F, N>& c) {
  Dual<F, N> r = Dual<F, N>::chain(fma(a.v, b.v, c.v), b.v, a, a.v, b);
  for (int k = 0; k < N; ++k) r.d[k] = r.d[k] + c.d[k];
  return r;
}
// a b + c for a constant b and c, its value fused as the value lanes' fma (a walk in duals keeps their values)
template <class F, int N> TAO_HOT Dual<F, N> fma(const Dual<F, N>& a, const F& b, const F& c) {
  Dual<F, N> r(fma(a.v, b, c));
  for (int k = 0; k < N; ++k) r.d[k] = a.d[k] * b;
  return r;
}
template <class F, int N> TAO_HOT Dual<F, N> abs(const Dual<F, N>& x) { return select(x.v < F(0.0f), neg(x), x); }
template <class F, int N> TAO_HOT Dual<F, N> sqrt(const Dual<F, N>& x) {
  const F r = sqrt(x.v);
  return Dual<F, N>::chain(r, sqrt_slope(r), x);
}
// walk.h's norm2 and norm3 as one operation (0 derivative at 0, as sqrt's)
template <class F, int N> TAO_HOT Dual<F, N> norm2(const Dual<F, N>& x, const Dual<F, N>& y) {
  const F r = sqrt(x.v * x.v + y.v * y.v), inv = norm_inverse(r);
  return Dual<F, N>::chain(r, x.v * inv, x, y.v * inv, y);
}
template <class F, int N> TAO_HOT Dual<F, N> norm3(const Dual<F, N>* a) {
  const F r = sqrt(a[0].v * a[0].v + a[1].v * a[1].v + a[2].v * a[2].v), inv = norm_inverse(r);
  Dual<F, N> out = Dual<F, N>::chain(r, a[0].v * inv, a[0], a[1].v * inv, a[1]);
  const F c = a[2].v * inv;
  for (int k = 0; k < N; ++k) out.d[k] = out.d[k] + c * a[2].d[k];
  return out;
}
template <class F, int N> TAO_HOT Dual<F, N> rsqrt(const Dual<F, N>& x) {
  const F r = rsqrt(x.v);
  return Dual<F, N>::chain(r, rsqrt_slope(r), x);
}
template <class F, int N> TAO_HOT Dual<F, N> reciprocal(const Dual<F, N>& x) {
  const F r = reciprocal(x.v);
  return Dual<F, N>::chain(r, reciprocal_slope(r), x);
}
template <class F, int N> TAO_HOT Dual<F, N> floor(const Dual<F, N>& x) { return Dual<F, N>(floor(x.v)); }
template <class F, int N> TAO_HOT Dual<F, N> ceil(const Dual<F, N>& x) { return Dual<F, N>(ceil(x.v)); }
template <class F, int N> TAO_HOT Dual<F, N> rint(const Dual<F, N>& x) { return Dual<F, N>(rint(x.v)); }
template <class F, int N> TAO_HOT Dual<F, N> atan2(const Dual<F, N>& y, const Dual<F, N>& x) {
  F by_y, by_x;
  atan2_slopes(y.v, x.v, by_y, by_x);
  return Dual<F, N>::chain(atan2(y.v, x.v), by_y, y, by_x, x);
}
template <class F, int N> TAO_HOT Dual<F, N> cos(const Dual<F, N>& x) { return Dual<F, N>::chain(cos(x.v), neg(sin(x.v)), x); }
template <class F, int N> TAO_HOT Dual<F, N> sin(const Dual<F, N>& x) { return Dual<F, N>::chain(sin(x.v), cos(x.v), x); }
template <class F, int N> TAO_HOT void cos_sin_rounded(const Dual<F, N>& x, Dual<F, N>& c, Dual<F, N>& s) {
  F cv, sv;
  cos_sin_rounded(x.v, cv, sv);
  c = Dual<F, N>::chain(cv, neg(sv), x), s = Dual<F, N>::chain(sv, cv, x);
}
template <class F, int N> TAO_HOT Dual<F, N> asin(const Dual<F, N>& x) {
  return Dual<F, N>::chain(asin(x.v), asin_slope(x.v), x);
}
template <class F, int N> TAO_HOT Dual<F, N> acos(const Dual<F, N>& x) {
  return Dual<F, N>::chain(acos(x.v), neg(asin_slope(x.v)), x);
}
template <class F, int N> TAO_HOT Dual<F, N> pow(const Dual<F, N>& x, const Dual<F, N>& y) {
  return Dual<F, N>::chain(pow(x.v, y.v), pow_slope(x.v, y.v), x);
}
template <class F, int N> TAO_HOT Dual<F, N> max(const Dual<F, N>& a, const Dual<F, N>& b) {
  Dual<F, N> r = select(b.v > a.v, b, a);
  r.v = max(a.v, b.v);  // NaN-propagating
  return r;
}
template <class F, int N> TAO_HOT Dual<F, N> min(const Dual<F, N>& a, const Dual<F, N>& b) {
  Dual<F, N> r = select(b.v < a.v, b, a);
  r.v = min(a.v, b.v);
  return r;
}
template <class F, int N> TAO_HOT Dual<F, N> clamp_min(const Dual<F, N>& x, const Dual<F, N>& lo) {
  return select(x.v < lo.v, lo, x);
}
template <class F, int N> TAO_HOT Dual<F, N> clamp_max(const Dual<F, N>& x, const Dual<F, N>& hi) {
  return select(x.v > hi.v, hi, x);
}
template <class F, int N> TAO_HOT Dual<F, N> clamp(const Dual<F, N>& x, const Dual<F, N>& lo, const Dual<F, N>& hi) {
  return clamp_max(clamp_min(x, lo), hi);
}
template <class F, int N> TAO_HOT typename LaneTraits<F>::I to_int(const Dual<F, N>& x) { return to_int(x.v); }

// The walk's seed (walk.h's Pixels): tangents 0..2 the pixel's position, 3..5 its normal, 6 its depth
template <class F, int N> TAO_HOT void seed_pixel(Dual<F, N>* P, Dual<F, N>* Nrm, Dual<F, N>& depth) {
  static_assert(N >= 7, "seed_pixel: the pixel's own tangents need 7 slots");
  for (int c = 0; c < 3; ++c) {
    P[c].d[c] = F(1.0f);
    Nrm[c].d[3 + c] = F(1.0f);
  }
  depth.d[6] = F(1.0f);
}

// tangent 7: an accumulator's differentiable setting (walk.h's seed_setting)
template <class F, int N> TAO_HOT Dual<F, N> seed_setting(const Dual<F, N>& x) {
  static_assert(N >= 8, "seed_setting: the setting's tangent is the 8th");
  Dual<F, N> r(x);
  r.d[7] = F(1.0f);
  return r;
}

}  // namespace tao
