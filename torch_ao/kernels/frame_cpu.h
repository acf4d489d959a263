// The walk's CPU inputs as torch_ao/kernels/launch.py passes them, checked and read as packed.h's Frame:
// the CPU operators' (ops_cpu.cpp, walk_grad_cpu.cpp) one definition.
#pragma once

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>

#include "packed.h"

namespace tao {

// An optional image: empty, or contiguous float32 of `numel` values
inline const float* optional_image(const at::Tensor& t, int64_t numel, const char* name) {
  if (t.numel() == 0) return nullptr;
  TORCH_CHECK(t.numel() == numel && t.scalar_type() == at::kFloat && t.is_contiguous() && t.device().is_cpu(), name,
              ": expected empty or contiguous float32 of ", numel, " values");
  return t.data_ptr<float>();
}

// positions, normals (B, H, W, 3), the inverse depth and the depth (NaN where invalid), valid (B, H, W),
// intrinsics (B, 4) (fx, fy, cx, cy); light (B, H, W, 3), cells and backface (B, H, W), each possibly empty
inline Frame frame_of(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                      const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
                      const at::Tensor& light, const at::Tensor& cells, const at::Tensor& backface) {
  TORCH_CHECK(positions.dim() == 4 && positions.size(3) == 3, "positions: expected (B, H, W, 3)");
  for (const at::Tensor* t : {&positions, &normals, &inverse_depth, &depth, &intrinsics})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous() && t->device().is_cpu(),
                "expected contiguous float32 CPU inputs");
  TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous(), "valid: expected contiguous bool");
  const int64_t pixels = depth.numel();
  return Frame{positions.data_ptr<float>(), normals.data_ptr<float>(), inverse_depth.data_ptr<float>(),
               depth.data_ptr<float>(), intrinsics.data_ptr<float>(), optional_image(light, 3 * pixels, "light"),
               optional_image(cells, pixels, "cells"), optional_image(backface, pixels, "backface"),
               valid.data_ptr<bool>(), positions.size(0), positions.size(1), positions.size(2)};
}

// What the walk cfg's bilinear fetch reads at its taps, prepared once per call and returned (the caller keeps it
// alive; fr then reads it: Image::texels; an undefined tensor where nothing is prepared): an edge-aware fetch's cell
// flags in the inverse depth's sign (negative: not one surface), so that a sample reads no cell flag, and a back-face
// layer interleaved with the inverse depth (B, H, W, 2), both of a tap's floats in one gather of 64-bit lanes
// (lanes_simd.h's gather_pair). A nearest fetch, or one with neither, reads the inverse depth where it is. The
// separate images stay, for the reads of other buffers.
inline at::Tensor fetch_texels(const WalkSettings& cfg, Frame& fr) {
  const float *inverse = fr.inverse, *layer = fr.backface, *cells = cfg.edge_aware ? fr.cells : nullptr;
  if (!cfg.bilinear || (!layer && !cells)) return at::Tensor();
  const int64_t pixels = fr.B * fr.H * fr.W, channels = layer ? 2 : 1;
  at::Tensor texels = at::empty({pixels * channels}, at::TensorOptions().dtype(at::kFloat));
  float* out = texels.data_ptr<float>();
  at::parallel_for(0, pixels, 16384, [&](int64_t lo, int64_t hi) {
    for (int64_t p = lo; p < hi; ++p) {
      out[channels * p] = cells && !(cells[p] > 0.5f) ? -inverse[p] : inverse[p];
      if (layer) out[channels * p + 1] = layer[p];
    }
  });
  fr.texels = out, fr.texels_layer = layer != nullptr, fr.cells_in_sign = cells != nullptr;
  return texels;
}

}  // namespace tao
