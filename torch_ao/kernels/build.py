"""Building the C++ kernels on first use (``torch.utils.cpp_extension``), cached per CPU capability."""
from __future__ import annotations

import functools
import os
from pathlib import Path

import torch

__all__ = ["KernelUnavailable", "cpu_kernels"]

#: the C++ sources of the one extension (each registers its ops in ``torch_ao_kernels``; walk_cpu.h,
#: the walk they share, is included by them)
_SOURCES = tuple(Path(__file__).with_name(name) for name in ("bitmask_cpu.cpp", "gtao_cpu.cpp",
                                                             "soft_bitmask_cpu.cpp"))

#: compiler flags per ``torch.backends.cpu.get_cpu_capability()``: the kernel's ``Vectorized<float>``
#: must be the width torch's own CPU kernels dispatch to, so that both call the same SLEEF functions
_CAPABILITY_FLAGS = {
    "AVX512": ["-mavx512f", "-mavx512bw", "-mavx512vl", "-mavx512dq", "-mfma", "-DCPU_CAPABILITY=AVX512",
               "-DCPU_CAPABILITY_AVX512"],
    "AVX2": ["-mavx2", "-mfma", "-DCPU_CAPABILITY=AVX2", "-DCPU_CAPABILITY_AVX2"],
}


class KernelUnavailable(RuntimeError):
    """A kernel cannot run here (no C++ compiler, a failed build, an unsupported device)."""


@functools.lru_cache(maxsize=None)
def cpu_kernels():
    """The ``torch.ops.torch_ao_kernels`` namespace, building the C++ source on first use.

    Raises :class:`KernelUnavailable` when it cannot be built (the message says why). The build
    (about a minute, once per source version and CPU capability) is cached in
    ``$TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``).
    """
    from torch.utils import cpp_extension

    capability = torch.backends.cpu.get_cpu_capability()
    # -fopenmp: ATen's parallel_for is a header template, threaded only where the including code is
    # built with OpenMP (as Inductor builds its kernels); without it the walk runs on one thread
    flags = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fopenmp"] + _CAPABILITY_FLAGS.get(capability, [])
    vml = torch.backends.mkl.is_available()  # torch.cos/sin then use MKL's vector math: the kernel too
    if vml:
        flags.append("-DTORCH_AO_MKL_VML")
    name = f"torch_ao_kernels_{capability.lower()}{'_vml' if vml else ''}"
    try:
        cpp_extension.load(name=name, sources=[str(p) for p in _SOURCES], extra_cflags=flags, extra_ldflags=["-fopenmp"],
                           is_python_module=False,
                           verbose=bool(os.environ.get("TORCH_AO_KERNELS_VERBOSE")))
    except Exception as exc:  # no compiler, missing headers, a failed build...
        raise KernelUnavailable(f"the C++ kernels could not be built ({type(exc).__name__}: "
                                f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else exc})") from exc
    _register_fake()
    return torch.ops.torch_ao_kernels


def _register_fake() -> None:
    """Shapes of the kernels' outputs for tracing (``torch.compile`` calls the op as one graph node)."""

    @torch.library.register_fake("torch_ao_kernels::bitmask_walk")
    def _(positions, *args):
        B, H, W, _ = positions.shape
        indirect, bent = args[-2:]
        return (positions.new_empty(B, 1, H, W), positions.new_empty(B if indirect else 0, 3, H, W),
                positions.new_empty(B if bent else 0, 3, H, W))

    @torch.library.register_fake("torch_ao_kernels::glsl_walk")
    def _(positions, *args):
        B, H, W, _ = positions.shape
        return positions.new_empty(B, 1, H, W), positions.new_empty(B if args[-1] else 0, 3, H, W)

    @torch.library.register_fake("torch_ao_kernels::gtao_sums")
    def _(positions, *args):
        B, H, W, _ = positions.shape
        return positions.new_empty(B, H, W, 5 if args[-1] else 2)  # args[-1]: bent normals

    @torch.library.register_fake("torch_ao_kernels::hbao_sums")
    def _(positions, *args):
        B, H, W, _ = positions.shape
        return positions.new_empty(B, H, W, 1)

    @torch.library.register_fake("torch_ao_kernels::soft_bitmask")
    def _(positions, normals, inverse_depth, depth, valid, intrinsics, radius, thickness, slices, steps, *args):
        B, H, W, _ = positions.shape  # the visibility, and one byte per 16 pixels, slice and step (live steps)
        return positions.new_empty(B, 1, H, W), positions.new_empty(B, H, -(-W // 16), slices, 2 * steps,
                                                                      dtype=torch.uint8)

    @torch.library.register_fake("torch_ao_kernels::soft_bitmask_backward")
    def _(grad, live, positions, normals, inverse_depth, depth, valid, intrinsics, radius, thickness, *args):
        return radius.new_empty(()), thickness.new_empty(())
