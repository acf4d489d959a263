// Pieces of the walk that the C++ kernels share (included by bitmask_cpu.cpp and soft_bitmask_cpu.cpp).
#pragma once

#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>

#include <cstdint>

namespace torch_ao_walk {

using Vec = at::vec::Vectorized<float>;
using Int = at::vec::Vectorized<int32_t>;

// The perspective-correct bilinear footprint of samples at screen (su, sv) (torch_ao.walk.fetch.bilinear_taps):
// the top-left texel (fu0, fv0), the fractions (fu, fv), the four taps' inverse depths t0..t3 of the
// (W x H) image `inverse_depth` (rows and columns clamped to the image), and whether all four are valid
// (an invalid texel holds NaN).
struct BilinearTaps {
  Vec fu0, fv0, fu, fv, t0, t1, t2, t3, ok;
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
  tap.t0 = at::vec::gather<4>(inverse_depth, r0 + c0);
  tap.t1 = at::vec::gather<4>(inverse_depth, r0 + c1);
  tap.t2 = at::vec::gather<4>(inverse_depth, r1 + c0);
  tap.t3 = at::vec::gather<4>(inverse_depth, r1 + c1);
  tap.ok = (tap.t0 == tap.t0) & (tap.t1 == tap.t1) & (tap.t2 == tap.t2) & (tap.t3 == tap.t3);
  return tap;
}

}  // namespace torch_ao_walk
