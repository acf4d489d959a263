"""Hard unions over a slice's steps: the shaders' integer masks, and the same rule on float visibility
(the straight-through forward)."""
from __future__ import annotations

import torch

from .rule import SECTORS, bits_to_mask, hard_coverage, hard_mask, mask_bits


def mask_union(s, w, rounding, weights, p0):
    """The shaders' loop over steps with 32-bit masks, bit for bit: ``mask |= bits_j`` and, with
    ``weights`` ``(N, 32)``, ``newly_j = sum of weights over bits_j & ~mask`` (the bitmask blog's
    ``ComputeGI`` counts these bits).

    ``s, w`` ``(N, J)`` in sector units; ``p0`` ``(N, 32)`` (sectors with ``p0 < 1/2`` start occluded) or
    ``None``. Returns the float visibility bits ``(N, 32)`` and ``newly`` ``(N, J)`` (``(N, 0)`` without
    weights)."""
    N, J = s.shape
    occ = torch.zeros(N, dtype=torch.int64, device=s.device) if p0 is None else bits_to_mask(1 - p0)
    newly = s.new_zeros(N, J) if weights is not None else s.new_zeros(N, 0)
    cols = []
    for j in range(J):
        m = hard_mask(s[:, j], w[:, j], rounding)
        if weights is not None:
            cols.append((mask_bits(m & ~occ, s.dtype) * weights).sum(-1))
        occ = occ | m
    if cols:
        newly = torch.stack(cols, 1)
    return 1 - mask_bits(occ, s.dtype), newly


def coverage_union(s, w, weights, p0, rounding):
    """The hard rule on float visibility: ``P_{j+1} = P_j - C_j P_j`` with ``C_j`` the 0/1
    :func:`~.rule.hard_coverage` of step ``j``, and ``newly_j = sum_k weights_k C_jk P_jk``. Equal to
    :func:`mask_union` for a 0/1 ``p0``; also takes a fractional one.

    ``s, w`` ``(N, J)`` in sector units; ``weights``, ``p0`` ``(N, 32)`` or ``None``. Returns ``visible``
    ``(N, 32)`` and ``newly`` ``(N, J)`` (``(N, 0)`` without weights)."""
    N, J = s.shape
    visible = torch.ones(N, SECTORS, dtype=s.dtype, device=s.device) if p0 is None else p0.clone()
    newly = s.new_zeros(N, J) if weights is not None else s.new_zeros(N, 0)
    for j in range(J):
        g = hard_coverage(s[:, j], w[:, j], rounding).mul_(visible)
        if weights is not None:
            newly[:, j] = (g * weights).sum(-1)
        visible = visible - g
    return visible, newly
