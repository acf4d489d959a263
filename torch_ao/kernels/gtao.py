"""The GTAO kernel: ``GTAO`` (every variant) forward in one fused pass (``gtao_cpu.cpp``).

It walks exactly what the tensor path walks (the same slice directions, jitter, step placement, fetch
and border, :mod:`torch_ao.walk`) with the accumulators of :mod:`torch_ao.methods.gtao` (a horizon per
side, the clamped arc integral of :func:`torch_ao.ops.arc_integral`), and returns the per-pixel sums
over slices; the module's own ``GTAOAccumulator.finish`` turns them into the outputs, so the
normalisation, final power and multi-bounce fit are the tensor path's code. docs/performance.md gives
the measured agreement.
"""
from __future__ import annotations

from types import SimpleNamespace

import torch

from ..gbuffer import GBuffer
from .build import cpu_kernels

__all__ = ["gtao_sums", "gtao_forward", "gtao_covers"]

#: the variants in the kernel's numbering
VARIANTS = ("exact", "hdrp", "ue4")


def _channels_last(x: torch.Tensor) -> torch.Tensor:
    """``(B,C,H,W)`` -> contiguous ``(B,H,W,C)`` float32."""
    return x.permute(0, 2, 3, 1).to(torch.float32).contiguous()


def _kernel_inputs(gbuffer: GBuffer, normals: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The walk's inputs as the kernels read them: positions and normals ``(B,H,W,3)``, the inverse
    depth (NaN where invalid: a texel's validity travels with it), depth and validity ``(B,H,W)`` and
    the intrinsics ``(B,4)`` ``(fx, fy, cx, cy)`` in pixels."""
    depth = gbuffer.safe_depth[:, 0].to(torch.float32).contiguous()
    valid = gbuffer.valid[:, 0].contiguous()
    inverse = torch.where(valid, depth.reciprocal(), torch.nan)
    cam = gbuffer.camera
    intrinsics = torch.stack((cam.fx, cam.fy, cam.cx, cam.cy), -1).to(torch.float32).contiguous()
    return _channels_last(gbuffer.positions()), _channels_last(normals), inverse, depth, valid, intrinsics


def _value(x) -> float:
    """A 0-d parameter (or a number) as the float32 value the tensor path computes with."""
    return float(torch.as_tensor(x).detach().to(torch.float32))


def gtao_sums(gbuffer: GBuffer, normals: torch.Tensor, *, variant: str = "exact", slices: int, steps: int,
              walk_radius: float, radius: float, falloff: float = 0.0, thickness: float = 1.0,
              step_power: float = 1.0, min_step_px: float = 1.0, max_radius_px: float | None = None,
              jitter: bool = True, seed: int = 0, fetch: str = "bilinear", border: str = "drop",
              azimuth: str = "view", projected_normal_weight: bool = True,
              bent_normals: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-pixel sums over slices of GTAO's walk: ``(sums, bent)``.

    Args:
        gbuffer: a float32 CPU G-buffer; normals: its ``(B,3,H,W)`` unit view-space normals.
        variant: ``"exact"``, ``"hdrp"`` or ``"ue4"`` (the accumulator and, for the shaders, their step
            placement). slices, steps: counts; walk_radius: world units the walk covers on screen
            (``radius * search_scale``); radius: world units within which samples count.
        falloff: exact: ``falloff_range * radius`` clamped to 1e-12 (world units), 0 for a hard cut;
            thickness: ue4's thickness heuristic. step_power, min_step_px (pixels), max_radius_px
            (pixels, ``None``: none), jitter, seed, fetch, border, azimuth, projected_normal_weight: as
            :class:`~torch_ao.GTAO`.

    Returns ``sums`` ``(B,H,W,2)``: per pixel the slice integrals and the unoccluded integrals summed
    over slices (0 on background), and ``bent`` ``(B,H,W,3)`` the bent-normal sum (``None`` unless
    ``bent_normals``). Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built.
    """
    ops = cpu_kernels()
    sums, bent = ops.gtao_sums(
        *_kernel_inputs(gbuffer, normals), VARIANTS.index(variant), int(slices), int(steps), float(walk_radius),
        float(radius), float(falloff), float(thickness), float(step_power), float(min_step_px),
        float(max_radius_px or 0.0), bool(jitter), int(seed), fetch == "bilinear", border == "drop",
        azimuth == "screen", bool(projected_normal_weight), bool(bent_normals))
    return sums, (bent if bent_normals else None)


def gtao_forward(module, gbuffer: GBuffer) -> dict[str, torch.Tensor]:
    """``module(gbuffer)``'s outputs ``{"visibility": (B,1,H,W)[, "bent_normal": (B,3,H,W)]}`` for a
    :class:`~torch_ao.GTAO` the kernel covers (:func:`gtao_covers`), finished by the module's own
    accumulator (background: visibility 1, the G-buffer's normal as bent normal)."""
    m = module
    normals = gbuffer.view_normals(m.normals_method)
    falloff = 0.0
    if m.variant == "exact" and _value(m.falloff_range) > 0:
        falloff = _value((m.falloff_range * m.radius).clamp_min(1e-12))
    sums, bent = gtao_sums(
        gbuffer, normals, variant=m.variant, slices=m.slices, steps=m.steps,
        walk_radius=_value(m.radius * m.search_scale) if m.variant == "exact" else _value(m.radius),
        radius=_value(m.radius), falloff=falloff, thickness=_value(m.thickness_heuristic),
        step_power=m.step_power, min_step_px=m.min_step_px, max_radius_px=m.max_radius_px, jitter=m.jitter,
        seed=m.seed, fetch=m.fetch, border=m.border, azimuth=m.azimuth,
        projected_normal_weight=m.projected_normal_weight, bent_normals=m.bent_normals)
    B, _, H, W = gbuffer.depth.shape
    flat = {"vis": sums[..., 0].reshape(-1, 1), "free": sums[..., 1].reshape(-1, 1)}
    if bent is not None:
        flat["bent"] = bent.reshape(-1, 3)
    # the module's accumulator finishes every pixel (rows are independent); background is put back
    out = m.accumulator(SimpleNamespace(dtype=torch.float32)).finish(flat, None, m.slices)
    valid = gbuffer.valid
    result = {"visibility": torch.where(valid, out["visibility"].view(B, H, W, 1).permute(0, 3, 1, 2), 1.0)}
    if bent is not None:
        result["bent_normal"] = torch.where(valid, out["bent_normal"].view(B, H, W, 3).permute(0, 3, 1, 2), normals)
    return result


#: options of a GTAO module the kernel reproduces: ``None`` for any value, else the values it covers
_COVERED = {
    "preset": None, "slices": None, "steps": None, "radius": None, "step_power": None, "min_step_px": None,
    "jitter": None, "seed": None, "fetch": None, "border": None, "azimuth": None, "normals": None,
    "chunk_size": None, "recompute": None, "trainable": None, "backend": None,
    "variant": VARIANTS, "falloff_range": None, "thickness_heuristic": None, "final_power": None,
    "multibounce": None, "albedo": None, "bent_normals": None, "normalize": None,
    "projected_normal_weight": None, "max_radius_px": None, "search_scale": None,
}


def gtao_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`gtao_forward` computes ``module(gbuffer)`` (a ``GTAO``), else why not.

    Every option of the module must be one the kernel knows (an option added to the module later sends
    the call to the tensor path); its parameters must be scalars; the G-buffer float32 on CPU; and no
    gradient may be asked for (the kernel has no backward: such a call runs the tensor path).
    """
    values = dict(getattr(module, "values", {}))
    for name, value in values.items():
        if name not in _COVERED:
            return f"option {name!r} (unknown to the kernel)"
        allowed = _COVERED[name]
        if allowed is not None and value not in allowed:
            return f"{name}={value!r}"
    parameters = [getattr(module, name) for name in ("radius", "falloff_range", "thickness_heuristic", "final_power",
                                                     "albedo")]
    if any(not isinstance(p, torch.Tensor) or p.dim() != 0 for p in parameters):
        return "a parameter other than a scalar"
    if gbuffer.position is not None and module.fetch == "bilinear":
        return "bilinear reads of a position buffer (the kernel unprojects the interpolated depth)"
    if gbuffer.depth.device.type != "cpu" or gbuffer.depth.dtype != torch.float32:
        return f"a {gbuffer.depth.dtype} G-buffer on {gbuffer.depth.device.type} (the kernel is float32 CPU)"
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                       for t in [gbuffer.depth, gbuffer.normals, *parameters]):
        return "a gradient is asked for (the kernel has no backward)"
    return None
