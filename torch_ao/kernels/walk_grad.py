"""The one walk with a backward: GTAO's exact variant as a ``torch.autograd.Function`` over the walk's
channel-last inputs (positions, normals, inverse depth, depth), so that autograd chains its gradients to
the G-buffer through :func:`~torch_ao.kernels.frame.walk_inputs`' torch ops.

The backward (``torch_ao_kernels::walk_backward``, walk_grad_cpu.cpp) walks again in dual lanes
(lanes_dual.h): forward-mode tangents on each pixel's own position, normal and depth, and on each
horizon's winning sample, whose taps it scatters into (bilinear: the inverse depth of its four taps;
nearest: the tap's position).

The radius needs no tangent of its own: the walk is scale-invariant (scaling positions, depth and every
length setting by s leaves its outputs as they are: screen positions, angles and the falloff ratio do not
change; step settings are in pixels), so for L = sum(grad * out) Euler's identity gives
``R dL/dR = -sum(dL/dP . P + dL/ddepth depth - dL/dinverse inverse)`` over the walk's inputs.
"""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer
from .build import cpu_kernels, grad_kernels
from .frame import scalar_lanes
from .launch import packed_inputs

__all__ = ["differentiable_walk", "wants_gradient"]


class _Walk(torch.autograd.Function):
    """``walk(accumulator, positions, normals, inverse, depth, ...)`` ``(B,C,H,W)`` and its backward."""

    @staticmethod
    def forward(ctx, accumulator, positions, normals, inverse, depth, valid, intrinsics, ints, floats, channels,
                scalar, radius):
        none = torch.empty(0)
        ctx.accumulator, ctx.scalar = accumulator, scalar
        ctx.save_for_backward(positions, normals, inverse, depth, valid, intrinsics, ints, floats, radius)
        return cpu_kernels().walk(accumulator, positions, normals, inverse, depth, valid, intrinsics, none, none,
                                  none, ints, floats, channels, scalar)

    @staticmethod
    def backward(ctx, grad):
        positions, normals, inverse, depth, valid, intrinsics, ints, floats, radius = ctx.saved_tensors
        g_pos, g_nrm, g_inv, g_depth = grad_kernels().walk_backward(
            ctx.accumulator, grad.to(torch.float32).contiguous(), positions, normals, inverse, depth, valid,
            intrinsics, ints, floats, ctx.scalar)
        g_radius = None
        if ctx.needs_input_grad[-1]:  # Euler's identity (module docstring); invalid texels hold NaN
            along = (g_pos * positions).sum() + (g_depth * depth).sum() - torch.where(valid, g_inv * inverse, 0.0).sum()
            g_radius = (-along / radius).to(radius.dtype)
        return None, g_pos, g_nrm, g_inv, g_depth, None, None, None, None, None, None, g_radius


def wants_gradient(gbuffer: GBuffer, normals: torch.Tensor, radius=None) -> bool:
    """Whether autograd records through the walk's inputs (grad mode on, the depth, normals or the
    ``radius`` tensor requiring it)."""
    return torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad
                                           for t in (gbuffer.depth, gbuffer.normals, gbuffer.position, normals, radius))


def differentiable_walk(accumulator: str, gbuffer: GBuffer, normals: torch.Tensor,
                        settings: tuple[list[int], list[float]], acc_ints: list, acc_floats: list, channels: int,
                        *, radius: torch.Tensor | float, lanes: str = "simd") -> torch.Tensor:
    """:func:`~torch_ao.kernels.launch.run_walk` on a CPU G-buffer with autograd history: gradients reach
    ``gbuffer``'s depth, normals (and position buffer) through the walk's inputs. ``accumulator``:
    ``"gtao"`` (the exact variant, bilinear fetch, dropped border). ``radius``: the 0-d tensor every length
    setting is proportional to (GTAO's radius), which receives its gradient, or a number."""
    inputs, _, ints, floats = packed_inputs(gbuffer, normals, settings, acc_ints, acc_floats)
    radius = torch.as_tensor(radius)
    return _Walk.apply(accumulator, *inputs, ints, floats, int(channels), scalar_lanes(lanes), radius)
