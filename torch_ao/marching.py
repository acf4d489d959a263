"""The one slice-marching core shared by every horizon and visibility-bitmask method.

Every method of the horizon family walks the same way: per pixel, a few screen-space directions
("slices"); along each, a few samples ("steps") on one or both sides; per sample, the view-space
offset to the centre pixel and its angle from the view vector inside the slice plane. Methods only
say what they keep per step (max horizon, falloff-weighted horizon, a bitmask, soft sector
coverage, gathered light), by implementing :class:`SliceAccumulator`.

Work is done on a flat list of *query* pixels (the valid, non-background ones), so background
costs nothing and the list can be processed in chunks to bound memory.

Geometry of one slice (all view space, unit vectors, shapes ``(N, 3)``):

* ``V``: from the pixel toward the camera.
* ``T``: the slice tangent, orthogonal to ``V``; side ``+1`` marches toward the screen image of ``+T``.
  (The plane through the camera spanned by ``V`` and ``T`` projects to one screen line through the
  pixel, so samples along that line lie in the slice plane.)
* ``axis = T x V``: normal of the slice plane.
* The projected normal ``n_p = N - axis (N . axis)`` has length ``normal_length`` and signed angle
  ``normal_angle = atan2(n_p . T, n_p . V)`` from ``V`` (positive toward ``+T``).

A sample on side ``s`` has angle ``theta = atan2(delta . (s T), delta . V)`` from ``V``, measured toward
its own side: 0 looks at the camera, ``pi`` looks away. In signed slice coordinates it sits at
``s * theta``; the hemisphere around the projected normal spans ``[normal_angle - pi/2, normal_angle + pi/2]``.
"""
from __future__ import annotations

import abc
import functools
import math
from dataclasses import dataclass, field
from typing import Protocol

import torch
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

from .gbuffer import GBuffer

__all__ = [
    "Frame",
    "Queries",
    "SliceGeometry",
    "Sample",
    "SliceAccumulator",
    "SamplingPattern",
    "SlicePattern",
    "march",
    "interleaved_gradient_noise",
    "fast_acos",
]

FETCH_MODES = ("nearest", "bilinear")
BORDER_MODES = ("clamp", "drop")


def interleaved_gradient_noise(u: torch.Tensor, v: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Jimenez's interleaved gradient noise in ``[0, 1)`` at integer pixel coordinates.

    ``frac(52.9829189 * frac(0.06711056 * x + 0.00583715 * y))``; ``seed`` shifts the pattern
    (by 5.588238 pixels per unit, the per-frame offset of the original), so every seed is a new,
    reproducible pattern.
    """
    x = u.double() + 5.588238 * seed
    y = v.double() + 5.588238 * seed
    return torch.frac(52.9829189 * torch.frac(0.06711056 * x + 0.00583715 * y))


def fast_acos(x: torch.Tensor) -> torch.Tensor:
    """HDRP/XeGTAO's polynomial ``acos`` (max error ~1e-2 rad): ``(pi/2 - 0.156583|x|) sqrt(1-|x|)``."""
    ax = x.abs()
    inside = ax < 1
    # sqrt'(0) is infinite: evaluate it on a safe value at |x| >= 1, where the result is exactly 0/pi.
    root = torch.where(inside, torch.sqrt(torch.where(inside, 1 - ax, torch.ones_like(ax))), torch.zeros_like(ax))
    res = (-0.156583 * ax + math.pi / 2) * root
    return torch.where(x >= 0, res, math.pi - res)


# ---------------------------------------------------------------------------------------------
# Inputs: flattened buffers and query pixels
# ---------------------------------------------------------------------------------------------
@dataclass
class Queries:
    """The pixels being computed (a subset of the frame, flattened). All tensors have N rows."""

    index: torch.Tensor  # (N,) long, flat index b*H*W + v*W + u
    batch: torch.Tensor  # (N,) long
    u: torch.Tensor  # (N,) pixel column (float)
    v: torch.Tensor  # (N,) pixel row (float)
    position: torch.Tensor  # (N,3) view-space position P
    normal: torch.Tensor  # (N,3) unit normal
    view: torch.Tensor  # (N,3) unit vector toward the camera, V = normalize(-P)
    depth: torch.Tensor  # (N,) positive depth
    values: dict[str, torch.Tensor] = field(default_factory=dict)  # per-query extras, (N, C)

    def __len__(self) -> int:
        return self.index.shape[0]

    def map_rows(self, fn) -> "Queries":
        """The queries with ``fn`` applied to every per-row tensor (a slice, a gather, a repeat...)."""
        return Queries(fn(self.index), fn(self.batch), fn(self.u), fn(self.v), fn(self.position), fn(self.normal),
                       fn(self.view), fn(self.depth), {k: fn(x) for k, x in self.values.items()})

    def subset(self, sl: slice) -> "Queries":
        return self.map_rows(lambda x: x[sl])

    def repeat(self, times: int) -> "Queries":
        """The rows repeated ``times`` times, block-major: row ``j * N + i`` is query ``i``."""
        return self if times == 1 else self.map_rows(functools.partial(_repeat_rows, times=times))


class Frame:
    """A G-buffer flattened for gathering: buffers are ``(B*H*W, C)``, channel-last.

    Args:
        gbuffer: the validated inputs.
        normals: ``(B,3,H,W)`` unit normals to use (e.g. ``gbuffer.view_normals()``); ``None``
            uses ``gbuffer.view_normals()``.
        buffers: extra ``(B,C,H,W)`` images that samples may gather (light, normals of samples,
            object ids, per-pixel parameter maps...).
        query_values: extra ``(B,C,H,W)`` images gathered once at the query pixels.
        queries_mask: optional ``(B,1,H,W)`` bool restricting which pixels are computed
            (default: every valid pixel).
    """

    def __init__(
        self,
        gbuffer: GBuffer,
        normals: torch.Tensor | None = None,
        buffers: dict[str, torch.Tensor] | None = None,
        query_values: dict[str, torch.Tensor] | None = None,
        queries_mask: torch.Tensor | None = None,
    ) -> None:
        self.gbuffer = gbuffer
        B, _, H, W = gbuffer.depth.shape
        self.shape = (B, H, W)
        self.dtype = gbuffer.depth.dtype
        self.device = gbuffer.depth.device
        cam = gbuffer.camera
        self.fx, self.fy, self.cx, self.cy = cam.fx, cam.fy, cam.cx, cam.cy  # (B,)
        self.safe_depth = _flat(gbuffer.safe_depth)[:, 0]  # (BHW,)
        self.inverse_depth = self.safe_depth.reciprocal()  # (BHW,): what bilinear fetches interpolate
        self.positions = _flat(gbuffer.positions())  # (BHW, 3)
        self.valid = _flat(gbuffer.valid)[:, 0]  # (BHW,)
        self.buffers = {k: _flat(v) for k, v in (buffers or {}).items()}
        if normals is None:
            normals = gbuffer.view_normals()
        mask = gbuffer.valid if queries_mask is None else gbuffer.valid & queries_mask
        index = _flat(mask)[:, 0].nonzero()[:, 0]
        hw = H * W
        batch = torch.div(index, hw, rounding_mode="floor")
        rem = index - batch * hw
        v = torch.div(rem, W, rounding_mode="floor")
        u = rem - v * W
        P = self.positions[index]
        self.queries = Queries(
            index=index,
            batch=batch,
            u=u.to(self.dtype),
            v=v.to(self.dtype),
            position=P,
            normal=_flat(normals)[index],
            view=F.normalize(-P, dim=-1),
            depth=self.safe_depth[index],
            values={k: _flat(x)[index] for k, x in (query_values or {}).items()},
        )

    def intrinsics(self, batch: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(fx, fy, cx, cy)`` of each row's image ``batch`` ``(N,)``: 0-d tensors for a single image
        (broadcast, no gather), else ``(N,)``."""
        if self.shape[0] == 1:
            return self.fx[0], self.fy[0], self.cx[0], self.cy[0]
        return self.fx[batch], self.fy[batch], self.cx[batch], self.cy[batch]

    def scatter(self, values: torch.Tensor, fill: float | torch.Tensor) -> torch.Tensor:
        """Place per-query rows ``(N, C)`` into a ``(B, C, H, W)`` image, ``fill`` elsewhere."""
        B, H, W = self.shape
        C = values.shape[1]
        if isinstance(fill, torch.Tensor):  # (B,C,H,W) background image
            base = _flat(fill.to(values.dtype))
        else:
            base = values.new_full((B * H * W, C), float(fill))
        out = base.index_put((self.queries.index,), values)
        return out.view(B, H, W, C).permute(0, 3, 1, 2)


def _repeat_rows(x: torch.Tensor, times: int) -> torch.Tensor:
    """``x`` ``(N, ...)`` stacked ``times`` times along the rows: ``(times * N, ...)``."""
    return x.repeat(times, *([1] * (x.dim() - 1)))


def _flat(x: torch.Tensor) -> torch.Tensor:
    """``(B,C,H,W)`` -> contiguous ``(B*H*W, C)`` (row gathers from a strided view are many times slower)."""
    B, C, H, W = x.shape
    return x.permute(0, 2, 3, 1).reshape(B * H * W, C).contiguous()


# ---------------------------------------------------------------------------------------------
# Slices and samples
# ---------------------------------------------------------------------------------------------
@dataclass
class SliceGeometry:
    """Per-pixel frame of one slice; see the module docstring. Vectors ``(N,3)``, scalars ``(N,)``."""

    index: int
    tangent: torch.Tensor  # (N,3) T, unit, orthogonal to V
    axis: torch.Tensor  # (N,3) normal of the slice plane
    normal_angle: torch.Tensor  # (N,) signed angle of the projected normal from V (toward +T)
    normal_length: torch.Tensor  # (N,) length of the projected normal
    pixels_per_unit: torch.Tensor  # (N,2) screen motion (du, dv) in pixels per world unit along +T

    def map_rows(self, fn) -> "SliceGeometry":
        """The geometry with ``fn`` applied to every per-row tensor."""
        return SliceGeometry(self.index, fn(self.tangent), fn(self.axis), fn(self.normal_angle), fn(self.normal_length),
                             fn(self.pixels_per_unit))

    def repeat(self, times: int) -> "SliceGeometry":
        """The rows repeated ``times`` times, block-major (as :meth:`Queries.repeat`)."""
        return self if times == 1 else self.map_rows(functools.partial(_repeat_rows, times=times))


class Sample:
    """One step of the walk on one side of a slice, for every query pixel (``N`` rows).

    With an accumulator that sets ``batch_steps = True``, one ``Sample`` holds all ``steps`` steps of
    a side at once: its rows (and those of the queries and geometry passed with it) are block-major,
    row ``j * N + i`` being step ``j`` of query ``i``; ``step`` is then ``None``.

    Attributes:
        side: ``+1`` or ``-1``; step: the step number; steps: how many steps the rows hold (1 or all);
            dtype: the floating type of the walk.
        position: ``(N,3)`` sample's view-space position; ``delta = position - P``.
        valid: ``(N,)`` bool; invalid samples (background, dropped at the border, or on the centre
            texel) have a safe ``delta`` pointing away from the camera, so they never occlude.
        along_view, along_tangent: ``delta . V`` and ``delta . (side T)``, ``(N,)``.
        distance: ``|delta|`` ``(N,)``; distance_px: the screen distance in pixels ``(N,)``.

    When autograd records the walk, ``along_view``/``along_tangent`` come from :class:`SampleAlong`
    (fused, a few floats per sample), and ``position``/``delta`` are only recorded if a method asks.
    """

    def __init__(self, frame: Frame, geom: SliceGeometry, side: int, step: int | None, queries: Queries,
                 footprint: "Footprint", valid: torch.Tensor, offset: torch.Tensor, steps: int = 1,
                 base: tuple[Queries, SliceGeometry] | None = None) -> None:
        self.side, self.step, self.steps = side, step, steps
        self.dtype = queries.position.dtype
        self._frame, self._footprint, self._queries, self._geom = frame, footprint, queries, geom
        self._offset = offset
        self._raw_position = None  # the fetched position, when it was computed without a graph
        self._base = (queries, geom) if base is None else base
        with torch.no_grad():
            position = footprint.position(frame)
            delta = position - queries.position
            # A sample on the centre texel (or a degenerate one) would give 0/0 angles: drop it.
            self.valid = valid = valid & (delta.square().sum(-1) > 1e-20 * queries.depth.square())
            self._delta_values = torch.where(valid[:, None], delta, -queries.view)  # away from the camera
        base_q, base_g = self._base
        self._inputs = footprint.inputs(frame) + (base_q.position, base_q.view, base_g.tangent)
        self._graph = torch.is_grad_enabled() and any(t.requires_grad for t in self._inputs)
        if not self._graph:  # keep the values computed above
            self._raw_position = position
            self.__dict__["delta"] = self._delta_values

    @functools.cached_property
    def along_view(self) -> torch.Tensor:
        return self._along[0]

    @functools.cached_property
    def along_tangent(self) -> torch.Tensor:
        return self._along[1]

    @functools.cached_property
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
        take = functools.partial(_take, index=index)
        return Sample(self._frame, self._geom.map_rows(take), self.side, None, self._queries.map_rows(take),
                      self._footprint.map_rows(take), take(self.valid), take(self._offset))

    # Computed on first use only: most methods need neither, and autograd would keep their inputs.
    @functools.cached_property
    def position(self) -> torch.Tensor:
        raw = self._footprint.position(self._frame) if self._raw_position is None else self._raw_position
        return torch.where(self.valid[:, None], raw, self._queries.position - self._queries.view)

    @functools.cached_property
    def delta(self) -> torch.Tensor:
        return torch.where(self.valid[:, None], self.position - self._queries.position, -self._queries.view)

    @functools.cached_property
    def distance(self) -> torch.Tensor:
        return self.delta.norm(dim=-1)

    @functools.cached_property
    def distance_px(self) -> torch.Tensor:
        return self._offset.norm(dim=-1)

    def angle(self, view_offset: torch.Tensor | float = 0.0) -> torch.Tensor:
        """Angle ``(N,)`` in ``[-pi, pi]`` from V toward this side of ``delta - view_offset * V``,
        projected onto the slice plane (``atan2``, stable at every angle)."""
        return torch.atan2(self.along_tangent, self.along_view - view_offset)

    def cos_view(self, view_offset: torch.Tensor | float = 0.0) -> torch.Tensor:
        """``dot(normalize(delta - view_offset * V), V)`` ``(N,)``: the seeds' horizon cosine (3D, not projected)."""
        off = torch.as_tensor(view_offset, dtype=self.delta.dtype, device=self.delta.device)
        view = self._queries.view
        d = self.delta - (off[:, None] if off.dim() == 1 else off) * view
        return (d * view).sum(-1) / d.norm(dim=-1).clamp_min(1e-30)

    def gather(self, name: str) -> torch.Tensor:
        """Value ``(N, C)`` of the frame buffer ``name`` at this sample (nearest or bilinear,
        as the walk fetches depth; integer buffers are always nearest)."""
        buf = self._frame.buffers[name]
        f = self._footprint
        if f.fu is None or not buf.is_floating_point():
            return _take(buf, f.index if f.fu is None else f.index[:, 0])
        fu, fv = f.fu.to(buf.dtype)[:, None], f.fv.to(buf.dtype)[:, None]
        return _bilerp(_take(buf, f.index).unbind(1), fu, fv)  # (N,C)


def _along(delta: torch.Tensor, view: torch.Tensor, tangent: torch.Tensor, side: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(delta . V, side * delta . T)`` ``(N,)``."""
    return (delta * view).sum(-1), side * (delta * tangent).sum(-1)


class SliceAccumulator(Protocol):
    """What a method keeps while the core walks. ``state`` is any object the method chooses.

    An accumulator with a true ``batch_steps`` attribute gets one :meth:`step` call per side holding
    every step of that side (see :class:`Sample`): far fewer, larger tensor ops, which matters most
    when autograd records them.
    """

    def begin_slice(self, queries: Queries, geom: SliceGeometry): ...

    def step(self, state, queries: Queries, geom: SliceGeometry, sample: Sample): ...

    def end_slice(self, state, queries: Queries, geom: SliceGeometry) -> dict[str, torch.Tensor]:
        """Per-slice contributions ``{name: (N, C)}``; the core sums them over slices."""
        ...

    def finish(self, sums: dict[str, torch.Tensor], queries: Queries, num_slices: int) -> dict[str, torch.Tensor]:
        """Final per-query outputs ``{name: (N, C)}`` from the slice sums."""
        ...


# ---------------------------------------------------------------------------------------------
# Sampling patterns
# ---------------------------------------------------------------------------------------------
class SamplingPattern(abc.ABC):
    """Where the walk goes: slice tangents, sides, and the pixel offsets of the steps. Subclass to change it."""

    num_slices: int
    sides: tuple[int, ...] = (1, -1)
    fetch: str = "nearest"
    border: str = "clamp"

    @abc.abstractmethod
    def slice_tangent(self, frame: Frame, q: Queries, s: int) -> torch.Tensor:
        """``(N,3)`` unit slice tangent ``T`` of slice ``s``, orthogonal to ``V``."""

    @abc.abstractmethod
    def step_offsets(self, q: Queries, geom: "SliceGeometry", side: int) -> list[torch.Tensor]:
        """Pixel offsets ``(N,2)`` ``(du, dv)`` of the steps on ``side`` (``geom.pixels_per_unit``
        maps a world displacement along ``T`` to pixels)."""


def tangent_from_screen_angle(q: Queries, phi: torch.Tensor) -> torch.Tensor:
    """Slice tangent whose screen direction has angle ``phi`` (radians, counter-clockwise from +u,
    image up = +v upward): ``(cos phi, sin phi, 0)`` made orthogonal to V (XeGTAO, HDRP, the GLSL seed)."""
    d = torch.stack((torch.cos(phi), torch.sin(phi), torch.zeros_like(phi)), -1)
    V = q.view
    return F.normalize(d - (d * V).sum(-1, keepdim=True) * V, dim=-1, eps=1e-12)


def tangent_from_view_azimuth(q: Queries, psi: torch.Tensor) -> torch.Tensor:
    """Slice tangent at azimuth ``psi`` around V: uniform ``psi`` gives slices uniform around the
    view vector, which makes the slice integral exact for off-centre pixels."""
    V = q.view
    # Orthonormal basis of the plane orthogonal to V, continuous away from V = +-Y (never in view).
    e1 = F.normalize(torch.cross(V.new_tensor([0.0, 1.0, 0.0]).expand_as(V), V, dim=-1), dim=-1, eps=1e-12)
    e2 = torch.cross(V, e1, dim=-1)
    return torch.cos(psi)[:, None] * e1 + torch.sin(psi)[:, None] * e2


class SlicePattern(SamplingPattern):
    """The default walk: ``slices`` directions evenly over the half circle (both sides marched),
    or over the full circle (one side each) with ``full_circle=True``; ``steps`` samples per side.

    Step ``j`` lies at ``min_step_px + (R_px - min_step_px) * ((j + xi) / steps) ** step_power``
    pixels, where ``R_px`` is ``radius`` (world units, scalar or ``(N,)``) projected at the pixel
    along the slice. With ``jitter``, the slice angle and ``xi`` come from interleaved gradient
    noise seeded by ``seed``; without, the slice angles start at 0 and ``xi = 0.5``.

    Args:
        slices, steps: counts (>= 1).
        radius: world-space radius, a float, a 0-d tensor (e.g. an ``nn.Parameter``) or ``(N,)``.
        step_power: 1 = linear, 2 = quadratic (denser near the pixel), etc.
        min_step_px: the first sample is at least this many pixels away.
        jitter, seed: per-pixel noise.
        fetch: ``"nearest"`` texel, or ``"bilinear"`` (perspective-correct: interpolates 1/depth, so
            planes are reproduced exactly); border: ``"clamp"`` to the edge or ``"drop"`` off-screen samples.
        azimuth: ``"view"`` spaces slices evenly around the view vector (exact slice integral);
            ``"screen"`` evenly in screen angle (XeGTAO/HDRP; biased off-centre).
        max_radius_px: optional clamp of the screen radius.
    """

    def __init__(self, slices: int, steps: int, radius, *, step_power: float = 1.0, min_step_px: float = 1.0,
                 jitter: bool = True, seed: int = 0, fetch: str = "nearest", border: str = "clamp",
                 full_circle: bool = False, azimuth: str = "view", max_radius_px: float | None = None) -> None:
        for name, value in (("slices", slices), ("steps", steps)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
        if fetch not in FETCH_MODES:
            raise ValueError(f"fetch: expected one of {FETCH_MODES}, got {fetch!r}")
        if border not in BORDER_MODES:
            raise ValueError(f"border: expected one of {BORDER_MODES}, got {border!r}")
        if azimuth not in ("view", "screen"):
            raise ValueError(f"azimuth: expected 'view' or 'screen', got {azimuth!r}")
        if not step_power > 0:
            raise ValueError(f"step_power: expected > 0, got {step_power}")
        self.num_slices, self.steps, self.radius = slices, steps, radius
        self.step_power, self.min_step_px = float(step_power), float(min_step_px)
        self.jitter, self.seed = jitter, int(seed)
        self.fetch, self.border, self.azimuth = fetch, border, azimuth
        self.full_circle = full_circle
        self.sides = (1,) if full_circle else (1, -1)
        self.max_radius_px = max_radius_px

    def _noise(self, q: Queries) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-pixel ``(N,)`` noise for the slice angle and for the step offset."""
        if not self.jitter:
            zero = torch.zeros_like(q.u)
            return zero, zero + 0.5
        a = interleaved_gradient_noise(q.u, q.v, self.seed).to(q.u.dtype)
        b = interleaved_gradient_noise(q.u + 37.0, q.v + 59.0, self.seed + 1).to(q.u.dtype)
        return a, b

    def slice_tangent(self, frame, q, s):
        span = 2 * math.pi if self.full_circle else math.pi
        angle = (s + self._noise(q)[0]) * (span / self.num_slices)
        if self.azimuth == "screen":
            return tangent_from_screen_angle(q, angle)
        return tangent_from_view_azimuth(q, angle)

    def radius_px(self, geom: "SliceGeometry") -> torch.Tensor:
        """``(N,)`` the world radius in pixels along the slice."""
        r = torch.as_tensor(self.radius, dtype=geom.pixels_per_unit.dtype, device=geom.pixels_per_unit.device)
        r = r * geom.pixels_per_unit.norm(dim=-1)
        return r if self.max_radius_px is None else r.clamp_max(self.max_radius_px)

    def step_offsets(self, q, geom, side):
        xi = self._noise(q)[1]
        unit = F.normalize(geom.pixels_per_unit, dim=-1, eps=1e-12) * side
        radius_px = self.radius_px(geom)
        span = (radius_px - self.min_step_px).clamp_min(0)
        j = torch.arange(self.steps, dtype=xi.dtype, device=xi.device)[:, None]
        fraction = ((j + xi) / self.steps) ** self.step_power  # (steps, N): all steps in one op
        return list(((self.min_step_px + span * fraction)[..., None] * unit).unbind(0))


# ---------------------------------------------------------------------------------------------
# The walk
# ---------------------------------------------------------------------------------------------
def slice_geometry(frame: Frame, q: Queries, pattern: SamplingPattern, s: int) -> SliceGeometry:
    T = pattern.slice_tangent(frame, q, s)
    V = q.view
    axis = torch.cross(T, V, dim=-1)
    n_proj = q.normal - axis * (q.normal * axis).sum(-1, keepdim=True)
    normal_length = n_proj.norm(dim=-1)
    normal_angle = torch.atan2((n_proj * T).sum(-1), (n_proj * V).sum(-1))
    # Derivative of the projection (u, v) = (fx x/d + cx, -fy y/d + cy), d = -z, along T.
    b = q.batch
    d = q.depth
    x, y = q.position[:, 0], q.position[:, 1]
    du = frame.fx[b] * (T[:, 0] + x * T[:, 2] / d) / d
    dv = -frame.fy[b] * (T[:, 1] + y * T[:, 2] / d) / d
    return SliceGeometry(s, T, axis, normal_angle, normal_length, torch.stack((du, dv), -1))


def _take(buf: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``buf[index]`` (rows of ``buf`` at an integer index of any shape), by ``index_select``
    (several times faster than advanced indexing on CPU)."""
    return buf.index_select(0, index.reshape(-1)).view(*index.shape, *buf.shape[1:])


def _bilerp(taps, fu: torch.Tensor, fv: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of the four taps ``(u0,v0), (u0+1,v0), (u0,v0+1), (u0+1,v0+1)``."""
    t0, t1, t2, t3 = taps
    return torch.lerp(torch.lerp(t0, t1, fu), torch.lerp(t2, t3, fu), fv)


class PerspectiveBilinearDepth(torch.autograd.Function):
    """Perspective-correct bilinear depth ``1 / sum_k w_k(fu, fv) / z_k`` ``(N,)`` at four taps.

    Interpolating ``1/depth`` (affine in screen space across a plane) reproduces planes exactly. The plain
    autograd path of the walk; the fused one (:class:`SampleAlong`) differentiates it by hand too.
    Inputs: ``safe_depth`` ``(P,)`` positive depths of the frame, ``index`` ``(N,4)`` taps into it,
    ``fu, fv`` ``(N,)`` fractional offsets in ``[0,1)``. A custom function because the walk fetches
    ``slices x sides x steps`` samples per pixel: plain autograd would keep the 64-bit tap indices, the
    gathered depths, the weights and their quotients for every sample (about 90 bytes each); this keeps
    32-bit indices, ``fu``, ``fv`` and the result (28 bytes) and gathers the depths again in backward.
    """

    @staticmethod
    def forward(ctx, safe_depth, index, fu, fv):
        depth = _bilerp(_take(safe_depth, index).reciprocal().unbind(-1), fu, fv).reciprocal()
        small = safe_depth.shape[0] < 2**31  # every tap indexes safe_depth
        ctx.save_for_backward(safe_depth, index.to(torch.int32) if small else index, fu, fv, depth)
        return depth

    @staticmethod
    def backward(ctx, grad):
        safe_depth, index, fu, fv, depth = ctx.saved_tensors
        inverse = _take(safe_depth, index).reciprocal()
        # d(1/z_k) = -(1/z_k)^2 dz_k
        g_inverse, grad_fu, grad_fv = _bilerp_depth_backward(inverse, fu, fv, depth, grad)
        grad_depth = None
        if ctx.needs_input_grad[0]:
            contrib = g_inverse.mul_(inverse.square_()).neg_()
            grad_depth = torch.zeros_like(safe_depth).index_add_(0, index.reshape(-1), contrib.view(-1))
        return grad_depth, None, grad_fu, grad_fv


@dataclass
class Footprint:
    """Where a sample reads the frame: the nearest texel (``index`` ``(N,)``) or four bilinear taps
    (``index`` ``(N,4)``, fractions ``fu``, ``fv``) at screen position ``(su, sv)`` ``(N,)``;
    ``batch`` ``(N,)`` is each row's image."""

    batch: torch.Tensor
    su: torch.Tensor
    sv: torch.Tensor
    index: torch.Tensor
    fu: torch.Tensor | None = None
    fv: torch.Tensor | None = None

    @staticmethod
    def at(frame: Frame, batch: torch.Tensor, su: torch.Tensor, sv: torch.Tensor, fetch: str) -> tuple["Footprint", torch.Tensor]:
        """The footprint of screen positions ``(su, sv)`` and whether each lies inside the frame."""
        B, H, W = frame.shape
        base = batch * (H * W)
        if fetch == "nearest":
            iu, iv = torch.floor(su + 0.5).long(), torch.floor(sv + 0.5).long()
            inside = (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
            index = iv.clamp(0, H - 1) * W + iu.clamp(0, W - 1)
            return Footprint(batch, su, sv, index if B == 1 else index + base), inside
        index, fu, fv = _bilinear_taps(frame, batch, su, sv)
        u0, v0 = torch.floor(su), torch.floor(sv)
        inside = (u0 >= 0) & (u0 + 1 < W) & (v0 >= 0) & (v0 + 1 < H)
        return Footprint(batch, su, sv, index, fu, fv), inside

    def map_rows(self, fn) -> "Footprint":
        """The footprint with ``fn`` applied to every per-row tensor."""
        return Footprint(fn(self.batch), fn(self.su), fn(self.sv), fn(self.index),
                         None if self.fu is None else fn(self.fu), None if self.fv is None else fn(self.fv))

    def valid(self, frame: Frame) -> torch.Tensor:
        v = _take(frame.valid, self.index)
        return v if self.fu is None else v.all(-1)

    def inputs(self, frame: Frame) -> tuple[torch.Tensor, ...]:
        """The differentiable tensors the position depends on (the frame's positions or depths, ``su``, ``sv``)."""
        if self.fu is None:
            return (frame.positions, self.su, self.sv)
        return (frame.inverse_depth, self.su, self.sv)

    def fusable(self, frame: Frame) -> bool:
        """Whether :class:`SampleAlong` can differentiate the position (camera intrinsics without gradient)."""
        return not any(t.requires_grad for t in (frame.fx, frame.fy, frame.cx, frame.cy))

    def position(self, frame: Frame) -> torch.Tensor:
        """``(N,3)`` view-space position: the texel's, or the perspective-correct bilinear depth
        unprojected at ``(su, sv)`` clamped to the frame."""
        if self.fu is None:
            return _take(frame.positions, self.index)
        if torch.is_grad_enabled():
            depth = PerspectiveBilinearDepth.apply(frame.safe_depth, self.index, self.fu, self.fv)
        else:  # the same values, from the frame's inverse depths
            depth = _bilerp(_take(frame.inverse_depth, self.index).unbind(-1), self.fu, self.fv).reciprocal()
        return _unproject(frame, self.batch, self.su, self.sv, depth)


def _bilinear_taps(frame: Frame, batch: torch.Tensor, su: torch.Tensor, sv: torch.Tensor):
    """Four taps ``(N,4)`` (``(u0,v0), (u0+1,v0), (u0,v0+1), (u0+1,v0+1)``, clamped to the frame) around
    screen positions ``(su, sv)`` ``(N,)`` and the fractions ``fu, fv`` ``(N,)``."""
    B, H, W = frame.shape
    u0, v0 = torch.floor(su.detach()), torch.floor(sv.detach())  # (floor has no gradient)
    fu, fv = su - u0, sv - v0
    # 32-bit index arithmetic (3x faster) where it cannot overflow; the clamp to [-1, size] first is exact.
    itype = torch.int32 if B * H * W < 2**31 - 1 else torch.int64
    u0, v0 = u0.clamp(-1, W).to(itype), v0.clamp(-1, H).to(itype)
    c0, c1 = u0.clamp(0, W - 1), u0.add_(1).clamp_(0, W - 1)
    r0, r1 = v0.clamp(0, H - 1).mul_(W), v0.add_(1).clamp_(0, H - 1).mul_(W)
    if B > 1:
        base = batch.to(itype) * (H * W)
        r0, r1 = r0.add_(base), r1.add_(base)
    return torch.stack((r0 + c0, r0 + c1, r1 + c0, r1 + c1), -1), fu, fv


def _unproject(frame: Frame, batch: torch.Tensor, su: torch.Tensor, sv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """``(N,3)`` view-space points at screen ``(su, sv)`` (clamped to the frame) and ``depth``."""
    B, H, W = frame.shape
    fx, fy, cx, cy = frame.intrinsics(batch)
    su_c, sv_c = su.clamp(0, W - 1), sv.clamp(0, H - 1)
    return torch.stack(((su_c - cx) / fx * depth, -(sv_c - cy) / fy * depth, -depth), -1)


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
            # delta_j = position_j - P where valid (m = 1), else -V; along_view = delta . V, along_tangent = side delta . T.
            # Rows are block-major (J, N); only rows with a gradient are worked on (see GradientRows).
            rows = GradientRows(J, N, g_view, g_tangent)
            g_view, g_tangent, su, sv, valid = map(rows.take, (g_view, g_tangent, su, sv, valid))
            m = valid.to(P.dtype)
            gv = g_view * m  # gradients reaching valid samples
            gt = g_tangent * (m if side > 0 else -m)
            a, b = rows.per_query(gv)[:, None], rows.per_query(gt)[:, None]  # (N,1)
            c = rows.per_query(g_view)[:, None] - a  # ... and invalid ones
            e = side * rows.per_query(g_tangent)[:, None] - b
            Vr, Tr = rows.per_row(V), rows.per_row(T)
            grads = [None] * 13
            if ctx.nearest:
                index = rows.take(index)
                px, py, pz = _take(source, index).unbind(-1)
                if ctx.needs_input_grad[7]:
                    g_pos = gv[:, None] * Vr + gt[:, None] * Tr
                    grads[7] = torch.zeros_like(source).index_add_(0, index, g_pos)
            else:
                B, H, W = frame.shape
                batch_rows = rows.per_row(batch) if B > 1 else batch  # (a single image needs no per-row batch)
                taps, fu, fv = _bilinear_taps(frame, batch_rows, su, sv)
                inverse = _take(source, taps)  # (rows,4) inverse depths
                depth = _bilerp(inverse.unbind(-1), fu, fv).reciprocal()
                fx, fy, cx, cy = frame.intrinsics(batch_rows)
                # position = depth * (xh, yh, -1) with xh = (clamp(su) - cx) / fx, yh = -(clamp(sv) - cy) / fy
                su_c, sv_c = su.clamp(0, W - 1), sv.clamp(0, H - 1)
                xh, yh = (su_c - cx) / fx, (sv_c - cy) / -fy
                g_x = torch.addcmul(gv * Vr[:, 0], gt, Tr[:, 0])
                g_y = torch.addcmul(gv * Vr[:, 1], gt, Tr[:, 1])
                g_z = torch.addcmul(gv * Vr[:, 2], gt, Tr[:, 2])
                g_inverse, g_fu, g_fv = _bilerp_depth_backward(inverse, fu, fv, depth, g_x * xh + g_y * yh - g_z)
                if ctx.needs_input_grad[7]:
                    grads[7] = torch.zeros_like(source).index_add_(0, taps.view(-1), g_inverse.view(-1))
                # fu = su - floor(su); clamp passes the gradient inside [0, W - 1]
                grads[8] = rows.put(torch.where(su_c == su, g_x * (depth / fx), 0.0).add_(g_fu))
                grads[9] = rows.put(torch.where(sv_c == sv, g_y * (depth / -fy), 0.0).add_(g_fv))
                px, py, pz = xh * depth, yh * depth, -depth
            # sums over the steps of the gradients times the position
            Sv = torch.stack([rows.per_query(gv * p) for p in (px, py, pz)], -1)  # (N,3)
            St = torch.stack([rows.per_query(gt * p) for p in (px, py, pz)], -1)
            if ctx.needs_input_grad[10]:
                grads[10] = -(a * V + b * T)
            if ctx.needs_input_grad[11]:
                grads[11] = Sv - a * P - 2 * c * V - e * T
            if ctx.needs_input_grad[12]:
                grads[12] = St - b * P - e * V
        return tuple(grads)


class GradientRows:
    """The rows ``(J * N,)`` (block-major over ``J`` steps of ``N`` queries) a backward works on: all of
    them, or, when at most half have a nonzero gradient in any of ``grads`` (samples that occlude
    nothing get none), only those. ``take``/``per_row`` select them, ``put`` scatters results back (zeros
    elsewhere), ``per_query`` sums them per query ``(N, ...)``."""

    def __init__(self, J: int, N: int, *grads: torch.Tensor) -> None:
        self.J, self.N = J, N
        nonzero = grads[0] != 0
        for g in grads[1:]:
            nonzero |= g != 0
        self.index = nonzero.nonzero()[:, 0] if 2 * int(nonzero.sum()) <= J * N else None
        self.query = None if self.index is None else self.index.remainder(N)

    def take(self, x: torch.Tensor) -> torch.Tensor:
        return x if self.index is None else _take(x, self.index)

    def put(self, x: torch.Tensor) -> torch.Tensor:
        if self.index is None:
            return x
        return x.new_zeros(self.J * self.N, *x.shape[1:]).index_copy_(0, self.index, x)

    def per_row(self, x: torch.Tensor) -> torch.Tensor:
        """Per-query ``x`` ``(N, ...)`` for each row."""
        return _repeat_rows(x, self.J) if self.index is None else _take(x, self.query)

    def per_query(self, x: torch.Tensor) -> torch.Tensor:
        """Sum of per-row ``x`` over each query's rows ``(N, ...)``."""
        if self.index is None:
            return x.view(self.J, self.N, *x.shape[1:]).sum(0)
        return x.new_zeros(self.N, *x.shape[1:]).index_add_(0, self.query, x)


def _bilerp_depth_backward(inverse: torch.Tensor, fu: torch.Tensor, fv: torch.Tensor, depth: torch.Tensor,
                           grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients of ``depth = 1 / bilerp(inverse, fu, fv)`` ``(N,)`` to the tap inverse depths ``(N,4)``,
    ``fu`` and ``fv`` given ``grad`` ``(N,)`` of ``depth``."""
    g = -grad * depth.square()  # d depth = -depth^2 dS, S the interpolated inverse depth
    i0, i1, i2, i3 = inverse.unbind(-1)
    lower, upper = g * fv, g * (1 - fv)  # S = (1 - fv) top + fv bottom
    right_up, right_low = upper * fu, lower * fu
    g_inverse = torch.stack((upper - right_up, right_up, lower - right_low, right_low), -1)
    g_fu = torch.lerp(i1 - i0, i3 - i2, fv).mul_(g)
    g_fv = (torch.lerp(i2, i3, fu) - torch.lerp(i0, i1, fu)).mul_(g)
    return g_inverse, g_fu, g_fv


def fetch_sample(frame: Frame, q: Queries, geom: SliceGeometry, pattern: SamplingPattern,
                 side: int, step: int | None, offset: torch.Tensor, steps: int = 1,
                 base: tuple[Queries, SliceGeometry] | None = None) -> Sample:
    """The sample at pixel ``offset`` ``(N,2)`` from each query pixel, on ``side`` (``steps`` > 1: the
    rows of ``q``, ``geom`` and ``offset`` hold that many steps, block-major, and ``base`` gives the
    queries and geometry of one step)."""
    footprint, inside = Footprint.at(frame, q.batch, q.u + offset[:, 0], q.v + offset[:, 1], pattern.fetch)
    valid = footprint.valid(frame)
    if pattern.border == "drop":
        valid = valid & inside
    return Sample(frame, geom, side, step, q, footprint, valid, offset, steps, base)


def _walk(frame: Frame, q: Queries, pattern: SamplingPattern, method: SliceAccumulator) -> dict[str, torch.Tensor]:
    sums: dict[str, torch.Tensor] = {}
    repeated: dict[int, Queries] = {}  # the queries stacked per step count, built once per walk
    for s in range(pattern.num_slices):
        geom = slice_geometry(frame, q, pattern, s)
        state = method.begin_slice(q, geom)
        for side in pattern.sides:
            offsets = pattern.step_offsets(q, geom, side)
            if getattr(method, "batch_steps", False):
                if offsets:
                    J = len(offsets)
                    if J not in repeated:
                        repeated[J] = q.repeat(J)
                    qj, gj = repeated[J], geom.repeat(J)
                    sample = fetch_sample(frame, qj, gj, pattern, side, None, torch.cat(offsets, 0), J, (q, geom))
                    state = method.step(state, qj, gj, sample)
                continue
            for j, offset in enumerate(offsets):
                state = method.step(state, q, geom, fetch_sample(frame, q, geom, pattern, side, j, offset))
        for name, value in method.end_slice(state, q, geom).items():
            sums[name] = value if name not in sums else sums[name] + value
    return method.finish(sums, q, pattern.num_slices)


def march(
    frame: Frame,
    pattern: SamplingPattern,
    method: SliceAccumulator,
    *,
    chunk_size: int | None = None,
    recompute: bool = False,
) -> dict[str, torch.Tensor]:
    """Walk every query pixel of ``frame`` and return ``method``'s outputs ``{name: (N, C)}``.

    Args:
        chunk_size: process at most this many query pixels at a time (bounds memory).
        recompute: with autograd, keep only each chunk's inputs and outputs and recompute the walk
            in backward (activation checkpointing); combine with ``chunk_size`` to bound the memory
            of forward+backward by one chunk.
    """
    q = frame.queries
    n = len(q)
    size = max(n, 1) if chunk_size is None else max(1, int(chunk_size))
    outputs: list[dict[str, torch.Tensor]] = []
    # An empty query list (an all-background frame) still walks once, on empty tensors, so that
    # outputs stay connected to the parameters (with zero gradient).
    for start in range(0, max(n, 1), size):
        qc = q if size >= n else q.subset(slice(start, start + size))
        if recompute and torch.is_grad_enabled():
            outputs.append(checkpoint(_walk, frame, qc, pattern, method, use_reentrant=False))
        else:
            outputs.append(_walk(frame, qc, pattern, method))
    if len(outputs) == 1:
        return outputs[0]
    return {k: torch.cat([o[k] for o in outputs], 0) for k in outputs[0]}
