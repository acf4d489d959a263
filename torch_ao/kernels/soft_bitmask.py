"""The soft / straight-through bitmask AO kernel: ``BitmaskAO(variant="default", mode="soft" | "straight_through")``
on the one walk (``walk.h`` with ``soft.h``'s accumulator), differentiable with respect to the scalar ``radius``
and ``thickness``.

The forward is the tensor path's visibility (soft coverage of :mod:`torch_ao.sectors.soft_union`, or the
hard coverage in straight-through mode). When a gradient is wanted, the same walk also returns each pixel's
derivatives of its visibility with respect to radius and thickness (the soft union's reverse scan per slice,
in registers), and the backward is their sum weighted by the upstream gradient: nothing is kept per sample,
two channels per pixel. Gradients of the G-buffer (depth, normals, intrinsics) are not computed: such a call
runs the tensor path (:func:`kernel_covers` says why).
"""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer
from ..sectors import ROUNDINGS
from .bitmask import options_uncovered
from .build import cpu_kernels
from .launch import run_walk, walk_settings

__all__ = ["bitmask_soft", "kernel_covers", "module_forward"]


def bitmask_soft(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: torch.Tensor,
                 thickness: torch.Tensor, tau: float, weighting: str = "uniform", straight_through: bool = False,
                 step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True, seed: int = 0, noise: str = "ign",
                 stagger: bool = False,
                 fetch: str = "bilinear", border: str = "drop", rounding: str = "ceil",
                 sector_epsilon: float = 0.01, lanes: str = "simd") -> torch.Tensor:
    """Soft (or straight-through) bitmask visibility ``(B,1,H,W)`` in ``[0, 1]`` (background pixels 1),
    differentiable with respect to ``radius`` and ``thickness``.

    Args:
        gbuffer: a float32 G-buffer (CPU, or CUDA) without gradients; normals: its ``(B,3,H,W)`` unit
            view-space normals (without gradients).
        slices, steps: directions per pixel and samples per side (at most 32).
        radius, thickness: 0-d float tensors, world units (``nn.Parameter``\\ s get gradients).
        tau: temperature of the soft masks (sectors, > 0); weighting: ``"uniform"`` or ``"cosine"``;
            straight_through: hard coverage in the forward, the soft gradient in the backward.
        step_power, min_step_px (pixels), jitter, seed, noise, stagger, fetch, border, rounding, sector_epsilon (sectors):
            as :class:`~torch_ao.BitmaskAO`; lanes: on CPU, ``"simd"`` or ``"scalar"`` (the CUDA thread's walk).

    Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built here, and
    ``ValueError`` naming ``gbuffer``/``normals`` when they carry a gradient (the kernel does not compute it).
    """
    if torch.is_grad_enabled() and (normals.requires_grad or gbuffer.depth.requires_grad or (
            gbuffer.position is not None and gbuffer.position.requires_grad)):
        raise ValueError("gbuffer/normals: the soft kernel differentiates radius and thickness only; "
                         "detach the G-buffer or use backend='torch'")
    if gbuffer.depth.device.type == "cpu":
        cpu_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
    scalars = []
    for name, t in (("radius", radius), ("thickness", thickness)):
        t = torch.as_tensor(t)
        if t.dim() != 0:
            raise ValueError(f"{name}: expected a 0-d tensor, got shape {tuple(t.shape)}")
        scalars.append(t)
    options = dict(slices=int(slices), steps=int(steps), tau=float(tau), cosine=weighting == "cosine",
                   straight_through=bool(straight_through), step_power=float(step_power),
                   min_step_px=float(min_step_px), jitter=bool(jitter), seed=int(seed), noise=noise, stagger=bool(stagger), fetch=fetch, border=border,
                   rounding=ROUNDINGS.index(rounding), epsilon=float(sector_epsilon), lanes=lanes)
    return _SoftWalk.apply(gbuffer, normals, *scalars, options)


def _walk(gbuffer, normals, radius, thickness, o, gradients):
    """The walk's channels: the visibility, then (with ``gradients``) d visibility / d radius, d thickness."""
    settings = walk_settings(slices=o["slices"], steps=o["steps"], radius=float(radius), jitter=o["jitter"],
                             seed=o["seed"], noise=o["noise"], stagger=o["stagger"], fetch=o["fetch"], border=o["border"], step_power=o["step_power"],
                             min_step_px=o["min_step_px"])
    acc_ints = [o["rounding"], o["cosine"], o["straight_through"]]
    acc_floats = [float(thickness), o["epsilon"], o["tau"]]
    return run_walk("soft_gradients" if gradients else "soft", gbuffer, normals, settings, acc_ints, acc_floats, 3 if gradients else 1, lanes=o["lanes"])


class _SoftWalk(torch.autograd.Function):
    @staticmethod
    def forward(ctx, gbuffer, normals, radius, thickness, options):
        wanted = bool(ctx.needs_input_grad[2] or ctx.needs_input_grad[3])
        out = _walk(gbuffer, normals, radius, thickness, options, wanted)
        if wanted:
            ctx.save_for_backward(out[:, 1:].contiguous())
        ctx.dtypes = (radius.dtype, thickness.dtype)
        return out[:, :1].contiguous()

    @staticmethod
    def backward(ctx, grad):
        (jacobian,) = ctx.saved_tensors  # (B, 2, H, W): d visibility / d radius, d thickness per pixel
        sums = (grad.double() * jacobian.double()).sum(dim=(0, 2, 3))
        return None, None, sums[0].to(ctx.dtypes[0]), sums[1].to(ctx.dtypes[1]), None


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
                        min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, noise=module.noise, stagger=module.stagger,
                        fetch=module.fetch,
                        border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon)
