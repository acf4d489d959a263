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

// fn(b, row) for every row of a batch of B images H rows high, as over_rows hands them out
template <class Fn>
void for_each_row(int64_t B, int64_t H, const Fn& fn) {
  over_rows(B * H, [&](int64_t r) { fn(r / H, r % H); });
}

// fn(b, row, u0, n, lanes) for every block of a row: n = 1 pixel at a time with lanes = std::false_type
// (scalar), else blocks of up to L pixels with lanes = std::true_type (SIMD lanes of width L)
template <int L, class Fn>
void for_each_block(int64_t B, int64_t H, int64_t W, bool scalar, const Fn& fn) {
  for_each_row(B, H, [&](int64_t b, int64_t row) {
    if (scalar) {
      for (int64_t u = 0; u < W; ++u) fn(b, row, u, 1, std::false_type{});
      return;
    }
    for (int64_t u0 = 0; u0 < W; u0 += L) fn(b, row, u0, int(std::min<int64_t>(L, W - u0)), std::true_type{});
  });
}

}  // namespace torch_ao_rows
