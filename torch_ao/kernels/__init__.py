"""Fused kernels for the walk: one pixel's whole walk in registers, SIMD across pixels, on every core.

The tensor-op walk (:mod:`torch_ao.walk`) stays the reference and serves whatever a kernel does
not cover; a kernel is tested against it by tolerance (tests/kernel_agreement.py). Every kernel is one
walk (``walk.h``) for every backend: the CPU (SIMD lanes) and CUDA (NVRTC, one thread per pixel). Covered:

* hard visibility-bitmask AO, the ``"default"`` variant with uniform or cosine sectors, indirect light
  and bent normals (:func:`bitmask_hard`, :func:`bitmask_outputs`); the ``"exact"`` variant's union with
  a thickness of the form ``scale * value + offset`` (:class:`~torch_ao.thickness.ThicknessLayer`) and every
  fetch (:func:`exact_hard`); the ``"ssilvb_glsl"`` variant's
  AO and indirect light (:func:`ssilvb_glsl_hard`);
* soft / straight-through bitmask AO, its indirect light and bent normals, forward and backward, gradients of radius and the thickness model's offset and scale
  (:func:`bitmask_soft`, :func:`soft_outputs`); the ``"ssilvb_glsl"`` variant's too (:func:`ssilvb_glsl_soft`);
* ``GTAO`` (every variant, bent normals too) and ``HBAO`` forward (:func:`gtao_sums`, :func:`hbao_sums`), and
  on CPU their backward: gradients of depth, normals and the parameters (not ``ue4``'s radius, not the
  intrinsics), for either fetch and border (each slice recorded in plain lanes, then the steps that changed
  its state replayed in forward-mode dual lanes, ``lanes_dual.h``; ``walk_grad.py``). See docs/performance.md
  for its cost (``benchmarks/bench_gtao_grad.py --threads 1``);
* ``UE4SSAO``, ``PSSAO`` and ``SSAO`` forward and backward (:func:`ue4_ssao_sums`, :func:`pssao_sums`,
  :func:`hemisphere_visibility`).

C++ sources built on first use with the compiler PyTorch's extensions use (``torch.utils.cpp_extension``)
and cached, CUDA ones on first use with NVRTC; see docs/performance.md for how it was chosen and what it
measures.
"""
from __future__ import annotations

from .build import KernelUnavailable, cpu_kernels
from .bitmask import KernelOutputs, bitmask_hard, bitmask_outputs, exact_covers, exact_hard, kernel_covers, ssilvb_glsl_hard
from .gtao import gtao_covers, gtao_sums, hbao_covers, hbao_sums
from .ssao import hemisphere_visibility, pssao_covers, pssao_sums, ssao_covers, ue4_ssao_covers, ue4_ssao_sums
from .soft_bitmask import bitmask_soft, soft_outputs
from .soft_glsl import ssilvb_glsl_soft
from .dispatch import BACKENDS, KERNELS, kernel_forward

__all__ = ["KernelUnavailable", "cpu_kernels", "bitmask_hard", "bitmask_outputs", "exact_hard", "exact_covers",
           "ssilvb_glsl_hard", "ssilvb_glsl_soft", "KernelOutputs",
           "bitmask_soft", "soft_outputs", "kernel_covers", "gtao_sums", "gtao_covers", "hbao_sums", "hbao_covers", "ue4_ssao_sums",
           "ue4_ssao_covers", "pssao_sums", "pssao_covers", "hemisphere_visibility", "ssao_covers", "BACKENDS",
           "KERNELS", "kernel_forward"]
