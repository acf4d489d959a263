"""The soft / straight-through bitmask AO kernel: ``BitmaskAO(variant="default" | "hdrp", mode="soft" |
"straight_through")``'s visibility, indirect light (``SSILVB``) and bent normals on the one walk (``walk.h`` with
``soft.h``'s accumulator),
differentiable with respect to the scalar ``radius``,
the thickness model's offset ``thickness``, scale (``scale * value + offset``: one scalar, the back-face layer,
a map, a per-object table, the net's map, the linear model in depth) and growth (times ``1 + growth * |sample -
pixel|``), the G-buffer (depth or positions, normals,
the intrinsics) and the thickness layer the model reads (and through it the back-face depth, a map, a table, the net's weights),
on the CPU and CUDA.

The forward is the tensor path's visibility (soft coverage of :mod:`torch_ao.sectors.soft_union`, or the
hard coverage in straight-through mode). When only radius and the thickness' scalars want a gradient, the same
walk also returns each pixel's derivatives of its visibility with respect to them (the soft union's reverse scan
per slice, in registers), and the backward is their sum weighted by the upstream gradient: nothing is kept per
sample, three channels per pixel (four with a thickness growth).

When the G-buffer or the layer wants one, the forward is the plain walk over the channel-last inputs of
:func:`~torch_ao.kernels.frame.walk_inputs` and the layer (so that autograd chains their gradients to depth,
positions, normals and whatever made the layer through its torch ops), and the backward (walk_grad.h's
``soft_grad_block``: ``torch_ao_kernels::soft_backward`` on the CPU, ``tao_soft_backward`` on CUDA) walks again
with the pixel and its slices in dual lanes (``lanes_dual.h``: tangents on each pixel's own position, normal and
depth), runs the reverse scan per slice, contracts each step's d visibility / d (s, w) with the tangents of its
interval, and scatters its d visibility / d delta to the step's fetch taps (bilinear: the four inverse depths;
nearest: the tap's position; on CUDA atomically) and d visibility / d its thickness, times the scale, to the
layer's taps (the linear model's value is the sample's depth: it joins d / d delta). The offset's and the scale's
gradients are per-pixel sums of the same adjoints. The radius needs no tangent: the walk is scale-invariant
(positions, depth, a layer, radius and offset scaled together, and the growth, per world unit, inversely, leave it
as it is; the scale is unitless), so Euler's identity gives ``R dL/dR = -sum(dL/dP . P + dL/ddepth depth -
dL/dinverse inverse + dL/dlayer layer) - T dL/dT + g dL/dg``. With indirect light the walk also returns the light
the newly occluded sectors send (3 channels), with bent normals the slices' bent-normal sum (3; its direction is
taken in torch); the backward's reverse scan is seeded
by every output's upstream gradient, each step's light replayed for its gradients to the light and the senders'
normals at its taps; their radius and thickness gradients take that backward too (the light does not scale with the
scene: Euler's identity holds without it). The intrinsics reach the walk twice: through the positions (``walk_inputs``' unprojection, by
autograd) and in the kernel (the slice's screen motion ``(fx a, -fy b) / depth``, whose direction places the
steps and whose length the span; a bilinear fetch's unprojection), whose adjoints the backward chains by hand
per slice and step and sums per pixel.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from ..checks import check_scalar_tensor
from ..gbuffer import GBuffer
from ..ops import bent_direction
from ..sectors import ROUNDINGS
from .bitmask import HARD_VARIANTS, KernelOutputs, module_thickness, options_uncovered, thickness_read_index
from .build import cpu_kernels, grad_kernels
from .frame import first_order, light_input, scalar_lanes, scale_derivative
from .launch import full_walk, launch_cuda, packed_inputs, run_walk, walk_settings
from .walk_grad import wants_gradient

__all__ = ["bitmask_soft", "soft_outputs", "kernel_covers", "module_forward"]


def bitmask_soft(gbuffer: GBuffer, normals: torch.Tensor, **options) -> torch.Tensor:
    """Soft (or straight-through) bitmask visibility ``(B,1,H,W)`` in ``[0, 1]`` (background pixels 1):
    :func:`soft_outputs`' visibility (its keyword ``options``, without bent normals)."""
    return soft_outputs(gbuffer, normals, **options).visibility


def soft_outputs(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: torch.Tensor,
                 thickness: torch.Tensor, tau: float, layer: torch.Tensor | None = None,
                 layer_scale: torch.Tensor | None = None, thickness_read: str | None = None,
                 thickness_growth: torch.Tensor | None = None, weighting: str = "uniform",
                 straight_through: bool = False, indirect: bool = False, bent_normals: bool = False,
                 step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True, seed: int = 0,
                 noise: str = "ign", stagger: bool = False,
                 fetch: str = "bilinear", border: str = "drop", rounding: str = "ceil", azimuth: str = "view",
                 sector_epsilon: float = 0.01, variant: str = "default", slice_sampling: str = "uniform",
                 sample_extent: str = "radius", thickness_direction: str = "view", clip_to_radius: bool = False,
                 lanes: str = "simd") -> KernelOutputs:
    """Soft (or straight-through) bitmask visibility ``(B,1,H,W)`` in ``[0, 1]`` (background pixels 1) and, with
    ``indirect``, the indirect light ``(B,3,H,W)`` (background 0), with ``bent_normals`` the bent normals
    ``(B,3,H,W)`` (unit view-space; ``normals`` where the visible sectors' sum is about 0 and on background),
    differentiable with respect to ``radius``, ``thickness``, ``layer_scale``, ``thickness_growth``, ``layer`` and
    the G-buffer's depth, positions, intrinsics, ``normals`` and light.

    Args:
        gbuffer: a float32 G-buffer on the CPU or CUDA; normals: its ``(B,3,H,W)``
            unit view-space normals.
        slices, steps: directions per pixel and samples per side (at most 32).
        radius, thickness: 0-d float tensors, world units (``nn.Parameter``\\ s get gradients); with ``layer``
            ``(B,1,H,W)`` (read at each sample as depth is) the thickness there is ``layer_scale * layer +
            thickness``, ``layer_scale`` a 0-d tensor (default 1, e.g. the back-face model's
            ``thickness_scale``); ``thickness_read``: as :func:`~torch_ao.kernels.bitmask_outputs`
            (``"depth"``: ``layer_scale`` per world unit of the sample's depth, no layer); ``thickness_growth``: a
            0-d tensor ``g`` (per world unit; ``None``: none), the thickness times ``1 + g * |sample - pixel|``.
        tau: temperature of the soft masks (sectors, > 0); weighting: ``"uniform"`` or ``"cosine"``;
            straight_through: hard coverage in the forward, the soft gradient in the backward; indirect: the light
            the newly occluded sectors send too (``gbuffer.light`` needed); bent_normals: the visible sectors' mean
            direction too (their gradients are the backward's walk, as the G-buffer's).
        step_power, min_step_px (pixels), jitter, seed, noise, stagger, fetch, border, rounding, sector_epsilon (sectors),
            azimuth (``"view"``/``"screen"``), variant (``"default"``/``"hdrp"``: the sector rule and slice frame),
            slice_sampling, sample_extent
            (``"sphere"``: the steps over the radius' sphere's screen extent), thickness_direction and
            clip_to_radius (the ``"exact"`` variant's segment geometry, with ``"default"``'s plane angles): as
            :class:`~torch_ao.BitmaskAO`; lanes: on CPU, ``"simd"`` or ``"scalar"`` (the CUDA thread's
            walk).

    Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built here.
    """
    if variant not in HARD_VARIANTS + ("exact",):
        raise ValueError(f"variant: expected one of {HARD_VARIANTS + ('exact',)}, got {variant!r}")
    if (thickness_direction == "depth" or clip_to_radius) and variant == "hdrp":
        raise ValueError("thickness_direction, clip_to_radius: the segment geometry takes the plane angles of the "
                         "'default' and 'exact' variants (got variant='hdrp')")
    read = thickness_read_index(thickness_read, layer)
    named = (("radius", radius), ("thickness", thickness), ("layer_scale", 1.0 if layer_scale is None else layer_scale),
             ("thickness_growth", 0.0 if thickness_growth is None else thickness_growth))
    scalars = [check_scalar_tensor(name, t) for name, t in named]
    light = light_input(gbuffer, True) if indirect else None
    # the backward's walk: the G-buffer's gradients, and those of indirect light and bent normals (the settings'
    # too: one reverse scan seeded by every output, where the forward's derivative channels would be 9 more each)
    backward_walk = wants_gradient(gbuffer, normals, layer, light, *(scalars if indirect or bent_normals else ()))
    if gbuffer.depth.device.type == "cpu":
        cpu_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
        if backward_walk:
            grad_kernels()
    options = dict(slices=int(slices), steps=int(steps), tau=float(tau), cosine=weighting == "cosine",
                   straight_through=bool(straight_through), step_power=float(step_power),
                   min_step_px=float(min_step_px), jitter=bool(jitter), seed=int(seed), noise=noise,
                   stagger=bool(stagger), fetch=fetch, border=border, azimuth=azimuth,
                   rounding=ROUNDINGS.index(rounding), epsilon=float(sector_epsilon), lanes=lanes, read=read,
                   angles=int(variant == "hdrp"), bent=bool(bent_normals), indirect=bool(indirect),
                   along_ray=thickness_direction == "depth", clip=bool(clip_to_radius),
                   grows=thickness_growth is not None, slice_sampling=slice_sampling,
                   sphere=sample_extent == "sphere")
    if backward_walk:
        out = _gbuffer_walk(gbuffer, normals, *scalars, layer, light, options)
    elif indirect or bent_normals:  # (no gradient: the plain walk)
        out = _walk(gbuffer, normals, *scalars, layer, options, False, light)
    else:
        out = _SoftWalk.apply(gbuffer, normals, *scalars, None if layer is None else layer.detach(), options)
    lit = out[:, 1:4] if indirect else None
    # (where the light alone requires a gradient, the visibility and the bent normal, which read none, are off the
    # graph, as on the tensor path)
    unlit = out.detach() if backward_walk and not wants_gradient(gbuffer, normals, layer, *scalars) else out
    bent = bent_normal(unlit[:, 1 + 3 * bool(indirect):], normals, gbuffer.valid) if bent_normals else None
    return KernelOutputs(unlit[:, :1], lit, bent)


def bent_normal(sums: torch.Tensor, normals: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The bent normals ``(B,3,H,W)`` of the walk's bent-normal sums ``(B,3,H,W)``: their direction, or ``normals``
    where a sum is about 0 (every sector occluded) and where not ``valid`` (SectorAccumulator.finish)."""
    return torch.where(valid, bent_direction(sums, normals, 1), normals)


def _settings(radius, thickness, scale, growth, o):
    """The packed settings ``(walk settings, accumulator ints, accumulator floats)`` of ``soft.h``'s walk."""
    settings = walk_settings(slices=o["slices"], steps=o["steps"], radius=radius.detach(), jitter=o["jitter"],
                             seed=o["seed"], noise=o["noise"], stagger=o["stagger"], fetch=o["fetch"], border=o["border"],
                             step_power=o["step_power"], min_step_px=o["min_step_px"], azimuth=o["azimuth"],
                             slice_sampling=o["slice_sampling"], sphere_extent=o["sphere"])
    return (settings, [o["rounding"], o["cosine"], o["straight_through"], o["read"], o["angles"], o["bent"],
                       o["indirect"], o["grows"], o["along_ray"], o["clip"]],
            [thickness.detach(), o["epsilon"], o["tau"], scale.detach(), growth.detach()])


def _outputs(o) -> int:
    """The walk's outputs: the visibility, the indirect light (3), the bent normals' sum (3)."""
    return 1 + 3 * o["indirect"] + 3 * o["bent"]


def _walk(gbuffer, normals, radius, thickness, scale, growth, layer, o, gradients, light=None):
    """The walk's channels: the visibility, then (with ``gradients``) d visibility / d radius, d thickness,
    d layer_scale, d thickness_growth, or the other outputs (:func:`_outputs`; ``light``: the channel-last light)."""
    settings, acc_ints, acc_floats = _settings(radius, thickness, scale, growth, o)
    accumulator = "soft"
    if gradients:  # (on CUDA, the short slice's arrays where its steps fit: soft_walk_short)
        accumulator = "soft_gradients_short" if gbuffer.depth.is_cuda and soft_walk_short(o["steps"]) else "soft_gradients"
    channels = 4 + o["grows"] if gradients else _outputs(o)
    return run_walk(accumulator, gbuffer, normals, settings, acc_ints, acc_floats, channels,
                    light=light, backface=layer, lanes=o["lanes"], segments=o["along_ray"] or o["clip"])


def _gbuffer_walk(gbuffer, normals, radius, thickness, scale, growth, layer, light, o):
    """The outputs (:func:`_outputs`) with gradients to the walk's channel-last inputs (so to the G-buffer), the
    channel-last ``light``, the thickness ``layer`` and the scalars."""
    packed = _settings(radius, thickness, scale, growth, o)
    full = full_walk("soft", gbuffer, packed[0], segments=o["along_ray"] or o["clip"])
    kernels = SoftKernels("soft", "tao_walk_soft", soft_backward_kernel(o["steps"]), True, full)
    return gbuffer_walk(gbuffer, normals, packed, light, layer, radius, thickness, scale, o["lanes"], kernels,
                        _outputs(o), growth if o["grows"] else None)


class SoftKernels(NamedTuple):
    """A soft walk's kernels: the CPU operator's accumulator, the CUDA forward and backward, whether the backward
    gives the intrinsics a gradient of its own (the walk moves its steps with them), and whether the CUDA ones are
    the full build's (:func:`~torch_ao.kernels.launch.full_walk`)."""

    cpu: str
    cuda_forward: str
    cuda_backward: str
    camera: bool
    full: bool = False


def gbuffer_walk(gbuffer, normals, packed, light, layer, radius, thickness, scale, lanes: str, kernels: SoftKernels,
                 channels: int, growth: torch.Tensor | None = None) -> torch.Tensor:
    """A soft walk's ``channels`` outputs (``packed``: its settings, walk's and accumulator's) with gradients to the
    walk's channel-last inputs (so to the G-buffer), the channel-last ``light``, the thickness ``layer`` and the
    scalars ``radius``, ``thickness``, ``scale`` and ``growth`` (the thickness growth's, ``None`` where it has none),
    by ``kernels``."""
    inputs, (light, cells, layer_image), ints, floats = packed_inputs(gbuffer, normals, *packed, light=light,
                                                                      backface=layer)
    return _GBufferWalk.apply(*inputs, light, cells, layer_image, ints, floats, radius, thickness, scale, growth,
                              scalar_lanes(lanes), kernels, channels)


#: soft.h's kSoftShortSteps: the most steps of a slice (both sides) the short CUDA kernels keep
SHORT_SLICE_STEPS = 16


def soft_walk_short(steps: int) -> bool:
    """Whether a slice of ``steps`` per side fits the short CUDA kernels' arrays (every preset's):
    ``tao_walk_soft_gradients_short`` and ``tao_soft_backward_short``, whose threads keep a quarter of the local
    memory of the kernels that take up to 32 steps a side."""
    return 2 * steps <= SHORT_SLICE_STEPS


def soft_backward_kernel(steps: int) -> str:
    """The CUDA soft backward for ``steps`` per side (:func:`soft_walk_short`)."""
    return "tao_soft_backward_short" if soft_walk_short(steps) else "tao_soft_backward"


class _GBufferWalk(torch.autograd.Function):
    """A soft walk (``kernels``: :class:`SoftKernels`) over ``(positions, normals, inverse, depth, valid,
    intrinsics)``, the channel-last ``light``, the edge-aware fetch's ``cells`` and the thickness ``layer`` (each empty
    where unused), its ``channels`` outputs, and ``soft_backward``; ``growth``: the thickness growth, or ``None``."""

    @staticmethod
    def forward(ctx, positions, normals, inverse, depth, valid, intrinsics, light, cells, layer, ints, floats, radius,
                thickness, scale, growth, scalar, kernels, channels):
        ctx.scalar, ctx.scale_dtype, ctx.kernels = scalar, scale.dtype, kernels
        growth = radius.new_zeros(()) if growth is None else growth
        ctx.save_for_backward(positions, normals, inverse, depth, valid, intrinsics, light, cells, layer, ints, floats,
                              radius, thickness, growth)
        frame = (positions, normals, inverse, depth, valid, intrinsics)
        if depth.is_cuda:
            out = torch.empty(depth.shape[0], channels, *depth.shape[1:], device=depth.device)
            launch_cuda(kernels.cuda_forward, depth.device, [*frame, light, cells, layer, out, ints, floats],
                        tuple(depth.shape), full=kernels.full)
            return out
        return cpu_kernels().walk(kernels.cpu, *frame, light, cells, layer, ints, floats, channels, scalar)

    @staticmethod
    @first_order
    def backward(ctx, grad):
        positions, normals, inverse, depth, valid, intrinsics, light, cells, layer, ints, floats, radius, thickness, \
            growth = ctx.saved_tensors
        frame = (positions, normals, inverse, depth, valid, intrinsics, light, cells, layer)
        grad = grad.to(torch.float32).contiguous()
        camera = ctx.needs_input_grad[5] and ctx.kernels.camera  # the intrinsics' gradients, per pixel (B, H, W, 4)
        if depth.is_cuda:  # the pixels' own gradients, and their taps' scattered atomically into images of their own
            g_pos, g_nrm, taps = torch.zeros_like(positions), torch.zeros_like(normals), torch.zeros_like(positions)
            g_depth, g_inv, g_layer = torch.zeros_like(depth), torch.zeros_like(depth), torch.zeros_like(depth)
            senders, g_light = torch.zeros_like(normals), torch.zeros_like(normals)
            g_setting = depth.new_zeros((*depth.shape, 3))
            g_camera = depth.new_zeros((*depth.shape, 4) if camera else (0,))  # (empty: a null pointer)
            launch_cuda(ctx.kernels.cuda_backward, depth.device,
                        [*frame, grad, g_pos, g_nrm, g_depth, g_setting, taps, g_inv, g_layer, senders, g_light,
                         g_camera, ints, floats], tuple(depth.shape), full=ctx.kernels.full)
            g_pos += taps
            g_nrm += senders
        else:
            g_pos, g_nrm, g_inv, g_depth, g_setting, g_layer, g_light, g_camera = grad_kernels().soft_backward(
                grad, *frame, ints, floats, camera, ctx.scalar)
        g_intrinsics = g_camera.double().sum((1, 2)).to(intrinsics.dtype) if camera else None
        g_thickness, g_scale, g_growth = g_setting.double().sum(dim=(0, 1, 2)).unbind()
        g_radius = None
        if ctx.needs_input_grad[11]:  # Euler's identity (module docstring); invalid texels hold NaN
            along = scale_derivative(valid, (g_pos, positions), (g_depth, depth), (g_inv, -inverse))
            if layer.numel():  # (a layer is world units: it scales with the scene)
                along = along + torch.where(torch.isfinite(layer), g_layer.double() * layer, 0.0).sum()
            g_radius = (-(along + thickness.double() * g_thickness - growth.double() * g_growth)
                        / radius.double()).to(radius.dtype)
        return (g_pos, g_nrm, g_inv, g_depth, None, g_intrinsics, g_light if light.numel() else None, None,
                g_layer if layer.numel() else None, None, None, g_radius,
                g_thickness.to(thickness.dtype) if ctx.needs_input_grad[12] else None,
                g_scale.to(ctx.scale_dtype) if ctx.needs_input_grad[13] else None,
                g_growth.to(growth.dtype) if ctx.needs_input_grad[14] else None, None, None, None)


class _SoftWalk(torch.autograd.Function):
    @staticmethod
    def forward(ctx, gbuffer, normals, radius, thickness, scale, growth, layer, options):
        wanted = any(ctx.needs_input_grad[2:6])
        out = _walk(gbuffer, normals, radius, thickness, scale, growth, layer, options, wanted)
        if wanted:
            ctx.save_for_backward(out[:, 1:].contiguous())
        ctx.dtypes = (radius.dtype, thickness.dtype, scale.dtype, growth.dtype)
        return out[:, :1].contiguous()

    @staticmethod
    @first_order
    def backward(ctx, grad):
        # (B, 3 or 4, H, W): d visibility / d radius, d thickness, d scale (, d growth) per pixel
        (jacobian,) = ctx.saved_tensors
        sums = (grad.double() * jacobian.double()).sum(dim=(0, 2, 3))
        grads = [sums[k].to(ctx.dtypes[k]) for k in range(jacobian.shape[1])]
        return None, None, *grads, *[None] * (4 - len(grads)), None, None


#: options of a module the soft kernel reproduces (beyond the hard kernel's): the modes and weightings (hard
#: mode is the straight-through forward without a graph: the hard kernel's masks with cosine weights too)
_MODES = ("hard", "soft", "straight_through")
_WEIGHTINGS = ("uniform", "cosine")
#: the variants (bitmask.h's sector rules and slice frames)
_VARIANTS = HARD_VARIANTS + ("exact",)  # (the exact variant: its segment geometry with the sector union)
#: beyond what every bitmask kernel covers: the edge-aware fetch, bent normals, and a constant ambient colour (the
#: visibility times the colour, in torch: dispatch.py)
_EXTRA = {"fetch": ("nearest", "bilinear", "edge_aware"), "indirect": (False, True), "bent_normals": (False, True),
          "ambient": (None, "a colour"), "sample_extent": ("radius", "sphere"), "thickness_direction": ("view", "depth"),
          "clip_to_radius": (False, True)}


def kernel_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`bitmask_soft` computes ``module(gbuffer)`` and its gradients (a ``BitmaskAO``
    of :data:`~torch_ao.kernels.bitmask.HARD_VARIANTS` in soft or straight-through mode, or hard mode, whose masks have
    none), else why not: the hard kernel's
    options (any slices, steps, radius, jitter, rounding, fetch, border... a thickness of the form ``scale *
    value + offset``, visibility, indirect light, bent normals and a constant ambient colour, a float32 CPU or CUDA
    G-buffer) with either weighting; gradients of radius and the thickness' offset and scale, of depth, positions,
    normals, the light, the intrinsics and the layer the thickness reads."""
    of_gbuffer = wants_gradient(gbuffer, gbuffer.normals)
    reason = options_uncovered(module, gbuffer, modes=_MODES, weightings=_WEIGHTINGS, variants=_VARIANTS, extra=_EXTRA,
                               layers=True, growth=True)
    if reason is not None:
        return reason
    if module.mode == "hard" and of_gbuffer:
        return "a gradient of the G-buffer in hard mode (the kernel's backward is the soft union's)"
    if module.thickness_direction == "depth" or module.clip_to_radius:
        if module.variant == "hdrp":
            return "the segment geometry with variant='hdrp' (its rule has none)"
    return None


def module_forward(module, gbuffer: GBuffer) -> KernelOutputs:
    """``module(gbuffer)``'s visibility and bent normals by :func:`soft_outputs` (a call :func:`kernel_covers`
    accepts)."""
    hard = module.mode == "hard"  # hard masks have no gradient: no graph
    form = module_thickness(module, gbuffer)
    radius, thickness, scale, growth = module.radius, form.offset, form.scale, form.growth
    if hard:
        radius, thickness, scale = radius.detach(), thickness.detach(), scale.detach()
        growth = None if growth is None else growth.detach()
    layer = None if form.layer is None else form.layer.detach() if hard else form.layer
    return soft_outputs(gbuffer, gbuffer.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                        radius=radius, thickness=thickness, layer=layer, layer_scale=scale, thickness_read=form.read,
                        thickness_growth=growth, tau=module.tau, weighting=module.weighting,
                        indirect=module.want_indirect, bent_normals=module.want_bent,
                        straight_through=module.mode != "soft", step_power=module.step_power,
                        min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, noise=module.noise,
                        stagger=module.stagger, fetch=module.fetch, border=module.border, rounding=module.rounding,
                        sector_epsilon=module.sector_epsilon, azimuth=module.azimuth, variant=module.variant,
                        slice_sampling=module.slice_sampling, sample_extent=module.sample_extent,
                        thickness_direction=module.thickness_direction, clip_to_radius=module.clip_to_radius)
