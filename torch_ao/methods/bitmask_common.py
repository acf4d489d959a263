"""Pieces shared by the visibility-bitmask variants: thickness lookup and sector weights."""
from __future__ import annotations

import math

import torch

from ..ops import arc_measure as _arc_integral
from ..ops import safe_acos
from ..walk import Sample
from ..sectors import SECTORS

__all__ = ["ThicknessLookup", "cosine_sector_weights", "sector_centres", "safe_acos"]


class ThicknessLookup:
    """Thickness of the occluder at a sample ``(N,)`` (or a 0-d tensor).

    ``kind``: ``"scalar"`` (``value`` 0-d), ``"map"`` (``value`` a ``(B,1,H,W)`` map gathered at the
    sample as the frame buffer ``"thickness"``), ``"object"`` (``value`` a ``(K,)`` table indexed by
    the sample's ``object_id``, gathered as the frame buffer ``"object_id"``). ``growth`` multiplies by
    ``1 + growth * |sample - pixel|`` (world units) when not ``None``.
    """

    def __init__(self, kind: str, value: torch.Tensor, growth: torch.Tensor | None = None) -> None:
        self.kind, self.value, self.growth = kind, value, growth

    def __call__(self, sample: Sample) -> torch.Tensor:
        if self.kind == "scalar":
            t = self.value.to(sample.dtype)
        elif self.kind == "map":
            t = sample.gather("thickness")[:, 0]
        else:
            ids = sample.gather("object_id")[:, 0].long().clamp(0, self.value.shape[0] - 1)
            t = self.value.to(sample.dtype)[ids]
        if self.growth is not None:
            t = t * (1 + self.growth.to(sample.dtype) * sample.distance)
        return t


def sector_centres(gamma: torch.Tensor) -> torch.Tensor:
    """``(N, 32)`` signed slice angles of the sector centres (sector ``k`` spans
    ``gamma - pi/2 + pi [k, k+1] / 32``)."""
    k = torch.arange(SECTORS, dtype=gamma.dtype, device=gamma.device)
    return gamma[:, None] - math.pi / 2 + math.pi * (k + 0.5) / SECTORS


def cosine_sector_weights(gamma: torch.Tensor, normal_length: torch.Tensor) -> torch.Tensor:
    """``(N, 32)`` each sector's exact share of the cosine-weighted slice:
    ``|n_p| int_sector cos(theta - gamma) |sin theta| dtheta`` (sums to ``|n_p|`` over the hemisphere;
    averaged over slices uniform around ``V`` this is the cosine-weighted hemisphere measure)."""
    k = torch.arange(SECTORS + 1, dtype=gamma.dtype, device=gamma.device)
    edges = gamma[:, None] - math.pi / 2 + math.pi * k / SECTORS
    H = _arc_integral(edges, gamma[:, None])
    return (H[:, 1:] - H[:, :-1]).clamp_min(0) * normal_length[:, None]
