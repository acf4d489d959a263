"""Choosing between a fused kernel and the tensor-op walk for a module's call (``backend=``)."""
from __future__ import annotations

import warnings

import torch

from ..gbuffer import GBuffer
from . import soft_bitmask
from .soft_exact import exact_soft_covers, exact_soft_forward
from .soft_glsl import glsl_soft_covers, glsl_soft_forward
from .bitmask import (bitmask_hard, bitmask_outputs, exact_covers, exact_forward, kernel_covers, module_thickness,
                      ssilvb_glsl_hard, thickness_options)
from .build import KernelUnavailable
from .frame import view_geometry
from .gtao import gtao_covers, gtao_forward, hbao_covers, hbao_forward
from .ssao import pssao_covers, pssao_forward, ssao_covers, ssao_forward, ue4_ssao_covers, ue4_ssao_forward

__all__ = ["BACKENDS", "kernel_forward"]

#: ``"auto"``: the kernel when it covers the call, else the tensor path; ``"kernel"``: the kernel, and a
#: ``ValueError`` for a call it does not cover; ``"torch"``: always the tensor path
BACKENDS = ("auto", "kernel", "torch")

_warned: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _warned:
        _warned.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=4)


def _bitmask_hard(module, gbuffer: GBuffer) -> dict:
    """A covered hard ``BitmaskAO`` call through its variant's kernel: ``{AOOutput field: tensor}``."""
    normals = gbuffer.view_normals(module.normals_method)
    radius = module.radius  # (a tensor: indirect light's gradient reaches it)
    thickness = thickness_options(module_thickness(module, gbuffer))
    if module.variant == "ssilvb_glsl":
        vis, indirect, _ = ssilvb_glsl_hard(gbuffer, normals, slices=module.slices, steps=module.steps,
                                            radius=module.radius, **thickness, jitter=module.jitter,
                                            rounding=module.rounding, numerics=module.glsl_numerics,
                                            indirect=module.want_indirect)
        return {"visibility": vis, "indirect": indirect}
    options = dict(slices=module.slices, steps=module.steps, radius=radius,
                   **thickness, step_power=module.step_power, min_step_px=module.min_step_px, jitter=module.jitter,
                   seed=module.seed, noise=module.noise, stagger=module.stagger, fetch=module.fetch,
                   border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon,
                   weighting=module.weighting, variant=module.variant, azimuth=module.azimuth,
                   thickness_direction=module.thickness_direction, clip_to_radius=module.clip_to_radius,
                   sample_extent=module.sample_extent, slice_sampling=module.slice_sampling)
    if not (module.want_indirect or module.want_bent):
        vis, indirect, bent = bitmask_hard(gbuffer, normals, **options), None, None
    else:
        vis, indirect, bent = bitmask_outputs(gbuffer, normals, indirect=module.want_indirect,
                                              bent_normals=module.want_bent, **options)
    return {"visibility": vis, "indirect": indirect, "bent_normal": bent, "ambient": _constant_ambient(module, gbuffer, vis)}


def _constant_ambient(module, gbuffer: GBuffer, vis: torch.Tensor) -> torch.Tensor | None:
    """A constant ambient colour's light ``(B,3,H,W)`` (SectorAccumulator.finish: the visibility times the colour;
    0 on background), or ``None`` without one."""
    if module.ambient_constant is None:
        return None
    return torch.where(gbuffer.valid, vis * module.ambient_constant.to(vis.dtype).view(1, 3, 1, 1), 0.0)


def _bitmask_soft(module, gbuffer: GBuffer) -> dict:
    vis, indirect, bent = soft_bitmask.module_forward(module, gbuffer)
    return {"visibility": vis, "indirect": indirect, "bent_normal": bent,
            "ambient": _constant_ambient(module, gbuffer, vis)}


#: a method's ``has_kernel`` -> its kernels, tried in order: ``(covers, run)`` pairs, ``covers(module,
#: gbuffer)`` is ``None`` when that kernel computes the call, else why not; ``run(module, gbuffer)`` gives the
#: outputs ``{AOOutput field: tensor}``. Bitmask AO has the hard kernel, the exact union's (the ``"exact"``
#: variant), the exact union's with its gradients, the ``"ssilvb_glsl"`` shader's soft / straight-through one and the
#: other variants' soft / straight-through one (with their backwards).
KERNELS = {
    "bitmask": ((kernel_covers, _bitmask_hard), (exact_covers, exact_forward), (exact_soft_covers, exact_soft_forward),
                (glsl_soft_covers, glsl_soft_forward), (soft_bitmask.kernel_covers, _bitmask_soft)),
    "gtao": ((gtao_covers, gtao_forward),),
    "hbao": ((hbao_covers, hbao_forward),),
    "ue4_ssao": ((ue4_ssao_covers, ue4_ssao_forward),),
    "pssao": ((pssao_covers, pssao_forward),),
    "ssao": ((ssao_covers, ssao_forward),),
}


def kernel_forward(module, gbuffer: GBuffer, backend: str) -> dict | None:
    """The kernel's outputs ``{"visibility": (B,1,H,W), ...}`` for ``module(gbuffer)``, or ``None`` where
    the tensor path runs.

    A method names its kernels in ``has_kernel`` (a key of :data:`KERNELS`); the first whose ``covers``
    accepts the call runs it. A kernel that cannot be built here (no compiler, a failed build) falls back
    to the tensor path with one warning per process, whatever ``backend`` asks.
    """
    if backend == "torch":
        return None
    reasons, run = [], None
    for covers, candidate in KERNELS.get(module.has_kernel, ()):
        reason = covers(module, gbuffer)
        if reason is None:
            run = candidate
            break
        reasons.append(reason)
    if run is None:
        if backend == "kernel":
            reason = " / ".join(dict.fromkeys(reasons)) or f"no kernel for {type(module).__name__}"
            raise ValueError(f"backend: 'kernel' does not cover this call ({reason}); use backend='auto' or 'torch'")
        return None
    try:
        view_geometry(gbuffer, module.normals_method)  # (where the call records gradients: one pass, not torch ops)
        return run(module, gbuffer)
    except KernelUnavailable as exc:
        _warn_once(f"torch_ao: {exc}; using the tensor-op walk instead (backend='torch' silences this)")
        return None
