// GTAO (torch_ao.GTAO, its three variants) in one fused pass: the walk of walk_cpu.h with the
// accumulators of torch_ao/methods/gtao.py (a horizon per side, then the clamped arc integral of
// torch_ao/ops.py), one pixel's walk in registers, SIMD across the pixels of a row.
//
// It returns the per-pixel sums over slices that GTAOAccumulator.finish turns into the outputs (the
// slice integrals, the unoccluded integrals and, when asked, the bent-normal sum), so that the
// normalisation, final power and multi-bounce fit have one definition (in Python).
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include "walk_cpu.h"

namespace {

using namespace torch_ao_walk;

enum class Variant : int64_t { exact = 0, hdrp = 1, ue4 = 2 };

struct GTAOSettings {
  Variant variant;
  float radius;            // world units: where samples stop counting (not the walk's radius)
  float falloff;           // exact: falloff_range * radius clamped to 1e-12; <= 0: a hard cut
  float thickness;         // ue4: the thickness heuristic
  bool projected_normal_weight, bent;
};

const Vec half_pi = Vec(float(M_PI / 2));

// HDRP's GTAOFastAcos / UE4's acosFast (torch_ao.ops.fast_acos)
inline Vec fast_acos(const Vec& x) {
  const Vec ax = x.abs();
  const Vec inside = ax < Vec(1.0f);
  const Vec root = select(inside, select(inside, Vec(1.0f) - ax, Vec(1.0f)).sqrt(), Vec(0.0f));
  const Vec res = (Vec(-0.156583f) * ax + half_pi) * root;
  return select(x >= Vec(0.0f), res, Vec(float(M_PI)) - res);
}

inline Vec sign(const Vec& x) {
  return select(x > Vec(0.0f), Vec(1.0f), select(x < Vec(0.0f), Vec(-1.0f), Vec(0.0f)));
}

// torch_ao.ops.arc_integral's two halves, given cos(2 h - n) of each end
inline Vec arc_integral(const Vec& h1, const Vec& h2, const Vec& cos1, const Vec& cos2, const Vec& cos_n, const Vec& sin_n) {
  const Vec two = Vec(2.0f);
  return Vec(0.25f) * ((cos1.neg() + cos_n + two * h1 * sin_n) + (cos2.neg() + cos_n + two * h2 * sin_n));
}

// GTAOAccumulator and its three variants: begin_slice, step, angles + end_slice
struct GTAOAccumulator {
  GTAOSettings g;
  struct State { Vec best[2]; };  // [0]: side +1, [1]: side -1
  struct Sums { Vec vis, free, bent[3]; };

  State begin_slice(const Slice& sl) const {
    if (g.variant == Variant::exact)  // the smallest angle from V per side, from the hemisphere boundary
      return State{{half_pi + sl.gamma, half_pi - sl.gamma}};
    return State{{Vec(-1.0f), Vec(-1.0f)}};  // the shaders' largest horizon cosine, from cos(pi)
  }

  void step(State& st, int side, const Pixels& px, const Slice& sl, const Sample& smp) const {
    Vec& best = st.best[side > 0 ? 0 : 1];
    const Vec R = Vec(g.radius);
    if (g.variant == Variant::exact) {
      const Vec along_view = dot3(smp.delta, px.V), along_tangent = Vec(float(side)) * dot3(smp.delta, sl.T);
      const Vec theta = at::vec::clamp(along_tangent.atan2(along_view), Vec(0.0f), Vec(float(M_PI)));
      const Vec distance = norm3(smp.delta);
      Vec w = g.falloff > 0 ? at::vec::clamp((R - distance) / Vec(g.falloff), Vec(0.0f), Vec(1.0f))
                            : select(distance < R, Vec(1.0f), Vec(0.0f));
      w = select(smp.valid, w, Vec(0.0f));
      const Vec bound = half_pi + Vec(float(side)) * sl.gamma;
      best = at::vec::minimum(best, bound + w * (theta - bound));
    } else if (g.variant == Variant::hdrp) {  // UpdateHorizon
      const Vec distance = norm3(smp.delta);
      const Vec cand = dot3(smp.delta, px.V) / at::vec::clamp_min(distance, Vec(1e-30f));
      const Vec falloff = at::vec::clamp(Vec(1.0f) - (distance * distance) / (R * R), Vec(0.0f), Vec(1.0f));
      const Vec upd = select(cand > best, best + falloff * (cand - best), best);
      best = select(smp.valid, upd, best);
    } else {  // SearchForLargestAngleDual
      const Vec len_sq = dot3(smp.delta, smp.delta);
      Vec ang = dot3(smp.delta, px.V) * (len_sq + Vec(1e-4f)).rsqrt();
      const Vec falloff = at::vec::clamp(len_sq * (Vec(2.0f) / (R * R)), Vec(0.0f), Vec(1.0f));
      ang = ang + falloff * (best - ang);
      const Vec upd = select(ang > best, ang, ang + Vec(g.thickness) * (best - ang));
      best = select(smp.valid, upd, best);
    }
  }

  void end_slice(const State& st, const Pixels& px, const Slice& sl, Sums& sums, bool first) const {
    // angles: the horizons h1 <= 0 <= h2, the projected normal's angle n, its cos and sin, the weight
    Vec h1, h2, n, cos_n, sin_n, weight, degenerate;
    Vec cs[2];
    cos_sin(&sl.gamma, 1, &cs[0], &cs[1]);  // cos(gamma), sin(gamma)
    const Vec length = sl.length;
    if (g.variant == Variant::exact) {
      h1 = st.best[1].neg(), h2 = st.best[0], n = sl.gamma, cos_n = cs[0], sin_n = cs[1], weight = length;
    } else {
      const Vec one = Vec(1.0f), minus_one = Vec(-1.0f);
      h1 = fast_acos(at::vec::clamp(st.best[1], minus_one, one)).neg();
      h2 = fast_acos(at::vec::clamp(st.best[0], minus_one, one));
      if (g.variant == Variant::hdrp) {
        const Vec safe = at::vec::clamp_min(length, Vec(1e-12f));
        const Vec nT = (length * cs[1]) / safe, nV = (length * cs[0]) / safe;
        cos_n = at::vec::clamp(nV, minus_one, one);
        n = sign(nT) * fast_acos(cos_n);
        cos_sin(&n, 1, nullptr, &sin_n);
        weight = g.projected_normal_weight ? length : one;
        degenerate = length < Vec(1e-6f);
      } else {  // ComputeInnerIntegral, with its own |n_p| + 1e-6
        const Vec Lp = length + Vec(1e-6f);
        const Vec cos_ang = (length * cs[1]) / Lp;
        n = half_pi - fast_acos(at::vec::clamp(cos_ang, minus_one, one));
        cos_n = (length * cs[0]) / Lp, sin_n = cos_ang, weight = Lp;
      }
    }
    const Vec lo = n - half_pi, hi = n + half_pi;
    h1 = at::vec::maximum(h1, lo);  // n + max(h1 - n, -pi/2)
    h2 = at::vec::minimum(h2, hi);  // n + min(h2 - n, pi/2)
    const Vec two = Vec(2.0f);
    Vec arg[4] = {two * h1 - n, two * h2 - n, two * lo - n, two * hi - n}, c[4];
    cos_sin(arg, 4, c, nullptr);
    Vec integral = weight * arc_integral(h1, h2, c[0], c[1], cos_n, sin_n);
    Vec free = weight * arc_integral(lo, hi, c[2], c[3], cos_n, sin_n);
    if (g.variant == Variant::hdrp) {  // AnyIsNaN(...) ? 1
      integral = select(degenerate, Vec(1.0f), integral);
      free = select(degenerate, Vec(1.0f), free);
    }
    sums.vis = first ? integral : sums.vis + integral;
    sums.free = first ? free : sums.free + free;
    if (g.bent) {  // bent_vector(h1, h2, n), times |n_p|, in the slice's (V, T) frame
      Vec h[2] = {h2, h1}, ch[2], sh[2], cn, sn;
      cos_sin(h, 2, ch, sh);
      cos_sin(&n, 1, &cn, &sn);
      const Vec three = Vec(3.0f);
      Vec fc[2], fs[2];
      for (int k = 0; k < 2; ++k) {
        const Vec c3 = ch[k] * ch[k] * ch[k], s3 = sh[k] * sh[k] * sh[k];
        fc[k] = ((c3.neg() * cn) + s3 * sn) / three;
        fs[k] = (s3 * cn) / three + sn * (c3 / three - ch[k]);
      }
      const Vec along_v = (fc[0] + fc[1]) + (two * cn) / three;
      const Vec along_t = (fs[0] + fs[1]) + (Vec(4.0f) * sn) / three;
      for (int k = 0; k < 3; ++k) {
        const Vec b = length * (along_v * px.V[k] + along_t * sl.T[k]);
        sums.bent[k] = first ? b : sums.bent[k] + b;
      }
    }
  }
};

void walk_row(const WalkSettings& cfg, const GTAOAccumulator& acc, const Image& img, const float* normals,
              const float* depth, const bool* valid, int64_t row, float* sums_out, float* bent_out) {
  const SliceAngles angles(cfg, row, img.W);
  for (int64_t u0 = 0; u0 < img.W; u0 += L) {
    const Pixels px(cfg, img, normals, depth, valid, row, u0);
    const int64_t p0 = row * img.W + u0;
    if (!px.any) {  // background: zero sums (the caller puts 1 and the G-buffer's normal there)
      for (int l = 0; l < px.n; ++l) {
        sums_out[2 * (p0 + l)] = sums_out[2 * (p0 + l) + 1] = 0.0f;
        if (bent_out != nullptr)
          for (int c = 0; c < 3; ++c) bent_out[3 * (p0 + l) + c] = 0.0f;
      }
      continue;
    }
    GTAOAccumulator::Sums sums;
    for (int64_t s = 0; s < cfg.slices; ++s) {  // Algorithm 1: for each slice
      const Slice sl(cfg, img, px, angles.cos(s, u0), angles.sin(s, u0));
      GTAOAccumulator::State st = acc.begin_slice(sl);
      for (int side = 1; side >= -1; side -= 2) {  // for each side
        const Vec sgn = Vec(float(side));
        for (int64_t j = 0; j < cfg.steps; ++j) {  // for each sample
          const Sample smp(cfg, img, px, sl, sgn, step_distance(cfg, sl, px.xi, j));
          acc.step(st, side, px, sl, smp);
        }
      }
      acc.end_slice(st, px, sl, sums, s == 0);
    }
    alignas(64) float lanes[5][L];
    const Vec zero = Vec(0.0f);
    select(px.live, sums.vis, zero).store(lanes[0]);
    select(px.live, sums.free, zero).store(lanes[1]);
    if (bent_out != nullptr)
      for (int c = 0; c < 3; ++c) select(px.live, sums.bent[c], zero).store(lanes[2 + c]);
    for (int l = 0; l < px.n; ++l) {
      sums_out[2 * (p0 + l)] = lanes[0][l];
      sums_out[2 * (p0 + l) + 1] = lanes[1][l];
      if (bent_out != nullptr)
        for (int c = 0; c < 3; ++c) bent_out[3 * (p0 + l) + c] = lanes[2 + c][l];
    }
  }
}

std::vector<at::Tensor> gtao_sums(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                                  const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
                                  int64_t variant, int64_t slices, int64_t steps, double walk_radius, double radius,
                                  double falloff, double thickness, double step_power, double min_step_px,
                                  double max_radius_px, bool jitter, int64_t seed, bool bilinear, bool drop,
                                  bool screen_azimuth, bool projected_normal_weight, bool bent) {
  TORCH_CHECK(positions.dim() == 4 && positions.size(3) == 3, "positions: expected (B, H, W, 3)");
  for (const at::Tensor* t : {&positions, &normals, &inverse_depth, &depth, &intrinsics})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous(), "expected contiguous float32 inputs");
  TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous(), "valid: expected contiguous bool");
  TORCH_CHECK(variant >= 0 && variant <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2);
  const Variant v = Variant(variant);
  const WalkSettings cfg{slices, steps, float(walk_radius), float(step_power), float(min_step_px), float(max_radius_px),
                         jitter, bilinear, drop, /*full_circle=*/false, screen_azimuth, seed,
                         v == Variant::exact ? Steps::power : v == Variant::hdrp ? Steps::hdrp : Steps::ue4};
  const GTAOAccumulator acc{{v, float(radius), float(falloff), float(thickness), projected_normal_weight, bent}};
  at::Tensor sums = at::empty({B, H, W, 2}, positions.options());
  at::Tensor bent_sum = bent ? at::empty({B, H, W, 3}, positions.options()) : at::zeros({0}, positions.options());
  const float *P = positions.data_ptr<float>(), *Nr = normals.data_ptr<float>();
  const float *inv = inverse_depth.data_ptr<float>(), *d = depth.data_ptr<float>(), *K = intrinsics.data_ptr<float>();
  const bool* ok = valid.data_ptr<bool>();
  float *out = sums.data_ptr<float>(), *out_bent = bent ? bent_sum.data_ptr<float>() : nullptr;
  const int64_t plane = H * W;
  for_each_row(B, H, [&](int64_t b, int64_t row) {
    const Image img{H, W, K[4 * b], K[4 * b + 1], K[4 * b + 2], K[4 * b + 3], inv + b * plane, P + 3 * b * plane};
    walk_row(cfg, acc, img, Nr + 3 * b * plane, d + b * plane, ok + b * plane, row, out + 2 * b * plane,
             out_bent == nullptr ? nullptr : out_bent + 3 * b * plane);
  });
  return {sums, bent_sum};
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("gtao_sums(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, int variant, int slices, int steps, float walk_radius, float radius, float falloff, "
        "float thickness, float step_power, float min_step_px, float max_radius_px, bool jitter, int seed, "
        "bool bilinear, bool drop, bool screen_azimuth, bool projected_normal_weight, bool bent) -> Tensor[]");
  m.impl("gtao_sums", c10::DispatchKey::CPU, TORCH_FN(gtao_sums));
}
