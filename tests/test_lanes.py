"""The CPU lanes' own functions (lanes_simd.h: atan2, logistic, reduce_min/reduce_max) against libm in double:
a small program compiled with the kernels' flags, which evaluates them over random and special arguments."""
import math

import pytest
import torch

from kernel_programs import needs_compiler, run_program

pytestmark = needs_compiler

PROGRAM = r"""
#include "lanes_simd.h"
#include <cmath>
#include <cstdio>
#include <random>
using namespace tao;
int main() {
  constexpr int L = Vec::size();
  std::mt19937 g(7);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::uniform_int_distribution<int> e(-30, 30);
  alignas(64) float y[L], x[L], out[L];
  double atan2_error = 0.0, logistic_error = 0.0;
  for (int it = 0; it < 200000; ++it) {
    for (int l = 0; l < L; ++l) y[l] = std::ldexp(u(g), e(g)), x[l] = std::ldexp(u(g), e(g));
    atan2(Vec::loadu(y), Vec::loadu(x)).store(out);
    for (int l = 0; l < L; ++l) atan2_error = std::fmax(atan2_error, std::fabs(out[l] - std::atan2(double(y[l]), double(x[l]))));
    for (int l = 0; l < L; ++l) x[l] = 120.0f * u(g);
    logistic(Vec::loadu(x)).store(out);
    for (int l = 0; l < L; ++l) {
      const double ref = 1.0 / (1.0 + std::exp(-std::fmax(-87.0, std::fmin(87.0, double(x[l])))));
      logistic_error = std::fmax(logistic_error, std::fabs(out[l] - ref) / ref);
    }
  }
  std::printf("atan2_error %.9g\nlogistic_error %.9g\n", atan2_error, logistic_error);
  const float special[][2] = {{0.0f, -0.0f}, {-0.0f, -0.0f}, {0.0f, 0.0f}, {-0.0f, 0.0f}, {1.0f, 0.0f}, {-1.0f, 0.0f},
                              {0.0f, -1.0f}, {-0.0f, -1.0f}, {1.0f, 1.0f}, {-1.0f, -1.0f}, {NAN, 1.0f}, {1.0f, NAN}};
  for (const auto& p : special) {
    for (int l = 0; l < L; ++l) y[l] = p[0], x[l] = p[1];
    atan2(Vec::loadu(y), Vec::loadu(x)).store(out);
    std::printf("atan2 %a %a %a\n", double(p[0]), double(p[1]), double(out[0]));
  }
  for (int l = 0; l < L; ++l) x[l] = float((l * 7) % L) - 3.5f;
  std::printf("reduce %g %g\n", double(reduce_min(Vec::loadu(x))), double(reduce_max(Vec::loadu(x))));
}
"""


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict:
    stdout = run_program(PROGRAM, tmp_path_factory.mktemp("lanes"), "lanes")
    out = {"atan2": []}
    for line in stdout.splitlines():
        name, *values = line.split()
        if name == "atan2":  # y, x, atan2(y, x) in hexadecimal (signed zeros and NaN kept)
            out["atan2"].append(tuple(float.fromhex(v) for v in values))
        else:
            out[name] = [float(v) for v in values]
    return out


def test_atan2_is_within_3e_7_rad_of_libm(results):
    assert results["atan2_error"][0] <= 3e-7


def test_atan2_takes_signed_zeros_and_nan_as_ieee(results):
    assert len(results["atan2"]) == 12
    for y, x, value in results["atan2"]:
        if math.isnan(y) or math.isnan(x):
            assert math.isnan(value)
            continue
        want = math.atan2(y, x)
        assert abs(value - want) <= 3e-7 and math.copysign(1.0, value) == math.copysign(1.0, want), (y, x, value, want)


def test_logistic_is_within_5e_7_relative(results):
    assert results["logistic_error"][0] <= 5e-7


def test_reductions_over_the_lanes(results):
    lanes = 16 if torch.backends.cpu.get_cpu_capability() == "AVX512" else 8  # (Vectorized<float>::size())
    assert results["reduce"] == [-3.5, lanes - 1 - 3.5]
