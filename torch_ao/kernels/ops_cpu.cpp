// The CPU operator of the one walk (walk.h with the accumulators of horizon.h, bitmask.h, bitmask_glsl.h,
// ssao.h and soft.h, settings unpacked by packed.h): rows over torch's threads, each row's pixels in SIMD lanes (lanes_simd.h) or,
// with scalar=True, one pixel at a time through walk_pixel in float lanes (lanes_scalar.h): the body of
// the CUDA kernel's threads (walk_cuda.cu), run on the CPU.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <string>

#include "lanes_simd.h"
#include "packed.h"
#include "frame_cpu.h"
#include "rows_cpu.h"

namespace {

using namespace tao;

// Every pixel's channels (B, C, H, W): blocks of a row in SIMD lanes, or walk_pixel pixel by pixel
template <class Acc>
void walk_frame(const WalkSettings& cfg, const Acc& acc, const Frame& fr, float* dst, bool scalar) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t H = fr.H, W = fr.W;
  const int C = acc.channels();
  torch_ao_rows::for_each_block<L>(fr.B, H, W, scalar, [&](int64_t b, int64_t row, int64_t u0, int n, auto simd) {
    if constexpr (!decltype(simd)::value) {
      walk_pixel(cfg, acc, fr, dst, (b * H + row) * W + u0);
    } else {
      Vec values[8];
      alignas(64) float lanes[L];
      walk_block(cfg, fr.image(b), acc, row, u0, n, values);
      for (int c = 0; c < C; ++c) {
        to_lanes(values[c], lanes);
        std::copy(lanes, lanes + n, dst + ((b * C + c) * H + row) * W + u0);
      }
    }
  });
}

// A thickness read (ThicknessRead) the kernels know, with its layer where it reads one
void check_thickness(int64_t read, const Frame& fr) {
  TORCH_CHECK(read >= 0 && read <= 3, "thickness read: expected 0 (constant), 1 (layer), 2 (first tap) or 3 (depth)");
  const auto r = ThicknessRead(read);
  TORCH_CHECK((r != ThicknessRead::layer && r != ThicknessRead::first_tap) || fr.backface,
              "layer: the thickness model reads a layer; none was given");
}

// torch_ao_kernels::walk: the accumulator named `accumulator` ("gtao", "hbao", "bitmask", "exact", "exact_gradients",
// "glsl", "wedge", "pssao", "hemisphere", "soft", "soft_gradients", "soft_glsl") over the frame,
// settings in `ints` (int64) and `floats` (float32) as packed.h reads them; (B, channels, H, W)
at::Tensor walk(c10::string_view accumulator, const at::Tensor& positions, const at::Tensor& normals,
                const at::Tensor& inverse_depth, const at::Tensor& depth, const at::Tensor& valid,
                const at::Tensor& intrinsics, const at::Tensor& light, const at::Tensor& cells, const at::Tensor& backface,
                const at::Tensor& ints, const at::Tensor& floats, int64_t channels, bool scalar) {
  Frame fr = frame_of(positions, normals, inverse_depth, depth, valid, intrinsics, light, cells, backface);
  TORCH_CHECK(ints.scalar_type() == at::kLong && ints.is_contiguous() && floats.scalar_type() == at::kFloat &&
                  floats.is_contiguous() && ints.device().is_cpu() && floats.device().is_cpu(),
              "ints, floats: expected the packed int64 and float32 settings on the CPU");
  TORCH_CHECK(ints.numel() >= kAccInts && floats.numel() >= kAccFloats, "ints, floats: the walk's settings are missing");
  // the accumulator's own count after the walk's, then the walk's table (packed.h): a sample set's per slice
  // (Steps::wedge, optional), the pixel offsets per slice and step (Steps::pixels)
  const int64_t table_start = ints.data_ptr<int64_t>()[13], table = table_floats(ints.data_ptr<int64_t>());
  auto packed = [&](int64_t n_ints, int64_t n_floats) {
    TORCH_CHECK(ints.numel() == kAccInts + n_ints && floats.numel() == kAccFloats + n_floats + table, accumulator,
                ": expected ", kAccInts + n_ints, " ints and ", kAccFloats + n_floats + table, " floats");
    TORCH_CHECK(table_start == (table > 0 ? kAccFloats + n_floats : 0),
                "ints: the walk's table starts after the accumulator's floats, or is none");
  };
  TORCH_CHECK(!ints.data_ptr<int64_t>()[9] || fr.cells, "cells: the edge-aware fetch needs the cell flags");
  TORCH_CHECK(ints.data_ptr<int64_t>()[11] >= 0 && ints.data_ptr<int64_t>()[11] <= 3,
              "noise: expected 0 (ign), 1 (hilbert_r2), 2 (glsl) or 3 (glsl_mediump)");
  const int64_t* i = ints.data_ptr<int64_t>();
  const float* f = floats.data_ptr<float>();
  const WalkSettings cfg = unpack_walk(i, f);
  const at::Tensor texels = fetch_texels(cfg, fr);
  at::Tensor out = at::empty({fr.B, channels, fr.H, fr.W}, positions.options());
  auto run = [&](const auto& acc) {
    TORCH_CHECK(acc.channels() == channels && channels <= 8, "channels: expected ", acc.channels());
    walk_frame(cfg, acc, fr, out.data_ptr<float>(), scalar);
  };
  const std::string name(accumulator);
  if (name == "gtao") {
    packed(3, 3);
    TORCH_CHECK(i[kAccInts] >= 0 && i[kAccInts] <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
    run(unpack_gtao(i, f));
  } else if (name == "hbao") {
    packed(3, 2);
    run(unpack_hbao(i, f));
  } else if (name == "bitmask") {
    packed(8, 5);
    TORCH_CHECK(!i[kAccInts + 2] || fr.light, "light: indirect light needs the light buffer");
    check_thickness(i[kAccInts + 4], fr);
    TORCH_CHECK(i[kAccInts + 5] == 0 || i[kAccInts + 5] == 1, "variant: expected 0 (default) or 1 (hdrp)");
    run(unpack_bitmask(i, f));
  } else if (name == "exact") {
    packed(5, 5);
    TORCH_CHECK(i[1] <= kMaxIntervals / 2, "steps: the exact union holds at most ", kMaxIntervals / 2, " per side");
    check_thickness(i[kAccInts + 3], fr);
    run(unpack_exact(i, f));
  } else if (name == "exact_gradients" || name == "exact_gradients_growth") {
    packed(5, 5);
    TORCH_CHECK(i[1] <= kMaxIntervals / 2, "steps: the exact union holds at most ", kMaxIntervals / 2, " per side");
    check_thickness(i[kAccInts + 3], fr);
    TORCH_CHECK(i[3] == int64_t(Steps::power) && !i[7], "exact_gradients: the radius' derivative is the power step "
                "placement's, without full circle");
    if (name == "exact_gradients") {
      run(unpack_exact_gradients<false>(i, f));
    } else {
      run(unpack_exact_gradients<true>(i, f));
    }
  } else if (name == "glsl") {
    packed(4, 3);
    check_thickness(i[kAccInts + 3], fr);
    TORCH_CHECK(i[3] == int64_t(Steps::glsl) && i[0] >= 3 && i[1] >= 2,
                "glsl: expected the GLSL step placement over sliceCount + 1 >= 3 slices and sampleCount + 1 >= 2 steps");
    TORCH_CHECK(!i[kAccInts + 1] || fr.light, "light: indirect light needs the light buffer");
    run(unpack_glsl(i, f));
  } else if (name == "wedge") {
    packed(1, 3);
    TORCH_CHECK(i[3] == int64_t(Steps::wedge) && f[kAccFloats] > 0, "wedge: expected the wedge step placement and fade_distance > 0");
    run(unpack_wedge(i, f));
  } else if (name == "pssao") {
    packed(0, 1);
    TORCH_CHECK(i[3] == int64_t(Steps::pixels), "pssao: expected the pixel-offset step placement");
    run(unpack_pssao(i, f));
  } else if (name == "hemisphere") {
    packed(0, 2);
    TORCH_CHECK(i[3] == int64_t(Steps::hemisphere) && i[0] == 1 && i[7], "hemisphere: expected the hemisphere step "
                "placement over one slice, one side");
    run(unpack_hemisphere(i, f));
  } else if (name == "soft" || name == "soft_gradients") {
    packed(10, 5);
    check_thickness(i[kAccInts + 3], fr);
    TORCH_CHECK(f[kAccFloats + 2] > 0, "tau: expected > 0");
    TORCH_CHECK(name == "soft" || (!i[kAccInts + 5] && !i[kAccInts + 6]),
                "soft_gradients: bent normals' and indirect light's derivatives are soft_backward's");
    TORCH_CHECK(!i[kAccInts + 6] || fr.light, "light: indirect light needs the light buffer");
    TORCH_CHECK(i[1] <= kSoftMaxSteps / 2, "steps: the soft union holds at most ", kSoftMaxSteps / 2, " per side");
    if (name == "soft") {
      run(unpack_soft<false>(i, f));
    } else {
      TORCH_CHECK(i[3] == 0 && f[3] <= 0 && !i[7],
                  "soft_gradients: the radius' derivative is the power step placement's (step_motion: with the "
                  "sphere's extent too), without max_radius_px or full circle");
      run(unpack_soft<true>(i, f));
    }
  } else if (name == "soft_glsl") {
    packed(6, 4);
    check_thickness(i[kAccInts + 3], fr);
    TORCH_CHECK(f[kAccFloats + 3] > 0, "tau: expected > 0");
    TORCH_CHECK(i[3] == int64_t(Steps::glsl) && i[0] >= 3 && i[1] >= 2,
                "soft_glsl: expected the GLSL step placement over sliceCount + 1 >= 3 slices and sampleCount + 1 >= 2 steps");
    TORCH_CHECK(!i[kAccInts + 1] || fr.light, "light: indirect light needs the light buffer");
    run(unpack_soft_glsl_forward(i, f));
  } else {
    TORCH_CHECK(false, "accumulator: expected gtao, hbao, bitmask, exact, exact_gradients, glsl, wedge, pssao, "
                "hemisphere, soft, soft_gradients or soft_glsl, got ", name);
  }
  return out;
}

}  // namespace

TORCH_LIBRARY(torch_ao_kernels, m) {
  m.def("walk(str accumulator, Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor light, Tensor cells, Tensor backface, Tensor ints, Tensor floats, int channels, "
        "bool scalar) -> Tensor");
  m.impl("walk", c10::DispatchKey::CPU, TORCH_FN(walk));
}
