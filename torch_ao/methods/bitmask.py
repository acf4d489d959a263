"""Visibility-bitmask ambient occlusion (Therrien et al. 2023) and its indirect-light extension (SSILVB).

Each slice's hemisphere (around the projected normal) is split into 32 sectors. Every sample
occludes the sectors between its *front* direction and its *back* direction (the sample pushed
``thickness`` away from the camera), so light passes behind thin surfaces. The union over a slice's
steps gives its occluded sectors; visibility is the share of unoccluded sectors, averaged over slices.
See :mod:`torch_ao.sectors` for the masks and their soft versions, :mod:`torch_ao.thickness` for the
thickness models, :mod:`.bitmask_common` for the slice / sample / finish loop the variants share.

Variants (``variant=``), one accumulator each:

``"default"``
    Slices evenly over the half circle around the view vector (or in screen angle with
    ``azimuth="screen"``), both sides marched into one 32-sector mask per slice, exact in-plane
    angles (``atan2`` in the slice plane), signed slice coordinate ``side * theta`` mapped by
    ``(side * theta - gamma + pi/2) / pi`` (``gamma`` = projected-normal angle). Visibility in [0, 1].
``"exact"``
    ``"default"``'s geometry made to converge (see docs/bitmask.md, "Convergence"): the exact measure
    of the union of the steps' intervals instead of 32 sectors (``union="exact"``), each occluder
    segment clipped to the radius (``clip_to_radius=True``), the back point along the sample's own
    camera ray (``thickness_direction="depth"``), the steps over the sphere's screen extent
    (``sample_extent="sphere"``) from a quarter pixel out (``min_step_px=0.25``), cosine weighting,
    depth read by the skirt-free ``fetch="edge_aware"``. Visibility only.
``"hdrp"``
    The bitmask blog's HLSL on HDRP's GTAO: both sides into one bitfield; the 3D cosines
    ``dot(normalize(delta - t V), V)`` through the polynomial ``fast_acos``;
    ``N = -sign(dot(projN, T)) * fast_acos(cosN)``; ``saturate((side * -angle - N + pi/2) / pi)`` and the
    ``yx`` swap on the positive side. (HDRP's sample clamp to ``[2, size - 2]`` pixels and its
    half-resolution depth mips are not reproduced; use ``border=``/``fetch=``.)
``"ssilvb_glsl"``
    The SSILVB GLSL article's shader as written (see :mod:`torch_ao.methods.bitmask_glsl` for its quirks).

Options (:data:`OPTIONS` describes each: unit, range, default): ``mode`` ``"hard" | "soft" |
"straight_through"`` with temperature ``tau`` (sector units); ``rounding`` ``"ceil" | "round" | "floor"``;
``weighting`` ``"uniform"`` (the paper: every sector 1/32) or ``"cosine"`` (each sector weighted by its
exact share of the cosine-weighted slice ``|n_p| int cos(theta - gamma) |sin theta| dtheta``, normalised
so an unoccluded pixel gives exactly 1; converges to cosine-weighted ray-traced AO); ``union``,
``clip_to_radius``, ``thickness_direction`` (the ``"exact"`` variant's improvements, each usable on its
own with ``"default"``). ``thickness``: a float, a ``(K,)`` per-object table, a ``(B,1,H,W)`` map, or any
:class:`~torch_ao.thickness.Thickness` model (linear in depth, a back-face layer...); ``thickness_growth``
multiplies it by ``1 + growth * |sample - pixel|``.

Outputs beyond visibility are computed only when asked (``indirect=True``, ``bent_normals=True``,
``ambient=``): an AO-only call never gathers the light or normal buffers.

* ``indirect`` ``(B,3,H,W)``: for every step, the *newly* occluded sectors times the sample's light
  ``L``, the sender's ``saturate(N_s . -l)`` and, with uniform weighting, the receiver's
  ``saturate(N . l)`` (the bitmask blog and the SSILVB GLSL article; ``l`` = unit direction to the
  sample). With cosine weighting the receiver's cosine is already in the sector weights, so it is not
  applied twice.
* ``ambient`` ``(B,3,H,W)``: the bitmask blog's ``ComputeAmbient``: unoccluded sectors, grouped into
  ``ambient_directions`` sub-regions, times the ambient light from each sub-region's centre direction
  (a constant RGB colour, or a callable ``(M,3)`` view-space directions -> ``(M,3)``).
* ``bent_normal`` ``(B,3,H,W)``: the normalised weighted mean direction of the unoccluded sectors.
"""
from __future__ import annotations

import math

import torch

from ..gbuffer import GBuffer
from dataclasses import replace

from ..intervals import THICKNESS_DIRECTIONS, back_point, clip_to_sphere, sphere_stretch
from ..ops import safe_fast_acos as _safe_fast_acos
from ..options import Option, options_by_name
from ..sectors import MODES, ROUNDINGS, SECTORS, sector_interval
from ..thickness import BoundThickness, as_thickness, matching
from ..walk import Frame, GradientRows, SamplingPattern
from .base import ScreenSpaceAO, make_parameter
from .common import RADIUS, declare_signature, functional_twin
from .bitmask_common import SectorAccumulator

__all__ = ["BitmaskAO", "SSILVB", "bitmask_ao", "ssilvb", "VARIANTS", "WEIGHTINGS", "UNIONS", "OPTIONS"]

VARIANTS = ("default", "exact", "hdrp", "ssilvb_glsl")
WEIGHTINGS = ("uniform", "cosine")
UNIONS = ("sectors", "exact")
SAMPLE_EXTENTS = ("radius", "sphere")
#: the ``"exact"`` variant's default ``min_step_px`` (pixels): where its first step lies
EXACT_MIN_STEP_PX = 0.25
#: ... and its default depth fetch
EXACT_FETCH = "edge_aware"
_HALF_PI = math.pi / 2

#: The bitmask family's options (beyond :class:`~torch_ao.methods.base.ScreenSpaceAO`'s sampling options).
OPTIONS = (
    Option("variant", "default", "which published rule: the clean one, its converging form, the bitmask blog's HDRP "
           "HLSL, or the SSILVB GLSL article's shader as written", str, choices=VARIANTS),
    Option("mode", "hard", "integer sector masks (bit for bit as the shaders, zero gradient), soft sector coverage, "
           "or hard forward with soft gradients", str, choices=MODES),
    Option("tau", 0.25, "temperature of the soft sector masks (smaller is closer to hard, stiffer gradients)",
           float, unit="sectors", minimum=0.0, open_minimum=True),
    Option("rounding", "ceil", "sector count of an interval: every sector touched, half covered, or fully covered",
           str, choices=ROUNDINGS),
    Option("weighting", None, "each sector 1/32 (the paper), or its exact share of the cosine-weighted slice "
           "(converges to cosine-weighted ray-traced AO); None: cosine for variant exact, else uniform",
           str, choices=WEIGHTINGS),
    Option("union", None, "how a slice's intervals are combined: 32 sectors (the paper), or the exact weighted "
           "measure of their union (no quantisation; visibility only); None: exact for variant exact, else sectors",
           str, choices=UNIONS),
    Option("clip_to_radius", None, "clip each occluder segment (front point to back point) to the sphere of the "
           "radius around the pixel, as the reference counts only occluders within it; None: True for variant "
           "exact, else False", bool),
    Option("thickness_direction", None, "where an occluder's back point lies: thickness behind it along the "
           "pixel's view vector (the paper, both shaders) or along its own camera ray to depth + thickness (a "
           "depth buffer of thick surfaces, a back-face layer); None: depth for variant exact, else view",
           str, choices=THICKNESS_DIRECTIONS),
    Option("sample_extent", None, "how far the steps reach on screen: the radius projected along the slice "
           "tangent at the pixel (every method's walk), or the screen extent of the radius' sphere around the "
           "pixel, which also reaches occluders nearer the camera; None: sphere for variant exact, else radius",
           str, choices=SAMPLE_EXTENTS),
    Option("thickness", 0.5, "how deep each occluder reaches behind its visible surface (a scalar; tables, maps "
           "and models from Python)", float, unit="world units", minimum=0.0, fitted=True),
    Option("thickness_growth", None, "thickness times 1 + growth * |sample - pixel| (None: no growth)", float,
           unit="1 / world units", minimum=0.0, fitted=True),
    Option("sector_epsilon", None, "width removed from every interval before rounding, so float noise on flat "
           "surfaces never occludes a sector with ceil; None: 0.01 for variant default, else 0", float,
           unit="sectors", minimum=0.0, maximum=1.0, open_maximum=True),
    Option("indirect", False, "also compute one-bounce indirect light (needs the G-buffer's light)", bool),
    Option("bent_normals", False, "also compute bent normals", bool),
    Option("ambient_directions", 8, "sub-regions per slice for a callable ambient light (divides 32)", int,
           minimum=1, maximum=SECTORS),
    Option("glsl_numerics", "ieee", "variant ssilvb_glsl only: exact acos, Mesa's polynomial acos, or also "
           "llvmpipe's float16 mediump jitter", str, choices=("ieee", "mesa", "mesa_mediump")),
)
_OPTIONS = options_by_name(OPTIONS)
#: options of the walk and the module whose default the signature shows as None: resolved per variant
#: (``azimuth``, ``min_step_px``, ``fetch``) or per call (``recompute``: see :meth:`BitmaskAO.auto_chunking`)
_RESOLVED_LATER = {"azimuth": None, "min_step_px": None, "fetch": None, "recompute": None}
#: per variant, the defaults of the options whose default is ``None``
_VARIANT_DEFAULTS = {
    "default": dict(weighting="uniform", union="sectors", clip_to_radius=False, thickness_direction="view", sample_extent="radius", sector_epsilon=0.01),
    "exact": dict(weighting="cosine", union="exact", clip_to_radius=True, thickness_direction="depth", sample_extent="sphere", sector_epsilon=0.0),
    "hdrp": dict(weighting="uniform", union="sectors", clip_to_radius=False, thickness_direction="view", sample_extent="radius", sector_epsilon=0.0),
    "ssilvb_glsl": dict(weighting="uniform", union="sectors", clip_to_radius=False, thickness_direction="view", sample_extent="radius", sector_epsilon=0.0),
}


def _saturate(x: torch.Tensor) -> torch.Tensor:
    return x.clamp(0.0, 1.0)


def _interval_from_unit(lo: torch.Tensor, hi: torch.Tensor, epsilon: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Interval ``[lo, hi]`` of ``[0, 1]`` -> start and width in sector units, ``epsilon`` sectors narrower.
    The width may come out negative: the sector union reads that as empty (and without gradient)."""
    start, width = sector_interval(lo, hi)
    return start, (width - epsilon if epsilon > 0 else width)


def _hemisphere_shift(gamma: torch.Tensor) -> torch.Tensor:
    """``(pi/2 - gamma) / pi``: where angle 0 (the view vector) lies across the hemisphere around the
    projected normal at angle ``gamma``."""
    return (_HALF_PI - gamma) / math.pi


def _unit_positions(along_view, along_tangent, back_view, shift, side, back_tangent=None):
    """Unclamped positions ``shift + side * theta / pi`` across the hemisphere of the front angle
    ``atan2(along_tangent, along_view)`` and the back angle ``atan2(back_tangent, back_view)``
    (``back_tangent`` defaults to ``along_tangent``); ``shift`` broadcasts against the angles' shape."""
    scale = along_view.new_tensor(side / math.pi)
    back_tangent = along_tangent if back_tangent is None else back_tangent
    return (torch.addcmul(shift, torch.atan2(along_tangent, along_view), scale),
            torch.addcmul(shift, torch.atan2(back_tangent, back_view), scale))


def _unit_angles(along_view, along_tangent, back_view, gamma, side, back_tangent=None):
    """:func:`_unit_positions` of samples whose rows are block-major over ``gamma``'s ``(N,)``."""
    N = gamma.shape[0]
    J = along_view.shape[0] // max(N, 1)
    rows = lambda x: None if x is None else x.view(J, N)  # noqa: E731
    front, back = _unit_positions(rows(along_view), rows(along_tangent), rows(back_view), _hemisphere_shift(gamma),
                                  side, rows(back_tangent))
    return front.view(-1), back.view(-1)


def _between(front: torch.Tensor, back: torch.Tensor, side: int, epsilon: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Interval ``(start, width)`` in sector units between the unit positions of the front and back
    angles, each clamped to the hemisphere (the back angle lies beyond the front one on side ``side``)."""
    xf, xb = _saturate(front), _saturate(back)
    lo, hi = (xf, xb) if side > 0 else (xb, xf)
    return _interval_from_unit(lo, hi, epsilon)


def _sector_interval(along_view, along_tangent, thickness, gamma, side: int, epsilon: float):
    """The default variant's occluded interval ``(start, width)`` in sector units ``(rows,)``: from the
    front angle to the back angle (the sample pushed ``thickness`` away along the view vector)."""
    return _between(*_unit_angles(along_view, along_tangent, along_view - thickness, gamma, side), side, epsilon)


class SectorInterval(torch.autograd.Function):
    """:func:`_sector_interval` with a hand-written backward that keeps only its inputs.

    Inputs: ``along_view``, ``along_tangent`` ``(rows,)`` (rows = steps x N, block-major),
    ``thickness`` (0-d or ``(rows,)``), ``gamma`` ``(N,)`` the projected normal's angle, ``side``,
    ``epsilon``. Outputs ``start``, ``width`` ``(rows,)`` (a negative width: an empty interval). Autograd
    through the ``atan2``s and clamps would keep about a dozen tensors per sample; the angles are
    recomputed in backward instead.
    """

    @staticmethod
    def forward(ctx, along_view, along_tangent, thickness, gamma, side, epsilon):
        ctx.side, ctx.epsilon = side, epsilon
        ctx.save_for_backward(along_view, along_tangent, thickness, gamma)
        return _sector_interval(along_view, along_tangent, thickness, gamma, side, epsilon)

    @staticmethod
    def backward(ctx, g_start, g_width):
        av, at, t, gamma = ctx.saved_tensors
        side = ctx.side
        N = gamma.shape[0]
        J = av.shape[0] // max(N, 1)
        with torch.no_grad():
            zero = torch.zeros_like(av)
            g_start = zero if g_start is None else g_start
            g_width = zero if g_width is None else g_width
            rows = GradientRows(J, N, g_start, g_width)  # (empty intervals have none)
            av, at, g_start, g_width = map(rows.take, (av, at, g_start, g_width))
            t_rows = t if t.dim() == 0 else rows.take(t)
            back_view = av - t_rows
            rf, rb = _unit_positions(av, at, back_view, rows.per_row(_hemisphere_shift(gamma)), side)
            g_lo = (g_start - g_width) * SECTORS
            g_hi = g_width * SECTORS
            g_f, g_b = (g_lo, g_hi) if side > 0 else (g_hi, g_lo)
            # clamp(r, 0, 1) passes gradient inside [0, 1] (ends included, as torch.clamp); r = (side theta - gamma + pi/2) / pi
            g_f = torch.where(rf.clamp(0.0, 1.0) == rf, g_f, 0.0)
            g_b = torch.where(rb.clamp(0.0, 1.0) == rb, g_b, 0.0)
            g_gamma = rows.per_query(g_f + g_b).mul_(-1 / math.pi)
            # theta = atan2(y, x): d theta = (x dy - y dx) / (x^2 + y^2)
            inv_f = torch.addcmul(at * at, av, av).reciprocal_().mul_(g_f).mul_(side / math.pi)
            inv_b = torch.addcmul(at * at, back_view, back_view).reciprocal_().mul_(g_b).mul_(side / math.pi)
            g_at = rows.put(torch.addcmul(av * inv_f, back_view, inv_b))
            g_t = at * inv_b
            g_t = g_t.sum() if t.dim() == 0 else rows.put(g_t)
            g_av = rows.put((inv_f + inv_b).mul_(at).neg_())
        return g_av, g_at, g_t, g_gamma, None, None


class DefaultAccumulator(SectorAccumulator):
    """The ``"default"`` and ``"exact"`` variants' rule: exact in-plane angles ``atan2`` of the front and
    back points, signed slice coordinate ``side * theta`` mapped by ``(side * theta - gamma + pi/2) / pi``.

    ``thickness_direction`` and ``clip_to_radius`` (``radius``: the AO radius, world units) choose the
    occluder segment (see :mod:`torch_ao.intervals`); with ``"view"`` and no clipping the interval has the
    hand-written backward :class:`SectorInterval`.
    """

    def __init__(self, *, thickness_direction: str = "view", clip_to_radius: bool = False, radius=None, **kwargs) -> None:
        super().__init__(**kwargs)
        self.thickness_direction, self.clip_to_radius, self.radius = thickness_direction, clip_to_radius, radius

    def interval(self, state, q, sample, t):
        gamma, side = state["gamma"], sample.side
        if self.thickness_direction == "view" and not self.clip_to_radius:
            args = (sample.along_view, sample.along_tangent, t, gamma, side, self.sector_epsilon)
            if torch.is_grad_enabled() and any(x.requires_grad for x in args[:4]):
                return SectorInterval.apply(*args)
            return _sector_interval(*args)
        fv, ft = sample.along_view, sample.along_tangent
        extra = {}
        if self.thickness_direction == "depth":
            extra = dict(pixel_distance=q.position.norm(dim=-1), sample_depth=-sample.position[:, 2])
        bv, bt = back_point(fv, ft, t, self.thickness_direction, **extra)
        live = sample.valid
        if self.clip_to_radius:
            radius = torch.as_tensor(self.radius, dtype=fv.dtype, device=fv.device)
            fv, ft, bv, bt, inside = clip_to_sphere(fv, ft, bv, bt, radius)
            live = live & inside
        start, width = _between(*_unit_angles(fv, ft, bv, gamma, side, bt), side, self.sector_epsilon)
        return start, torch.where(live, width, torch.full_like(width, -1.0))


class HDRPAccumulator(SectorAccumulator):
    """The ``"hdrp"`` variant (the bitmask blog's HLSL on HDRP's GTAO): the 3D cosines
    ``dot(normalize(delta - t V), V)`` through the polynomial ``fast_acos``;
    ``N = -sign(dot(projN, T)) * fast_acos(cosN)``; ``saturate((side * -angle - N + pi/2) / pi)`` and the
    ``yx`` swap on the positive side."""

    def slice_frame(self, q, geom):
        length = geom.normal_length  # (the projected normal's components: walk.slice_geometry's)
        cos_n = (q.normal * q.view).sum(-1) / length.clamp_min(1e-30)
        gamma = -torch.sign((q.normal * geom.tangent).sum(-1)) * _safe_fast_acos(cos_n)
        return gamma, length, -geom.tangent  # HDRP's signed angles grow toward -T

    def interval(self, state, q, sample, t):
        side = sample.side
        gamma = state["gamma"].repeat(sample.steps)
        front = _safe_fast_acos(sample.cos_view(0.0))
        back = _safe_fast_acos(sample.cos_view(t))
        # HDRP's angles grow toward -T: the front and back positions swap roles (its ``yx`` swap)
        return _between(((side * -front) - gamma + _HALF_PI) / math.pi, ((side * -back) - gamma + _HALF_PI) / math.pi,
                        -side, self.sector_epsilon)


class SphereExtent(SamplingPattern):
    """``pattern``'s walk with its steps spread over the screen extent of the sphere of radius ``radius``
    around the pixel (:func:`~torch_ao.intervals.sphere_stretch`) instead of the projection of the radius
    along the slice tangent, which misses occluders within the radius that are nearer the camera."""

    def __init__(self, pattern: SamplingPattern, radius) -> None:
        self.pattern, self.radius = pattern, radius
        self.num_slices, self.sides, self.fetch, self.border = pattern.num_slices, pattern.sides, pattern.fetch, pattern.border

    def slice_tangent(self, frame, q, s):
        return self.pattern.slice_tangent(frame, q, s)

    def slice_direction(self, frame, q, s):
        return self.pattern.slice_direction(frame, q, s)

    def step_offsets(self, q, geom, side):
        stretch = sphere_stretch(q.position.norm(dim=-1), self.radius)
        return self.pattern.step_offsets(q, replace(geom, pixels_per_unit=geom.pixels_per_unit * stretch[:, None]), side)


class BitmaskAO(ScreenSpaceAO):
    """Visibility-bitmask AO (and, with ``indirect=True``, SSILVB indirect light) as an ``nn.Module``.

    Args (:data:`OPTIONS` gives each option's unit, range and default):
        variant: ``"default"``, ``"exact"`` (converges; see docs/bitmask.md), ``"hdrp"`` (the bitmask
            blog) or ``"ssilvb_glsl"`` (the SSILVB GLSL article as written; there ``slices``/``steps`` are
            the shader's ``sliceCount``/``sampleCount`` uniforms, and ``radius``, which only picks the
            nearest texels its walk reads, is a buffer rather than a parameter).
        mode: ``"hard"`` (integer bitmasks, bit for bit; zero gradient a.e.), ``"soft"`` or
            ``"straight_through"`` (hard forward, soft gradient). No effect with ``union="exact"``, which
            is differentiable almost everywhere as it is.
        tau: soft temperature in sector units (``> 0``).
        rounding: ``"ceil"``, ``"round"`` or ``"floor"`` (sector count of an interval).
        weighting: ``"uniform"`` or ``"cosine"`` (default: cosine for ``"exact"``, else uniform).
        union: ``"sectors"`` (32 sectors) or ``"exact"`` (the exact weighted measure of the union of the
            intervals; visibility only).
        clip_to_radius: clip each occluder segment to the sphere of radius ``radius`` around the pixel.
        thickness_direction: ``"view"`` (back point ``thickness`` behind the sample along the pixel's
            view vector) or ``"depth"`` (along the sample's camera ray, at depth + ``thickness``).
        sample_extent: ``"radius"`` (steps up to the radius projected along the slice tangent) or
            ``"sphere"`` (up to the screen extent of the radius' sphere, :class:`SphereExtent`).
        thickness: a float, a ``(K,)`` per-object table (uses ``gbuffer.object_id``), a ``(B,1,H,W)`` map,
            or a :class:`~torch_ao.thickness.Thickness` model; its parameters are registered on this
            module under the model's names (``thickness``, ``thickness_slope``, ``thickness_scale``...),
            ``nn.Parameter``\\ s when ``trainable``.
        thickness_growth: optional scalar ``g``: thickness ``* (1 + g |sample - pixel|)``.
        indirect, bent_normals: compute these outputs (``indirect`` needs ``gbuffer.light``).
        ambient: ``None``, an RGB colour or a callable ``(M,3) -> (M,3)`` of view-space directions.
        ambient_directions: sub-regions per slice for a callable ambient (divides 32).
        sector_epsilon: width (in sectors) removed from every interval before rounding, so that the
            float noise of samples lying exactly in the tangent plane does not occlude a whole sector with
            ``ceil`` (a flat plane gives exactly 1). Default 0.01 for ``"default"``, 0 for the others.
        glsl_numerics: ``"ssilvb_glsl"`` only: ``"ieee"`` (exact ``acos``, input precision), ``"mesa"``
            (Mesa's polynomial ``acos``; matches Mesa softpipe) or ``"mesa_mediump"`` (also llvmpipe's
            float16 ``mediump`` jitter). See :mod:`torch_ao.methods.bitmask_glsl`.
        radius, preset, slices, steps, step_power, min_step_px, jitter, seed, fetch, border, azimuth,
        normals, chunk_size, recompute, trainable, resolution, backend: the walk's and every module's
            options (:class:`~torch_ao.methods.base.ScreenSpaceAO`; :meth:`options` describes each). Unless
            ``chunk_size``/``recompute`` are given, each call picks them (see :meth:`auto_chunking`): cache-sized chunks of 16384
            pixels, recomputed in backward only when a soft gradient's graph would exceed
            ``graph_budget`` (1 GiB). ``azimuth`` defaults to ``"view"`` for ``"default"``/``"exact"`` and
            ``"screen"`` for ``"hdrp"``; ``min_step_px`` to 0.25 for ``"exact"`` (:data:`EXACT_MIN_STEP_PX`),
            1 otherwise; ``fetch`` to ``"edge_aware"`` for ``"exact"`` (:data:`EXACT_FETCH`), bilinear otherwise.
    """

    has_kernel = "bitmask"  # hard visibility in torch_ao.kernels (kernel_covers says which calls)
    #: its own options and the radius (``options()`` adds the walk's and the module's: the CLI's flags)
    OPTIONS = (RADIUS,) + OPTIONS

    #: pixels per chunk of a walk when ``chunk_size`` is not given (chunks that stay in the CPU caches
    #: are faster than one piece: 1.7 s instead of 2.2 s for a hard 640x360 frame)
    default_chunk = 16384
    #: pixels per recomputed chunk of a walk with a soft gradient whose graph would exceed ``graph_budget``
    #: (halved when indirect light is asked for)
    default_soft_chunk = 16384
    #: a walk with a soft gradient keeps its whole autograd graph (no recomputation, so the walk runs
    #: once) when its estimate is at most this many bytes; above it, chunks are recomputed in backward
    graph_budget = 1 << 30
    #: estimated autograd bytes kept per sample (pixel x slice x side x step) by a soft walk, measured by
    #: summing the graph's saved tensors (tests/test_bitmask_recompute.py): about 47 for visibility, and
    #: up to about 330 more with indirect light (its light and normal gathers, for the samples whose
    #: interval is not empty: all of them at worst)
    graph_bytes_per_sample = 48
    graph_bytes_per_sample_indirect = 400
    #: ... and with the exact union, clipping or the camera-ray thickness direction (plain autograd
    #: through the segment geometry and the sort)
    graph_bytes_per_sample_exact = 400

    def __init__(self, *, variant: str = "default", mode: str = "hard", tau: float = 0.25, rounding: str = "ceil",
                 weighting: str | None = None, union: str | None = None, clip_to_radius: bool | None = None,
                 thickness_direction: str | None = None, sample_extent: str | None = None, thickness=0.5, thickness_growth: float | None = None,
                 indirect: bool = False, bent_normals: bool = False, ambient=None, ambient_directions: int = 8,
                 azimuth: str | None = None, glsl_numerics: str = "ieee",
                 sector_epsilon: float | None = None, **kwargs) -> None:
        # None: the variant's default (min_step_px, fetch) or the automatic choice per call (recompute)
        kwargs = {k: v for k, v in kwargs.items() if not (v is None and k in _RESOLVED_LATER)}
        given = dict(variant=variant, mode=mode, tau=tau, rounding=rounding, weighting=weighting, union=union,
                     clip_to_radius=clip_to_radius, thickness_direction=thickness_direction, sample_extent=sample_extent,
                     sector_epsilon=sector_epsilon, indirect=indirect, bent_normals=bent_normals,
                     ambient_directions=ambient_directions, glsl_numerics=glsl_numerics)
        for name, value in given.items():
            _OPTIONS[name].check(value)
        if SECTORS % ambient_directions:
            raise ValueError(f"ambient_directions: expected a divisor of {SECTORS}, got {ambient_directions!r}")
        defaults = _VARIANT_DEFAULTS[variant]
        resolved = {k: defaults[k] if given[k] is None else given[k] for k in defaults}
        _check_variant_options(variant, given, resolved, bent_normals or ambient is not None, indirect)
        self.variant, self.glsl_numerics = variant, glsl_numerics
        self.sample_extent = resolved["sample_extent"]
        if azimuth is None:
            azimuth = "screen" if variant in ("hdrp", "ssilvb_glsl") else "view"
        if variant == "exact":
            # The walk's first step 1 px out misses occluders within the first pixel (creases): a quarter
            # pixel halves the remaining bias against the screen-space truth on stairs (docs/bitmask.md).
            kwargs.setdefault("min_step_px", EXACT_MIN_STEP_PX)
            # Bilinear skirts across depth edges are surfaces its steps cannot resolve: with them the
            # estimator does not reach the truth on thin occluders (docs/bitmask.md, "Convergence").
            kwargs.setdefault("fetch", EXACT_FETCH)
        super().__init__(azimuth=azimuth, **kwargs)
        self.pattern_for(None)  # validate the variant's walk now (the base no longer calls it)
        self.mode, self.tau, self.rounding = mode, float(tau), rounding
        self.weighting, self.union = resolved["weighting"], resolved["union"]
        self.clip_to_radius, self.thickness_direction = resolved["clip_to_radius"], resolved["thickness_direction"]
        self.sector_epsilon = float(resolved["sector_epsilon"])
        # Chosen per call (the mode may change after construction, e.g. fit's set_mode).
        self._auto_chunk = kwargs.get("chunk_size") is None and "recompute" not in kwargs
        self.want_indirect, self.want_bent = bool(indirect), bool(bent_normals)
        self.ambient_directions = ambient_directions
        trainable = kwargs.get("trainable", True)
        self.thickness_model = as_thickness(thickness, thickness_growth)
        for name, p in self.thickness_model.parameters().items():
            make_parameter(self, name, p.value, trainable=trainable, minimum=p.minimum)
            self.thickness_model.check(name, getattr(self, name))
        if "thickness_growth" not in self.thickness_model.parameters():
            self.thickness_growth = None
        if ambient is None or callable(ambient):
            self.ambient = ambient
        else:
            colour = torch.as_tensor(ambient, dtype=torch.get_default_dtype()).reshape(-1)
            if colour.numel() == 1:
                colour = colour.expand(3)
            if colour.numel() != 3 or not bool(torch.isfinite(colour).all()):
                raise ValueError(f"ambient: expected a callable, an RGB colour or a scalar, got {ambient!r}")
            self.register_buffer("ambient_colour", colour.clone())
            self.ambient = None
        self._ambient_constant = ambient is not None and not callable(ambient)

    @property
    def ambient_constant(self) -> torch.Tensor | None:
        """The constant ambient colour ``(3,)`` (linear RGB) when ``ambient`` was a colour, else ``None``."""
        return self.ambient_colour if self._ambient_constant else None

    def no_gradient(self, values):
        if self.variant == "ssilvb_glsl":
            return {"radius": "the 'ssilvb_glsl' shader's walk reads nearest texels, which the radius only picks "
                              "(no gradient): use variant='default' to fit it"}
        return {}

    @property
    def _plain_autograd(self) -> bool:
        """Whether the interval geometry is recorded by plain autograd (the exact options), in any mode."""
        return self.union == "exact" or self.clip_to_radius or self.thickness_direction != "view"

    def graph_bytes(self, pixels: int) -> int:
        """Estimated autograd memory (bytes) of a soft walk over ``pixels`` query pixels kept whole."""
        per_sample = self.graph_bytes_per_sample_indirect if self.want_indirect else self.graph_bytes_per_sample
        if self._plain_autograd:
            per_sample = max(per_sample, self.graph_bytes_per_sample_exact)
        return pixels * self.slices * 2 * self.steps * per_sample

    def auto_chunking(self, pixels: int) -> tuple[int | None, bool]:
        """``(chunk_size, recompute)`` for a frame of ``pixels`` (``B*H*W``) when the user gave neither.

        Walks go in cache-sized chunks of ``default_chunk`` pixels. With a soft gradient (soft or
        straight-through mode, or the exact options, autograd on), the whole graph is kept if
        :meth:`graph_bytes` is at most ``graph_budget`` (the walk runs once); otherwise each chunk of
        ``default_soft_chunk`` pixels (half that with ``indirect``) is recomputed in backward, which bounds
        the memory of forward+backward by one chunk whatever the frame size.
        """
        chunk = self.default_chunk if pixels > self.default_chunk else None
        soft = self.mode != "hard" or self._plain_autograd
        if soft and torch.is_grad_enabled() and self.graph_bytes(pixels) > self.graph_budget:
            return self.default_soft_chunk // (2 if self.want_indirect else 1), True
        return chunk, False

    def chunking(self, gbuffer: GBuffer) -> tuple[int | None, bool]:
        if self._auto_chunk:
            return self.auto_chunking(gbuffer.depth.numel())
        return super().chunking(gbuffer)

    # ------------------------------------------------------------------ hooks
    def pattern_for(self, frame: Frame | None):
        if getattr(self, "variant", "default") == "ssilvb_glsl":
            from .bitmask_glsl import GLSLPattern

            return GLSLPattern(self.slices, self.steps, self.radius, jitter=self.jitter, frame=frame,
                               numerics=self.glsl_numerics)
        pattern = super().pattern_for(frame)
        return SphereExtent(pattern, self.radius) if getattr(self, "sample_extent", "radius") == "sphere" else pattern

    def bound_thickness(self) -> BoundThickness:
        """The thickness model with this module's current parameters (a ``thickness`` reassigned with
        another shape, e.g. a map set per frame, switches among the scalar/table/map models)."""
        model = matching(self.thickness_model, self.thickness)
        return BoundThickness(model, {name: getattr(self, name) for name in model.parameters()})

    def frame_buffers(self, gbuffer: GBuffer, normals: torch.Tensor) -> dict[str, torch.Tensor]:
        buffers = {}
        if self.want_indirect:
            if gbuffer.light is None:
                raise ValueError("gbuffer.light: indirect light needs a (B,3,H,W) direct-light buffer")
            buffers["light"] = gbuffer.light
            buffers["normals"] = normals
        buffers.update(self.bound_thickness().buffers(gbuffer))
        return buffers

    def accumulator(self, frame: Frame):
        if self.variant == "ssilvb_glsl":
            from .bitmask_glsl import GLSLAccumulator

            return GLSLAccumulator(mode=self.mode, rounding=self.rounding, tau=self.tau, thickness=self.bound_thickness(),
                                   indirect=self.want_indirect, slice_count=self.slices, frame=frame,
                                   jitter=self.jitter, numerics=self.glsl_numerics)
        common = dict(mode=self.mode, rounding=self.rounding, tau=self.tau, weighting=self.weighting,
                      thickness=self.bound_thickness(), indirect=self.want_indirect, bent_normals=self.want_bent,
                      ambient=self.ambient if self.ambient_constant is None else self.ambient_constant,
                      ambient_directions=self.ambient_directions, sector_epsilon=self.sector_epsilon, union=self.union)
        if self.variant == "hdrp":
            return HDRPAccumulator(**common)
        return DefaultAccumulator(thickness_direction=self.thickness_direction, clip_to_radius=self.clip_to_radius,
                                  radius=self.radius, **common)

    def extra_repr(self) -> str:
        return (f"variant={self.variant!r}, mode={self.mode!r}, tau={self.tau}, rounding={self.rounding!r}, "
                f"weighting={self.weighting!r}, union={self.union!r}, thickness={self.thickness_model.describe()}, "
                + super().extra_repr())


def _check_variant_options(variant: str, given: dict, resolved: dict, bent_or_ambient: bool, indirect: bool) -> None:
    """Refuse options a variant does not have (``ValueError`` naming the option)."""
    if variant == "ssilvb_glsl":
        if resolved["weighting"] != "uniform":
            raise ValueError("weighting: the 'ssilvb_glsl' variant is the shader as written (uniform sectors)")
        if bent_or_ambient:
            raise ValueError("bent_normals/ambient: not part of the 'ssilvb_glsl' shader; use variant='default'")
    if variant in ("hdrp", "ssilvb_glsl"):
        for name in ("clip_to_radius", "thickness_direction", "sample_extent") + (("union",) if variant == "ssilvb_glsl" else ()):
            if resolved[name] != _VARIANT_DEFAULTS[variant][name]:
                raise ValueError(f"{name}: not an option of the {variant!r} variant (its shader's rule); "
                                 f"use variant='default' or 'exact'")
    if resolved["union"] == "exact" and (indirect or bent_or_ambient):
        raise ValueError("union: 'exact' computes visibility only; use union='sectors' for indirect light, "
                         "bent normals or ambient light")


class SSILVB(BitmaskAO):
    """Screen-space indirect lighting with visibility bitmask: :class:`BitmaskAO` with ``indirect=True``
    (outputs ``visibility`` and ``indirect``; the G-buffer needs ``light``)."""

    def __init__(self, *, indirect: bool = True, **kwargs) -> None:
        super().__init__(indirect=indirect, **kwargs)


declare_signature(BitmaskAO, defaults=_RESOLVED_LATER, extra={"ambient": None})
declare_signature(SSILVB, defaults=_RESOLVED_LATER | {"indirect": True}, extra={"ambient": None})
bitmask_ao = functional_twin(BitmaskAO, "bitmask_ao")
ssilvb = functional_twin(SSILVB, "ssilvb")
