"""One sample of the walk (:class:`Sample`): what a method reads about a step, computed on first use."""
from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import torch

from .fetch import Footprint, GradientRows, _bilerp_depth_backward, bilerp, bilinear_taps, edge_aware_taps
from .frame import Frame, Queries, take

if TYPE_CHECKING:
    from .walk import SliceGeometry

__all__ = ["MIN_OFFSET", "Sample", "SampleAlong", "fetch_sample", "slice_coordinates"]

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
        along_view, along_tangent: ``delta . V`` and ``delta . (side T)``, ``(N,)``; a tangent coordinate
            within ``MIN_OFFSET`` of the pixel's depth is ``+0`` (:func:`slice_coordinates`).
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
        depth = -q.position[:, 2]
        if not self._graph:
            return slice_coordinates(self._delta_values, q.view, geom.tangent, self.side, depth)
        if self._footprint.fusable(self._frame):
            with torch.no_grad():
                values = slice_coordinates(self._delta_values, q.view, geom.tangent, self.side, depth)
            return SampleAlong.apply(self._frame, self._footprint, self.valid, self.side, self.steps,
                                     self._base[0].batch, values, *self._inputs)
        return slice_coordinates(self.delta, q.view, geom.tangent, self.side, depth)

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


def slice_coordinates(delta: torch.Tensor, view: torch.Tensor, tangent: torch.Tensor, side: int,
                      depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(delta . V, side delta . T)`` ``(N,)`` of offsets ``delta`` ``(N,3)`` from pixels at ``depth`` ``(N,)``
    (``-P_z``), the tangent coordinate ``+0`` (without gradient) within ``MIN_OFFSET`` of the depth.

    A sample in the plane of the view vector and the slice's normal (off the slice: one the border clamps into
    the pixel's own column, or an invalid one's ``-V``) has a tangent coordinate of 0 but for rounding, whose
    sign would decide whether its back angle is +pi or -pi, and with it which half of the hemisphere it
    occludes. Taken as ``+0``, it lies on its own side in every backend and precision."""
    along_view = (delta * view).sum(-1)
    along_tangent = side * (delta * tangent).sum(-1)
    off_slice = along_tangent.detach().abs() <= MIN_OFFSET * depth.detach()
    return along_view, torch.where(off_slice, 0.0, along_tangent)


class SampleAlong(torch.autograd.Function):
    """Gradients of ``(delta . V, side * delta . T)`` of ``steps`` block-major steps, fused.

    Inputs: the frame, the samples' :class:`Footprint` (``steps * N`` rows), ``valid`` (rows), ``side``,
    ``steps``, ``batch`` ``(N,)``, the two outputs' values (computed without a graph); then the
    footprint's differentiable inputs (``frame.positions`` ``(P,3)`` for nearest fetch or
    ``frame.inverse_depth`` ``(P,)`` for bilinear, ``su``, ``sv``) and the queries' ``P``, ``V``, ``T``
    ``(N,3)`` (not repeated per step). Plain autograd would keep the position, ``delta``, the repeated
    ``V`` and ``T`` and the fetch's intermediates for every sample (about 90 bytes); this keeps ``su``,
    ``sv`` and ``valid`` per sample and rebuilds the footprint, position and ``delta`` in backward.
    """

    @staticmethod
    def forward(ctx, frame, footprint, valid, side, steps, batch, along, source, su, sv, P, V, T):
        ctx.frame, ctx.side, ctx.steps, ctx.nearest = frame, side, steps, footprint.fu is None
        ctx.edge_aware = footprint.edge_aware
        ctx.save_for_backward(source, su, sv, valid, batch, P, V, T, footprint.index if ctx.nearest else None)
        return along

    @staticmethod
    def backward(ctx, g_view, g_tangent):
        source, su, sv, valid, batch, P, V, T, index = ctx.saved_tensors
        frame, side, J = ctx.frame, ctx.side, ctx.steps
        N = P.shape[0]
        g_view = torch.zeros(J * N, dtype=P.dtype, device=P.device) if g_view is None else g_view
        g_tangent = torch.zeros_like(g_view) if g_tangent is None else g_tangent
        with torch.no_grad():
            # delta_j = position_j - P where valid (m = 1), else -V; along_view = delta . V, along_tangent = side delta . T
            # (+0 without gradient off the slice: slice_coordinates). Rows are block-major (J, N); only rows with a
            # gradient are worked on (see GradientRows).
            rows = GradientRows(J, N, g_view, g_tangent)
            g_view, g_tangent, su, sv, valid = map(rows.take, (g_view, g_tangent, su, sv, valid))
            Vr, Tr, Pr = rows.per_row(V), rows.per_row(T), rows.per_row(P)
            # forward inputs after ctx: frame, footprint, valid, side, steps, batch, along (no gradient),
            # then source, su, sv, P, V, T
            needs = dict(zip(("source", "su", "sv", "P", "V", "T"), ctx.needs_input_grad[7:]))
            if ctx.nearest:
                index = rows.take(index)
                position = take(source, index)
            else:
                B, H, W = frame.shape
                batch_rows = rows.per_row(batch) if B > 1 else batch  # (a single image needs no per-row batch)
                taps, fu, fv = bilinear_taps(frame, batch_rows, su, sv)
                if ctx.edge_aware:
                    taps = edge_aware_taps(frame, taps, fu, fv)
                inverse = take(source, taps)  # (rows,4) inverse depths
                depth = bilerp(inverse.unbind(-1), fu, fv).reciprocal()
                fx, fy, cx, cy = frame.intrinsics(batch_rows)
                # position = depth * (xh, yh, -1) with xh = (clamp(su) - cx) / fx, yh = -(clamp(sv) - cy) / fy
                su_c, sv_c = su.clamp(0, W - 1), sv.clamp(0, H - 1)
                xh, yh = (su_c - cx) / fx, (sv_c - cy) / -fy
                position = torch.stack((xh * depth, yh * depth, -depth), -1)
            delta = torch.where(valid[:, None], position - Pr, -Vr)
            g_tangent = torch.where(slice_coordinates(delta, Vr, Tr, side, -Pr[:, 2])[1] == 0, 0.0, g_tangent)
            m = valid.to(P.dtype)
            gv = g_view * m  # gradients reaching valid samples
            gt = g_tangent * (m if side > 0 else -m)
            a, b = rows.per_query(gv)[:, None], rows.per_query(gt)[:, None]  # (N,1)
            c = rows.per_query(g_view)[:, None] - a  # ... and invalid ones
            e = side * rows.per_query(g_tangent)[:, None] - b
            g_source = g_su = g_sv = g_P = g_V = g_T = None
            if ctx.nearest:
                if needs["source"]:
                    g_pos = gv[:, None] * Vr + gt[:, None] * Tr
                    g_source = torch.zeros_like(source).index_add_(0, index, g_pos)
            else:
                g_x = torch.addcmul(gv * Vr[:, 0], gt, Tr[:, 0])
                g_y = torch.addcmul(gv * Vr[:, 1], gt, Tr[:, 1])
                g_z = torch.addcmul(gv * Vr[:, 2], gt, Tr[:, 2])
                g_inverse, g_fu, g_fv = _bilerp_depth_backward(inverse, fu, fv, depth, g_x * xh + g_y * yh - g_z)
                if needs["source"]:
                    g_source = torch.zeros_like(source).index_add_(0, taps.view(-1), g_inverse.view(-1))
                # fu = su - floor(su); clamp passes the gradient inside [0, W - 1]
                g_su = rows.put(torch.where(su_c == su, g_x * (depth / fx), 0.0).add_(g_fu))
                g_sv = rows.put(torch.where(sv_c == sv, g_y * (depth / -fy), 0.0).add_(g_fv))
            # sums over the steps of the gradients times the position
            Sv = torch.stack([rows.per_query(gv * p) for p in position.unbind(-1)], -1)  # (N,3)
            St = torch.stack([rows.per_query(gt * p) for p in position.unbind(-1)], -1)
            if needs["P"]:
                g_P = -(a * V + b * T)
            if needs["V"]:
                g_V = Sv - a * P - 2 * c * V - e * T
            if needs["T"]:
                g_T = St - b * P - e * V
        return (None,) * 7 + (g_source, g_su, g_sv, g_P, g_V, g_T)


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
