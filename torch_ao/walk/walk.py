"""The walk: every query pixel, every slice, both sides, every step; GTAO's Algorithm 1 as a loop.

The GTAO paper's Algorithm 1 (per pixel: for each slice, its direction and the projected normal's
angle ``n``; for each side, a horizon search over the steps; then the horizons clamped to the hemisphere
and the arc integrated) maps onto this module and the accumulator as follows:

=======================================================  ==============================================
Algorithm 1                                              here
=======================================================  ==============================================
slice direction ``phi`` (with per-pixel jitter)          ``pattern.slice_direction`` in :func:`slice_geometry`
``axis``, projected normal, its length and angle ``n``   :func:`slice_geometry` (``SliceGeometry``)
per side: initial horizon                                ``method.begin_slice``
per step: sample position, ``normalize(s - p)``          :func:`~torch_ao.walk.sample.fetch_sample`, ``Sample``
per step: ``max`` of the horizon cosine                  ``method.step`` (or ``step_pair``)
clamp ``h`` to ``n +- pi/2``, arc integral, ``|n_p|``    ``method.end_slice``
visibility ``/= sliceCount``                             ``method.finish``
=======================================================  ==============================================
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import torch
from torch.utils.checkpoint import checkpoint

from ..ops import safe_atan2
from .frame import Frame, Queries, repeat_rows
from .protocol import SamplingPattern, SliceAccumulator
from .sample import fetch_sample

__all__ = ["SliceGeometry", "slice_geometry", "march", "march_chunks"]


@dataclass
class SliceGeometry:
    """Per-pixel frame of one slice (see :mod:`torch_ao.walk`). Vectors ``(N,3)``, scalars ``(N,)``."""

    index: int
    tangent: torch.Tensor  # (N,3) T, unit, orthogonal to V
    normal_angle: torch.Tensor  # (N,) signed angle of the projected normal from V (toward +T)
    normal_length: torch.Tensor  # (N,) length of the projected normal
    pixels_per_unit: torch.Tensor  # (N,2) screen motion (du, dv) in pixels per world unit along +T
    weight: torch.Tensor | None = None  # (N,) the slice's weight in the estimator (None: evenly spaced slices)

    def map_rows(self, fn) -> "SliceGeometry":
        """The geometry with ``fn`` applied to every per-row tensor."""
        return SliceGeometry(self.index, fn(self.tangent), fn(self.normal_angle), fn(self.normal_length),
                             fn(self.pixels_per_unit), None if self.weight is None else fn(self.weight))

    def repeat(self, times: int) -> "SliceGeometry":
        """The rows repeated ``times`` times, block-major (as :meth:`Queries.repeat`)."""
        return self if times == 1 else self.map_rows(functools.partial(repeat_rows, times=times))



def slice_geometry(frame: Frame, q: Queries, pattern: SamplingPattern, s: int) -> SliceGeometry:
    """The frame of slice ``s`` at every query pixel: GTAO's Algorithm 1 from the slice direction to the
    projected normal's angle ``n``."""
    T, weight = pattern.slice_direction(frame, q, s)  # the slice direction, made orthogonal to V
    # the normal projected into the slice plane, N less its part along the plane's normal T x V: (N . V) V + (N . T) T
    along_view, along_tangent = (q.normal * q.view).sum(-1), (q.normal * T).sum(-1)
    normal_length = torch.stack((along_view, along_tangent), -1).norm(dim=-1)  # (at 0 a norm's gradient is 0, hypot's NaN)
    normal_angle = safe_atan2(along_tangent, along_view)  # (at 0 too its gradient is 0)
    # Derivative of the projection (u, v) = (fx x/d + cx, -fy y/d + cy), d = -z, along T.
    b = q.batch
    d = q.depth
    x, y = q.position[:, 0], q.position[:, 1]
    du = frame.fx[b] * (T[:, 0] + x * T[:, 2] / d) / d
    dv = -frame.fy[b] * (T[:, 1] + y * T[:, 2] / d) / d
    return SliceGeometry(s, T, normal_angle, normal_length, torch.stack((du, dv), -1), weight)

def _walk(frame: Frame, q: Queries, pattern: SamplingPattern, method: SliceAccumulator) -> dict[str, torch.Tensor]:
    """The outputs ``{name: (N, C)}`` of ``method`` walked over the queries ``q`` (one chunk)."""
    fetch = functools.partial(fetch_sample, frame, fetch=pattern.fetch, border=pattern.border)
    sums: dict[str, torch.Tensor] = {}
    repeated: dict[int, Queries] = {}  # the queries stacked per step count, built once per walk
    method.begin_walk(q)
    for s in range(pattern.num_slices):  # Algorithm 1: for each slice
        geom = slice_geometry(frame, q, pattern, s)
        state = method.begin_slice(q, geom)
        if method.paired_sides:  # step j of both sides together
            plus, minus = (pattern.step_offsets(q, geom, side) for side in (1, -1))
            for j, (op, om) in enumerate(zip(plus, minus)):
                state = method.step_pair(state, q, geom, fetch(q, geom, 1, j, op), fetch(q, geom, -1, j, om))
        else:
            for side in pattern.sides:  # Algorithm 1: for each side
                offsets = pattern.step_offsets(q, geom, side)
                if method.batch_steps and offsets:  # every step of the side in one Sample
                    J = len(offsets)
                    if J not in repeated:
                        repeated[J] = q.repeat(J)
                    qj, gj = repeated[J], geom.repeat(J)
                    state = method.step(state, qj, gj, fetch(qj, gj, side, None, torch.cat(offsets, 0), steps=J,
                                                             base=(q, geom)))
                elif not method.batch_steps:
                    for j, offset in enumerate(offsets):  # Algorithm 1: for each sample
                        state = method.step(state, q, geom, fetch(q, geom, side, j, offset))
        for name, value in method.end_slice(state, q, geom).items():
            if geom.weight is not None:  # slices drawn by a density: each weighted so the sum stays unbiased
                value = value * geom.weight.to(value.dtype)[:, None]
            sums[name] = value if name not in sums else sums[name] + value
    return method.finish(sums, q, pattern.num_slices)


def march_chunks(frame: Frame, walk: Callable[[Frame, Queries], dict[str, torch.Tensor]], *,
                 chunk_size: int | None = None, recompute: bool = False) -> dict[str, torch.Tensor]:
    """``walk(frame, queries)`` ``-> {name: (n, C)}`` run over the frame's query pixels in chunks of at
    most ``chunk_size`` (bounds memory), each recomputed in backward when ``recompute`` (activation
    checkpointing; with ``chunk_size`` the memory of forward+backward is bounded by one chunk), and the
    outputs concatenated ``{name: (N, C)}``. The one chunking and recompute machinery: :func:`march`
    uses it for slice walks, SSAO for its kernel."""
    q = frame.queries
    n = len(q)
    size = max(n, 1) if chunk_size is None else max(1, int(chunk_size))
    outputs: list[dict[str, torch.Tensor]] = []
    # An empty query list (an all-background frame) still walks once, on empty tensors, so that
    # outputs stay connected to the parameters (with zero gradient).
    for start in range(0, max(n, 1), size):
        qc = q if size >= n else q.subset(slice(start, start + size))
        if recompute and torch.is_grad_enabled():
            outputs.append(checkpoint(walk, frame, qc, use_reentrant=False))
        else:
            outputs.append(walk(frame, qc))
    if len(outputs) == 1:
        return outputs[0]
    return {k: torch.cat([o[k] for o in outputs], 0) for k in outputs[0]}


def march(frame: Frame, pattern: SamplingPattern, method: SliceAccumulator, *, chunk_size: int | None = None,
          recompute: bool = False) -> dict[str, torch.Tensor]:
    """Walk every query pixel of ``frame`` along ``pattern`` and return ``method``'s outputs ``{name: (N, C)}``.

    Args:
        chunk_size, recompute: memory controls (see :func:`march_chunks`).
    """
    return march_chunks(frame, lambda f, q: _walk(f, q, pattern, method), chunk_size=chunk_size, recompute=recompute)
