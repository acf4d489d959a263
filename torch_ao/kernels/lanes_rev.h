// Reverse-mode lanes over any lane type of lanes_scalar.h / lanes_simd.h: Rev<F> is a value and the index of
// the node that made it on the thread's tape (Tape<F>: per node its value's partial derivatives with respect
// to the node made just before it and to at most two other parent nodes), so the one walk (walk.h) run with
// F = Rev<Vec> (or Rev<float>) records itself, and one sweep back over the tape (Tape::sweep) gives d L / d every
// node for any L seeded on its outputs. A walk's gradient then costs a few times its own arithmetic, whatever the
// number of inputs; forward mode (lanes_dual.h) costs one walk per tangent.
//
// Every operation's value is the value lanes' own (a quotient divides, an fma is fused), so that a replay on the
// tape samples the texels, and drops the samples, that its forward did.
//
// Constants (id < 0) make no node, so what does not depend on a leaf costs nothing; nor does k x + c of a node x
// for constant lanes k, c, or a select between x and a constant: such a value carries x's id and its scale k
// (Rev::scale, by which its adjoint reaches x's; 0 in the lanes where the constant was chosen). The leaves: the pixel's
// own position, normal and depth (seed_pixel: ids kept in Tape::own), the accumulator's settings (seed_setting)
// and the camera's intrinsics (seed_camera; both Tape::parameter), and whatever the caller makes with
// Tape::leaf. Derivatives at non-differentiable points are lanes_dual.h's (torch's autograd of the tensor path).
//
// A node's value carries its tape; leaves are made on the thread's (current_tape<F>(): a CPU thread's own, a
// CUDA thread's slot in its block's shared array, one pointer per thread of kTapeThreads), whose arrays are
// the caller's (on CUDA: the thread's local memory).
// A full tape makes no more nodes and says so (Tape::overflow): the caller raises rather than use its sweep.
#pragma once

#include "lanes_scalar.h"
#include "slopes.h"

namespace tao {

template <class F> struct Tape {
  // Per node: its partial derivative with respect to the node made just before it (the sweep carries that
  // adjoint in a register: most nodes take the last one made, and passing it through memory would put a store
  // and its reload on the sweep's chain at every node), then those with respect to its other parents
  static constexpr int kPartials = 3;
  F* partial;        // [capacity][kPartials]: d node / d (node - 1), d node / d parent[0], parent[1]
  int32_t* parent;   // [capacity][2]: a parent other than the node before (none: -1 on CUDA, else the dump)
  F* adjoint;        // [2 capacity]: d L / d node, after sweep; on the CPU, capacity + node is the node's dump
  int32_t capacity, n = 0;
  int32_t own[7] = {-1, -1, -1, -1, -1, -1, -1};  // the pixel's P (3), N (3), depth (seed_pixel)
  bool overflow = false;

  // the arrays' lengths for cap nodes (F elements of partials and adjoints, int32 of parents)
  static TAO_FN constexpr int32_t partials_size(int32_t cap) { return kPartials * cap; }
  static TAO_FN constexpr int32_t parents_size(int32_t cap) { return 2 * cap; }
#ifdef __CUDACC_RTC__
  static TAO_FN constexpr int32_t adjoints_size(int32_t cap) { return cap; }
#else
  static TAO_FN constexpr int32_t adjoints_size(int32_t cap) { return 2 * cap; }
#endif

  TAO_FN Tape(F* partials, int32_t* parents, F* adjoints, int32_t cap)
      : partial(partials), parent(parents), adjoint(adjoints), capacity(cap) {}

  // a node of value-derivatives pa, pb with respect to a, b (ids, -1: none); -1 when the tape is full
  TAO_HOT int32_t push(int32_t a, const F& pa, int32_t b, const F& pb) {
    const int32_t before = n - 1;
    const bool a_before = a == before && a >= 0, b_before = b == before && b >= 0;
    const F p_before = a_before ? (b_before ? pa + pb : pa) : (b_before ? pb : F(0.0f));
    return node(p_before, a_before ? -1 : a, pa, b_before ? -1 : b, pb);
  }
  // a node of value-derivative p_before with respect to the node made just before it, and pa, pb with respect to
  // a, b (ids, -1: none; neither the node before); -1 when the tape is full
  TAO_HOT int32_t node(const F& p_before, int32_t a, const F& pa, int32_t b, const F& pb) {
    if (n == capacity) {
      overflow = true;
      return -1;
    }
#ifdef __CUDACC_RTC__  // (a warp's threads take the same branches: the sweep skips a missing parent)
    const int32_t none = -1;
#else  // (unary and binary nodes alternate with the code, so a skip would be mispredicted: the node's own dump
       // slot takes a missing parent's update instead, one a node so that no chain of updates runs through it)
    const int32_t none = capacity + n;
#endif
    partial[kPartials * n] = p_before, partial[kPartials * n + 1] = pa, partial[kPartials * n + 2] = pb;
    parent[2 * n] = a >= 0 ? a : none, parent[2 * n + 1] = b >= 0 ? b : none;
    adjoint[n] = F(0.0f);
    return n++;
  }
  TAO_FN int32_t leaf() { return push(-1, F(0.0f), -1, F(0.0f)); }
  TAO_FN void seed(int32_t id, const F& g) {
    if (id >= 0) adjoint[id] = adjoint[id] + g;
  }
  // the adjoints of nodes [stop, n) passed back to their parents, last node first
  TAO_FN void sweep(int32_t stop) {
    F carry(0.0f);  // d L / d node i - 1 by node i
    for (int32_t i = n - 1; i >= stop; --i) {
      const F a = adjoint[i] + carry;
      adjoint[i] = a;  // (a leaf's is read after the sweep)
      carry = a * partial[kPartials * i];
      const int32_t p0 = parent[2 * i], p1 = parent[2 * i + 1];
#ifdef __CUDACC_RTC__
      if (p0 >= 0) adjoint[p0] = adjoint[p0] + a * partial[kPartials * i + 1];
      if (p1 >= 0) adjoint[p1] = adjoint[p1] + a * partial[kPartials * i + 2];
#else
      adjoint[p0] = adjoint[p0] + a * partial[kPartials * i + 1];
      adjoint[p1] = adjoint[p1] + a * partial[kPartials * i + 2];
#endif
    }
    if (stop > 0) adjoint[stop - 1] = adjoint[stop - 1] + carry;
  }
  // the leaf of parameter k (kSetting + 0..2: seed_setting's; kCamera + 0..3: seed_camera's fx, fy, cx, cy), made
  // on first use, again after a cut below it
  TAO_FN int32_t parameter(int k) {
    if (parameter_id[k] < 0) parameter_id[k] = leaf();
    return parameter_id[k];
  }
  // the nodes from `to` on dropped
  TAO_FN void cut(int32_t to) {
    n = to;
    for (int k = 0; k < kParameters; ++k)
      if (parameter_id[k] >= to) parameter_id[k] = -1;
  }
  // d L / d parameter k, by the nodes from `from` on (after sweep)
  TAO_FN F parameter_adjoint(int k, int32_t from) const {
    return parameter_id[k] >= from ? adjoint[parameter_id[k]] : F(0.0f);
  }
  static constexpr int kSetting = 0, kSettings = 3, kCamera = kSetting + kSettings, kParameters = kCamera + 4;
  int32_t parameter_id[kParameters] = {-1, -1, -1, -1, -1, -1, -1};
  bool camera = false;  // whether seed_camera makes leaves (the intrinsics' gradients are asked for)
  void* fetches = nullptr;  // the caller's record of the leaves it makes outside the arithmetic (walk_grad.h)
};

#ifdef __CUDACC_RTC__
constexpr int kTapeThreads = 128;  // launch.py's threads per block
__shared__ void* tao_tape_slots[kTapeThreads];
template <class F> TAO_FN Tape<F>*& current_tape() {
  return reinterpret_cast<Tape<F>*&>(tao_tape_slots[threadIdx.x]);
}
#else
template <class F> struct TapeSlot {
  static inline thread_local Tape<F>* tape = nullptr;
};
template <class F> TAO_FN Tape<F>*& current_tape() { return TapeSlot<F>::tape; }
#endif

template <class F> struct Rev {
  using M = typename LaneTraits<F>::M;
  F v;
  F scale;        // d v / d the value of node id (k for k x + c: such a value of node x makes no node of its own)
  int32_t id;     // < 0: a constant
  Tape<F>* tape;  // the node's (null for a constant): found without the thread's slot

  TAO_HOT Rev() : v(0.0f), scale(1.0f), id(-1), tape(nullptr) {}
  TAO_HOT Rev(const F& x) : v(x), scale(1.0f), id(-1), tape(nullptr) {}  // a constant (float converts through F)
  TAO_HOT Rev(const F& x, int32_t i, Tape<F>* t, const F& s = F(1.0f))
      : v(x), scale(s), id(i), tape(i >= 0 ? t : nullptr) {}
  // value = k x + c for constant lanes k, c: x's node, its scale times k
  static TAO_HOT Rev affine(const F& value, const Rev& x, const F& k) {
    return Rev(value, x.id, x.tape, x.scale * k);
  }

  // value with derivatives a and b with respect to x and y (a constant where neither is a node)
  static TAO_HOT Rev link(const F& value, const Rev& x, const F& a) {
    if (x.id < 0) return Rev(value);
    return Rev(value, x.tape->push(x.id, a * x.scale, -1, F(0.0f)), x.tape);
  }
  static TAO_HOT Rev link(const F& value, const Rev& x, const F& a, const Rev& y, const F& b) {
    if (x.id < 0) return link(value, y, b);
    if (y.id < 0) return link(value, x, a);
    return Rev(value, x.tape->push(x.id, a * x.scale, y.id, b * y.scale), x.tape);
  }

  // a value with derivatives a, b, c with respect to x, y, z: one node where one of them is the last node made
  // (or x is a constant), else two
  static TAO_HOT Rev link(const F& value, const Rev& x, const F& a, const Rev& y, const F& b, const Rev& z,
                                const F& c) {
    if (x.id < 0) return link(value, y, b, z, c);  // (a constant parent: one node of the other two)
    if (y.id < 0) return link(value, x, a, z, c);
    if (z.id < 0) return link(value, x, a, y, b);
    Tape<F>* tape = x.tape;
    const int32_t last = tape->n - 1;
    if (x.id == last) return Rev(value, tape->node(a * x.scale, y.id, b * y.scale, z.id, c * z.scale), tape);
    if (y.id == last) return Rev(value, tape->node(b * y.scale, x.id, a * x.scale, z.id, c * z.scale), tape);
    if (z.id == last) return Rev(value, tape->node(c * z.scale, x.id, a * x.scale, y.id, b * y.scale), tape);
    return link(value, link(value, x, a, y, b), F(1.0f), z, c);
  }

  friend TAO_HOT Rev operator+(const Rev& a, const Rev& b) {
    if (b.id < 0) return affine(a.v + b.v, a, F(1.0f));
    if (a.id < 0) return affine(a.v + b.v, b, F(1.0f));
    return link(a.v + b.v, a, F(1.0f), b, F(1.0f));
  }
  friend TAO_HOT Rev operator-(const Rev& a, const Rev& b) {
    if (b.id < 0) return affine(a.v - b.v, a, F(1.0f));
    if (a.id < 0) return affine(a.v - b.v, b, F(-1.0f));
    return link(a.v - b.v, a, F(1.0f), b, F(-1.0f));
  }
  friend TAO_HOT Rev operator*(const Rev& a, const Rev& b) {
    if (b.id < 0) return affine(a.v * b.v, a, b.v);
    if (a.id < 0) return affine(a.v * b.v, b, a.v);
    return link(a.v * b.v, a, b.v, b, a.v);
  }
  friend TAO_HOT Rev operator/(const Rev& a, const Rev& b) {
    const F inv = F(1.0f) / b.v, q = a.v / b.v;
    if (b.id < 0) return affine(q, a, inv);
    return link(q, a, inv, b, neg(q * inv));
  }
  friend TAO_HOT M operator<(const Rev& a, const Rev& b) { return a.v < b.v; }
  friend TAO_HOT M operator>(const Rev& a, const Rev& b) { return a.v > b.v; }
  friend TAO_HOT M operator<=(const Rev& a, const Rev& b) { return a.v <= b.v; }
  friend TAO_HOT M operator>=(const Rev& a, const Rev& b) { return a.v >= b.v; }
  friend TAO_HOT M operator==(const Rev& a, const Rev& b) { return a.v == b.v; }
};

template <class F> struct LaneTraits<Rev<F>> {
  using M = typename LaneTraits<F>::M;
  using I = typename LaneTraits<F>::I;
  static constexpr int L = LaneTraits<F>::L;
};
template <class F> struct ValueOf<Rev<F>> {
  using type = F;
  static constexpr bool dual = true;
};
template <class F> TAO_FN const F& value(const Rev<F>& x) { return x.v; }

template <class F> TAO_HOT Rev<F> from_lanes(const float* x, const Rev<F>&) { return Rev<F>(from_lanes(x, F(0.0f))); }
template <class F> TAO_HOT Rev<F> select(const typename LaneTraits<F>::M& m, const Rev<F>& yes, const Rev<F>& no) {
  const F v = select(m, yes.v, no.v);
  // (one node, or one and a constant: that node, its scale where it is chosen, 0 where the constant is)
  if (yes.id == no.id) return Rev<F>(v, yes.id, yes.tape, select(m, yes.scale, no.scale));
  if (no.id < 0) return Rev<F>(v, yes.id, yes.tape, select(m, yes.scale, F(0.0f)));
  if (yes.id < 0) return Rev<F>(v, no.id, no.tape, select(m, F(0.0f), no.scale));
  return Rev<F>::link(v, yes, select(m, F(1.0f), F(0.0f)), no, select(m, F(0.0f), F(1.0f)));
}
template <class F> TAO_HOT Rev<F> neg(const Rev<F>& x) { return Rev<F>::affine(neg(x.v), x, F(-1.0f)); }
template <class F> TAO_HOT Rev<F> fma(const Rev<F>& a, const Rev<F>& b, const Rev<F>& c) {
  return Rev<F>::link(fma(a.v, b.v, c.v), a, b.v, b, a.v, c, F(1.0f));
}
// a b + c for a constant b and c, its value fused as the value lanes' fma
template <class F> TAO_HOT Rev<F> fma(const Rev<F>& a, const F& b, const F& c) {
  return Rev<F>::affine(fma(a.v, b, c), a, b);
}
template <class F> TAO_HOT Rev<F> abs(const Rev<F>& x) { return select(x.v < F(0.0f), neg(x), x); }
template <class F> TAO_HOT Rev<F> sqrt(const Rev<F>& x) {
  const F r = sqrt(x.v);
  return Rev<F>::link(r, x, sqrt_slope(r));
}
template <class F> TAO_HOT Rev<F> rsqrt(const Rev<F>& x) {
  const F r = rsqrt(x.v);
  return Rev<F>::link(r, x, rsqrt_slope(r));
}
template <class F> TAO_HOT Rev<F> reciprocal(const Rev<F>& x) {
  const F r = reciprocal(x.v);
  return Rev<F>::link(r, x, reciprocal_slope(r));
}
template <class F> TAO_HOT Rev<F> floor(const Rev<F>& x) { return Rev<F>(floor(x.v)); }
template <class F> TAO_HOT Rev<F> ceil(const Rev<F>& x) { return Rev<F>(ceil(x.v)); }
template <class F> TAO_HOT Rev<F> rint(const Rev<F>& x) { return Rev<F>(rint(x.v)); }
template <class F> TAO_HOT Rev<F> atan2(const Rev<F>& y, const Rev<F>& x) {
  F by_y, by_x;
  atan2_slopes(y.v, x.v, by_y, by_x);
  return Rev<F>::link(atan2(y.v, x.v), y, by_y, x, by_x);
}
template <class F> TAO_HOT Rev<F> cos(const Rev<F>& x) { return Rev<F>::link(cos(x.v), x, neg(sin(x.v))); }
template <class F> TAO_HOT Rev<F> sin(const Rev<F>& x) { return Rev<F>::link(sin(x.v), x, cos(x.v)); }
template <class F> TAO_FN void cos_sin_rounded(const Rev<F>& x, Rev<F>& c, Rev<F>& s) {
  F cv, sv;
  cos_sin_rounded(x.v, cv, sv);
  c = Rev<F>::link(cv, x, neg(sv)), s = Rev<F>::link(sv, x, cv);
}
template <class F> TAO_HOT Rev<F> logistic(const Rev<F>& x) {
  const F s = logistic(x.v);
  return Rev<F>::link(s, x, logistic_slope(s));
}
template <class F> TAO_HOT Rev<F> asin(const Rev<F>& x) { return Rev<F>::link(asin(x.v), x, asin_slope(x.v)); }
template <class F> TAO_HOT Rev<F> acos(const Rev<F>& x) {
  return Rev<F>::link(acos(x.v), x, neg(asin_slope(x.v)));
}
template <class F> TAO_HOT Rev<F> pow(const Rev<F>& x, const Rev<F>& y) {
  return Rev<F>::link(pow(x.v, y.v), x, pow_slope(x.v, y.v));
}
template <class F> TAO_HOT Rev<F> max(const Rev<F>& a, const Rev<F>& b) {
  Rev<F> r = select(b.v > a.v, b, a);
  r.v = max(a.v, b.v);  // NaN-propagating
  return r;
}
template <class F> TAO_HOT Rev<F> min(const Rev<F>& a, const Rev<F>& b) {
  Rev<F> r = select(b.v < a.v, b, a);
  r.v = min(a.v, b.v);
  return r;
}
template <class F> TAO_HOT Rev<F> clamp_min(const Rev<F>& x, const Rev<F>& lo) { return select(x.v < lo.v, lo, x); }
template <class F> TAO_HOT Rev<F> clamp_max(const Rev<F>& x, const Rev<F>& hi) { return select(x.v > hi.v, hi, x); }
template <class F> TAO_HOT Rev<F> clamp(const Rev<F>& x, const Rev<F>& lo, const Rev<F>& hi) {
  return clamp_max(clamp_min(x, lo), hi);
}
template <class F> TAO_FN typename LaneTraits<F>::I to_int(const Rev<F>& x) { return to_int(x.v); }

// walk.h's dot3 and cross in fewer nodes: each product joins the running sum in a node of three parents (the sum
// the node before it)
template <class F> TAO_HOT Rev<F> dot3(const Rev<F>* a, const Rev<F>* b) {
  using R = Rev<F>;
  const R p = R::link(a[0].v * b[0].v, a[0], b[0].v, b[0], a[0].v);
  const R q = R::link(p.v + a[1].v * b[1].v, p, F(1.0f), a[1], b[1].v, b[1], a[1].v);
  return R::link(q.v + a[2].v * b[2].v, q, F(1.0f), a[2], b[2].v, b[2], a[2].v);
}
template <class F> TAO_HOT void cross(const Rev<F>* a, const Rev<F>* b, Rev<F>* out) {
  using R = Rev<F>;
  for (int c = 0; c < 3; ++c) {
    const int i = (c + 1) % 3, j = (c + 2) % 3;  // out_c = a_i b_j - a_j b_i
    const R p = R::link(a[i].v * b[j].v, a[i], b[j].v, b[j], a[i].v);
    out[c] = R::link(p.v - a[j].v * b[i].v, p, F(1.0f), a[j], neg(b[i].v), b[i], neg(a[j].v));
  }
}

// walk.h's norm2 and norm3 in one node (0 derivative at 0, as sqrt's)
template <class F> TAO_HOT Rev<F> norm2(const Rev<F>& x, const Rev<F>& y) {
  const F r = sqrt(x.v * x.v + y.v * y.v), inv = norm_inverse(r);
  return Rev<F>::link(r, x, x.v * inv, y, y.v * inv);
}
template <class F> TAO_HOT Rev<F> norm3(const Rev<F>* a) {
  const F r = sqrt(a[0].v * a[0].v + a[1].v * a[1].v + a[2].v * a[2].v), inv = norm_inverse(r);
  return Rev<F>::link(r, a[0], a[0].v * inv, a[1], a[1].v * inv, a[2], a[2].v * inv);
}

// The walk's seed (walk.h's Pixels): the pixel's position, normal and depth as leaves, their ids in Tape::own
template <class F> TAO_FN void seed_pixel(Rev<F>* P, Rev<F>* Nrm, Rev<F>& depth) {
  Tape<F>* tape = current_tape<F>();
  for (int c = 0; c < 3; ++c) {
    P[c] = Rev<F>(P[c].v, tape->own[c] = tape->leaf(), tape);
    Nrm[c] = Rev<F>(Nrm[c].v, tape->own[3 + c] = tape->leaf(), tape);
  }
  depth = Rev<F>(depth.v, tape->own[6] = tape->leaf(), tape);
}

// an accumulator's differentiable setting k (< Tape::kSettings): its leaf (Tape::parameter(kSetting + k))
template <class F> TAO_HOT Rev<F> seed_setting(const Rev<F>& x, int k = 0) {
  Tape<F>* tape = current_tape<F>();
  return Rev<F>(x.v, tape->parameter(Tape<F>::kSetting + k), tape);
}
// intrinsic k of the camera (fx, fy, cx, cy): its leaf where the tape asks for the intrinsics' gradients
template <class F> TAO_HOT Rev<F> seed_camera(const Rev<F>& x, int k) {
  Tape<F>* tape = current_tape<F>();
  return tape->camera ? Rev<F>(x.v, tape->parameter(Tape<F>::kCamera + k), tape) : x;
}

}  // namespace tao
