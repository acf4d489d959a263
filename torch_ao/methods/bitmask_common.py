"""What the visibility-bitmask variants share: sector weights and the slice / sample / finish context.

:class:`SectorAccumulator` is the bitmask paper's loop, read top to bottom beside its Algorithm 1:

* **slice** (:meth:`~SectorAccumulator.begin_slice`): the projected normal's angle ``gamma`` and length
  ``|n_p|`` give the hemisphere ``[gamma - pi/2, gamma + pi/2]`` of the slice and each sector's weight;
* **sample** (:meth:`~SectorAccumulator.step`): each sample's occluded interval, from its front
  direction to its back direction (the variant's rule, :meth:`~SectorAccumulator.interval`), and the
  light it sends;
* **finish** (:meth:`~SectorAccumulator.end_slice`, :meth:`~SectorAccumulator.finish`): the union of
  the slice's intervals (32 sectors, or their exact measure), its visible share, the newly occluded
  sectors times the light, bent normal and ambient light; averaged over slices.

A variant subclasses it and supplies ``slice_frame`` (``gamma``, ``|n_p|``, the tangent its angles grow
toward) and ``interval`` (``start``, ``width`` in sector units).
"""
from __future__ import annotations

import abc

import math
from typing import Callable

import torch
import torch.nn.functional as F

from ..intervals import union_measure
from ..ops import arc_measure as arc_integral
from ..ops import bent_direction
from ..sectors import SECTORS, sector_union
from ..thickness import BoundThickness
from ..walk import Queries, Sample, SliceAccumulator, SliceGeometry

__all__ = ["SectorAccumulator", "cosine_sector_weights", "sector_centres"]




def sector_centres(gamma: torch.Tensor) -> torch.Tensor:
    """``(N, 32)`` signed slice angles of the sector centres (sector ``k`` spans
    ``gamma - pi/2 + pi [k, k+1] / 32``)."""
    k = torch.arange(SECTORS, dtype=gamma.dtype, device=gamma.device)
    return gamma[:, None] - math.pi / 2 + math.pi * (k + 0.5) / SECTORS


def cosine_sector_weights(gamma: torch.Tensor, normal_length: torch.Tensor) -> torch.Tensor:
    """``(N, 32)`` each sector's exact share of the cosine-weighted slice:
    ``|n_p| int_sector cos(theta - gamma) |sin theta| dtheta`` (summed over slices uniform around ``V``
    and normalised, this is the cosine-weighted hemisphere measure)."""
    k = torch.arange(SECTORS + 1, dtype=gamma.dtype, device=gamma.device)
    edges = gamma[:, None] - math.pi / 2 + math.pi * k / SECTORS
    H = arc_integral(edges, gamma[:, None])
    return (H[:, 1:] - H[:, :-1]).clamp_min(0) * normal_length[:, None]


def _cosine_measure(gamma: torch.Tensor, normal_length: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """``x -> |n_p| (H(theta(x)) - H(theta(0)))``: the cosine-weighted measure of ``[0, x]`` for positions
    ``x`` ``(N, M)`` in sector units across the hemisphere, ``theta(x) = gamma - pi/2 + pi x / 32``."""
    g = gamma[:, None]
    start = arc_integral(g - math.pi / 2, g)

    def measure(x):
        return (arc_integral(g + (x * (math.pi / SECTORS) - math.pi / 2), g) - start) * normal_length[:, None]

    return measure


def _light_rows(width: torch.Tensor) -> torch.Tensor:
    """Rows ``(M,)`` of the steps whose interval is not empty (``width >= 0``): only those can newly
    occlude sectors, so only they gather light."""
    return (width.detach() >= 0).nonzero()[:, 0]


class SectorAccumulator(SliceAccumulator):
    """The per-step work shared by the ``"default"``, ``"exact"`` and ``"hdrp"`` variants (a
    :class:`~torch_ao.walk.SliceAccumulator` that takes each side's steps in one call).

    Args:
        mode, rounding, tau: how :func:`~torch_ao.sectors.sector_union` turns intervals into sectors.
        union: ``"sectors"`` (32 sectors, the paper) or ``"exact"`` (the exact weighted measure of the
            union of the intervals, :func:`~torch_ao.intervals.union_measure`; visibility only).
        weighting: ``"uniform"`` (every sector 1/32) or ``"cosine"`` (:func:`cosine_sector_weights`).
        thickness: the bound thickness model.
        indirect, bent_normals, ambient, ambient_directions: the outputs beyond visibility.
        sector_epsilon: sectors removed from every interval's width.
    """

    batch_steps = True

    def __init__(self, *, mode: str, rounding: str, tau: float, weighting: str, thickness: BoundThickness,
                 indirect: bool = False, bent_normals: bool = False, ambient: torch.Tensor | Callable | None = None,
                 ambient_directions: int = 8, sector_epsilon: float = 0.0, union: str = "sectors") -> None:
        self.mode, self.rounding, self.tau, self.union = mode, rounding, tau, union
        self.weighting, self.thickness = weighting, thickness
        self.indirect, self.bent_normals = indirect, bent_normals
        self.ambient, self.ambient_directions = ambient, ambient_directions
        self.sector_epsilon = float(sector_epsilon)

    # ------------------------------------------------------------------ the variant's rules
    def slice_frame(self, q: Queries, geom: SliceGeometry) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``gamma`` ``(N,)`` (the projected normal's signed angle), ``|n_p|`` ``(N,)`` and the tangent
        ``(N,3)`` toward which signed angles grow."""
        return geom.normal_angle, geom.normal_length, geom.tangent

    @abc.abstractmethod
    def interval(self, state: dict, q: Queries, sample: Sample, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The occluded interval ``(start, width)`` ``(rows,)`` in sector units of every step of ``sample``
        (a negative width is empty); ``t`` is the occluders' thickness."""

    # ------------------------------------------------------------------ slice
    def begin_slice(self, q: Queries, geom: SliceGeometry):
        gamma, length, tangent = self.slice_frame(q, geom)
        if self.weighting == "cosine":
            weights = cosine_sector_weights(gamma, length)
        else:
            weights = gamma.new_full((1, SECTORS), 1.0 / SECTORS).expand(gamma.shape[0], SECTORS)
        return {"s": [], "w": [], "light": [], "gamma": gamma, "length": length, "tangent": tangent,
                "weights": weights}

    # ------------------------------------------------------------------ sample
    def step(self, state, q: Queries, geom: SliceGeometry, sample: Sample):
        J = sample.steps
        n = len(q) // J
        start, width = self.interval(state, q, sample, self.thickness(sample))
        state["s"].append(start.view(J, n))
        state["w"].append(width.view(J, n))
        if self.indirect:
            # Only a step whose interval is not empty can newly occlude sectors and send light: the
            # others (most samples) are never gathered.
            live = _light_rows(width)
            part = sample.rows(live)
            ldir = part.delta / part.distance.clamp_min(1e-30)[:, None]
            sender = (part.gather("normals") * -ldir).sum(-1).clamp(0.0, 1.0)
            factor = sender * part.valid.to(sender.dtype)
            if self.weighting == "uniform":
                factor = factor * (q.normal.index_select(0, live) * ldir).sum(-1).clamp(0.0, 1.0)
            light = part.gather("light") * factor[:, None]
            state["light"].append(light.new_zeros(J * n, 3).index_copy(0, live, light).view(J, n, 3))
        return state

    # ------------------------------------------------------------------ finish
    def end_slice(self, state, q: Queries, geom: SliceGeometry) -> dict[str, torch.Tensor]:
        S = torch.cat(state["s"], 0).t()  # (N, steps on both sides)
        W = torch.cat(state["w"], 0).t()
        omega = state["weights"]
        if self.union == "exact":
            if self.weighting == "cosine":
                measure = _cosine_measure(state["gamma"], state["length"])
                total = measure(S.new_full((S.shape[0], 1), float(SECTORS)))
                out = {"vis_num": total - union_measure(S, W, SECTORS, measure), "vis_den": total}
            else:
                out = {"vis_num": 1 - union_measure(S, W, SECTORS) / SECTORS}
            return out
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
            out["bent_normal"] = bent_direction(sums["bent"], q.normal, -1)
        if self.ambient is not None:
            if callable(self.ambient):
                out["ambient"] = sums["ambient"] / den
            else:
                out["ambient"] = vis * self.ambient.to(vis.dtype)
        return out
