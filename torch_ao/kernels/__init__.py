"""Fused kernels for the walk: one pixel's whole walk in registers, SIMD across pixels, on every core.

The tensor-op walk (:mod:`torch_ao.marching`) stays the reference and serves whatever a kernel does
not cover; a kernel is tested equal to it. Today, on CPU:

* hard visibility-bitmask AO, the ``"default"`` variant with uniform or cosine sectors, indirect light
  and bent normals (:func:`bitmask_hard`, :func:`bitmask_outputs`), and the ``"ssilvb_glsl"`` variant's
  AO and indirect light (:func:`ssilvb_glsl_hard`);
* soft / straight-through bitmask AO forward and backward, gradients of radius and thickness
  (:func:`bitmask_soft`);
* ``GTAO`` (every variant, bent normals too) and ``HBAO`` forward without gradients (:func:`gtao_sums`,
  :func:`hbao_sums`).

C++ sources built on first use with the compiler PyTorch's extensions use (``torch.utils.cpp_extension``)
and cached; see docs/performance.md for how it was chosen and what it measures.
"""
from __future__ import annotations

from .build import KernelUnavailable, cpu_kernels
from .bitmask import KernelOutputs, bitmask_hard, bitmask_outputs, kernel_covers, ssilvb_glsl_hard
from .gtao import gtao_covers, gtao_sums, hbao_covers, hbao_sums
from .soft_bitmask import bitmask_soft
from .dispatch import BACKENDS, KERNELS, kernel_forward

__all__ = ["KernelUnavailable", "cpu_kernels", "bitmask_hard", "bitmask_outputs", "ssilvb_glsl_hard", "KernelOutputs",
           "bitmask_soft", "kernel_covers", "gtao_sums", "gtao_covers", "hbao_sums", "hbao_covers", "BACKENDS",
           "KERNELS", "kernel_forward"]
