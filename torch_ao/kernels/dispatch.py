"""Choosing between a fused kernel and the tensor-op walk for a module's call (``backend=``)."""
from __future__ import annotations

import warnings

import torch

from ..gbuffer import GBuffer
from .bitmask import bitmask_hard, bitmask_outputs, kernel_covers, ssilvb_glsl_hard
from .build import KernelUnavailable

__all__ = ["BACKENDS", "kernel_forward"]

#: ``"auto"``: the kernel when it covers the call, else the tensor path; ``"kernel"``: the kernel, and a
#: ``ValueError`` for a call it does not cover; ``"torch"``: always the tensor path
BACKENDS = ("auto", "kernel", "torch")

_warned: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _warned:
        _warned.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=4)


def kernel_forward(module, gbuffer: GBuffer, backend: str):
    """The kernel's outputs (an :class:`~torch_ao.methods.base.AOOutput`) for ``module(gbuffer)``, or
    ``None`` where the tensor path runs.

    A kernel exists for ``BitmaskAO`` (and subclasses) in the settings :func:`kernel_covers` accepts.

    A kernel that cannot be built here (no compiler, a failed build) falls back to the tensor path with
    one warning per process, whatever ``backend`` asks.
    """
    if backend == "torch":
        return None
    reason = kernel_covers(module, gbuffer) if module.has_kernel else f"no kernel for {type(module).__name__}"
    if reason is not None:
        if backend == "kernel":
            raise ValueError(f"backend: 'kernel' does not cover this call ({reason}); use backend='auto' or 'torch'")
        return None
    try:
        return _bitmask_forward(module, gbuffer)
    except KernelUnavailable as exc:
        _warn_once(f"torch_ao: {exc}; using the tensor-op walk instead (backend='torch' silences this)")
        return None


def _bitmask_forward(module, gbuffer: GBuffer):
    """A covered ``BitmaskAO`` call through its variant's kernel."""
    from ..methods.base import AOOutput

    normals = gbuffer.view_normals(module.normals_method)
    radius, thickness = float(module.radius.detach()), float(module.thickness.detach())
    if module.variant == "ssilvb_glsl":
        vis, indirect, _ = ssilvb_glsl_hard(gbuffer, normals, slices=module.slices, steps=module.steps,
                                            radius=module.radius, thickness=thickness, jitter=module.jitter,
                                            rounding=module.rounding, numerics=module.glsl_numerics,
                                            indirect=module.want_indirect)
        return AOOutput(visibility=vis, indirect=indirect)
    options = dict(slices=module.slices, steps=module.steps, radius=radius, thickness=thickness,
                   step_power=module.step_power, min_step_px=module.min_step_px, jitter=module.jitter,
                   seed=module.seed, fetch=module.fetch, border=module.border, rounding=module.rounding,
                   sector_epsilon=module.sector_epsilon, weighting=module.weighting,
                   chunk_size=module.chunking(gbuffer)[0])
    if not (module.want_indirect or module.want_bent):
        vis, indirect, bent = bitmask_hard(gbuffer, normals, **options), None, None
    else:
        vis, indirect, bent = bitmask_outputs(gbuffer, normals, indirect=module.want_indirect,
                                              bent_normals=module.want_bent, **options)
    ambient = None
    if module._ambient_constant:  # SectorAccumulator.finish: visibility times the colour; 0 on background
        ambient = torch.where(gbuffer.valid, vis * module.ambient_colour.to(vis.dtype).view(1, 3, 1, 1), 0.0)
    return AOOutput(visibility=vis, indirect=indirect, bent_normal=bent, ambient=ambient)
