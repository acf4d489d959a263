"""The hard bitmask kernels: ``BitmaskAO(variant="default" | "hdrp" | "ssilvb_glsl", mode="hard")`` in one fused pass.

:func:`bitmask_hard` / :func:`bitmask_outputs` walk exactly what the ``"default"`` and ``"hdrp"`` variants' tensor
path walks (the same slice directions, jitter, step placement, fetch, border and the variant's sector rule; see
:mod:`torch_ao.methods.bitmask`), with uniform or cosine sector weights, and return the same visibility, indirect
light and bent normals. :func:`ssilvb_glsl_hard` is the ``"ssilvb_glsl"``
variant (the SSILVB GLSL article's shader, :mod:`torch_ao.methods.bitmask_glsl`): AO and indirect light.
Both are the one walk of ``walk.h``, with the accumulator of ``bitmask.h`` or, with the shader's step
placement and jitter, of ``bitmask_glsl.h``; they agree with the tensor path by tolerance (hard masks on
all but a few pixels where an angle lies within rounding of a sector edge; tests/test_kernels.py,
tests/test_kernels_glsl.py), not by reproducing torch's float operations.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from ..gbuffer import GBuffer
from ..sectors import ROUNDINGS
from ..thickness import ThicknessLayer, matching
from .coverage import gbuffer_uncovered, option_uncovered
from .build import cpu_kernels, grad_kernels
from .frame import first_order, light_input, scalar_lanes, scale_derivative
from .launch import full_walk, launch_cuda, packed_inputs, run_walk, walk_settings
from .walk_grad import wants_gradient

__all__ = ["bitmask_hard", "bitmask_outputs", "exact_hard", "exact_covers", "exact_forward", "ssilvb_glsl_hard",
           "glsl_walk_settings",
           "kernel_covers", "options_uncovered", "module_thickness",
           "KernelOutputs"]

class KernelOutputs(NamedTuple):
    """A kernel's outputs: ``visibility`` ``(B,1,H,W)``; ``indirect``, ``bent_normal`` ``(B,3,H,W)`` or ``None``."""

    visibility: torch.Tensor
    indirect: torch.Tensor | None = None
    bent_normal: torch.Tensor | None = None


def bitmask_outputs(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: float,
                    thickness: float, step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True,
                    seed: int = 0, noise: str = "ign", stagger: bool = False, fetch: str = "bilinear", border: str = "drop", rounding: str = "ceil",
                    sector_epsilon: float = 0.01, weighting: str = "uniform", indirect: bool = False,
                    bent_normals: bool = False, layer: torch.Tensor | None = None, layer_scale: float = 1.0,
                    thickness_read: str | None = None, thickness_growth: float = 0.0, variant: str = "default",
                    azimuth: str = "view", thickness_direction: str = "view", clip_to_radius: bool = False,
                    sample_extent: str = "radius", slice_sampling: str = "uniform",
                    lanes: str = "simd") -> KernelOutputs:
    """The ``"default"`` (or ``"hdrp"``) variant's hard visibility ``(B,1,H,W)`` in ``[0, 1]`` (1 = unoccluded;
    background pixels 1) and, when asked, its indirect light and bent normals ``(B,3,H,W)`` (background: 0 and
    ``normals``).

    Args:
        gbuffer: a float32 G-buffer, CPU or CUDA (with ``light`` for ``indirect``); normals: its ``(B,3,H,W)`` unit view-space normals (as the module uses
            them, e.g. ``gbuffer.view_normals()``).
        slices, steps: directions per pixel (uniform around the view vector) and samples per side.
        radius, thickness: world units (scalars); with ``layer`` ``(B,1,H,W)``, read at each sample as depth
            is, the thickness there is ``layer_scale * layer + thickness`` (the back-face layer, a map, the
            net's map). ``thickness_read`` (default ``"layer"`` with a layer, else ``"constant"``) reads another
            value in place of the layer's: ``"first_tap"`` the layer at the first tap, ``"depth"`` the sample's
            depth (:class:`~torch_ao.thickness.ThicknessLayer`; :func:`thickness_options` gives all four from it);
            ``thickness_growth`` (per world unit) multiplies it by ``1 + growth * |sample - pixel|``;
            step_power, min_step_px (pixels), jitter, seed, noise, stagger, fetch (``"bilinear"``, ``"nearest"``,
            ``"edge_aware"``), border (``"drop"``/``"clamp"``), rounding, sector_epsilon (sectors),
            weighting (``"uniform"``/``"cosine"``), indirect, bent_normals, variant (:data:`HARD_VARIANTS`, or
            ``"exact"``: its angles are ``"default"``'s), azimuth (``"view"``/``"screen"``), thickness_direction,
            clip_to_radius, sample_extent (the ``"exact"`` variant's segment geometry, with the sector union; the
            ``"hdrp"`` variant's rule has none), slice_sampling: as :class:`~torch_ao.BitmaskAO`. Where
            :func:`needs_hard_backward`, the outputs have a backward (``_HardWalk``).
        lanes: ``"simd"`` (the CPU's vector lanes) or ``"scalar"`` (one pixel at a time: the CUDA
            kernel's arithmetic).

    Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built here.
    """
    if variant not in HARD_VARIANTS + ("exact",):
        raise ValueError(f"variant: expected one of {HARD_VARIANTS + ('exact',)}, got {variant!r}")
    radius = torch.as_tensor(radius)
    settings = walk_settings(slices=slices, steps=steps, radius=radius.detach(), step_power=step_power,
                             min_step_px=min_step_px, jitter=jitter, seed=seed, noise=noise, stagger=stagger,
                             fetch=fetch, border=border, sphere_extent=sample_extent == "sphere", azimuth=azimuth,
                             slice_sampling=slice_sampling)
    acc_ints = [ROUNDINGS.index(rounding), weighting == "cosine", bool(indirect), bool(bent_normals),
                thickness_read_index(thickness_read, layer), int(variant == "hdrp"), thickness_direction == "depth",
                bool(clip_to_radius)]
    acc_floats = [thickness, sector_epsilon, layer_scale, thickness_growth, radius.detach()]
    channels = 1 + 3 * bool(indirect) + 3 * bool(bent_normals)
    light = light_input(gbuffer, indirect) if indirect else None
    if needs_hard_backward(gbuffer, normals, weighting=weighting, indirect=indirect, bent_normals=bent_normals,
                           light=light, radius=radius, slice_sampling=slice_sampling):
        if gbuffer.depth.device.type == "cpu":
            cpu_kernels(), grad_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
        inputs, (light, cells, layer_image), ints, floats = packed_inputs(
            gbuffer, normals, settings, acc_ints, acc_floats, light, None if layer is None else layer.detach())
        out = _HardWalk.apply(*inputs, light, cells, layer_image, ints, floats, channels, int(slices),
                              scalar_lanes(lanes), radius if indirect else None, "",
                              full_walk("bitmask", gbuffer, settings))
    else:
        out = run_walk("bitmask", gbuffer, normals, settings, acc_ints, acc_floats, channels, light=light,
                       backface=layer, lanes=lanes)
    return hard_outputs(out, gbuffer, normals, weighting=weighting, slice_sampling=slice_sampling, indirect=indirect,
                        bent_normals=bent_normals, light=light, radius=radius if fetch != "nearest" else None)


#: the variants :func:`bitmask_outputs` walks, in bitmask.h's SectorAngles order
HARD_VARIANTS = ("default", "hdrp")


def needs_hard_backward(gbuffer: GBuffer, normals: torch.Tensor | None, *, weighting: str, indirect: bool,
                        bent_normals: bool, light: torch.Tensor | None = None, radius=None,
                        slice_sampling: str = "uniform") -> bool:
    """Whether a hard walk's outputs have gradients that autograd records, so that :func:`bitmask_outputs` and
    :func:`ssilvb_glsl_hard` run their backward (``_HardWalk``). Hard masks have none, but what they weight does:
    the cosine weights and the bent normals follow the slice (through the G-buffer and the ``normals``), and so
    does the weight of a slice drawn by the projected normal's density; indirect light also its ``light`` and,
    through the samples' extent, the ``radius``."""
    graded = weighting == "cosine" or bool(bent_normals) or bool(indirect) or slice_sampling == "projected_normal"
    return graded and wants_gradient(gbuffer, normals, *((light, radius) if indirect else ()))


def hard_outputs(out: torch.Tensor, gbuffer: GBuffer, normals: torch.Tensor, *, weighting: str, indirect: bool,
                 bent_normals: bool, light: torch.Tensor | None, radius=None, slice_sampling: str = "uniform"
                 ) -> KernelOutputs:
    """A hard walk's channels ``out`` (the visibility, then the light and the bent normals' sum where asked) as
    outputs, each on the autograd graph where its tensor-path twin is (one kernel call gives them all, so each would
    carry the graph of every input): the visibility through the weights that follow the slice (cosine, or a slice
    drawn by the projected normal's density), the bent normals through the slice's frame, both from the G-buffer and
    the ``normals``; the indirect light through those, its ``light`` and the ``radius`` (where its samples' reads
    move with it: ``None`` for a nearest fetch's or the shader's floored texels)."""
    on_frame = wants_gradient(gbuffer, normals)
    vis = out[:, :1]
    if not (on_frame and (weighting == "cosine" or slice_sampling == "projected_normal")):
        vis = vis.detach()
    lit = out[:, 1:4] if indirect else None
    if lit is not None and not wants_gradient(gbuffer, normals, light, radius):
        lit = lit.detach()
    bent = out[:, 1 + 3 * bool(indirect):] if bent_normals else None
    if bent is not None and not on_frame:
        bent = bent.detach()
    return KernelOutputs(vis, lit, bent)


class _HardWalk(torch.autograd.Function):
    """The hard sector walk over ``(positions, normals, inverse, depth, valid, intrinsics)`` (and the light, the
    edge-aware fetch's ``cells``, the thickness layer), recording each pixel's slices' occupied sectors, with
    ``hard_backward``: the gradients of its cosine weights and bent normals to the pixels' own positions, normals
    and depth (the masks have none), and of its indirect light to the senders' light, normals and positions at the
    taps; the radius' by Euler's identity (the walk is scale-invariant: the masks' angles, the senders' directions
    and the steps in pixels do not change when positions, depth and radius scale together; the thickness moves
    only the masks, which have no gradient): ``R dL/dR = -sum(dL/dP . P + dL/ddepth depth - dL/dinverse inverse)``.
    The intrinsics move only the steps on screen, so the cosine weights' and bent normals' gradient to them is the
    positions' own, which autograd chains through ``walk_inputs``' unprojection; indirect light's samples move with
    them (its light, normals and position at the taps): its backward chains those to them per pixel. Both
    :data:`HARD_VARIANTS` (their ``ints`` name the variant's angles: HDRP's slice frame in the backward's tangents).

    ``kernel`` ``"_glsl"``: the ``"ssilvb_glsl"`` variant's walk (``ints``/``floats`` its packed settings) with indirect
    light, whose record is its carried mask after each slice and whose backward is its light's (walk_grad.h's
    ``hard_grad_block`` of ``GlslAccumulator``): to the light, the senders' normals and positions at the taps and
    the pixel's own normal and position. Its texels are floored (they do not move): no radius (``None``) or
    intrinsics gradient of its own (the positions carry the intrinsics'). ``full``: on CUDA, the full build's
    kernels (:func:`~torch_ao.kernels.launch.full_walk`)."""

    @staticmethod
    def forward(ctx, positions, normals, inverse, depth, valid, intrinsics, light, cells, layer, ints, floats, channels,
                slices, scalar, radius, kernel, full):
        frame = (positions, normals, inverse, depth, valid, intrinsics)
        if depth.is_cuda:
            B, H, W = depth.shape
            out = torch.empty(B, channels, H, W, device=depth.device)
            record = torch.empty(B, H, W, slices, dtype=torch.int32, device=depth.device)
            launch_cuda(f"tao_record_hard{kernel}", depth.device,
                        [*frame, light, cells, layer, out, record, ints, floats], (B, H, W), full=full)
        else:
            out, record = grad_kernels().hard_record(*frame, light, cells, layer, ints, floats, channels, slices, scalar)
        ctx.scalar, ctx.kernel, ctx.full = scalar, kernel, full
        ctx.save_for_backward(*frame, light, cells, layer, ints, floats, record, radius)
        return out

    @staticmethod
    @first_order
    def backward(ctx, grad):
        *frame, light, cells, layer, ints, floats, record, radius = ctx.saved_tensors
        grad = grad.to(torch.float32).contiguous()
        positions, depth, valid, inverse = frame[0], frame[3], frame[4], frame[2]
        # indirect light's samples move with the intrinsics (the default variant's; the shader's texels do not)
        camera = ctx.needs_input_grad[5] and light.numel() > 0 and not ctx.kernel
        if depth.is_cuda:  # the pixels' own gradients, and their taps' scattered atomically into images of their own
            g_pos, g_nrm, g_depth = torch.zeros_like(positions), torch.zeros_like(frame[1]), torch.zeros_like(depth)
            taps, senders, g_inv = torch.zeros_like(positions), torch.zeros_like(frame[1]), torch.zeros_like(depth)
            g_light = torch.zeros(light.shape if light.numel() else (0,), device=depth.device)
            g_camera = depth.new_zeros((*depth.shape, 4) if camera else (0,))  # (empty: a null pointer)
            launch_cuda(f"tao_hard_backward{ctx.kernel}", depth.device, [*frame, light, cells, layer, grad, record, g_pos, g_nrm,
                                                            g_depth, taps, g_inv, senders, g_light, g_camera, ints,
                                                            floats], tuple(depth.shape), full=ctx.full)
            g_pos += taps
            g_nrm += senders
        else:
            g_pos, g_nrm, g_inv, g_depth, g_light, g_camera = grad_kernels().hard_backward(
                grad, *frame, light, cells, layer, ints, floats, record, camera, ctx.scalar)
        g_intrinsics = g_camera.double().sum((1, 2)).to(frame[5].dtype) if camera else None
        g_radius = None
        if radius is not None and ctx.needs_input_grad[14]:  # Euler's identity (the class docstring)
            along = scale_derivative(valid, (g_pos, positions), (g_depth, depth), (g_inv, -inverse))
            g_radius = (-along / radius.to(torch.float64)).to(radius.dtype)
        g_light = g_light if light.numel() else None
        return (g_pos, g_nrm, g_inv, g_depth, None, g_intrinsics, g_light, None, None, None, None, None, None, None,
                g_radius, None, None)


def exact_hard(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: float, thickness: float,
               layer: torch.Tensor | None = None, layer_scale: float = 1.0, thickness_read: str | None = None,
               step_power: float = 1.0,
               min_step_px: float = 0.25,
               jitter: bool = True, seed: int = 0, noise: str = "ign", stagger: bool = False, fetch: str = "edge_aware", border: str = "drop",
               weighting: str = "cosine", thickness_direction: str = "depth", clip_to_radius: bool = True,
               sample_extent: str = "sphere", sector_epsilon: float = 0.0, azimuth: str = "view",
               thickness_growth: float = 0.0, slice_sampling: str = "uniform", lanes: str = "simd") -> torch.Tensor:
    """Visibility ``(B,1,H,W)`` (background 1) of the exact union of a slice's occluder intervals
    (``union="exact"``, the ``"exact"`` variant's rule; its defaults here), in one fused pass.

    Args:
        gbuffer: a float32 G-buffer (CPU or CUDA); normals: its ``(B,3,H,W)`` unit view-space normals.
        slices, steps (<= 32 per side); radius, thickness, layer, layer_scale, thickness_read, thickness_growth: as
            :func:`bitmask_outputs`;
            step_power, min_step_px
            (pixels), jitter, seed, noise, stagger, fetch (``"nearest"``, ``"bilinear"``, ``"edge_aware"``), border, weighting,
            thickness_direction, clip_to_radius, sample_extent, sector_epsilon, azimuth (``"view"``/``"screen"``),
            slice_sampling: as :class:`~torch_ao.BitmaskAO`.
        lanes: on CPU, ``"simd"`` or ``"scalar"``.
    """
    settings = walk_settings(slices=slices, steps=steps, radius=radius, step_power=step_power, min_step_px=min_step_px,
                             jitter=jitter, seed=seed, noise=noise, stagger=stagger, fetch=fetch, border=border,
                             sphere_extent=sample_extent == "sphere", azimuth=azimuth, slice_sampling=slice_sampling)
    return run_walk("exact", gbuffer, normals, settings,
                    [weighting == "cosine", thickness_direction == "depth", bool(clip_to_radius),
                     thickness_read_index(thickness_read, layer), False],
                    [thickness, layer_scale, radius, sector_epsilon, thickness_growth], 1, backface=layer, lanes=lanes)


def module_thickness(module, gbuffer: GBuffer) -> ThicknessLayer:
    """A bitmask module's thickness model with its current parameters as the kernels read it (a model
    :func:`options_uncovered` accepted: ``t = scale * value + offset``)."""
    return module.bound_thickness().layer(gbuffer)


def thickness_options(form: ThicknessLayer) -> dict:
    """The kernels' ``thickness``, ``layer``, ``layer_scale``, ``thickness_read`` arguments of ``form`` (and its
    ``thickness_growth`` where it has one)."""
    growth = {} if form.growth is None else {"thickness_growth": form.growth.detach()}
    return dict(thickness=form.offset.detach(), layer=None if form.layer is None else form.layer.detach(),
                layer_scale=form.scale.detach(), thickness_read=form.read, **growth)


#: bitmask.h's ThicknessRead, in its order
THICKNESS_READS = ("constant", "layer", "first_tap", "depth")


def thickness_read_index(read: str | None, layer: torch.Tensor | None) -> int:
    """The packed int of ``read`` (``None``: ``"layer"`` with a ``layer``, else ``"constant"``); ``ValueError``
    naming the argument for an unknown read or a layer read without its layer."""
    read = read or ("layer" if layer is not None else "constant")
    if read not in THICKNESS_READS:
        raise ValueError(f"thickness_read: expected one of {THICKNESS_READS}, got {read!r}")
    if read in ("layer", "first_tap") and layer is None:
        raise ValueError(f"layer: thickness_read={read!r} reads a (B,1,H,W) layer; none was given")
    return THICKNESS_READS.index(read)


def bitmask_hard(gbuffer: GBuffer, normals: torch.Tensor, **options) -> torch.Tensor:
    """Hard visibility ``(B,1,H,W)`` of the ``"default"`` (or ``"hdrp"``) variant: :func:`bitmask_outputs`'s first
    output (same arguments, visibility only)."""
    options.update(indirect=False, bent_normals=False)
    return bitmask_outputs(gbuffer, normals, **options).visibility


def glsl_walk_settings(slices: int, steps: int, radius, jitter: bool, numerics: str):
    """The packed walk settings of the ``"ssilvb_glsl"`` shader's loops: ``sliceCount + 1`` slices of ``sampleCount +
    1`` steps, one side each, nearest texels clamped to the image, its one jitter (in float16 with
    ``"mesa_mediump"`` numerics)."""
    return walk_settings(slices=int(slices) + 1, steps=int(steps) + 1, radius=torch.as_tensor(radius).detach(),
                         jitter=jitter, seed=0, fetch="nearest", border="clamp", placement="glsl", full_circle=True,
                         azimuth="screen", noise="glsl_mediump" if numerics == "mesa_mediump" else "glsl")


def ssilvb_glsl_hard(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius,
                     thickness: float, jitter: bool = True, rounding: str = "ceil", numerics: str = "ieee",
                     indirect: bool = False, layer: torch.Tensor | None = None, layer_scale: float = 1.0,
                     thickness_read: str | None = None, thickness_growth: float = 0.0,
                     lanes: str = "simd") -> KernelOutputs:
    """The ``"ssilvb_glsl"`` variant in hard mode: visibility ``(B,1,H,W)`` (background 1; may exceed 1,
    as the shader's) and, with ``indirect``, its light ``(B,3,H,W)`` (background 0).

    Args:
        gbuffer, normals: as :func:`bitmask_outputs` (CPU or CUDA); slices, steps: the shader's ``sliceCount``
            (>= 2) and ``sampleCount`` (>= 1); radius (world units, a float or 0-d tensor), thickness (world
            units; with ``layer``, ``layer_scale``, ``thickness_read`` and ``thickness_growth`` a model read at each
            sample's texel, as :func:`bitmask_outputs`'), jitter, rounding, numerics (``glsl_numerics``): as :class:`~torch_ao.BitmaskAO`.
        lanes: on CPU, ``"simd"`` or ``"scalar"``.

    With ``indirect`` and autograd recording through the G-buffer, the normals or the light, the light has a
    backward (``_HardWalk``'s ``"_glsl"`` kernel): to the light, the normals and the positions (so depth and
    intrinsics); the visibility (hard masks) and the radius (the texels are floored) have none.
    """
    settings = glsl_walk_settings(slices, steps, radius, jitter, numerics)
    acc_ints = [ROUNDINGS.index(rounding), bool(indirect), numerics != "ieee", thickness_read_index(thickness_read, layer)]
    acc_floats, channels = [thickness, layer_scale, thickness_growth], 4 if indirect else 1
    light = light_input(gbuffer, indirect) if indirect else None
    layer = None if layer is None else layer.detach()  # (hard masks: the thickness has no gradient)
    if needs_hard_backward(gbuffer, normals, weighting="uniform", indirect=indirect, bent_normals=False, light=light):
        if gbuffer.depth.device.type == "cpu":
            cpu_kernels(), grad_kernels()  # built (or KernelUnavailable raised) before any graph is recorded
        inputs, (light, cells, layer), ints, floats = packed_inputs(gbuffer, normals, settings, acc_ints, acc_floats,
                                                                    light, layer)
        out = _HardWalk.apply(*inputs, light, cells, layer, ints, floats, channels, int(slices) + 1,
                              scalar_lanes(lanes), None, "_glsl", False)
    else:
        out = run_walk("glsl", gbuffer, normals, settings, acc_ints, acc_floats, channels, light=light, backface=layer,
                       lanes=lanes)
    return hard_outputs(out, gbuffer, normals, weighting="uniform", indirect=indirect, bent_normals=False, light=light)


#: options of a module the kernels reproduce: ``None`` for any value, else the values they cover
_COVERED = {
    # the walk's and every module's options
    "preset": None, "slices": None, "steps": None, "radius": None, "step_power": None, "min_step_px": None,
    "jitter": None, "seed": None, "noise": None, "stagger": None, "slice_sampling": ("uniform", "projected_normal"), "fetch": ("nearest", "bilinear"), "border": None, "azimuth": ("view", "screen"), "normals": None,
    "chunk_size": None, "recompute": None, "trainable": None, "backend": None,
    "resolution": None,  # the kernel walks the (smaller) G-buffer it is given
    # the bitmask family's
    "variant": ("default", "ssilvb_glsl"), "mode": ("hard", "straight_through"), "tau": None, "rounding": None,
    "weighting": ("uniform", "cosine"), "union": ("sectors",), "clip_to_radius": (False,),
    "thickness_direction": ("view",), "sample_extent": ("radius",), "thickness": None, "thickness_growth": (None,),
    "indirect": (False, True), "bent_normals": (False, True), "ambient": (None, "a colour"),
    "ambient_directions": None, "sector_epsilon": None, "glsl_numerics": None,
}
#: what the ``"ssilvb_glsl"`` variant's walk ignores (its shader places its own samples and reads their nearest texel,
#: clamped to the image), and its slices: the shader's
_GLSL = {"azimuth": None, "fetch": None, "border": None, "slice_sampling": ("uniform",)}


def kernel_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when a kernel computes ``module(gbuffer)`` (a ``BitmaskAO``), else why not.

    Every option of the module must be one the kernels know, at a value they reproduce (an option they
    do not know, e.g. one added to the module later, sends the call to the tensor path). Hard masks
    have no gradient, so uniform hard visibility is covered with autograd on too; cosine weights and bent
    normals have gradients in hard mode too (through the slice: the normals and positions), which the hard
    kernel's backward computes (the intrinsics' too); indirect light has one to the light, the sample positions and
    the intrinsics (either of :data:`HARD_VARIANTS`: the ``"hdrp"`` variant's too); the ``"ssilvb_glsl"`` shader's
    light to the light, the normals and the positions (its own backward, :func:`ssilvb_glsl_hard`'s); straight-through
    mode (hard values, soft gradients) without a gradient, every output and variant: its values are hard mode's.
    """
    reason = options_uncovered(module, gbuffer, modes=("hard", "straight_through"), weightings=("uniform", "cosine"),
                               variants=("default", "hdrp", "exact", "ssilvb_glsl"), outputs=True,
                               extra=_HARD.get(module.variant), layers=True, growth=True)
    if reason is not None:
        return reason
    if module.mode == "straight_through" and _needs_grad(module, gbuffer):
        return "a straight-through gradient is asked for"  # (hard mode has none: its values are the same)
    # in hard mode every variant's graded outputs (needs_hard_backward) have the kernel's backward
    return None


#: what the hard kernel of the ``"default"`` and ``"hdrp"`` variants covers beyond the options every bitmask kernel
#: does
_HARD = {variant: {"fetch": ("nearest", "bilinear", "edge_aware"), "clip_to_radius": (False, True),
                   "thickness_direction": ("view", "depth"), "sample_extent": ("radius", "sphere")}
         for variant in HARD_VARIANTS + ("exact",)}
#: what the exact union's kernel covers beyond the hard kernels' options
_EXACT = {"variant": ("default", "exact"), "union": ("exact",), "clip_to_radius": (False, True),
          "thickness_direction": ("view", "depth"), "sample_extent": ("radius", "sphere"),
          "fetch": ("nearest", "bilinear", "edge_aware")}
#: the most steps per side the exact union's kernel holds (kMaxIntervals / 2 in bitmask.h)
EXACT_MAX_STEPS = 32


def exact_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`exact_hard` computes ``module(gbuffer)`` (a ``BitmaskAO`` with ``union="exact"``:
    the ``"exact"`` variant), else why not. Visibility only, hard mode, a thickness of the form ``scale * value +
    offset`` (:class:`~torch_ao.thickness.ThicknessLayer`);
    the exact union has gradients in hard mode too, so only when no gradient is asked for."""
    if getattr(module, "union", None) != "exact":
        return "union other than 'exact' (the hard kernels')"
    reason = options_uncovered(module, gbuffer, modes=("hard",), weightings=("uniform", "cosine"),
                               variants=("default", "exact"), extra=_EXACT, layers=True, growth=True)
    if reason is not None:
        return reason
    if module.steps > EXACT_MAX_STEPS:
        return f"steps={module.steps} (the exact union's kernel holds {EXACT_MAX_STEPS} per side)"
    if _needs_grad(module, gbuffer) or (torch.is_grad_enabled() and any(
            getattr(module, name).requires_grad for name in module.thickness_model.parameters())):
        return "a gradient is asked for (the exact union has one in hard mode)"
    return None


def exact_forward(module, gbuffer: GBuffer) -> dict:
    """``module(gbuffer)``'s ``{"visibility": (B,1,H,W)}`` for a module :func:`exact_covers` accepts."""
    vis = exact_hard(gbuffer, gbuffer.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                     radius=module.radius.detach(), **thickness_options(module_thickness(module, gbuffer)),
                     step_power=module.step_power,
                     min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, noise=module.noise,
                     stagger=module.stagger, fetch=module.fetch,
                     border=module.border, weighting=module.weighting, thickness_direction=module.thickness_direction,
                     clip_to_radius=module.clip_to_radius, sample_extent=module.sample_extent,
                     sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                     slice_sampling=module.slice_sampling)
    return {"visibility": vis}


#: the outputs beyond visibility, for a kernel that computes visibility only
_VISIBILITY_ONLY = {"indirect": (False,), "bent_normals": (False,), "ambient": (None,)}


def options_uncovered(module, gbuffer: GBuffer, *, modes: tuple[str, ...], weightings: tuple[str, ...],
                      variants: tuple[str, ...] = ("default",), outputs: bool = False,
                      extra: dict | None = None,
                      layers: bool = False, growth: bool = False) -> str | None:
    """Why a bitmask kernel walking one of ``variants`` in one of ``modes`` with one of ``weightings`` (and,
    with ``outputs``, indirect light, bent normals and a constant ambient; else visibility only) does not
    reproduce ``module(gbuffer)`` (an option it does not know or covers at another value, a thickness it
    does not read: see :func:`thickness_uncovered`, a G-buffer other than float32 on the CPU or CUDA), or
    ``None``. ``layers``: whether the kernel reads a thickness layer per sample; ``growth``:
    whether it grows the thickness with the sample's distance (values only: none of the kernels with gradients)."""
    values = dict(getattr(module, "values", {}))
    for name in ("variant", "mode", "weighting", "union", "clip_to_radius", "thickness_direction", "sample_extent",
                 "azimuth", "thickness_growth", "ambient"):
        values[name] = getattr(module, name, "?")  # resolved per variant, kept as attributes
    values["indirect"] = getattr(module, "want_indirect", "?")
    values["bent_normals"] = getattr(module, "want_bent", "?")
    if getattr(module, "ambient_constant", None) is not None:
        values["ambient"] = "a colour"
    covered = {**_COVERED, "mode": modes, "weighting": weightings, "variant": variants,
               **({} if outputs else _VISIBILITY_ONLY), **(_GLSL if values["variant"] == "ssilvb_glsl" else {}),
               **(extra or {}), **({"thickness_growth": None} if growth else {})}
    reason = option_uncovered(values, covered)
    if reason is not None:
        return reason
    reason = thickness_uncovered(module, layers, growth)
    if reason is not None:
        return reason
    return gbuffer_uncovered(gbuffer)


def thickness_uncovered(module, layers: bool, growth: bool = False) -> str | None:
    """Why a bitmask kernel cannot read ``module``'s thickness model, or ``None``. Every kernel reads one
    scalar; one that reads ``layers`` also every model of the form ``scale * value + offset``
    (:attr:`~torch_ao.thickness.Thickness.kernel_read`: the back-face layer, a map, the net's map, a
    per-object table, the linear model in depth); one that grows the thickness with the sample's distance (``growth``)
    also a model's growth."""
    thickness, model = getattr(module, "thickness", None), getattr(module, "thickness_model", None)
    if model is None:
        scalar = isinstance(thickness, torch.Tensor) and thickness.dim() == 0
        return None if scalar else "a thickness other than one scalar"
    model = matching(model, thickness)
    name = type(model).__name__
    if model.growth is not None and not growth:
        return "a thickness growth (the hard kernels grow it; this one does not)"
    if model.kernel_read is None:
        return f"thickness model {name} (not of the form scale * value + offset)"
    if model.kernel_read != "constant" and not layers:
        return f"thickness model {name} (this kernel reads one scalar thickness)"
    return None


def _needs_grad(module, gbuffer: GBuffer) -> bool:
    """Whether autograd would record a gradient of the G-buffer's tensors or of the module's radius and its
    thickness model's parameters."""
    if not torch.is_grad_enabled():
        return False
    tensors = [gbuffer.depth, gbuffer.normals, gbuffer.light, gbuffer.position] + _parameter_tensors(module)
    return any(isinstance(t, torch.Tensor) and t.requires_grad for t in tensors)


def _parameter_tensors(module) -> list:
    """A bitmask module's radius and its thickness model's parameters."""
    model = getattr(module, "thickness_model", None)
    names = ["thickness"] if model is None else list(model.parameters())
    return [module.radius] + [getattr(module, name) for name in names]
