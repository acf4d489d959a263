"""The reference renderer's AO rays on analytic scenes in one C++ pass (``tracer_cpu.cpp``).

For each pixel it draws the same stratified samples as :mod:`.sampling`, turns them into the same
hemisphere directions and tests them for any hit within ``R`` against the scene's planes, spheres,
boxes and cylinders, without the ``(rays, primitives)`` tensors of :class:`~.tracer.Tracer`. It
covers CPU float32 tracers of scenes without meshes; :func:`occlusion` returns ``None`` otherwise, and
when the library cannot be built (with one warning), and the caller traces with the tensor path.
"""
from __future__ import annotations

import functools
import warnings
from pathlib import Path

import torch

from . import sampling
from .tracer import _Boxes, _Cylinders, _Planes, _Spheres, Tracer

__all__ = ["BACKENDS", "occlusion", "covers"]

#: ``render_reference(backend=...)``: ``"auto"`` (the kernel where it covers the render, else the
#: tensor path), ``"kernel"`` (the kernel or an error), ``"torch"`` (the tensor path).
BACKENDS = ("auto", "kernel", "torch")

_SOURCE = Path(__file__).with_name("tracer_cpu.cpp")


@functools.lru_cache(maxsize=None)
def _ops():
    from ..kernels.build import load_cpu_library

    load_cpu_library("torch_ao_tracer", [_SOURCE])
    return torch.ops.torch_ao_tracer


@functools.lru_cache(maxsize=None)
def _available() -> bool:
    from ..kernels.build import KernelUnavailable

    try:
        _ops()
    except KernelUnavailable as exc:
        warnings.warn(f"reference renderer: {exc}; AO rays are traced with tensor ops (slower)", stacklevel=3)
        return False
    return True


def covers(tracer: Tracer) -> bool:
    """Whether the kernel can trace this tracer's AO rays (CPU, float32, analytic primitives only)."""
    return (tracer.device.type == "cpu" and tracer.dtype == torch.float32
            and all(type(g) in (_Planes, _Spheres, _Boxes, _Cylinders) for g in tracer.groups))


def _tables(tracer: Tracer) -> list[torch.Tensor]:
    """The primitive tables in the kernel's argument order, taken from the tracer's own groups (so both
    paths intersect the same float32 numbers), and float64 bounding spheres ``(S+X+C, 4)``."""
    if getattr(tracer, "_kernel_tables", None) is not None:
        return tracer._kernel_tables
    f32 = dict(dtype=torch.float32)
    empty3, empty = torch.zeros(0, 3, **f32), torch.zeros(0, **f32)
    kinds = {type(g): g for g in tracer.groups}
    pl, sp, bx, cy = (kinds.get(k) for k in (_Planes, _Spheres, _Boxes, _Cylinders))
    bounds = []
    if sp is not None:
        bounds.append(torch.cat([sp.c.double(), sp.r2.double().sqrt()[:, None]], 1))
    if bx is not None:
        bounds.append(torch.cat([bx.c.double(), bx.h.double().norm(dim=1, keepdim=True)], 1))
    if cy is not None:
        bounds.append(torch.cat([cy.c.double(), (cy.r2.double() + cy.h.double().square()).sqrt()[:, None]], 1))
    tables = [pl.n if pl else empty3, pl.off if pl else empty,
              sp.c if sp else empty3, sp.r2 if sp else empty,
              bx.Rcat if bx else torch.zeros(3, 0, **f32), bx.cl if bx else empty,
              bx.h_axis_major if bx else torch.zeros(3, 0, **f32),
              cy.c if cy else empty3, cy.a if cy else empty3, cy.r2 if cy else empty, cy.h if cy else empty,
              torch.cat(bounds) if bounds else torch.zeros(0, 4, dtype=torch.float64)]
    tracer._kernel_tables = [t.contiguous() for t in tables]
    return tracer._kernel_tables


def occlusion(tracer: Tracer, backend: str, origins: torch.Tensor, tangents: torch.Tensor,
              bitangents: torch.Tensor, normals: torch.Tensor, keys: torch.Tensor, spp: int, groups: int,
              seed: int, stream: int, cosine: bool, max_distance: float) -> torch.Tensor | None:
    """``(m, spp)`` bool: is sample ``j`` of pixel ``i`` occluded within ``max_distance`` (world units).

    ``origins``, ``tangents``, ``bitangents``, ``normals`` ``(m,3)`` (the offset ray origins and each
    pixel's frame), ``keys (m,)`` int64 the pixels' sample keys; the samples are
    :func:`.sampling.stratified_square` of ``(seed, stream)`` mapped to the cosine
    (``cosine=True``) or uniform hemisphere. ``None`` when ``backend`` is ``"torch"`` or the kernel
    does not cover the tracer (``backend="kernel"`` then raises ``ValueError``).
    """
    if backend == "torch":
        return None
    if not covers(tracer):
        if backend == "kernel":
            raise ValueError("backend: 'kernel' traces AO rays of analytic scenes on the CPU in float32 only; "
                             "use 'auto' or 'torch' for meshes, other devices or dtypes")
        return None
    if not _available():
        if backend == "kernel":
            from ..kernels.build import KernelUnavailable

            raise KernelUnavailable("backend='kernel': the reference tracer's C++ kernel could not be built")
        return None
    _, nx, ny = sampling.group_grid(spp, groups)
    constants = [c for s in (stream, stream + 1, stream + 2) for c in sampling.stream_constants(seed, s)]
    return _ops().ao_occlusion(origins.contiguous(), tangents.contiguous(), bitangents.contiguous(),
                               normals.contiguous(), keys.contiguous(), spp, groups, nx, ny, cosine,
                               float(max_distance), constants, *_tables(tracer))
