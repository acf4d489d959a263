// Rows of a batch over torch's intra-op threads, for the CPU kernels.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <type_traits>

#include "mkl_vml.h"

namespace torch_ao_rows {

// fn(r) for every r in [0, rows), handed out a few at a time to whichever of torch's threads is
// free (an even split waits for a busy core)
template <class Fn>
void over_rows(int64_t rows, const Fn& fn) {
  const int64_t chunk = 4;
  std::atomic<int64_t> next{0};
  at::parallel_for(0, at::get_num_threads(), 1, [&](int64_t, int64_t) {
#ifdef TORCH_AO_MKL_VML
    const int mkl_threads = MKL_Set_Num_Threads_Local(1);  // MKL's own threads inside ours: 7x slower
#endif
    for (int64_t r0 = next.fetch_add(chunk); r0 < rows; r0 = next.fetch_add(chunk))
      for (int64_t r = r0; r < std::min(rows, r0 + chunk); ++r) fn(r);
#ifdef TORCH_AO_MKL_VML
    MKL_Set_Num_Threads_Local(mkl_threads);
#endif
  });
}

// fn(b, row, u0, n, lanes) for every block of a row: n = 1 pixel at a time with lanes = std::false_type
// (scalar), else blocks of up to L pixels with lanes = std::true_type (SIMD lanes of width L). The image is walked
// in strips kStrip pixels wide, each top to bottom: a pixel's samples reach rows around it, and down a strip the
// next rows' samples fall on texels the last rows brought into the cache (row after row over the whole width,
// they had left it: hard ssilvb_glsl at 1280x720, 4 x 8, 13 % faster)
constexpr int64_t kStrip = 128;  // a multiple of every lane width
// fn(b, row, u_begin, u_end) for every row of every strip (for_each_block's units)
template <class Fn>
void for_each_strip_row(int64_t B, int64_t H, int64_t W, const Fn& fn) {
  const int64_t strips = (W + kStrip - 1) / kStrip;
  over_rows(B * strips * H, [&](int64_t r) {  // (b, strip, row)
    const int64_t b = r / (strips * H), row = r % H, u_begin = (r / H) % strips * kStrip;
    fn(b, row, u_begin, std::min(W, u_begin + kStrip));
  });
}
template <int L, class Fn>
void for_each_block(int64_t B, int64_t H, int64_t W, bool scalar, const Fn& fn) {
  static_assert(kStrip % L == 0, "a strip holds whole blocks");
  for_each_strip_row(B, H, W, [&](int64_t b, int64_t row, int64_t u_begin, int64_t u_end) {
    if (scalar) {
      for (int64_t u = u_begin; u < u_end; ++u) fn(b, row, u, 1, std::false_type{});
      return;
    }
    for (int64_t u0 = u_begin; u0 < u_end; u0 += L) fn(b, row, u0, int(std::min<int64_t>(L, u_end - u0)), std::true_type{});
  });
}

}  // namespace torch_ao_rows
