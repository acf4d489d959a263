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
the hard step only ``rangeCheck`` and the fetched positions carry gradients. Samples that are invalid
(background, dropped at the border, behind the camera) occlude nothing. Visibility is in [0, 1] by
construction.

This is not a slice walk, but it runs on the core: :class:`HemispherePattern` is a
:class:`~torch_ao.marching.SamplingPattern` with one "slice" whose steps are the projected kernel points,
so fetching, chunking and recomputation are the core's.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..gbuffer import GBuffer
from ..marching import (BORDER_MODES, FETCH_MODES, SamplingPattern, interleaved_gradient_noise,
                        tangent_from_view_azimuth)
from .base import AOOutput, ScreenSpaceAO, make_parameter
from .gtao import check_choice, run_functional, with_base_signature

__all__ = ["SSAO", "ssao", "hemisphere_kernel", "HemispherePattern"]


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


class HemispherePattern(SamplingPattern):
    """One slice, one side; step ``k`` is the screen offset of kernel point ``k``."""

    sides = (1,)

    def __init__(self, module: "SSAO", frame) -> None:
        check_choice("fetch", module.fetch, FETCH_MODES)
        check_choice("border", module.border, BORDER_MODES)
        self.m, self.frame = module, frame
        self.num_slices, self.fetch, self.border = 1, module.fetch, module.border

    def slice_tangent(self, frame, q, s):
        # The walk starts here: drop points cached by an earlier walk (a recomputation in backward
        # must rebuild them inside its own graph).
        self._cache = None
        return tangent_from_view_azimuth(q, torch.zeros_like(q.u))  # any; SSAO ignores the slice frame

    def points(self, q, k: int) -> torch.Tensor:
        """``(N,3)`` view-space kernel point ``k`` of every query pixel (cached per query list, so the
        walk's offsets and the accumulator's comparisons share one computation)."""
        cache = getattr(self, "_cache", None)
        if cache is None or cache[0] is not q:
            t, b = self._frame_axes(q)
            kernel = self.m.kernel.to(q.depth.dtype) * self.m.radius.to(q.depth.dtype)  # (K,3)
            pts = q.position[:, None] + kernel[None, :, 0:1] * t[:, None] + kernel[None, :, 1:2] * b[:, None] \
                + kernel[None, :, 2:3] * q.normal[:, None]  # (N,K,3)
            self._cache = cache = (q, pts)
        return cache[1][:, k]

    def _frame_axes(self, q):
        n = q.normal
        if self.m.jitter:
            alpha = 2 * math.pi * interleaved_gradient_noise(q.u, q.v, self.m.seed).to(q.u.dtype)
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

    def step_offsets(self, q, geom, side):
        f = self.frame
        b = q.batch[:, None]
        self.points(q, 0)
        S = self._cache[1]  # (N,K,3)
        d = (-S[..., 2]).clamp_min(1e-6 * q.depth.detach()[:, None])  # behind the camera: invalid in the accumulator
        u = S[..., 0] / d * f.fx[b] + f.cx[b]
        v = -S[..., 1] / d * f.fy[b] + f.cy[b]
        offsets = torch.stack((u - q.u[:, None], v - q.v[:, None]), -1)  # (N,K,2)
        return list(offsets.unbind(1))


class SSAOAccumulator:
    def __init__(self, module: "SSAO", pattern: HemispherePattern) -> None:
        self.m, self.pattern = module, pattern

    def begin_slice(self, q, geom):
        return torch.zeros_like(q.depth)

    def step(self, occ, q, geom, sample):
        m = self.m
        dtype = q.depth.dtype
        S = self.pattern.points(q, sample.step)
        z_s = -S[:, 2]
        z_b = -sample.position[:, 2]
        diff = z_s - z_b - m.bias.to(dtype)
        if m.softness > 0:
            occluded = torch.sigmoid(diff / m.softness)
        else:
            occluded = (diff >= 0).to(dtype) + 0 * diff  # a step: zero (not missing) gradient to depth and bias
        R = m.radius.to(dtype)
        x = (R / (q.depth - z_b).abs().clamp_min(1e-12 * R.detach().clamp_min(1e-30))).clamp(0.0, 1.0)
        range_check = x * x * (3 - 2 * x)
        ok = sample.valid & (z_s > 1e-6 * q.depth)
        return occ + torch.where(ok, occluded * range_check, torch.zeros_like(occ))

    def end_slice(self, occ, q, geom):
        return {"occ": occ[:, None]}

    def finish(self, sums, q, num_slices):
        return {"visibility": 1 - sums["occ"] / self.m.samples}


@with_base_signature
class SSAO(ScreenSpaceAO):
    """Crytek-style SSAO with a normal-oriented hemisphere kernel; see the module docstring.

    Args:
        samples: kernel size ``K`` (default ``2 * slices * steps``, i.e. 64 with the default 4 x 8, the
            same number of depth fetches as the slice methods).
        radius: kernel radius in world units (parameter).
        bias: depth bias in world units (parameter; LearnOpenGL's 0.025).
        softness: > 0 replaces the occlusion step by a logistic of this width (world units).
        seed: seeds the kernel and the per-pixel rotation.
        fetch, border: default bilinear / drop.
    """

    unused_base_arguments = ("azimuth", "step_power", "min_step_px")

    def __init__(self, *, samples: int | None = None, radius: float = 1.0, bias: float = 0.025, softness: float = 0.0,
                 trainable: bool = True, **kwargs) -> None:
        for name in self.unused_base_arguments:
            if name in kwargs:
                raise ValueError(f"{name}: not used by SSAO (it samples a hemisphere kernel, not slices)")
        if not (isinstance(softness, (int, float)) and softness >= 0):
            raise ValueError(f"softness: expected a number >= 0, got {softness!r}")
        self.softness = float(softness)
        super().__init__(radius=radius, trainable=trainable, **kwargs)
        if samples is None:
            samples = 2 * self.slices * self.steps
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise ValueError(f"samples: expected an integer >= 1, got {samples!r}")
        self.samples = samples
        self.register_buffer("kernel", hemisphere_kernel(samples, self.seed).to(torch.get_default_dtype()),
                             persistent=False)
        make_parameter(self, "bias", bias, trainable=trainable)
        if self.bias.dim() != 0:
            raise ValueError(f"bias: expected a scalar, got shape {tuple(self.bias.shape)}")

    def pattern_for(self, frame):
        if frame is None:  # construction-time validation
            check_choice("fetch", self.fetch, FETCH_MODES)
            check_choice("border", self.border, BORDER_MODES)
            return None
        self._pattern = (frame, HemispherePattern(self, frame))
        return self._pattern[1]

    def accumulator(self, frame):
        cached = getattr(self, "_pattern", None)
        pattern = cached[1] if cached is not None and cached[0] is frame else HemispherePattern(self, frame)
        self._pattern = None
        return SSAOAccumulator(self, pattern)

    def extra_repr(self) -> str:
        return f"samples={self.samples}, fetch={self.fetch!r}, border={self.border!r}"


def ssao(gbuffer: GBuffer, *, radius=1.0, bias=0.025, **options) -> AOOutput:
    """Functional :class:`SSAO`: float arguments may be tensors (gradients flow to them)."""
    return run_functional(SSAO, gbuffer, dict(radius=radius, bias=bias), **options)
