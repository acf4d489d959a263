"""The exact union's kernel with gradients: ``BitmaskAO(variant="exact")`` (``union="exact"``) in soft,
straight-through or hard mode, differentiable with respect to ``radius`` and the thickness model's scalars
(``thickness``, the back-face model's ``thickness_scale``, the linear model's ``thickness_slope``), on the one walk
(``walk.h`` with ``exact_soft.h``'s accumulator).

The exact union has no temperature: its measure is differentiable almost everywhere as it is, so the three
modes have one forward (the hard kernel's, :func:`~torch_ao.kernels.exact_hard`, value for value) and one
gradient. The walk runs in dual lanes carrying the derivatives of each sample's interval with respect to
the three parameters through the union, and returns each pixel's derivatives of its visibility; the backward
is their sum weighted by the upstream gradient (nothing is kept per sample: three channels per pixel).
Gradients of the G-buffer are not computed (:func:`exact_soft_covers` sends such a call to the tensor path).
"""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer
from .bitmask import EXACT_MAX_STEPS, _EXACT, module_thickness, options_uncovered, thickness_read_index
from .build import cpu_kernels
from .launch import run_walk, walk_settings

__all__ = ["exact_soft", "exact_soft_covers", "exact_soft_forward"]


def exact_soft(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: torch.Tensor,
               thickness: torch.Tensor, layer: torch.Tensor | None = None, layer_scale: torch.Tensor | None = None,
               thickness_read: str | None = None, step_power: float = 1.0,
               min_step_px: float = 0.25, jitter: bool = True, seed: int = 0, noise: str = "ign",
               stagger: bool = False, fetch: str = "edge_aware", border: str = "drop", weighting: str = "cosine",
               thickness_direction: str = "depth", clip_to_radius: bool = True, sample_extent: str = "sphere",
               sector_epsilon: float = 0.0, lanes: str = "simd") -> torch.Tensor:
    """Visibility ``(B,1,H,W)`` of the exact union (background 1; :func:`~torch_ao.kernels.exact_hard`'s),
    differentiable with respect to ``radius``, ``thickness`` and ``layer_scale``.

    Args:
        gbuffer: a float32 G-buffer (CPU or CUDA), whose tensors want no gradient; normals: its ``(B,3,H,W)``
            unit view-space normals.
        radius, thickness: 0-d tensors, world units (``nn.Parameter``\\ s get gradients); with ``layer``
            ``(B,1,H,W)`` (a model's :class:`~torch_ao.thickness.ThicknessLayer`, read at each sample as depth
            is; no gradient reaches it) the thickness there is ``layer_scale * layer + thickness``, with
            ``layer_scale`` a 0-d tensor (default 1, e.g. the back-face model's ``thickness_scale``);
            ``thickness_read``: as :func:`~torch_ao.kernels.bitmask_outputs` (``"depth"``: ``layer_scale``
            times the sample's depth, LinearThickness' slope).
        slices, steps (<= 32 per side), step_power, min_step_px (pixels), jitter, seed, noise, stagger, fetch,
            border, weighting, thickness_direction, clip_to_radius, sample_extent, sector_epsilon: as
            :class:`~torch_ao.BitmaskAO`; lanes: on CPU, ``"simd"`` or ``"scalar"``.

    Raises ``ValueError`` naming the argument for a parameter that is not 0-d, or ``steps`` beyond 32.
    """
    if int(steps) > EXACT_MAX_STEPS:
        raise ValueError(f"steps: the exact union's kernel holds at most {EXACT_MAX_STEPS} per side, got {steps}")
    scalars = []
    read = thickness_read_index(thickness_read, layer)
    if read != 0 and layer_scale is None:
        layer_scale = torch.ones(())
    for name, t in (("radius", radius), ("thickness", thickness), ("layer_scale", layer_scale)):
        if t is None:
            scalars.append(None)
            continue
        t = torch.as_tensor(t)
        if t.dim() != 0:
            raise ValueError(f"{name}: expected a 0-d tensor, got shape {tuple(t.shape)}")
        scalars.append(t)
    if gbuffer.depth.device.type == "cpu":
        cpu_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
    options = dict(slices=int(slices), steps=int(steps), step_power=float(step_power), min_step_px=float(min_step_px),
                   jitter=bool(jitter), seed=int(seed), noise=noise, stagger=bool(stagger), fetch=fetch, border=border,
                   cosine=weighting == "cosine", along_ray=thickness_direction == "depth", clip=bool(clip_to_radius),
                   sphere=sample_extent == "sphere", epsilon=float(sector_epsilon), read=read, lanes=lanes)
    return _ExactWalk.apply(gbuffer, normals, *scalars[:2], options, scalars[2], None if layer is None else layer.detach())


def _walk(gbuffer, normals, radius, thickness, scale, layer, o, gradients: bool) -> torch.Tensor:
    """The walk's channels: the visibility, then (with ``gradients``) d visibility / d radius, d the
    thickness' offset, d its scale."""
    r = float(radius.detach())
    settings = walk_settings(slices=o["slices"], steps=o["steps"], radius=r, step_power=o["step_power"],
                             min_step_px=o["min_step_px"], jitter=o["jitter"], seed=o["seed"], noise=o["noise"],
                             stagger=o["stagger"], fetch=o["fetch"], border=o["border"], sphere_extent=o["sphere"])
    return run_walk("exact_gradients" if gradients else "exact", gbuffer, normals, settings,
                    [o["cosine"], o["along_ray"], o["clip"], o["read"]],
                    [float(thickness.detach()), 1.0 if scale is None else float(scale.detach()), r, o["epsilon"]],
                    4 if gradients else 1, backface=layer, lanes=o["lanes"])


class _ExactWalk(torch.autograd.Function):
    @staticmethod
    def forward(ctx, gbuffer, normals, radius, thickness, options, scale, layer):
        wanted = bool(ctx.needs_input_grad[2] or ctx.needs_input_grad[3]
                      or (scale is not None and ctx.needs_input_grad[5]))
        out = _walk(gbuffer, normals, radius, thickness, scale, layer, options, wanted)
        if wanted:
            ctx.save_for_backward(out[:, 1:].contiguous())
        ctx.dtypes = (radius.dtype, thickness.dtype, None if scale is None else scale.dtype)
        return out[:, :1].contiguous()

    @staticmethod
    def backward(ctx, grad):
        (jacobian,) = ctx.saved_tensors  # (B, 3, H, W): d visibility / d radius, offset, scale
        sums = (grad.double() * jacobian.double()).sum(dim=(0, 2, 3))
        g_scale = None if ctx.dtypes[2] is None else sums[2].to(ctx.dtypes[2])
        return None, None, sums[0].to(ctx.dtypes[0]), sums[1].to(ctx.dtypes[1]), None, g_scale, None


#: what this kernel covers beyond the exact union's hard kernel: every mode (one forward, one gradient)
_MODES = ("hard", "soft", "straight_through")


def exact_soft_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`exact_soft` computes ``module(gbuffer)`` and its gradients (a ``BitmaskAO`` with
    ``union="exact"``, any mode: visibility only, a thickness of the form ``scale * value + offset``, a float32
    CPU or CUDA G-buffer), else why not. Gradients of the radius and of the model's scalar parameters (the
    offset ``thickness``, the back-face model's ``thickness_scale``, the linear model's ``thickness_slope``); not of the G-buffer (depth, positions,
    normals, the back-face layer) nor of what makes a layer (a map, a table, the net's weights), which the
    tensor path computes."""
    if getattr(module, "union", None) != "exact":
        return "union other than 'exact' (the sector kernels')"
    reason = options_uncovered(module, gbuffer, modes=_MODES, weightings=("uniform", "cosine"),
                               variants=("default", "exact"), devices=("cpu", "cuda"), extra=_EXACT, layers=True)
    if reason is not None:
        return reason
    if module.steps > EXACT_MAX_STEPS:
        return f"steps={module.steps} (the exact union's kernel holds {EXACT_MAX_STEPS} per side)"
    cam = gbuffer.camera
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (
            gbuffer.depth, gbuffer.normals, gbuffer.position, gbuffer.backface_depth, cam.fx, cam.fy, cam.cx, cam.cy)):
        return "a gradient of the G-buffer (the kernel differentiates the radius and the thickness model's scalars)"
    if torch.is_grad_enabled():
        layered = [name for name in module.thickness_model.parameters()
                   if getattr(module, name).dim() != 0 and getattr(module, name).requires_grad]
        if layered:
            return f"a gradient of {layered[0]} (the kernel differentiates the thickness model's scalars only)"
    return None


def exact_soft_forward(module, gbuffer: GBuffer) -> dict:
    """``module(gbuffer)``'s ``{"visibility": (B,1,H,W)}`` for a module :func:`exact_soft_covers` accepts."""
    form = module_thickness(module, gbuffer)
    vis = exact_soft(gbuffer, gbuffer.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                     radius=module.radius, thickness=form.offset, layer=form.layer,
                     layer_scale=None if form.read == "constant" else form.scale, thickness_read=form.read,
                     step_power=module.step_power, min_step_px=module.min_step_px, jitter=module.jitter,
                     seed=module.seed, noise=module.noise, stagger=module.stagger, fetch=module.fetch,
                     border=module.border, weighting=module.weighting, thickness_direction=module.thickness_direction,
                     clip_to_radius=module.clip_to_radius, sample_extent=module.sample_extent,
                     sector_epsilon=module.sector_epsilon)
    return {"visibility": vis}
