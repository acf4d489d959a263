// The CPU operators of the one walk (walk.h with the accumulators of horizon.h and bitmask.h): rows over
// torch's threads, each row's pixels in SIMD lanes (lanes_simd.h) or, with scalar=True, one pixel at a
// time in float lanes (lanes_scalar.h): the CUDA kernel's arithmetic, run on the CPU.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include "lanes_simd.h"
#include "bitmask.h"
#include "horizon.h"
#include "rows_cpu.h"

namespace {

using namespace tao;

// The walk's inputs as torch_ao/kernels/frame.py passes them: positions, normals (B, H, W, 3), the inverse
// depth (NaN where invalid), depth, valid (B, H, W), intrinsics (B, 4) (fx, fy, cx, cy), light (B, H, W, 3)
// or empty
struct Inputs {
  at::Tensor positions, normals, inverse_depth, depth, valid, intrinsics, light;

  void check() const {
    TORCH_CHECK(positions.dim() == 4 && positions.size(3) == 3, "positions: expected (B, H, W, 3)");
    for (const at::Tensor* t : {&positions, &normals, &inverse_depth, &depth, &intrinsics})
      TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous() && t->device().is_cpu(),
                  "expected contiguous float32 CPU inputs");
    TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous(), "valid: expected contiguous bool");
    TORCH_CHECK(light.numel() == 0 || (light.sizes() == positions.sizes() && light.scalar_type() == at::kFloat &&
                                       light.is_contiguous()),
                "light: expected empty or contiguous float32 (B, H, W, 3)");
  }

  Image image(int64_t b) const {
    const int64_t H = positions.size(1), W = positions.size(2), plane = H * W;
    const float* K = intrinsics.data_ptr<float>() + 4 * b;
    return Image{H, W, K[0], K[1], K[2], K[3], positions.data_ptr<float>() + 3 * b * plane,
                 normals.data_ptr<float>() + 3 * b * plane, inverse_depth.data_ptr<float>() + b * plane,
                 depth.data_ptr<float>() + b * plane,
                 light.numel() ? light.data_ptr<float>() + 3 * b * plane : nullptr, valid.data_ptr<bool>() + b * plane};
  }
};

// Every pixel's channels (B, C, H, W) through walk_block in lanes of type F
template <class F, class Acc>
at::Tensor walk_lanes(const WalkSettings& cfg, const Acc& acc, const Inputs& in) {
  constexpr int L = LaneTraits<F>::L;
  const int64_t B = in.positions.size(0), H = in.positions.size(1), W = in.positions.size(2);
  const int C = acc.channels();
  TORCH_CHECK(C <= 8, "at most 8 output channels");
  at::Tensor out = at::empty({B, C, H, W}, in.positions.options());
  float* dst = out.data_ptr<float>();
  torch_ao_rows::for_each_row(B, H, [&](int64_t b, int64_t row) {
    const Image img = in.image(b);
    F values[8];
    alignas(64) float lanes[L];
    for (int64_t u0 = 0; u0 < W; u0 += L) {
      const int n = int(std::min<int64_t>(L, W - u0));
      walk_block(cfg, img, acc, row, u0, n, values);
      for (int c = 0; c < C; ++c) {
        to_lanes(values[c], lanes);
        std::copy(lanes, lanes + n, dst + ((b * C + c) * H + row) * W + u0);
      }
    }
  });
  return out;
}

template <class Acc>
at::Tensor walk(const WalkSettings& cfg, const Acc& acc, const Inputs& in, bool scalar) {
  in.check();
  return scalar ? walk_lanes<float>(cfg, acc, in) : walk_lanes<Vec>(cfg, acc, in);
}

at::Tensor gtao_sums(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                     const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, int64_t variant,
                     int64_t slices, int64_t steps, double walk_radius, double radius, double falloff, double thickness,
                     double step_power, double min_step_px, double max_radius_px, bool jitter, int64_t seed,
                     bool bilinear, bool drop, bool screen_azimuth, bool projected_normal_weight, bool bent,
                     bool scalar) {
  TORCH_CHECK(variant >= 0 && variant <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
  const GTAOVariant v = GTAOVariant(variant);
  const WalkSettings cfg{slices, steps, float(walk_radius), float(step_power), float(min_step_px), float(max_radius_px),
                         jitter, bilinear, drop, /*full_circle=*/false, screen_azimuth, seed,
                         v == GTAOVariant::exact ? Steps::power : v == GTAOVariant::hdrp ? Steps::hdrp : Steps::ue4};
  const GTAOAccumulator acc{v, float(radius), float(falloff), float(thickness), projected_normal_weight, bent};
  return walk(cfg, acc, Inputs{positions, normals, inverse_depth, depth, valid, intrinsics, at::Tensor()}, scalar);
}

at::Tensor hbao_sums(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                     const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, int64_t slices,
                     int64_t steps, double radius, double angle_bias, bool quadratic, bool incremental,
                     bool view_elevation, double step_power, double min_step_px, bool jitter, int64_t seed,
                     bool bilinear, bool drop, bool screen_azimuth, bool scalar) {
  const WalkSettings cfg{slices, steps, float(radius), float(step_power), float(min_step_px), /*max_radius_px=*/0.0f,
                         jitter, bilinear, drop, /*full_circle=*/true, screen_azimuth, seed, Steps::power};
  const HBAOAccumulator acc{float(radius), float(angle_bias), quadratic, incremental, view_elevation};
  return walk(cfg, acc, Inputs{positions, normals, inverse_depth, depth, valid, intrinsics, at::Tensor()}, scalar);
}

at::Tensor bitmask_walk(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                        const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
                        const at::Tensor& light, int64_t slices, int64_t steps, double radius, double thickness,
                        double step_power, double min_step_px, bool jitter, int64_t seed, bool bilinear, bool drop,
                        int64_t rounding, double epsilon, bool cosine, bool indirect, bool bent, bool scalar) {
  TORCH_CHECK(!indirect || light.numel() > 0, "light: indirect light needs the light buffer");
  const WalkSettings cfg{slices, steps, float(radius), float(step_power), float(min_step_px), /*max_radius_px=*/0.0f,
                         jitter, bilinear, drop, /*full_circle=*/false, /*screen_azimuth=*/false, seed, Steps::power};
  const BitmaskAccumulator acc{slices, float(thickness), float(epsilon), rounding, cosine, indirect, bent};
  return walk(cfg, acc, Inputs{positions, normals, inverse_depth, depth, valid, intrinsics, light}, scalar);
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("gtao_sums(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, int variant, int slices, int steps, float walk_radius, float radius, float falloff, "
        "float thickness, float step_power, float min_step_px, float max_radius_px, bool jitter, int seed, "
        "bool bilinear, bool drop, bool screen_azimuth, bool projected_normal_weight, bool bent, bool scalar) -> Tensor");
  m.impl("gtao_sums", c10::DispatchKey::CPU, TORCH_FN(gtao_sums));
  m.def("hbao_sums(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, int slices, int steps, float radius, float angle_bias, bool quadratic, bool incremental, "
        "bool view_elevation, float step_power, float min_step_px, bool jitter, int seed, bool bilinear, bool drop, "
        "bool screen_azimuth, bool scalar) -> Tensor");
  m.impl("hbao_sums", c10::DispatchKey::CPU, TORCH_FN(hbao_sums));
  m.def("bitmask_walk(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, Tensor light, int slices, int steps, float radius, float thickness, float step_power, "
        "float min_step_px, bool jitter, int seed, bool bilinear, bool drop, int rounding, float epsilon, "
        "bool cosine, bool indirect, bool bent, bool scalar) -> Tensor");
  m.impl("bitmask_walk", c10::DispatchKey::CPU, TORCH_FN(bitmask_walk));
}
