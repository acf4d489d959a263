"""Crytek-style SSAO with a normal-oriented hemisphere kernel (Mittring 2007; the normal-oriented
kernel and range check of Chapman 2013 / LearnOpenGL).

A seeded random kernel of ``samples`` points in the unit hemisphere ``z > 0`` (direction uniform in
``x, y in [-1, 1], z in [0, 1]``, length uniform in [0, 1), scaled by ``lerp(0.1, 1, (i/K)^2)`` so that
more samples lie near the centre) is oriented along each pixel's normal (tangent frame rotated per pixel
by interleaved gradient noise when ``jitter``) and scaled by ``radius``. Each kernel point ``S`` is
projected with the camera; the depth buffer is read there (the core's fetch: nearest/bilinear,
border clamp/drop); with ``z_s`` the depth of ``S`` and ``z_b`` the buffer's depth::

    occluded   = z_s - z_b >= bias                          (the surface is in front of S by bias)
    rangeCheck = smoothstep(0, 1, radius / |z_p - z_b|)      (z_p: the pixel's depth)
    visibility = 1 - (1/K) sum_k occluded_k * rangeCheck_k

``softness > 0`` (an improvement, off by default) replaces the step by
``sigmoid((z_s - z_b - bias) / softness)`` so that depth gets a gradient through the comparison; with
the hard step only ``rangeCheck`` and the fetched positions carry gradients, and ``bias``, which then
has none, is a buffer rather than a parameter. Samples that are invalid
(background, dropped at the border, behind the camera) occlude nothing. Visibility is in [0, 1] by
construction.

This is not a slice walk: :func:`kernel_occlusion` samples the kernel with the walk's fetch
(:func:`~torch_ao.walk.fetch_sample`) and its chunking and recomputation (:func:`~torch_ao.walk.march_chunks`).
The fused kernel (:func:`torch_ao.kernels.ssao.hemisphere_visibility`) computes the same, this being its
specification.
"""
from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from ..camera import view_to_pixels
from ..options import Option
from ..walk import Frame, Queries, fetch_sample, interleaved_gradient_noise, march_chunks
from .base import ScreenSpaceAO
from .common import RADIUS, Sampling, declare_signature, functional_twin, register_parameters

__all__ = ["SSAO", "ssao", "hemisphere_kernel", "hemisphere_table", "kernel_points", "kernel_occlusion"]


def hemisphere_kernel(samples: int, seed: int = 0) -> torch.Tensor:
    """``(samples, 3)`` float64 points in the unit hemisphere ``z > 0``, denser near the origin."""
    g = torch.Generator().manual_seed(int(seed))
    u = torch.rand(samples, 3, generator=g, dtype=torch.float64)
    d = torch.stack((u[:, 0] * 2 - 1, u[:, 1] * 2 - 1, u[:, 2].clamp_min(1e-3)), -1)
    d = d / d.norm(dim=-1, keepdim=True)
    length = torch.rand(samples, generator=g, dtype=torch.float64)
    i = torch.arange(samples, dtype=torch.float64) / samples
    scale = 0.1 + 0.9 * i.square()
    return d * (length * scale)[:, None]


@torch.compiler.assume_constant_result
def hemisphere_table(samples: int, seed: int = 0) -> tuple[float, ...]:
    """:func:`hemisphere_kernel`'s points as the fused walk reads them: ``x, y, z`` of each, float32 values.
    ``torch.compile`` calls it while tracing and keeps the result as constants (a tensor's ``tolist`` would
    break the graph)."""
    return _hemisphere_table(int(samples), int(seed))


@functools.lru_cache(maxsize=64)
def _hemisphere_table(samples: int, seed: int) -> tuple[float, ...]:
    return tuple(hemisphere_kernel(samples, seed).to(torch.float32).flatten().tolist())


def _tangent_frame(q: Queries, jitter: bool, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(N,3)`` unit tangent and bitangent around each query's normal, rotated by noise when ``jitter``."""
    n = q.normal
    if jitter:
        alpha = 2 * math.pi * interleaved_gradient_noise(q.u, q.v, seed).to(q.u.dtype)
    else:
        alpha = torch.zeros_like(q.u)
    r = torch.stack((torch.cos(alpha), torch.sin(alpha), torch.zeros_like(alpha)), -1)
    t = r - n * (r * n).sum(-1, keepdim=True)
    alt = torch.zeros_like(r)
    alt[:, 2] = 1.0
    t_alt = alt - n * (alt * n).sum(-1, keepdim=True)
    t = torch.where(t.norm(dim=-1, keepdim=True) > 1e-3, t, t_alt)
    t = F.normalize(t, dim=-1, eps=1e-12)
    return t, torch.cross(n, t, dim=-1)


def kernel_points(q: Queries, kernel: torch.Tensor, jitter: bool, seed: int) -> torch.Tensor:
    """``(N,K,3)`` view-space kernel points: ``kernel`` ``(K,3)`` (world units, ``z`` along the normal)
    in each query's tangent frame around its position."""
    t, b = _tangent_frame(q, jitter, seed)
    return q.position[:, None] + kernel[None, :, 0:1] * t[:, None] + kernel[None, :, 1:2] * b[:, None] \
        + kernel[None, :, 2:3] * q.normal[:, None]


def kernel_occlusion(frame: Frame, q: Queries, module: "SSAO") -> dict[str, torch.Tensor]:
    """SSAO's visibility ``{"visibility": (N,1)}`` at the queries ``q`` (see the module docstring)."""
    dtype = q.depth.dtype
    S = kernel_points(q, module.kernel.to(dtype) * module.radius.to(dtype), module.jitter, module.seed)  # (N,K,3)
    d = (-S[..., 2]).clamp_min(1e-6 * q.depth.detach()[:, None])  # behind the camera: invalid below
    b = q.batch[:, None]
    u, v = view_to_pixels(S, d, frame.fx[b], frame.fy[b], frame.cx[b], frame.cy[b])
    offsets = torch.stack((u - q.u[:, None], v - q.v[:, None]), -1)  # (N,K,2)
    R = module.radius.to(dtype)
    occ = torch.zeros_like(q.depth)
    for k in range(S.shape[1]):
        sample = fetch_sample(frame, q, None, 1, k, offsets[:, k], fetch=module.fetch, border=module.border)
        z_s = -S[:, k, 2]
        z_b = -sample.position[:, 2]
        diff = z_s - z_b - module.bias.to(dtype)
        if module.softness > 0:
            occluded = torch.sigmoid(diff / module.softness)
        else:
            occluded = (diff >= 0).to(dtype) + 0 * diff  # a step: zero (not missing) gradient to depth and bias
        x = (R / (q.depth - z_b).abs().clamp_min(1e-12 * R.detach().clamp_min(1e-30))).clamp(0.0, 1.0)
        range_check = x * x * (3 - 2 * x)
        ok = sample.valid & (z_s > 1e-6 * q.depth)
        occ = occ + torch.where(ok, occluded * range_check, torch.zeros_like(occ))
    return {"visibility": 1 - occ[:, None] / module.samples}


@declare_signature
class SSAO(ScreenSpaceAO):
    """Crytek-style SSAO with a normal-oriented hemisphere kernel; see the module docstring and :meth:`options`."""

    OPTIONS = (
        Option("samples", None, "Kernel size K (default 2 x slices x steps: 18 with the default high preset's 3 x 3, the "
               "same number of depth fetches as the slice methods)", kind=int, minimum=1),
        RADIUS,
        Option("bias", 0.025, "Depth bias: a kernel point is occluded when the surface is this much in front of it "
               "(LearnOpenGL's 0.025)", unit="world units", fitted=True),
        Option("softness", 0.0, "> 0: the occlusion step becomes a logistic of this width, so depth gets a gradient "
               "through the comparison (0: the hard step)", unit="world units", minimum=0.0),
    )
    SAMPLING = Sampling.options_for(("preset", "slices", "steps", "jitter", "seed", "fetch", "border"))
    has_kernel = "ssao"  # forward and backward in torch_ao.kernels (ssao_covers says which calls)

    def __init__(self, **options) -> None:
        super().__init__(**options)
        v = self.values
        self.softness = float(v["softness"])
        self.samples = 2 * self.slices * self.steps if v["samples"] is None else v["samples"]
        self.register_buffer("kernel", hemisphere_kernel(self.samples, self.seed).to(torch.get_default_dtype()),
                             persistent=False)
        register_parameters(self, self.options(), v, ("bias",), trainable=self.trainable,
                            frozen=self.no_gradient_options)

    def no_gradient(self, values):
        if float(values["softness"]) == 0:
            return {"bias": "the hard occlusion step (softness 0) has no gradient: give softness > 0 to fit it"}
        return {}

    def kernel_table(self) -> tuple[float, ...]:
        """``kernel``'s points as the fused walk reads them (:func:`hemisphere_table`): ``3 K`` floats."""
        return hemisphere_table(self.samples, self.seed)

    def walk(self, frame, chunk_size, recompute):
        return march_chunks(frame, functools.partial(kernel_occlusion, module=self), chunk_size=chunk_size,
                            recompute=recompute)

    def extra_repr(self) -> str:
        return f"samples={self.samples}, fetch={self.fetch!r}, border={self.border!r}"


ssao = functional_twin(SSAO, "ssao")
