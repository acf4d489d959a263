"""The soft / straight-through bitmask AO kernel: ``BitmaskAO(variant="default", mode="soft" | "straight_through")``
forward and backward in fused passes, differentiable with respect to the scalar ``radius`` and ``thickness``.

The forward is the tensor path's visibility (soft coverage of :mod:`torch_ao.sectors.soft_union`, or the
hard coverage in straight-through mode); the backward walks every pixel again and runs the soft union's
reverse scan in registers, so forward+backward keep nothing per sample: their memory is the G-buffer's
(channel-last copies) and the output. Gradients of the G-buffer (depth, normals, intrinsics) are not
computed: such a call runs the tensor path (:func:`kernel_covers` says why).
"""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer
from ..sectors import ROUNDINGS
from .bitmask import options_uncovered
from .frame import walk_inputs
from .build import cpu_kernels

__all__ = ["bitmask_soft", "kernel_covers", "module_forward"]

_OP = "torch_ao_kernels::soft_bitmask"
#: the op's arguments after its eight tensors, in order
_SETTINGS = ("slices", "steps", "step_power", "min_step_px", "jitter", "seed", "bilinear", "drop", "rounding",
             "epsilon", "tau", "cosine")


def bitmask_soft(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: torch.Tensor,
                 thickness: torch.Tensor, tau: float, weighting: str = "uniform", straight_through: bool = False,
                 step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True, seed: int = 0,
                 fetch: str = "bilinear", border: str = "drop", rounding: str = "ceil",
                 sector_epsilon: float = 0.01) -> torch.Tensor:
    """Soft (or straight-through) bitmask visibility ``(B,1,H,W)`` in ``[0, 1]`` (background pixels 1),
    differentiable with respect to ``radius`` and ``thickness``.

    Args:
        gbuffer: a float32 CPU G-buffer without gradients; normals: its ``(B,3,H,W)`` unit view-space
            normals (without gradients).
        slices, steps: directions per pixel and samples per side.
        radius, thickness: 0-d float tensors, world units (``nn.Parameter``\\ s get gradients).
        tau: temperature of the soft masks (sectors, > 0); weighting: ``"uniform"`` or ``"cosine"``;
            straight_through: hard coverage in the forward, the soft gradient in the backward.
        step_power, min_step_px (pixels), jitter, seed, fetch, border, rounding, sector_epsilon (sectors):
            as :class:`~torch_ao.BitmaskAO`.

    Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built here, and
    ``ValueError`` naming ``gbuffer``/``normals`` when they carry a gradient (the kernel does not compute it).
    """
    ops = cpu_kernels()
    _register_autograd()
    if torch.is_grad_enabled() and (normals.requires_grad or gbuffer.depth.requires_grad or (
            gbuffer.position is not None and gbuffer.position.requires_grad)):
        raise ValueError("gbuffer/normals: the soft kernel differentiates radius and thickness only; "
                         "detach the G-buffer or use backend='torch'")
    scalars = []
    for name, t in (("radius", radius), ("thickness", thickness)):
        t = torch.as_tensor(t)
        if t.dim() != 0:
            raise ValueError(f"{name}: expected a 0-d tensor, got shape {tuple(t.shape)}")
        scalars.append(t)
    return ops.soft_bitmask(*walk_inputs(gbuffer, normals), *scalars, int(slices), int(steps), float(step_power),
                            float(min_step_px), bool(jitter), int(seed), fetch == "bilinear", border == "drop",
                            ROUNDINGS.index(rounding), float(sector_epsilon), float(tau), weighting == "cosine",
                            bool(straight_through))[0]


def _setup_context(ctx, inputs, output):
    ctx.save_for_backward(output[1], *inputs[:8])  # the forward's marks of the live steps, then its tensors
    ctx.settings = inputs[8:8 + len(_SETTINGS)]


def _backward(ctx, grad, _):
    live, *tensors = ctx.saved_tensors
    g_radius, g_thickness = torch.ops.torch_ao_kernels.soft_bitmask_backward(grad, live, *tensors, *ctx.settings)
    return (None,) * 6 + (g_radius, g_thickness) + (None,) * (len(_SETTINGS) + 1)


_registered = False


def _register_autograd() -> None:
    """The op's backward: :func:`_backward` (the walk again, no stored samples). Once, after the build."""
    global _registered
    if not _registered:
        torch.library.register_autograd(_OP, _backward, setup_context=_setup_context)
        _registered = True


#: options of a module the soft kernel reproduces (beyond the hard kernel's): the modes and weightings (hard
#: mode is the straight-through forward without a graph: the hard kernel's masks with cosine weights too)
_MODES = ("hard", "soft", "straight_through")
_WEIGHTINGS = ("uniform", "cosine")


def kernel_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`bitmask_soft` computes ``module(gbuffer)`` and its gradients (a ``BitmaskAO``
    in soft or straight-through mode, or hard mode, whose masks have none), else why not: the hard kernel's options (any slices, steps, radius,
    jitter, rounding, fetch, border... one scalar thickness, visibility only, a float32 CPU G-buffer) with
    either weighting, and no gradient asked of the G-buffer (depth, position, normals, intrinsics)."""
    reason = options_uncovered(module, gbuffer, modes=_MODES, weightings=_WEIGHTINGS)
    if reason is not None:
        return reason
    if torch.is_grad_enabled():
        cam = gbuffer.camera
        buffers = [gbuffer.depth, gbuffer.normals, gbuffer.position, cam.fx, cam.fy, cam.cx, cam.cy]
        if any(t is not None and t.requires_grad for t in buffers):
            return "a gradient of the G-buffer (the kernel differentiates radius and thickness only)"
    return None


def module_forward(module, gbuffer: GBuffer) -> torch.Tensor:
    """``module(gbuffer).visibility`` by :func:`bitmask_soft` (a call :func:`kernel_covers` accepts)."""
    hard = module.mode == "hard"  # hard masks have no gradient: no graph
    radius, thickness = (module.radius.detach(), module.thickness.detach()) if hard else (module.radius, module.thickness)
    return bitmask_soft(gbuffer, gbuffer.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                        radius=radius, thickness=thickness, tau=module.tau, weighting=module.weighting,
                        straight_through=module.mode != "soft", step_power=module.step_power,
                        min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, fetch=module.fetch,
                        border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon)
