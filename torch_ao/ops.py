"""Small differentiable maths shared across methods: one definition each."""
from __future__ import annotations

import math
from typing import Callable

import torch

__all__ = ["fast_acos", "safe_fast_acos", "clamped_gradient", "safe_acos", "safe_pow", "arc_integral", "arc_measure",
           "channel_norm", "normalize_channels", "bent_direction", "UE4_EPSILON"]

#: UE4's GTAO ``rsqrt(|delta|^2 + 1e-4)`` (``SearchForLargestAngleDual``): world units squared
UE4_EPSILON = 1e-4


def fast_acos(x: torch.Tensor) -> torch.Tensor:
    """HDRP's ``GTAOFastAcos`` / UE4's ``acosFast`` / XeGTAO's polynomial ``acos`` ``(...)``, max error
    ~1e-2 rad: ``(pi/2 - 0.156583|x|) sqrt(1-|x|)``, mirrored for ``x < 0``.

    Its gradient is finite everywhere: at ``|x| >= 1``, where the value is exactly 0 or ``pi``, the
    ``sqrt`` (infinite slope at 0) is differentiated as 0.
    """
    ax = x.abs()
    inside = ax < 1
    # sqrt'(0) is infinite: evaluate it on a safe value at |x| >= 1, where the result is exactly 0/pi.
    root = torch.where(inside, torch.sqrt(torch.where(inside, 1 - ax, torch.ones_like(ax))), torch.zeros_like(ax))
    res = (-0.156583 * ax + math.pi / 2) * root
    return torch.where(x >= 0, res, math.pi - res)


def clamped_gradient(fn: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """``fn(x)`` ``(...)`` with the gradient of ``fn(clamp(x, -1 + eps, 1 - eps))`` (the straight-through
    trick): ``fn``'s own slope inside, zero beyond ``1 - eps`` in magnitude, so functions like ``acos``
    whose slope is infinite at ``+-1`` get finite gradients. ``eps`` is 1e-6 in float64, 1e-4 otherwise.
    Without autograd: ``fn(x)``."""
    value = fn(x)
    if not x.requires_grad:
        return value
    eps = 1e-6 if x.dtype == torch.float64 else 1e-4
    soft = fn(x.clamp(-1 + eps, 1 - eps))
    return value.detach() + (soft - soft.detach())


def safe_fast_acos(x: torch.Tensor) -> torch.Tensor:
    """:func:`fast_acos` ``(...)`` with the clamped gradient of :func:`clamped_gradient` (same values)."""
    return clamped_gradient(fast_acos, x)


def safe_acos(x: torch.Tensor) -> torch.Tensor:
    """``acos(clamp(x, -1, 1))`` ``(...)`` with a finite gradient at ``|x| = 1`` (:func:`clamped_gradient`)."""
    return clamped_gradient(lambda t: torch.acos(t.clamp(-1.0, 1.0)), x)


def safe_atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``atan2(y, x)`` ``(...)`` whose gradient at the origin is 0 on every torch release (as a norm's is there; the
    kernels' too): torch 2.13's own atan2 gives 0 there, torch 2.4's NaN."""
    origin = (y == 0) & (x == 0)  # (there atan2 reads detached inputs: where's backward drops its NaN there)
    return torch.atan2(torch.where(origin, y.detach(), y), torch.where(origin, x.detach(), x))


def safe_pow(x: torch.Tensor, power: torch.Tensor) -> torch.Tensor:
    """``x ** power`` for ``x`` in [0, 1] with finite gradients (x is floored at 1e-12)."""
    return x.clamp(1e-12, 1.0) ** power


def arc_integral(h1: torch.Tensor, h2: torch.Tensor, n: torch.Tensor, cos_n: torch.Tensor,
                 sin_n: torch.Tensor) -> torch.Tensor:
    """``int_{h1}^{h2} cos(t - n) |sin t| dt`` ``(...)`` for ``h1 <= 0 <= h2`` (the GTAO paper's slice
    integral; HDRP's ``IntegrateArcCosWeighted`` with its ``cos n``, ``sin n`` passed in, which UE4
    replaces by its own approximations)."""
    return 0.25 * ((-torch.cos(2 * h1 - n) + cos_n + 2 * h1 * sin_n) + (-torch.cos(2 * h2 - n) + cos_n + 2 * h2 * sin_n))


def arc_measure(theta: torch.Tensor, gamma: torch.Tensor) -> torch.Tensor:
    """``H(theta) = int_0^theta cos(t - gamma) |sin t| dt`` ``(...)`` for a signed ``theta``: one side of
    :func:`arc_integral` as a function of its end, the cosine-weighted measure of a slice from ``V``."""
    F = lambda t: -torch.cos(2 * t - gamma) / 4 + t * torch.sin(gamma) / 2  # noqa: E731
    return torch.sign(theta) * (F(theta) - F(torch.zeros_like(theta)))


def bent_direction(sums: torch.Tensor, normals: torch.Tensor, dim: int) -> torch.Tensor:
    """Bent normals from the visible sectors' direction sums ``sums`` (3 components along ``dim``): the sums'
    direction, or ``normals`` (same shape) where a sum is at most 1e-12 long (every sector occluded)."""
    keep = torch.linalg.vector_norm(sums, dim=dim, keepdim=True) > 1e-12
    return torch.where(keep, torch.nn.functional.normalize(sums, dim=dim, eps=1e-12), normals)


def channel_norm(x: torch.Tensor) -> torch.Tensor:
    """The Euclidean norm of ``x`` ``(B,C,H,W)`` over its channels, ``(B,1,H,W)``.

    torch's vector norm over a strided dimension (``x.norm(dim=1)`` of a contiguous ``(B,C,H,W)`` image) is about
    30x slower on the CPU than a sum of squares (26 ms against 0.8 ms at 640x360, one thread); with the channels
    innermost (channels-last) torch's own is the faster and is used. The squares are of ``x`` over its largest
    magnitude (held constant for autograd: the gradient is ``x / norm``, and 0 for a zero vector, as torch's), so
    that none overflows or underflows."""
    if x.stride(1) == 1:
        return torch.linalg.vector_norm(x, dim=1, keepdim=True)
    scale = x.detach().abs().amax(1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)
    return (x / scale).square().sum(1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny).sqrt() * scale


def normalize_channels(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``F.normalize(x, dim=1, eps=eps)`` for ``x`` ``(B,C,H,W)``: ``x / max(|x|, eps)`` by :func:`channel_norm`.

    Its backward is the closed form ``(g - n (g . n)) / |x|`` (``g / eps`` where the norm is clamped), where
    autograd of the quotient differentiates the norm's broadcast and its reduction over the channels (in a
    G-buffer's normals at 640x360, one thread: 10 ms of backward against 13 ms). Twice differentiable."""
    if not (torch.is_grad_enabled() and x.requires_grad):
        return x / channel_norm(x).clamp_min(eps)
    return _NormalizeChannels.apply(x, eps)


class _NormalizeChannels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, eps):
        n = x / channel_norm(x).clamp_min(eps)
        ctx.eps = eps
        ctx.save_for_backward(x, n)
        return n

    @staticmethod
    def backward(ctx, g):
        x, n = ctx.saved_tensors
        # |x| from the input and output (x . n = |x|, or |x|^2 / eps <= eps where clamped): the backward is torch
        # ops of saved inputs and outputs, so autograd differentiates it again
        norm = (x * n).sum(1, keepdim=True).clamp_min(ctx.eps)
        radial = torch.where(norm > ctx.eps, (g * n).sum(1, keepdim=True), 0.0)
        return (g - n * radial) / norm, None
