"""Plain-autograd reference of the soft sector union, for the tests of :class:`torch_ao.sectors.SectorUnion`:
the per-sector :func:`~torch_ao.sectors.soft_coverage` of every step, then the product over steps with
an autograd graph per step (what the blocked union computes without one)."""
import torch

from torch_ao.sectors import soft_coverage


def plain_union(s, w, weights, p0, tau, rounding):
    """``(visible (N, 32), newly (N, J))`` of the steps ``(s, w)`` ``(N, J)``: ``P_{j+1} = P_j (1 - c_j)``
    from ``p0`` (or 1), ``newly_j = sum_k weights_k c_jk P_jk`` (``(N, 0)`` without ``weights``)."""
    c = soft_coverage(s, w, tau, rounding)
    P = torch.ones_like(c[:, 0]) if p0 is None else p0.clone()
    newly = []
    for j in range(s.shape[1]):
        g = c[:, j] * P
        if weights is not None:
            newly.append((g * weights).sum(-1))
        P = P * (1 - c[:, j])
    return P, (torch.stack(newly, 1) if weights is not None else s.new_zeros(s.shape[0], 0))
