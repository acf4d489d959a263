// The walk's and the accumulators' settings as two arrays (int64 and float32), packed in Python by
// torch_ao/kernels/launch.py: one encoding for every backend (the CPU operator and the CUDA kernel read
// the same arrays), and walk_pixel, one pixel's whole walk: the body of a CUDA thread, and of the CPU's
// scalar lanes.
#pragma once

#include "bitmask.h"
#include "bitmask_glsl.h"
#include "exact_soft.h"
#include "horizon.h"
#include "soft.h"
#include "soft_glsl.h"
#include "ssao.h"

namespace tao {

// ints: slices, steps, seed, placement, jitter, bilinear, drop, full_circle, screen_azimuth, edge_aware,
// sphere_extent, noise, stagger, the walk's table's start in the floats (0: none), unprojected, then the
// accumulator's from kAccInts; floats: radius, step_power, min_step_px, max_radius_px, then from kAccFloats the accumulator's, then
// the walk's table (WalkSettings::table)
constexpr int kAccInts = 16, kAccFloats = 4;

// The step placement of the walk's packed ints (a call can tell its accumulator by it before unpacking the rest)
TAO_FN Steps packed_placement(const int64_t* i) { return Steps(i[3]); }

TAO_FN WalkSettings unpack_walk(const int64_t* i, const float* f) {
  WalkSettings c;
  c.slices = i[0], c.steps = i[1], c.seed = i[2], c.placement = packed_placement(i);
  c.jitter = i[4] != 0, c.bilinear = i[5] != 0, c.drop = i[6] != 0, c.full_circle = i[7] != 0, c.screen_azimuth = i[8] != 0;
  c.edge_aware = i[9] != 0, c.sphere_extent = i[10] != 0, c.noise = Noise(i[11]);
  c.stagger = i[12] != 0;
  c.table = i[13] > 0 ? f + i[13] : nullptr;
  c.unprojected = i[14] != 0;
  c.projected_normal = i[15] != 0;
  c.radius = f[0], c.step_power = f[1], c.min_step_px = f[2], c.max_radius_px = f[3];
  return c;
}

// ints: variant, projected_normal_weight, bent; floats: radius, falloff, thickness
TAO_FN GTAOAccumulator unpack_gtao(const int64_t* i, const float* f) {
  i += kAccInts, f += kAccFloats;
  return GTAOAccumulator{GTAOVariant(i[0]), f[0], f[1], f[2], i[1] != 0, i[2] != 0};
}

// ints: quadratic, incremental, view_elevation; floats: radius, angle_bias
TAO_FN HBAOAccumulator unpack_hbao(const int64_t* i, const float* f) {
  i += kAccInts, f += kAccFloats;
  return HBAOAccumulator{f[0], f[1], i[0] != 0, i[1] != 0, i[2] != 0};
}

// ints: rounding, cosine, indirect, bent, the thickness' read (ThicknessRead), the variant's angles (SectorAngles),
// along_ray, clip; floats: the thickness' offset, epsilon, its scale, its growth, the clip's radius
TAO_FN BitmaskAccumulator unpack_bitmask(const int64_t* i, const float* f) {
  const int64_t slices = i[0];
  i += kAccInts, f += kAccFloats;
  return BitmaskAccumulator{slices, ThicknessModel{f[0], f[2], ThicknessRead(i[4]), f[3]}, f[1], i[0], i[1] != 0, i[2] != 0,
                            i[3] != 0, SectorAngles(i[5]), i[6] != 0, i[7] != 0, f[4]};
}

// ints: rounding, indirect, exact (glsl_numerics "mesa"/"mesa_mediump"), the thickness' read (ThicknessRead); floats:
// the thickness' offset, its scale, its growth. The walk's slices are sliceCount + 1
TAO_FN GlslAccumulator unpack_glsl(const int64_t* i, const float* f) {
  const int64_t slices = i[0];
  i += kAccInts, f += kAccFloats;
  return GlslAccumulator{slices - 1, ThicknessModel{f[0], f[1], ThicknessRead(i[3]), f[2]}, i[0], i[1] != 0,
                         GlslVectorOps{i[2] != 0}};
}

// ints: cosine, along_ray, clip, the thickness' read (ThicknessRead), whether it has a growth; floats: the
// thickness' offset, its scale, radius, epsilon, its growth
TAO_FN ExactAccumulator unpack_exact(const int64_t* i, const float* f) {
  const int64_t slices = i[0], steps = i[1];
  i += kAccInts, f += kAccFloats;
  return ExactAccumulator{slices, steps, ThicknessModel{f[0], f[1], ThicknessRead(i[3]), f[4]}, f[2], f[3], i[0] != 0,
                          i[1] != 0, i[2] != 0};
}

// unpack_exact's settings: the exact union with d visibility / d radius, thickness, thickness_scale (, its growth)
template <bool kGrowth> TAO_FN ExactGradAccumulator<kGrowth> unpack_exact_gradients(const int64_t* i, const float* f) {
  return ExactGradAccumulator<kGrowth>{unpack_exact(i, f), unpack_walk(i, f)};
}
TAO_FN ExactGradAccumulator<false> unpack_exact_gradients_plain(const int64_t* i, const float* f) {
  return unpack_exact_gradients<false>(i, f);
}
TAO_FN ExactGradAccumulator<true> unpack_exact_gradients_growth(const int64_t* i, const float* f) {
  return unpack_exact_gradients<true>(i, f);
}

// The soft union's rounding offset (sectors.rule.rounding_offset) and its smooth floor's window of its tau
// (sweeps.floor_window_width)
template <class Union> TAO_FN void soft_window(Union& acc) {
  acc.delta = acc.rounding == 0 ? 0.0f : acc.rounding == 1 ? 0.5f : 1.0f;
  acc.reach = int(ceil(kSoftClamp * acc.tau)) + 1;
  acc.window = 2 * acc.reach < kSectors ? 2 * acc.reach : kSectors;
  acc.windowed = acc.window <= kSoftWindowMax;
  // sigmoid_run's runs: the first term's clamp at kSoftClamp + (run - 1) / tau, its products down to e^-(that +
  // (run - 1) / tau), at least e^-86 (normal floats: e^-87.3)
  const double inv_tau = 1.0 / double(acc.tau);
  acc.run = 1 + int(floor(28.0 / inv_tau));
  if (acc.run > kSoftRunMax) acc.run = kSoftRunMax;
  acc.run_bound = float(double(kSoftClamp) + double(acc.run - 1) * inv_tau);
  acc.run_ratio = expf(float(-inv_tau));
}

// ints: rounding, cosine, straight_through, the thickness' read (ThicknessRead), the variant's angles
// (SectorAngles), bent, indirect, whether the thickness has a growth, the exact variant's segment geometry (the back
// point along the sample's ray, the clip to the radius' sphere); floats: the thickness' offset, epsilon, tau, the
// thickness' scale, its growth
template <bool kGradients, bool kAdjoint = false, int kMostSteps = kSoftMaxSteps>
TAO_FN SoftAccumulator<kGradients, kAdjoint, kMostSteps> unpack_soft(const int64_t* i, const float* f) {
  SoftAccumulator<kGradients, kAdjoint, kMostSteps> acc;
  acc.walk = unpack_walk(i, f);
  i += kAccInts, f += kAccFloats;
  acc.rounding = i[0], acc.cosine = i[1] != 0, acc.straight_through = i[2] != 0, acc.angles = SectorAngles(i[4]);
  acc.bent = i[5] != 0, acc.indirect = i[6] != 0, acc.grows = i[7] != 0, acc.along_ray = i[8] != 0, acc.clip = i[9] != 0;
  acc.thickness = ThicknessModel{f[0], f[3], ThicknessRead(i[3]), f[4]}, acc.epsilon = f[1], acc.tau = f[2];
  soft_window(acc);
  return acc;
}
TAO_FN SoftAccumulator<false> unpack_soft_forward(const int64_t* i, const float* f) { return unpack_soft<false>(i, f); }
TAO_FN SoftAccumulator<true> unpack_soft_gradients(const int64_t* i, const float* f) { return unpack_soft<true>(i, f); }
// (a slice of at most kSoftShortSteps steps: the CUDA forward with gradients of every preset, walk_cuda.cu)
TAO_FN SoftAccumulator<true, false, kSoftShortSteps> unpack_soft_gradients_short(const int64_t* i, const float* f) {
  return unpack_soft<true, false, kSoftShortSteps>(i, f);
}

// unpack_glsl's settings and then ints: straight_through, whether the thickness has a growth; floats: tau
// (soft_glsl.h's GlslSoftAccumulator; Union: its forward's SoftAccumulator<false>, or its backward's with each step
// kept, whose thickness is the shader's)
template <class Union> TAO_FN GlslSoftAccumulator<Union> unpack_soft_glsl(const int64_t* i, const float* f) {
  GlslSoftAccumulator<Union> acc;
  acc.shader = unpack_glsl(i, f);
  acc.soft.walk = unpack_walk(i, f);
  acc.soft.rounding = acc.shader.rounding, acc.soft.angles = SectorAngles::plane, acc.soft.epsilon = 0.0f;
  acc.soft.straight_through = i[kAccInts + 4] != 0, acc.soft.tau = f[kAccFloats + 3];
  acc.soft.thickness = acc.shader.thickness, acc.soft.grows = i[kAccInts + 5] != 0;
  acc.soft.cosine = acc.soft.bent = acc.soft.indirect = false;
  soft_window(acc.soft);
  return acc;
}
TAO_FN GlslSoftAccumulator<SoftAccumulator<false>> unpack_soft_glsl_forward(const int64_t* i, const float* f) {
  return unpack_soft_glsl<SoftAccumulator<false>>(i, f);
}

// floats: fade_distance (clamped to 1e-30), flat_surface_bias, flat_softness; ints: accurate_angle
TAO_FN WedgeAccumulator unpack_wedge(const int64_t* i, const float* f) {
  i += kAccInts, f += kAccFloats;
  return WedgeAccumulator{f[0], f[1], f[2], i[0] != 0};
}

// The floats of the walk's table (after the accumulator's): a sample set's angle and length per slice
// (Steps::wedge, where ints[13] says it has one), the pixel offsets per slice and step (Steps::pixels), the
// kernel points per step (Steps::hemisphere)
TAO_FN int64_t table_floats(const int64_t* i) {
  if (i[3] == int64_t(Steps::pixels)) return 2 * i[0] * i[1];
  if (i[3] == int64_t(Steps::hemisphere)) return 3 * i[1];
  return i[3] == int64_t(Steps::wedge) && i[13] > 0 ? 2 * i[0] : 0;
}

// floats: distance_bias
TAO_FN PSSAOAccumulator unpack_pssao(const int64_t*, const float* f) { return PSSAOAccumulator{f[kAccFloats]}; }

// floats: bias, softness; the radius is the walk's, the kernel's size its steps
TAO_FN HemisphereAccumulator unpack_hemisphere(const int64_t* i, const float* f) {
  return HemisphereAccumulator{f[0], f[kAccFloats], f[kAccFloats + 1], i[1]};
}

// A batch of B images channel-last (walk.h's Image per image; light, cells and backface may be null)
struct Frame {
  const float *positions, *normals, *inverse, *depth, *intrinsics, *light, *cells, *backface;
  const bool* valid;
  int64_t B, H, W;
  const float* texels = nullptr;  // (B, H, W, 1 or 2), or null: Image's (frame_cpu.h's fetch_texels)
  bool texels_layer = false, cells_in_sign = false;

  TAO_FN Image image(int64_t b) const {
    const int64_t plane = H * W;
    const float* K = intrinsics + 4 * b;
    return Image{H, W, K[0], K[1], K[2], K[3], positions + 3 * b * plane, normals + 3 * b * plane, inverse + b * plane,
                 depth + b * plane, light ? light + 3 * b * plane : nullptr, valid + b * plane,
                 cells ? cells + b * plane : nullptr, backface ? backface + b * plane : nullptr,
                 texels ? texels + (texels_layer ? 2 : 1) * b * plane : nullptr, texels_layer, cells_in_sign};
  }
};

// Pixel p (of B H W, row-major) walked alone, its channels written to out (B, C, H, W)
template <class Acc> TAO_FN void walk_pixel(const WalkSettings& cfg, const Acc& acc, const Frame& fr, float* out, int64_t p) {
  const int64_t plane = fr.H * fr.W, b = p / plane, row = (p % plane) / fr.W, u = p % fr.W;
  float values[8];
  walk_block(cfg, fr.image(b), acc, row, u, 1, values);
  const int C = acc.channels();
  for (int c = 0; c < C; ++c) out[((b * C + c) * fr.H + row) * fr.W + u] = values[c];
}

}  // namespace tao
