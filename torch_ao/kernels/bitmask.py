"""The hard bitmask AO kernel: ``BitmaskAO(variant="default", mode="hard")`` in one fused pass.

It walks exactly what the tensor path walks (the same slice directions around the view vector, jitter,
step placement, fetch, border and sector rule; see :mod:`torch_ao.methods.bitmask`) and returns the
same visibility: bit for bit where both evaluate the same float operations in the same order (the
C++ source follows torch's kernels operation by operation; docs/performance.md gives the measured
agreement).
"""
from __future__ import annotations

import torch

from ..gbuffer import GBuffer
from ..sectors import ROUNDINGS
from ..thickness import ScalarThickness
from .build import cpu_kernels

__all__ = ["bitmask_hard", "kernel_covers"]


def _channels_last(x: torch.Tensor) -> torch.Tensor:
    """``(B,C,H,W)`` -> contiguous ``(B,H,W,C)`` float32."""
    return x.permute(0, 2, 3, 1).to(torch.float32).contiguous()


def bitmask_hard(gbuffer: GBuffer, normals: torch.Tensor, *, slices: int, steps: int, radius: float,
                 thickness: float, step_power: float = 1.0, min_step_px: float = 1.0, jitter: bool = True,
                 seed: int = 0, fetch: str = "bilinear", border: str = "drop", rounding: str = "ceil",
                 sector_epsilon: float = 0.01) -> torch.Tensor:
    """Hard bitmask visibility ``(B,1,H,W)`` in ``[0, 1]`` (1 = unoccluded; background pixels 1).

    Args:
        gbuffer: a float32 CPU G-buffer; normals: its ``(B,3,H,W)`` unit view-space normals (as the
            module uses them, e.g. ``gbuffer.view_normals()``).
        slices, steps: directions per pixel (uniform around the view vector) and samples per side.
        radius, thickness: world units (scalars); step_power, min_step_px (pixels), jitter, seed, fetch
            (``"bilinear"``/``"nearest"``), border (``"drop"``/``"clamp"``), rounding, sector_epsilon
            (sectors): as :class:`~torch_ao.BitmaskAO`.

    Raises :class:`~torch_ao.kernels.KernelUnavailable` when the kernel cannot be built here.
    """
    ops = cpu_kernels()
    depth = gbuffer.safe_depth[:, 0].to(torch.float32).contiguous()
    valid = gbuffer.valid[:, 0].contiguous()
    # the kernel reads a texel's validity from its inverse depth: NaN where invalid
    inverse = torch.where(valid, depth.reciprocal(), torch.nan)
    cam = gbuffer.camera
    intrinsics = torch.stack((cam.fx, cam.fy, cam.cx, cam.cy), -1).to(torch.float32).contiguous()
    return ops.bitmask_hard(
        _channels_last(gbuffer.positions()), _channels_last(normals), inverse, depth, valid, intrinsics, int(slices), int(steps), float(radius), float(thickness),
        float(step_power), float(min_step_px), bool(jitter), int(seed), fetch == "bilinear", border == "drop",
        ROUNDINGS.index(rounding), float(sector_epsilon))


#: options of a module the kernel reproduces: ``None`` for any value, else the values it covers
_COVERED = {
    # the walk's and every module's options
    "preset": None, "slices": None, "steps": None, "radius": None, "step_power": None, "min_step_px": None,
    "jitter": None, "seed": None, "fetch": ("nearest", "bilinear"), "border": None, "azimuth": ("view",), "normals": None,
    "chunk_size": None, "recompute": None, "trainable": None, "backend": None,
    # the bitmask family's
    "variant": ("default",), "mode": ("hard", "straight_through"), "tau": None, "rounding": None,
    "weighting": ("uniform",), "union": ("sectors",), "clip_to_radius": (False,), "thickness_direction": ("view",),
    "sample_extent": ("radius",), "thickness": None, "thickness_growth": (None,), "indirect": (False,),
    "bent_normals": (False,), "ambient": (None,), "ambient_directions": None, "sector_epsilon": None,
    "glsl_numerics": None,
}


def kernel_covers(module, gbuffer: GBuffer) -> str | None:
    """``None`` when :func:`bitmask_hard` computes ``module(gbuffer)`` (a ``BitmaskAO``), else why not.

    Every option of the module must be one the kernel knows, at a value it reproduces (an option it
    does not know, e.g. one added to the module later, sends the call to the tensor path). Hard masks
    have no gradient, so hard mode is covered with autograd on too; straight-through mode (hard values,
    soft gradients) only when no gradient is asked for.
    """
    values = dict(getattr(module, "values", {}))
    for name in ("variant", "mode", "weighting", "union", "clip_to_radius", "thickness_direction", "sample_extent",
                 "azimuth", "thickness_growth", "ambient"):
        values[name] = getattr(module, name, "?")  # resolved per variant, kept as attributes
    values["indirect"] = getattr(module, "want_indirect", "?")
    values["bent_normals"] = getattr(module, "want_bent", "?")
    if getattr(module, "_ambient_constant", False):
        values["ambient"] = "a colour"
    for name, value in values.items():
        if name not in _COVERED:
            return f"option {name!r} (unknown to the kernel)"
        allowed = _COVERED[name]
        if allowed is not None and not any(value is a or (isinstance(value, str) and value == a) for a in allowed):
            return f"{name}={value!r}"
    thickness, model = getattr(module, "thickness", None), getattr(module, "thickness_model", None)
    if not isinstance(thickness, torch.Tensor) or thickness.dim() != 0 or (
            model is not None and (type(model) is not ScalarThickness or model.growth is not None)):
        return "a thickness other than one scalar (a table, a map, a model, a growth)"
    if gbuffer.depth.device.type != "cpu" or gbuffer.depth.dtype != torch.float32:
        return f"a {gbuffer.depth.dtype} G-buffer on {gbuffer.depth.device.type} (the kernel is float32 CPU)"
    if module.mode == "straight_through" and _needs_grad(module, gbuffer):
        return "a straight-through gradient is asked for"  # (hard mode has none: its values are the same)
    return None


def _needs_grad(module, gbuffer: GBuffer) -> bool:
    if not torch.is_grad_enabled():
        return False
    tensors = [gbuffer.depth, gbuffer.normals, module.radius, module.thickness]
    return any(t is not None and t.requires_grad for t in tensors)
