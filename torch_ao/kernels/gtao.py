"""The horizon kernels: ``GTAO`` (every variant) and ``HBAO`` forward in one fused pass (the one walk of
``walk.h`` with the accumulators of ``horizon.h``).

It walks what the tensor path walks (the same slice directions, jitter, step placement, fetch
and border, :mod:`torch_ao.walk`) with the accumulators of :mod:`torch_ao.methods.gtao` (a horizon per
side, the clamped arc integral of :func:`torch_ao.ops.arc_integral`), and returns the per-pixel sums
over slices; the module's own ``GTAOAccumulator.finish`` turns them into the outputs, so the
normalisation, final power and multi-bounce fit are the tensor path's code; the sums agree with the
tensor path's to float rounding (tests/test_kernels_gtao.py). ``HBAO`` is the same walk over the full circle with its accumulator
(:mod:`torch_ao.methods.hbao`), finished the same way. Where autograd records (CPU, CUDA), both run with the
walk's backward (:mod:`torch_ao.kernels.walk_grad`); :func:`gradient_uncovered` says which gradients it
does not give.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from ..gbuffer import GBuffer
from ..ops import UE4_EPSILON
from ..walk import SLICE_SAMPLINGS
from .coverage import call_uncovered
from .launch import run_walk, walk_settings
from .walk_grad import MAX_CUDA_STEPS, differentiable_walk, gbuffer_requires_grad, wants_gradient

__all__ = ["gtao_sums", "gtao_forward", "gtao_covers", "hbao_sums", "hbao_forward", "hbao_covers"]

#: the variants in the kernel's numbering
VARIANTS = ("exact", "hdrp", "ue4")


def packed_value(x) -> float | torch.Tensor:
    """A 0-d parameter detached (:func:`~torch_ao.kernels.launch.packed_settings` puts it among the floats on its
    device, without reading it back from a GPU), or a number."""
    return x.detach() if isinstance(x, torch.Tensor) else float(x)


def gtao_sums(gbuffer: GBuffer, normals: torch.Tensor, *, variant: str = "exact", slices: int, steps: int,
              walk_radius: float, radius: float | torch.Tensor, falloff: float | torch.Tensor = 0.0,
              thickness: float | torch.Tensor = 1.0, step_power: float = 1.0, min_step_px: float = 1.0,
              max_radius_px: float | None = None, jitter: bool = True, seed: int = 0, noise: str = "ign",
              stagger: bool = False, fetch: str = "bilinear", border: str = "drop", azimuth: str = "view",
              slice_sampling: str = "uniform", projected_normal_weight: bool = True,
              bent_normals: bool = False, lanes: str = "simd") -> torch.Tensor:
    """Per-pixel sums over slices of GTAO's walk ``(B,C,H,W)`` (0 on background).

    Args:
        gbuffer: a float32 CPU G-buffer; normals: its ``(B,3,H,W)`` unit view-space normals.
        variant: ``"exact"``, ``"hdrp"`` or ``"ue4"`` (the accumulator and, for the shaders, their step
            placement). slices, steps: counts; walk_radius: world units the walk covers on screen
            (``radius * search_scale``, a number: with a ``radius`` tensor it must be proportional to it);
            radius: world units within which samples count.
        falloff: exact: ``falloff_range * radius`` clamped to 1e-12 (world units), 0 for a hard cut;
            thickness: ue4's thickness heuristic. step_power, min_step_px (pixels), max_radius_px
            (pixels, ``None``: none), jitter, seed, noise, stagger, fetch, border, azimuth, slice_sampling (each slice's
            sums weighted by its azimuth's estimator weight), projected_normal_weight: as
            :class:`~torch_ao.GTAO`. lanes: on CPU, ``"simd"`` or ``"scalar"`` (the CUDA thread's
            body); a CUDA G-buffer runs the CUDA kernel. With autograd recording through the G-buffer or
            the tensors ``radius``, ``falloff`` (exact) or ``thickness`` (ue4), the sums carry their
            gradients (walk_grad.py).

    Channels: the slice integrals and the unoccluded integrals summed over slices, then with
    ``bent_normals`` the bent-normal sum (3). Raises :class:`~torch_ao.kernels.KernelUnavailable` when the
    kernel cannot be built.
    """
    settings = walk_settings(slices=slices, steps=steps, radius=walk_radius, step_power=step_power,
                             min_step_px=min_step_px, max_radius_px=max_radius_px, jitter=jitter, seed=seed,
                             noise=noise, stagger=stagger, fetch=fetch, border=border, azimuth=azimuth,
                             slice_sampling=slice_sampling, placement="power" if variant == "exact" else variant)
    # the backward's settings (horizon.h's seed_setting) and their world-unit dimensions (Euler's identity)
    setting, dimension = {"exact": ((falloff,), (1,)), "ue4": ((thickness, UE4_EPSILON), (0, 2))}.get(variant, ((0.0,), (0,)))
    walk, options = run_walk, {}
    if wants_gradient(gbuffer, normals, radius, *setting):
        _check_gradient(gbuffer)
        walk, options = differentiable_walk, {"radius": radius, "setting": setting, "setting_dimension": dimension,
                                              "replaces": variant == "exact"}
    return walk("gtao", gbuffer, normals, settings,
                [VARIANTS.index(variant), bool(projected_normal_weight), bool(bent_normals)],
                [packed_value(radius), packed_value(falloff), packed_value(thickness)], 5 if bent_normals else 2,
                lanes=lanes, **options)


def _check_gradient(gbuffer: GBuffer) -> None:
    """A ``ValueError`` for a gradient the walk's backward cannot give (:func:`gradient_uncovered`)."""
    if gbuffer.depth.device.type not in ("cpu", "cuda"):
        raise ValueError(f"gbuffer: gradients through the kernel are computed on CPU and CUDA, not on "
                         f"{gbuffer.depth.device.type}")


def hbao_sums(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: float | torch.Tensor,
              angle_bias: float | torch.Tensor, falloff: str = "linear", accumulate: str = "incremental",
              elevation: str = "image", step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True,
              seed: int = 0, noise: str = "ign", stagger: bool = False, fetch: str = "bilinear", border: str = "drop",
              azimuth: str = "screen", lanes: str = "simd") -> torch.Tensor:
    """Per-pixel sum over directions of HBAO's weighted horizon rise ``(B,1,H,W)`` (0 on background).

    Args:
        gbuffer, normals: as :func:`gtao_sums`. slices: directions over the full circle; steps: samples
        per direction; radius: world units; angle_bias: radians; falloff, accumulate, elevation,
        step_power, min_step_px (pixels), jitter, seed, noise, stagger, fetch, border, azimuth: as :class:`~torch_ao.HBAO`.
        With autograd recording through the G-buffer, ``radius`` or ``angle_bias`` (CPU), the sums carry
        their gradients (walk_grad.py).
    """
    settings = walk_settings(slices=slices, steps=steps, radius=packed_value(radius), step_power=step_power,
                             min_step_px=min_step_px, jitter=jitter, seed=seed, noise=noise, stagger=stagger,
                             fetch=fetch, border=border, azimuth=azimuth, full_circle=True)
    walk, options = run_walk, {}
    if wants_gradient(gbuffer, normals, radius, angle_bias):
        _check_gradient(gbuffer)
        walk, options = differentiable_walk, {"radius": radius, "setting": (angle_bias,),
                                              "replaces": accumulate == "max"}
    return walk("hbao", gbuffer, normals, settings,
                [falloff == "quadratic", accumulate == "incremental", elevation == "view"],
                [packed_value(radius), packed_value(angle_bias)], 1, lanes=lanes, **options)


class _SumsFrame(NamedTuple):
    """What an accumulator reads of its frame to finish the kernel's sums: their dtype (a tuple, which
    ``torch.compile`` traces)."""
    dtype: torch.dtype


def finish_sums(module, gbuffer: GBuffer, sums: dict[str, torch.Tensor], normals: torch.Tensor) -> dict[str, torch.Tensor]:
    """The module's accumulator's ``finish`` of per-pixel ``sums`` ``{name: (B*H*W, C)}`` on every pixel (rows
    are independent), as images, with the background put back (visibility 1, the G-buffer's normal)."""
    B, _, H, W = gbuffer.depth.shape
    out = module.accumulator(_SumsFrame(torch.float32)).finish(sums, None, module.slices)
    images = {"visibility": 1.0, "bent_normal": normals}
    return {name: torch.where(gbuffer.valid, out[name].view(B, H, W, -1).permute(0, 3, 1, 2), images[name])
            for name in out}


def gtao_forward(module, gbuffer: GBuffer) -> dict[str, torch.Tensor]:
    """``module(gbuffer)``'s outputs ``{"visibility": (B,1,H,W)[, "bent_normal": (B,3,H,W)]}`` for a
    :class:`~torch_ao.GTAO` the kernel covers (:func:`gtao_covers`)."""
    m = module
    normals = gbuffer.view_normals(m.normals_method)
    falloff = 0.0
    if m.variant == "exact":  # (chosen on the device: a CUDA call reads nothing back, and can be captured in a graph)
        falloff = torch.where(m.falloff_range > 0, (m.falloff_range * m.radius).clamp_min(1e-12), 0.0)
    sums = gtao_sums(
        gbuffer, normals, variant=m.variant, slices=m.slices, steps=m.steps,
        walk_radius=packed_value(m.radius * m.search_scale if m.variant == "exact" else m.radius),
        radius=m.radius, falloff=falloff, thickness=m.thickness_heuristic,
        step_power=m.step_power, min_step_px=m.min_step_px, max_radius_px=m.max_radius_px, jitter=m.jitter,
        seed=m.seed, noise=m.noise, stagger=m.stagger, fetch=m.fetch, border=m.border, azimuth=m.azimuth,
        slice_sampling=m.slice_sampling, projected_normal_weight=m.projected_normal_weight, bent_normals=m.bent_normals)
    sums = sums.permute(0, 2, 3, 1).reshape(-1, sums.shape[1])
    flat = {"vis": sums[:, 0:1], "free": sums[:, 1:2]}
    if m.bent_normals:
        flat["bent"] = sums[:, 2:5].contiguous()
    return finish_sums(m, gbuffer, flat, normals)


def hbao_forward(module, gbuffer: GBuffer) -> dict[str, torch.Tensor]:
    """``module(gbuffer)``'s outputs ``{"visibility": (B,1,H,W)}`` for an :class:`~torch_ao.HBAO` the kernel
    covers (:func:`hbao_covers`)."""
    m = module
    normals = gbuffer.view_normals(m.normals_method)
    sums = hbao_sums(gbuffer, normals, slices=m.slices, steps=m.steps, radius=m.radius, angle_bias=m.angle_bias,
                     falloff=m.falloff, accumulate=m.accumulate, elevation=m.elevation, step_power=m.step_power, min_step_px=m.min_step_px, jitter=m.jitter,
                     seed=m.seed, noise=m.noise, stagger=m.stagger, fetch=m.fetch, border=m.border, azimuth=m.azimuth)
    return finish_sums(m, gbuffer, {"ao": sums.reshape(-1, 1)}, normals)


#: options of every module the horizon kernels know: ``None`` for any value, else the values covered
_WALK_OPTIONS = dict.fromkeys(("preset", "slices", "steps", "radius", "step_power", "min_step_px", "jitter", "seed", "noise", "stagger",
                               "border", "azimuth", "normals", "chunk_size", "recompute", "trainable",
                               "backend", "resolution")) | {"fetch": ("bilinear", "nearest", "edge_aware"),
                                                           "slice_sampling": ("uniform",)}
_GTAO_OPTIONS = _WALK_OPTIONS | {"variant": VARIANTS, "slice_sampling": SLICE_SAMPLINGS} | dict.fromkeys((
    "falloff_range", "thickness_heuristic", "final_power", "multibounce", "albedo", "bent_normals", "normalize",
    "projected_normal_weight", "max_radius_px", "search_scale"))
_HBAO_OPTIONS = _WALK_OPTIONS | dict.fromkeys(("angle_bias", "falloff", "accumulate", "elevation"))


#: per module, the parameters whose gradients the walk's backward gives: the radius by scale invariance, the
#: setting it seeds (walk_grad.py), and those the module's finish applies with torch ops
_BACKWARD_PARAMETERS = {"gtao": ("radius", "falloff_range", "thickness_heuristic", "final_power", "albedo"),
                        "hbao": ("radius", "angle_bias")}


def _covers(module, gbuffer: GBuffer, options: dict, parameters: tuple[str, ...]) -> str | None:
    """Why the kernel cannot compute ``module(gbuffer)`` (``None``: it can).

    Every option of the module must be one the kernel knows, at a value it covers (an option added to
    the module later sends the call to the tensor path); the ``parameters`` must be scalars, the
    G-buffer float32 on CPU, and, where autograd records, a gradient the backward covers (:func:`gradient_uncovered`).
    """
    reason = call_uncovered(module, gbuffer, options, parameters)
    if reason is not None:
        return reason
    if torch.is_grad_enabled():
        asked = [name for name in parameters if getattr(module, name).requires_grad]
        if asked or gbuffer_requires_grad(gbuffer):
            return gradient_uncovered(module, gbuffer, asked)
    return None


def gradient_uncovered(module, gbuffer: GBuffer, parameters=()) -> str | None:
    """Why the walk's backward cannot give ``module(gbuffer)``'s gradients to the G-buffer and to the
    ``parameters`` (names) asked for, or ``None``."""
    kind = getattr(module, "has_kernel", None)
    if kind not in _BACKWARD_PARAMETERS:
        return f"a gradient is asked for (the kernel's backward covers the horizon accumulators {tuple(_BACKWARD_PARAMETERS)})"
    if gbuffer.depth.is_cuda and module.steps > MAX_CUDA_STEPS:
        return f"a gradient is asked for on CUDA with {module.steps} steps per side (its backward replays at most {MAX_CUDA_STEPS})"
    others = [name for name in parameters if name not in _BACKWARD_PARAMETERS[kind]]
    if others:
        return (f"a gradient of {', '.join(others)} is asked for (the kernel's backward gives "
                f"{', '.join(_BACKWARD_PARAMETERS[kind])})")
    return None


def gtao_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`gtao_forward` computes ``module(gbuffer)`` (a ``GTAO``), else why not."""
    return _covers(module, gbuffer, _GTAO_OPTIONS, ("radius", "falloff_range", "thickness_heuristic", "final_power",
                                                   "albedo"))


def hbao_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`hbao_forward` computes ``module(gbuffer)`` (an ``HBAO``), else why not."""
    return _covers(module, gbuffer, _HBAO_OPTIONS, ("radius", "angle_bias"))
