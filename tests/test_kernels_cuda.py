"""The CUDA kernels' source, run on the CPU: ``cuda_source()`` (the headers NVRTC compiles, and the
``__global__`` entry points of walk_cuda.cu) compiled by the host C++ compiler with its device branch on
(``__CUDACC_RTC__``) and stand-ins for what NVRTC provides, then launched thread by thread over a grid
of blocks. Its output must be the CPU operator's scalar lanes' (the same walk_pixel), and so the tensor
path's by tests/kernel_agreement.py. On a machine with CUDA, the kernels themselves run against the CPU
operator.
"""
import dataclasses
import math
import shutil
import subprocess

import numpy as np
import pytest
import torch

from kernel_agreement import assert_masks_agree, assert_values_agree, relative_error
from test_kernels import FRAMES, built  # noqa: F401,F811  (built: the fixture)
from test_kernels_position_reads import moved_positions
from torch_ao.kernels.launch import _THREADS, cuda_source, packed_inputs, run_walk, walk_settings
from torch_ao.kernels.soft_bitmask import soft_backward_kernel
from torch_ao.kernels.walk_grad import cuda_backward, replayed_fetches
from torch_ao.methods.pssao import PSSAOPattern
from torch_ao.methods.ssao import hemisphere_kernel
from torch_ao.methods.ue4_ssao import SAMPLE_SETS

COMPILER = shutil.which("g++") or shutil.which("c++")
pytestmark = pytest.mark.skipif(COMPILER is None, reason="needs a C++ compiler")

# what NVRTC provides, for the host compiler: no system header in this unit (the device branch defines
# its own int64_t), the math functions declared, the thread indices as globals the driver sets
SHIM = """
#define __device__
#define __forceinline__ inline
#define __global__
#define __launch_bounds__(...)
#define __shared__
extern "C" {
float fabsf(float); float sqrtf(float); float floorf(float); float ceilf(float); float rintf(float);
float atan2f(float, float); float acosf(float); float asinf(float); float cosf(float); float sinf(float);
float powf(float, float); float fmaf(float, float, float); float expf(float); float expm1f(float);
double cos(double); double sin(double);
struct tao_dim3 { unsigned x, y, z; };
tao_dim3 blockIdx, blockDim, threadIdx;
}
static inline int __popc(unsigned x) { return __builtin_popcount(x); }
static inline int __popcll(unsigned long long x) { return __builtin_popcountll(x); }
static inline int __ffs(int x) { return __builtin_ffs(x); }
static inline int __ffsll(long long x) { return __builtin_ffsll(x); }
static inline unsigned __float_as_uint(float x) { unsigned b; __builtin_memcpy(&b, &x, sizeof b); return b; }
static inline float __uint_as_float(unsigned b) { float x; __builtin_memcpy(&x, &b, sizeof x); return x; }
static inline float atomicAdd(float* to, float x) { float old = *to; *to = old + x; return old; }  // (one thread at a time)
"""

# what both drivers share: the thread indices the kernels read, reading the inputs' files back
DRIVER_COMMON = r"""
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>
extern "C" {
struct tao_dim3 { unsigned x, y, z; };
extern tao_dim3 blockIdx, blockDim, threadIdx;
}
template <class T> std::vector<T> load(const std::string& dir, const char* name) {
  std::vector<T> v;
  FILE* f = std::fopen((dir + "/" + name).c_str(), "rb");
  if (!f) return v;
  T x;
  while (std::fread(&x, sizeof(T), 1, f) == 1) v.push_back(x);
  std::fclose(f);
  return v;
}
"""

DRIVER = DRIVER_COMMON + r"""
extern "C" {
typedef void Kernel(const float*, const float*, const float*, const float*, const bool*, const float*, const float*,
                    const float*, const float*, float*, const long long*, const float*, int, int, int);
Kernel tao_walk_gtao, tao_walk_hbao, tao_walk_bitmask, tao_walk_exact, tao_walk_glsl, tao_walk_soft,
    tao_walk_soft_gradients, tao_walk_soft_gradients_short, tao_walk_exact_gradients, tao_walk_exact_gradients_growth,
    tao_walk_wedge, tao_walk_pssao,
    tao_walk_hemisphere, tao_walk_soft_glsl;
}
int main(int argc, char** argv) {  // driver NAME DIR B H W C THREADS: a launch of <<<blocks, THREADS>>>
  const std::string name = argv[1], dir = argv[2];
  const int B = std::atoi(argv[3]), H = std::atoi(argv[4]), W = std::atoi(argv[5]), C = std::atoi(argv[6]);
  const unsigned threads = unsigned(std::atoi(argv[7]));
  Kernel* kernel = name == "gtao" ? tao_walk_gtao : name == "hbao" ? tao_walk_hbao
                 : name == "exact" ? tao_walk_exact : name == "glsl" ? tao_walk_glsl : name == "soft" ? tao_walk_soft
                 : name == "soft_gradients" ? tao_walk_soft_gradients
                 : name == "soft_gradients_short" ? tao_walk_soft_gradients_short
                 : name == "exact_gradients" ? tao_walk_exact_gradients
                 : name == "exact_gradients_growth" ? tao_walk_exact_gradients_growth : name == "wedge" ? tao_walk_wedge
                 : name == "pssao" ? tao_walk_pssao : name == "hemisphere" ? tao_walk_hemisphere
                 : name == "soft_glsl" ? tao_walk_soft_glsl : tao_walk_bitmask;
  auto P = load<float>(dir, "positions"), N = load<float>(dir, "normals"), I = load<float>(dir, "inverse");
  auto D = load<float>(dir, "depth"), K = load<float>(dir, "intrinsics"), Li = load<float>(dir, "light");
  auto Ce = load<float>(dir, "cells"), Bf = load<float>(dir, "backface");
  auto V8 = load<unsigned char>(dir, "valid");  // (std::vector<bool> holds bits)
  const bool* V = reinterpret_cast<const bool*>(V8.data());
  auto ints = load<long long>(dir, "ints");
  auto floats = load<float>(dir, "floats");
  std::vector<float> out(size_t(B) * C * H * W, -7.0f);
  const long long pixels = (long long)B * H * W;
  blockDim.x = threads;
  for (unsigned b = 0; (long long)b * threads < pixels; ++b)
    for (unsigned t = 0; t < threads; ++t) {  // every thread of the grid, the last block's idle ones too
      blockIdx.x = b, threadIdx.x = t;
      kernel(P.data(), N.data(), I.data(), D.data(), V, K.data(), Li.empty() ? nullptr : Li.data(),
             Ce.empty() ? nullptr : Ce.data(), Bf.empty() ? nullptr : Bf.data(), out.data(),
             ints.data(), floats.data(), B, H, W);
    }
  FILE* f = std::fopen((dir + "/out").c_str(), "wb");
  std::fwrite(out.data(), sizeof(float), out.size(), f);
  std::fclose(f);
  return 0;
}
"""


GRAD_DRIVER = DRIVER_COMMON + r"""
extern "C" {
typedef void Record(const float*, const float*, const float*, const float*, const bool*, const float*, const float*,
                    float*, long long*, const long long*, const float*, int, int, int);
typedef void Backward(const float*, const float*, const float*, const float*, const bool*, const float*, const float*,
                      const float*, const long long*, float*, float*, float*, float*, float*, float*, float*,
                      const long long*, const float*, int, int, int);
typedef void SoftBackward(const float*, const float*, const float*, const float*, const bool*, const float*,
                          const float*, const float*, const float*, const float*, float*, float*, float*, float*,
                          float*, float*, float*, float*, float*, float*, const long long*, const float*, int, int,
                          int);
typedef void HardRecord(const float*, const float*, const float*, const float*, const bool*, const float*,
                        const float*, const float*, const float*, float*, int*, const long long*, const float*, int,
                        int, int);
typedef void HardBackward(const float*, const float*, const float*, const float*, const bool*, const float*,
                          const float*, const float*, const float*, const float*, const int*, float*, float*, float*,
                          float*, float*, float*, float*, float*, const long long*, const float*, int, int, int);
typedef void ExactBackward(const float*, const float*, const float*, const float*, const bool*, const float*,
                           const float*, const float*, const float*, float*, float*, float*, float*, float*, float*,
                           float*, const long long*, const float*, int, int, int);
Record tao_record_gtao, tao_record_hbao, tao_record_pssao;
Backward tao_backward_gtao, tao_backward_gtao_short, tao_backward_gtao_small, tao_backward_hbao,
    tao_backward_hbao_short, tao_backward_hbao_small, tao_backward_wedge, tao_backward_wedge_short,
    tao_backward_pssao_small, tao_backward_hemisphere, tao_backward_hemisphere_short;
SoftBackward tao_soft_backward, tao_soft_backward_short, tao_soft_backward_glsl, tao_soft_backward_glsl_short;
ExactBackward tao_exact_backward;
HardRecord tao_record_hard, tao_record_hard_glsl;
HardBackward tao_hard_backward, tao_hard_backward_glsl;
}
template <class T> void save(const std::string& dir, const char* name, const std::vector<T>& v) {
  FILE* f = std::fopen((dir + "/" + name).c_str(), "wb");
  std::fwrite(v.data(), sizeof(T), v.size(), f);
  std::fclose(f);
}
template <class Fn> void grid(long long pixels, unsigned threads, const Fn& fn) {  // every thread of <<<blocks, threads>>>
  blockDim.x = threads;
  for (unsigned b = 0; (long long)b * threads < pixels; ++b)
    for (unsigned t = 0; t < threads; ++t) blockIdx.x = b, threadIdx.x = t, fn();
}
Backward* horizon_backward(const std::string& name) {  // (tao_backward_NAME)
  const std::pair<const char*, Backward*> entries[] = {
      {"gtao", tao_backward_gtao}, {"gtao_short", tao_backward_gtao_short},
      {"gtao_small", tao_backward_gtao_small}, {"hbao", tao_backward_hbao},
      {"hbao_short", tao_backward_hbao_short}, {"hbao_small", tao_backward_hbao_small},
      {"wedge", tao_backward_wedge}, {"wedge_short", tao_backward_wedge_short},
      {"pssao_small", tao_backward_pssao_small}, {"hemisphere", tao_backward_hemisphere},
      {"hemisphere_short", tao_backward_hemisphere_short}};
  for (const auto& entry : entries)
    if (name == entry.first) return entry.second;
  return nullptr;
}
int main(int argc, char** argv) {  // grad_driver NAME DIR B H W C RECORD_WORDS THREADS: record, then backward
                                   // (NAME soft, exact, hard, wedge, hemisphere: that walk's backward alone;
                                   // gtao, hbao, pssao, wedge, hemisphere with their entry's suffix, as _short)
  const std::string name = argv[1], dir = argv[2];
  const int B = std::atoi(argv[3]), H = std::atoi(argv[4]), W = std::atoi(argv[5]), C = std::atoi(argv[6]);
  const long long words = std::atoll(argv[7]);
  const unsigned threads = unsigned(std::atoi(argv[8]));
  const auto named = [&](const char* prefix) { return name.rfind(prefix, 0) == 0; };
  Record* record = named("gtao") ? tao_record_gtao : named("pssao") ? tao_record_pssao : tao_record_hbao;
  Backward* backward = horizon_backward(name);
  auto P = load<float>(dir, "positions"), N = load<float>(dir, "normals"), I = load<float>(dir, "inverse");
  auto D = load<float>(dir, "depth"), K = load<float>(dir, "intrinsics"), Ce = load<float>(dir, "cells");
  auto Bf = load<float>(dir, "backface");
  auto V8 = load<unsigned char>(dir, "valid");
  const bool* V = reinterpret_cast<const bool*>(V8.data());
  auto ints = load<long long>(dir, "ints");
  auto floats = load<float>(dir, "floats");
  auto grad = load<float>(dir, "grad");
  const long long pixels = (long long)B * H * W;
  const float* cells = Ce.empty() ? nullptr : Ce.data();
  std::vector<float> out(size_t(B) * C * H * W, -7.0f);
  std::vector<long long> rec(size_t(pixels * words), -1);
  const size_t n = size_t(pixels);
  std::vector<float> gp(3 * n), gn(3 * n), gd(n), gs(3 * n), taps(3 * n), ti(n), tl(n), gc(4 * n);  // (gs: 3 settings)
  if (name == "hard" || name == "hard_glsl") {  // (the "ssilvb_glsl" variant's: its GlslAccumulator)
    HardRecord* hard_record = name == "hard" ? tao_record_hard : tao_record_hard_glsl;
    HardBackward* hard_backward = name == "hard" ? tao_hard_backward : tao_hard_backward_glsl;
    const long long slices = ints[0];
    std::vector<int> occ(size_t(pixels * slices), -1);
    std::vector<float> senders(3 * n), tli(3 * n);
    auto Li = load<float>(dir, "light");
    const float* light = Li.empty() ? nullptr : Li.data();
    grid(pixels, threads, [&] { hard_record(P.data(), N.data(), I.data(), D.data(), V, K.data(), light, cells,
                                                Bf.empty() ? nullptr : Bf.data(), out.data(), occ.data(), ints.data(),
                                                floats.data(), B, H, W); });
    grid(pixels, threads, [&] { hard_backward(P.data(), N.data(), I.data(), D.data(), V, K.data(), light, cells,
                                                  Bf.empty() ? nullptr : Bf.data(), grad.data(), occ.data(), gp.data(),
                                                  gn.data(), gd.data(), taps.data(), ti.data(), senders.data(),
                                                  tli.data(), light ? gc.data() : nullptr, ints.data(), floats.data(),
                                                  B, H, W); });
    save(dir, "occupied", occ), save(dir, "tap_normals", senders), save(dir, "tap_light", tli);
  } else if (name == "exact") {
    grid(pixels, threads, [&] { tao_exact_backward(P.data(), N.data(), I.data(), D.data(), V, K.data(), cells,
                                                   Bf.empty() ? nullptr : Bf.data(), grad.data(), gp.data(), gn.data(),
                                                   gd.data(), taps.data(), ti.data(), tl.data(), gc.data(),
                                                   ints.data(), floats.data(), B, H, W); });
  } else if (name.rfind("soft", 0) == 0) {  // (a slice's steps in soft.h's arrays of 64, or of 16; the glsl variant's)
    SoftBackward* soft = name == "soft" ? tao_soft_backward : name == "soft_short" ? tao_soft_backward_short
                       : name == "soft_glsl" ? tao_soft_backward_glsl : tao_soft_backward_glsl_short;
    std::vector<float> senders(3 * n), tli(3 * n);
    auto Li = load<float>(dir, "light");
    const float* light = Li.empty() ? nullptr : Li.data();
    grid(pixels, threads, [&] { soft(P.data(), N.data(), I.data(), D.data(), V, K.data(), light, cells,
                                                  Bf.empty() ? nullptr : Bf.data(), grad.data(), gp.data(), gn.data(),
                                                  gd.data(), gs.data(), taps.data(), ti.data(), tl.data(),
                                                  senders.data(), tli.data(), gc.data(), ints.data(), floats.data(),
                                                  B, H, W); });
    save(dir, "tap_normals", senders), save(dir, "tap_light", tli);
  } else if (named("wedge") || named("hemisphere")) {  // (every step replayed: no record)
    grid(pixels, threads, [&] { backward(P.data(), N.data(), I.data(), D.data(), V, K.data(), cells, grad.data(), nullptr,
                                      gp.data(), gn.data(), gd.data(), gs.data(), taps.data(), ti.data(), gc.data(),
                                      ints.data(), floats.data(), B, H, W); });
  } else {
    grid(pixels, threads, [&] { record(P.data(), N.data(), I.data(), D.data(), V, K.data(), cells, out.data(),
                                       rec.data(), ints.data(), floats.data(), B, H, W); });
    grid(pixels, threads, [&] { backward(P.data(), N.data(), I.data(), D.data(), V, K.data(), cells, grad.data(),
                                         rec.data(), gp.data(), gn.data(), gd.data(), gs.data(), taps.data(), ti.data(),
                                         gc.data(), ints.data(), floats.data(), B, H, W); });
  }
  save(dir, "out", out), save(dir, "record", rec), save(dir, "g_positions", gp), save(dir, "g_normals", gn);
  save(dir, "g_depth", gd), save(dir, "g_setting", gs), save(dir, "tap_positions", taps), save(dir, "tap_inverse", ti);
  save(dir, "tap_layer", tl), save(dir, "g_camera", gc);
  return 0;
}
"""


def _compile_on_cpu(folder, *defines: str):
    """The CUDA source (with ``defines``) compiled for the host in ``folder``, linked with the drivers: the forward
    driver's path (the backward's, ``grad_driver``, beside it)."""
    (folder / "kernels.cpp").write_text(SHIM + cuda_source())
    (folder / "driver.cpp").write_text(DRIVER)
    flags = ["-std=c++17", "-O2", "-ffp-contract=off", "-fno-math-errno"]
    subprocess.run([COMPILER, *flags, "-D__CUDACC_RTC__", *defines, "-c", "kernels.cpp", "-o", "kernels.o"],
                   cwd=folder, check=True)
    subprocess.run([COMPILER, *flags, "driver.cpp", "kernels.o", "-lm", "-o", "driver"], cwd=folder, check=True)
    (folder / "grad_driver.cpp").write_text(GRAD_DRIVER)
    subprocess.run([COMPILER, *flags, "grad_driver.cpp", "kernels.o", "-lm", "-o", "grad_driver"], cwd=folder,
                   check=True)
    return folder / "driver"


@pytest.fixture(scope="module")
def cuda_on_cpu(tmp_path_factory):
    """The lean CUDA build, compiled for the host: its forward driver's path."""
    return _compile_on_cpu(tmp_path_factory.mktemp("cuda_on_cpu"))


@pytest.fixture(scope="module")
def cuda_on_cpu_full(tmp_path_factory):
    """The full CUDA build (walk.h's TAO_FULL_WALK), compiled for the host: its forward driver's path."""
    return _compile_on_cpu(tmp_path_factory.mktemp("cuda_on_cpu_full"), "-DTAO_FULL_WALK")


def launch_on_cpu(program, accumulator, gbuffer, normals, settings, acc_ints, acc_floats, channels, light=None):
    inputs, extra, ints, floats = packed_inputs(gbuffer, normals, settings, acc_ints, acc_floats, light)
    folder = program.parent / accumulator
    folder.mkdir(exist_ok=True)
    for name, t in zip(("positions", "normals", "inverse", "depth", "valid", "intrinsics", "light", "cells", "backface"),
                       (*inputs, *extra)):
        t.numpy().tofile(folder / name)
    ints.numpy().tofile(folder / "ints")
    floats.numpy().tofile(folder / "floats")
    B, H, W = inputs[3].shape
    subprocess.run([str(program), accumulator, str(folder), str(B), str(H), str(W), str(channels), str(_THREADS)],
                   check=True)
    return torch.from_numpy(np.fromfile(folder / "out", dtype=np.float32).reshape(B, channels, H, W))


def _hemisphere_settings(samples: int, **walk) -> tuple[list[int], list[float]]:
    """SSAO's walk settings: its ``samples`` kernel points (seed 2) as the table of one slice, radius 2 (pixels
    away on the tiny frame too; on the rough one some behind the camera)."""
    table = hemisphere_kernel(samples, 2).to(torch.float32).flatten().tolist()
    return walk_settings(slices=1, steps=samples, radius=2.0, seed=2, placement="hemisphere", full_circle=True,
                         table=table, **walk)


def cases(gb):
    """(accumulator, walk settings, its ints, floats, channels, light) of GTAO (3 variants), HBAO, bitmask AO
    (hard: the default and hdrp variants; exact and with its parameters' derivatives, the GLSL shader's in its three
    numerics, soft: its forward,
    and with the radius and thickness derivatives), GTAO and HBAO with the Hilbert-indexed R2 noise and staggered
    steps, UE4 SSAO's wedge pairs (a sample set's table, evenly spaced directions), PSSAO's pixel offsets (their
    table) and SSAO's hemisphere kernel points (their table; the hard step and the logistic)."""
    light = torch.rand(*gb.depth.shape[:1], *gb.depth.shape[-2:], 3, generator=torch.Generator().manual_seed(0))
    common = dict(slices=3, steps=4, radius=1.0, jitter=True, seed=1, fetch="bilinear", border="drop")
    yield "gtao", walk_settings(**common), [0, True, True], [1.0, 0.3, 1.0], 5, None
    yield "gtao", walk_settings(**common, placement="hdrp"), [1, True, True], [1.0, 0.0, 1.0], 5, None
    yield "gtao", walk_settings(**dict(common, fetch="nearest"), placement="ue4"), [2, True, False], [1.0, 0.0, 0.6], 2, None
    yield "hbao", walk_settings(**common, full_circle=True, azimuth="screen"), [False, True, False], [1.0, 0.1], 1, None
    yield "gtao", walk_settings(**common, noise="hilbert_r2", stagger=True), [0, True, True], [1.0, 0.3, 1.0], 5, None
    # (slices drawn by the projected normal's density: a CUDA thread computes the bins again rather than keep them)
    yield ("gtao", walk_settings(**common, slice_sampling="projected_normal", placement="hdrp"), [1, True, True],
           [1.0, 0.0, 1.0], 5, None)
    yield ("hbao", walk_settings(**common, full_circle=True, noise="hilbert_r2", stagger=True), [False, True, False],
           [1.0, 0.1], 1, None)
    # (rounding, cosine, indirect, bent, the thickness' read, the variant: 0 default, 1 hdrp, along_ray, clip); the
    # thickness' offset, epsilon, its scale, its growth, the clip's radius
    yield "bitmask", walk_settings(**common), [0, True, True, True, False, 0, 0, 0], [0.5, 0.01, 1.0, 0.5, 0.0], 7, light
    yield "bitmask", walk_settings(**dict(common, border="clamp", jitter=False)), [0, False, False, False, False, 0, 0, 0], [0.3, 0.01, 1.0, 0.0, 0.0], 1, None
    yield "bitmask", walk_settings(**dict(common, fetch="edge_aware")), [0, True, True, False, False, 0, 0, 0], [0.3, 0.01, 1.0, 0.0, 0.0], 4, light
    yield "bitmask", walk_settings(**common, azimuth="screen"), [0, False, False, False, 0, 1, 0, 0], [0.5, 0.0, 1.0, 0.0, 0.0], 1, None
    yield "bitmask", walk_settings(**dict(common, fetch="nearest"), azimuth="screen"), [1, True, True, True, 0, 1, 0, 0], [0.5, 0.0, 1.0, 0.0, 0.0], 7, light
    # the exact variant's segment geometry with the sector union: along the camera ray, clipped to the sphere
    yield "bitmask", walk_settings(**common, sphere_extent=True), [0, True, True, True, 0, 0, 1, 1], [0.5, 0.01, 1.0, 0.0, 1.0], 7, light
    exact = dict(common, fetch="edge_aware")
    yield "exact", walk_settings(**exact, min_step_px=0.25, sphere_extent=True), [True, True, True, False, True], [0.4, 1.0, 1.0, 0.0, 0.6], 1, None
    yield "exact", walk_settings(**dict(exact, fetch="nearest")), [False, False, False, False, False], [0.4, 1.0, 1.0, 0.0, 0.0], 1, None
    yield ("exact_gradients_growth", walk_settings(**exact, min_step_px=0.25, sphere_extent=True),
           [True, True, True, False, True], [0.4, 1.0, 1.0, 0.0, 0.6], 5, None)
    yield ("exact_gradients", walk_settings(**dict(exact, fetch="bilinear", border="clamp")), [False, False, False, False, False],
           [0.4, 1.0, 1.0, 0.01, 0.0], 4, None)
    glsl = dict(slices=4 + 1, steps=5 + 1, radius=1.0, jitter=True, seed=0, fetch="nearest", border="clamp",
                placement="glsl", full_circle=True, azimuth="screen")  # (the shader's sliceCount 4, sampleCount 5)
    # (rounding, indirect, exact numerics, the thickness' read: 3 the sample's depth); the thickness' offset, scale,
    # growth
    yield "glsl", walk_settings(**glsl, noise="glsl"), [0, True, True, 0], [0.3, 1.0, 0.0], 4, light
    yield "glsl", walk_settings(**glsl, noise="glsl_mediump"), [0, True, True, 3], [0.05, 0.1, 0.4], 4, light
    yield "glsl", walk_settings(**dict(glsl, jitter=False), noise="glsl"), [1, False, False, 0], [0.0, 1.0, 0.0], 1, None
    # its soft / straight-through walk (soft_glsl.h): the hard accumulator's ints, then straight-through and whether
    # the thickness has a growth; its floats (growth among them), then tau
    yield "soft_glsl", walk_settings(**glsl, noise="glsl"), [0, True, False, 0, False, False], [0.3, 1.0, 0.0, 0.25], 4, light
    yield "soft_glsl", walk_settings(**glsl, noise="glsl_mediump"), [1, True, True, 3, False, True], [0.05, 0.1, 0.4, 0.1], 4, light
    yield "soft_glsl", walk_settings(**glsl, noise="glsl"), [0, False, False, 0, True, False], [0.3, 1.0, 0.0, 0.25], 1, None
    # soft: ints rounding, cosine, straight-through, the thickness' read, the variant's angles (hdrp: 1), bent,
    # indirect, a growth, the segment geometry (the full build's: 0 here); floats offset, epsilon, tau, scale, growth
    yield "soft", walk_settings(**common), [0, False, False, 0, 0, 0, 0, 0, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.0], 1, None
    yield "soft", walk_settings(**common), [0, True, False, 3, 0, 1, 0, 0, 0, 0], [0.1, 0.01, 0.25, 0.05, 0.0], 4, None  # bent normals
    yield "soft", walk_settings(**common, sphere_extent=True), [0, True, False, 0, 0, 1, 0, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 4, None
    yield "soft", walk_settings(**dict(common, azimuth="screen")), [0, False, True, 0, 1, 1, 0, 1, 0, 0], [0.4, 0.0, 0.25, 0.0, 0.6], 4, None
    # indirect light (and bent normals): soft, straight-through
    yield "soft", walk_settings(**common), [0, True, False, 0, 0, 1, 1, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 7, light
    yield "soft", walk_settings(**dict(common, fetch="edge_aware")), [0, False, True, 0, 0, 0, 1, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 4, light
    yield "soft_gradients", walk_settings(**common), [0, False, False, 0, 0, 0, 0, 1, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.6], 5, None
    yield "soft_gradients", walk_settings(**dict(common, border="clamp")), [1, True, True, 0, 0, 0, 0, 0, 0, 0], [0.4, 0.01, 0.05, 0.0, 0.0], 4, None
    yield "soft_gradients", walk_settings(**common), [0, True, False, 3, 0, 0, 0, 0, 0, 0], [0.05, 0.01, 0.25, 0.15, 0.0], 4, None  # linear
    yield "soft_gradients", walk_settings(**common, sphere_extent=True), [0, False, False, 0, 0, 0, 0, 0, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.0], 4, None
    yield "soft_gradients", walk_settings(**dict(common, azimuth="screen")), [0, True, True, 0, 1, 0, 0, 1, 0, 0], [0.4, 0.0, 0.25, 0.0, 0.6], 5, None
    # the same walk with a short slice's arrays (CUDA only: the CPU operator runs "soft_gradients" for it, CPU_TWIN)
    yield "soft_gradients_short", walk_settings(**common), [0, True, False, 0, 0, 0, 0, 0, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.0], 4, None
    yield "soft_gradients_short", walk_settings(**dict(common, steps=8)), [1, False, True, 3, 1, 0, 0, 0, 0, 0], [0.05, 0.01, 0.25, 0.15, 0.0], 4, None
    wedge = dict(common, steps=3, placement="wedge", azimuth="screen")
    table = [v for x, y in SAMPLE_SETS["ue4_6"] for v in (math.atan2(y, x), math.hypot(x, y))]
    yield ("wedge", walk_settings(**dict(wedge, slices=6, fetch="nearest", border="clamp"), table=table), [False],
           [0.4, 0.025, 0.0], 2, None)
    yield "wedge", walk_settings(**dict(wedge, fetch="edge_aware")), [True], [0.3, 0.05, 0.02], 2, None
    pattern = PSSAOPattern(6, 5)
    offsets = [v for s in range(6) for k in range(5) for v in pattern.pixel_offset(s, k)]
    pixels = dict(slices=6, steps=5, radius=0.0, jitter=False, seed=0, placement="pixels", full_circle=True,
                  azimuth="screen", table=offsets)
    yield "pssao", walk_settings(**pixels, fetch="nearest", border="drop"), [], [1.0], 3, None
    yield "pssao", walk_settings(**pixels, fetch="bilinear", border="clamp"), [], [0.5], 3, None
    for fetch, border, jitter, softness in (("nearest", "clamp", True, 0.0), ("bilinear", "drop", False, 0.05),
                                            ("edge_aware", "clamp", True, 0.1)):
        yield ("hemisphere", _hemisphere_settings(8, fetch=fetch, border=border, jitter=jitter), [], [0.025, softness],
               1, None)


#: the CPU operator's accumulator computing what a CUDA-only one does (the same walk in arrays of another size)
CPU_TWIN = {"soft_gradients_short": "soft_gradients"}
DERIVATIVES = ("soft_gradients", "soft_gradients_short", "exact_gradients", "exact_gradients_growth")  # (their
# channels after the first)


def full_cases(gb):
    """What the full build alone walks (:func:`cases`' layout): slices drawn by the projected normal's density in the
    bitmask family's accumulators (hard with every output, the exact union with its derivatives, soft, straight-through
    and their derivatives' walks) and the soft accumulators' segment geometry (along the camera ray, clipped to the
    radius' sphere), each in soft and straight-through mode, with and without derivatives."""
    light = torch.rand(*gb.depth.shape[:1], *gb.depth.shape[-2:], 3, generator=torch.Generator().manual_seed(0))
    common = dict(slices=3, steps=4, radius=1.0, jitter=True, seed=1, fetch="bilinear", border="drop")
    drawn = walk_settings(**common, slice_sampling="projected_normal")
    yield "bitmask", drawn, [0, True, True, True, False, 0, 0, 0], [0.5, 0.01, 1.0, 0.5, 0.0], 7, light
    yield "bitmask", drawn, [1, False, False, False, False, 0, 1, 1], [0.3, 0.01, 1.0, 0.0, 1.0], 1, None
    yield "exact", drawn, [True, True, True, False, True], [0.4, 1.0, 1.0, 0.0, 0.6], 1, None
    yield "exact_gradients_growth", drawn, [True, True, True, False, True], [0.4, 1.0, 1.0, 0.0, 0.6], 5, None
    yield "soft", drawn, [0, True, False, 0, 0, 1, 1, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 7, light
    yield "soft", drawn, [0, False, True, 3, 0, 0, 0, 1, 0, 0], [0.1, 0.01, 0.25, 0.05, 0.6], 1, None
    yield "soft_gradients", drawn, [0, True, False, 0, 0, 0, 0, 1, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.6], 5, None
    yield "soft_gradients_short", drawn, [0, False, True, 0, 0, 0, 0, 0, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.0], 4, None
    # the segment geometry (ints 8, 9: along the ray, clipped), with the sphere's extent and without
    extent = walk_settings(**common, sphere_extent=True)
    yield "soft", extent, [0, True, False, 0, 0, 1, 1, 0, 1, 1], [0.5, 0.01, 0.25, 0.0, 0.0], 7, light
    yield "soft", walk_settings(**common), [0, False, True, 0, 0, 0, 0, 0, 1, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 1, None
    yield "soft_gradients", extent, [0, True, False, 0, 0, 0, 0, 1, 0, 1], [0.5, 0.01, 0.25, 0.0, 0.6], 5, None
    yield "soft_gradients_short", extent, [0, False, True, 0, 0, 0, 0, 0, 1, 1], [0.4, 0.01, 0.1, 0.0, 0.0], 4, None


def position_cases(gb):
    """A position buffer read between texels (bilinear, edge-aware), :func:`cases`' layout: GTAO, HBAO, hard bitmask AO
    with every output, the exact union, soft and straight-through bitmask AO and their derivatives' walk."""
    light = torch.rand(*gb.depth.shape[:1], *gb.depth.shape[-2:], 3, generator=torch.Generator().manual_seed(0))
    for fetch in ("bilinear", "edge_aware"):
        common = dict(slices=3, steps=4, radius=1.0, jitter=True, seed=1, fetch=fetch, border="drop")
        walk = walk_settings(**common)
        yield "gtao", walk, [0, True, True], [1.0, 0.3, 1.0], 5, None
        hbao = walk_settings(**common, full_circle=True, azimuth="screen")
        yield "hbao", hbao, [False, True, False], [1.0, 0.1], 1, None
        yield "bitmask", walk, [0, True, True, True, False, 0, 0, 0], [0.5, 0.01, 1.0, 0.5, 0.0], 7, light
        yield "exact", walk, [True, True, True, False, True], [0.4, 1.0, 1.0, 0.0, 0.6], 1, None
        yield "soft", walk, [0, True, True, 0, 0, 1, 1, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 7, light
        yield "soft_gradients", walk, [0, True, False, 0, 0, 0, 0, 1, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.6], 5, None


def assert_the_scalar_lanes_walk(program, gb, all_cases):
    """Each of ``all_cases`` (:func:`cases`' layout) launched by ``program`` on ``gb``: every pixel written, the CPU
    operator's scalar lanes' values (derivatives relative to their scale), the SIMD lanes' by tolerance."""
    normals = gb.view_normals()
    for accumulator, settings, ints, floats, channels, light in all_cases:
        cuda = launch_on_cpu(program, accumulator, gb, normals, settings, ints, floats, channels, light)
        twin = CPU_TWIN.get(accumulator, accumulator)
        scalar = run_walk(twin, gb, normals, settings, ints, floats, channels, light=light, lanes="scalar")
        assert (cuda != -7.0).all()  # every pixel written, by exactly its thread
        simd = run_walk(twin, gb, normals, settings, ints, floats, channels, light=light)
        if accumulator in DERIVATIVES:  # (derivatives: relative to their scale)
            scale = scalar[:, 1:].abs().amax(dim=(0, 2, 3)).clamp_min(1e-6)[None, :, None, None]
            assert (cuda[:, :1] - scalar[:, :1]).abs().max() <= 1e-6
            assert ((cuda[:, 1:] - scalar[:, 1:]) / scale).abs().max() <= 1e-5, accumulator
        else:
            assert (cuda - scalar).abs().max() <= 1e-6, (accumulator, (cuda - scalar).abs().max())
        assert_lanes_agree(cuda, simd, accumulator, settings[0][0], gb.valid, weighted=bool(settings[0][15]))


def test_a_call_needing_an_option_the_lean_build_leaves_out_runs_the_full_one():
    """launch.full_walk: slices drawn by the projected normal's density in a sector accumulator (horizon.h's weigh
    theirs in the lean build too), a position buffer read between texels, the soft segment geometry."""
    from torch_ao.kernels.launch import full_walk

    gb, moved = FRAMES["rough"](), moved_positions()[0]
    common = dict(slices=3, steps=4, radius=1.0, jitter=True, seed=1, fetch="bilinear", border="drop")
    plain, drawn = walk_settings(**common), walk_settings(**common, slice_sampling="projected_normal")
    nearest = walk_settings(**dict(common, fetch="nearest"))
    assert not any(full_walk(name, gb, plain) for name in ("bitmask", "exact", "soft", "soft_gradients", "gtao"))
    assert all(full_walk(name, gb, drawn) for name in ("bitmask", "exact", "exact_gradients", "soft", "soft_gradients"))
    assert not full_walk("gtao", gb, drawn) and not full_walk("hbao", gb, drawn)
    assert full_walk("gtao", moved, plain)
    assert full_walk("bitmask", moved, walk_settings(**dict(common, fetch="edge_aware")))
    assert not full_walk("gtao", moved, nearest)
    assert full_walk("soft", gb, plain, segments=True)


@pytest.mark.parametrize("frame", ["rough", "tiny"])
def test_the_cuda_source_run_on_the_cpu_is_the_scalar_lanes_walk(built, cuda_on_cpu, frame):
    gb = FRAMES[frame]()
    assert_the_scalar_lanes_walk(cuda_on_cpu, gb, cases(gb))


def test_the_full_cuda_build_run_on_the_cpu_is_the_scalar_lanes_walk(built, cuda_on_cpu_full):
    """The full build: what the lean one walks, the same; slices drawn by the projected normal's density and the soft
    segment geometry (:func:`full_cases`); a position buffer read between texels (:func:`position_cases`, whose
    outputs differ from the same walk's of the buffer's depth)."""
    gb = FRAMES["rough"]()
    assert_the_scalar_lanes_walk(cuda_on_cpu_full, gb, cases(gb))
    assert_the_scalar_lanes_walk(cuda_on_cpu_full, gb, full_cases(gb))
    moved, depth_only = moved_positions()
    assert_the_scalar_lanes_walk(cuda_on_cpu_full, moved, position_cases(moved))
    for accumulator, settings, ints, floats, channels, light in position_cases(moved):
        read = launch_on_cpu(cuda_on_cpu_full, accumulator, moved, moved.view_normals(), settings, ints, floats,
                             channels, light)
        of_depth = launch_on_cpu(cuda_on_cpu_full, accumulator, depth_only, moved.view_normals(), settings, ints,
                                 floats, channels, light)
        assert (read[:, :1] - of_depth[:, :1]).abs().max() > 0.02, accumulator


def assert_lanes_agree(out: torch.Tensor, ref: torch.Tensor, accumulator: str, slices: int, valid: torch.Tensor,
                       weighted: bool = False):
    """A walk's outputs in other lanes than ``ref``'s (SIMD against scalar, a GPU's against the CPU's): each
    rounds differently, which a decision can amplify. Uniform hard visibility of even slices as
    :func:`assert_masks_agree` (``weighted``: slices drawn by a density, weighed each, as values), the derivative
    channels of ``*_gradients`` within 1e-3 of their scale, values as :func:`assert_values_agree`."""
    if accumulator in DERIVATIVES:
        scale = ref[:, 1:].abs().amax(dim=(0, 2, 3)).clamp_min(1e-6)[None, :, None, None]
        assert ((out[:, 1:] - ref[:, 1:]) / scale).abs().max() <= 1e-3, accumulator
        out, ref = out[:, :1], ref[:, :1]
    if accumulator == "bitmask" and out.shape[1] == 1 and not weighted:
        assert_masks_agree(out, ref, valid, slices)
    else:
        assert_values_agree(out, ref, valid, atol=1e-4, bound=0.5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_kernels_agree_with_the_cpu_operator(built):
    """Every case of both builds (the full one's: :func:`full_cases`, :func:`position_cases`) on the GPU."""
    rough, moved = FRAMES["rough"](), moved_positions()[0]
    failed = []
    for gb, walks in ((rough, cases(rough)), (rough, full_cases(rough)), (moved, position_cases(moved))):
        normals = gb.view_normals()
        device = gb.to(device="cuda")
        for index, (accumulator, settings, ints, floats, channels, light) in enumerate(walks):
            cpu = run_walk(CPU_TWIN.get(accumulator, accumulator), gb, normals, settings, ints, floats, channels,
                           light=light, lanes="scalar")
            segments = accumulator.startswith("soft") and accumulator != "soft_glsl" and bool(ints[8] or ints[9])
            gpu = run_walk(accumulator, device, normals.cuda(), settings, ints, floats, channels,
                           light=None if light is None else light.cuda(), segments=segments)
            try:
                assert_lanes_agree(gpu.cpu(), cpu, accumulator, settings[0][0], gb.valid,
                                   weighted=bool(settings[0][15]))
            except AssertionError as error:  # every case's verdict, not the first failure's alone
                failed.append((index, accumulator, str(error).splitlines()[0]))
    assert not failed, failed


def _replaces(accumulator: str, acc_ints: list) -> bool:
    """Whether the packed accumulator's take replaces its state, as its module tells the kernels: GTAO's exact
    variant (``acc_ints[0] == 0``), HBAO's ``accumulate="max"`` (``acc_ints[1]`` false), PSSAO."""
    if accumulator == "gtao":
        return acc_ints[0] == 0
    if accumulator == "hbao":
        return not acc_ints[1]
    return accumulator == "pssao"


def _settings(accumulator: str, acc_ints: list) -> int:
    """The packed accumulator's settings() (horizon.h, ssao.h): UE4 SSAO's 3, SSAO's 2, GTAO's ue4 variant's 2
    (``acc_ints[0] == 2``), else 1."""
    return {"wedge": 3, "hemisphere": 2}.get(accumulator, 2 if accumulator == "gtao" and acc_ints[0] == 2 else 1)


def _backward_cases():
    """(accumulator, walk settings, ints, floats, channels) of GTAO's three variants, HBAO (incremental and
    max), UE4 SSAO's wedge pairs, PSSAO and SSAO's hemisphere points (every step replayed), the soft walk (uniform, cosine, straight-through), the exact union (cosine and uniform; a layer read
    bilinearly, at its first tap, or none; along the ray or the view) and the hard sector walk (cosine weights,
    bent normals, indirect light; the default and hdrp variants), every fetch, either border."""
    common = dict(slices=3, steps=5, radius=1.0, jitter=True, seed=1, fetch="bilinear", border="drop")
    yield "gtao", walk_settings(**common), [0, True, True], [1.0, 0.3, 1.0], 5
    yield "gtao", walk_settings(**dict(common, fetch="edge_aware", border="clamp")), [0, True, False], [1.0, 0.3, 1.0], 2
    yield "gtao", walk_settings(**common, placement="hdrp"), [1, True, False], [1.0, 0.0, 1.0], 2
    yield "gtao", walk_settings(**dict(common, fetch="nearest"), placement="ue4"), [2, True, False], [1.0, 0.0, 0.6], 2
    yield "gtao", walk_settings(**common, slice_sampling="projected_normal"), [0, True, True], [1.0, 0.3, 1.0], 5
    yield "hbao", walk_settings(**common, full_circle=True, azimuth="screen"), [False, True, False], [1.0, 0.1], 1
    yield ("hbao", walk_settings(**dict(common, fetch="edge_aware"), full_circle=True, azimuth="screen"),
           [True, True, False], [1.0, 0.1], 1)
    # more steps than the _short entries replay (GTAO: 2 x 9 fetches a slice; HBAO, one side a slice: 17; the
    # _small entry's 4, 2 whatever the steps where a take replaces)
    yield "gtao", walk_settings(**dict(common, steps=9), placement="hdrp"), [1, True, False], [1.0, 0.0, 1.0], 2
    yield "gtao", walk_settings(**dict(common, steps=9)), [0, True, False], [1.0, 0.3, 1.0], 2
    yield ("hbao", walk_settings(**dict(common, steps=17), full_circle=True, azimuth="screen"), [False, True, False],
           [1.0, 0.1], 1)  # (one side a slice: the full entry from 17 steps)
    yield ("hbao", walk_settings(**dict(common, steps=3), full_circle=True, azimuth="screen"), [False, True, False],
           [1.0, 0.1], 1)  # (the default's 3 steps: every rise replayed by the _small entry)
    yield ("hbao", walk_settings(**dict(common, steps=9), full_circle=True, azimuth="screen"), [False, False, False],
           [1.0, 0.1], 1)
    # (accurate_angle); fade_distance, flat_surface_bias, flat_softness / distance_bias; PSSAO's offsets as a table
    yield ("wedge", walk_settings(**dict(common, steps=3), placement="wedge", azimuth="screen"), [True],
           [0.4, 0.05, 0.02], 2)
    yield ("wedge", walk_settings(**dict(common, steps=2, fetch="nearest", border="clamp"), placement="wedge",
                                  azimuth="screen", table=[0.3, 1.0, 1.9, 0.7, 3.5, 0.5]), [False], [0.3, 0.05, 0.0], 2)
    offsets = [float(v) for s in range(3) for k in range(4) for v in (round((k + 1.5) * math.cos(2.1 * s + 0.3)),
                                                                       round((k + 1.5) * math.sin(2.1 * s + 0.3)))]
    yield ("pssao", walk_settings(**dict(common, steps=4, jitter=False), placement="pixels", full_circle=True,
                                  azimuth="screen", table=offsets), [], [1.0], 3)
    # (bias, softness): the logistic (the hard step's gradients, rangeCheck's, vanish on these smooth frames)
    yield "hemisphere", _hemisphere_settings(6, fetch="bilinear", border="drop", jitter=True), [], [0.025, 0.05], 1
    yield "hemisphere", _hemisphere_settings(5, fetch="nearest", border="clamp", jitter=False), [], [0.01, 0.1], 1
    yield "hemisphere", _hemisphere_settings(6, fetch="edge_aware", border="clamp", jitter=True), [], [0.0, 0.05], 1
    yield "hemisphere", _hemisphere_settings(17, fetch="bilinear", border="drop", jitter=True), [], [0.025, 0.05], 1
    # (rounding, cosine, straight, read, variant, bent, indirect, a growth, the segment geometry: along the ray, clip)
    yield "soft", walk_settings(**common), [0, False, False, 0, 0, 0, 0, 1, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.6], 1
    yield "soft", walk_settings(**dict(common, fetch="edge_aware", border="clamp")), [0, True, True, 0, 0, 0, 0, 0, 0, 0], [0.4, 0.01, 0.1, 0.0, 0.0], 1
    yield "soft", walk_settings(**dict(common, fetch="nearest")), [1, True, False, 0, 0, 0, 0, 0, 0, 0], [0.5, 0.0, 0.3, 0.0, 0.0], 1
    # (offset, epsilon, tau, scale, growth): the back-face layer, a per-object table's first tap, the linear model
    yield "soft", walk_settings(**dict(common, fetch="edge_aware")), [0, True, False, 1, 0, 0, 0, 1, 0, 0], [0.1, 0.01, 0.25, 0.8, 0.6], 1
    yield "soft", walk_settings(**common), [0, False, False, 2, 0, 0, 0, 0, 0, 0], [0.05, 0.01, 0.25, 1.0, 0.0], 1
    yield "soft", walk_settings(**common), [0, True, True, 3, 0, 0, 0, 0, 0, 0], [0.1, 0.01, 0.25, 0.05, 0.0], 1
    yield "soft", walk_settings(**dict(common, azimuth="screen")), [0, True, False, 1, 1, 0, 0, 1, 0, 0], [0.1, 0.0, 0.25, 0.8, 0.6], 1  # hdrp
    # bent normals: the visibility's and the bent normal sum's upstream gradients (4 channels); both variants
    yield "soft", walk_settings(**dict(common, fetch="edge_aware")), [0, True, False, 1, 0, 1, 0, 0, 0, 0], [0.1, 0.01, 0.25, 0.8, 0.0], 4
    yield "soft", walk_settings(**dict(common, azimuth="screen")), [0, False, True, 0, 1, 1, 0, 0, 0, 0], [0.4, 0.0, 0.25, 0.0, 0.0], 4
    # indirect light: uniform and cosine (with bent normals: 7 channels), straight-through, the hdrp variant
    yield "soft", walk_settings(**common), [0, False, False, 0, 0, 0, 1, 1, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.6], 4
    yield "soft", walk_settings(**dict(common, fetch="edge_aware")), [0, True, True, 0, 0, 1, 1, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 7
    yield "soft", walk_settings(**dict(common, azimuth="screen")), [0, True, False, 1, 1, 0, 1, 0, 0, 0], [0.1, 0.0, 0.25, 0.8, 0.0], 4
    # more steps than the short backward keeps (tao_soft_backward's arrays of 64)
    yield "soft", walk_settings(**dict(common, steps=9)), [0, True, False, 0, 0, 0, 0, 1, 0, 0], [0.3, 0.01, 0.25, 1.0, 0.6], 1
    # (cosine, along the ray, clipped, the layer's read: constant 0, layer 1, first tap 2); offset, scale, radius, epsilon
    exact = dict(common, fetch="edge_aware", min_step_px=0.25, sphere_extent=True)
    yield "exact", walk_settings(**exact), [True, True, True, 1, True], [0.05, 0.8, 1.0, 0.0, 0.6], 1
    yield "exact", walk_settings(**dict(common, border="clamp")), [False, False, False, 0, False], [0.4, 1.0, 1.0, 0.01, 0.0], 1
    yield "exact", walk_settings(**dict(common, fetch="nearest")), [True, True, True, 2, True], [0.1, 1.0, 1.0, 0.0, 0.6], 1
    # (rounding, cosine, indirect, bent, the layer's read, the variant); thickness, epsilon, the layer's scale, growth
    yield "hard", walk_settings(**dict(common, fetch="edge_aware")), [0, True, False, True, 1, 0, 0, 0], [0.1, 0.01, 1.0, 0.0, 0.0], 4
    yield "hard", walk_settings(**dict(common, border="clamp")), [1, True, False, False, 0, 0, 0, 0], [0.4, 0.01, 1.0, 0.0, 0.0], 1
    yield "hard", walk_settings(**dict(common, fetch="edge_aware")), [0, True, True, True, 0, 0, 0, 0], [0.4, 0.01, 1.0, 0.5, 0.0], 7
    yield "hard", walk_settings(**dict(common, fetch="nearest")), [0, False, True, False, 0, 0, 0, 0], [0.4, 0.01, 1.0, 0.0, 0.0], 4
    # the hdrp variant's (its slice angle in the backward's tangents), screen directions as its module's default
    yield "hard", walk_settings(**dict(common, fetch="edge_aware"), azimuth="screen"), [0, True, True, True, 1, 1, 0, 0], [0.1, 0.0, 1.0, 0.0, 0.0], 7
    yield "hard", walk_settings(**common, sphere_extent=True), [0, True, True, True, 0, 0, 1, 1], [0.4, 0.01, 1.0, 0.0, 1.0], 7
    # the "ssilvb_glsl" variant's (rounding, indirect, exact numerics, the layer's read); thickness, the layer's scale,
    # growth:
    # its indirect light's backward
    glsl = dict(slices=4, steps=5, radius=1.0, jitter=True, seed=0, fetch="nearest", border="clamp", placement="glsl",
                full_circle=True, azimuth="screen")
    yield "hard_glsl", walk_settings(**glsl, noise="glsl"), [0, True, False, 0], [0.3, 1.0, 0.0], 4
    yield "hard_glsl", walk_settings(**glsl, noise="glsl_mediump"), [1, True, True, 1], [0.0, 1.2, 0.4], 4
    # its soft / straight-through walk's (soft_glsl.h; ints and floats as "hard_glsl"'s, then straight-through, a
    # growth, tau):
    # slices of 6 steps (the short backward's) and of 18
    yield "soft_glsl", walk_settings(**glsl, noise="glsl"), [0, True, False, 0, False, False], [0.3, 1.0, 0.0, 0.25], 4
    yield "soft_glsl", walk_settings(**glsl, noise="glsl"), [1, True, True, 1, True, True], [0.05, 1.2, 0.5, 0.2], 4
    yield "soft_glsl", walk_settings(**dict(glsl, steps=18), noise="glsl"), [0, False, False, 3, False, False], [0.05, 0.1, 0.0, 0.25], 1


def _full_backward_cases():
    """What the full build alone differentiates (:func:`_backward_cases`' layout): slices drawn by the projected
    normal's density in the hard walk (every output), the soft and straight-through walks and the exact union's, and
    the soft walk's segment geometry (along the ray, clipped; soft and straight-through, with indirect light)."""
    common = dict(slices=3, steps=5, radius=1.0, jitter=True, seed=1, fetch="bilinear", border="drop")
    drawn = walk_settings(**common, slice_sampling="projected_normal")
    yield "hard", drawn, [0, True, True, True, 0, 0, 0, 0], [0.4, 0.01, 1.0, 0.5, 0.0], 7
    yield "soft", drawn, [0, True, False, 1, 0, 1, 1, 1, 0, 0], [0.1, 0.01, 0.25, 0.8, 0.6], 7
    yield "soft", drawn, [0, False, True, 0, 0, 0, 0, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 1
    yield "exact", drawn, [True, True, True, 1, True], [0.05, 0.8, 1.0, 0.0, 0.6], 1
    extent = walk_settings(**common, sphere_extent=True)
    yield "soft", extent, [0, True, False, 0, 0, 0, 1, 0, 1, 1], [0.4, 0.01, 0.25, 0.0, 0.0], 4
    yield "soft", walk_settings(**common), [0, False, True, 1, 0, 1, 0, 1, 1, 0], [0.1, 0.01, 0.25, 0.8, 0.6], 4


def _position_backward_cases():
    """A position buffer read between texels (:func:`_backward_cases`' layout): GTAO, HBAO, the hard walk with every
    output, the soft walk with indirect light and bent normals, straight-through, the exact union; bilinear and
    edge-aware."""
    for fetch in ("bilinear", "edge_aware"):
        common = dict(slices=3, steps=5, radius=1.0, jitter=True, seed=1, fetch=fetch, border="drop")
        walk = walk_settings(**common)
        yield "gtao", walk, [0, True, True], [1.0, 0.3, 1.0], 5
        yield "hbao", walk_settings(**common, full_circle=True, azimuth="screen"), [False, True, False], [1.0, 0.1], 1
        yield "hard", walk, [0, True, True, True, 0, 0, 0, 0], [0.4, 0.01, 1.0, 0.5, 0.0], 7
        yield "soft", walk, [0, True, False, 0, 0, 1, 1, 0, 0, 0], [0.4, 0.01, 0.25, 0.0, 0.0], 7
        yield "soft", walk, [0, False, True, 0, 0, 0, 0, 1, 0, 0], [0.5, 0.01, 0.25, 0.0, 0.6], 1
        yield "exact", walk, [True, True, True, 0, True], [0.4, 1.0, 1.0, 0.0, 0.6], 1


@pytest.mark.parametrize("frame", ["rough", "tiny"])
def test_the_cuda_backward_run_on_the_cpu_is_the_scalar_lanes_backward(built, cuda_on_cpu, frame):
    """The CUDA record and backward kernels (walk_grad.h's record_block and grad_block, soft_grad_block; one thread
    a pixel, the taps scattered with atomicAdd) launched thread by thread on the CPU: the CPU operators' scalar
    lanes, which run the same functions, to float rounding (the scatters' order differs)."""
    assert_the_scalar_lanes_backward(cuda_on_cpu, FRAMES[frame](), _backward_cases())


def test_each_call_picks_the_smallest_cuda_backward_that_holds_its_fetches():
    """cuda_backward: the smallest of the accumulator's entries in walk_cuda.cu whose scratch holds the slice's
    fetches (replayed_fetches: one side a slice with full_circle; each side's last take where a take replaces)."""
    picks = {("gtao", replayed_fetches(9, True)): "tao_backward_gtao_small",  # (exact: 2 whatever the steps)
             ("gtao", replayed_fetches(8, False)): "tao_backward_gtao_short",  # (hdrp, ue4: 2 x 8)
             ("gtao", replayed_fetches(9, False)): "tao_backward_gtao",
             ("hbao", replayed_fetches(16, False, full_circle=True)): "tao_backward_hbao_short",
             ("hbao", replayed_fetches(17, False, full_circle=True)): "tao_backward_hbao",
             ("hbao", replayed_fetches(32, True, full_circle=True)): "tao_backward_hbao_small",
             ("hbao", replayed_fetches(3, False, full_circle=True)): "tao_backward_hbao_small",  # (the default)
             ("hbao", replayed_fetches(5, False, full_circle=True)): "tao_backward_hbao_short",
             ("pssao", replayed_fetches(32, True, full_circle=True)): "tao_backward_pssao_small",
             ("wedge", replayed_fetches(2, False)): "tao_backward_wedge_short",  # (no _small entry)
             ("hemisphere", replayed_fetches(2, False, full_circle=True)): "tao_backward_hemisphere_short",
             ("hemisphere", replayed_fetches(18, False, full_circle=True)): "tao_backward_hemisphere"}
    assert {key: cuda_backward(*key) for key in picks} == picks
    with pytest.raises(ValueError, match="no backward of 'pssao' for 5 fetches"):
        cuda_backward("pssao", 5)


def test_a_cuda_kernel_compiles_its_group_alone(monkeypatch):
    """A CUDA call compiles (or loads) the group of walk_cuda.cu that holds its kernel (launch.cuda_groups), lean or
    full, and no other; a name walk_cuda.cu does not have is a KernelUnavailable."""
    from torch_ao.kernels import launch
    from torch_ao.kernels.build import KernelUnavailable

    asked = []

    def compiled(device_index, full, group):
        asked.append((full, group))
        return {name: f"{group} {name}" for name in launch.cuda_groups()[group]}

    monkeypatch.setattr(launch, "_cuda_kernels", compiled)
    assert launch._cuda_kernel("tao_backward_gtao_small", 0) == "gtao_small tao_backward_gtao_small"
    assert launch._cuda_kernel("tao_walk_gtao", 0, full=True) == "walks tao_walk_gtao"
    assert launch._cuda_kernel("tao_record_gtao", 0) == "records tao_record_gtao"
    assert asked == [(False, "gtao_small"), (True, "walks"), (False, "records")]
    with pytest.raises(KernelUnavailable, match="no kernel tao_backward_nothing"):
        launch._cuda_kernel("tao_backward_nothing", 0)


def test_a_cuda_backward_too_small_for_its_call_writes_nan(built, cuda_on_cpu):
    """HBAO's incremental sum of 5 steps (5 fetches a slice) run by the entry whose thread holds 4
    (tao_backward_hbao_small): every live pixel's position gradient is NaN, never a partial gradient."""
    gb = FRAMES["rough"]()
    settings = walk_settings(slices=3, steps=5, radius=1.0, jitter=True, seed=1, fetch="bilinear", border="drop",
                             full_circle=True, azimuth="screen")
    case = ("hbao", settings, [False, True, False], [1.0, 0.1], 1)
    assert_the_scalar_lanes_backward(cuda_on_cpu, gb, [case])  # (its own entry, tao_backward_hbao_short: agrees)
    with pytest.raises(AssertionError, match="hbao"):
        assert_the_scalar_lanes_backward(cuda_on_cpu, gb, [case], entry="hbao_small")
    B, _, H, W = gb.depth.shape
    g_pos = np.fromfile(cuda_on_cpu.parent / "grad_hbao" / "g_positions", dtype=np.float32).reshape(B, H, W, 3)
    live = gb.valid[:, 0].numpy()
    assert live.any() and np.isnan(g_pos[live]).all()


def test_the_full_cuda_builds_backward_run_on_the_cpu_is_the_scalar_lanes_backward(built, cuda_on_cpu_full):
    """The full build's record and backward kernels: slices drawn by the projected normal's density and the soft
    segment geometry (:func:`_full_backward_cases`), a position buffer read between texels, whose taps' positions
    take the gradient (:func:`_position_backward_cases`)."""
    assert_the_scalar_lanes_backward(cuda_on_cpu_full, FRAMES["rough"](), _full_backward_cases())
    assert_the_scalar_lanes_backward(cuda_on_cpu_full, moved_positions()[0], _position_backward_cases())


def assert_the_scalar_lanes_backward(program, gb, all_cases, entry=None):
    """Each of ``all_cases`` (:func:`_backward_cases`' layout) launched by ``program``'s backward driver on ``gb``: the
    CPU operators' scalar lanes' gradients, relative to their largest. ``entry``: the driver's kernel instead of the
    one the module's call would run (tao_backward_``entry``)."""
    from torch_ao.kernels.build import grad_kernels

    normals = gb.view_normals()
    backface = 0.3 * gb.depth.detach() + 0.1 * torch.rand(gb.depth.shape, generator=torch.Generator().manual_seed(2))
    for accumulator, settings, acc_ints, acc_floats, channels in all_cases:
        reads = {"exact": 3, "soft": 3, "hard": 4, "hard_glsl": 3, "soft_glsl": 3}
        layer = backface if accumulator in reads and acc_ints[reads[accumulator]] in (1, 2) else None
        light = torch.rand(*normals.shape[:1], *normals.shape[2:], 3, generator=torch.Generator().manual_seed(3))
        light = light if ((accumulator == "hard" and acc_ints[2]) or (accumulator == "hard_glsl" and acc_ints[1])
                          or (accumulator == "soft" and acc_ints[6])
                          or (accumulator == "soft_glsl" and acc_ints[1])) else None
        inputs, (light, cells, layer), ints, floats = packed_inputs(gb, normals, settings, acc_ints, acc_floats,
                                                                    light=light, backface=layer)
        B, H, W = inputs[3].shape
        grad = torch.linspace(0.5, 1.5, B * channels * H * W).view(B, channels, H, W)
        folder = program.parent / f"grad_{accumulator}"
        folder.mkdir(exist_ok=True)
        for name, t in zip(("positions", "normals", "inverse", "depth", "valid", "intrinsics", "light", "cells",
                            "backface", "grad"), (*inputs, light, cells, layer, grad)):
            t.numpy().tofile(folder / name)
        ints.numpy().tofile(folder / "ints")
        floats.numpy().tofile(folder / "floats")
        words = (settings[0][0] * 2 * settings[0][1] + 63) // 64
        kernel = {"tao_soft_backward_short": "soft_short"}.get(soft_backward_kernel(settings[0][1]), "soft")
        if accumulator == "soft_glsl":  # (the short arrays where a slice's steps fit 16)
            kernel = "soft_glsl_short" if settings[0][1] <= 16 else "soft_glsl"
        fetches = replayed_fetches(settings[0][1], _replaces(accumulator, acc_ints), full_circle=settings[0][7])
        if accumulator in ("gtao", "hbao", "pssao", "wedge", "hemisphere"):  # (the entry the module's call would run)
            kernel = cuda_backward(accumulator, fetches).removeprefix("tao_backward_")
        elif not accumulator.startswith("soft"):
            kernel = accumulator
        kernel = entry or kernel
        subprocess.run([str(program.parent / "grad_driver"), kernel,
                        str(folder), str(B), str(H), str(W),
                        str(channels), str(words), str(_THREADS)], check=True)

        def read(name, *shape, dtype=np.float32):  # (the first values: the driver's setting buffer holds 3 a pixel)
            return torch.from_numpy(np.fromfile(folder / name, dtype=dtype, count=math.prod(shape)).reshape(*shape))

        cpu = {}
        if accumulator in ("hard", "hard_glsl"):
            out, record = grad_kernels().hard_record(*inputs, light, cells, layer, ints, floats, channels,
                                                     settings[0][0], True)
            assert torch.equal(read("occupied", *record.shape, dtype=np.int32), record)
            assert (read("out", *out.shape) - out).abs().max() <= 1e-6
            g_pos, g_nrm, g_inv, g_depth, cpu["light"], camera = grad_kernels().hard_backward(
                grad, *inputs, light, cells, layer, ints, floats, record, light.numel() > 0, True)
            if light.numel():
                cpu["camera"] = camera
            g_setting = torch.zeros_like(g_depth)
        elif accumulator == "exact":
            g_pos, g_nrm, g_inv, g_depth, cpu["layer"], cpu["camera"] = grad_kernels().exact_backward(
                grad, *inputs, cells, layer, ints, floats, True, True)
            g_setting = torch.zeros_like(g_depth)
        elif accumulator.startswith("soft"):  # (the glsl variant's texels are floored: no intrinsics gradient)
            g_pos, g_nrm, g_inv, g_depth, g_setting, layer_grad, light_grad, camera = grad_kernels().soft_backward(
                grad, *inputs, light, cells, layer, ints, floats, accumulator == "soft", True)
            if accumulator == "soft":
                cpu["camera"] = camera
            if layer.numel():
                cpu["layer"] = layer_grad
            if light.numel():
                cpu["light"] = light_grad
        elif accumulator in ("wedge", "hemisphere"):
            g_pos, g_nrm, g_inv, g_depth, g_setting, cpu["camera"] = grad_kernels().walk_backward(
                accumulator, grad, *inputs, cells, ints, floats, torch.empty(0, dtype=torch.int64), fetches,
                _settings(accumulator, acc_ints), True, True)
        else:
            out, record = grad_kernels().walk_record(accumulator, *inputs, cells, ints, floats, channels, words,
                                                     True)
            assert torch.equal(read("record", *record.shape, dtype=np.int64), record)
            assert (read("out", *out.shape) - out).abs().max() <= 1e-6
            g_pos, g_nrm, g_inv, g_depth, g_setting, cpu["camera"] = grad_kernels().walk_backward(
                accumulator, grad, *inputs, cells, ints, floats, record, fetches, _settings(accumulator, acc_ints),
                True, True)
        cuda = {"positions": read("g_positions", *g_pos.shape) + read("tap_positions", *g_pos.shape),
                "normals": read("g_normals", *g_nrm.shape), "inverse": read("tap_inverse", *g_inv.shape),
                "depth": read("g_depth", *g_depth.shape), "setting": read("g_setting", *g_setting.shape)}
        cpu.update(positions=g_pos, normals=g_nrm, inverse=g_inv, depth=g_depth, setting=g_setting)
        if "camera" in cpu:  # (the intrinsics' gradients per pixel: none where a nearest fetch reads the buffer)
            cuda["camera"] = read("g_camera", *cpu["camera"].shape)
            assert cpu["camera"].abs().max() > 0 or not settings[0][5]
        if "layer" in cpu:
            cuda["layer"] = read("tap_layer", *g_depth.shape)
            assert layer.numel() == 0 or cpu["layer"].abs().max() > 0
        if "light" in cpu:  # (the senders' normals join the pixels' own)
            cuda["normals"] = cuda["normals"] + read("tap_normals", *g_nrm.shape)
            cuda["light"] = read("tap_light", *g_nrm.shape)
            assert light.numel() == 0 or cpu["light"].abs().max() > 0
        # (the comparison means something; UE4's wedge reads no normal)
        assert g_pos.abs().max() > 0 and (accumulator == "wedge" or g_nrm.abs().max() > 0)
        for name, reference in cpu.items():
            finite = torch.isfinite(reference)
            scale = reference[finite].abs().max().clamp_min(1e-6)
            assert ((cuda[name] - reference)[finite].abs().max() / scale) <= 1e-5, (accumulator, name)


def _ue4ssao():
    import torch_ao

    m = torch_ao.UE4SSAO(sample_set="uniform", slices=3, steps=3, fetch="bilinear", border="drop")
    m.radius.requires_grad_(False), m.flat_surface_bias.requires_grad_(False)  # (the tensor path's)
    return m


def _gradient_modules() -> dict:
    import torch_ao
    from torch_ao.thickness import BackfaceThickness

    return {"gtao": lambda: torch_ao.GTAO(slices=3, steps=5, fetch="edge_aware"),
            "hdrp": lambda: torch_ao.GTAO(variant="hdrp", slices=3, steps=4),
            "hbao": lambda: torch_ao.HBAO(slices=4, steps=4),
            "soft": lambda: torch_ao.BitmaskAO(mode="soft", weighting="cosine", fetch="edge_aware", slices=3, steps=4),
            "soft_backface": lambda: torch_ao.BitmaskAO(mode="soft", weighting="cosine", fetch="edge_aware",
                                                        thickness=BackfaceThickness(0.8, 0.1), slices=3, steps=4),
            "soft_hdrp": lambda: torch_ao.BitmaskAO(variant="hdrp", mode="soft", weighting="cosine",
                                                    thickness=BackfaceThickness(0.8, 0.1), slices=3, steps=4),
            "exact": lambda: torch_ao.BitmaskAO(variant="exact", thickness=BackfaceThickness(), slices=3, steps=4),
            "hard": lambda: torch_ao.BitmaskAO(weighting="cosine", bent_normals=True, slices=3, steps=4),
            "indirect": lambda: torch_ao.SSILVB(mode="hard", weighting="cosine", slices=3, steps=4),
            "soft_indirect": lambda: torch_ao.SSILVB(mode="soft", weighting="cosine", bent_normals=True, slices=3,
                                                     steps=4),
            "glsl_soft": lambda: torch_ao.SSILVB(variant="ssilvb_glsl", mode="soft", thickness=BackfaceThickness(0.8, 0.1),
                                                 slices=3, steps=4),
            "gtao_camera": lambda: torch_ao.GTAO(slices=3, steps=4),
            # (the full build's: slices drawn by the projected normal's density, the soft segment geometry)
            "soft_projected": lambda: torch_ao.SSILVB(mode="soft", weighting="cosine", bent_normals=True, slices=3,
                                                      steps=4, slice_sampling="projected_normal"),
            "hard_projected": lambda: torch_ao.BitmaskAO(weighting="cosine", bent_normals=True, slices=3, steps=4,
                                                         slice_sampling="projected_normal"),
            "exact_projected": lambda: torch_ao.BitmaskAO(variant="exact", thickness=BackfaceThickness(), slices=3,
                                                          steps=4, slice_sampling="projected_normal"),
            "soft_segments": lambda: torch_ao.BitmaskAO(variant="exact", union="sectors", mode="soft", slices=3,
                                                        steps=4),
            "ue4ssao": _ue4ssao,
            "pssao": lambda: torch_ao.PSSAO(slices=4, steps=3, fetch="bilinear"),
            "ssao": lambda: torch_ao.SSAO(softness=0.05)}


GRADIENT_METHODS = ("gtao", "hdrp", "hbao", "soft", "soft_backface", "soft_hdrp", "exact", "hard", "indirect",
                    "soft_indirect", "glsl_soft", "gtao_camera", "ue4ssao", "pssao", "ssao", "soft_projected",
                    "hard_projected", "exact_projected", "soft_segments")


def gbuffer_gradients(method: str, device: str, dtype: torch.dtype = torch.float32, backend: str = "auto") -> tuple:
    """``(visibility, d loss / d depth, d loss / d radius or None, d loss / d intrinsics or None)`` of ``method``
    on the rough frame (a back-face layer and a light), loss the sum of the visibility, the indirect light and the
    bent normals."""
    import torch_ao

    camera = method in ("gtao_camera", "ue4ssao", "pssao", "ssao")
    gb = FRAMES["rough"]().to(dtype=dtype)
    m = _gradient_modules()[method]().to(device=device, dtype=dtype)
    m.backend = backend
    depth = gb.depth.to(device).clone().requires_grad_()
    light = torch.rand(2, 3, *gb.depth.shape[-2:], generator=torch.Generator().manual_seed(1)).to(device, dtype)
    cam = gb.camera.to(device=device)
    if camera:
        cam = dataclasses.replace(cam, intrinsics=cam.intrinsics.clone().requires_grad_())
    g = torch_ao.GBuffer(depth=depth, camera=cam, backface_depth=(gb.depth * 1.3).to(device), light=light)
    out = m(g)
    outputs = (out.visibility, out.indirect, out.bent_normal)
    sum(x.sum() for x in outputs if x is not None).backward()
    radius = getattr(m, "radius", None)
    return (out.visibility.detach().cpu(), depth.grad.cpu(), None if radius is None or radius.grad is None
            else radius.grad.cpu(), cam.intrinsics.grad.cpu() if camera else None)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("method", GRADIENT_METHODS)
def test_cuda_gbuffer_gradients_agree_with_the_cpu(built, method):
    """GTAO / HBAO (tao_record_*, tao_backward_*), soft bitmask AO (tao_soft_backward; one scalar thickness and the
    back-face layer; the "hdrp" variant's sector rule and frame) and the exact union with the
    back-face layer (tao_exact_backward) with depth and parameter gradients, soft SSILVB with bent normals (its light
    and bent normals' backward), the ssilvb_glsl shader's soft SSILVB (tao_soft_backward_glsl_short), hard cosine bitmask AO with bent normals
    (tao_hard_backward: the normals' gradient, through the normals from depth), UE4 SSAO and PSSAO
    (tao_backward_wedge, tao_backward_pssao) and SSAO's hemisphere (tao_walk_hemisphere, tao_backward_hemisphere:
    with the radius' gradient) on a CUDA G-buffer against the same call on the CPU; with the intrinsics' gradients
    too for GTAO ("gtao_camera"), UE4 SSAO, PSSAO and SSAO (the backward's g_camera)."""
    reference = gbuffer_gradients(method, "cpu", torch.float64, backend="torch")
    cpu, cuda = (gbuffer_gradients(method, device, backend="kernel") for device in ("cpu", "cuda"))
    for name, ref, on_cpu, on_cuda in zip(("visibility", "depth", "radius", "intrinsics"), reference, cpu, cuda):
        if ref is None:  # (hard masks: no gradient of the radius; UE4 SSAO's is a frozen buffer, PSSAO has none)
            assert on_cpu is None and on_cuda is None, name
            continue
        # float32 rounding, which some methods' decisions amplify (GTAO's hdrp steps, UE4 SSAO's wedges: a few
        # 1e-4 on the CPU too), is what both kernels see against the float64 walk; the GPU's fused multiply-adds
        # round differently, not worse
        e_cpu, e_cuda = relative_error(on_cpu.double(), ref), relative_error(on_cuda.double(), ref)
        assert e_cuda <= max(1e-4, 3 * e_cpu), (name, e_cuda, e_cpu)