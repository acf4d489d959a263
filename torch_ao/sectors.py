"""Visibility-bitmask sectors: hard 32-bit masks (bit for bit as the shaders) and soft, differentiable coverage.

A slice's hemisphere is split into ``SECTORS = 32`` equal sectors. One step occludes the interval
``[min, max]`` of ``[0, 1]`` (front and back angle mapped across the hemisphere). In sector units
``s = 32 * min`` (start) and ``w = 32 * (max - min)`` (width); the shaders (seed 000 ``UpdatePartitions``,
seed 001 ``updateSectors``) set

    start = uint(s)                      # floor, s >= 0
    count = ceil(w) | round(w) | floor(w)
    bits  = (0xFFFFFFFF >> (32 - count)) << start      (count > 0, truncated to 32 bits)

so sector ``k`` is on iff ``floor(s) <= k`` and ``n = k - floor(s) < count``. For an integer ``n``:
``n < ceil(w)  <=>  n < w``, ``n < round(w) <=> n + 1/2 < w`` (ties aside), ``n < floor(w) <=> n + 1 <= w``.
So with ``delta = 0, 1/2, 1``: sector ``k`` is on iff ``s < k + 1`` and ``w - (k - floor(s)) - delta > 0``.

Hard masks (:func:`hard_mask`, :func:`popcount32`) use torch integer ops on ``int64`` tensors holding
32-bit values. Soft coverage (:func:`soft_coverage`) replaces each test by a logistic of temperature
``tau`` (in sector units) and ``floor(s)`` by the smooth staircase ``sum_m sigmoid((s - m) / tau)``; a
gate ``tanh(w / tau)`` makes zero-width intervals cover nothing. As ``tau -> 0`` it converges to the hard
rule. The union over steps ``1 - prod_j (1 - c_j)`` and each step's newly covered fraction
``c_j prod_{i<j} (1 - c_i)`` are computed by :class:`SectorUnion`, a custom autograd function: one
in-place ``(N, 32)`` pass per step (no ``(N, steps, 32)`` autograd graph) that keeps only its ``(N, steps)``
inputs; backward rebuilds the coverage and its analytic derivatives block by block for a linear
reverse scan.
"""
from __future__ import annotations

import math

import torch


__all__ = [
    "SECTORS",
    "ROUNDINGS",
    "MODES",
    "sector_interval",
    "hard_count",
    "hard_mask",
    "popcount32",
    "mask_bits",
    "bits_to_mask",
    "hard_coverage",
    "soft_floor",
    "soft_coverage",
    "SectorUnion",
    "sector_union",
]

SECTORS = 32
ROUNDINGS = ("ceil", "round", "floor")
MODES = ("hard", "soft", "straight_through")
_DELTA = {"ceil": 0.0, "round": 0.5, "floor": 1.0}
_FULL = 0xFFFFFFFF


def _check_rounding(rounding: str) -> float:
    if rounding not in _DELTA:
        raise ValueError(f"rounding: expected one of {ROUNDINGS}, got {rounding!r}")
    return _DELTA[rounding]


def sector_interval(min_h: torch.Tensor, max_h: torch.Tensor, sectors: int = SECTORS) -> tuple[torch.Tensor, torch.Tensor]:
    """``(s, w) = (sectors * min, sectors * (max - min))`` in sector units, as the shaders compute them."""
    return min_h * sectors, (max_h - min_h) * sectors


def hard_count(w: torch.Tensor, rounding: str = "ceil") -> torch.Tensor:
    """Number of sectors ``ceil(w)``, ``round(w)`` (ties to even, as HLSL ``round``) or ``floor(w)``,
    as ``int64`` clamped to ``[0, 32]`` (``w`` is a width in sector units)."""
    _check_rounding(rounding)
    fn = {"ceil": torch.ceil, "round": torch.round, "floor": torch.floor}[rounding]
    return fn(w.detach()).clamp(0, SECTORS).to(torch.int64)


def hard_mask(s: torch.Tensor, w: torch.Tensor, rounding: str = "ceil") -> torch.Tensor:
    """32-bit sector mask (in an ``int64`` tensor) of the interval starting at ``s`` with width ``w``.

    Exactly ``UpdatePartitions`` / ``updateSectors``: ``start = uint(s)``; ``count`` by ``rounding``;
    ``(0xFFFFFFFF >> (32 - count)) << start`` if ``count > 0``, truncated to 32 bits.
    """
    start = torch.floor(s.detach()).clamp(0, 63).to(torch.int64)
    count = hard_count(w, rounding)
    full = torch.full_like(count, _FULL)
    run = torch.where(count > 0, full >> (SECTORS - count).clamp(0, SECTORS), torch.zeros_like(count))
    return (run << start) & _FULL


def popcount32(x: torch.Tensor) -> torch.Tensor:
    """Number of set bits of 32-bit values held in an integer tensor (the shaders' ``bitCount``)."""
    v = x.to(torch.int64) & _FULL
    v = v - ((v >> 1) & 0x55555555)
    v = (v & 0x33333333) + ((v >> 2) & 0x33333333)
    v = (v + (v >> 4)) & 0x0F0F0F0F
    return ((v * 0x01010101) & _FULL) >> 24


_SHIFTS: dict[torch.device, torch.Tensor] = {}


def _shifts(device) -> torch.Tensor:
    t = _SHIFTS.get(device)
    if t is None:
        t = _SHIFTS[device] = torch.arange(SECTORS, dtype=torch.int64, device=device)
    return t


def mask_bits(mask: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(..., 32)`` bits (0/1 in ``dtype``) of 32-bit masks ``(...)``; bit ``k`` is sector ``k``."""
    return ((mask[..., None] >> _shifts(mask.device)) & 1).to(dtype)


def bits_to_mask(bits: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`mask_bits`: ``(..., 32)`` 0/1 values -> ``int64`` masks ``(...)``."""
    return ((bits > 0.5).to(torch.int64) << _shifts(bits.device)).sum(-1)


def _sectors(like: torch.Tensor, lo: int = 0, hi: int = SECTORS) -> torch.Tensor:
    return torch.arange(lo, hi, dtype=like.dtype, device=like.device)


def hard_coverage(s: torch.Tensor, w: torch.Tensor, rounding: str = "ceil", lo: int = 0, hi: int = SECTORS) -> torch.Tensor:
    """Float 0/1 coverage ``(..., hi - lo)`` of sectors ``lo..hi-1``; equal to :func:`mask_bits` of
    :func:`hard_mask` (the same integer rule, evaluated per sector)."""
    k = _sectors(s, lo, hi)
    start = torch.floor(s.detach())[..., None]
    count = hard_count(w, rounding).to(s.dtype)[..., None]
    n = k - start
    return ((n >= 0) & (n < count)).to(s.dtype)


def soft_floor(s: torch.Tensor, tau: float) -> torch.Tensor:
    """Smooth ``floor(s)`` on ``[0, 32]``: ``sum_{m=1..32} sigmoid((s - m) / tau)``."""
    m = _sectors(s, 1, SECTORS + 1)
    return torch.sigmoid((s[..., None] - m) / tau).sum(-1)


def _soft_floor_window(s: torch.Tensor, tau: float, slope: bool = False):
    """Smooth floor ``F(s)`` (and, with ``slope``, ``F'(s)``), summed over a window of ``W`` consecutive
    integers ``lo .. lo + W - 1`` inside ``[1, 32]`` that contains every integer within ``_CLAMP * tau``
    of ``s``; the integers ``1 .. lo - 1`` count fully (their logistic is within ``sigmoid(-_CLAMP)`` of
    1) and those above the window not at all. Costs ``O(N * W)``, not ``O(N * 32)``."""
    reach = int(math.ceil(_CLAMP * tau)) + 1
    width = min(2 * reach, SECTORS)
    inv_tau = 1.0 / tau
    lo = (torch.floor(s.detach()) - (reach - 1)).clamp_(1, SECTORS - width + 1)  # (...)
    offsets = torch.arange(width, dtype=s.dtype, device=s.device) * inv_tau
    x = torch.sub(((s - lo) * inv_tau)[..., None], offsets).clamp_(-_CLAMP, _CLAMP).sigmoid_()  # (..., W)
    F = x.sum(-1).add_(lo - 1)
    if not slope:
        return F
    return F, torch.sub(1, x).mul_(x).sum(-1).mul_(inv_tau)


def soft_coverage(s: torch.Tensor, w: torch.Tensor, tau: float, rounding: str = "ceil", lo: int = 0,
                  hi: int = SECTORS, floor_s: torch.Tensor | None = None) -> torch.Tensor:
    """Soft coverage ``(..., hi - lo)`` in ``[0, 1]`` of sectors ``lo..hi-1`` (differentiable by autograd).

    ``sigmoid((k + 1 - s) / tau) * sigmoid((w - (k - F(s)) - delta) / tau) * tanh(w / tau)`` with
    ``F`` = :func:`soft_floor`; zero width covers nothing; ``tau -> 0`` gives the hard rule.
    """
    delta = _check_rounding(rounding)
    if not tau > 0:
        raise ValueError(f"tau: expected > 0, got {tau}")
    k = _sectors(s, lo, hi)
    F = soft_floor(s, tau) if floor_s is None else floor_s
    w = w.clamp_min(0)
    a = torch.sigmoid((k + 1 - s[..., None]) / tau)
    b = torch.sigmoid((w[..., None] - k + F[..., None] - delta) / tau)
    return a * b * torch.tanh(w / tau)[..., None]


_CLAMP = 30.0  # logistic arguments are clamped to +-30 (sigmoid(-30) ~ 9e-14)
_TINY = 1e-30  # per-sector visibilities below this are flushed to 0 (no subnormals)


# ---------------------------------------------------------------------------------------------
# Union over steps (custom autograd)
# ---------------------------------------------------------------------------------------------
def _soft_sweep(s, w, weights, p0, tau, delta, tables):
    """The soft union's forward sweep, one ``(N, 32)`` step at a time, in place.

    Returns ``visible``, ``newly`` and, when ``tables``, the backward tables ``C`` ``(J, N, 32)``
    (``c_j``), ``D`` ``(J, 2, N, 32)`` (``P_j dc_j/ds``, ``P_j dc_j/dw``) and ``Gn`` ``(J, N, 32)``
    (``P_j c_j``, only when ``weights`` is given). With ``c = a b g`` (``a = sigmoid((k+1-s)/tau)``,
    ``b = sigmoid((w+F-delta-k)/tau)``, ``g = tanh(w/tau)``) and ``sigma' = sigma (1 - sigma) / tau``:
    ``dc/ds = c ((1 - b) F'(s) - (1 - a)) / tau``, ``dc/dw = a b g' + c (1 - b) / tau``.
    """
    N, J = s.shape
    inv_tau = 1.0 / tau
    k1 = _sectors(s) + 1
    want_newly = weights is not None
    newly = s.new_zeros(N, J) if want_newly else s.new_zeros(N, 0)
    P = s.new_ones(N, SECTORS) if p0 is None else p0.clone()
    if tables:
        F, dF = _soft_floor_window(s, tau, slope=True)  # (N, J)
        # Per-step rows, not (J, N, 32) blocks: blocks that large are fresh mmap'd pages on every call
        # (page faults cost about as much as the sweep), while rows are recycled by the allocator.
        C, D, Gn = [], [], [] if want_newly else None
    else:
        F = _soft_floor_window(s, tau)
    gate = torch.tanh(w * inv_tau)  # (N, J)
    # Logistic arguments in units of tau: a = sigmoid(k1 / tau - s / tau), b = sigmoid((w + F - delta + 1) / tau - k1 / tau).
    k1 = k1 * inv_tau
    s_tau = s * inv_tau
    b_tau = (w + F - delta + 1) * inv_tau
    if tables:
        dgate = (1 - gate * gate) * inv_tau
    for j in range(J):
        # Logistic arguments clamped to +-_CLAMP (beyond, sigma is within 1e-13 of 0/1) so that no
        # subnormal floats appear (they are ~100x slower on CPUs).
        a = torch.sub(k1, s_tau[:, j, None]).clamp_(-_CLAMP, _CLAMP).sigmoid_()
        b = torch.sub(b_tau[:, j, None], k1).clamp_(-_CLAMP, _CLAMP).sigmoid_()
        if tables:
            ab = a * b
            c = ab * gate[:, j, None]
            G = c * P  # newly covered share P_j c_j
            nb = b.neg_().add_(1)  # 1 - b
            Dj = s.new_empty(2, N, SECTORS)
            torch.mul(ab, P, out=Dj[1]).mul_(dgate[:, j, None]).addcmul_(G, nb, value=inv_tau)
            torch.mul(G, nb.mul_(dF[:, j, None]).add_(a).sub_(1), out=Dj[0]).mul_(inv_tau)
            C.append(c)
            D.append(Dj)
            if want_newly:
                Gn.append(G)
        else:
            G = a.mul_(b).mul_(gate[:, j, None]).mul_(P)
        if want_newly:
            newly[:, j] = (G * weights).sum(-1)
        P.sub_(G)  # == P (1 - c), exact in [0, P]
        torch.nn.functional.threshold_(P, _TINY, 0.0)  # flush tiny values (no subnormals)
    if tables:
        return P, newly, C, D, Gn
    return P, newly, None, None, None


class SectorUnion(torch.autograd.Function):
    """Union over the steps of one slice, per sector, with newly covered fractions.

    Inputs: ``s, w`` ``(N, J)`` interval starts and widths in sector units (step order matters for
    "newly"); ``weights`` ``(N, 32)`` per-sector weights for ``newly`` (or ``None``: no newly output);
    ``p0`` ``(N, 32)`` initial per-sector visibility (or ``None`` = 1); ``tau``, ``rounding``,
    ``hard_forward`` (straight-through: hard coverage in forward, soft gradients in backward).

    Outputs: ``visible`` ``(N, 32)`` = ``p0 * prod_j (1 - c_j)``, and ``newly`` ``(N, J)`` =
    ``sum_k weights_k c_jk p0_k prod_{i<j} (1 - c_ik)`` (empty ``(N, 0)`` without weights).

    Forward keeps only its inputs (``O(N J)``). Backward rebuilds, for blocks of ``BACKWARD_BLOCK``
    rows at a time, each step's ``c_j``, ``P_j dc_j/ds`` and ``P_j dc_j/dw`` (``P_j = p0 prod_{i<j} (1 - c_i)``;
    and ``P_j c_j`` for the weights' gradient) in one forward sweep, then runs a reverse linear scan
    (``S_{J-1} = G_v``, ``D_m = S_m - G_m``, ``dL/dc_m = -P_m D_m``, ``S_{m-1} = S_m - c_m D_m``), never
    dividing by ``1 - c``. So neither memory nor time is spent on tables in the forward pass (which a
    recomputed walk runs twice), and the tables only ever exist for one block.
    """

    #: rows per block of the backward's table rebuild (its transient memory: ``3 J`` rows of 32 per row)
    BACKWARD_BLOCK = 4096

    @staticmethod
    def forward(ctx, s, w, weights, p0, tau, rounding, hard_forward):
        w = w.clamp_min(0)
        if hard_forward:
            visible, newly = _hard_sweep(s, w, weights, p0, rounding)
        else:
            visible, newly = _soft_sweep(s, w, weights, p0, tau, _DELTA[rounding], False)[:2]
        ctx.tau, ctx.delta = tau, _DELTA[rounding]
        ctx.save_for_backward(s, w, weights, p0)
        return visible, newly

    @staticmethod
    def backward(ctx, grad_visible, grad_newly):
        s, w, weights, p0 = ctx.saved_tensors
        N, J = s.shape
        want_newly = weights is not None and grad_newly is not None and grad_newly.numel() > 0
        keep_gn = want_newly and ctx.needs_input_grad[2]
        gs, gw = torch.empty_like(s), torch.empty_like(s)
        gweights = torch.zeros_like(weights) if keep_gn else None
        gp0 = torch.empty(N, SECTORS, dtype=s.dtype, device=s.device) if ctx.needs_input_grad[3] else None
        for start in range(0, N, SectorUnion.BACKWARD_BLOCK):
            r = slice(start, start + SectorUnion.BACKWARD_BLOCK)
            wr = None if weights is None else weights[r]
            _, _, C, D, Gn = _soft_sweep(s[r], w[r], wr, None if p0 is None else p0[r], ctx.tau, ctx.delta, True)
            gnr = grad_newly[r] if want_newly else None
            if keep_gn:
                for j in range(J):
                    gweights[r].addcmul_(gnr[:, j, None], Gn[j])
            # Reverse linear scan: S_{J-1} = G_v, D_m = S_m - G_m, S_{m-1} = S_m - c_m D_m.
            S = torch.zeros_like(C[0]) if grad_visible is None else grad_visible[r]
            gsw = torch.empty(J, 2, C[0].shape[0], dtype=s.dtype, device=s.device)
            for m in range(J - 1, -1, -1):
                Dm = torch.addcmul(S, gnr[:, m, None], wr, value=-1) if want_newly else S
                torch.sum(D[m] * Dm, -1, out=gsw[m])
                S = torch.addcmul(S, C[m], Dm, value=-1)
            gs[r] = gsw[:, 0].t().neg()
            gw[r] = gsw[:, 1].t().neg()
            if gp0 is not None:
                gp0[r] = S
        return gs, gw, gweights, gp0, None, None, None


def _hard_sweep(s, w, weights, p0, rounding):
    """Straight-through forward: the hard per-sector rule on floats (``visible``, ``newly``)."""
    N, J = s.shape
    visible = torch.ones(N, SECTORS, dtype=s.dtype, device=s.device) if p0 is None else p0.clone()
    newly = s.new_zeros(N, J) if weights is not None else s.new_zeros(N, 0)
    for j in range(J):
        g = hard_coverage(s[:, j], w[:, j], rounding).mul_(visible)
        if weights is not None:
            newly[:, j] = (g * weights).sum(-1)
        visible = visible - g
    return visible, newly


def sector_union(s: torch.Tensor, w: torch.Tensor, *, mode: str = "hard", rounding: str = "ceil",
                 tau: float = 0.1, weights: torch.Tensor | None = None,
                 p0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sector visibility ``(N, 32)`` after the ``J`` steps ``(s, w)`` ``(N, J)`` of a slice, and the
    weighted newly-occluded fraction of each step ``(N, J)`` (``(N, 0)`` when ``weights`` is None).

    ``mode``: ``"hard"`` (exact integer masks, zero gradient), ``"soft"`` (temperature ``tau`` in
    sector units) or ``"straight_through"`` (hard values, soft gradients). ``p0`` is an initial
    per-sector visibility (the GLSL seed keeps its mask across slices).
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    _check_rounding(rounding)
    if mode == "hard":
        return _hard_union(s, w, rounding, weights, p0)
    if not (isinstance(tau, (int, float)) and tau > 0 and math.isfinite(tau)):
        raise ValueError(f"tau: expected a positive finite float, got {tau!r}")
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in (s, w, weights, p0))
    if not needs_grad:  # no graph: the plain sweep, without the backward tables
        if mode == "straight_through":
            return _hard_sweep(s, w.clamp_min(0), weights, p0, rounding)
        return _soft_sweep(s, w.clamp_min(0), weights, p0, float(tau), _DELTA[rounding], False)[:2]
    return SectorUnion.apply(s, w, weights, p0, float(tau), rounding, mode == "straight_through")


def _hard_union(s, w, rounding, weights, p0):
    """Integer-mask union (bit for bit as the shaders); returns float visibility bits and newly."""
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
