"""One sample of the walk (:class:`Sample`): what a method reads about a step, computed on first use."""
from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import torch

from .fetch import Footprint, SampleAlong, bilerp
from .frame import Frame, Queries, take

if TYPE_CHECKING:
    from .walk import SliceGeometry

__all__ = ["MIN_OFFSET", "Sample", "fetch_sample"]

#: the shortest offset of a sample from its pixel, as a fraction of the pixel's depth, that can occlude: float32
#: rounding of the pixel's own position is ~1e-7 of the depth, and a step 0.005 pixels long at a focal length of
#: 500 pixels is 1e-5 of it
MIN_OFFSET = 1e-5


class cached_property:  # noqa: N801 (functools' name)
    """``functools.cached_property`` without its lock: Python 3.11's takes an ``RLock``, a context manager
    that ``torch.compile`` cannot trace (a graph break at every first read of a sample's attribute)."""

    def __init__(self, fn) -> None:
        self.fn, self.name, self.__doc__ = fn, fn.__name__, fn.__doc__

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        value = obj.__dict__[self.name] = self.fn(obj)
        return value


class Sample:
    """One step of the walk on one side of a slice, for every query pixel (``N`` rows).

    With an accumulator that sets ``batch_steps = True``, one ``Sample`` holds all ``steps`` steps of
    a side at once: its rows (and those of the queries and geometry passed with it) are block-major,
    row ``j * N + i`` being step ``j`` of query ``i``; ``step`` is then ``None``.

    Attributes:
        side: ``+1`` or ``-1``; step: the step number (``None`` for a batch of steps, or for a sample
            taken outside a slice walk); steps: how many steps the rows hold (1 or all);
            dtype: the floating type of the walk.
        offset: ``(N,2)`` the pixel offset ``(du, dv)`` of the sample from its query pixel.
        inside: ``(N,)`` bool, whether the sample's screen position lies in the image (pixel centres
            ``[0, W-1] x [0, H-1]``), whatever the border mode did with it.
        position: ``(N,3)`` sample's view-space position; ``delta = position - P``.
        valid: ``(N,)`` bool; invalid samples (background, dropped at the border, or on the centre
            texel) have a safe ``delta`` pointing away from the camera, so they never occlude.
        along_view, along_tangent: ``delta . V`` and ``delta . (side T)``, ``(N,)``.
        distance: ``|delta|`` ``(N,)``; distance_px: the screen distance in pixels ``(N,)``.

    ``geom`` may be ``None`` for a sample taken outside a slice walk (SSAO's kernel): then only the
    position-based attributes exist (no ``along_*``, ``angle`` or ``cos_view``).

    When autograd records the walk, ``along_view``/``along_tangent`` come from :class:`SampleAlong`
    (fused, a few floats per sample), and ``position``/``delta`` are only recorded if a method asks.
    """

    def __init__(self, frame: Frame, geom: "SliceGeometry | None", side: int, step: int | None, queries: Queries,
                 footprint: Footprint, valid: torch.Tensor, offset: torch.Tensor, steps: int = 1,
                 base: "tuple[Queries, SliceGeometry] | None" = None) -> None:
        self.side, self.step, self.steps = side, step, steps
        self.dtype = queries.position.dtype
        self._frame, self._footprint, self._queries, self._geom = frame, footprint, queries, geom
        self.offset = offset
        self._raw_position = None  # the fetched position, when it was computed without a graph
        self._base = (queries, geom) if base is None else base
        with torch.no_grad():
            position = footprint.position(frame)
            delta = position - queries.position
            # A sample on the centre texel, or one whose offset is the rounding of the pixel's own position
            # (a footprint clamped onto it at the border, read back through the inverse depth: ~1e-7 of the
            # depth in float32), would occlude in a direction made of noise: drop it.
            self.valid = valid = valid & ((delta / queries.depth[:, None]).square().sum(-1) > MIN_OFFSET ** 2)
            self._delta_values = torch.where(valid[:, None], delta, -queries.view)  # away from the camera
        base_q, base_g = self._base
        self._inputs = footprint.inputs(frame) + (base_q.position, base_q.view) + (() if base_g is None else (base_g.tangent,))
        self._graph = torch.is_grad_enabled() and any(t.requires_grad for t in self._inputs)
        if not self._graph:  # keep the values computed above
            self._raw_position = position
            self.__dict__["delta"] = self._delta_values

    @cached_property
    def along_view(self) -> torch.Tensor:
        return self._along[0]

    @cached_property
    def along_tangent(self) -> torch.Tensor:
        return self._along[1]

    @cached_property
    def _along(self) -> tuple[torch.Tensor, torch.Tensor]:
        q, geom = self._queries, self._geom
        if not self._graph:
            return _along(self._delta_values, q.view, geom.tangent, self.side)
        if self._footprint.fusable(self._frame):
            with torch.no_grad():
                values = _along(self._delta_values, q.view, geom.tangent, self.side)
            return SampleAlong.apply(self._frame, self._footprint, self.valid, self.side, self.steps,
                                     self._base[0].batch, values, *self._inputs)
        return _along(self.delta, q.view, geom.tangent, self.side)

    def rows(self, index: torch.Tensor) -> "Sample":
        """The sample restricted to rows ``index`` ``(M,)`` (one flat step: ``steps = 1``)."""
        pick = functools.partial(take, index=index)
        return Sample(self._frame, self._geom.map_rows(pick), self.side, None, self._queries.map_rows(pick),
                      self._footprint.map_rows(pick), pick(self.valid), pick(self.offset))

    # Computed on first use only: most methods need neither, and autograd would keep their inputs.
    @cached_property
    def position(self) -> torch.Tensor:
        raw = self._footprint.position(self._frame) if self._raw_position is None else self._raw_position
        return torch.where(self.valid[:, None], raw, self._queries.position - self._queries.view)

    @cached_property
    def delta(self) -> torch.Tensor:
        return torch.where(self.valid[:, None], self.position - self._queries.position, -self._queries.view)

    @cached_property
    def distance(self) -> torch.Tensor:
        return self.delta.norm(dim=-1)

    @cached_property
    def distance_px(self) -> torch.Tensor:
        return self.offset.norm(dim=-1)

    @cached_property
    def inside(self) -> torch.Tensor:
        _, H, W = self._frame.shape
        su, sv = self._footprint.su, self._footprint.sv
        return (su >= 0) & (su <= W - 1) & (sv >= 0) & (sv <= H - 1)

    def angle(self, view_offset: torch.Tensor | float = 0.0) -> torch.Tensor:
        """Angle ``(N,)`` in ``[-pi, pi]`` from V toward this side of ``delta - view_offset * V``,
        projected onto the slice plane (``atan2``, stable at every angle)."""
        return torch.atan2(self.along_tangent, self.along_view - view_offset)

    def cos_view(self, view_offset: torch.Tensor | float = 0.0) -> torch.Tensor:
        """``dot(normalize(delta - view_offset * V), V)`` ``(N,)``: the shaders' horizon cosine (3D, not projected)."""
        off = torch.as_tensor(view_offset, dtype=self.delta.dtype, device=self.delta.device)
        view = self._queries.view
        d = self.delta - (off[:, None] if off.dim() == 1 else off) * view
        return (d * view).sum(-1) / d.norm(dim=-1).clamp_min(1e-30)

    def gather(self, name: str) -> torch.Tensor:
        """Value ``(N, C)`` of the frame buffer ``name`` at this sample (nearest, bilinear or edge-aware,
        as the walk fetches depth; integer buffers are always nearest)."""
        buf = self._frame.buffers[name]
        f = self._footprint
        if f.fu is None or not buf.is_floating_point():
            return take(buf, f.index if f.fu is None else f.index[:, 0])
        fu, fv = f.fu.to(buf.dtype)[:, None], f.fv.to(buf.dtype)[:, None]
        return bilerp(take(buf, f.index).unbind(1), fu, fv)  # (N,C)


def _along(delta: torch.Tensor, view: torch.Tensor, tangent: torch.Tensor, side: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(delta . V, side * delta . T)`` ``(N,)``."""
    return (delta * view).sum(-1), side * (delta * tangent).sum(-1)


def fetch_sample(frame: Frame, q: Queries, geom: "SliceGeometry | None", side: int, step: int | None,
                 offset: torch.Tensor, *, fetch: str, border: str, steps: int = 1,
                 base: "tuple[Queries, SliceGeometry] | None" = None) -> Sample:
    """The sample at pixel ``offset`` ``(N,2)`` from each query pixel, on ``side``, read with ``fetch``
    (``"nearest"``/``"bilinear"``/``"edge_aware"``) and ``border`` (``"clamp"``/``"drop"``). With ``steps`` > 1 the rows of
    ``q``, ``geom`` and ``offset`` hold that many steps, block-major, and ``base`` gives the queries and
    geometry of one step."""
    footprint, inside = Footprint.at(frame, q.batch, q.u + offset[:, 0], q.v + offset[:, 1], fetch)
    valid = footprint.valid(frame) & ~footprint.on_own_texel(q.index)
    if border == "drop":
        valid = valid & inside
    return Sample(frame, geom, side, step, q, footprint, valid, offset, steps, base)
