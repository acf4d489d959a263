"""Where the walk goes: slice tangents, per-pixel noise, and the pixel offsets of the steps.

:class:`SlicePattern` is the default walk of the horizon family (GTAO's Algorithm 1: ``slices``
directions, ``steps`` samples per side, both rotated per pixel by noise). Other methods subclass it
or :class:`~torch_ao.walk.protocol.SamplingPattern` to place their samples as their shader does.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from ..checks import check_choice, check_float, check_int
from ..ops import safe_atan2
from .frame import Queries
from .protocol import SamplingPattern

__all__ = ["SlicePattern", "FETCH_MODES", "BORDER_MODES", "AZIMUTHS", "NOISES", "interleaved_gradient_noise",
           "hilbert_index", "hilbert_r2_noise", "SLICE_SAMPLINGS", "view_basis", "unoccluded_slice_integral",
           "projected_normal_azimuths", "staggered_offset",
           "tangent_from_screen_angle", "tangent_from_view_azimuth", "radius_px", "step_direction"]

#: Depth fetch: the nearest texel, perspective-correct bilinear (interpolates 1/depth), or bilinear inside
#: a surface and the nearest texel across a depth edge (``"edge_aware"``: no skirts; see walk/fetch.py).
FETCH_MODES = ("nearest", "bilinear", "edge_aware")
#: Samples outside the image: clamped to the edge texel, or dropped (they occlude nothing).
BORDER_MODES = ("clamp", "drop")
#: Slice spacing: evenly around the view vector, or evenly in screen angle.
AZIMUTHS = ("view", "screen")
#: Per-pixel noise of the slice rotation and the step offset: Jimenez's interleaved gradient noise, or
#: XeGTAO's R2 low-discrepancy sequence indexed along a 64x64 Hilbert curve (``"hilbert_r2"``).
NOISES = ("ign", "hilbert_r2")
#: How the slice directions are drawn: evenly around V (``"uniform"``), or by the density of GTAO's unoccluded
#: slice integral, the cosine-weighted projected normal (``"projected_normal"``, each slice weighted by
#: ``1 / (pi p)`` so that the estimate stays unbiased).
SLICE_SAMPLINGS = ("uniform", "projected_normal")
#: Bins over the half circle of the tabulated projected-normal density (a piecewise-constant density: its
#: inverse CDF and its weights are exact for it).
PROJECTED_NORMAL_BINS = 32
#: Side of the Hilbert tile of ``"hilbert_r2"`` (XeGTAO's XE_HILBERT_WIDTH) and the index shift of one seed.
HILBERT_WIDTH, HILBERT_SEED_SHIFT = 64, 288
#: The R2 sequence's generators ``1 / g``, ``1 / g**2`` (g the plastic number, g**3 = g + 1).
R2_ALPHA = (0.75487766624669276005, 0.5698402909980532659114)


def interleaved_gradient_noise(u: torch.Tensor, v: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Jimenez's interleaved gradient noise in ``[0, 1)`` at integer pixel coordinates.

    ``frac(52.9829189 * frac(0.06711056 * x + 0.00583715 * y))``; ``seed`` shifts the pattern
    (by 5.588238 pixels per unit, the per-frame offset of the original), so every seed is a new,
    reproducible pattern.
    """
    x = u.double() + 5.588238 * seed
    y = v.double() + 5.588238 * seed
    return torch.frac(52.9829189 * torch.frac(0.06711056 * x + 0.00583715 * y))


def hilbert_index(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Index ``(N,)`` int64 in ``[0, 4096)`` of integer pixel ``(u, v)`` (taken modulo 64) along the 64x64
    Hilbert curve (XeGTAO's ``HilbertIndex``): pixels close on the curve are close on screen."""
    x = u.long() % HILBERT_WIDTH
    y = v.long() % HILBERT_WIDTH
    index = torch.zeros_like(x)
    level = HILBERT_WIDTH // 2
    while level > 0:
        rx, ry = (x & level) > 0, (y & level) > 0
        index = index + level * level * ((3 * rx.long()) ^ ry.long())
        flip = ~ry & rx
        x, y = torch.where(flip, HILBERT_WIDTH - 1 - x, x), torch.where(flip, HILBERT_WIDTH - 1 - y, y)
        x, y = torch.where(ry, x, y), torch.where(ry, y, x)  # swap where ry == 0
        level //= 2
    return index


def hilbert_r2_noise(u: torch.Tensor, v: torch.Tensor, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """XeGTAO's spatio-temporal noise: two values in ``[0, 1)`` (float64) per integer pixel, the R2
    sequence ``frac(0.5 + i * (1/g, 1/g^2))`` at ``i`` = the pixel's :func:`hilbert_index` ``+ 288 * seed``.

    Along the Hilbert curve consecutive pixels take consecutive points of a low-discrepancy sequence, so
    any compact block of pixels (a denoiser's window) holds well-spread pairs, and both values are
    decorrelated from each other (unlike one hash shifted)."""
    i = (hilbert_index(u, v) + HILBERT_SEED_SHIFT * int(seed)).double()
    return tuple(torch.frac(0.5 + i * alpha) for alpha in R2_ALPHA)


def tangent_from_screen_angle(q: Queries, phi: torch.Tensor) -> torch.Tensor:
    """Slice tangent whose screen direction has angle ``phi`` (radians, counter-clockwise from +u,
    image up = +v upward): ``(cos phi, sin phi, 0)`` made orthogonal to V (XeGTAO, HDRP, the GLSL seed)."""
    d = torch.stack((torch.cos(phi), torch.sin(phi), torch.zeros_like(phi)), -1)
    V = q.view
    return F.normalize(d - (d * V).sum(-1, keepdim=True) * V, dim=-1, eps=1e-12)


def view_basis(q: Queries) -> tuple[torch.Tensor, torch.Tensor]:
    """``(e1, e2)`` ``(N,3)``: the orthonormal basis of the plane orthogonal to V in which view azimuths are
    measured (``e1 = normalize(+Y x V)``, ``e2 = V x e1``; continuous away from V = +-Y, never in view)."""
    V = q.view
    e1 = F.normalize(torch.cross(V.new_tensor([0.0, 1.0, 0.0]).expand_as(V), V, dim=-1), dim=-1, eps=1e-12)
    return e1, torch.cross(V, e1, dim=-1)


def tangent_from_view_azimuth(q: Queries, psi: torch.Tensor) -> torch.Tensor:
    """Slice tangent at azimuth ``psi`` around V: uniform ``psi`` gives slices uniform around the
    view vector, which makes the slice integral exact for off-centre pixels."""
    e1, e2 = view_basis(q)
    return torch.cos(psi)[:, None] * e1 + torch.sin(psi)[:, None] * e2


def unoccluded_slice_integral(normal_view: torch.Tensor, normal_tangent: torch.Tensor) -> torch.Tensor:
    """GTAO's unoccluded slice integral ``|n_p| (cos g + g sin g)`` ``(...)`` (``|n_p|`` times
    :func:`~torch_ao.ops.arc_integral` from ``g - pi/2`` to ``g + pi/2``) from the normal's components
    along V and along the slice tangent: ``n.V + g n.T`` with ``g = atan2(n.T, n.V)``. Its mean over
    azimuths uniform around V is 1 (the cosine-weighted hemisphere's measure over pi)."""
    return normal_view + safe_atan2(normal_tangent, normal_view) * normal_tangent


def projected_normal_azimuths(q: Queries, u: torch.Tensor, bins: int = PROJECTED_NORMAL_BINS
                              ) -> tuple[torch.Tensor, torch.Tensor]:
    """View azimuths ``psi`` ``(N,)`` in ``[0, pi)`` at the quantiles ``u`` ``(N,)`` in ``[0, 1)`` of the
    density ``p`` proportional to :func:`unoccluded_slice_integral` (tabulated in ``bins`` equal bins: a
    piecewise-constant density), and each azimuth's estimator weight ``1 / (pi p(psi))`` ``(N,)``.

    Stratified ``u`` (``(s + xi) / slices``) give slices where the cosine-weighted hemisphere of the
    normal has its measure (GT-VBAO's projected-normal slice sampling); a walk that weights each slice's
    contribution by ``weight`` estimates the same integral as uniform slices."""
    e1, e2 = view_basis(q)
    n = q.normal
    nv, n1, n2 = (n * q.view).sum(-1, keepdim=True), (n * e1).sum(-1, keepdim=True), (n * e2).sum(-1, keepdim=True)
    width = math.pi / bins
    centres = (torch.arange(bins, dtype=n.dtype, device=n.device) + 0.5) * width
    # (a floor keeps p > 0 everywhere: a slice the normal's hemisphere hardly sees can still be drawn)
    w = unoccluded_slice_integral(nv, n1 * torch.cos(centres) + n2 * torch.sin(centres)).clamp_min(1e-4)  # (N,K)
    cdf = torch.cumsum(w, -1)
    target = u.to(n.dtype)[:, None] * cdf[:, -1:]
    k = torch.searchsorted(cdf.detach().contiguous(), target.detach().contiguous(), right=True).clamp_max(bins - 1)
    wk = w.gather(-1, k)
    before = cdf.gather(-1, k) - wk
    psi = (k.to(n.dtype) + ((target - before) / wk).clamp(0.0, 1.0)) * width
    weight = cdf[:, -1:] / (bins * wk)
    return psi[:, 0], weight[:, 0]


class SlicePattern(SamplingPattern):
    """The default walk: ``slices`` directions evenly over the half circle (both sides marched),
    or over the full circle (one side each) with ``full_circle=True``; ``steps`` samples per side.

    Step ``j`` lies at ``min_step_px + (R_px - min_step_px) * ((j + xi) / steps) ** step_power``
    pixels, where ``R_px`` is ``radius`` (world units, scalar or ``(N,)``) projected at the pixel
    along the slice. With ``jitter``, the slice angle and ``xi`` come from per-pixel ``noise`` seeded by
    ``seed``; without, the slice angles start at 0 and ``xi = 0.5``.

    Args:
        slices, steps: counts (>= 1).
        radius: world-space radius, a float, a 0-d tensor (e.g. an ``nn.Parameter``) or ``(N,)``.
        step_power: 1 = linear, 2 = quadratic (denser near the pixel), etc.
        min_step_px: the first sample is at least this many pixels away.
        slice_sampling: ``"uniform"`` around V, or ``"projected_normal"`` (:func:`projected_normal_azimuths`:
            the slices at quantiles of the projected normal's density, each weighted by ``1 / (pi p)``;
            needs ``azimuth="view"`` and a half circle).
        stagger: shift the step offset of each half-slice by ``1 / (2 slices)`` of a step
            (:func:`staggered_offset`): the slices of a pixel sample interleaved distances, not the same ones.
        jitter, seed: per-pixel noise; noise: its kind (:data:`NOISES`): ``"ign"`` interleaved gradient
            noise, ``"hilbert_r2"`` the R2 sequence along a Hilbert curve (:func:`hilbert_r2_noise`).
        fetch: ``"nearest"`` texel, ``"bilinear"`` (perspective-correct: interpolates 1/depth, so
            planes are reproduced exactly), or ``"edge_aware"`` (bilinear inside a surface, the nearest
            texel across a depth edge; :mod:`~torch_ao.walk.fetch`); border: ``"clamp"`` to the edge or ``"drop"`` off-screen samples.
        azimuth: ``"view"`` spaces slices evenly around the view vector (exact slice integral);
            ``"screen"`` evenly in screen angle (XeGTAO/HDRP; biased off-centre).
        max_radius_px: optional clamp of the screen radius.
    """

    def __init__(self, slices: int, steps: int, radius, *, step_power: float = 1.0, min_step_px: float = 1.0,
                 jitter: bool = True, seed: int = 0, fetch: str = "nearest", border: str = "clamp",
                 full_circle: bool = False, azimuth: str = "view", max_radius_px: float | None = None,
                 noise: str = "ign", slice_sampling: str = "uniform", stagger: bool = False) -> None:
        check_int("slices", slices, 1)
        check_int("steps", steps, 1)
        check_choice("fetch", fetch, FETCH_MODES)
        check_choice("border", border, BORDER_MODES)
        check_choice("azimuth", azimuth, AZIMUTHS)
        check_choice("noise", noise, NOISES)
        check_choice("slice_sampling", slice_sampling, SLICE_SAMPLINGS)
        if slice_sampling != "uniform" and (azimuth != "view" or full_circle):
            raise ValueError(f"slice_sampling: {slice_sampling!r} draws slices around the view vector over a half "
                             f"circle: it needs azimuth='view' and a half circle (got azimuth={azimuth!r}"
                             f"{', a full circle' if full_circle else ''})")
        self.slice_sampling, self.stagger = slice_sampling, bool(stagger)
        check_float("step_power", step_power, 0.0, open_minimum=True)
        self.num_slices, self.steps, self.radius = slices, steps, radius
        self.step_power, self.min_step_px = float(step_power), float(min_step_px)
        self.jitter, self.seed, self.noise = jitter, int(seed), noise
        self.fetch, self.border, self.azimuth = fetch, border, azimuth
        self.full_circle = full_circle
        self.sides = (1,) if full_circle else (1, -1)
        self.max_radius_px = max_radius_px

    def _noise(self, q: Queries) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-pixel ``(N,)`` noise for the slice angle and for the step offset."""
        if not self.jitter:
            zero = torch.zeros_like(q.u)
            return zero, zero + 0.5
        if self.noise == "hilbert_r2":
            return tuple(x.to(q.u.dtype) for x in hilbert_r2_noise(q.u, q.v, self.seed))
        a = interleaved_gradient_noise(q.u, q.v, self.seed).to(q.u.dtype)
        b = interleaved_gradient_noise(q.u + 37.0, q.v + 59.0, self.seed + 1).to(q.u.dtype)
        return a, b

    def slice_direction(self, frame, q, s):
        if self.slice_sampling == "projected_normal":
            psi, weight = projected_normal_azimuths(q, (s + self._noise(q)[0]) / self.num_slices)
            return tangent_from_view_azimuth(q, psi), weight
        return self.slice_tangent(frame, q, s), None

    def slice_tangent(self, frame, q, s):
        span = 2 * math.pi if self.full_circle else math.pi
        angle = (s + self._noise(q)[0]) * (span / self.num_slices)
        if self.azimuth == "screen":
            return tangent_from_screen_angle(q, angle)
        return tangent_from_view_azimuth(q, angle)

    def radius_px(self, geom) -> torch.Tensor:
        """``(N,)`` the world radius in pixels along the slice, clamped to ``max_radius_px``."""
        r = radius_px(self.radius, geom)
        return r if self.max_radius_px is None else r.clamp_max(self.max_radius_px)

    def step_noise(self, q, geom, side) -> torch.Tensor:
        """``(N,)`` the step offset ``xi`` of slice ``geom.index`` on ``side`` (staggered with ``stagger``)."""
        xi = self._noise(q)[1]
        return staggered_offset(xi, geom.index, side, self.num_slices) if self.stagger else xi

    def step_offsets(self, q, geom, side):
        xi = self.step_noise(q, geom, side)
        unit = step_direction(geom, side)
        radius_px = self.radius_px(geom)
        span = (radius_px - self.min_step_px).clamp_min(0)
        j = torch.arange(self.steps, dtype=xi.dtype, device=xi.device)[:, None]
        fraction = ((j + xi) / self.steps) ** self.step_power  # (steps, N): all steps in one op
        return list(((self.min_step_px + span * fraction)[..., None] * unit).unbind(0))


def staggered_offset(xi: torch.Tensor, s: int, side: int, slices: int) -> torch.Tensor:
    """The step offset ``xi`` ``(N,)`` of slice ``s`` on ``side``: ``frac(xi + (s + [side < 0] / 2) / slices)``,
    so that the ``2 * slices`` half-slices of a pixel sample ``2 * slices * steps`` distinct distances (each
    offset still uniform where ``xi`` is)."""
    return torch.frac(xi + (s + (0.5 if side < 0 else 0.0)) / slices)


def radius_px(radius, geom) -> torch.Tensor:
    """``(N,)`` a world-space ``radius`` (float, 0-d or ``(N,)`` tensor) in pixels along the slice of
    ``geom``, projected at each query pixel's depth."""
    ppu = geom.pixels_per_unit
    return torch.as_tensor(radius, dtype=ppu.dtype, device=ppu.device) * ppu.norm(dim=-1)


def step_direction(geom, side: int) -> torch.Tensor:
    """``(N,2)`` unit screen direction ``(du, dv)`` of the walk on ``side`` of the slice of ``geom``."""
    return F.normalize(geom.pixels_per_unit, dim=-1, eps=1e-12) * side
