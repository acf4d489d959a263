"""bitmask.h's sample_angles_adjoint (the soft backward's chain from a step's front and back angles to its delta,
the slice's V and T and its thickness) against central differences of the two angles in double, computed here
from their definition (the plane rule's atan2(side delta . T, delta . V) and atan2(side delta . T, delta . V - t);
HDRP's fast_acos of the cosines between V and delta, delta - t V). At the degenerate points it must not turn into
NaN: a sample at the pixel itself (atan2(0, 0), no derivative) and a sample off the slice (its tangent coordinate a
constant 0). A small program compiled with the kernels' flags, in scalar and SIMD lanes."""
import math

import pytest

from kernel_programs import needs_compiler, run_program

pytestmark = needs_compiler

PROGRAM = r"""
#include "lanes_simd.h"
#include "bitmask.h"
#include <cmath>
#include <cstdio>
#include <random>
using namespace tao;

// HDRP's fast_acos: (pi/2 - 0.156583 |x|) sqrt(1 - |x|), mirrored for x < 0
static double fast_acos_reference(double x) {
  const double res = (M_PI / 2 - 0.156583 * std::fabs(x)) * std::sqrt(1.0 - std::fabs(x));
  return x >= 0 ? res : M_PI - res;
}

// the angles' loss g_front front + g_back back in double, from their definition: the plane rule's atan2s, or
// HDRP's fast_acos of the cosines between V and delta, delta - t V
static double loss(SectorAngles angles, const double* d, const double* v, const double* t, double thick, int side,
                   double g_front, double g_back) {
  const double along_view = d[0] * v[0] + d[1] * v[1] + d[2] * v[2];
  if (angles == SectorAngles::hdrp) {
    double b[3];
    for (int k = 0; k < 3; ++k) b[k] = d[k] - thick * v[k];
    const double front = along_view / std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    const double back = (b[0] * v[0] + b[1] * v[1] + b[2] * v[2]) / std::sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]);
    return g_front * fast_acos_reference(front) + g_back * fast_acos_reference(back);
  }
  const double along_tangent = side * (d[0] * t[0] + d[1] * t[1] + d[2] * t[2]);
  return g_front * std::atan2(along_tangent, along_view) + g_back * std::atan2(along_tangent, along_view - thick);
}

// the adjoint in lanes F (every lane the same case): d loss / d delta, V, T (9) and t, in out[10]
template <class F>
static void adjoint(SectorAngles angles, const float* d, const float* v, const float* t, float thick, int side,
                    float g_front, float g_back, float* out) {
  F delta[3], V[3], T[3], g_delta[3], g_V[3], g_T[3];
  for (int c = 0; c < 3; ++c) {
    delta[c] = F(d[c]), V[c] = F(v[c]), T[c] = F(t[c]);
    g_delta[c] = g_V[c] = g_T[c] = F(0.0f);
  }
  const F g_t = sample_angles_adjoint(angles, side, delta, V, T, F(-2.0f), F(thick), F(g_front), F(g_back), g_delta,
                                      g_V, g_T);
  const F* parts[3] = {g_delta, g_V, g_T};
  for (int p = 0; p < 3; ++p)
    for (int c = 0; c < 3; ++c) {
      float lanes[LaneTraits<F>::L];
      to_lanes(parts[p][c], lanes);
      out[3 * p + c] = lanes[LaneTraits<F>::L - 1];
    }
  float lanes[LaneTraits<F>::L];
  to_lanes(g_t, lanes);
  out[9] = lanes[LaneTraits<F>::L - 1];
}

static void report(SectorAngles angles, const char* name, const float* d, const float* v, const float* t, float thick,
                   int side, float g_front, float g_back) {
  float scalar[10], simd[10];
  adjoint<float>(angles, d, v, t, thick, side, g_front, g_back, scalar);
  adjoint<Vec>(angles, d, v, t, thick, side, g_front, g_back, simd);
  std::printf("%s%s", angles == SectorAngles::hdrp ? "hdrp_" : "", name);
  for (int k = 0; k < 10; ++k) std::printf(" %.9g", double(scalar[k]));
  for (int k = 0; k < 10; ++k) std::printf(" %.9g", double(simd[k]));
  std::printf("\n");
}

int main() {
  std::mt19937 g(11);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  for (SectorAngles angles : {SectorAngles::plane, SectorAngles::hdrp}) {
  double worst = 0.0;
  for (int it = 0; it < 400; ++it) {
    // an orthonormal V, T (T perpendicular to V), delta = a V + b side T + c (V x T): b > 0.2 keeps the back angle
    // away from atan2's branch cut; t > 0.1
    double v[3] = {u(g) - 0.5, u(g) - 0.5, -1.0 - u(g)}, r[3] = {u(g) - 0.5, u(g) - 0.5, u(g) - 0.5}, t[3], n[3];
    const double lv = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    for (int c = 0; c < 3; ++c) v[c] /= lv;
    const double rv = r[0] * v[0] + r[1] * v[1] + r[2] * v[2];
    for (int c = 0; c < 3; ++c) t[c] = r[c] - rv * v[c];
    const double lt = std::sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]);
    for (int c = 0; c < 3; ++c) t[c] /= lt;
    n[0] = v[1] * t[2] - v[2] * t[1], n[1] = v[2] * t[0] - v[0] * t[2], n[2] = v[0] * t[1] - v[1] * t[0];
    const int side = it % 2 ? 1 : -1;
    const double a = 2.0 * u(g) - 1.0, b = 0.2 + u(g), c = u(g) - 0.5, thick = 0.1 + u(g);
    const double g_front = 2.0 * u(g) - 1.0, g_back = 2.0 * u(g) - 1.0;
    double d[3];
    for (int k = 0; k < 3; ++k) d[k] = a * v[k] + b * side * t[k] + c * n[k];
    // (the float inputs, and the reference at exactly those values)
    float df[3], vf[3], tf[3];
    double dd[3], vd[3], td[3];
    for (int k = 0; k < 3; ++k) {
      df[k] = float(d[k]), vf[k] = float(v[k]), tf[k] = float(t[k]);
      dd[k] = df[k], vd[k] = vf[k], td[k] = tf[k];
    }
    const float thick_f = float(thick);
    float out[2][10];
    adjoint<float>(angles, df, vf, tf, thick_f, side, float(g_front), float(g_back), out[0]);
    adjoint<Vec>(angles, df, vf, tf, thick_f, side, float(g_front), float(g_back), out[1]);
    double* inputs[3] = {dd, vd, td};
    const double h = 1e-6;
    for (int k = 0; k < 10; ++k) {
      double fd;
      if (k < 9) {
        double* x = inputs[k / 3] + k % 3;
        const double x0 = *x;
        *x = x0 + h;
        const double up = loss(angles, dd, vd, td, thick_f, side, g_front, g_back);
        *x = x0 - h;
        const double down = loss(angles, dd, vd, td, thick_f, side, g_front, g_back);
        *x = x0;
        fd = (up - down) / (2.0 * h);
      } else {
        fd = (loss(angles, dd, vd, td, thick_f + h, side, g_front, g_back) -
              loss(angles, dd, vd, td, thick_f - h, side, g_front, g_back)) / (2.0 * h);
      }
      for (int l = 0; l < 2; ++l) worst = std::fmax(worst, std::fabs(out[l][k] - fd) / (1.0 + std::fabs(fd)));
    }
  }
  std::printf("%sworst %.9g\n", angles == SectorAngles::hdrp ? "hdrp_" : "", worst);
  // a sample at the pixel itself: atan2(0, 0) has no derivative, and the back angle's tangent coordinate is 0
  // (HDRP's: the front's direction is none, the back's cosine -1 where fast_acos has no slope)
  const float zero[3] = {0.0f, 0.0f, 0.0f}, v[3] = {0.0f, 0.0f, -1.0f}, t[3] = {1.0f, 0.0f, 0.0f};
  report(angles, "origin", zero, v, t, 0.5f, 1, 0.7f, -0.3f);
  report(angles, "origin_no_gradient", zero, v, t, 0.5f, -1, 0.0f, 0.0f);
  // a sample off the slice (within kMinOffset of it along T): its tangent coordinate is a constant 0, so neither
  // angle moves (the tensor walk's slice_coordinates)
  const float off[3] = {1e-6f, 0.6f, -0.4f};
  if (angles == SectorAngles::plane) report(angles, "off_slice", off, v, t, 0.5f, 1, 0.7f, -0.3f);
  }
}
"""


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict:
    stdout = run_program(PROGRAM, tmp_path_factory.mktemp("angle_slopes"), "slopes")
    return {name: [float(v) for v in values] for name, *values in (line.split() for line in stdout.splitlines())}


@pytest.mark.parametrize("rule, bound", [("", 2e-6), ("hdrp_", 1e-5)])
def test_adjoint_matches_central_differences_in_double(results, rule, bound):
    """400 random samples on both sides, scalar and SIMD lanes, of the plane rule's angles and HDRP's: every one of
    the ten partial derivatives within ``bound`` of the double-precision central difference, relative to 1 + its
    size (float32 rounding; measured 2.4e-7 and 1.1e-6: HDRP's cosines divide by |d|^3)."""
    assert results[rule + "worst"][0] <= bound


@pytest.mark.parametrize("case", ["origin", "origin_no_gradient", "off_slice", "hdrp_origin", "hdrp_origin_no_gradient"])
def test_degenerate_samples_have_no_gradient(results, case):
    """At the pixel itself (atan2(0, 0): no derivative, where dividing by r^2 = 0 would give NaN) and off the
    slice every partial derivative is 0, in scalar and SIMD lanes alike."""
    values = results[case]
    assert len(values) == 20 and all(math.isfinite(v) for v in values), values
    assert values == [0.0] * 20
