"""The soft / straight-through kernel of the ``"ssilvb_glsl"`` variant: ``BitmaskAO(variant="ssilvb_glsl",
mode="soft" | "straight_through")`` and ``SSILVB(...)`` of it, the shader's visibility and light on the one walk
(``walk.h`` with ``soft_glsl.h``'s accumulator), differentiable with respect to the thickness model's offset,
scale and growth, the G-buffer (depth or positions, normals, the light; the intrinsics through the positions) and the layer the
thickness reads.

The forward is the tensor path's (:class:`~torch_ao.methods.bitmask_glsl.GLSLAccumulator`): the shader's walk and
horizons, each step's interval in the soft union of :mod:`torch_ao.sectors.soft_union` whose per-sector visible
share is carried from slice to slice as the shader carries its mask, and the light weighed by one minus the share a
step newly occludes; straight-through mode has the hard masks' values. Its backward (walk_grad.h's
``soft_grad_block`` of the accumulator: ``torch_ao_kernels::soft_backward`` on the CPU, ``tao_soft_backward_glsl``
on CUDA) walks the slices last to first, each from its start, so that each slice's reverse scan is seeded with what
the later slices owe its end. The shader's texels are floored, so the radius has no gradient (as on the tensor path)
and the intrinsics only the positions' (``walk_inputs``' unprojection, by autograd).
"""
from __future__ import annotations

import torch

from ..checks import check_scalar_tensor
from ..gbuffer import GBuffer
from ..sectors import ROUNDINGS
from .bitmask import KernelOutputs, glsl_walk_settings, module_thickness, options_uncovered, thickness_read_index
from .build import cpu_kernels, grad_kernels
from .frame import light_input
from .launch import run_walk
from .soft_bitmask import SoftKernels, gbuffer_walk
from .walk_grad import wants_gradient

__all__ = ["ssilvb_glsl_soft", "glsl_soft_covers", "glsl_soft_forward", "GLSL_MAX_SLICES", "GLSL_MAX_STEPS"]

#: soft_glsl.h's kGlslMaxSlices - 1: the most ``sliceCount`` the backward holds (it keeps each slice's start)
GLSL_MAX_SLICES = 16
#: soft.h's kSoftMaxSteps - 1: the most ``sampleCount`` (a slice's steps are ``sampleCount + 1``)
GLSL_MAX_STEPS = 63
#: the short CUDA backward's steps a slice (soft.h's kSoftShortSteps)
_SHORT_STEPS = 16


def ssilvb_glsl_soft(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius, thickness: torch.Tensor,
                     tau: float, straight_through: bool = False, jitter: bool = True, rounding: str = "ceil",
                     numerics: str = "ieee", indirect: bool = False, layer: torch.Tensor | None = None,
                     layer_scale: torch.Tensor | None = None, thickness_read: str | None = None,
                     thickness_growth: torch.Tensor | None = None, lanes: str = "simd") -> KernelOutputs:
    """The ``"ssilvb_glsl"`` variant in soft (or straight-through) mode: visibility ``(B,1,H,W)`` (background 1; up
    to ``(slices + 1) / slices``, as the shader's) and, with ``indirect``, its light ``(B,3,H,W)`` (background 0).

    Args:
        gbuffer: a float32 G-buffer on the CPU or CUDA; normals: its ``(B,3,H,W)`` unit view-space normals.
        slices, steps: the shader's ``sliceCount`` (2 to 16) and ``sampleCount`` (1 to 63); radius: world units
            (no gradient: the shader's texels are floored).
        thickness: a 0-d tensor, world units (an ``nn.Parameter`` gets its gradient); with ``layer`` ``(B,1,H,W)``,
            ``layer_scale`` (0-d) and ``thickness_read`` the model ``layer_scale * value + thickness`` read at each
            sample's texel, as :func:`~torch_ao.kernels.bitmask_outputs`'; ``thickness_growth``: a 0-d tensor ``g``
            (per world unit; ``None``: none), the thickness times ``1 + g * |sample - pixel|``.
        tau: temperature of the soft masks (sectors, > 0); straight_through: the hard masks' values, the soft
            gradients; jitter, rounding, numerics (``glsl_numerics``): as :class:`~torch_ao.BitmaskAO`; indirect:
            the light too (``gbuffer.light`` needed).
        lanes: on CPU, ``"simd"`` or ``"scalar"`` (the CUDA thread's walk).

    Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built here.
    """
    if not 2 <= int(slices) <= GLSL_MAX_SLICES or not 1 <= int(steps) <= GLSL_MAX_STEPS:
        raise ValueError(f"slices, steps: expected 2 <= slices <= {GLSL_MAX_SLICES} and 1 <= steps <= "
                         f"{GLSL_MAX_STEPS}, got {slices}, {steps}")
    if not tau > 0:
        raise ValueError(f"tau: expected > 0, got {tau!r}")
    read = thickness_read_index(thickness_read, layer)
    thickness = check_scalar_tensor("thickness", thickness)
    scale = check_scalar_tensor("layer_scale", 1.0 if layer_scale is None else layer_scale)
    growth = None if thickness_growth is None else check_scalar_tensor("thickness_growth", thickness_growth)
    radius = torch.as_tensor(radius).detach()
    light = light_input(gbuffer, True) if indirect else None
    settings = glsl_walk_settings(slices, steps, radius, jitter, numerics)
    acc_ints = [ROUNDINGS.index(rounding), bool(indirect), numerics != "ieee", read, bool(straight_through),
                growth is not None]
    acc_floats = [thickness.detach(), scale.detach(), 0.0 if growth is None else growth.detach(), float(tau)]
    channels = 4 if indirect else 1
    if gbuffer.depth.device.type == "cpu":
        cpu_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
    if wants_gradient(gbuffer, normals, layer, light, thickness, scale, growth):
        if gbuffer.depth.device.type == "cpu":
            grad_kernels()
        backward = "tao_soft_backward_glsl_short" if int(steps) + 1 <= _SHORT_STEPS else "tao_soft_backward_glsl"
        kernels = SoftKernels("soft_glsl", "tao_walk_soft_glsl", backward, False)
        out = gbuffer_walk(gbuffer, normals, (settings, acc_ints, acc_floats), light, layer, radius, thickness, scale,
                           lanes, kernels, channels, growth)
        # (where the light alone requires a gradient, the visibility, which reads none, is off the graph: see
        # soft_outputs)
        unlit = out if wants_gradient(gbuffer, normals, layer, thickness, scale, growth) else out.detach()
    else:
        out = unlit = run_walk("soft_glsl", gbuffer, normals, settings, acc_ints, acc_floats, channels, light=light,
                               backface=None if layer is None else layer.detach(), lanes=lanes)
    return KernelOutputs(unlit[:, :1], out[:, 1:] if indirect else None)


def glsl_soft_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`ssilvb_glsl_soft` computes ``module(gbuffer)`` and its gradients (a ``BitmaskAO`` or
    ``SSILVB`` of the ``"ssilvb_glsl"`` variant in soft or straight-through mode, ``slices`` and ``steps`` within its
    bounds, a thickness of the form ``scale * value + offset``), else why not."""
    if getattr(module, "variant", None) != "ssilvb_glsl":
        return "a variant other than 'ssilvb_glsl' (its soft kernel's)"
    reason = options_uncovered(module, gbuffer, modes=("soft", "straight_through"), weightings=("uniform",),
                               variants=("ssilvb_glsl",), outputs=True, layers=True, growth=True)
    if reason is not None:
        return reason
    if module.slices > GLSL_MAX_SLICES or module.steps > GLSL_MAX_STEPS:
        return (f"slices={module.slices}, steps={module.steps} (the 'ssilvb_glsl' soft kernel holds {GLSL_MAX_SLICES} "
                f"slices of {GLSL_MAX_STEPS} steps)")
    return None


def glsl_soft_forward(module, gbuffer: GBuffer) -> dict:
    """``module(gbuffer)``'s ``{"visibility", "indirect"}`` for a module :func:`glsl_soft_covers` accepts."""
    form = module_thickness(module, gbuffer)
    vis, indirect, _ = ssilvb_glsl_soft(
        gbuffer, gbuffer.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
        radius=module.radius, thickness=form.offset, layer=form.layer, layer_scale=form.scale,
        thickness_read=form.read, thickness_growth=form.growth, tau=module.tau, straight_through=module.mode == "straight_through",
        jitter=module.jitter, rounding=module.rounding, numerics=module.glsl_numerics, indirect=module.want_indirect)
    return {"visibility": vis, "indirect": indirect}
