"""Fused kernels for the walk: one pixel's whole walk in registers, SIMD across pixels, on every core.

The tensor-op walk (:mod:`torch_ao.marching`) stays the reference and serves whatever a kernel does
not cover; a kernel is tested equal to it. Today: hard visibility-bitmask AO on CPU, the
``"default"`` variant with uniform or cosine sectors, indirect light and bent normals
(:func:`bitmask_hard`, :func:`bitmask_outputs`) and the ``"ssilvb_glsl"`` variant's AO and indirect
light (:func:`ssilvb_glsl_hard`), a C++ source built on first use with
the compiler PyTorch's extensions use (``torch.utils.cpp_extension``) and cached; see
docs/performance.md for how it was chosen and what it measures.
"""
from __future__ import annotations

from .build import KernelUnavailable, cpu_kernels
from .bitmask import KernelOutputs, bitmask_hard, bitmask_outputs, kernel_covers, ssilvb_glsl_hard
from .dispatch import BACKENDS, kernel_forward

__all__ = ["KernelUnavailable", "cpu_kernels", "bitmask_hard", "bitmask_outputs", "ssilvb_glsl_hard", "KernelOutputs",
           "kernel_covers", "BACKENDS", "kernel_forward"]
