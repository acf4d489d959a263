// The frame's view-space geometry in one pass, for the kernels' calls that record gradients (kernels/frame.py's
// view_geometry): GBuffer.positions (the depth unprojected, background at depth 1) and GBuffer.view_normals of a
// G-buffer with normals (_unit_facing: unit length, the direction toward the camera on background, turned to
// face the camera), channel-last, the inverse depth and the depth that walk_inputs hands the kernels, and their
// backward to the depth and the normals. The tensor ops stay the definition (and run everywhere else: float64,
// CUDA, the tensor-op walk); these are their arithmetic per pixel.
#include <ATen/core/Tensor.h>
#include <ATen/Parallel.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/scalar_tensor.h>
#include <torch/library.h>

#include <cmath>
#include <limits>
#include <tuple>
#include <vector>

#include "lanes_simd.h"
#include "rows_cpu.h"
#include "walk.h"

namespace {

using namespace tao;

constexpr float kTiny = std::numeric_limits<float>::min();  // torch.finfo(float32).tiny
constexpr float kEps = 1e-12f;                                // normalize_channels' eps

// A block of pixels' geometry in lanes F: the position, the normal's input n (the given normal, or -position on
// background) over the scale s that _unit_facing divides it by, the unit normal and the sign that turns it toward
// the camera
template <class F> struct PixelGeometry {
  using M = typename LaneTraits<F>::M;
  F pos[3], ray[3];  // ray: d position / d depth (where the depth is valid)
  F n[3], s, unit[3], sign;
  M valid;

  PixelGeometry(const Image& img, const F& u, const F& v, const F& depth, const F* normal, const M& ok) : valid(ok) {
    unproject(img, u, v, F(1.0f), ray);
    const F safe = select(ok, depth, F(1.0f));  // (GBuffer.safe_depth)
    for (int c = 0; c < 3; ++c) pos[c] = ray[c] * safe;  // (unproject's at depth safe, bit for bit)
    F largest(0.0f);
    for (int c = 0; c < 3; ++c) {
      n[c] = select(ok, normal[c], neg(pos[c]));
      largest = max(largest, abs(n[c]));
    }
    // a length whose square would overflow or underflow: in units of the largest component first
    s = select(land(largest > F(1e-15f), largest < F(1e15f)), F(1.0f), max(largest, F(kTiny)));
    F scale(0.0f), sum(0.0f);  // channel_norm: the squares of n over its largest magnitude
    for (int c = 0; c < 3; ++c) n[c] = n[c] / s, scale = max(scale, abs(n[c]));
    scale = max(scale, F(kTiny));
    for (int c = 0; c < 3; ++c) sum = sum + (n[c] / scale) * (n[c] / scale);
    const F norm = max(sqrt(max(sum, F(kTiny))) * scale, F(kEps));
    F facing(0.0f);
    for (int c = 0; c < 3; ++c) unit[c] = n[c] / norm, facing = facing + unit[c] * pos[c];
    sign = select(facing <= F(0.0f), F(1.0f), F(-1.0f));
  }
};

void check_inputs(const at::Tensor& depth, const at::Tensor& normals, const at::Tensor& valid,
                  const at::Tensor& intrinsics) {
  TORCH_CHECK(depth.dim() == 4 && depth.size(1) == 1, "depth: expected (B, 1, H, W)");
  const int64_t B = depth.size(0), H = depth.size(2), W = depth.size(3);
  TORCH_CHECK(normals.dim() == 4 && normals.size(0) == B && normals.size(1) == 3 && normals.size(2) == H &&
                  normals.size(3) == W, "normals: expected (B, 3, H, W) as depth's");
  TORCH_CHECK(valid.sizes() == depth.sizes() && valid.scalar_type() == at::kBool && valid.is_contiguous(),
              "valid: expected contiguous bool (B, 1, H, W)");
  TORCH_CHECK(intrinsics.dim() == 2 && intrinsics.size(0) == B && intrinsics.size(1) == 4,
              "intrinsics: expected (B, 4): fx, fy, cx, cy");
  for (const at::Tensor* t : {&depth, &normals, &intrinsics})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous() && t->device().is_cpu(),
                "depth, normals, intrinsics: expected contiguous float32 CPU tensors");
}

// fn(geometry, p, n, b, q): the geometry of every block of n <= L pixels of a row in SIMD lanes (lanes past the
// row's end repeat its last pixel), p the first's index in (B, H, W), q in its (H, W) plane
template <class Fn>
void for_each_block(const at::Tensor& depth, const at::Tensor& normals, const at::Tensor& valid,
                    const at::Tensor& intrinsics, const Fn& fn) {
  constexpr int L = LaneTraits<Vec>::L;
  const int64_t B = depth.size(0), H = depth.size(2), W = depth.size(3), plane = H * W;
  const float *d = depth.data_ptr<float>(), *nrm = normals.data_ptr<float>(), *K = intrinsics.data_ptr<float>();
  const bool* ok = valid.data_ptr<bool>();
  torch_ao_rows::for_each_block<L>(B, H, W, false, [&](int64_t b, int64_t v, int64_t u0, int n, auto) {
    Image img{};
    img.H = H, img.W = W, img.fx = K[4 * b], img.fy = K[4 * b + 1], img.cx = K[4 * b + 2], img.cy = K[4 * b + 3];
    const int64_t q = v * W + u0, p = b * plane + q;
    alignas(64) float lane[6][L];  // u, valid, then (a block past the row's end) depth and the normal
    for (int l = 0; l < L; ++l) {
      const int64_t k = l < n ? l : n - 1;
      lane[0][l] = float(u0 + k), lane[1][l] = ok[p + k] ? 1.0f : 0.0f;
      if (n < L) {
        lane[2][l] = d[p + k];
        for (int c = 0; c < 3; ++c) lane[3 + c][l] = nrm[(3 * b + c) * plane + q + k];
      }
    }
    // (a whole block's depth and normals are consecutive floats: NCHW)
    auto at = [&](const float* x, int i) { return n == L ? Vec::loadu(x) : Vec::loadu(lane[i]); };
    const Vec normal[3] = {at(nrm + 3 * b * plane + q, 3), at(nrm + (3 * b + 1) * plane + q, 4),
                           at(nrm + (3 * b + 2) * plane + q, 5)};
    fn(PixelGeometry<Vec>(img, Vec::loadu(lane[0]), Vec(float(v)), at(d + p, 2), normal,
                          Vec::loadu(lane[1]) > Vec(0.5f)), p, n, b, q);
  });
}

// the n lanes of x into out[stride * l] (an interleaved channel)
void store_channel(const Vec& x, float* out, int n, int64_t stride) {
  if (stride == 1 && n == LaneTraits<Vec>::L) return x.store(out);  // (unaligned)
  alignas(64) float lane[LaneTraits<Vec>::L];
  x.store(lane);
  for (int l = 0; l < n; ++l) out[stride * l] = lane[l];
}

// the n lanes from in[channels * l] (channels interleaved, each into out[c]; zeros where in is null, and past n)
template <int channels> void load_channels(const float* in, int n, Vec* out) {
  constexpr int L = LaneTraits<Vec>::L;
  if (in && channels == 1 && n == L) {
    out[0] = Vec::loadu(in);
    return;
  }
  alignas(64) float lane[channels][L] = {};
  if (in)
    for (int l = 0; l < n; ++l)
      for (int c = 0; c < channels; ++c) lane[c][l] = in[channels * l + c];
  for (int c = 0; c < channels; ++c) out[c] = Vec::loadu(lane[c]);
}

// torch_ao_kernels::view_geometry: positions and unit normals facing the camera, both (B, H, W, 3), and the
// inverse depth and the depth, both (B, H, W) and NaN where invalid (walk_inputs')
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> view_geometry(const at::Tensor& depth,
                                                                         const at::Tensor& normals,
                                                                         const at::Tensor& valid,
                                                                         const at::Tensor& intrinsics) {
  check_inputs(depth, normals, valid, intrinsics);
  const int64_t B = depth.size(0), H = depth.size(2), W = depth.size(3);
  at::Tensor positions = at::empty({B, H, W, 3}, depth.options()), unit = at::empty({B, H, W, 3}, depth.options());
  at::Tensor inverse = at::empty({B, H, W}, depth.options()), depth_nan = at::empty({B, H, W}, depth.options());
  float *pos = positions.data_ptr<float>(), *out = unit.data_ptr<float>();
  float *inv = inverse.data_ptr<float>(), *dn = depth_nan.data_ptr<float>();
  const Vec nan(std::numeric_limits<float>::quiet_NaN());
  auto write = [&](const PixelGeometry<Vec>& g, int64_t p, int n, int64_t, int64_t) {
    for (int c = 0; c < 3; ++c) {
      store_channel(g.pos[c], pos + 3 * p + c, n, 3);
      store_channel(g.unit[c] * g.sign, out + 3 * p + c, n, 3);
    }
    const Vec d = neg(g.pos[2]);
    store_channel(select(g.valid, Vec(1.0f) / d, nan), inv + p, n, 1);
    store_channel(select(g.valid, d, nan), dn + p, n, 1);
  };
  for_each_block(depth, normals, valid, intrinsics, write);
  return {positions, unit, inverse, depth_nan};
}

// torch_ao_kernels::view_geometry_backward: d L / d depth (B, 1, H, W) and d L / d normals (B, 3, H, W) from those
// of the positions and the unit normals (B, H, W, 3), the inverse depth and the depth (B, H, W) (each empty: none).
// The normal's is normalize_channels' closed form ((g - n (g . n)) / |n|, g / eps where the norm is clamped)
// through the sign and the scale; on background it reaches the position, whose depth there is the constant 1.
std::tuple<at::Tensor, at::Tensor> view_geometry_backward(const at::Tensor& g_positions, const at::Tensor& g_normals,
                                                          const at::Tensor& g_inverse, const at::Tensor& g_depth_nan,
                                                          const at::Tensor& depth, const at::Tensor& normals,
                                                          const at::Tensor& valid, const at::Tensor& intrinsics) {
  check_inputs(depth, normals, valid, intrinsics);
  const int64_t B = depth.size(0), H = depth.size(2), W = depth.size(3), plane = H * W;
  for (const at::Tensor* g : {&g_positions, &g_normals})
    TORCH_CHECK(g->numel() == 0 || (g->numel() == B * plane * 3 && g->scalar_type() == at::kFloat &&
                                    g->is_contiguous() && g->device().is_cpu()),
                "g_positions, g_normals: expected empty or contiguous float32 (B, H, W, 3)");
  for (const at::Tensor* g : {&g_inverse, &g_depth_nan})
    TORCH_CHECK(g->numel() == 0 || (g->numel() == B * plane && g->scalar_type() == at::kFloat && g->is_contiguous() &&
                                    g->device().is_cpu()),
                "g_inverse, g_depth_nan: expected empty or contiguous float32 (B, H, W)");
  const float* gp = g_positions.numel() ? g_positions.data_ptr<float>() : nullptr;
  const float* gn = g_normals.numel() ? g_normals.data_ptr<float>() : nullptr;
  const float* g_inv = g_inverse.numel() ? g_inverse.data_ptr<float>() : nullptr;
  const float* g_dn = g_depth_nan.numel() ? g_depth_nan.data_ptr<float>() : nullptr;
  at::Tensor g_depth = at::empty({B, 1, H, W}, depth.options()), g_in = at::empty({B, 3, H, W}, depth.options());
  float *gd = g_depth.data_ptr<float>(), *gi = g_in.data_ptr<float>();
  for_each_block(depth, normals, valid, intrinsics, [&](const PixelGeometry<Vec>& g, int64_t p, int n, int64_t b,
                                                        int64_t q) {
    Vec to_n[3] = {Vec(0.0f), Vec(0.0f), Vec(0.0f)}, to_pos[3], g_unit[3], along_inverse, along_depth;
    load_channels<3>(gp ? gp + 3 * p : nullptr, n, to_pos);
    load_channels<1>(g_inv ? g_inv + p : nullptr, n, &along_inverse);
    load_channels<1>(g_dn ? g_dn + p : nullptr, n, &along_depth);
    if (gn) {
      Vec along(0.0f), length(0.0f);
      load_channels<3>(gn + 3 * p, n, g_unit);
      for (int c = 0; c < 3; ++c) g_unit[c] = g_unit[c] * g.sign, length = length + g.n[c] * g.unit[c];
      const Vec norm = max(length, Vec(kEps));  // |n| from the input and the output, as the tensor op's
      for (int c = 0; c < 3; ++c) along = along + g_unit[c] * g.unit[c];
      along = select(norm > Vec(kEps), along, Vec(0.0f));
      for (int c = 0; c < 3; ++c) to_n[c] = (g_unit[c] - g.unit[c] * along) / norm / g.s;
    }
    Vec slope(0.0f);
    for (int c = 0; c < 3; ++c) {
      to_pos[c] = select(g.valid, to_pos[c], to_pos[c] - to_n[c]);  // (the normal on background is -position)
      slope = slope + to_pos[c] * g.ray[c];
      store_channel(select(g.valid, to_n[c], Vec(0.0f)), gi + (3 * b + c) * plane + q, n, 1);
    }
    const Vec inverse = Vec(1.0f) / neg(g.pos[2]);  // (d (1 / d) / d d = -(1 / d)^2)
    slope = slope + along_depth - along_inverse * (inverse * inverse);
    store_channel(select(g.valid, slope, Vec(0.0f)), gd + p, n, 1);
  });
  return {g_depth, g_in};
}

// torch_ao_kernels::scale_derivative: kernels/frame.py's scale_derivative, sum(g x) in float64 over the pairs of
// gradients[i] and inputs[i] (float32, numel a multiple of valid's: channels per pixel) on the valid (B, H, W)
// pixels, in one pass. Summed in pieces of a fixed size, each piece's sum in order on one thread and the pieces'
// in order: the same total on any number of threads.
at::Tensor scale_derivative(const at::Tensor& valid, at::TensorList gradients, at::TensorList inputs) {
  TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous() && valid.device().is_cpu(),
              "valid: expected a contiguous bool (B, H, W) CPU tensor");
  TORCH_CHECK(gradients.size() == inputs.size(), "gradients, inputs: expected as many of each, got ",
              gradients.size(), " and ", inputs.size());
  constexpr int64_t kPiece = 1 << 13;  // pixels
  const int64_t pixels = valid.numel(), pieces = (pixels + kPiece - 1) / kPiece;
  if (pixels == 0) return at::scalar_tensor(0.0, at::TensorOptions().dtype(at::kDouble));
  const bool* ok = valid.data_ptr<bool>();
  std::vector<double> partial(size_t(pieces), 0.0);
  for (size_t i = 0; i < gradients.size(); ++i) {
    const at::Tensor &g = gradients[i], &x = inputs[i];
    for (const at::Tensor* t : {&g, &x})
      TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous() && t->device().is_cpu() &&
                      t->numel() == g.numel() && t->numel() % pixels == 0,
                  "gradients, inputs: expected contiguous float32 CPU pairs of equal size, channels per valid pixel");
    const int64_t C = g.numel() / pixels;
    const float *gp = g.data_ptr<float>(), *xp = x.data_ptr<float>();
    at::parallel_for(0, pieces, 1, [&](int64_t begin, int64_t end) {
      for (int64_t k = begin; k < end; ++k) {
        double sum = 0.0;
        for (int64_t p = k * kPiece; p < std::min(pixels, (k + 1) * kPiece); ++p)
          if (ok[p])  // (elsewhere the inputs hold NaN)
            for (int64_t c = 0; c < C; ++c) sum += double(gp[C * p + c]) * double(xp[C * p + c]);
        partial[size_t(k)] += sum;
      }
    });
  }
  double total = 0.0;
  for (double v : partial) total += v;
  return at::scalar_tensor(total, at::TensorOptions().dtype(at::kDouble));
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("view_geometry(Tensor depth, Tensor normals, Tensor valid, Tensor intrinsics) -> (Tensor, Tensor, Tensor, "
        "Tensor)");
  m.def("view_geometry_backward(Tensor g_positions, Tensor g_normals, Tensor g_inverse, Tensor g_depth_nan, "
        "Tensor depth, Tensor normals, Tensor valid, Tensor intrinsics) -> (Tensor, Tensor)");
  m.def("scale_derivative(Tensor valid, Tensor[] gradients, Tensor[] inputs) -> Tensor");
  m.impl("view_geometry", c10::DispatchKey::CPU, TORCH_FN(view_geometry));
  m.impl("scale_derivative", c10::DispatchKey::CPU, TORCH_FN(scale_derivative));
  m.impl("view_geometry_backward", c10::DispatchKey::CPU, TORCH_FN(view_geometry_backward));
}
