// Hard visibility-bitmask AO (the "default" variant of torch_ao.BitmaskAO), one pixel's whole walk in
// registers, SIMD across the pixels of a row (ATen's Vectorized<float>: the same SLEEF atan2/sin/cos
// as torch's own CPU kernels) and rows spread over torch's intra-op threads.
//
// It repeats the tensor path's float arithmetic operation by operation, so that the 32-bit masks come
// out the same: where a torch CPU kernel fuses a multiply and an add (cross products, addcmul, lerp,
// the tail of a 2-/3-element norm) this code calls fma, and nowhere else (built with
// -ffp-contract=off). See torch_ao/kernels/bitmask.py for the inputs; docs/performance.md for the
// measured agreement.
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/cpu/vec/functional.h>
#include <ATen/cpu/vec/vec.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <atomic>
#include <cmath>
#include <cstdint>
#include <vector>

#include "mkl_vml.h"  // torch.cos/torch.sin on a build with MKL call its vector math; so does this

namespace {

using Vec = at::vec::Vectorized<float>;
using Int = at::vec::Vectorized<int32_t>;
constexpr int L = Vec::size();

struct Settings {
  int64_t slices, steps;
  float radius, thickness, step_power, min_step_px, epsilon;
  bool jitter, bilinear, drop;
  int64_t seed, rounding;  // rounding: 0 ceil, 1 round (half to even), 2 floor
};

inline Vec fma(const Vec& a, const Vec& b, const Vec& c) { return at::vec::fmadd(a, b, c); }
inline Vec dot3(const Vec* a, const Vec* b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }
// torch's norm over a last dimension shorter than a vector: an fma chain, then sqrt
inline Vec norm3(const Vec* a) { return fma(a[2], a[2], fma(a[1], a[1], a[0] * a[0])).sqrt(); }
inline Vec norm2(const Vec& a, const Vec& b) { return fma(b, b, a * a).sqrt(); }
inline Vec select(const Vec& mask, const Vec& yes, const Vec& no) { return Vec::blendv(no, yes, mask); }
// torch.lerp: start + w (end - start) for |w| < 0.5, else end - (1 - w) (end - start), both fused
inline Vec lerp(const Vec& start, const Vec& end, const Vec& w) {
  Vec small = w.abs() < Vec(0.5f);
  return fma(select(small, w, w - Vec(1.0f)), end - start, select(small, start, end));
}

// Jimenez's interleaved gradient noise, in double as torch_ao.marching.interleaved_gradient_noise
inline float ign(float u, float v, int64_t seed) {
  double x = double(u) + 5.588238 * double(seed), y = double(v) + 5.588238 * double(seed);
  double a = 0.06711056 * x;
  double b = 0.00583715 * y;
  double s = a + b;
  double f = s - std::trunc(s);
  double g = 52.9829189 * f;
  return float(g - std::trunc(g));
}

inline Vec load_lanes(const float* lanes) { return Vec::loadu(lanes); }
inline Int to_int(const Vec& x) { return at::vec::convert_to_int_of_same_size<float>(x); }
inline Int operator~(const Int& x) { return x ^ Int(-1); }

void walk_row(const Settings& cfg, int64_t b, int64_t row, int64_t H, int64_t W, const float* positions,
              const float* normals, const float* inverse_depth, const float* depth, const bool* valid,
              const float* intrinsics, float* out) {
  const float fx = intrinsics[4 * b], fy = intrinsics[4 * b + 1], cx = intrinsics[4 * b + 2],
              cy = intrinsics[4 * b + 3];
  const int64_t plane = b * H * W;
  const float* inv = inverse_depth + plane;
  const bool* ok = valid + plane;
  const float* pos = positions + 3 * plane;
  const float slice_step = float(M_PI / double(cfg.slices));
  const Vec half_pi = Vec(float(M_PI / 2)), pi = Vec(float(M_PI)), sectors = Vec(32.0f);
  const Int zero_i = Int(0), one_i = Int(1), three_i = Int(3), all_i = Int(32), Wi = Int(int32_t(W));
  const Int Wlast = Int(int32_t(W - 1)), Hlast = Int(int32_t(H - 1));
  const Vec Wf = Vec(float(W)), Hf = Vec(float(H)), Wmax = Vec(float(W - 1)), Hmax = Vec(float(H - 1));
  // cos and sin of every pixel's slice angles, one call per row (torch evaluates them over all pixels)
  const int64_t S = cfg.slices, row_stride = (W + L - 1) / L * L;
  std::vector<float> angle(S * row_stride), cosine(S * row_stride), sine(S * row_stride);
  for (int64_t u = 0; u < row_stride; ++u) {
    const float a = cfg.jitter ? ign(float(u), float(row), cfg.seed) : 0.0f;
    for (int64_t s = 0; s < S; ++s) angle[s * row_stride + u] = (a + float(s)) * slice_step;
  }
#ifdef TORCH_AO_MKL_VML
  vmsCos(int(angle.size()), angle.data(), cosine.data(), kVmlMode);
  vmsSin(int(angle.size()), angle.data(), sine.data(), kVmlMode);
#else
  for (size_t i = 0; i < angle.size(); i += L) {
    Vec x = Vec::loadu(angle.data() + i);
    x.cos().store(cosine.data() + i);
    x.sin().store(sine.data() + i);
  }
#endif
  for (int64_t u0 = 0; u0 < W; u0 += L) {
    const int n = int(std::min<int64_t>(L, W - u0));
    alignas(64) float lane[10][L];
    bool any = false;
    for (int l = 0; l < L; ++l) {
      const int64_t u = u0 + std::min(l, n - 1), p = row * W + u;
      const bool live = l < n && ok[p];
      any |= live;
      for (int c = 0; c < 3; ++c) {
        lane[c][l] = pos[3 * p + c];
        lane[3 + c][l] = normals[3 * (plane + p) + c];
      }
      lane[6][l] = depth[plane + p];
      lane[7][l] = float(u0 + l);
      lane[8][l] = live ? 1.0f : 0.0f;
      lane[9][l] = cfg.jitter ? ign(float(u0 + l) + 37.0f, float(row) + 59.0f, cfg.seed + 1) : 0.5f;
    }
    if (!any) {
      for (int l = 0; l < n; ++l) out[plane + row * W + u0 + l] = 1.0f;
      continue;
    }
    Vec P[3], N[3], V[3], e1[3], e2[3];
    for (int c = 0; c < 3; ++c) {
      P[c] = load_lanes(lane[c]);
      N[c] = load_lanes(lane[3 + c]);
    }
    const Vec d = load_lanes(lane[6]), u = load_lanes(lane[7]), v = Vec(float(row));
    const Vec live = load_lanes(lane[8]) > Vec(0.5f);
    const Vec xi = load_lanes(lane[9]);
    // V = normalize(-P); e1 = normalize(cross(+Y, V)) = normalize((V_z, 0, -V_x)); e2 = cross(V, e1)
    {
      Vec minus[3] = {P[0].neg(), P[1].neg(), P[2].neg()};
      Vec len = at::vec::clamp_min(norm3(minus), Vec(1e-12f));
      for (int c = 0; c < 3; ++c) V[c] = minus[c] / len;
      Vec c1[3] = {V[2], Vec(0.0f), V[0].neg()};
      Vec len1 = at::vec::clamp_min(norm3(c1), Vec(1e-12f));
      for (int c = 0; c < 3; ++c) e1[c] = c1[c] / len1;
      e2[0] = fma(V[1], e1[2], (V[2] * e1[1]).neg());
      e2[1] = fma(V[2], e1[0], (V[0] * e1[2]).neg());
      e2[2] = fma(V[0], e1[1], (V[1] * e1[0]).neg());
    }
    const Vec depth_floor = Vec(1e-20f) * (d * d);
    Vec visible = Vec(0.0f);  // unoccluded sectors summed over slices (exact small integers)
    for (int64_t s = 0; s < cfg.slices; ++s) {
      const Vec cs = Vec::loadu(cosine.data() + s * row_stride + u0), sn = Vec::loadu(sine.data() + s * row_stride + u0);
      Vec T[3], axis[3], np[3];
      for (int c = 0; c < 3; ++c) T[c] = cs * e1[c] + sn * e2[c];
      axis[0] = fma(T[1], V[2], (T[2] * V[1]).neg());
      axis[1] = fma(T[2], V[0], (T[0] * V[2]).neg());
      axis[2] = fma(T[0], V[1], (T[1] * V[0]).neg());
      const Vec nd = dot3(N, axis);
      for (int c = 0; c < 3; ++c) np[c] = N[c] - axis[c] * nd;
      const Vec gamma = dot3(np, T).atan2(dot3(np, V));
      const Vec shift = (half_pi - gamma) / pi;
      // screen motion (pixels per world unit along +T) of the projection (fx x/d + cx, -fy y/d + cy)
      const Vec du = (Vec(fx) * (T[0] + (P[0] * T[2]) / d)) / d;
      const Vec dv = (Vec(-fy) * (T[1] + (P[1] * T[2]) / d)) / d;
      const Vec len = norm2(du, dv);
      const Vec unit_u = du / at::vec::clamp_min(len, Vec(1e-12f)), unit_v = dv / at::vec::clamp_min(len, Vec(1e-12f));
      const Vec span = at::vec::clamp_min(Vec(cfg.radius) * len - Vec(cfg.min_step_px), Vec(0.0f));
      Int occ = zero_i;
      for (int side = 1; side >= -1; side -= 2) {
        const Vec sgn = Vec(float(side)), scale = Vec(float(side / M_PI));
        const Vec su_dir = unit_u * sgn, sv_dir = unit_v * sgn;
        for (int64_t j = 0; j < cfg.steps; ++j) {
          Vec frac = (Vec(float(j)) + xi) / Vec(float(cfg.steps));
          if (cfg.step_power == 2.0f) {
            frac = frac * frac;
          } else if (cfg.step_power != 1.0f) {
            frac = frac.pow(Vec(cfg.step_power));
          }
          const Vec dist = Vec(cfg.min_step_px) + span * frac;
          const Vec su = u + dist * su_dir, sv = v + dist * sv_dir;
          Vec pos_s[3], sample_ok;
          if (cfg.bilinear) {
            const Vec fu0 = su.floor(), fv0 = sv.floor();
            const Vec fu = su - fu0, fv = sv - fv0;
            const Int iu = to_int(at::vec::clamp(fu0, Vec(-1.0f), Wf)), iv = to_int(at::vec::clamp(fv0, Vec(-1.0f), Hf));
            const Int c0 = at::vec::clamp(iu, zero_i, Wlast), c1 = at::vec::clamp(iu + one_i, zero_i, Wlast);
            const Int r0 = at::vec::clamp(iv, zero_i, Hlast) * Wi, r1 = at::vec::clamp(iv + one_i, zero_i, Hlast) * Wi;
            // invalid texels hold NaN: a sample is valid when its four taps are
            const Vec t0 = at::vec::gather<4>(inv, r0 + c0), t1 = at::vec::gather<4>(inv, r0 + c1);
            const Vec t2 = at::vec::gather<4>(inv, r1 + c0), t3 = at::vec::gather<4>(inv, r1 + c1);
            sample_ok = (t0 == t0) & (t1 == t1) & (t2 == t2) & (t3 == t3);
            if (cfg.drop) {
              sample_ok = sample_ok & (fu0 >= Vec(0.0f)) & (fu0 + Vec(1.0f) < Wf) & (fv0 >= Vec(0.0f)) &
                          (fv0 + Vec(1.0f) < Hf);
            }
            const Vec depth_s = lerp(lerp(t0, t1, fu), lerp(t2, t3, fu), fv).reciprocal();
            const Vec su_c = at::vec::clamp(su, Vec(0.0f), Wmax), sv_c = at::vec::clamp(sv, Vec(0.0f), Hmax);
            pos_s[0] = ((su_c - Vec(cx)) / Vec(fx)) * depth_s;
            pos_s[1] = ((sv_c - Vec(cy)).neg() / Vec(fy)) * depth_s;
            pos_s[2] = depth_s.neg();
          } else {
            const Vec fu0 = (su + Vec(0.5f)).floor(), fv0 = (sv + Vec(0.5f)).floor();
            const Int iu = at::vec::clamp(to_int(at::vec::clamp(fu0, Vec(-1.0f), Wf)), zero_i, Wlast);
            const Int iv = at::vec::clamp(to_int(at::vec::clamp(fv0, Vec(-1.0f), Hf)), zero_i, Hlast);
            const Int texel = iv * Wi + iu, at3 = texel * three_i;
            const Vec t = at::vec::gather<4>(inv, texel);
            sample_ok = t == t;
            if (cfg.drop) {
              sample_ok = sample_ok & (fu0 >= Vec(0.0f)) & (fu0 < Wf) & (fv0 >= Vec(0.0f)) & (fv0 < Hf);
            }
            for (int c = 0; c < 3; ++c) pos_s[c] = at::vec::gather<4>(pos + c, at3);
          }
          Vec delta[3];
          for (int c = 0; c < 3; ++c) delta[c] = pos_s[c] - P[c];
          // a sample on the centre texel (or a degenerate one) would give 0/0 angles: it never occludes
          sample_ok = sample_ok & (dot3(delta, delta) > depth_floor);
          for (int c = 0; c < 3; ++c) delta[c] = select(sample_ok, delta[c], V[c].neg());
          const Vec along_view = dot3(delta, V);
          const Vec along_tangent = sgn * dot3(delta, T);
          const Vec front = fma(along_tangent.atan2(along_view), scale, shift);
          const Vec back = fma(along_tangent.atan2(along_view - Vec(cfg.thickness)), scale, shift);
          const Vec xf = at::vec::clamp(front, Vec(0.0f), Vec(1.0f)), xb = at::vec::clamp(back, Vec(0.0f), Vec(1.0f));
          const Vec lo = side > 0 ? xf : xb, hi = side > 0 ? xb : xf;
          Vec width = (hi - lo) * sectors;
          if (cfg.epsilon > 0) width = width - Vec(cfg.epsilon);
          const Vec count = cfg.rounding == 0 ? width.ceil() : cfg.rounding == 1 ? width.round() : width.floor();
          // bits [k0, k0 + count) of 32, as (0xFFFFFFFF >> (32 - count)) << k0 (shifts by 32 give 0)
          const Int k0 = to_int(at::vec::clamp((lo * sectors).floor(), Vec(0.0f), sectors));
          const Int k1 = at::vec::minimum(k0 + to_int(at::vec::clamp(count, Vec(0.0f), sectors)), all_i);
          occ = occ | (((one_i << k1) - one_i) & ~((one_i << k0) - one_i));
        }
      }
      // 32 - popcount(occ), SWAR (arithmetic shifts are safe here: the masks clear the smeared sign bits)
      Int x = occ - ((occ >> one_i) & Int(0x55555555));
      x = (x & Int(0x33333333)) + ((x >> Int(2)) & Int(0x33333333));
      x = (x + (x >> Int(4))) & Int(0x0F0F0F0F);
      const Vec free_sectors = at::vec::convert_to_fp_of_same_size<float>(all_i - ((x * Int(0x01010101)) >> Int(24)));
      visible = visible + free_sectors;
    }
    const Vec vis = select(live, (visible * Vec(1.0f / 32.0f)) / Vec(float(cfg.slices)), Vec(1.0f));
    alignas(64) float result[L];
    vis.store(result);
    for (int l = 0; l < n; ++l) out[plane + row * W + u0 + l] = result[l];
  }
}

at::Tensor bitmask_hard(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                        const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics,
                        int64_t slices, int64_t steps, double radius, double thickness, double step_power,
                        double min_step_px, bool jitter, int64_t seed, bool bilinear, bool drop, int64_t rounding,
                        double epsilon) {
  TORCH_CHECK(positions.dim() == 4 && positions.size(3) == 3, "positions: expected (B, H, W, 3)");
  for (const at::Tensor* t : {&positions, &normals, &inverse_depth, &depth, &intrinsics})
    TORCH_CHECK(t->scalar_type() == at::kFloat && t->is_contiguous(), "expected contiguous float32 inputs");
  TORCH_CHECK(valid.scalar_type() == at::kBool && valid.is_contiguous(), "valid: expected contiguous bool");
  const int64_t B = positions.size(0), H = positions.size(1), W = positions.size(2);
  Settings cfg{slices, steps, float(radius), float(thickness), float(step_power), float(min_step_px),
               float(epsilon), jitter, bilinear, drop, seed, rounding};
  at::Tensor out = at::empty({B, 1, H, W}, positions.options());
  const float *P = positions.data_ptr<float>(), *Nr = normals.data_ptr<float>();
  const float *inv = inverse_depth.data_ptr<float>(), *d = depth.data_ptr<float>(), *K = intrinsics.data_ptr<float>();
  const bool* ok = valid.data_ptr<bool>();
  float* o = out.data_ptr<float>();
  // rows handed out a few at a time to whichever thread is free (even split fails when a core is busy)
  const int64_t rows = B * H, chunk = 4;
  std::atomic<int64_t> next{0};
  at::parallel_for(0, at::get_num_threads(), 1, [&](int64_t, int64_t) {
#ifdef TORCH_AO_MKL_VML
    const int mkl_threads = MKL_Set_Num_Threads_Local(1);  // MKL's own threads inside ours: 7x slower
#endif
    for (int64_t r0 = next.fetch_add(chunk); r0 < rows; r0 = next.fetch_add(chunk))
      for (int64_t r = r0; r < std::min(rows, r0 + chunk); ++r) walk_row(cfg, r / H, r % H, H, W, P, Nr, inv, d, ok, K, o);
#ifdef TORCH_AO_MKL_VML
    MKL_Set_Num_Threads_Local(mkl_threads);
#endif
  });
  return out;
}

}  // namespace

TORCH_LIBRARY(torch_ao_kernels, m) {
  m.def("bitmask_hard(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, int slices, int steps, float radius, float thickness, float step_power, "
        "float min_step_px, bool jitter, int seed, bool bilinear, bool drop, int rounding, float epsilon) -> Tensor");
  m.impl("bitmask_hard", c10::DispatchKey::CPU, TORCH_FN(bitmask_hard));
}
