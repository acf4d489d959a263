// The hard visibility-bitmask accumulator of torch_ao.BitmaskAO's "default" and "hdrp" variants
// (methods/bitmask.py DefaultAccumulator and HDRPAccumulator, methods/bitmask_common.py's SectorAccumulator) for
// walk.h: 32 sectors per slice, each sample's occluded interval [front, back] (the sector rule of
// torch_ao/sectors/rule.py), with uniform or cosine sector weights, and optionally the indirect light
// of the newly occluded sectors and the bent normal of the visible ones.
#pragma once

#include "walk.h"

namespace tao {

constexpr int kSectors = 32;

// cos and sin of pi k / 16, k = 0..32: the doubled sector edges (cosine weights)
TAO_CONST float kEdgeCos[33] = {1.0f, 0.98078528f, 0.923879533f, 0.831469612f, 0.707106781f, 0.555570233f, 0.382683432f, 0.195090322f, 6.123234e-17f, -0.195090322f, -0.382683432f, -0.555570233f, -0.707106781f, -0.831469612f, -0.923879533f, -0.98078528f, -1.0f, -0.98078528f, -0.923879533f, -0.831469612f, -0.707106781f, -0.555570233f, -0.382683432f, -0.195090322f, -1.8369702e-16f, 0.195090322f, 0.382683432f, 0.555570233f, 0.707106781f, 0.831469612f, 0.923879533f, 0.98078528f, 1.0f};
TAO_CONST float kEdgeSin[33] = {0.0f, 0.195090322f, 0.382683432f, 0.555570233f, 0.707106781f, 0.831469612f, 0.923879533f, 0.98078528f, 1.0f, 0.98078528f, 0.923879533f, 0.831469612f, 0.707106781f, 0.555570233f, 0.382683432f, 0.195090322f, 1.2246468e-16f, -0.195090322f, -0.382683432f, -0.555570233f, -0.707106781f, -0.831469612f, -0.923879533f, -0.98078528f, -1.0f, -0.98078528f, -0.923879533f, -0.831469612f, -0.707106781f, -0.555570233f, -0.382683432f, -0.195090322f, -2.4492936e-16f};
// cos and sin of pi (k + 1/2) / 32, k = 0..31: the sector centres from the hemisphere's edge (bent normals)
TAO_CONST float kCentreCos[32] = {0.998795456f, 0.98917651f, 0.970031253f, 0.941544065f, 0.903989293f, 0.85772861f, 0.803207531f, 0.740951125f, 0.671558955f, 0.595699304f, 0.514102744f, 0.427555093f, 0.336889853f, 0.24298018f, 0.146730474f, 0.0490676743f, -0.0490676743f, -0.146730474f, -0.24298018f, -0.336889853f, -0.427555093f, -0.514102744f, -0.595699304f, -0.671558955f, -0.740951125f, -0.803207531f, -0.85772861f, -0.903989293f, -0.941544065f, -0.970031253f, -0.98917651f, -0.998795456f};
TAO_CONST float kCentreSin[32] = {0.0490676743f, 0.146730474f, 0.24298018f, 0.336889853f, 0.427555093f, 0.514102744f, 0.595699304f, 0.671558955f, 0.740951125f, 0.803207531f, 0.85772861f, 0.903989293f, 0.941544065f, 0.970031253f, 0.98917651f, 0.998795456f, 0.998795456f, 0.98917651f, 0.970031253f, 0.941544065f, 0.903989293f, 0.85772861f, 0.803207531f, 0.740951125f, 0.671558955f, 0.595699304f, 0.514102744f, 0.427555093f, 0.336889853f, 0.24298018f, 0.146730474f, 0.0490676743f};

// sectors.hard_mask: bits [floor(s), floor(s) + count) of 32 (bits past 31 are shifted out), count the
// interval's width w rounded (0 ceil, 1 round half to even, 2 floor), both clamped to [0, 32]
template <class F>
TAO_FN typename LaneTraits<F>::I sector_bits(const F& s, const F& w, int64_t rounding) {
  using I = typename LaneTraits<F>::I;
  const F sectors = F(float(kSectors));
  const F count = rounding == 0 ? ceil(w) : rounding == 1 ? rint(w) : floor(w);
  const I k0 = to_int(clamp(floor(s), F(0.0f), sectors));
  const I k1 = imin(k0 + to_int(clamp(count, F(0.0f), sectors)), I(kSectors));
  return low_bits(k1) & bnot(low_bits(k0));
}

// cosine_sector_weights: each sector's share |n_p| int cos(theta - gamma) |sin theta| over it, as
// H(e_k+1) - H(e_k), H(t) = sign(t) (G(t) - G(0)), G(t) = -cos(2t - gamma) / 4 + t sin(gamma) / 2
// (ops.arc_measure), edges e_k = gamma - pi/2 + pi k / 32: cos(2 e_k - gamma) = -cos(gamma + pi k / 16)
// (of a slice's angle gamma with its cos and sin, and |n_p|: length)
template <class F> struct FrameAngle { F gamma, cos_gamma, sin_gamma; };
template <class F, class Weights>
TAO_FN void cosine_sector_weights(const FrameAngle<F>& fa, const F& length, Weights& omega) {
  const F cg = fa.cos_gamma, sg = fa.sin_gamma;
  const F G0 = neg(cg) / F(4.0f);
  F H_prev = F(0.0f);
  for (int k = 0; k <= kSectors; ++k) {
    const F edge = fa.gamma - F(kHalfPi) + F(kPi * float(k) / float(kSectors));
    const F G = (cg * F(kEdgeCos[k]) - sg * F(kEdgeSin[k])) / F(4.0f) + edge * sg / F(2.0f);
    const F H = sign(edge) * (G - G0);
    if (k > 0) omega[k - 1] = clamp_min(H - H_prev, F(0.0f)) * length;
    H_prev = H;
  }
}
template <class F, class Weights> TAO_FN void cosine_sector_weights(const Slice<F>& sl, Weights& omega) {
  cosine_sector_weights(FrameAngle<F>{sl.gamma, sl.cos_gamma, sl.sin_gamma}, sl.length, omega);
}

// The thickness at a sample (thickness.ThicknessLayer): t = scale * value + offset, the value by `read`
enum class ThicknessRead : int64_t {
  constant = 0,   // none: t = offset
  layer = 1,      // the layer image read as depth is (Sample.gather): back-face, map, the net's map
  first_tap = 2,  // the layer at the footprint's first tap (an integer buffer's read: a per-object table)
  depth = 3,      // the sample's own depth (LinearThickness)
};

struct ThicknessModel {
  float offset;  // world units
  float scale;   // unitless (the layer's) or per world unit (the depth's)
  ThicknessRead read;
  float growth = 0.0f;  // per world unit: t times 1 + growth |delta| (Thickness.value; the hard kernels')

  TAO_FN bool reads_layer() const { return read == ThicknessRead::layer || read == ThicknessRead::first_tap; }
  // what scale multiplies at the sample (0 for a constant)
  template <class F> TAO_FN F value(const Pixels<F>& px, const Sample<F>& smp) const {
    switch (read) {
      case ThicknessRead::layer:
        if constexpr (!ValueOf<F>::dual) {  // (dual lanes read the taps again: their weights move)
          if (smp.has_layer) return smp.layer;
        }
        return smp.gather(smp.image->backface, 0, 1);
      case ThicknessRead::first_tap: return gather(smp.image->backface, smp.index[0]);
      case ThicknessRead::depth: return neg(smp.delta[2] + px.P[2]);
      default: return F(0.0f);
    }
  }
  // the thickness before growth: a sample's on the pixel's own texel (|delta| = 0 there; delta is a stand-in)
  template <class F> TAO_FN F ungrown(const Pixels<F>& px, const Sample<F>& smp) const {
    return read == ThicknessRead::constant ? F(offset) : F(scale) * value(px, smp) + F(offset);
  }
  template <class F> TAO_FN F at(const Pixels<F>& px, const Sample<F>& smp) const {
    const F t = ungrown(px, smp);
    F length;
    return growth != 0.0f ? t * growth_factor(smp.delta, length) : t;
  }
  // the growth's factor 1 + growth |delta| at a sample's delta, |delta| into length
  template <class F> TAO_FN F growth_factor(const F* delta, F& length) const {
    length = norm3(delta);
    return F(1.0f) + F(growth) * length;
  }
  // d t along a motion that moves delta by d_delta and the base (scale value + offset) by d_base, t = base factor
  // (out of line: the kernels call it only with a growth)
  template <class F> TAO_COLD F grown_motion(const F& d_base, const F* delta, const F* d_delta, const F& t) const {
    F length;
    const F factor = growth_factor(delta, length);
    return d_base * factor + (t / factor) * F(growth) * dot3(delta, d_delta) / clamp_min(length, F(1e-30f));
  }
  // d value as the sample's fetch moves by (dsu, dsv) pixels and its position by d_pos: the layer's bilinear
  // read at the moving taps (Sample.gather), the sample's depth; a first tap's read is piecewise constant
  template <class F>
  TAO_FN F motion(const Sample<F>& smp, const F* d_pos, const F& dsu, const F& dsv) const {
    if (read == ThicknessRead::depth) return neg(d_pos[2]);
    F d_su, d_sv;
    layer_slope(smp, d_su, d_sv);
    return d_su * dsu + d_sv * dsv;
  }
  // the layer's part of motion: d value / d su and d sv as the taps' weights move (0 unless read == layer)
  template <class F> TAO_FN void layer_slope(const Sample<F>& smp, F& d_su, F& d_sv) const {
    if (read == ThicknessRead::layer) {
      smp.gather_slope(smp.image->backface, 0, 1, d_su, d_sv);
    } else {
      d_su = d_sv = F(0.0f);
    }
  }
};

// The hemisphere's edge on side -1 as a fraction of the half circle from the view vector's side: (pi/2 - gamma) / pi
// (the sector rule's shift: a sample's angle from the view vector, times side / pi, plus this)
template <class F> TAO_FN F edge_shift(const Slice<F>& sl) { return (F(kHalfPi) - sl.gamma) / F(kPi); }

// Sample.cos_view: the shaders' horizon cosine (3D, not projected) of a sample at delta, c = dot(normalize(d), V),
// d = delta - offset V, with root = sqrt(1 - |c|) for fast_acos_of_root taken as |d x V| / sqrt(|d| (|d| + |d . V|))
// (V a unit vector): as |c| -> 1, 1 - |c| would cancel in float32 (and acos' slope there is unbounded), where the
// cross product keeps its relative precision. d, |d| and d x V are kept for sample_angles_adjoint.
template <class F> struct ViewCosine {
  F d[3], length, normal[3], c, root;
  TAO_FN ViewCosine(const F* delta, const F* V, const F& offset) {
    for (int k = 0; k < 3; ++k) d[k] = delta[k] - offset * V[k];
    length = clamp_min(norm3(d), F(1e-30f));
    const F along = dot3(d, V);
    c = along / length;
    cross(d, V, normal);
    root = norm3(normal) / sqrt(length * (length + abs(along)));
  }
};

// HDRP's slice angle -sign(s) fast_acos(c) of a slice whose projected normal makes cosine c and sine s with V
// (HDRPAccumulator.slice_frame), in any lane type. fast_acos' sqrt(1 - |c|) is taken as |s| / sqrt(1 + |c|): where
// the normal nearly faces V, 1 - |c| would cancel in float32 (the angle's slope is unbounded in c there, not in the
// slice's own angle). Its derivative is the tensor walk's (safe_fast_acos in float64): none where 1 - |c| < 1e-6.
template <class F> TAO_FN F hdrp_slice_angle(const F& c, const F& s) {
  const F ac = abs(c), as = abs(s);
  const F gamma = neg(sign(s)) * fast_acos_of_root(c, as / sqrt(F(1.0f) + ac));
  const auto sloped = as * as >= F(1e-6f) * (F(1.0f) + ac);  // 1 - |c| = s^2 / (1 + |c|)
  return select(sloped, gamma, F(value(gamma)));
}

// Which published rule measures a sample's angles (methods/bitmask.py's accumulators): variant "default"'s exact
// in-plane atan2 from V toward +T, or "hdrp"'s 3D cosines through fast_acos, from V toward -T
enum class SectorAngles : int64_t { plane = 0, hdrp = 1 };

// The walk's slice in the frame the variant's angles are measured in (SectorAccumulator.slice_frame): as walked,
// or HDRP's gamma = -sign(n_p . T) fast_acos(cos_n) from V toward the tangent -T (HDRPAccumulator.slice_frame);
// frame_angle: its angle alone
template <class F> TAO_FN FrameAngle<F> frame_angle(SectorAngles angles, const Slice<F>& walked) {
  if (angles != SectorAngles::hdrp) return FrameAngle<F>{walked.gamma, walked.cos_gamma, walked.sin_gamma};
  const F gamma = hdrp_slice_angle(walked.cos_gamma, walked.sin_gamma);
  return FrameAngle<F>{gamma, cos(gamma), sin(gamma)};
}
// frame_tangent: a component of the frame's tangent, of the walked slice's
template <class F> TAO_FN F frame_tangent(SectorAngles angles, const F& walked) {
  return angles == SectorAngles::hdrp ? neg(walked) : walked;
}
template <class F> TAO_FN Slice<F> slice_frame(SectorAngles angles, const Slice<F>& walked) {
  if (angles != SectorAngles::hdrp) return walked;
  Slice<F> sl = walked;
  const FrameAngle<F> fa = frame_angle(angles, walked);
  sl.gamma = fa.gamma, sl.cos_gamma = fa.cos_gamma, sl.sin_gamma = fa.sin_gamma;
  for (int c = 0; c < 3; ++c) sl.T[c] = frame_tangent(angles, walked.T[c]);
  return sl;
}

// The side of the frame's tangent a sample on the walk's side lies toward (HDRP's tangent is -T: its yx swap)
TAO_FN int sector_turn(SectorAngles angles, int side) { return angles == SectorAngles::hdrp ? -side : side; }

// The sector rule's angles of a sample at delta with thickness t on the walk's side: its front (delta) and back
// (delta - t V) seen from the pixel, from V toward the frame's tangent on sector_turn's side (T: the walked slice's;
// pixel_z: the pixel's view-space z, slice_coordinates')
template <class F>
TAO_HOT void sample_angles(SectorAngles angles, int side, const F* delta, const F* V, const F* T, const F& pixel_z,
                          const F& t, F& front, F& back) {
  if (angles == SectorAngles::hdrp) {
    const ViewCosine<F> to_front(delta, V, F(0.0f)), to_back(delta, V, t);
    front = fast_acos_of_root(to_front.c, to_front.root);
    back = fast_acos_of_root(to_back.c, to_back.root);
  } else {
    F along_view, along_tangent;
    slice_coordinates(side, delta, V, T, pixel_z, along_view, along_tangent);
    front = atan2(along_tangent, along_view);
    back = atan2(along_tangent, along_view - t);
  }
}

// The interval (start s, width w) in sector units between a sample's front and back positions (fractions of the
// hemisphere from its edge: the angles times turn / pi plus the edge's shift), each clamped to it
template <class F>
TAO_FN void sample_interval(int turn, const F& front, const F& back, float epsilon, F& start, F& width) {
  const F f = clamp(front, F(0.0f), F(1.0f)), b = clamp(back, F(0.0f), F(1.0f));
  const F lo = turn > 0 ? f : b, hi = turn > 0 ? b : f;
  start = lo * F(float(kSectors));
  width = (hi - lo) * F(float(kSectors));
  if (epsilon > 0) width = width - F(epsilon);
}

// The occluder's segment from its front point to its back point (thickness t along the view vector, or along the
// sample's own camera ray: intervals.back_point) in the slice's half plane: seg = (front . V, side front . T,
// back . V, side back . T), of a sample at delta from a pixel |P| = pixel_distance from the camera at view-space z
// pixel_z (G: any lane type; its tangents follow every input)
template <class G>
TAO_HOT void segment_of(bool along_ray, int side, const G* delta, const G* V, const G* T, const G& pixel_distance,
                        const G& pixel_z, const G& t, G* seg) {
  G fv, ft;
  slice_coordinates(side, delta, V, T, pixel_z, fv, ft);
  seg[0] = fv, seg[1] = ft;
  if (along_ray) {  // B = F (1 + k), k = t / depth_F: B_view = fv + k (fv - |P|), B_tangent = ft (1 + k)
    const G k = t / clamp_min(neg(delta[2] + pixel_z), G(1e-30f));
    seg[2] = fv + k * (fv - pixel_distance), seg[3] = ft * (G(1.0f) + k);
  } else {
    seg[2] = fv - t, seg[3] = ft;
  }
}
// segment_of the walk's pixel and slice (their frame without tangents: G's follow delta and t)
template <class F, class G>
TAO_HOT void occluder_segment(bool along_ray, int side, const Pixels<F>& px, const Slice<F>& sl, const G* delta,
                              const G& t, G* seg) {
  const G V[3] = {G(px.V[0]), G(px.V[1]), G(px.V[2])}, T[3] = {G(sl.T[0]), G(sl.T[1]), G(sl.T[2])};
  segment_of(along_ray, side, delta, V, T, G(px.distance), G(px.P[2]), t, seg);
}

// The part of segment seg inside the sphere of the radius around the pixel, in place (intervals.clip_to_sphere;
// live loses the segments that miss it)
template <class F, class G> TAO_HOT void clip_segment(G* seg, const G& radius, typename LaneTraits<F>::M& live) {
  const G fv = seg[0], ft = seg[1], bv = seg[2], bt = seg[3];
  // the part of F -> B inside |x| <= R: a u^2 + 2 b u + c <= 0, u in [0, 1]
  const G ev = bv - fv, et = bt - ft;
  const G a = ev * ev + et * et, b = fv * ev + ft * et, c = fv * fv + ft * ft - radius * radius;
  const G disc = b * b - a * c;
  const auto degenerate = a <= G(1e-30f) * clamp_min(fv * fv + ft * ft, G(1e-30f));  // a point occluder
  const auto hit = land(disc > G(0.0f), lnot(degenerate));
  const G safe_a = select(hit, a, G(1.0f)), root = sqrt(select(hit, disc, G(1.0f)));
  const G u0 = select(hit, clamp((neg(b) - root) / safe_a, G(0.0f), G(1.0f)), G(0.0f));
  const G u1 = select(hit, clamp((neg(b) + root) / safe_a, G(0.0f), G(1.0f)), G(1.0f));
  live = land(live, select(degenerate, c <= G(0.0f), land(hit, u1 > u0)));
  seg[0] = fv + u0 * ev, seg[1] = ft + u0 * et, seg[2] = fv + u1 * ev, seg[3] = ft + u1 * et;
}

// The angles from V of a segment's ends seen from the pixel, of its part inside the radius' sphere where clip
// (clip_segment, in place)
template <class F, class G>
TAO_HOT void segment_end_angles(bool clip, G* seg, const G& radius, typename LaneTraits<F>::M& live, G& front,
                                G& back) {
  if (clip) clip_segment<F>(seg, radius, live);
  front = atan2(seg[1], seg[0]), back = atan2(seg[3], seg[2]);
}

// A segment as an interval of the hemisphere (shift: the slice's edge_shift), its part inside the radius' sphere
// where clip (clip_segment): start (sector units, the lower end clamped to the hemisphere) and width (sector units,
// epsilon narrower; <= 0: empty), DefaultAccumulator.interval's
template <class F, class G>
TAO_HOT void segment_span(bool clip, float epsilon, int side, const G* seg, const F& shift, const G& radius,
                          typename LaneTraits<F>::M& live, G& start, G& width) {
  G part[4] = {seg[0], seg[1], seg[2], seg[3]}, front_angle, back_angle;
  segment_end_angles<F>(clip, part, radius, live, front_angle, back_angle);
  const F scale = F(float(side) / kPi);
  const G front = clamp(fma(front_angle, scale, shift), G(0.0f), G(1.0f));
  const G back = clamp(fma(back_angle, scale, shift), G(0.0f), G(1.0f));
  const G lo = side > 0 ? front : back, hi = side > 0 ? back : front;
  width = (hi - lo) * G(float(kSectors));
  if (epsilon > 0) width = width - G(epsilon);
  start = lo * G(float(kSectors));
}

// The soft union's angles of a sample with the exact variant's segment geometry (a back point along its camera ray
// where along_ray, the segment clipped to the radius' sphere where clip: live loses the segments that miss it): its
// front and back ends seen from the pixel, as sample_angles' plane angles
template <class F>
TAO_HOT void segment_angles(bool along_ray, bool clip, int side, const Pixels<F>& px, const Slice<F>& sl,
                            const F* delta, const F& t, const F& radius, typename LaneTraits<F>::M& live, F& front,
                            F& back) {
  F seg[4];
  occluder_segment(along_ray, side, px, sl, delta, t, seg);
  segment_end_angles<F>(clip, seg, radius, live, front, back);
}

// d fast_acos(x) / d x (given root = sqrt(1 - |x|)) as the tensor walk takes it (safe_fast_acos in float64): none
// where 1 - |x| < 1e-6
template <class F> TAO_FN F fast_acos_slope(const F& x, const F& root) {
  const F ax = abs(x), safe = clamp_min(root, F(1e-3f));
  const F slope = F(-0.156583f) * safe - (F(-0.156583f) * ax + F(kHalfPi)) / (F(2.0f) * safe);
  return select(root * root >= F(1e-6f), slope, F(0.0f));
}

// sample_angles' adjoint: of L with d L / d front = g_front and d L / d back = g_back (the angles), d L / d delta, V
// and T added to g_delta, g_V and g_T, d L / d t returned (HDRP's angles: safe_fast_acos' slope, none where
// 1 - |c| < 1e-6)
template <class F>
TAO_FN F sample_angles_adjoint(SectorAngles angles, int side, const F* delta, const F* V, const F* T, const F& pixel_z,
                               const F& t, const F& g_front, const F& g_back, F* g_delta, F* g_V, F* g_T) {
  if (angles == SectorAngles::hdrp) {
    // c = d . V / |d|, d = delta - o V: dc/d delta = q = (V - c d / |d|) / |d| = ((d x V) x d) / |d|^3 (without
    // cancellation as |c| -> 1), dc/dV = d / |d| - o q, dc/do = -q . V
    const auto add = [&](const F& o, const F& g) {
      const ViewCosine<F> view(delta, V, o);
      F q[3];
      const F inv = F(1.0f) / view.length, g_c = g * fast_acos_slope(view.c, view.root);
      cross(view.normal, view.d, q);
      for (int k = 0; k < 3; ++k) {
        q[k] = q[k] * inv * inv * inv * g_c;  // (left to right: 0 where d is)
        g_delta[k] = g_delta[k] + q[k];
        g_V[k] = g_V[k] + g_c * view.d[k] * inv - o * q[k];
      }
      return neg(dot3(q, V));
    };
    add(F(0.0f), g_front);
    return add(t, g_back);
  }
  // the front's atan2 of (delta . V, side delta . T), the back's of (delta . V - t, side delta . T)
  F along_view, along_tangent, front_view, front_tangent, back_view, back_tangent;
  slice_coordinates(side, delta, V, T, pixel_z, along_view, along_tangent);
  slice_angle_slopes(side, along_view, along_tangent, front_view, front_tangent);
  slice_angle_slopes(side, along_view - t, along_tangent, back_view, back_tangent);
  const F g_view = g_front * front_view + g_back * back_view;
  const F g_tangent = g_front * front_tangent + g_back * back_tangent;
  for (int k = 0; k < 3; ++k) {
    g_delta[k] = g_delta[k] + g_view * V[k] + g_tangent * T[k];
    g_V[k] = g_V[k] + g_view * delta[k];
    g_T[k] = g_T[k] + g_tangent * delta[k];
  }
  return neg(g_back * back_view);  // (d back / d t = -d back / d its along_view)
}

// Sector k's centre phi_k = gamma - pi/2 + c_k (c_k = pi (k + 1/2) / 32) in a slice's (V, T) frame, of its
// gamma's cos and sin: cos phi_k = sin(gamma + c_k), sin phi_k = -cos(gamma + c_k)
template <class G> TAO_HOT void sector_centre(int k, const G& cos_gamma, const G& sin_gamma, G& along_v, G& along_t) {
  along_v = sin_gamma * G(kCentreCos[k]) + cos_gamma * G(kCentreSin[k]);
  along_t = sin_gamma * G(kCentreSin[k]) - cos_gamma * G(kCentreCos[k]);
}

// A slice's bent-normal sum in its (V, T) frame: sum_k wv(k) (cos phi_k, sin phi_k), wv(k) the visible share of
// sector k times its weight (SectorAccumulator.end_slice)
template <class G, class Weight>
TAO_FN void bent_axes(const Weight& wv, const G& cos_gamma, const G& sin_gamma, G& along_v, G& along_t) {
  along_v = G(0.0f), along_t = G(0.0f);
  for (int k = 0; k < kSectors; ++k) {
    G v, t;
    sector_centre(k, cos_gamma, sin_gamma, v, t);
    const G w = wv(k);
    along_v = along_v + w * v;
    along_t = along_t + w * t;
  }
}

// How much of its light a sample at offset delta sends the pixel (SectorAccumulator.step): how much its surface
// (sender_n, its normal) faces the pixel and, with uniform sectors (not cosine), how much the pixel's normal N faces
// it; 0 where not valid
template <class F, class M>
TAO_FN F light_factor(const F* delta, const F* sender_n, const F* N, const M& valid, bool cosine) {
  const F distance = clamp_min(norm3(delta), F(1e-30f));
  F ldir[3], away[3];
  for (int c = 0; c < 3; ++c) {
    ldir[c] = delta[c] / distance;
    away[c] = neg(ldir[c]);
  }
  F factor = select(valid, clamp(dot3(sender_n, away), F(0.0f), F(1.0f)), F(0.0f));
  if (!cosine) factor = factor * clamp(dot3(N, ldir), F(0.0f), F(1.0f));
  return factor;
}

struct BitmaskAccumulator {
  int64_t slices;
  ThicknessModel thickness;  // world units along the view ray
  float epsilon;    // sector_epsilon: sectors taken off each interval's width
  int64_t rounding;
  bool cosine, indirect, bent;
  SectorAngles angles;
  // the "exact" variant's segment geometry (plane angles only, as DefaultAccumulator: HDRP's rule has none): the
  // back point along the sample's camera ray, the segment clipped to the sphere of this radius (world units)
  bool along_ray = false, clip = false;
  float radius = 0.0f;
  // its sums weighed by Slice::weight: its walk may draw the slices by the projected normal's density (walked_slice;
  // the CPU's: kSectorsWeighSlices)
  static constexpr bool kWeighsSlices = kSectorsWeighSlices;

  template <class F> struct State {
    typename LaneTraits<F>::I occ;
    F shift;             // (pi/2 - gamma) / pi: the hemisphere's edge in sector units / 32
    F omega[kSectors];   // the sectors' weights (cosine or bent normals)
    F light[3];          // the light the slice's newly occluded sectors send
  };
  template <class F> struct Sums {
    F visible = F(0.0f), num = F(0.0f), den = F(0.0f);  // uniform: visible sectors; cosine: weighted
    F light[3] = {F(0.0f), F(0.0f), F(0.0f)}, bent[3] = {F(0.0f), F(0.0f), F(0.0f)};
  };
  TAO_FN int channels() const { return 1 + (indirect ? 3 : 0) + (bent ? 3 : 0); }
  TAO_FN bool weighted() const { return cosine || bent; }

  // the walk's slice in the frame the variant's angles are measured in (slice_frame)
  template <class F> TAO_FN Slice<F> frame(const Slice<F>& walked) const { return slice_frame(angles, walked); }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>& walked) const {
    const Slice<F> sl = frame(walked);
    State<F> st;
    st.occ = typename LaneTraits<F>::I(0);
    st.shift = edge_shift(sl);
    for (int c = 0; c < 3; ++c) st.light[c] = F(0.0f);
    if (cosine) {
      cosine_sector_weights(sl, st.omega);
    } else if (bent) {
      for (int k = 0; k < kSectors; ++k) st.omega[k] = F(1.0f / kSectors);
    }
    return st;
  }

  template <class F>
  TAO_HOT void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    using I = typename LaneTraits<F>::I;
    // the sector rule: the sample's front (delta) and back point seen from the pixel, as fractions of the
    // hemisphere from its edge on the frame's side -1
    const F t = thickness.at(px, smp);
    F start, width;
    if (angles == SectorAngles::plane) {  // (DefaultAccumulator.interval: an invalid sample's is empty)
      F seg[4];
      auto live = smp.valid;
      occluder_segment(along_ray, side, px, sl, smp.delta, t, seg);
      segment_span(clip, epsilon, side, seg, st.shift, F(radius), live, start, width);
      width = select(live, width, F(-1.0f));
    } else {  // HDRP's 3D cosines, its back point t along V
      const int turn = sector_turn(angles, side);
      const F scale = F(float(turn) / kPi);
      F front_angle, back_angle;
      sample_angles(angles, side, smp.delta, px.V, sl.T, px.P[2], t, front_angle, back_angle);
      sample_interval(turn, fma(front_angle, scale, st.shift), fma(back_angle, scale, st.shift), epsilon, start, width);
    }
    const I bits = sector_bits(start, width, rounding);
    if (indirect) {
      // SectorAccumulator.step: the light the sample sends, times the share it newly occludes (only a non-empty
      // interval gathers light; a step that occludes nothing new on any lane sends none, and reads no light)
      const I fresh = bits & bnot(st.occ);
      const auto sends = land(width >= F(0.0f), lnot(ieq(fresh, I(0))));
      if (any(sends)) {
        F sender_n[3], light[3], sent[3];
        for (int c = 0; c < 3; ++c) sender_n[c] = smp.gather(smp.image->normals, c), light[c] = smp.gather(smp.image->light, c);
        light_sent(px, smp, newly_occluded(st, fresh), sender_n, light, sent);
        for (int c = 0; c < 3; ++c) st.light[c] = st.light[c] + select(sends, sent[c], F(0.0f));
      }
    }
    st.occ = st.occ | bits;
  }

  // The share of the hemisphere the sectors `fresh` cover (the sectors' weights, or their count / 32)
  template <class F>
  TAO_FN F newly_occluded(const State<F>& st, const typename LaneTraits<F>::I& fresh) const {
    if (!cosine) return to_float(popcount(fresh)) * F(1.0f / kSectors);
    F newly = F(0.0f);
    for (int k = 0; k < kSectors; ++k) newly = newly + bit(fresh, k) * st.omega[k];
    return newly;
  }

  // The light a sample sends: the share it newly occludes (newly), times its light, times light_factor; 0 from
  // an invalid sample
  template <class F>
  TAO_FN void light_sent(const Pixels<F>& px, const Sample<F>& smp, const F& newly, const F* sender_n, const F* light,
                         F* sent) const {
    const F factor = light_factor(smp.delta, sender_n, px.N, smp.valid, cosine);
    for (int c = 0; c < 3; ++c) sent[c] = newly * (light[c] * factor);
  }

  template <class F>
  TAO_FN void end_slice(const State<F>& st, const Pixels<F>& px, const Slice<F>& walked, Sums<F>& sums) const {
    // every sum weighs by the slice's weight (1 but for slices drawn by a density; none where kWeighsSlices is not)
    const auto weigh = [&](const F& x) { return weighed(walked, x); };
    if (!cosine) sums.visible = sums.visible + weigh(to_float(typename LaneTraits<F>::I(kSectors) - popcount(st.occ)));
    if (weighted()) {
      F wv[kSectors];
      for (int k = 0; k < kSectors; ++k) wv[k] = (F(1.0f) - bit(st.occ, k)) * st.omega[k];
      if (cosine)
        for (int k = 0; k < kSectors; ++k) {
          sums.num = sums.num + weigh(wv[k]);
          sums.den = sums.den + weigh(st.omega[k]);
        }
      if (bent) {
        const Slice<F> sl = frame(walked);
        F along_v, along_t;
        bent_axes([&](int k) { return wv[k]; }, sl.cos_gamma, sl.sin_gamma, along_v, along_t);
        along_v = weigh(along_v), along_t = weigh(along_t);
        for (int c = 0; c < 3; ++c) sums.bent[c] = sums.bent[c] + along_v * px.V[c] + along_t * sl.T[c];
      }
    }
    if (indirect)
      for (int c = 0; c < 3; ++c) sums.light[c] = sums.light[c] + weigh(st.light[c]);
  }

  // finish's d indirect light / d a slice's light sum, the same for every slice (den: the sums' den)
  template <class F> TAO_FN F per_light(const F& den) const {
    return F(1.0f) / (cosine ? clamp_min(den, F(1e-30f)) : F(float(slices)));
  }

  // visibility (background 1), the indirect light (background 0), the bent normal (the pixel's normal
  // where the visible sectors' sum is ~0 or on background)
  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    const F den = cosine ? clamp_min(sums.den, F(1e-30f)) : F(float(slices));
    const F vis = cosine ? sums.num / den : (sums.visible * F(1.0f / kSectors)) / den;
    out[0] = select(px.live, vis, F(1.0f));
    int c0 = 1;
    if (indirect) {
      for (int c = 0; c < 3; ++c) out[c0 + c] = select(px.live, sums.light[c] / den, F(0.0f));
      c0 += 3;
    }
    if (bent) {
      const F nb = norm3(sums.bent);
      const auto keep = land(px.live, nb > F(1e-12f));
      const F scale = clamp_min(nb, F(1e-12f));
      for (int c = 0; c < 3; ++c) out[c0 + c] = select(keep, sums.bent[c] / scale, px.N[c]);
    }
  }
};


// H(theta) = int_0^theta cos(t - gamma) |sin t| dt (ops.arc_measure) of the slice's hemisphere from its
// edge at x = 0 to position x (sector units): theta(x) = gamma - pi/2 + pi x / 32 (G: F, or duals over F)
template <class G, class F> TAO_HOT G arc_measure_at(const G& x, const Slice<F>& sl) {
  const G theta = G(sl.gamma) - G(kHalfPi) + x * G(kPi / float(kSectors));
  const G H = neg(cos(G(2.0f) * theta - G(sl.gamma))) / G(4.0f) + theta * G(sl.sin_gamma) / G(2.0f);
  const G H0 = G(neg(sl.cos_gamma) / F(4.0f));
  return sign(theta) * (H - H0);
}

// The "exact" variant's accumulator (methods/bitmask.py DefaultAccumulator with union="exact",
// bitmask_common's end_slice): each sample's occluder segment from its front point to its back point
// (thickness along the view vector, or along its own camera ray: intervals.back_point), clipped to the
// radius' sphere (intervals.clip_to_sphere), as an interval of the hemisphere; a slice's visible share is
// the exact (uniform or cosine) measure of what the union of its intervals leaves (intervals.union_measure).
// interval, union_measure and add_slice take value lanes G = F, or duals over F carrying derivatives
// (exact_soft.h), whose values are the plain lanes'.
constexpr int kMaxIntervals = 64;  // both sides' steps of a slice: steps <= 32

struct ExactAccumulator {
  int64_t slices, steps;
  ThicknessModel thickness;
  float radius;   // world units: the sphere the segments are clipped to
  float epsilon;  // sector_epsilon
  bool cosine, along_ray, clip;
  static constexpr bool kWeighsSlices = kSectorsWeighSlices;  // (add_slice weighs a slice drawn by a density)

  template <class F> struct State {
    F shift;
    LaneArray<F, kMaxIntervals> lo, hi;
    int n;
  };
  template <class F> struct Sums { F num = F(0.0f), den = F(0.0f); };
  TAO_FN int channels() const { return 1; }

  template <class F> TAO_FN State<F> begin_slice(const Pixels<F>&, const Slice<F>& sl) const {
    State<F> st;
    st.shift = edge_shift(sl);
    st.n = 0;
    return st;
  }

  // The interval [lo, hi] of the hemisphere (sector units, clipped to [0, 32]; [0, 0] where empty or not
  // live) that a sample at offset delta from the pixel occludes on side, with thickness t and the sphere's
  // radius (shift: the slice's edge_shift): segment, then segment_interval
  template <class F, class G>
  TAO_HOT void interval(int side, const Pixels<F>& px, const Slice<F>& sl, const F& shift, const G* delta, const G& t,
                       const G& radius, typename LaneTraits<F>::M live, G& lo_out, G& hi_out) const {
    G seg[4];
    segment(side, px, sl, delta, t, seg);
    segment_interval(side, seg, shift, radius, live, lo_out, hi_out);
  }

  // occluder_segment, with this accumulator's direction
  template <class F, class G>
  TAO_HOT void segment(int side, const Pixels<F>& px, const Slice<F>& sl, const G* delta, const G& t, G* seg) const {
    occluder_segment(along_ray, side, px, sl, delta, t, seg);
  }

  // segment's interval (segment_span) as union_measure clips its ends: an empty (or dead) interval is [0, 0]
  template <class F, class G>
  TAO_HOT void segment_interval(int side, const G* seg, const F& shift, const G& radius,
                               typename LaneTraits<F>::M live, G& lo_out, G& hi_out) const {
    G start, width;
    segment_span(clip, epsilon, side, seg, shift, radius, live, start, width);
    const auto open = land(live, width > G(0.0f));
    lo_out = select(open, clamp(start, G(0.0f), G(float(kSectors))), G(0.0f));
    hi_out = select(open, clamp(start + width, G(0.0f), G(float(kSectors))), G(0.0f));
  }

  template <class F>
  TAO_HOT void step(State<F>& st, int side, const Pixels<F>& px, const Slice<F>& sl, const Sample<F>& smp) const {
    interval(side, px, sl, st.shift, smp.delta, thickness.at(px, smp), F(radius), smp.valid, st.lo[st.n], st.hi[st.n]);
    ++st.n;
  }

  // The n intervals [lo, hi] sorted by start, lane by lane: Batcher's odd-even merge sort, a fixed sequence of
  // compare-exchanges for any n (19 for 8 intervals, 63 for 16, where an insertion sort's lanes take all 28 and
  // 120); also(swap, a, b) exchanges what travels with intervals a and b where swap holds
  template <class G, class Also> TAO_FN void sort_by_start(G* lo, G* hi, int n, const Also& also) const {
    for (int p = 1; p < n; p += p)
      for (int k = p; k >= 1; k /= 2)
        for (int j = k % p; j + k < n; j += 2 * k)
          for (int i = 0; i < k && i + j + k < n; ++i) {
            const int a = i + j, b = i + j + k;
            if ((a ^ b) >= 2 * p) continue;  // (a / 2p != b / 2p: 2p is a power of two)
            const auto swap = lo[b] < lo[a];
            const G l = select(swap, lo[b], lo[a]), h = select(swap, hi[b], hi[a]);
            lo[b] = select(swap, lo[a], lo[b]), hi[b] = select(swap, hi[a], hi[b]);
            lo[a] = l, hi[a] = h;
            also(swap, a, b);
          }
  }
  struct Alone {  // (sort_by_start: nothing travels with the intervals)
    template <class M> TAO_FN void operator()(const M&, int, int) const {}
  };

  // What [a, b] (a <= b, sector units) covers of the slice: b - a, or with cosine weights its arc measure
  template <class F, class G> TAO_FN G measure(const G& a, const G& b, const Slice<F>& sl) const {
    return cosine ? (arc_measure_at(b, sl) - arc_measure_at(a, sl)) * G(sl.length) : b - a;
  }

  // The measure of the union of the n intervals [lo, hi] (reordered in place): sorted by start, each interval adds
  // what lies beyond the reach of those before it. An interval empty in every lane (lo = hi: dead, or clamped at an
  // end of the hemisphere) adds nothing and leaves the reach as it is (its tangents are zero but where its start
  // clamps exactly at an end), so it is dropped before the sort, whose cost grows as n log^2 n (on a floor, each
  // sample of the floor is such an interval)
  template <class F, class G> TAO_FN G union_measure(G* lo, G* hi, int n, const Slice<F>& sl) const {
    int kept = 0;
    for (int j = 0; j < n; ++j)
      if (any(hi[j] > lo[j])) lo[kept] = lo[j], hi[kept] = hi[j], ++kept;
    sort_by_start(lo, hi, kept, Alone{});
    G reach = G(0.0f), covered = G(0.0f);
    for (int j = 0; j < kept; ++j) {
      const G a = max(lo[j], reach), b = max(hi[j], reach);
      covered = covered + measure(a, b, sl);
      reach = b;
    }
    return covered;
  }

  // A slice's visible share into num (with cosine weights its whole measure into den) from the covered one, weighed
  // by the slice's Slice::weight
  template <class F, class G> TAO_FN void add_slice(const G& covered, const Slice<F>& sl, G& num, F& den) const {
    if (cosine) {
      const F total = (arc_measure_at(F(float(kSectors)), sl) - arc_measure_at(F(0.0f), sl)) * sl.length;
      num = num + weighed(sl, G(total) - covered);
      den = den + weighed(sl, total);
    } else {
      num = num + weighed(sl, G(1.0f) - covered / G(float(kSectors)));
    }
  }

  template <class F>
  TAO_FN void end_slice(State<F>& st, const Pixels<F>&, const Slice<F>& sl, Sums<F>& sums) const {
    add_slice(union_measure(&st.lo[0], &st.hi[0], st.n, sl), sl, sums.num, sums.den);
  }

  template <class F> TAO_FN void finish(const Sums<F>& sums, const Pixels<F>& px, F* out) const {
    const F vis = cosine ? sums.num / clamp_min(sums.den, F(1e-30f)) : sums.num / F(float(slices));
    out[0] = select(px.live, vis, F(1.0f));
  }
  // finish's d visibility / d a slice's covered measure, the same for every slice (den: the sums' whole measure)
  template <class F> TAO_FN F per_covered(const F& den) const {
    return cosine ? neg(F(1.0f) / clamp_min(den, F(1e-30f))) : F(-1.0f / (float(kSectors) * float(slices)));
  }
};

}  // namespace tao
