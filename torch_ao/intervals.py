"""Exact geometry of a slice's occluders: each sample's occluder segment, clipped to the radius, and the
exact measure of the union of their angular intervals.

The 32-sector masks of the bitmask paper quantise every interval: with ``ceil`` each tiny interval
becomes a whole sector, so many fine steps add up to many extra sectors and the estimate *drifts* as
steps are added. :func:`union_measure` instead sorts a slice's intervals and sweeps them, adding for
each the weighted measure of the part not yet covered (a closed form for the cosine weight): no
quantisation, and differentiable almost everywhere (through the sort's permutation and the running
maximum) without a temperature.

Occluder segments live in the slice plane, in coordinates ``(view, tangent) = (delta . V, delta . sT)``
of the offset ``delta`` from the pixel ``P`` (``V`` toward the camera, ``s`` the side). A sample at the
front point ``F`` occludes the directions between ``F`` and its back point ``B`` (the thickness model
says how far behind): :func:`back_point` gives ``B``, :func:`clip_to_sphere` clips the segment ``F -> B``
to the sphere ``|x| <= R`` of the AO radius (the reference AO counts only occluders within ``R``).
"""
from __future__ import annotations

from typing import Callable

import torch

__all__ = ["THICKNESS_DIRECTIONS", "back_point", "clip_to_sphere", "sphere_stretch", "union_measure"]

#: ``"view"``: the back point is ``F - t V`` (the centre pixel's view vector: the bitmask paper and both
#: published shaders); ``"depth"``: ``F`` pushed along its own camera ray to depth ``depth_F + t`` (what a
#: depth-buffer surface of thickness ``t``, or a back-face depth layer, is)
THICKNESS_DIRECTIONS = ("view", "depth")


def back_point(along_view: torch.Tensor, along_tangent: torch.Tensor, thickness: torch.Tensor, direction: str, *,
               pixel_distance: torch.Tensor | None = None, sample_depth: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Slice coordinates ``(view, tangent)`` ``(rows,)`` of the back point of the occluder at
    ``(along_view, along_tangent)`` with ``thickness`` (world units, 0-d or ``(rows,)``).

    ``direction="depth"`` needs ``pixel_distance`` ``|P|`` and ``sample_depth`` ``depth_F`` ``(rows,)``: with
    ``k = t / depth_F``, ``B = F (1 + k)`` in camera coordinates, so (as ``P . V = -|P|`` and ``P . T = 0``)
    ``B_view = along_view + k (along_view - |P|)`` and ``B_tangent = along_tangent (1 + k)``.
    """
    if direction == "view":
        return along_view - thickness, along_tangent
    k = thickness / sample_depth
    return along_view + k * (along_view - pixel_distance), along_tangent * (1 + k)


def clip_to_sphere(fv: torch.Tensor, ft: torch.Tensor, bv: torch.Tensor, bt: torch.Tensor, radius: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The part of the segment from ``F = (fv, ft)`` to ``B = (bv, bt)`` ``(rows,)`` inside ``|x| <= radius``.

    Points ``F + u (B - F)``, ``u`` in ``[0, 1]``, are inside where ``a u^2 + 2 b u + c <= 0`` with
    ``a = |B - F|^2``, ``b = F . (B - F)``, ``c = |F|^2 - R^2``; the clipped ends are at
    ``u = clamp((-b -+ sqrt(b^2 - a c)) / a, 0, 1)``. Returns the clipped ends and ``inside`` ``(rows,)``
    (False where the segment misses the sphere: its clipped ends are then meaningless).
    """
    ev, et = bv - fv, bt - ft
    a = ev * ev + et * et
    b = fv * ev + ft * et
    c = fv * fv + ft * ft - radius * radius
    disc = b * b - a * c
    degenerate = a <= 1e-30 * (fv * fv + ft * ft).clamp_min(1e-30)  # a point occluder (zero thickness)
    hit = (disc > 0) & ~degenerate
    safe_a = torch.where(hit, a, torch.ones_like(a))
    root = torch.sqrt(torch.where(hit, disc, torch.ones_like(disc)))
    u0 = ((-b - root) / safe_a).clamp(0.0, 1.0)
    u1 = ((-b + root) / safe_a).clamp(0.0, 1.0)
    inside = torch.where(degenerate, c <= 0, hit & (u1 > u0))
    u0 = torch.where(hit, u0, torch.zeros_like(u0))
    u1 = torch.where(hit, u1, torch.ones_like(u1))
    return fv + u0 * ev, ft + u0 * et, fv + u1 * ev, ft + u1 * et, inside


def sphere_stretch(distance: torch.Tensor, radius, cap: float = 10.0) -> torch.Tensor:
    """``(N,)`` factor by which the screen extent of the sphere ``|x - P| <= R`` along a slice exceeds the
    projection of ``R`` along the slice tangent at ``P`` (``distance = |P|``, the pixel's distance to the
    camera): ``1 / sqrt(1 - (R / |P|)^2)``, at most ``cap``.

    A point ``P + a V + b T`` lies on the camera ray of ``P + T b |P| / (|P| - a)``; over the circle
    ``a^2 + b^2 = R^2`` the largest ``b |P| / (|P| - a)`` is ``R / sqrt(1 - R^2 / |P|^2)`` (the tangent from
    the camera). Occluders nearer the camera than ``P`` (``a > 0``) within ``R`` reach that far on screen.
    """
    ratio = (torch.as_tensor(radius, dtype=distance.dtype, device=distance.device) / distance).square()
    return (1 - ratio).clamp_min(1 / (cap * cap)).rsqrt()


def union_measure(start: torch.Tensor, width: torch.Tensor, size: float,
                  measure: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Exact measure ``(N, 1)`` of the union of the intervals ``[start, start + width]`` ``(N, M)`` clipped
    to ``[0, size]`` (a width ``<= 0`` is empty), under ``measure``: ``x -> mu([0, x])`` for ``(N, M)``
    positions, nondecreasing (default: the length, ``mu([0, x]) = x``).

    Sorted by start, interval ``j`` adds ``mu([max(lo_j, M_{j-1}), max(hi_j, M_{j-1})])`` with ``M_{j-1}``
    the largest end before it: the part of it not yet covered. Cost ``O(M log M)`` per row.
    """
    live = width > 0
    lo = torch.where(live, start.clamp(0.0, size), torch.zeros_like(start))
    hi = torch.where(live, (start + width).clamp(0.0, size), torch.zeros_like(start))
    order = torch.argsort(lo.detach(), dim=1)
    lo, hi = lo.gather(1, order), hi.gather(1, order)
    reach = torch.cummax(hi, dim=1).values
    before = torch.cat((torch.zeros_like(reach[:, :1]), reach[:, :-1]), 1)
    a, b = torch.maximum(lo, before), torch.maximum(hi, before)
    if measure is None:
        return (b - a).sum(1, keepdim=True)
    return (measure(b) - measure(a)).sum(1, keepdim=True)
