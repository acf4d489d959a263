// GTAO (torch_ao.GTAO, its three variants) in one fused pass: the walk of walk_cpu.h with the
// accumulators of torch_ao/methods/gtao.py (a horizon per side, then the clamped arc integral of
// torch_ao/ops.py), one pixel's walk in registers, SIMD across the pixels of a row.
//
// It returns the per-pixel sums over slices that GTAOAccumulator.finish turns into the outputs (the
// slice integrals, the unoccluded integrals and, when asked, the bent-normal sum), so that the
// normalisation, final power and multi-bounce fit have one definition (in Python). HBAO
// (torch_ao/methods/hbao.py) is the same walk over the full circle with its own accumulator.
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
  const Vec root = select(inside, torch_ao_walk::sqrt(select(inside, Vec(1.0f) - ax, Vec(1.0f))), Vec(0.0f));
  const Vec res = (Vec(-0.156583f) * ax + half_pi) * root;
  return select(x >= Vec(0.0f), res, Vec(float(M_PI)) - res);
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
  int channels() const { return g.bent ? 5 : 2; }
  void store(const Sums& sums, float lanes[][L]) const {
    sums.vis.store(lanes[0]);
    sums.free.store(lanes[1]);
    if (g.bent)
      for (int c = 0; c < 3; ++c) sums.bent[c].store(lanes[2 + c]);
  }

  State begin_slice(const Pixels&, const Slice& sl) const {
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

// HBAOAccumulator (torch_ao/methods/hbao.py): per direction, the running horizon sin h above the
// tangent's sin t and its weighted rise
struct HBAOSettings {
  float radius, angle_bias;
  bool quadratic, incremental, view_elevation;
};

struct HBAOAccumulator {
  HBAOSettings h;
  struct State { Vec sin_t, sin_h, ao, w; };
  struct Sums { Vec ao; };
  int channels() const { return 1; }
  void store(const Sums& sums, float lanes[][L]) const { sums.ao.store(lanes[0]); }

  State begin_slice(const Pixels& px, const Slice& sl) const {
    Vec t;
    if (h.view_elevation) {  // the hemisphere boundary on side +1 sits at angle pi/2 + gamma from V
      t = sl.gamma.neg();
    } else {  // the elevation of the tangent cos(b) V + sin(b) T, b = pi/2 + gamma, above the image plane
      const Vec boundary = half_pi + sl.gamma;
      Vec c, s;
      cos_sin(&boundary, 1, &c, &s);
      t = asin(at::vec::clamp(c * px.V[2] + s * sl.T[2], Vec(float(-1 + 1e-7)), Vec(float(1 - 1e-7))));
    }
    const Vec biased = at::vec::clamp_max(t + Vec(h.angle_bias), half_pi);
    Vec sin_t;
    cos_sin(&biased, 1, nullptr, &sin_t);
    return State{sin_t, sin_t, Vec(0.0f), Vec(0.0f)};
  }

  void step(State& st, int, const Pixels& px, const Slice& sl, const Sample& smp) const {
    const Vec distance = norm3(smp.delta);
    Vec sin_s;
    if (h.view_elevation) {
      const Vec angle = dot3(smp.delta, sl.T).atan2(dot3(smp.delta, px.V));
      cos_sin(&angle, 1, &sin_s, nullptr);
    } else {
      sin_s = smp.delta[2] / at::vec::clamp_min(distance, Vec(1e-30f));
    }
    const Vec r = distance / Vec(std::max(h.radius, 1e-30f));
    const Vec w = at::vec::clamp_min(h.quadratic ? Vec(1.0f) - r * r : Vec(1.0f) - r, Vec(0.0f));
    const Vec rise = smp.valid & (r < Vec(1.0f)) & (sin_s > st.sin_h);
    if (h.incremental) {
      st.ao = select(rise, st.ao + w * (sin_s - st.sin_h), st.ao);
    } else {
      st.w = select(rise, w, st.w);
    }
    st.sin_h = select(rise, sin_s, st.sin_h);
  }

  void end_slice(const State& st, const Pixels&, const Slice&, Sums& sums, bool first) const {
    const Vec ao = h.incremental ? st.ao : st.w * (st.sin_h - st.sin_t);
    sums.ao = first ? ao : sums.ao + ao;
  }
};

at::Tensor gtao_sums(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                     const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, int64_t variant,
                     int64_t slices, int64_t steps, double walk_radius, double radius, double falloff, double thickness,
                     double step_power, double min_step_px, double max_radius_px, bool jitter, int64_t seed,
                     bool bilinear, bool drop, bool screen_azimuth, bool projected_normal_weight, bool bent) {
  TORCH_CHECK(variant >= 0 && variant <= 2, "variant: expected 0 (exact), 1 (hdrp) or 2 (ue4)");
  const Variant v = Variant(variant);
  const WalkSettings cfg{slices, steps, float(walk_radius), float(step_power), float(min_step_px), float(max_radius_px),
                         jitter, bilinear, drop, /*full_circle=*/false, screen_azimuth, seed,
                         v == Variant::exact ? Steps::power : v == Variant::hdrp ? Steps::hdrp : Steps::ue4};
  const GTAOAccumulator acc{{v, float(radius), float(falloff), float(thickness), projected_normal_weight, bent}};
  return walk(cfg, acc, Inputs{positions, normals, inverse_depth, depth, valid, intrinsics});
}

at::Tensor hbao_sums(const at::Tensor& positions, const at::Tensor& normals, const at::Tensor& inverse_depth,
                     const at::Tensor& depth, const at::Tensor& valid, const at::Tensor& intrinsics, int64_t slices,
                     int64_t steps, double radius, double angle_bias, bool quadratic, bool incremental,
                     bool view_elevation, double step_power, double min_step_px, bool jitter, int64_t seed,
                     bool bilinear, bool drop, bool screen_azimuth) {
  const WalkSettings cfg{slices, steps, float(radius), float(step_power), float(min_step_px), /*max_radius_px=*/0.0f,
                         jitter, bilinear, drop, /*full_circle=*/true, screen_azimuth, seed, Steps::power};
  const HBAOAccumulator acc{{float(radius), float(angle_bias), quadratic, incremental, view_elevation}};
  return walk(cfg, acc, Inputs{positions, normals, inverse_depth, depth, valid, intrinsics});
}

}  // namespace

TORCH_LIBRARY_FRAGMENT(torch_ao_kernels, m) {
  m.def("gtao_sums(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, int variant, int slices, int steps, float walk_radius, float radius, float falloff, "
        "float thickness, float step_power, float min_step_px, float max_radius_px, bool jitter, int seed, "
        "bool bilinear, bool drop, bool screen_azimuth, bool projected_normal_weight, bool bent) -> Tensor");
  m.impl("gtao_sums", c10::DispatchKey::CPU, TORCH_FN(gtao_sums));
  m.def("hbao_sums(Tensor positions, Tensor normals, Tensor inverse_depth, Tensor depth, Tensor valid, "
        "Tensor intrinsics, int slices, int steps, float radius, float angle_bias, bool quadratic, bool incremental, "
        "bool view_elevation, float step_power, float min_step_px, bool jitter, int seed, bool bilinear, bool drop, "
        "bool screen_azimuth) -> Tensor");
  m.impl("hbao_sums", c10::DispatchKey::CPU, TORCH_FN(hbao_sums));
}
