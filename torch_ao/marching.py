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

    def subset(self, sl: slice) -> "Queries":
        return Queries(
            self.index[sl], self.batch[sl], self.u[sl], self.v[sl], self.position[sl], self.normal[sl],
            self.view[sl], self.depth[sl], {k: x[sl] for k, x in self.values.items()},
        )

    def repeat(self, times: int) -> "Queries":
        """The rows repeated ``times`` times, block-major: row ``j * N + i`` is query ``i``."""
        if times == 1:
            return self
        r = functools.partial(_repeat_rows, times=times)
        return Queries(r(self.index), r(self.batch), r(self.u), r(self.v), r(self.position), r(self.normal),
                       r(self.view), r(self.depth), {k: r(x) for k, x in self.values.items()})


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
    """``(B,C,H,W)`` -> ``(B*H*W, C)``."""
    B, C, H, W = x.shape
    return x.permute(0, 2, 3, 1).reshape(B * H * W, C)


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

    def repeat(self, times: int) -> "SliceGeometry":
        """The rows repeated ``times`` times, block-major (as :meth:`Queries.repeat`)."""
        if times == 1:
            return self
        r = functools.partial(_repeat_rows, times=times)
        return SliceGeometry(self.index, r(self.tangent), r(self.axis), r(self.normal_angle), r(self.normal_length),
                             r(self.pixels_per_unit))


class Sample:
    """One step of the walk on one side of a slice, for every query pixel (``N`` rows).

    With an accumulator that sets ``batch_steps = True``, one ``Sample`` holds all ``steps`` steps of
    a side at once: its rows (and those of the queries and geometry passed with it) are block-major,
    row ``j * N + i`` being step ``j`` of query ``i``; ``step`` is then ``None``.

    Attributes:
        side: ``+1`` or ``-1``; step: the step number; steps: how many steps the rows hold (1 or all).
        position: ``(N,3)`` sample's view-space position; ``delta = position - P``.
        valid: ``(N,)`` bool; invalid samples (background, dropped at the border, or on the centre
            texel) have a safe ``delta`` pointing away from the camera, so they never occlude.
        along_view, along_tangent: ``delta . V`` and ``delta . (side T)``, ``(N,)``.
        distance: ``|delta|`` ``(N,)``; distance_px: the screen distance in pixels ``(N,)``.
    """

    def __init__(self, frame: Frame, geom: SliceGeometry, side: int, step: int, queries: Queries,
                 index: torch.Tensor, fraction: tuple[torch.Tensor, torch.Tensor] | None, position: torch.Tensor,
                 valid: torch.Tensor, offset: torch.Tensor, steps: int = 1) -> None:
        self.side, self.step, self.steps = side, step, steps
        # fraction: the bilinear fetch's (fu, fv); its tap weights are only built when a buffer is gathered.
        self._frame, self._index, self._fraction, self._view = frame, index, fraction, queries.view
        delta = position - queries.position
        # A sample on the centre texel (or a degenerate one) would give 0/0 angles: drop it.
        valid = valid & (delta.detach().square().sum(-1) > 1e-20 * queries.depth.detach().square())
        away = -queries.view  # a safe offset that looks away from the camera
        self.valid = valid
        self.position = torch.where(valid[:, None], position, queries.position + away)
        self.delta = torch.where(valid[:, None], delta, away)
        self.along_view = (self.delta * queries.view).sum(-1)
        self.along_tangent = side * (self.delta * geom.tangent).sum(-1)
        self._offset = offset

    # Computed on first use only: most methods need neither, and autograd would keep their inputs.
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
        d = self.delta - (off[:, None] if off.dim() == 1 else off) * self._view
        return (d * self._view).sum(-1) / d.norm(dim=-1).clamp_min(1e-30)

    def gather(self, name: str) -> torch.Tensor:
        """Value ``(N, C)`` of the frame buffer ``name`` at this sample (nearest or bilinear,
        as the walk fetches depth; integer buffers are always nearest)."""
        buf = self._frame.buffers[name]
        if self._fraction is None or not buf.is_floating_point():
            idx = self._index if self._fraction is None else self._index[:, 0]
            return buf[idx]
        taps = buf[self._index.reshape(-1)].reshape(*self._index.shape, buf.shape[1])  # (N,4,C)
        return (taps * _bilinear_weights(*self._fraction)[..., None].to(buf.dtype)).sum(1)


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
        return [(self.min_step_px + span * ((j + xi) / self.steps) ** self.step_power)[:, None] * unit
                for j in range(self.steps)]


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


def _bilinear_weights(fu: torch.Tensor, fv: torch.Tensor) -> torch.Tensor:
    """``(N,4)`` weights of the taps ``(u0,v0), (u0+1,v0), (u0,v0+1), (u0+1,v0+1)``."""
    return torch.stack(((1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv), -1)


class PerspectiveBilinearDepth(torch.autograd.Function):
    """Perspective-correct bilinear depth ``1 / sum_k w_k(fu, fv) / z_k`` ``(N,)`` at four taps.

    Interpolating ``1/depth`` (affine in screen space across a plane) reproduces planes exactly.
    Inputs: ``safe_depth`` ``(P,)`` positive depths of the frame, ``index`` ``(N,4)`` taps into it,
    ``fu, fv`` ``(N,)`` fractional offsets in ``[0,1)``. A custom function because the walk fetches
    ``slices x sides x steps`` samples per pixel: plain autograd would keep the 64-bit tap indices, the
    gathered depths, the weights and their quotients for every sample (about 90 bytes each); this keeps
    32-bit indices, ``fu``, ``fv`` and the result (28 bytes) and gathers the depths again in backward.
    """

    @staticmethod
    def forward(ctx, safe_depth, index, fu, fv):
        inv = safe_depth[index].reciprocal()
        depth = (_bilinear_weights(fu, fv) * inv).sum(-1).reciprocal()
        small = safe_depth.shape[0] < 2**31  # every tap indexes safe_depth
        ctx.save_for_backward(safe_depth, index.to(torch.int32) if small else index, fu, fv, depth)
        return depth

    @staticmethod
    def backward(ctx, grad):
        safe_depth, index, fu, fv, depth = ctx.saved_tensors
        index = index.long()
        inv = safe_depth[index].reciprocal()  # (N,4)
        # depth = 1 / S with S = sum_k w_k / z_k: d depth = -depth^2 dS.
        g = grad * depth.square()
        grad_depth = grad_fu = grad_fv = None
        if ctx.needs_input_grad[0]:
            contrib = (g[:, None] * _bilinear_weights(fu, fv) * inv.square()).reshape(-1)
            grad_depth = torch.zeros_like(safe_depth).index_add_(0, index.reshape(-1), contrib)
        if ctx.needs_input_grad[2]:
            grad_fu = -g * ((1 - fv) * (inv[:, 1] - inv[:, 0]) + fv * (inv[:, 3] - inv[:, 2]))
        if ctx.needs_input_grad[3]:
            grad_fv = -g * ((1 - fu) * (inv[:, 2] - inv[:, 0]) + fu * (inv[:, 3] - inv[:, 1]))
        return grad_depth, None, grad_fu, grad_fv


def fetch_sample(frame: Frame, q: Queries, geom: SliceGeometry, pattern: SamplingPattern,
                 side: int, step: int | None, offset: torch.Tensor, steps: int = 1) -> Sample:
    """The sample at pixel ``offset`` ``(N,2)`` from each query pixel, on ``side`` (``steps`` > 1: the
    rows of ``q``, ``geom`` and ``offset`` hold that many steps, block-major)."""
    B, H, W = frame.shape
    su, sv = q.u + offset[:, 0], q.v + offset[:, 1]
    base = q.batch * (H * W)
    if pattern.fetch == "nearest":
        iu, iv = torch.floor(su + 0.5).long(), torch.floor(sv + 0.5).long()
        inside = (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
        iu, iv = iu.clamp(0, W - 1), iv.clamp(0, H - 1)
        index = base + iv * W + iu
        valid = frame.valid[index]
        position = frame.positions[index]
        fraction = None
    else:
        u0, v0 = torch.floor(su), torch.floor(sv)
        fu, fv = su - u0, sv - v0
        u0, v0 = u0.long(), v0.long()
        inside = (u0 >= 0) & (u0 + 1 < W) & (v0 >= 0) & (v0 + 1 < H)
        cols = torch.stack((u0, u0 + 1, u0, u0 + 1), -1).clamp(0, W - 1)
        rows = torch.stack((v0, v0, v0 + 1, v0 + 1), -1).clamp(0, H - 1)
        index = base[:, None] + rows * W + cols  # (N,4)
        fraction = (fu, fv)
        valid = frame.valid[index].all(-1)
        depth = PerspectiveBilinearDepth.apply(frame.safe_depth, index, fu, fv)
        b = q.batch
        su_c = su.clamp(0, W - 1)
        sv_c = sv.clamp(0, H - 1)
        position = torch.stack(((su_c - frame.cx[b]) / frame.fx[b] * depth,
                                -(sv_c - frame.cy[b]) / frame.fy[b] * depth, -depth), -1)
    if pattern.border == "drop":
        valid = valid & inside
    return Sample(frame, geom, side, step, q, index, fraction, position, valid, offset, steps)


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
                    sample = fetch_sample(frame, qj, gj, pattern, side, None, torch.cat(offsets, 0), J)
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
