"""The screen-space ground truth: what a depth buffer of a given thickness occludes, by brute force.

For every valid pixel ``P`` (view-space position, unit normal ``n`` facing the camera) this traces many
rays ``P + t w`` over the hemisphere around ``n`` and tests points along each ray against the depth
buffer itself, treated as surfaces of thickness ``T``: a point at view-space depth ``-z`` that projects
to screen position ``(u, v)`` is inside the occluder when

    ``front(u, v) <= -z <= front(u, v) + T(u, v)``

with ``front`` the depth buffer and ``T`` the thickness at ``(u, v)`` (both fetched the way the
screen-space methods fetch: perspective-correct bilinear, or the nearest texel). A ray is blocked when
any of its points ``t in (0, R]`` is inside. Then

* cosine-weighted visibility ``(1/pi) int_H V cos(w, n) dw`` (cosine-distributed rays), and
* uniform-weighted visibility ``(1/(2 pi)) int_H V dw`` (uniformly distributed rays),

each with its per-pixel Monte Carlo standard error (independent groups of stratified samples, as the
ray tracer of :mod:`torch_ao.reference` reports it).

What counts as an occluder, and what does not:

* Points that project outside the frame (for bilinear fetch: outside the pixel centres' rectangle
  ``[0, W-1] x [0, H-1]``, as the methods' ``border="drop"``), or behind the camera, occlude nothing:
  **rays leaving the screen are unoccluded**.
* Background texels (and, with bilinear fetch, any footprint touching one) occlude nothing; with
  nearest fetch neither does the pixel's own texel (as in the methods' walk).
* Nearest fetch makes the depth buffer a staircase of flat tiles, which occludes rays that graze a
  slanted surface; perspective-correct bilinear fetch reproduces planes exactly (the default).
* The thickness is measured along the view axis at the sample, ``depth + T``. (Bitmask AO pushes each
  sample along the *centre pixel's* view vector instead; the two agree to first order away from the
  image border.)

It converges, as rays and steps grow, to the visibility of the depth buffer's surfaces of that
thickness: the quantity every screen-space method approximates for the same thickness model. The
ray-traced reference minus this is what the screen cannot know (hidden and off-screen geometry, the
true thickness); a method minus this is what the method adds (its bias and noise). See
:func:`split_error`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Union

import torch
import torch.nn.functional as F

from .checks import check_bool, check_choice, check_float, check_int
from .gbuffer import GBuffer
from .metrics import error_metrics
from .reference import sampling
from .reference.render import _group_stats
from .walk.fetch import NEAREST_TIE, continuous_cell_image, continuous_cells

__all__ = ["FETCHES", "SCREEN_REACH", "ScreenTruth", "screen_space_truth", "thickness_map", "ErrorSplit", "split_error", "ray_steps"]

Thickness = Union[float, torch.Tensor, Callable[[GBuffer], torch.Tensor]]
_COSINE_STREAM, _UNIFORM_STREAM, _STEP_STREAM = 32, 48, 64
FETCHES = ("bilinear", "nearest", "edge_aware")
#: How far rays go (in units of ``R``) with ``bound="screen"``.
SCREEN_REACH = 4.0
_BIG = 1e30  # stands in for an infinite thickness inside interpolation (inf * 0 would be NaN)


@dataclass
class ScreenTruth:
    """A screen-space ground truth. Images ``(B,1,H,W)``; background pixels have visibility 1, error 0.

    ``visibility``/``stderr``: cosine-weighted; ``uniform``/``uniform_stderr``: uniform-weighted (``None``
    unless asked for). ``steps`` ``(B,1,H,W)`` int: the points tested per ray at each pixel.
    """

    visibility: torch.Tensor
    stderr: torch.Tensor
    uniform: torch.Tensor | None
    uniform_stderr: torch.Tensor | None
    steps: torch.Tensor
    radius: float
    rays: int
    seed: int


def thickness_map(gbuffer: GBuffer, thickness: Thickness = math.inf,
                  backface_depth: torch.Tensor | None = None) -> float | torch.Tensor:
    """The thickness ``T`` of every texel, in world units: a float, or a ``(B,1,H,W)`` map.

    Args:
        gbuffer: the views.
        thickness: a number (``inf``: the horizon assumption, everything behind a surface is solid),
            a 0-d tensor, a ``(K,)`` table indexed by ``gbuffer.object_id`` (per object), a ``(B,1,H,W)``
            map, or a callable ``gbuffer -> (B,1,H,W)`` map (a new thickness model plugs in here).
        backface_depth: optional ``(B,1,H,W)`` depth of the back surface along each camera ray (a
            front-face-culled depth pass, or the tracer's exit depth); overrides ``thickness``:
            ``T = backface_depth - depth`` (``inf``/``nan`` back faces are infinitely thick).
    """
    B, _, H, W = gbuffer.depth.shape
    depth = gbuffer.depth
    if backface_depth is not None:
        if not isinstance(backface_depth, torch.Tensor) or tuple(backface_depth.shape) != (B, 1, H, W):
            raise ValueError(f"backface_depth: expected a tensor of shape {(B, 1, H, W)}, "
                             f"got {getattr(backface_depth, 'shape', type(backface_depth).__name__)}")
        back = torch.nan_to_num(backface_depth.to(depth), nan=math.inf)
        t = torch.where(gbuffer.valid, (back - gbuffer.safe_depth).clamp_min(0), torch.zeros_like(depth))
        return _finite_map("backface_depth", t)
    if callable(thickness) and not isinstance(thickness, torch.Tensor):
        t = thickness(gbuffer)
        if not isinstance(t, torch.Tensor) or tuple(t.shape) != (B, 1, H, W):
            raise ValueError(f"thickness: a callable must return a (B,1,H,W) = {(B, 1, H, W)} tensor, "
                             f"got {getattr(t, 'shape', type(t).__name__)}")
        return _finite_map("thickness", t.to(depth))
    if isinstance(thickness, torch.Tensor):
        t = thickness.detach().to(depth)
        if t.dim() == 0:
            return check_float("thickness", float(t), 0.0, finite=False)
        if t.dim() == 1:
            if gbuffer.object_id is None:
                raise ValueError("thickness: a (K,) per-object table needs gbuffer.object_id")
            ids = gbuffer.object_id.clamp_max(t.shape[0] - 1)
            return _finite_map("thickness", t[ids])
        if tuple(t.shape) != (B, 1, H, W):
            raise ValueError(f"thickness: expected a number, a (K,) table or a {(B, 1, H, W)} map, got {tuple(t.shape)}")
        return _finite_map("thickness", t)
    return check_float("thickness", thickness, 0.0, finite=False)


def _finite_map(name: str, t: torch.Tensor) -> torch.Tensor:
    if bool(torch.isnan(t).any()) or bool((t < 0).any()):
        raise ValueError(f"{name}: expected thicknesses >= 0 (no NaN)")
    return t.clamp_max(_BIG)


def ray_steps(depth: torch.Tensor, fx: torch.Tensor, radius: float, step_px: float, min_steps: int,
              max_steps: int) -> torch.Tensor:
    """Points per ray ``(N,)`` int for pixels at ``depth (N,)`` with focal length ``fx (N,)`` (pixels):
    about one every ``step_px`` pixels of the radius' projected length ``R fx / depth``, within
    ``[min_steps, max_steps]``."""
    n = torch.ceil(radius * fx / (depth * step_px))
    return n.clamp(min_steps, max_steps).long()


@torch.no_grad()
def screen_space_truth(
    gbuffer: GBuffer,
    radius: float = 1.0,
    thickness: Thickness = math.inf,
    *,
    backface_depth: torch.Tensor | None = None,
    rays: int = 1024,
    min_steps: int = 32,
    max_steps: int = 256,
    step_px: float = 0.5,
    uniform: bool = False,
    fetch: str = "bilinear",
    edge_ratio: float | None = None,
    seed: int = 0,
    chunk_points: int = 1 << 21,
    where: torch.Tensor | None = None,
    bound: str = "sphere",
) -> ScreenTruth:
    """Brute-force visibility of the depth buffer's surfaces of thickness ``thickness`` within ``radius``.

    Args:
        gbuffer: the views (depth, camera; normals given or reconstructed from depth).
        radius: ``R``, the ray length in world units (> 0, finite).
        thickness, backface_depth: the thickness model, see :func:`thickness_map`.
        rays: rays per pixel for each weighting (>= 2, with a divisor in [2, 16] for the standard error).
        min_steps, max_steps, step_px: points tested per ray, equally spaced in ``t`` with one random
            offset ``u`` per ray (``t_k = R (k + u) / (n - 1 + u)``, ``k < n``: the last at ``R``), ``n`` = one
            per ``step_px`` pixels of the radius' projected length ``R f / depth``, within
            ``[min_steps, max_steps]`` (raise ``min_steps`` for thin occluders: a slab of thickness ``T`` is
            found surely once ``R / n`` is well below ``T``).
        uniform: also estimate uniform-weighted visibility (another ``rays`` rays per pixel).
        fetch: how the depth buffer becomes surfaces: ``"bilinear"`` (perspective-correct, as the
            methods' default fetch: across a depth edge it interpolates a "skirt" joining the near and far
            surface, which occludes rays that pass behind the near one), ``"nearest"`` (flat tiles), or
            ``"edge_aware"`` (bilinear inside every 2x2 cell that is one surface, the nearest texel in the
            others: no skirts; see ``edge_ratio``).
        edge_ratio: ``None`` (default): ``"edge_aware"`` finds edges as the methods' walk does
            (:func:`~torch_ao.walk.fetch.continuous_cell_image`: a pair of texels is one surface when their
            depths are within 2 % or their jump continues a neighbouring pair's, so a plane at any angle and a
            crease stay bilinear); a float (> 1): a cell is an edge when ``max/min`` of its depths exceeds it,
            whatever its neighbours.
        seed: the random numbers are a hash of ``(seed, pixel, ray)``: reproducible whatever the chunking.
        chunk_points: ray points tested at once (memory: about 100 bytes each).
        bound: which ray points count: ``"sphere"`` (the definition: within distance ``R`` of the pixel) or
            ``"screen"`` (a diagnostic: every point up to ``SCREEN_REACH * R`` along the ray that projects within
            ``R fx / depth`` pixels of the pixel, whatever its distance: what a screen-space walk over the
            projected radius sees when it counts each sample's occluder whole).
        where: optional ``(B,1,H,W)`` bool: estimate only these pixels (the others read as background:
            visibility 1, error 0); every valid pixel still occludes.
    Returns:
        a :class:`ScreenTruth` of ``(B,1,H,W)`` images.
    """
    radius = check_float("radius", radius, 0.0, open_minimum=True)
    rays = check_int("rays", rays, 2)
    groups = sampling.choose_groups(rays)
    min_steps = check_int("min_steps", min_steps, 1)
    max_steps = check_int("max_steps", max_steps, min_steps)
    step_px = check_float("step_px", step_px, 0.0, open_minimum=True)
    check_bool("uniform", uniform)
    check_choice("fetch", fetch, FETCHES)
    check_choice("bound", bound, ("sphere", "screen"))
    length = radius * (SCREEN_REACH if bound == "screen" else 1.0)
    if edge_ratio is not None:
        edge_ratio = check_float("edge_ratio", edge_ratio, 1.0, open_minimum=True)
    seed = check_int("seed", seed, 0)
    chunk_points = check_int("chunk_points", chunk_points, 1)
    T = thickness_map(gbuffer, thickness, backface_depth)
    if where is not None and (not isinstance(where, torch.Tensor) or where.dtype != torch.bool
                              or where.shape != gbuffer.depth.shape):
        raise ValueError(f"where: expected a bool tensor of shape {tuple(gbuffer.depth.shape)}, got "
                         f"{getattr(where, 'dtype', type(where).__name__)} {tuple(getattr(where, 'shape', ()))}")
    queried = gbuffer.valid if where is None else gbuffer.valid & where

    B, _, H, W = gbuffer.depth.shape
    dtype = torch.float32
    device = gbuffer.depth.device
    valid = gbuffer.valid
    depth = gbuffer.safe_depth.to(dtype)
    # Channels sampled at each ray point: inverse depth (interpolated: perspective-correct depth), -_BIG on
    # background so that any footprint touching it comes out negative (no occluder), and a thickness map.
    inv = torch.where(valid, depth.reciprocal(), torch.full_like(depth, -_BIG))
    planes = [inv]
    if isinstance(T, torch.Tensor):
        planes.append(T.to(dtype))
    image = torch.cat(planes, 1)
    cells = _continuous_cells(inv, edge_ratio) if fetch == "edge_aware" else None
    scalar_T = None if isinstance(T, torch.Tensor) else min(float(T), _BIG)

    camera = gbuffer.camera.to(dtype=dtype)
    pos = gbuffer.positions().to(dtype)
    nrm = gbuffer.view_normals().to(dtype)
    key_all = torch.arange(B * H * W, device=device).view(B, H, W)

    cos_out = torch.ones(B, H * W, dtype=dtype, device=device)
    cos_se = torch.zeros_like(cos_out)
    uni_out = torch.ones_like(cos_out) if uniform else None
    uni_se = torch.zeros_like(cos_out) if uniform else None
    steps_img = torch.zeros(B, H * W, dtype=torch.long, device=device)
    for b in range(B):
        idx = queried[b, 0].reshape(-1).nonzero()[:, 0]
        if idx.numel() == 0:
            continue
        P = pos[b].reshape(3, -1)[:, idx].T  # (N,3)
        n = nrm[b].reshape(3, -1)[:, idx].T
        fx, fy, cx, cy = (float(v[b]) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
        focal = torch.full_like(P[:, 2], max(fx, fy))
        nsteps = ray_steps(-P[:, 2], focal, length, step_px, min_steps, max_steps)
        disc = radius * focal / -P[:, 2] if bound == "screen" else None  # (N,) pixels
        steps_img[b, idx] = nsteps
        # Pixels sorted by step count, so a chunk marches (nearly) the steps each of its pixels needs.
        order = torch.argsort(nsteps, stable=True)
        proj = (fx, fy, cx, cy, W, H)
        start, total = 0, order.numel()
        while start < total:
            m = _chunk_pixels(nsteps, order, start, rays, chunk_points)
            sel = order[start:start + m]
            start += m
            s_max = int(nsteps[sel].max())
            key = key_all[b].reshape(-1)[idx[sel]]
            for stream, out, se in ((_COSINE_STREAM, cos_out, cos_se), (_UNIFORM_STREAM, uni_out, uni_se)):
                if out is None:
                    continue
                u1, u2 = sampling.stratified_square(key, rays, groups, seed, stream, dtype)
                local = (sampling.cosine_hemisphere if stream == _COSINE_STREAM else sampling.uniform_hemisphere)(u1, u2)
                t_axis, b_axis = sampling.frame(n[sel])
                w = (local[..., :1] * t_axis[:, None] + local[..., 1:2] * b_axis[:, None]
                     + local[..., 2:] * n[sel][:, None])  # (m, rays, 3)
                jitter = sampling.uniform(key[:, None] * rays + torch.arange(rays, device=device), seed,
                                          stream + _STEP_STREAM, dtype)
                surfaces = (image[b:b + 1], None if cells is None else cells[b:b + 1], fetch, scalar_T)
                open_ = _unblocked(surfaces, P[sel], n[sel], w, jitter, nsteps[sel], s_max, length, proj,
                                   None if disc is None else disc[sel])
                mean, err = _group_stats(open_.to(dtype), groups)
                out[b, idx[sel]], se[b, idx[sel]] = mean, err

    def img(x):
        return None if x is None else x.view(B, 1, H, W)

    return ScreenTruth(img(cos_out), img(cos_se), img(uni_out), img(uni_se), img(steps_img), radius, rays, seed)


def _chunk_pixels(nsteps, order, start, rays, chunk_points) -> int:
    """How many pixels from ``order[start:]`` (ascending step counts) fit ``chunk_points`` points."""
    total = order.numel()
    m = max(1, chunk_points // (rays * int(nsteps[order[start]])))
    while m > 1:
        last = int(nsteps[order[min(start + m, total) - 1]])
        if m * rays * last <= chunk_points:
            break
        m = max(1, chunk_points // (rays * last))
    return m


def _continuous_cells(inv: torch.Tensor, edge_ratio: float | None) -> torch.Tensor:
    """``(B,1,H-1,W-1)`` float, 1 where the 2x2 cell of texels ``(i..i+1, j..j+1)`` is one surface (``inv > 0``
    where valid): :func:`continuous_cell_image` (``edge_ratio=None``), else all four valid and ``max(depth)
    <= edge_ratio * min(depth)`` (:func:`continuous_cells`)."""
    if edge_ratio is None:
        return continuous_cell_image(inv).to(inv.dtype)
    taps = torch.stack((inv[..., :-1, :-1], inv[..., :-1, 1:], inv[..., 1:, :-1], inv[..., 1:, 1:]), -1)
    return continuous_cells(taps, edge_ratio).to(inv.dtype)


def _fetch(surfaces, grid: torch.Tensor, size: tuple[int, int]):
    """The sampled channels ``(C, ...)`` at ``grid`` ``(..., 2)`` (grid_sample coordinates) and where the
    nearest texel was used (``None``: nowhere; ``True``: everywhere; else a bool tensor)."""
    image, cells, fetch, _ = surfaces
    H, W = size
    shape = grid.shape[:-1]
    flat = grid.view(1, -1, shape[-1], 2)

    def sample(img, g, mode):
        return F.grid_sample(img, g, mode=mode, padding_mode="border", align_corners=True)[0].view(-1, *shape)

    def nearest(img):  # a tie between two texels read as the walk does: the lower one (walk.fetch.NEAREST_TIE)
        tie = flat.new_tensor((2 * NEAREST_TIE / max(W - 1, 1), 2 * NEAREST_TIE / max(H - 1, 1)))
        return sample(img, flat - tie, "nearest")

    if fetch == "nearest":
        return nearest(image), True
    if fetch != "edge_aware":
        return sample(image, flat, fetch), None
    # The cell holding screen point u is floor(u): the nearest cell centre to u - 1/2.
    to_cells = flat.new_tensor(((W - 1) / max(W - 2, 1), (H - 1) / max(H - 2, 1)))
    shift = flat.new_tensor((1 / max(W - 2, 1), 1 / max(H - 2, 1)))
    smooth = sample(cells, (flat + 1) * to_cells - 1 - shift, "nearest")[0] > 0.5
    return torch.where(smooth, sample(image, flat, "bilinear"), nearest(image)), ~smooth


def _unblocked(surfaces, P, n, w, jitter, nsteps, s_max, radius, proj, disc=None) -> torch.Tensor:
    """``(m, rays)`` bool: True where no point of the ray ``P + t w`` lies inside the occluders.

    ``surfaces`` = ``(image, cells, fetch, scalar_T)``: ``image`` ``(1,C,H,W)`` the sampled channels
    (inverse depth, ``-_BIG`` on background; then the thickness map if any), ``cells`` the
    :func:`_continuous_cells` of ``"edge_aware"`` fetch; ``P``/``n`` ``(m,3)``, ``w`` ``(m,rays,3)`` unit
    directions, ``jitter`` ``(m,rays)`` step offsets in [0,1), ``nsteps`` ``(m,)`` points per ray
    (``<= s_max``; the steps beyond a pixel's own count are masked out); ``radius`` the ray length;
    ``disc`` ``(m,)`` optional: only points within this many pixels of the pixel count.
    """
    fx, fy, cx, cy, W, H = proj
    k = torch.arange(s_max, device=P.device, dtype=P.dtype)
    ns = nsteps.to(P.dtype)[:, None, None]
    # Spacing R / (n - 1 + u) from u times it: the last point is exactly at R, so an infinitely thick
    # occluder reached within R is always found.
    j = jitter[..., None]
    t = (k + j) * (radius / (ns - 1 + j))  # (m, rays, s)
    # Origin offset along the normal against self-intersection on float noise (as the ray tracer does).
    o = P + n * (1e-5 * -P[:, 2:3])
    dz = torch.addcmul(-o[:, 2, None, None], t, w[..., 2, None], value=-1.0)  # depth -z of each point
    rz = dz.clamp_min(1e-30).reciprocal_()
    # grid_sample with align_corners=True puts pixel centre 0 at -1 and W-1 at +1.
    ax, ay = 2 * fx / max(W - 1, 1), 2 * fy / max(H - 1, 1)
    bx, by = 2 * cx / max(W - 1, 1) - 1, 2 * cy / max(H - 1, 1) - 1
    grid = torch.empty(*t.shape, 2, dtype=t.dtype, device=t.device)
    gx, gy = grid[..., 0], grid[..., 1]
    torch.addcmul(o[:, 0, None, None], t, w[..., 0, None], out=gx).mul_(rz).mul_(ax).add_(bx)
    torch.addcmul(o[:, 1, None, None], t, w[..., 1, None], out=gy).mul_(rz).mul_(-ay).add_(by)
    inside = (dz > 0) & (gx.abs() <= 1) & (gy.abs() <= 1)
    own_gx = (o[:, 0] / -o[:, 2] * ax + bx)[:, None, None]  # the pixel itself, in grid coordinates
    own_gy = (o[:, 1] / o[:, 2] * ay + by)[:, None, None]
    if int(nsteps.min()) < s_max:
        inside &= k < ns
    if disc is not None:
        du = (gx - own_gx) * ((W - 1) / 2)
        dv = (gy - own_gy) * ((H - 1) / 2)
        inside &= du.square_() + dv.square_() <= disc.square()[:, None, None]
    sampled, nearest = _fetch(surfaces, grid, (H, W))
    if nearest is not None:
        # The pixel's own texel never occludes through a nearest fetch (as in the methods' walk): its flat
        # tile would hide every ray that leaves a slanted surface away from the camera.
        def texel(g, size):
            return torch.round((g + 1) * ((size - 1) / 2))
        own = (texel(gx, W) == texel(own_gx, W)) & (texel(gy, H) == texel(own_gy, H))
        inside &= ~own if nearest is True else ~(own & nearest)
    inv = sampled[0]  # <= 0 wherever a background texel takes part
    # Behind the front surface: dz >= 1/inv; in front of the back one: dz - T < 1/inv (inv > 0). The slab is
    # half-open, [front, front + T), so that zero thickness occludes nothing whatever the rounding of dz * inv.
    hit = inside & (dz * inv >= 1)
    scalar_T = surfaces[3]
    if scalar_T is None:
        hit &= (dz - sampled[1]) * inv < 1
    elif scalar_T < _BIG:
        hit &= (dz - scalar_T) * inv < 1
    return ~hit.any(-1)


# ------------------------------------------------------------------------------------------ error split
@dataclass
class ErrorSplit:
    """The error of one method on one view, split in two (metrics dicts of :func:`error_metrics` with
    ``bias``, the mean signed error, added).

    ``screen``: the screen-space truth against the ray-traced reference (what the screen cannot know:
    hidden and off-screen geometry, the thickness model). ``estimator``: the method against the
    screen-space truth (what the method adds: bias and noise). ``total``: the method against the
    reference. ``truth_stderr``: the truth's mean per-pixel standard error (the noise floor of
    ``estimator``).
    """

    screen: dict
    estimator: dict
    total: dict
    truth_stderr: float


def split_error(method: torch.Tensor, truth: ScreenTruth | torch.Tensor, reference: torch.Tensor,
                valid: torch.Tensor | None = None) -> list[ErrorSplit]:
    """One :class:`ErrorSplit` per view of ``(B,1,H,W)`` images: the method's visibility, the
    screen-space truth (a :class:`ScreenTruth` or its visibility) and the ray-traced reference AO,
    on ``valid`` pixels ``(B,1,H,W)`` bool (default all)."""
    t = truth.visibility if isinstance(truth, ScreenTruth) else truth
    se = truth.stderr if isinstance(truth, ScreenTruth) else torch.zeros_like(t)
    for name, x in (("truth", t), ("reference", reference)):
        if not isinstance(x, torch.Tensor) or x.shape != method.shape:
            raise ValueError(f"{name}: expected shape {tuple(method.shape)} (that of the method), got "
                             f"{getattr(x, 'shape', type(x).__name__)}")
    if valid is None:
        valid = torch.ones_like(method, dtype=torch.bool)
    out = []
    for b in range(method.shape[0]):
        sl = slice(b, b + 1)
        v = valid[sl]
        out.append(ErrorSplit(
            screen=_metrics(t[sl], reference[sl], v),
            estimator=_metrics(method[sl], t[sl], v),
            total=_metrics(method[sl], reference[sl], v),
            truth_stderr=float(se[sl][v].mean()) if bool(v.any()) else 0.0,
        ))
    return out


def _metrics(prediction, target, valid) -> dict:
    """:func:`error_metrics` plus ``bias``, the mean signed error (negative: too much occlusion)."""
    bias = float((prediction - target)[valid].mean()) if bool(valid.any()) else 0.0
    return {**error_metrics(prediction, target, valid), "bias": bias}
