// Reverse-mode lanes over any lane type of lanes_scalar.h / lanes_simd.h: Rev<F> is a value and the index of
// the node that made it on the thread's tape (Tape<F>: per node its value's partial derivatives with respect
// to at most two parent nodes), so the one walk (walk.h) run with F = Rev<Vec> (or Rev<float>) records itself,
// and one sweep back over the tape (Tape::sweep) gives d L / d every node for any L seeded on its outputs. A
// walk's gradient then costs a few times its own arithmetic, whatever the number of inputs; forward mode
// (lanes_dual.h) costs one walk per tangent.
//
// Constants (id < 0) make no node, so what does not depend on a leaf costs nothing. The leaves: the pixel's
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

namespace tao {

// (always inlined on the CPU: a node is a few stores, which a call would outweigh)
#ifdef __CUDACC_RTC__
#define TAO_FN_ALWAYS TAO_FN
#else
#define TAO_FN_ALWAYS inline __attribute__((always_inline))
#endif

template <class F> struct Tape {
  F* partial;        // [capacity + 1][2]: d node / d parent
  int32_t* parent;   // [capacity + 1][2]
  F* adjoint;        // [capacity + 1]: d L / d node, after sweep
  int32_t capacity, n = 0;
  int32_t own[7] = {-1, -1, -1, -1, -1, -1, -1};  // the pixel's P (3), N (3), depth (seed_pixel)
  bool overflow = false;

  // (the arrays' last slot is the sweep's sink: a node's missing parent passes its adjoint there)
  TAO_FN Tape(F* partials, int32_t* parents, F* adjoints, int32_t cap)
      : partial(partials), parent(parents), adjoint(adjoints), capacity(cap - 1) {
    adjoint[capacity] = F(0.0f);
  }

  // a node of value-derivatives pa, pb with respect to a, b (ids, -1: none); -1 when the tape is full
  TAO_FN_ALWAYS int32_t push(int32_t a, const F& pa, int32_t b, const F& pb) {
    if (n == capacity) {
      overflow = true;
      return -1;
    }
    partial[2 * n] = pa, partial[2 * n + 1] = pb;
    parent[2 * n] = a, parent[2 * n + 1] = b;
    adjoint[n] = F(0.0f);
    return n++;
  }
  TAO_FN int32_t leaf() { return push(-1, F(0.0f), -1, F(0.0f)); }
  TAO_FN void seed(int32_t id, const F& g) {
    if (id >= 0) adjoint[id] = adjoint[id] + g;
  }
  // the adjoints of nodes [stop, n) passed back to their parents, last node first
  TAO_FN void sweep(int32_t stop) {
    for (int32_t i = n - 1; i >= stop; --i) {
      const F a = adjoint[i];
#ifdef __CUDACC_RTC__  // (a warp's threads take the same branches)
      const int32_t p0 = parent[2 * i], p1 = parent[2 * i + 1];
      if (p0 >= 0) adjoint[p0] = adjoint[p0] + a * partial[2 * i];
      if (p1 >= 0) adjoint[p1] = adjoint[p1] + a * partial[2 * i + 1];
#else  // (unary and binary nodes alternate with the code: the sink in place of a skip the CPU would mispredict)
      const int32_t p0 = parent[2 * i] >= 0 ? parent[2 * i] : capacity;
      const int32_t p1 = parent[2 * i + 1] >= 0 ? parent[2 * i + 1] : capacity;
      adjoint[p0] = adjoint[p0] + a * partial[2 * i];
      adjoint[p1] = adjoint[p1] + a * partial[2 * i + 1];
#endif
    }
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
  int32_t id;     // < 0: a constant
  Tape<F>* tape;  // the node's (null for a constant): found without the thread's slot

  TAO_FN_ALWAYS Rev() : v(0.0f), id(-1), tape(nullptr) {}
  TAO_FN_ALWAYS Rev(const F& x) : v(x), id(-1), tape(nullptr) {}  // a constant (float converts through F)
  TAO_FN_ALWAYS Rev(const F& x, int32_t i, Tape<F>* t) : v(x), id(i), tape(i >= 0 ? t : nullptr) {}

  // value with derivatives a and b with respect to x and y (a constant where neither is a node)
  static TAO_FN_ALWAYS Rev link(const F& value, const Rev& x, const F& a) {
    if (x.id < 0) return Rev(value);
    return Rev(value, x.tape->push(x.id, a, -1, F(0.0f)), x.tape);
  }
  static TAO_FN_ALWAYS Rev link(const F& value, const Rev& x, const F& a, const Rev& y, const F& b) {
    if (x.id < 0) return link(value, y, b);
    if (y.id < 0) return link(value, x, a);
    return Rev(value, x.tape->push(x.id, a, y.id, b), x.tape);
  }

  friend TAO_FN_ALWAYS Rev operator+(const Rev& a, const Rev& b) { return link(a.v + b.v, a, F(1.0f), b, F(1.0f)); }
  friend TAO_FN_ALWAYS Rev operator-(const Rev& a, const Rev& b) { return link(a.v - b.v, a, F(1.0f), b, F(-1.0f)); }
  friend TAO_FN_ALWAYS Rev operator*(const Rev& a, const Rev& b) { return link(a.v * b.v, a, b.v, b, a.v); }
  friend TAO_FN_ALWAYS Rev operator/(const Rev& a, const Rev& b) {
    const F inv = F(1.0f) / b.v, q = a.v * inv;
    return link(q, a, inv, b, neg(q * inv));
  }
  friend TAO_FN_ALWAYS M operator<(const Rev& a, const Rev& b) { return a.v < b.v; }
  friend TAO_FN_ALWAYS M operator>(const Rev& a, const Rev& b) { return a.v > b.v; }
  friend TAO_FN_ALWAYS M operator<=(const Rev& a, const Rev& b) { return a.v <= b.v; }
  friend TAO_FN_ALWAYS M operator>=(const Rev& a, const Rev& b) { return a.v >= b.v; }
  friend TAO_FN_ALWAYS M operator==(const Rev& a, const Rev& b) { return a.v == b.v; }
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

template <class F> TAO_FN_ALWAYS Rev<F> from_lanes(const float* x, const Rev<F>&) { return Rev<F>(from_lanes(x, F(0.0f))); }
template <class F> TAO_FN_ALWAYS Rev<F> select(const typename LaneTraits<F>::M& m, const Rev<F>& yes, const Rev<F>& no) {
  const F v = select(m, yes.v, no.v);
  if (yes.id == no.id) return Rev<F>(v, yes.id, yes.tape);
  return Rev<F>::link(v, yes, select(m, F(1.0f), F(0.0f)), no, select(m, F(0.0f), F(1.0f)));
}
template <class F> TAO_FN_ALWAYS Rev<F> neg(const Rev<F>& x) { return Rev<F>::link(neg(x.v), x, F(-1.0f)); }
template <class F> TAO_FN_ALWAYS Rev<F> fma(const Rev<F>& a, const Rev<F>& b, const Rev<F>& c) { return a * b + c; }
// a b + c for a constant b and c, its value fused as the value lanes' fma
template <class F> TAO_FN_ALWAYS Rev<F> fma(const Rev<F>& a, const F& b, const F& c) {
  return Rev<F>::link(fma(a.v, b, c), a, b);
}
// a / b with the value lanes' quotient as its value
template <class F> TAO_FN_ALWAYS Rev<F> quotient(const Rev<F>& a, const Rev<F>& b) {
  const F inv = F(1.0f) / b.v, q = a.v / b.v;
  return Rev<F>::link(q, a, inv, b, neg(q * inv));
}
template <class F> TAO_FN_ALWAYS Rev<F> abs(const Rev<F>& x) { return select(x.v < F(0.0f), neg(x), x); }
template <class F> TAO_FN_ALWAYS Rev<F> sqrt(const Rev<F>& x) {  // (0 at 0, as lanes_dual.h's)
  const F r = sqrt(x.v);
  return Rev<F>::link(r, x, select(r > F(0.0f), F(0.5f) / r, F(0.0f)));
}
template <class F> TAO_FN_ALWAYS Rev<F> rsqrt(const Rev<F>& x) {
  const F r = rsqrt(x.v);
  return Rev<F>::link(r, x, F(-0.5f) * r * r * r);
}
template <class F> TAO_FN_ALWAYS Rev<F> reciprocal(const Rev<F>& x) {
  const F r = reciprocal(x.v);
  return Rev<F>::link(r, x, neg(r * r));
}
template <class F> TAO_FN_ALWAYS Rev<F> floor(const Rev<F>& x) { return Rev<F>(floor(x.v)); }
template <class F> TAO_FN_ALWAYS Rev<F> ceil(const Rev<F>& x) { return Rev<F>(ceil(x.v)); }
template <class F> TAO_FN_ALWAYS Rev<F> rint(const Rev<F>& x) { return Rev<F>(rint(x.v)); }
template <class F> TAO_FN_ALWAYS Rev<F> atan2(const Rev<F>& y, const Rev<F>& x) {  // (none at the origin)
  const F r2 = x.v * x.v + y.v * y.v;
  const F inv = select(r2 > F(0.0f), reciprocal(r2), F(0.0f));
  return Rev<F>::link(atan2(y.v, x.v), y, x.v * inv, x, neg(y.v) * inv);
}
template <class F> TAO_FN_ALWAYS Rev<F> cos(const Rev<F>& x) { return Rev<F>::link(cos(x.v), x, neg(sin(x.v))); }
template <class F> TAO_FN_ALWAYS Rev<F> sin(const Rev<F>& x) { return Rev<F>::link(sin(x.v), x, cos(x.v)); }
template <class F> TAO_FN void cos_sin_rounded(const Rev<F>& x, Rev<F>& c, Rev<F>& s) {
  F cv, sv;
  cos_sin_rounded(x.v, cv, sv);
  c = Rev<F>::link(cv, x, neg(sv)), s = Rev<F>::link(sv, x, cv);
}
template <class F> TAO_FN_ALWAYS Rev<F> logistic(const Rev<F>& x) {  // (its slope s (1 - s): finite everywhere)
  const F s = logistic(x.v);
  return Rev<F>::link(s, x, s * (F(1.0f) - s));
}
template <class F> TAO_FN_ALWAYS Rev<F> asin(const Rev<F>& x) { return Rev<F>::link(asin(x.v), x, rsqrt(F(1.0f) - x.v * x.v)); }
template <class F> TAO_FN_ALWAYS Rev<F> acos(const Rev<F>& x) {
  return Rev<F>::link(acos(x.v), x, neg(rsqrt(F(1.0f) - x.v * x.v)));
}
template <class F> TAO_FN_ALWAYS Rev<F> pow(const Rev<F>& x, const Rev<F>& y) {  // (the base's derivative alone)
  return Rev<F>::link(pow(x.v, y.v), x, y.v * pow(x.v, y.v - F(1.0f)));
}
template <class F> TAO_FN_ALWAYS Rev<F> max(const Rev<F>& a, const Rev<F>& b) {
  Rev<F> r = select(b.v > a.v, b, a);
  r.v = max(a.v, b.v);  // NaN-propagating
  return r;
}
template <class F> TAO_FN_ALWAYS Rev<F> min(const Rev<F>& a, const Rev<F>& b) {
  Rev<F> r = select(b.v < a.v, b, a);
  r.v = min(a.v, b.v);
  return r;
}
template <class F> TAO_FN_ALWAYS Rev<F> clamp_min(const Rev<F>& x, const Rev<F>& lo) { return select(x.v < lo.v, lo, x); }
template <class F> TAO_FN_ALWAYS Rev<F> clamp_max(const Rev<F>& x, const Rev<F>& hi) { return select(x.v > hi.v, hi, x); }
template <class F> TAO_FN_ALWAYS Rev<F> clamp(const Rev<F>& x, const Rev<F>& lo, const Rev<F>& hi) {
  return clamp_max(clamp_min(x, lo), hi);
}
template <class F> TAO_FN typename LaneTraits<F>::I to_int(const Rev<F>& x) { return to_int(x.v); }

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
template <class F> TAO_FN_ALWAYS Rev<F> seed_setting(const Rev<F>& x, int k = 0) {
  Tape<F>* tape = current_tape<F>();
  return Rev<F>(x.v, tape->parameter(Tape<F>::kSetting + k), tape);
}
// intrinsic k of the camera (fx, fy, cx, cy): its leaf where the tape asks for the intrinsics' gradients
template <class F> TAO_FN_ALWAYS Rev<F> seed_camera(const Rev<F>& x, int k) {
  Tape<F>* tape = current_tape<F>();
  return tape->camera ? Rev<F>(x.v, tape->parameter(Tape<F>::kCamera + k), tape) : x;
}

}  // namespace tao
