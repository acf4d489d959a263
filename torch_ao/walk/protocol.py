"""The walk's protocol: what a sampling pattern and an accumulator provide. Every hook is declared here.

The walk (:func:`torch_ao.walk.march`) calls, for every chunk of query pixels::

    method.begin_walk(queries)
    for each slice s < pattern.num_slices:
        T = pattern.slice_tangent(frame, queries, s); geom = the slice's frame
        state = method.begin_slice(queries, geom)
        for each side in pattern.sides, offsets = pattern.step_offsets(queries, geom, side):
            state = method.step(state, queries, geom, sample)            # one Sample per step, or
            state = method.step(state, queries', geom', all_steps)       # batch_steps: one per side, or
            state = method.step_pair(state, queries, geom, plus, minus)  # paired_sides: both sides of a step
        sums += method.end_slice(state, queries, geom)                   # {name: (N, C)}
    outputs = method.finish(sums, queries, pattern.num_slices)           # {name: (N, C)}
"""
from __future__ import annotations

import abc
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from .frame import Frame, Queries
    from .sample import Sample
    from .walk import SliceGeometry

__all__ = ["SamplingPattern", "SliceAccumulator"]


class SamplingPattern(abc.ABC):
    """Where the walk goes: slice tangents, sides, and the pixel offsets of the steps. Subclass to change it.

    Attributes:
        num_slices: slices per pixel; sides: the sides marched, ``(1, -1)`` (a half circle of slices)
            or ``(1,)`` (a full circle, one side each); fetch: ``"nearest"``, ``"bilinear"`` or ``"edge_aware"``;
            border: ``"clamp"`` or ``"drop"`` (see :mod:`torch_ao.walk.patterns`).
    """

    num_slices: int
    sides: tuple[int, ...] = (1, -1)
    fetch: str = "nearest"
    border: str = "clamp"

    @abc.abstractmethod
    def slice_tangent(self, frame: "Frame", q: "Queries", s: int) -> torch.Tensor:
        """``(N,3)`` unit slice tangent ``T`` of slice ``s``, orthogonal to ``V``."""

    def slice_direction(self, frame: "Frame", q: "Queries", s: int) -> "tuple[torch.Tensor, torch.Tensor | None]":
        """``(T, weight)``: :meth:`slice_tangent` and the slice's weight in the estimator ``(N,)`` (``1 / (pi p)``
        for slices drawn with density ``p`` over the half circle), ``None`` for evenly spaced slices (default)."""
        return self.slice_tangent(frame, q, s), None

    @abc.abstractmethod
    def step_offsets(self, q: "Queries", geom: "SliceGeometry", side: int) -> list[torch.Tensor]:
        """Pixel offsets ``(N,2)`` ``(du, dv)`` of the steps on ``side`` (``geom.pixels_per_unit``
        maps a world displacement along ``T`` to pixels)."""


class SliceAccumulator(abc.ABC):
    """What a method keeps while the walk goes. ``state`` is any object the method chooses.

    Attributes:
        batch_steps: when true, :meth:`step` gets one :class:`~torch_ao.walk.Sample` per side holding
            every step of that side, block-major (see ``Sample``): far fewer, larger tensor ops, which
            matters most when autograd records them.
        paired_sides: when true, the walk calls :meth:`step_pair` with step ``j`` of both sides at once
            (as XeGTAO and UE4 unroll the two sides of a slice) instead of :meth:`step`.
    """

    batch_steps: bool = False
    paired_sides: bool = False

    def begin_walk(self, queries: "Queries") -> None:
        """Called once per chunk of queries before its first slice (state across slices; default none)."""

    @abc.abstractmethod
    def begin_slice(self, queries: "Queries", geom: "SliceGeometry"):
        """The state at the start of a slice."""

    def step(self, state, queries: "Queries", geom: "SliceGeometry", sample: "Sample"):
        """The state after ``sample``."""
        raise TypeError(f"{type(self).__name__} takes no single steps (paired_sides={self.paired_sides})")

    def step_pair(self, state, queries: "Queries", geom: "SliceGeometry", plus: "Sample", minus: "Sample"):
        """With ``paired_sides``: the state after step ``j`` on side ``+1`` (``plus``) and ``-1`` (``minus``)."""
        raise TypeError(f"{type(self).__name__} takes no paired steps (paired_sides={self.paired_sides})")

    @abc.abstractmethod
    def end_slice(self, state, queries: "Queries", geom: "SliceGeometry") -> dict[str, torch.Tensor]:
        """Per-slice contributions ``{name: (N, C)}``; the walk sums them over slices."""

    @abc.abstractmethod
    def finish(self, sums: dict[str, torch.Tensor], queries: "Queries", num_slices: int) -> dict[str, torch.Tensor]:
        """Final per-query outputs ``{name: (N, C)}`` from the slice sums (the end of the walk)."""
