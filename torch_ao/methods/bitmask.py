"""Visibility-bitmask ambient occlusion (Therrien et al. 2023) and its indirect-light extension (SSILVB).

Each slice's hemisphere (around the projected normal) is split into 32 sectors. Every sample
occludes the sectors between its *front* direction and its *back* direction (the sample pushed
``thickness`` away from the camera along the view vector), so light passes behind thin surfaces.
The union over a slice's steps gives its occluded sectors; visibility is the share of unoccluded
sectors, averaged over slices. See :mod:`torch_ao.sectors` for the masks and their soft versions.

Variants (``variant=``):

``"default"``
    Slices evenly over the half circle around the view vector (or in screen angle with
    ``azimuth="screen"``), both sides marched into one 32-sector mask per slice, exact in-plane
    angles (``atan2`` in the slice plane), signed slice coordinate ``side * theta`` mapped by
    ``(side * theta - gamma + pi/2) / pi`` (``gamma`` = projected-normal angle). Visibility in [0, 1].
``"hdrp"``
    Seed 000 (HLSL on HDRP's GTAO): both sides into one bitfield; the 3D cosines
    ``dot(normalize(delta - t V), V)`` through the polynomial ``fast_acos``;
    ``N = -sign(dot(projN, T)) * fast_acos(cosN)``; ``saturate((side * -angle - N + pi/2) / pi)`` and the
    ``yx`` swap on the positive side. (HDRP's sample clamp to ``[2, size - 2]`` pixels and its
    half-resolution depth mips are not reproduced; use ``border=``/``fetch=``.)
``"ssilvb_glsl"``
    Seed 001, the GLSL shader as written (see :mod:`torch_ao.methods.bitmask_glsl` for its quirks).

Options: ``mode`` ``"hard" | "soft" | "straight_through"`` with temperature ``tau`` (sector units);
``rounding`` ``"ceil" | "round" | "floor"``; ``weighting`` ``"uniform"`` (the paper: every sector
1/32) or ``"cosine"`` (each sector weighted by its exact share of the cosine-weighted slice
``|n_p| int cos(theta - gamma) |sin theta| dtheta``, normalised so an unoccluded pixel gives exactly 1;
converges to cosine-weighted ray-traced AO). ``thickness``: a scalar, a ``(B,1,H,W)`` map (the
*occluder's* thickness, read at the sample), or a ``(K,)`` table indexed by the G-buffer's
``object_id`` at the sample; ``thickness_growth`` multiplies it by ``1 + growth * |sample - pixel|``.

Outputs beyond visibility are computed only when asked (``indirect=True``, ``bent_normals=True``,
``ambient=``): an AO-only call never gathers the light or normal buffers.

* ``indirect`` ``(B,3,H,W)``: for every step, the *newly* occluded sectors times the sample's light
  ``L``, the sender's ``saturate(N_s . -l)`` and, with uniform weighting, the receiver's
  ``saturate(N . l)`` (seeds 000/001; ``l`` = unit direction to the sample). With cosine weighting the
  receiver's cosine is already in the sector weights, so it is not applied twice.
* ``ambient`` ``(B,3,H,W)``: seed 000's ``ComputeAmbient``: unoccluded sectors, grouped into
  ``ambient_directions`` sub-regions, times the ambient light from each sub-region's centre direction
  (a constant RGB colour, or a callable ``(M,3)`` view-space directions -> ``(M,3)``).
* ``bent_normal`` ``(B,3,H,W)``: the normalised weighted mean direction of the unoccluded sectors.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
import torch.nn.functional as F

from ..gbuffer import GBuffer
from ..ops import safe_fast_acos as _safe_fast_acos
from ..walk import Frame, GradientRows, Queries, Sample, SliceAccumulator, SliceGeometry
from ..sectors import MODES, ROUNDINGS, SECTORS, sector_union
from .base import AOOutput, ScreenSpaceAO, make_parameter
from .bitmask_common import ThicknessLookup, cosine_sector_weights, sector_centres

__all__ = ["BitmaskAO", "SSILVB", "bitmask_ao", "ssilvb", "VARIANTS", "WEIGHTINGS"]

VARIANTS = ("default", "hdrp", "ssilvb_glsl")
WEIGHTINGS = ("uniform", "cosine")
_HALF_PI = math.pi / 2


def _saturate(x: torch.Tensor) -> torch.Tensor:
    return x.clamp(0.0, 1.0)


def _interval_from_unit(lo: torch.Tensor, hi: torch.Tensor, epsilon: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Interval ``[lo, hi]`` of ``[0, 1]`` -> start and width in sector units, ``epsilon`` sectors narrower.
    The width may come out negative: the sector union reads that as empty (and without gradient)."""
    width = (hi - lo) * SECTORS
    if epsilon > 0:
        width = width - epsilon
    return lo * SECTORS, width


def _hemisphere_shift(gamma: torch.Tensor) -> torch.Tensor:
    """``(pi/2 - gamma) / pi``: where angle 0 (the view vector) lies across the hemisphere around the
    projected normal at angle ``gamma``."""
    return (_HALF_PI - gamma) / math.pi


def _unit_positions(along_view, along_tangent, back_view, shift, side):
    """Unclamped positions ``shift + side * theta / pi`` across the hemisphere of the front angle
    ``atan2(along_tangent, along_view)`` and the back angle ``atan2(along_tangent, back_view)``;
    ``shift`` broadcasts against the angles' shape."""
    scale = along_view.new_tensor(side / math.pi)
    return (torch.addcmul(shift, torch.atan2(along_tangent, along_view), scale),
            torch.addcmul(shift, torch.atan2(along_tangent, back_view), scale))


def _unit_angles(along_view, along_tangent, thickness, gamma, side):
    """:func:`_unit_positions` of samples whose rows are block-major over ``gamma``'s ``(N,)``."""
    N = gamma.shape[0]
    J = along_view.shape[0] // max(N, 1)
    front, back = _unit_positions(along_view.view(J, N), along_tangent.view(J, N),
                                  (along_view - thickness).view(J, N), _hemisphere_shift(gamma), side)
    return front.view(-1), back.view(-1)


def _sector_interval(along_view, along_tangent, thickness, gamma, side: int, epsilon: float):
    """The default variant's occluded interval ``(start, width)`` in sector units ``(rows,)``: from the
    front angle to the back angle (the sample pushed ``thickness`` away along the view vector)."""
    xf, xb = (_saturate(x) for x in _unit_angles(along_view, along_tangent, thickness, gamma, side))
    lo, hi = (xf, xb) if side > 0 else (xb, xf)
    return _interval_from_unit(lo, hi, epsilon)


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


def _light_rows(width: torch.Tensor) -> torch.Tensor:
    """Rows ``(M,)`` of the steps whose interval is not empty (``width >= 0``): only those can newly
    occlude sectors, so only they gather light."""
    return (width.detach() >= 0).nonzero()[:, 0]


class BitmaskAccumulator(SliceAccumulator):
    """The per-step work of the ``"default"`` and ``"hdrp"`` variants (a :class:`SliceAccumulator`).

    It takes each side's steps in one call (``batch_steps``): state lists hold ``(steps, N)`` blocks.
    """

    batch_steps = True

    def __init__(self, *, variant: str, mode: str, rounding: str, tau: float, weighting: str,
                 thickness: ThicknessLookup, indirect: bool, bent_normals: bool,
                 ambient: torch.Tensor | Callable | None, ambient_directions: int,
                 sector_epsilon: float = 0.0) -> None:
        self.variant, self.mode, self.rounding, self.tau = variant, mode, rounding, tau
        self.weighting, self.thickness = weighting, thickness
        self.indirect, self.bent_normals = indirect, bent_normals
        self.ambient, self.ambient_directions = ambient, ambient_directions
        self.sector_epsilon = float(sector_epsilon)

    # ------------------------------------------------------------------ slice
    def begin_slice(self, q: Queries, geom: SliceGeometry):
        if self.variant == "hdrp":
            n_p = q.normal - geom.axis * (q.normal * geom.axis).sum(-1, keepdim=True)
            length = n_p.norm(dim=-1)
            cos_n = (n_p * q.view).sum(-1) / length.clamp_min(1e-30)
            gamma = -torch.sign((n_p * geom.tangent).sum(-1)) * _safe_fast_acos(cos_n)
            tangent = -geom.tangent  # HDRP's signed angles grow toward -T
        else:
            gamma, length, tangent = geom.normal_angle, geom.normal_length, geom.tangent
        if self.weighting == "cosine":
            weights = cosine_sector_weights(gamma, length)
        else:
            weights = gamma.new_full((1, SECTORS), 1.0 / SECTORS).expand(gamma.shape[0], SECTORS)
        return {"s": [], "w": [], "light": [], "gamma": gamma, "tangent": tangent, "weights": weights}

    def step(self, state, q: Queries, geom: SliceGeometry, sample: Sample):
        J = sample.steps
        n = len(q) // J
        t = self.thickness(sample)
        side = sample.side
        if self.variant == "hdrp":
            gamma = state["gamma"].repeat(J)
            front = _safe_fast_acos(sample.cos_view(0.0))
            back = _safe_fast_acos(sample.cos_view(t))
            xf = _saturate(((side * -front) - gamma + _HALF_PI) / math.pi)
            xb = _saturate(((side * -back) - gamma + _HALF_PI) / math.pi)
            lo, hi = (xb, xf) if side > 0 else (xf, xb)
            start, width = _interval_from_unit(lo, hi, self.sector_epsilon)
        else:
            gamma = state["gamma"]
            args = (sample.along_view, sample.along_tangent, t, gamma, side, self.sector_epsilon)
            if torch.is_grad_enabled() and any(x.requires_grad for x in args[:4]):
                start, width = SectorInterval.apply(*args)
            else:
                start, width = _sector_interval(*args)
        state["s"].append(start.view(J, n))
        state["w"].append(width.view(J, n))
        if self.indirect:
            # Only a step whose interval is not empty can newly occlude sectors and send light: the
            # others (most samples) are never gathered.
            live = _light_rows(width)
            part = sample.rows(live)
            ldir = part.delta / part.distance.clamp_min(1e-30)[:, None]
            sender = _saturate((part.gather("normals") * -ldir).sum(-1))
            factor = sender * part.valid.to(sender.dtype)
            if self.weighting == "uniform":
                factor = factor * _saturate((q.normal.index_select(0, live) * ldir).sum(-1))
            light = part.gather("light") * factor[:, None]
            state["light"].append(light.new_zeros(J * n, 3).index_copy(0, live, light).view(J, n, 3))
        return state

    def end_slice(self, state, q: Queries, geom: SliceGeometry) -> dict[str, torch.Tensor]:
        S = torch.cat(state["s"], 0).t()  # (N, steps on both sides)
        W = torch.cat(state["w"], 0).t()
        omega = state["weights"]
        visible, newly = sector_union(S, W, mode=self.mode, rounding=self.rounding, tau=self.tau,
                                      weights=omega if self.indirect else None)
        out = {"vis_num": (visible * omega).sum(-1, keepdim=True)}
        if self.weighting == "cosine":
            out["vis_den"] = omega.sum(-1, keepdim=True)
        if self.indirect:
            out["indirect"] = (newly.t()[:, :, None] * torch.cat(state["light"], 0)).sum(0)
        if self.bent_normals or callable(self.ambient):
            wv = visible * omega
            phi = sector_centres(state["gamma"])
            V, T = q.view, state["tangent"]
            if self.bent_normals:
                out["bent"] = (wv * torch.cos(phi)).sum(-1, keepdim=True) * V + (wv * torch.sin(phi)).sum(-1, keepdim=True) * T
            if callable(self.ambient):
                G = self.ambient_directions
                group = wv.reshape(wv.shape[0], G, SECTORS // G).sum(-1)  # (N, G)
                centre = phi.reshape(phi.shape[0], G, SECTORS // G).mean(-1)  # (N, G)
                dirs = torch.cos(centre)[..., None] * V[:, None] + torch.sin(centre)[..., None] * T[:, None]
                radiance = self.ambient(F.normalize(dirs, dim=-1).reshape(-1, 3)).reshape(dirs.shape)
                out["ambient"] = (group[..., None] * radiance.to(group.dtype)).sum(1)
        return out

    def finish(self, sums, q: Queries, num_slices: int) -> dict[str, torch.Tensor]:
        den = sums["vis_den"].clamp_min(1e-30) if self.weighting == "cosine" else sums["vis_num"].new_tensor(float(num_slices))
        vis = sums["vis_num"] / den
        out = {"visibility": vis}
        if self.indirect:
            out["indirect"] = sums["indirect"] / den
        if self.bent_normals:
            b = sums["bent"]
            ok = b.norm(dim=-1, keepdim=True) > 1e-12
            out["bent_normal"] = torch.where(ok, F.normalize(b, dim=-1, eps=1e-12), q.normal)
        if self.ambient is not None:
            if callable(self.ambient):
                out["ambient"] = sums["ambient"] / den
            else:
                out["ambient"] = vis * self.ambient.to(vis.dtype)
        return out


class BitmaskAO(ScreenSpaceAO):
    """Visibility-bitmask AO (and, with ``indirect=True``, SSILVB indirect light) as an ``nn.Module``.

    Args:
        variant: ``"default"``, ``"hdrp"`` (seed 000) or ``"ssilvb_glsl"`` (seed 001 as written; there
            ``slices``/``steps`` are the shader's ``sliceCount``/``sampleCount`` uniforms).
        mode: ``"hard"`` (integer bitmasks, bit for bit; zero gradient a.e.), ``"soft"`` or
            ``"straight_through"`` (hard forward, soft gradient).
        tau: soft temperature in sector units (``> 0``).
        rounding: ``"ceil"``, ``"round"`` or ``"floor"`` (sector count of an interval).
        weighting: ``"uniform"`` or ``"cosine"``.
        thickness: scalar, ``(K,)`` per-object table (uses ``gbuffer.object_id``) or ``(B,1,H,W)`` map;
            an ``nn.Parameter`` when ``trainable``.
        thickness_growth: optional scalar ``g``: thickness ``* (1 + g |sample - pixel|)``.
        indirect, bent_normals: compute these outputs (``indirect`` needs ``gbuffer.light``).
        ambient: ``None``, an RGB colour or a callable ``(M,3) -> (M,3)`` of view-space directions.
        ambient_directions: sub-regions per slice for a callable ambient (divides 32).
        sector_epsilon: width (in sectors) removed from every interval before rounding, so that the
            float noise of samples lying exactly in the tangent plane does not occlude a whole sector with
            ``ceil`` (a flat plane gives exactly 1). Default 0.01 for ``"default"``, 0 for the seeds' variants.
        glsl_numerics: ``"ssilvb_glsl"`` only: ``"ieee"`` (exact ``acos``, input precision), ``"mesa"``
            (Mesa's polynomial ``acos``; matches Mesa softpipe) or ``"mesa_mediump"`` (also llvmpipe's
            float16 ``mediump`` jitter). See :mod:`torch_ao.methods.bitmask_glsl`.
        **kwargs: :class:`~torch_ao.methods.base.ScreenSpaceAO` options (``slices``, ``steps``,
            ``preset``, ``radius``, ``fetch``, ``border``, ``azimuth``, ``jitter``, ``seed``,
            ``chunk_size``, ``recompute``, ``trainable``...). Unless ``chunk_size``/``recompute`` are
            given, each call picks them (see :meth:`auto_chunking`): cache-sized chunks of 16384
            pixels, recomputed in backward only when a soft gradient's graph would exceed
            ``graph_budget`` (1 GiB). ``azimuth`` defaults to ``"view"`` for ``"default"`` and
            ``"screen"`` for ``"hdrp"``.
    """

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

    def __init__(self, *, variant: str = "default", mode: str = "hard", tau: float = 0.25, rounding: str = "ceil",
                 weighting: str = "uniform", thickness=0.5, thickness_growth: float | None = None,
                 indirect: bool = False, bent_normals: bool = False, ambient=None, ambient_directions: int = 8,
                 azimuth: str | None = None, glsl_numerics: str = "ieee",
                 sector_epsilon: float | None = None, **kwargs) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
        if mode not in MODES:
            raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
        if rounding not in ROUNDINGS:
            raise ValueError(f"rounding: expected one of {ROUNDINGS}, got {rounding!r}")
        if weighting not in WEIGHTINGS:
            raise ValueError(f"weighting: expected one of {WEIGHTINGS}, got {weighting!r}")
        if isinstance(tau, bool) or not isinstance(tau, (int, float)) or not (tau > 0 and math.isfinite(tau)):
            raise ValueError(f"tau: expected a positive finite float, got {tau!r}")
        if isinstance(ambient_directions, bool) or not isinstance(ambient_directions, int) or ambient_directions < 1 \
                or SECTORS % ambient_directions:
            raise ValueError(f"ambient_directions: expected a divisor of {SECTORS}, got {ambient_directions!r}")
        if variant == "ssilvb_glsl":
            if weighting != "uniform":
                raise ValueError("weighting: the 'ssilvb_glsl' variant is the shader as written (uniform sectors)")
            if bent_normals or ambient is not None:
                raise ValueError("bent_normals/ambient: not part of the 'ssilvb_glsl' shader; use variant='default'")
        if glsl_numerics not in ("ieee", "mesa", "mesa_mediump"):
            raise ValueError(f"glsl_numerics: expected 'ieee', 'mesa' or 'mesa_mediump', got {glsl_numerics!r}")
        self.variant, self.glsl_numerics = variant, glsl_numerics
        if azimuth is None:
            azimuth = "screen" if variant in ("hdrp", "ssilvb_glsl") else "view"
        super().__init__(azimuth=azimuth, **kwargs)
        self.pattern_for(None)  # validate the variant's walk now (the base no longer calls it)
        self.mode, self.tau, self.rounding, self.weighting = mode, float(tau), rounding, weighting
        # Chosen per call (the mode may change after construction, e.g. fit's set_mode).
        self._auto_chunk = kwargs.get("chunk_size") is None and "recompute" not in kwargs
        self.want_indirect, self.want_bent = bool(indirect), bool(bent_normals)
        self.ambient_directions = ambient_directions
        if sector_epsilon is None:
            sector_epsilon = 0.01 if variant == "default" else 0.0
        if isinstance(sector_epsilon, bool) or not isinstance(sector_epsilon, (int, float)) or not 0 <= sector_epsilon < 1:
            raise ValueError(f"sector_epsilon: expected a float in [0, 1), got {sector_epsilon!r}")
        self.sector_epsilon = float(sector_epsilon)
        trainable = kwargs.get("trainable", True)
        make_parameter(self, "thickness", thickness, trainable=trainable, minimum=0.0)
        if self.thickness.dim() not in (0, 1, 4) or (self.thickness.dim() == 4 and self.thickness.shape[1] != 1):
            raise ValueError(f"thickness: expected a scalar, a (K,) table or a (B,1,H,W) map, got shape {tuple(self.thickness.shape)}")
        if thickness_growth is not None:
            make_parameter(self, "thickness_growth", thickness_growth, trainable=trainable, minimum=0.0)
        else:
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

    def graph_bytes(self, pixels: int) -> int:
        """Estimated autograd memory (bytes) of a soft walk over ``pixels`` query pixels kept whole."""
        per_sample = self.graph_bytes_per_sample_indirect if self.want_indirect else self.graph_bytes_per_sample
        return pixels * self.slices * 2 * self.steps * per_sample

    def auto_chunking(self, pixels: int) -> tuple[int | None, bool]:
        """``(chunk_size, recompute)`` for a frame of ``pixels`` (``B*H*W``) when the user gave neither.

        Walks go in cache-sized chunks of ``default_chunk`` pixels. With a soft gradient (soft or
        straight-through mode, autograd on), the whole graph is kept if :meth:`graph_bytes` is at most
        ``graph_budget`` (the walk runs once); otherwise each chunk of ``default_soft_chunk`` pixels
        (half that with ``indirect``) is recomputed in backward, which bounds the memory of
        forward+backward by one chunk whatever the frame size.
        """
        chunk = self.default_chunk if pixels > self.default_chunk else None
        if self.mode != "hard" and torch.is_grad_enabled() and self.graph_bytes(pixels) > self.graph_budget:
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
        return super().pattern_for(frame)

    def _thickness_kind(self) -> str:
        return {0: "scalar", 1: "object", 4: "map"}[self.thickness.dim()]

    def frame_buffers(self, gbuffer: GBuffer, normals: torch.Tensor) -> dict[str, torch.Tensor]:
        buffers = {}
        if self.want_indirect:
            if gbuffer.light is None:
                raise ValueError("gbuffer.light: indirect light needs a (B,3,H,W) direct-light buffer")
            buffers["light"] = gbuffer.light
            buffers["normals"] = normals
        kind = self._thickness_kind()
        if kind == "map":
            B, _, H, W = gbuffer.depth.shape
            t = self.thickness
            if t.shape[-2:] != (H, W) or t.shape[0] not in (1, B):
                raise ValueError(f"thickness: map of shape {tuple(t.shape)} does not match the G-buffer (B={B}, H={H}, W={W})")
            buffers["thickness"] = t.to(gbuffer.depth.dtype).expand(B, 1, H, W)
        elif kind == "object":
            if gbuffer.object_id is None:
                raise ValueError("gbuffer.object_id: a per-object thickness table needs an object_id buffer")
            buffers["object_id"] = gbuffer.object_id
        return buffers

    def _lookup(self) -> ThicknessLookup:
        return ThicknessLookup(self._thickness_kind(), self.thickness, self.thickness_growth)

    def accumulator(self, frame: Frame):
        ambient = self.ambient_colour if self._ambient_constant else self.ambient
        if self.variant == "ssilvb_glsl":
            from .bitmask_glsl import GLSLAccumulator

            return GLSLAccumulator(mode=self.mode, rounding=self.rounding, tau=self.tau, thickness=self._lookup(),
                                   indirect=self.want_indirect, slice_count=self.slices, frame=frame,
                                   jitter=self.jitter, numerics=self.glsl_numerics)
        return BitmaskAccumulator(variant=self.variant, mode=self.mode, rounding=self.rounding, tau=self.tau,
                                  weighting=self.weighting, thickness=self._lookup(), indirect=self.want_indirect,
                                  bent_normals=self.want_bent, ambient=ambient,
                                  ambient_directions=self.ambient_directions,
                                  sector_epsilon=self.sector_epsilon)

    def extra_repr(self) -> str:
        return (f"variant={self.variant!r}, mode={self.mode!r}, tau={self.tau}, rounding={self.rounding!r}, "
                f"weighting={self.weighting!r}, " + super().extra_repr())


class SSILVB(BitmaskAO):
    """Screen-space indirect lighting with visibility bitmask: :class:`BitmaskAO` with ``indirect=True``
    (outputs ``visibility`` and ``indirect``; the G-buffer needs ``light``)."""

    def __init__(self, *, indirect: bool = True, **kwargs) -> None:
        super().__init__(indirect=indirect, **kwargs)


def _functional(cls, gbuffer: GBuffer, radius, thickness, thickness_growth, kwargs) -> AOOutput:
    kwargs = dict(kwargs)
    kwargs.setdefault("trainable", False)
    tensors = {}
    for name, value in (("radius", radius), ("thickness", thickness), ("thickness_growth", thickness_growth)):
        if isinstance(value, torch.Tensor):
            tensors[name] = value
            kwargs[name] = value.detach()
        elif value is not None:
            kwargs[name] = value
    module = cls(**kwargs)
    for name, value in tensors.items():  # keep the caller's tensors (and their autograd graph)
        setattr(module, name, value)
    return module(gbuffer)


def bitmask_ao(gbuffer: GBuffer, *, radius=1.0, thickness=0.5, thickness_growth=None, **kwargs) -> AOOutput:
    """Functional :class:`BitmaskAO`: ``radius``/``thickness`` may be tensors that require grad."""
    return _functional(BitmaskAO, gbuffer, radius, thickness, thickness_growth, kwargs)


def ssilvb(gbuffer: GBuffer, *, radius=1.0, thickness=0.5, thickness_growth=None, **kwargs) -> AOOutput:
    """Functional :class:`SSILVB` (visibility and indirect light)."""
    return _functional(SSILVB, gbuffer, radius, thickness, thickness_growth, kwargs)
