"""What every kernel reads of a G-buffer: channel-last float32 images, the inverse depth, the intrinsics."""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer

__all__ = ["LANES", "channels_last", "walk_inputs", "light_input", "scale_derivative"]

#: the kernels' lane types: ``"simd"`` (the CPU's vector lanes, the default) or ``"scalar"`` (one pixel at a
#: time in float lanes: the arithmetic of the CUDA kernel, which compiles the same walk)
LANES = ("simd", "scalar")


def channels_last(x: torch.Tensor) -> torch.Tensor:
    """``(B,C,H,W)`` -> contiguous ``(B,H,W,C)`` float32."""
    return x.permute(0, 2, 3, 1).to(torch.float32).contiguous()


def walk_inputs(gbuffer: GBuffer, normals: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Channel-last positions and normals ``(B,H,W,3)``, the inverse depth and the depth (both NaN where
    invalid: the kernels read a texel's validity from the one they fetch), validity ``(B,H,W)``, and the
    intrinsics ``(B,4)`` ``(fx, fy, cx, cy)`` in pixels."""
    safe = gbuffer.safe_depth[:, 0].to(torch.float32)
    valid = gbuffer.valid[:, 0].contiguous()
    depth = torch.where(valid, safe, torch.nan)
    inverse = torch.where(valid, safe.reciprocal(), torch.nan)
    cam = gbuffer.camera
    intrinsics = torch.stack((cam.fx, cam.fy, cam.cx, cam.cy), -1).to(torch.float32).contiguous()
    return channels_last(gbuffer.positions()), channels_last(normals), inverse, depth, valid, intrinsics


def light_input(gbuffer: GBuffer, wanted: bool) -> torch.Tensor:
    """The direct light channel-last ``(B,H,W,3)``, or an empty tensor when not ``wanted``; a ``ValueError``
    naming ``gbuffer.light`` when it is wanted and missing."""
    if not wanted:
        return torch.empty(0)
    if gbuffer.light is None:
        raise ValueError("gbuffer.light: indirect light needs a (B,3,H,W) direct-light buffer")
    return channels_last(gbuffer.light)


def scalar_lanes(lanes: str) -> bool:
    """Whether ``lanes`` (one of :data:`LANES`) asks for the scalar lanes; a ``ValueError`` naming it otherwise."""
    if lanes not in LANES:
        raise ValueError(f"lanes: expected one of {LANES}, got {lanes!r}")
    return lanes == "scalar"


def scale_derivative(valid: torch.Tensor, *pairs: tuple[torch.Tensor, torch.Tensor | None]) -> torch.Tensor:
    """``sum(dL/dx * x)`` over ``pairs`` of a gradient and its world-unit input ``x`` (positions, depth: ``+x``;
    the inverse depth: pass ``-x``), on the ``valid`` ``(B,H,W)`` texels (elsewhere the inputs hold NaN), in
    float64: d L / d s of the scene scaled by ``s`` at ``s = 1``, which the walks' scale invariance turns into
    the radius' gradient (Euler's identity)."""
    total = torch.zeros((), dtype=torch.float64, device=valid.device)
    for g, x in pairs:
        mask = valid if g.dim() == valid.dim() else valid[..., None]
        total = total + torch.where(mask, g.double() * x.double(), 0.0).sum()
    return total
