"""Walking at a reduced resolution: decimate the G-buffer, walk the smaller frame, upsample depth-aware.

Engines run their AO at half resolution to cut its cost about 4x (XeGTAO's FAQ, the bitmask paper,
Godot, three.js). Here a method with ``resolution="half"`` (or a preset ``"high@half"``) does three steps:

1. :func:`downsample_gbuffer`: keep one texel of every ``f x f`` block, the top-left one, and give the
   smaller G-buffer a camera whose pixel ``(i, j)`` is the full-resolution pixel ``(f i, f j)``
   (intrinsics ``fx/f, fy/f, cx/f, cy/f``). The texel is *picked*, never averaged: an average of depths
   across an edge is a surface that does not exist (a floating occluder), and a min/max or checkerboard
   pick moves the chosen point off its pixel's centre by up to half a full pixel, which bends a tilted
   plane into a zigzag that occludes itself. With a fixed pick and the matching camera the smaller frame
   is the same scene seen with pixels ``f`` times larger, so planes stay planes and closed forms carry
   over. Normals (reconstructed at full resolution when the G-buffer has none, then picked), light, mask,
   ids, back-face depth and positions come from the same texel. The cost: an occluder thinner than ``f``
   pixels is seen only where it crosses a picked row or column.
2. The method walks the smaller G-buffer unchanged (a world radius covers ``1/f`` as many pixels; options
   in pixels, e.g. ``min_step_px``, are in the walk's pixels).
3. :func:`upsample`: a joint bilateral normalised convolution at full resolution (kornia's
   ``joint_bilateral_blur``, through :func:`torch_ao.denoise.normalized_filter`) of the walked values
   placed at their texels, guided by the full-resolution log-depth and normals, so a pixel takes its
   value from samples on its own surface and nothing bleeds across a depth edge. Differentiable in the
   values and the guide.
"""
from __future__ import annotations

import torch

from .camera import PinholeCamera
from .checks import check_choice
from .denoise import denoise_guide, normalized_filter
from .gbuffer import GBuffer

__all__ = ["RESOLUTIONS", "resolution_factor", "downsample_gbuffer", "upsample", "reduced_forward"]

#: resolution names and their decimation factor per axis
RESOLUTIONS: dict[str, int] = {"full": 1, "half": 2, "quarter": 4}

#: weight of the plain spatial filter added to the bilateral one: a pixel whose window holds no sample
#: on its surface (an isolated sliver thinner than the sampling grid) takes its neighbours' mean
#: instead of dividing by nothing; elsewhere it moves the value by at most this fraction
SPATIAL_FLOOR = 1e-4


def resolution_factor(resolution: str) -> int:
    """Decimation factor per axis of ``resolution`` (``"full"`` 1, ``"half"`` 2, ``"quarter"`` 4)."""
    return RESOLUTIONS[check_choice("resolution", resolution, tuple(RESOLUTIONS))]


def _pick(x: torch.Tensor | None, f: int) -> torch.Tensor | None:
    return None if x is None else x[..., ::f, ::f]


def downsample_gbuffer(gbuffer: GBuffer, factor: int, *, normals: torch.Tensor | None = None) -> GBuffer:
    """The G-buffer of every ``factor``-th texel per axis, ``(B,C,ceil(H/f),ceil(W/f))``, with the matching
    camera (see the module docstring for why a fixed pick).

    ``normals``: ``(B,3,H,W)`` view-space normals to pick (default: the G-buffer's own, if any; pass
    ``gbuffer.view_normals(...)`` to reconstruct them at full resolution first).
    """
    f = int(factor)
    if f == 1:
        return gbuffer
    cam = gbuffer.camera
    K = cam.intrinsics.clone()
    K[:, :2, :] = K[:, :2, :] / f  # fx, fy, cx, cy; the skew stays 0
    B, _, H, W = gbuffer.depth.shape
    camera = PinholeCamera(K, -(-H // f), -(-W // f))
    return GBuffer(depth=_pick(gbuffer.depth, f), camera=camera,
                   normals=_pick(gbuffer.normals if normals is None else normals, f),
                   light=_pick(gbuffer.light, f), mask=_pick(gbuffer.valid, f), object_id=_pick(gbuffer.object_id, f),
                   backface_depth=_pick(gbuffer.backface_depth, f), position=_pick(gbuffer.position, f))


def upsample(values: torch.Tensor, low_valid: torch.Tensor, gbuffer: GBuffer, factor: int, *,
             guide: torch.Tensor | None = None, fill: float | torch.Tensor = 0.0) -> torch.Tensor:
    """Full-resolution ``(B,C,H,W)`` of values walked on :func:`downsample_gbuffer`'s frame.

    Args:
        values: ``(B,C,h,w)`` per low-resolution texel (``h = ceil(H/f)``, ``w = ceil(W/f)``).
        low_valid: ``(B,1,h,w)`` bool, the low-resolution frame's valid texels (the only samples used).
        gbuffer: the full-resolution G-buffer (its valid pixels get values; the guide comes from it).
        factor: ``f``, the decimation factor per axis.
        guide: ``(B,G,H,W)`` normalised guide (default :func:`~torch_ao.denoise.denoise_guide` of
            ``gbuffer``: log-depth / 0.05 and normals / 0.3, range sigma 1).
        fill: value of background pixels (a number or a ``(B,C,H,W)`` tensor).

    The spatial kernel is ``2f+1`` pixels wide with sigma ``0.75 f`` pixels, so every pixel's window
    holds the samples on both sides of it.
    """
    f = int(factor)
    B, C = values.shape[:2]
    H, W = gbuffer.depth.shape[-2:]
    if values.shape[-2:] != (-(-H // f), -(-W // f)) or low_valid.shape != (B, 1, *values.shape[-2:]):
        raise ValueError(f"values/low_valid: expected (B,C,{-(-H // f)},{-(-W // f)}) and (B,1,...) for a {H}x{W} "
                         f"frame at 1/{f}, got {tuple(values.shape)} and {tuple(low_valid.shape)}")
    placed = values.new_zeros(B, C, H, W)
    placed[..., ::f, ::f] = values
    samples = torch.zeros_like(gbuffer.valid)
    samples[..., ::f, ::f] = low_valid
    if guide is None:
        guide = denoise_guide(gbuffer)
    kernel, sigma = 2 * f + 1, 0.75 * f
    num, den = normalized_filter(placed, samples, guide, kernel_size=kernel, sigma_space=sigma)
    num_s, den_s = normalized_filter(placed, samples, torch.zeros_like(guide[:, :1]), kernel_size=kernel,
                                     sigma_space=sigma)
    out = (num + SPATIAL_FLOOR * num_s) / (den + SPATIAL_FLOOR * den_s).clamp_min(1e-30)
    fill = torch.as_tensor(fill, dtype=out.dtype, device=out.device)
    # background, and a pixel with no sample at all in its window (background all around it), get fill
    return torch.where(gbuffer.valid & (den_s > 0), out, fill)


def reduced_forward(forward, gbuffer: GBuffer, factor: int, normals: torch.Tensor):
    """``forward`` (a module's full-resolution call ``GBuffer -> AOOutput``) on the G-buffer decimated by
    ``factor``, its outputs upsampled to ``gbuffer``'s size: visibility (background 1), indirect and
    ambient light (background 0) and bent normals (renormalised; background: ``normals``, the
    ``(B,3,H,W)`` full-resolution normals the walk's normals are picked from)."""
    from .methods.base import AOOutput

    low = downsample_gbuffer(gbuffer, factor, normals=normals)
    out = forward(low)
    guide = denoise_guide(gbuffer, normals=normals)

    def up(x, fill):
        return None if x is None else upsample(x, low.valid, gbuffer, factor, guide=guide, fill=fill)

    bent = up(out.bent_normal, normals)
    if bent is not None:
        bent = torch.where(gbuffer.valid, torch.nn.functional.normalize(bent, dim=1, eps=1e-12), normals)
    return AOOutput(visibility=up(out.visibility, 1.0), indirect=up(out.indirect, 0.0), bent_normal=bent,
                    ambient=up(out.ambient, 0.0))
