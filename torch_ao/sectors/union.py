""":func:`sector_union`: a slice's per-sector visibility after its steps, hard, soft or straight-through."""
from __future__ import annotations

import torch

from ..checks import check_choice, check_float
from .hard_union import mask_union
from .rule import ROUNDINGS, rounding_offset
from .soft_union import SectorUnion, union_forward

__all__ = ["MODES", "sector_union"]

MODES = ("hard", "soft", "straight_through")


def sector_union(s: torch.Tensor, w: torch.Tensor, *, mode: str = "hard", rounding: str = "ceil",
                 tau: float = 0.1, weights: torch.Tensor | None = None,
                 p0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sector visibility ``(N, 32)`` after the ``J`` steps ``(s, w)`` ``(N, J)`` (interval starts and
    widths in sector units) of a slice, and the weighted newly occluded share of each step ``(N, J)``
    (``(N, 0)`` when ``weights`` ``(N, 32)`` is None).

    ``mode``: ``"hard"`` (the shaders' integer masks, zero gradient), ``"soft"`` (temperature ``tau`` in
    sector units, :class:`~.soft_union.SectorUnion`) or ``"straight_through"`` (hard values, soft
    gradients). ``p0`` ``(N, 32)`` is an initial per-sector visibility (the SSILVB GLSL article keeps its
    mask across slices).
    """
    check_choice("mode", mode, MODES)
    check_choice("rounding", rounding, ROUNDINGS)
    if mode == "hard":
        return mask_union(s, w, rounding, weights, p0)
    tau = check_float("tau", tau, 0.0, open_minimum=True)
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in (s, w, weights, p0))
    if not needs_grad:  # no graph: the plain sweep, without the backward tables
        return union_forward(s, w, weights, p0, tau, rounding_offset(rounding),
                          rounding if mode == "straight_through" else None)
    return SectorUnion.apply(s, w, weights, p0, tau, rounding, mode == "straight_through")
