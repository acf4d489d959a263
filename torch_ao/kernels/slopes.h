// The partial derivatives of the lanes' primitives, in value lanes: each rule's one definition, which the dual lanes
// (lanes_dual.h) chain forward, the reverse lanes (lanes_rev.h) record on their tape and the hand-written adjoints
// (walk.h's slice_angle_slopes) use. Where a primitive has no derivative, the one torch's autograd takes on the tensor
// path: 0 (a zero-length vector, a sample at the pixel itself) rather than an infinity or NaN.
#pragma once

#include "lanes_scalar.h"

namespace tao {

// d sqrt(x) / d x from its root r: 0 at 0, as torch's norm takes it there, not sqrt's infinite slope
template <class F> TAO_HOT F sqrt_slope(const F& root) { return select(root > F(0.0f), F(0.5f) / root, F(0.0f)); }
// d rsqrt(x) / d x from r = rsqrt(x)
template <class F> TAO_HOT F rsqrt_slope(const F& r) { return F(-0.5f) * r * r * r; }
// d (1 / x) / d x from r = 1 / x
template <class F> TAO_HOT F reciprocal_slope(const F& r) { return neg(r * r); }
// d asin(x) / d x (acos's is its negative)
template <class F> TAO_HOT F asin_slope(const F& x) { return rsqrt(F(1.0f) - x * x); }
// d logistic(x) / d x from s = logistic(x): finite everywhere
template <class F> TAO_HOT F logistic_slope(const F& s) { return s * (F(1.0f) - s); }
// d pow(x, y) / d x, the base's (the exponents the walk raises to are settings without a gradient)
template <class F> TAO_HOT F pow_slope(const F& x, const F& y) { return y * pow(x, y - F(1.0f)); }
// atan2(y, x)'s slopes: x / r^2 by y, -y / r^2 by x (r^2 = x^2 + y^2). None at the origin: atan2(0, 0) = 0 is a
// convention, not a limit
template <class F> TAO_HOT void atan2_slopes(const F& y, const F& x, F& by_y, F& by_x) {
  const F r2 = fma(x, x, y * y);
  const F inv = select(r2 > F(0.0f), reciprocal(r2), F(0.0f));
  by_y = x * inv;
  by_x = neg(y) * inv;
}
// 1 / |x| of a norm's value r (norm2, norm3), by which each component x_i gives its slope x_i / |x|: 0 at 0, as
// sqrt_slope's
template <class F> TAO_HOT F norm_inverse(const F& r) { return select(r > F(0.0f), reciprocal(r), F(0.0f)); }

}  // namespace tao
