"""The SSAO family's kernels: ``UE4SSAO``, ``PSSAO`` and ``SSAO`` forward in one fused pass (the one walk of
``walk.h`` with the accumulators of ``ssao.h``).

``UE4SSAO`` walks :class:`~torch_ao.methods.ue4_ssao.WedgePattern`'s directions (a sample set's, rotated per
pixel, or evenly spaced) with both sides of each step taken together (``walk_pairs``: the tensor walk's
``paired_sides``) and UE4's ``WedgeNoNormal`` per pair; ``PSSAO`` walks
:class:`~torch_ao.methods.pssao.PSSAOPattern`'s integer pixel offsets (the module's pattern computes them; the
kernel reads them as a table) with the largest occlusion per direction. Both return per-pixel sums over
slices that the module's own accumulator's ``finish`` turns into the visibility (UE4's final power and
intensity, PSSAO's normalisation), so those have one definition. Where autograd records (CPU, CUDA), both run
with the walk's backward (:mod:`torch_ao.kernels.walk_grad`, every step replayed in reverse lanes): gradients
to the G-buffer's depth, normals, positions and intrinsics, to every parameter of UE4 SSAO (the radius by
Euler's identity) and PSSAO's distance bias; :func:`ue4_ssao_covers` and :func:`pssao_covers` say why a call
runs on the tensor path (a float64 G-buffer, more than 32 steps on CUDA, ...).

``SSAO``'s samples are 3-D points around the normal, not steps along a screen direction: the walk's
``"hemisphere"`` placement reads the module's kernel points as a table and walks one slice of them
(walk.h's ``walk_points``: the per-pixel tangent frame, rotated by the pixel's interleaved gradient noise when
jittered, each point projected and fetched), and ``ssao.h``'s ``HemisphereAccumulator`` finishes the visibility
itself. Its backward replays every point: gradients to the G-buffer, the intrinsics, the bias (``softness > 0``)
and the radius (Euler's identity, the bias and softness lengths too); :func:`ssao_covers` says which calls run
on the tensor path.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from ..gbuffer import GBuffer
from .coverage import call_uncovered
from .gtao import finish_sums, packed_value
from .launch import run_walk, walk_settings
from .walk_grad import MAX_CUDA_STEPS, differentiable_walk, gbuffer_requires_grad, wants_gradient

__all__ = ["ue4_ssao_sums", "ue4_ssao_forward", "ue4_ssao_covers", "pssao_sums", "pssao_forward", "pssao_covers",
           "hemisphere_visibility", "ssao_forward", "ssao_covers"]

#: the fetches the walk reads (walk.h's Sample)
_FETCHES = ("nearest", "bilinear", "edge_aware")


def ue4_ssao_sums(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: float | torch.Tensor,
                  fade_distance: float | torch.Tensor, flat_surface_bias: float | torch.Tensor,
                  flat_softness: float = 0.0,
                  accurate_angle: bool = False, offsets=None, jitter: bool = True, seed: int = 0,
                  fetch: str = "nearest", border: str = "clamp", lanes: str = "simd") -> torch.Tensor:
    """Per-pixel sums over directions of UE4 SSAO's ``(1 - acc.x)^2 acc.y`` and ``acc.y`` ``(B,2,H,W)`` (0 on
    background).

    Args:
        gbuffer: a float32 G-buffer (CPU or CUDA); normals: its ``(B,3,H,W)`` view-space normals (the walk's
            basis; the accumulator reads none). slices: directions evenly over the half circle, or ``offsets``:
            a sample set's 2-D offsets ``((x, y), ...)``, one direction each (its angle and length:
            :data:`~torch_ao.methods.ue4_ssao.SAMPLE_SETS`); steps: pairs per direction; radius, fade_distance,
            flat_surface_bias, flat_softness: world units; accurate_angle, jitter, seed, fetch, border: as
            :class:`~torch_ao.UE4SSAO`. lanes: on CPU, ``"simd"`` or ``"scalar"`` (the CUDA thread's body).
            With autograd recording through the G-buffer or a ``radius``, ``fade_distance`` or
            ``flat_surface_bias`` tensor, the sums carry their gradients (the radius' by Euler's identity: the
            walk is scale-invariant with its three lengths, :mod:`~torch_ao.kernels.walk_grad`).
    """
    normals = normals.detach()  # (the walk's basis alone, its directions screen angles: no gradient, as in torch)
    table = None
    if offsets is not None:  # WedgePattern._direction: the offset's angle and length
        slices = len(offsets)
        table = [v for x, y in offsets for v in (math.atan2(y, x), math.hypot(x, y))]
    settings = walk_settings(slices=slices, steps=steps, radius=packed_value(radius), jitter=jitter, seed=seed,
                             fetch=fetch, border=border, placement="wedge", azimuth="screen", table=table)
    walk, options = run_walk, {}
    if wants_gradient(gbuffer, normals, radius, fade_distance, flat_surface_bias):
        walk, options = differentiable_walk, {"radius": radius, "setting": (fade_distance, flat_surface_bias,
                                                                            flat_softness),
                                              "setting_dimension": (1, 1, 1)}
    return walk("wedge", gbuffer, normals, settings, [bool(accurate_angle)],
                [packed_value(_floored(fade_distance)), packed_value(flat_surface_bias), float(flat_softness)], 2,
                lanes=lanes, **options)


def _floored(fade_distance: float | torch.Tensor) -> float | torch.Tensor:
    """The fade distance at least 1e-30 (the kernel divides by it), a tensor kept on its device (read back from a
    GPU it would make the call wait)."""
    if isinstance(fade_distance, torch.Tensor):
        return fade_distance.detach().to(torch.float32).clamp_min(1e-30)
    return max(float(torch.tensor(fade_distance, dtype=torch.float32)), 1e-30)


def pssao_sums(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, offsets,
               distance_bias: float | torch.Tensor,
               fetch: str = "nearest", border: str = "drop", lanes: str = "simd") -> torch.Tensor:
    """Per-pixel sums over directions of PSSAO's largest occlusion, in-image samples and directions with one
    ``(B,3,H,W)`` (0 on background).

    Args:
        gbuffer, normals: as :func:`ue4_ssao_sums` (the normals occlude: ``a = max(n . d, 0)``). slices,
            steps: the gist's angular and radius steps; offsets: ``offsets[s][k]`` the ``(du, dv)`` pixels of step
            ``k`` on direction ``s`` (:meth:`~torch_ao.methods.pssao.PSSAOPattern.pixel_offset`);
            distance_bias: world units; fetch, border: as
            :class:`~torch_ao.PSSAO`. lanes: as :func:`ue4_ssao_sums`. With autograd recording through the
            G-buffer or a ``distance_bias`` tensor, the sums carry their gradients.
    """
    table = [float(v) for s in range(slices) for k in range(steps) for v in offsets[s][k]]
    settings = walk_settings(slices=slices, steps=steps, radius=0.0, jitter=False, seed=0, fetch=fetch, border=border,
                             placement="pixels", full_circle=True, azimuth="screen", table=table)
    walk, options = run_walk, {}
    if wants_gradient(gbuffer, normals, distance_bias):
        walk, options = differentiable_walk, {"radius": 0.0, "setting": (distance_bias,), "replaces": True}
    return walk("pssao", gbuffer, normals, settings, [], [packed_value(distance_bias)], 3, lanes=lanes, **options)


def hemisphere_visibility(gbuffer: GBuffer, normals: torch.Tensor, *, kernel: torch.Tensor | Sequence[float],
                          radius: float | torch.Tensor, bias: float | torch.Tensor, softness: float = 0.0,
                          jitter: bool = True, seed: int = 0, fetch: str = "bilinear", border: str = "drop",
                          lanes: str = "simd") -> torch.Tensor:
    """SSAO's visibility over the hemisphere kernel ``(B,1,H,W)`` (1 on background).

    Args:
        gbuffer, normals: as :func:`ue4_ssao_sums` (the kernel is oriented along the normals). kernel: the
            ``(K,3)`` unit-hemisphere points (:func:`~torch_ao.methods.ssao.hemisphere_kernel`), or their ``3 K``
            coordinates as floats (:meth:`~torch_ao.SSAO.kernel_table`, constants to ``torch.compile``); radius, bias,
            softness: world units; jitter, seed, fetch, border: as :class:`~torch_ao.SSAO`. lanes: as
            :func:`ue4_ssao_sums`. With autograd recording through the G-buffer or a ``radius`` or ``bias``
            tensor, the visibility carries their gradients (the radius' by Euler's identity, the bias and
            softness being lengths).
    """
    if isinstance(kernel, torch.Tensor):
        kernel = kernel.detach().to(torch.float32).flatten().tolist()
    table = [float(v) for v in kernel]
    settings = walk_settings(slices=1, steps=len(table) // 3, radius=packed_value(radius), jitter=jitter, seed=seed,
                             fetch=fetch, border=border, placement="hemisphere", full_circle=True, table=table)
    walk, options = run_walk, {}
    if wants_gradient(gbuffer, normals, radius, bias):
        walk, options = differentiable_walk, {"radius": radius, "setting": (bias, softness),
                                              "setting_dimension": (1, 1)}
    return walk("hemisphere", gbuffer, normals, settings, [], [packed_value(bias), float(softness)], 1,
                lanes=lanes, **options)


def ue4_ssao_forward(module, gbuffer: GBuffer, lanes: str = "simd") -> dict[str, torch.Tensor]:
    """``module(gbuffer)``'s outputs ``{"visibility": (B,1,H,W)}`` for a :class:`~torch_ao.UE4SSAO` the kernel
    covers (:func:`ue4_ssao_covers`); lanes: as :func:`ue4_ssao_sums`."""
    m = module
    normals = gbuffer.view_normals(m.normals_method)
    sums = ue4_ssao_sums(gbuffer, normals, slices=m.slices, steps=m.steps, radius=m.radius,
                         fade_distance=m.fade_distance, flat_surface_bias=m.flat_surface_bias,
                         flat_softness=m.flat_softness, accurate_angle=m.accurate_angle,
                         offsets=m.pattern_for(None).offsets,
                         jitter=m.jitter, seed=m.seed, fetch=m.fetch, border=m.border, lanes=lanes)
    sums = sums.permute(0, 2, 3, 1).reshape(-1, 2)
    return finish_sums(m, gbuffer, {"num": sums[:, 0:1], "den": sums[:, 1:2]}, normals)


def pssao_forward(module, gbuffer: GBuffer, lanes: str = "simd") -> dict[str, torch.Tensor]:
    """``module(gbuffer)``'s outputs ``{"visibility": (B,1,H,W)}`` for a :class:`~torch_ao.PSSAO` the kernel
    covers (:func:`pssao_covers`); lanes: as :func:`ue4_ssao_sums`."""
    m = module
    normals = gbuffer.view_normals(m.normals_method)
    pattern = m.pattern_for(None)
    offsets = [[pattern.pixel_offset(s, k) for k in range(m.steps)] for s in range(m.slices)]
    sums = pssao_sums(gbuffer, normals, slices=m.slices, steps=m.steps, offsets=offsets,
                      distance_bias=m.distance_bias,
                      fetch=m.fetch, border=m.border, lanes=lanes)
    sums = sums.permute(0, 2, 3, 1).reshape(-1, 3)
    return finish_sums(m, gbuffer, {"sum": sums[:, 0:1], "count": sums[:, 1:2], "dirs": sums[:, 2:3]}, normals)


def ssao_forward(module, gbuffer: GBuffer, lanes: str = "simd") -> dict[str, torch.Tensor]:
    """``module(gbuffer)``'s outputs ``{"visibility": (B,1,H,W)}`` for an :class:`~torch_ao.SSAO` the kernel
    covers (:func:`ssao_covers`); lanes: as :func:`ue4_ssao_sums`."""
    m = module
    normals = gbuffer.view_normals(m.normals_method)
    return {"visibility": hemisphere_visibility(gbuffer, normals, kernel=m.kernel_table(), radius=m.radius, bias=m.bias,
                                                softness=m.softness, jitter=m.jitter, seed=m.seed, fetch=m.fetch,
                                                border=m.border, lanes=lanes)}


#: the options of every module these kernels know: ``None`` for any value, else the values covered
_MODULE_OPTIONS = dict.fromkeys(("preset", "slices", "steps", "border", "normals", "chunk_size", "recompute", "trainable",
                                 "backend", "resolution")) | {"fetch": _FETCHES}
_UE4_OPTIONS = _MODULE_OPTIONS | dict.fromkeys(("radius", "fade_distance", "flat_surface_bias", "final_power", "intensity",
                                                "sample_set", "accurate_angle", "flat_softness", "jitter", "seed")) | {
    "azimuth": ("screen",)}
_PSSAO_OPTIONS = _MODULE_OPTIONS | dict.fromkeys(("distance_bias", "normalize")) | {"jitter": (False,)}
_SSAO_OPTIONS = _MODULE_OPTIONS | dict.fromkeys(("samples", "radius", "bias", "softness", "jitter", "seed"))


def _covers(module, gbuffer: GBuffer, options: dict, parameters: tuple[str, ...], given: tuple[str, ...],
            steps: int | None = None) -> str | None:
    """Why the kernel cannot compute ``module(gbuffer)`` (``None``: it can): an option it does not know or
    cover, a ``parameter`` other than a scalar, a G-buffer other than float32 on CPU or CUDA, or,
    where autograd records, a gradient the walk's backward does not give (it gives the
    G-buffer's and the ``given`` parameters': its setting's, and those the module's finish applies with torch
    ops), or one on CUDA with more than :data:`~torch_ao.kernels.walk_grad.MAX_CUDA_STEPS` ``steps`` (default the
    module's) per side."""
    reason = call_uncovered(module, gbuffer, options, parameters)
    if reason is not None:
        return reason
    if torch.is_grad_enabled():
        others = [name for name in parameters if getattr(module, name).requires_grad and name not in given]
        if others:
            return (f"a gradient of {', '.join(others)} is asked for (the {type(module).__name__} kernel's backward "
                    f"gives {', '.join(given)} and the G-buffer's)")
        wanted = any(getattr(module, name).requires_grad for name in parameters) or gbuffer_requires_grad(gbuffer)
        steps = module.steps if steps is None else steps
        if wanted and gbuffer.depth.is_cuda and steps > MAX_CUDA_STEPS:
            return (f"a gradient is asked for on CUDA with {steps} steps per side (its backward replays at "
                    f"most {MAX_CUDA_STEPS})")
    return None


def ue4_ssao_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`ue4_ssao_forward` computes ``module(gbuffer)`` (a ``UE4SSAO``), else why not."""
    parameters = ("radius", "fade_distance", "flat_surface_bias", "final_power", "intensity")
    return _covers(module, gbuffer, _UE4_OPTIONS, parameters, given=parameters)


def pssao_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`pssao_forward` computes ``module(gbuffer)`` (a ``PSSAO``), else why not."""
    return _covers(module, gbuffer, _PSSAO_OPTIONS, ("distance_bias",), given=("distance_bias",))


def ssao_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`ssao_forward` computes ``module(gbuffer)`` (an ``SSAO``), else why not (its kernel
    points are the walk's steps: at most :data:`~torch_ao.kernels.walk_grad.MAX_CUDA_STEPS` with a gradient on
    CUDA)."""
    return _covers(module, gbuffer, _SSAO_OPTIONS, ("radius", "bias"), given=("radius", "bias"), steps=module.samples)
