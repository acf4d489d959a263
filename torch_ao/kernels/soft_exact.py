"""The exact union's kernel with gradients: ``BitmaskAO(variant="exact")`` (``union="exact"``) in soft,
straight-through or hard mode, differentiable with respect to ``radius``, the thickness model's scalars
(``thickness``, the back-face model's ``thickness_scale``, the linear model's ``thickness_slope``, a growth's
``thickness_growth``), the G-buffer
(depth, positions, normals) and the thickness layer the model reads (the back-face layer, and through it the
back-face depth; a map; the net's map; a per-object table), on the one walk, CPU and CUDA.

The exact union has no temperature: its measure is differentiable almost everywhere as it is, so the three
modes have one forward (the hard kernel's, :func:`~torch_ao.kernels.exact_hard`, value for value) and one
gradient. For the scalars the walk runs in dual lanes (``exact_soft.h``) carrying the derivatives of each
sample's interval with respect to them through the union, and returns each pixel's derivatives of its
visibility; the backward is their sum weighted by the upstream gradient (nothing is kept per sample: three
channels per pixel, four with a growth, whose tangent the walk carries only then: ``exact_gradients_growth``).

When the G-buffer or the layer wants a gradient, the walk reads the channel-last inputs of
:func:`~torch_ao.kernels.frame.walk_inputs` and the layer (so that autograd chains their gradients to depth,
positions, normals and whatever made the layer through its torch ops), and the backward (walk_grad.h's
``exact_grad_block``: ``torch_ao_kernels::exact_backward`` on the CPU, ``tao_exact_backward`` on CUDA) walks
each slice again: the union's adjoint by hand (its sort, its running reach), then the intervals that carry one
replayed in dual lanes, whose tangents reach the pixel's own position, normal and depth and, scattered, each
sample's taps (inverse depth or position, and the layer's). The intrinsics reach the walk through the positions
(``walk_inputs``' unprojection, by autograd) and in the kernel, where each replayed sample's place on screen (the
slice's screen motion) and a bilinear fetch's unprojection read them: walk.h's ``PlacementAdjoint`` and
``unprojection_camera`` chain those per pixel, summed per image.
"""
from __future__ import annotations

import torch

from ..checks import check_scalar_tensor
from ..gbuffer import GBuffer
from .bitmask import EXACT_MAX_STEPS, _EXACT, module_thickness, options_uncovered, thickness_read_index
from .build import cpu_kernels, grad_kernels
from .frame import first_order, scalar_lanes
from .launch import full_walk, launch_cuda, packed_inputs, run_walk, walk_settings
from .walk_grad import wants_gradient

__all__ = ["exact_soft", "exact_soft_covers", "exact_soft_forward"]


def exact_soft(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: torch.Tensor,
               thickness: torch.Tensor, layer: torch.Tensor | None = None, layer_scale: torch.Tensor | None = None,
               thickness_read: str | None = None, thickness_growth: torch.Tensor | None = None, step_power: float = 1.0,
               min_step_px: float = 0.25, jitter: bool = True, seed: int = 0, noise: str = "ign",
               stagger: bool = False, fetch: str = "edge_aware", border: str = "drop", weighting: str = "cosine",
               thickness_direction: str = "depth", clip_to_radius: bool = True, sample_extent: str = "sphere",
               sector_epsilon: float = 0.0, azimuth: str = "view", slice_sampling: str = "uniform",
               lanes: str = "simd") -> torch.Tensor:
    """Visibility ``(B,1,H,W)`` of the exact union (background 1; :func:`~torch_ao.kernels.exact_hard`'s),
    differentiable with respect to ``radius``, ``thickness``, ``layer_scale``, ``thickness_growth``, the G-buffer's
    depth, positions and ``normals``, and ``layer``.

    Args:
        gbuffer: a float32 G-buffer (CPU or CUDA); normals: its ``(B,3,H,W)`` unit view-space normals.
        radius, thickness: 0-d tensors, world units (``nn.Parameter``\\ s get gradients); with ``layer``
            ``(B,1,H,W)`` (a model's :class:`~torch_ao.thickness.ThicknessLayer`, read at each sample as depth
            is) the thickness there is ``layer_scale * layer + thickness``, with ``layer_scale`` a 0-d tensor
            (default 1, e.g. the back-face model's ``thickness_scale``);
            ``thickness_read``: as :func:`~torch_ao.kernels.bitmask_outputs` (``"depth"``: ``layer_scale``
            times the sample's depth, LinearThickness' slope); ``thickness_growth``: a 0-d tensor ``g`` (per
            world unit; ``None``: none), the thickness times ``1 + g * |sample - pixel|``.
        slices, steps (<= 32 per side), step_power, min_step_px (pixels), jitter, seed, noise, stagger, fetch,
            border, weighting, thickness_direction, clip_to_radius, sample_extent, sector_epsilon, azimuth,
            slice_sampling: as
            :class:`~torch_ao.BitmaskAO`; lanes: on CPU, ``"simd"`` or ``"scalar"``.

    Raises ``ValueError`` naming the argument for a parameter that is not 0-d, or ``steps`` beyond 32.
    """
    if int(steps) > EXACT_MAX_STEPS:
        raise ValueError(f"steps: the exact union's kernel holds at most {EXACT_MAX_STEPS} per side, got {steps}")
    scalars = []
    read = thickness_read_index(thickness_read, layer)
    if read != 0 and layer_scale is None:
        layer_scale = torch.ones(())
    for name, t in (("radius", radius), ("thickness", thickness), ("layer_scale", layer_scale),
                    ("thickness_growth", thickness_growth)):
        if t is None:
            scalars.append(None)
            continue
        scalars.append(check_scalar_tensor(name, t))
    of_gbuffer = wants_gradient(gbuffer, normals, layer)
    if gbuffer.depth.device.type == "cpu":
        cpu_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
        if of_gbuffer:
            grad_kernels()
    options = dict(slices=int(slices), steps=int(steps), step_power=float(step_power), min_step_px=float(min_step_px),
                   jitter=bool(jitter), seed=int(seed), noise=noise, stagger=bool(stagger), fetch=fetch, border=border,
                   azimuth=azimuth, cosine=weighting == "cosine", along_ray=thickness_direction == "depth", clip=bool(clip_to_radius),
                   sphere=sample_extent == "sphere", epsilon=float(sector_epsilon), read=read, lanes=lanes,
                   slice_sampling=slice_sampling)
    if of_gbuffer:
        return _gbuffer_walk(gbuffer, normals, *scalars, layer, options)
    return _ExactWalk.apply(gbuffer, normals, *scalars[:2], options, scalars[2], None if layer is None else layer.detach(),
                            scalars[3])


def _settings(radius, thickness, scale, growth, o) -> tuple:
    """The packed settings ``(walk settings, accumulator ints, accumulator floats)`` of the exact union's walk."""
    r = radius.detach()  # (0-d tensors: packed on the device, nothing read back)
    settings = walk_settings(slices=o["slices"], steps=o["steps"], radius=r, step_power=o["step_power"],
                             min_step_px=o["min_step_px"], jitter=o["jitter"], seed=o["seed"], noise=o["noise"],
                             stagger=o["stagger"], fetch=o["fetch"], border=o["border"], sphere_extent=o["sphere"],
                             azimuth=o["azimuth"], slice_sampling=o["slice_sampling"])
    return (settings, [o["cosine"], o["along_ray"], o["clip"], o["read"], growth is not None],
            [thickness.detach(), 1.0 if scale is None else scale.detach(), r, o["epsilon"],
             0.0 if growth is None else growth.detach()])


def _gradients_walk(growth) -> tuple[int, str]:
    """The channels and accumulator of the walk with derivatives: d radius, d offset, d scale, and with a
    ``growth`` (not ``None``) d growth (the one with a fourth tangent)."""
    return (4, "exact_gradients") if growth is None else (5, "exact_gradients_growth")


def _walk(gbuffer, normals, radius, thickness, scale, growth, layer, o, gradients: bool) -> torch.Tensor:
    """The walk's channels: the visibility, then (with ``gradients``) d visibility / d radius, d the
    thickness' offset, d its scale (, d its growth)."""
    channels, name = _gradients_walk(growth) if gradients else (1, "exact")
    return run_walk(name, gbuffer, normals, *_settings(radius, thickness, scale, growth, o), channels, backface=layer,
                    lanes=o["lanes"])


def _gbuffer_walk(gbuffer, normals, radius, thickness, scale, growth, layer, o) -> torch.Tensor:
    """The visibility with gradients to the walk's channel-last inputs (so to the G-buffer), the layer and the
    scalars."""
    packed = _settings(radius, thickness, scale, growth, o)
    inputs, (_, cells, layer_image), ints, floats = packed_inputs(gbuffer, normals, *packed, backface=layer)
    scale = torch.ones(()) if scale is None else scale
    return _GBufferWalk.apply(*inputs, cells, layer_image, ints, floats, radius, thickness, scale, growth,
                              scalar_lanes(o["lanes"]), full_walk("exact", gbuffer, packed[0]))


class _GBufferWalk(torch.autograd.Function):
    """The exact union's walk over ``(positions, normals, inverse, depth, valid, intrinsics)``, the edge-aware
    fetch's ``cells`` and the thickness ``layer`` (each empty where unused), and ``exact_backward`` (``full``: on
    CUDA, the full build's kernels)."""

    @staticmethod
    def forward(ctx, positions, normals, inverse, depth, valid, intrinsics, cells, layer, ints, floats, radius,
                thickness, scale, growth, scalar, full):
        wanted = any(ctx.needs_input_grad[10:14])  # the scalars': the walk's per-pixel derivatives
        channels, name = _gradients_walk(growth) if wanted else (1, "exact")
        frame = (positions, normals, inverse, depth, valid, intrinsics)
        none = torch.empty(0, device=depth.device)
        if depth.is_cuda:
            out = torch.empty(depth.shape[0], channels, *depth.shape[1:], device=depth.device)
            launch_cuda(f"tao_walk_{name}", depth.device, [*frame, none, cells, layer, out, ints, floats],
                        tuple(depth.shape), full=full)
        else:
            out = cpu_kernels().walk(name, *frame, none, cells, layer, ints, floats, channels, scalar)
        ctx.scalar, ctx.full = scalar, full
        ctx.dtypes = (radius.dtype, thickness.dtype, scale.dtype, None if growth is None else growth.dtype)
        ctx.save_for_backward(*frame, cells, layer, ints, floats, out[:, 1:] if wanted else none)
        return out[:, :1].contiguous()

    @staticmethod
    @first_order
    def backward(ctx, grad):
        *frame, cells, layer, ints, floats, jacobian = ctx.saved_tensors
        grad = grad.to(torch.float32).contiguous()
        depth, intrinsics = frame[3], frame[5]
        camera = ctx.needs_input_grad[5]  # the intrinsics' gradients, per pixel (B, H, W, 4)
        if depth.is_cuda:  # the pixels' own gradients, and their taps' scattered atomically into one image
            g_pos, g_nrm, taps = torch.zeros_like(frame[0]), torch.zeros_like(frame[1]), torch.zeros_like(frame[0])
            g_depth, g_inv, g_layer = torch.zeros_like(depth), torch.zeros_like(depth), torch.zeros_like(depth)
            g_camera = depth.new_zeros((*depth.shape, 4) if camera else (0,))  # (empty: a null pointer)
            launch_cuda("tao_exact_backward", depth.device,
                        [*frame, cells, layer, grad, g_pos, g_nrm, g_depth, taps, g_inv, g_layer, g_camera, ints,
                         floats], tuple(depth.shape), full=ctx.full)
            g_pos += taps
        else:
            g_pos, g_nrm, g_inv, g_depth, g_layer, g_camera = grad_kernels().exact_backward(
                grad, *frame, cells, layer, ints, floats, camera, ctx.scalar)
        g_intrinsics = g_camera.double().sum((1, 2)).to(intrinsics.dtype) if camera else None
        scalars = [None] * 4
        if jacobian.numel():  # (B, 3 or 4, H, W): d visibility / d radius, offset, scale (, growth)
            sums = (grad.double() * jacobian.double()).sum(dim=(0, 2, 3))
            scalars = [sums[k].to(ctx.dtypes[k]) if ctx.needs_input_grad[10 + k] else None
                       for k in range(jacobian.shape[1])] + [None] * (4 - jacobian.shape[1])
        return (g_pos, g_nrm, g_inv, g_depth, None, g_intrinsics, None, g_layer if layer.numel() else None, None, None,
                *scalars, None, None)


class _ExactWalk(torch.autograd.Function):
    @staticmethod
    def forward(ctx, gbuffer, normals, radius, thickness, options, scale, layer, growth):
        wanted = bool(ctx.needs_input_grad[2] or ctx.needs_input_grad[3]
                      or (scale is not None and ctx.needs_input_grad[5])
                      or (growth is not None and ctx.needs_input_grad[7]))
        out = _walk(gbuffer, normals, radius, thickness, scale, growth, layer, options, wanted)
        if wanted:
            ctx.save_for_backward(out[:, 1:].contiguous())
        ctx.dtypes = (radius.dtype, thickness.dtype, *(None if t is None else t.dtype for t in (scale, growth)))
        return out[:, :1].contiguous()

    @staticmethod
    @first_order
    def backward(ctx, grad):
        (jacobian,) = ctx.saved_tensors  # (B, 3 or 4, H, W): d visibility / d radius, offset, scale (, growth)
        sums = (grad.double() * jacobian.double()).sum(dim=(0, 2, 3))
        g_scale, g_growth = (None if ctx.dtypes[k] is None else sums[k].to(ctx.dtypes[k]) for k in (2, 3))
        return None, None, sums[0].to(ctx.dtypes[0]), sums[1].to(ctx.dtypes[1]), None, g_scale, None, g_growth


#: what this kernel covers beyond the exact union's hard kernel: every mode (one forward, one gradient)
_MODES = ("hard", "soft", "straight_through")


def exact_soft_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`exact_soft` computes ``module(gbuffer)`` and its gradients (a ``BitmaskAO`` with
    ``union="exact"``, any mode: visibility only, a thickness of the form ``scale * value + offset``, a float32
    CPU or CUDA G-buffer), else why not. Gradients of the radius, of the model's scalar parameters (the offset
    ``thickness``, the back-face model's ``thickness_scale``, the linear model's ``thickness_slope``), of the
    G-buffer (depth, positions, normals, the intrinsics, the back-face depth) and of what makes a layer (a map, a
    table, the net's weights)."""
    if getattr(module, "union", None) != "exact":
        return "union other than 'exact' (the sector kernels')"
    reason = options_uncovered(module, gbuffer, modes=_MODES, weightings=("uniform", "cosine"),
                               variants=("default", "exact"), extra=_EXACT, layers=True, growth=True)
    if reason is not None:
        return reason
    if module.steps > EXACT_MAX_STEPS:
        return f"steps={module.steps} (the exact union's kernel holds {EXACT_MAX_STEPS} per side)"
    return None


def exact_soft_forward(module, gbuffer: GBuffer) -> dict:
    """``module(gbuffer)``'s ``{"visibility": (B,1,H,W)}`` for a module :func:`exact_soft_covers` accepts."""
    form = module_thickness(module, gbuffer)
    vis = exact_soft(gbuffer, gbuffer.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                     radius=module.radius, thickness=form.offset, layer=form.layer,
                     layer_scale=None if form.read == "constant" else form.scale, thickness_read=form.read,
                     thickness_growth=form.growth, step_power=module.step_power, min_step_px=module.min_step_px, jitter=module.jitter,
                     seed=module.seed, noise=module.noise, stagger=module.stagger, fetch=module.fetch,
                     border=module.border, weighting=module.weighting, thickness_direction=module.thickness_direction,
                     clip_to_radius=module.clip_to_radius, sample_extent=module.sample_extent,
                     sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                     slice_sampling=module.slice_sampling)
    return {"visibility": vis}
