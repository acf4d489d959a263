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
blocked, in-place sweep (no ``(N, steps, 32)`` autograd graph) that keeps only its ``(N, steps)``
inputs; backward rebuilds the coverage and the tables of its analytic derivatives block by block for
a linear reverse scan.
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
_WINDOW_MAX = 8  # F(s) from its own window of logistics up to this width (tau <= 0.1), else from a


# ---------------------------------------------------------------------------------------------
# Union over steps (custom autograd)
# ---------------------------------------------------------------------------------------------
# Both sweeps work on blocks of ``B`` rows in a sector-major layout: per block the step inputs are
# ``(J, B)`` and the per-sector tensors ``(32, B)`` (sums over sectors are then row adds), held in
# scratch buffers allocated once per call and reused by every block and step (fresh ``(N, 32)``
# tensors per step cost page faults and cache misses). The logistics of a group of steps are
# evaluated together (fewer, larger ops); the visibility update is one ``(32, B)`` op per step. The
# views of the buffers are built once per block size (:class:`_Plan`), not per step.
#
# For tau > 0.1 the smooth floor needs no logistics of its own: its terms are the complements of ``a``,
# ``F(s) = sum_{m=1..32} sigmoid((s - m) / tau) = sum_k (1 - a_k)`` and ``F'(s) = sum_k a_k (1 - a_k) / tau``
# (with the clamped arguments; a term beyond the clamp is within sigmoid(-30) of 0 or 1). For smaller
# tau its window of logistics is narrow (``W <= 8``) and keeps ``F`` accurate where ``a``'s arguments
# ``(k + 1) / tau - s / tau`` are not (``(s - lo) / tau`` in :func:`_floor_window_into`).


class _Group:
    """Views of one group of ``q`` consecutive steps ``g`` (``slice``) of a :class:`_Plan`."""

    def __init__(self, plan, g, A, Bt, C, T, fs, xb):
        q = g.stop - g.start
        self.g, self.q, self.A, self.B, self.C, self.T = g, q, A, Bt, C, T
        self.C_rows = list(C.unbind(0))
        self.T_rows = None if T is None else list(T.unbind(0))
        self.xa, self.wd, self.gate = plan.xa[g], plan.wd[g], plan.gate[g]
        self.fs, self.xb = fs, xb
        self.dF = None if plan.dF is None else plan.dF[g]
        self.F = None if plan.F is None else plan.F[g]  # F(s) from the window (else from a)


class _Plan:
    """Scratch buffers and their views for blocks of ``B`` rows and ``J`` steps in groups of ``Q``.

    Forward (``store=False``): one group's ``a`` and ``b`` (then ``c = a b g``) at a time, with
    ``newly`` the weights ``(32, B)``, the group's newly covered shares ``c_j P_j`` and the ``(J, B)``
    sums. Backward (``store=True``): the tables ``(J, 4, 32, B)`` (``a_j``, ``b_j``, ``H_j = a_j b_j P_j``,
    ``c_j``) and the reverse scan's buffers (``sums``: the three sums over sectors per step;
    ``keep_gn``: the weights' gradient; ``slope``: ``F'(s)``)."""

    def __init__(self, like, B, J, Q, tau, store, newly, keep_gn=False, slope=False, sums=False):
        e = lambda *shape: like.new_empty(shape)  # noqa: E731
        width = _floor_width(tau)
        self.window = width <= _WINDOW_MAX  # F(s) and F'(s) from their own (narrow) window of logistics
        self.F = e(J, B) if self.window else None
        self.Fx = e((2 if slope else 1) * width * J * B) if self.window else None
        self.xa, self.wd, self.gate = e(J, 1, B), e(J, B), e(J, 1, B)
        self.P = e(SECTORS, B)
        self.wt = e(SECTORS, B) if newly else None
        self.newly = e(J, B) if newly else None  # forward: newly; backward: grad_newly
        self.dF = e(J, B) if slope else None
        T = e(Q, SECTORS, B) if store else None  # a b of a group
        fs, xb = e(Q, B), e(Q, 1, B)
        groups = [slice(j0, min(j0 + Q, J)) for j0 in range(0, J, Q)]
        self.groups = []
        if store:
            self.store = e(J, 4, SECTORS, B)
            self.H = list(self.store[:, 2].unbind(0))
            for g in groups:
                q = g.stop - g.start
                self.groups.append(_Group(self, g, self.store[g, 0], self.store[g, 1], self.store[g, 3], T[:q],
                                          fs[:q], xb[:q]))
            self.Sh = e(Q + 1, SECTORS, B)  # S_{m0} .. S_{m1} of a group
            D = e(Q, SECTORS, B) if newly else None
            Z = e(Q, 3, SECTORS, B) if sums else None
            self.sums = e(J, 3, B) if sums else None
            self.gwt = e(SECTORS, B) if keep_gn else None
            self.coef = e(J, B) if keep_gn else None
            for grp in self.groups:  # the reverse scan's views
                q, g = grp.q, grp.g
                grp.H, grp.AB = self.store[g, 2], self.store[g, :2]
                grp.S_rows = list(self.Sh[:q + 1].unbind(0))
                grp.D = self.Sh[1:q + 1] if D is None else D[:q]  # D_m = S_{m+1} without newly
                grp.D_rows = list(grp.D.unbind(0))
                if Z is not None:
                    grp.Z, grp.Y, grp.Y1, grp.Z12 = Z[:q], Z[:q, 0], Z[:q, :1], Z[:q, 1:]
                    grp.sums = self.sums[g]
        else:
            A, Bt = e(Q, SECTORS, B), e(Q, SECTORS, B)
            G = e(Q, SECTORS, B) if newly else None
            for g in groups:
                q = g.stop - g.start
                grp = _Group(self, g, A[:q], Bt[:q], Bt[:q], None, fs[:q], xb[:q])
                if newly:
                    grp.G, grp.G_rows = G[:q], list(G[:q].unbind(0))
                self.groups.append(grp)


def _expm1_tanh(x):
    """``tanh(x)`` for ``x >= 0``, in place: ``-expm1(-2x) / (2 + expm1(-2x))`` (within 2 ulp; faster)."""
    t = x.mul_(-2).expm1_()
    return t.div_(t.add(2)).neg_()


def _load(plan, s, w, p0, r, tau, delta):
    """Copies a block's inputs into ``plan``: ``xa = -s / tau`` (``a = sigmoid(K + xa)``, ``K = (k + 1) / tau``),
    ``wd = w - delta + 1``, the gate ``tanh(w / tau)`` and ``P = p0``."""
    inv_tau = 1.0 / tau
    torch.mul(s[r].t(), -inv_tau, out=plan.xa[:, 0])
    if plan.window:
        _floor_window_into(s[r].t().contiguous(), tau, plan.Fx, plan.F, plan.dF)
    torch.add(w[r].t(), 1 - delta, out=plan.wd)
    _expm1_tanh(torch.mul(w[r].t(), inv_tau, out=plan.gate[:, 0]))
    if p0 is None:
        plan.P.fill_(1)
    else:
        plan.P.copy_(p0[r].t())


def _floor_reach(tau: float) -> int:
    return int(math.ceil(_CLAMP * tau)) + 1


def _floor_width(tau: float) -> int:
    return min(2 * _floor_reach(tau), SECTORS)


def _floor_window_into(sT, tau, x_buf, F, dF):
    """Smooth floor ``F(s)`` of the contiguous ``sT`` into ``F`` (and ``F' tau`` into ``dF``), summed over
    a window of ``W`` consecutive integers ``lo .. lo + W - 1`` inside ``[1, 32]`` that contains every
    integer within ``_CLAMP * tau`` of ``s``: the integers ``1 .. lo - 1`` count fully (their logistic is
    within ``sigmoid(-_CLAMP)`` of 1) and those above the window not at all, so it costs ``O(W)`` per
    entry, not ``O(32)``. The ``W`` logistic terms are laid out ``(W, M)`` in the flat buffer ``x_buf``
    (``2 W M`` entries with ``dF``)."""
    reach = _floor_reach(tau)
    width = _floor_width(tau)
    inv_tau = 1.0 / tau
    flat = sT.reshape(-1)
    M = flat.numel()
    lo = torch.floor(flat).sub_(reach - 1).clamp_(1, SECTORS - width + 1)
    z = torch.sub(flat, lo).mul_(inv_tau)
    offsets = torch.arange(width, dtype=sT.dtype, device=sT.device).mul_(inv_tau)[:, None]
    x = torch.sub(z, offsets, out=x_buf[:width * M].view(width, M)).clamp_(-_CLAMP, _CLAMP).sigmoid_()
    torch.sum(x, 0, out=F.view(M)).add_(lo.sub_(1))
    if dF is not None:
        y = torch.sub(1, x, out=x_buf[width * M:2 * width * M].view(width, M)).mul_(x)
        torch.sum(y, 0, out=dF.view(M))


def _logistics(grp, K, inv_tau):
    """A group's ``a = sigmoid(K + xa)`` ``(q, 32, B)``, ``F = sum_k (1 - a_k)`` (and ``F'``) and
    ``b = sigmoid((w + F - delta + 1) / tau - K)``, arguments clamped to +-_CLAMP (beyond, sigma is
    within 1e-13 of 0/1) so that no subnormal floats appear (they are ~100x slower on CPUs)."""
    A, Bt = grp.A, grp.B
    torch.add(K, grp.xa, out=A).clamp_(-_CLAMP, _CLAMP).sigmoid_()
    F = grp.F
    if F is None:
        # F as a sum of the complements (not 32 - sum a: that loses the precision of a small F);
        # b's buffer is the scratch
        na = torch.sub(1, A, out=Bt)
        F = torch.sum(na, 1, out=grp.fs)
        if grp.dF is not None:  # F'(s) tau = sum_k a_k (1 - a_k)
            torch.sum(na.mul_(A), 1, out=grp.dF)
    torch.add(grp.wd, F, out=grp.xb[:, 0]).mul_(inv_tau)
    torch.sub(grp.xb, K, out=Bt).clamp_(-_CLAMP, _CLAMP).sigmoid_()


def _sweep(plan, K, tau, store=False, newly=False):
    """The forward sweep of one block, in place: per group of steps :func:`_logistics` and
    ``c = a b g``, then per step ``P <- P - c_j P`` and the flush of tiny values.

    ``plan.P``: ``p0``, replaced by the final visibility (unless ``store``); with ``newly``,
    ``plan.newly`` ``(J, B)`` receives ``sum_k weights_k c_jk P_jk``. With ``store``, step ``j`` keeps
    ``a_j``, ``b_j``, ``H_j = a_j b_j P_j`` and ``c_j`` in ``plan.store``, ``plan.dF`` (if any) receives
    ``F'(s)`` and the last update is skipped (``P`` is scratch then)."""
    inv_tau = 1.0 / tau
    P = plan.P
    for grp in plan.groups:
        _logistics(grp, K, inv_tau)
        if store:
            torch.mul(grp.A, grp.B, out=grp.T)  # a b
            torch.mul(grp.T, grp.gate, out=grp.C)  # c = a b g
        else:
            grp.C.mul_(grp.A).mul_(grp.gate)  # c = a b g (C is B's buffer)
        for i in range(grp.q):
            j = grp.g.start + i
            if store:
                torch.mul(grp.T_rows[i], P, out=plan.H[j])  # a b P_j
                if j == len(plan.H) - 1:
                    break
            if newly:
                P.sub_(torch.mul(grp.C_rows[i], P, out=grp.G_rows[i]))  # newly covered share c_j P_j
            else:
                P.addcmul_(grp.C_rows[i], P, value=-1)  # P_j (1 - c_j), in [0, P_j]
            torch.nn.functional.threshold_(P, _TINY, 0.0)  # flush tiny values (no subnormals)
        if newly:
            torch.sum(grp.G.mul_(plan.wt), 1, out=plan.newly[grp.g])
    if plan.dF is not None:
        plan.dF.mul_(inv_tau)


def _scan(plan, grad_visible, grad_newly, weights, r, want_newly, keep_gn, want_sw, want_p0):
    """The backward's reverse linear scan over one block's tables (``plan.store``), group by group:
    ``S_J = G_v``, ``D_m = S_{m+1} - gn_m weights``, ``dL/dc_m = -P_m D_m``, ``S_m = S_{m+1} - c_m D_m``,
    then, per group, ``Y = H_m D_m`` and the sums ``plan.sums[m]`` = (``sum Y``, ``sum Y a``, ``sum Y b``)
    over sectors; ``plan.gwt`` ``(32, B)`` receives ``sum_m gn_m g_m H_m`` (the weights' gradient).
    Returns ``S_0`` (the gradient of ``p0``)."""
    groups = plan.groups[::-1]
    top = groups[0].S_rows[-1]  # S_J
    if grad_visible is None:
        top.zero_()
    else:
        top.copy_(grad_visible[r].t())
    if want_newly:
        wtT = plan.wt.copy_(weights[r].t())
        gn = list(plan.newly.copy_(grad_newly[r].t()).unbind(0))
    if keep_gn:
        coef = list(torch.mul(plan.newly, plan.gate[:, 0], out=plan.coef).unbind(0))  # gn_j g_j
        gwt = plan.gwt.zero_()
        H = plan.H
    S = top
    for grp in groups:
        Sh, Ds = grp.S_rows, grp.D_rows
        if S is not Sh[-1]:
            Sh[-1].copy_(S)
        for i in range(grp.q - 1, -1, -1):
            m = grp.g.start + i
            if want_newly:
                torch.addcmul(Sh[i + 1], wtT, gn[m], value=-1, out=Ds[i])
            if keep_gn:
                gwt.addcmul_(H[m], coef[m])
            if m > 0 or want_p0:
                torch.addcmul(Sh[i + 1], grp.C_rows[i], Ds[i], value=-1, out=Sh[i])
        S = Sh[0]
        if want_sw:
            torch.mul(grp.H, grp.D, out=grp.Y)  # Y = a b P D
            torch.mul(grp.Y1, grp.AB, out=grp.Z12)  # Y a, Y b
            torch.sum(grp.Z, 2, out=grp.sums)
    return S


def _sector_offsets(s, tau):
    return ((_sectors(s) + 1) * (1.0 / tau))[:, None]  # (32, 1)


def _plans(N, block, make):
    """``(rows, plan)`` per block of ``block`` rows (one plan per distinct block size)."""
    plans = {}
    for start in range(0, N, block):
        B = min(block, N - start)
        if B not in plans:
            plans[B] = make(B)
        yield slice(start, start + B), plans[B]


def _soft_sweep(s, w, weights, p0, tau, delta, block=None, group=None):
    """The soft union's forward (no tables): ``visible`` ``(N, 32)`` and ``newly`` ``(N, J)`` (``(N, 0)``
    without ``weights``) for widths ``w >= 0``, in blocks of ``block`` rows and groups of ``group`` steps
    (defaults :attr:`SectorUnion.FORWARD_BLOCK`, :attr:`SectorUnion.FORWARD_GROUP`). With ``c = a b g``
    (``a = sigmoid((k+1-s)/tau)``, ``b = sigmoid((w+F-delta-k)/tau)``, ``g = tanh(w/tau)``):
    ``G_j = c_j P_j``, ``P_{j+1} = P_j - G_j``."""
    N, J = s.shape
    block = block or SectorUnion.FORWARD_BLOCK
    group = group or SectorUnion.FORWARD_GROUP
    want_newly = weights is not None
    K = _sector_offsets(s, tau)
    visible = s.new_empty(N, SECTORS)
    newly = s.new_empty(N, J) if want_newly else s.new_zeros(N, 0)
    for r, plan in _plans(N, block, lambda B: _Plan(s, B, J, max(1, min(group, J)), tau, False, want_newly)):
        _load(plan, s, w, p0, r, tau, delta)
        if want_newly:
            plan.wt.copy_(weights[r].t())
        _sweep(plan, K, tau, newly=want_newly)
        visible[r] = plan.P.t()
        if want_newly:
            newly[r] = plan.newly.t()
    return visible, newly


class SectorUnion(torch.autograd.Function):
    """Union over the steps of one slice, per sector, with newly covered fractions.

    Inputs: ``s, w`` ``(N, J)`` interval starts and widths in sector units (step order matters for
    "newly"); ``weights`` ``(N, 32)`` per-sector weights for ``newly`` (or ``None``: no newly output);
    ``p0`` ``(N, 32)`` initial per-sector visibility (or ``None`` = 1); ``tau``, ``rounding``,
    ``hard_forward`` (straight-through: hard coverage in forward, soft gradients in backward).

    Outputs: ``visible`` ``(N, 32)`` = ``p0 * prod_j (1 - c_j)``, and ``newly`` ``(N, J)`` =
    ``sum_k weights_k c_jk p0_k prod_{i<j} (1 - c_ik)`` (empty ``(N, 0)`` without weights).

    Forward keeps only its inputs (``O(N J)``). Backward rebuilds, for blocks of ``BACKWARD_BLOCK``
    rows at a time, each step's ``a_j``, ``b_j``, ``H_j = a_j b_j P_j`` and ``c_j = a_j b_j g_j``
    (``P_j = p0 prod_{i<j} (1 - c_i)``) in one forward sweep, then runs a reverse linear scan
    (``S_J = G_v``, ``D_m = S_{m+1} - gn_m weights``, ``dL/dc_m = -P_m D_m``, ``S_m = S_{m+1} - c_m D_m``),
    never dividing by ``1 - c``. With ``dc/ds = c ((1 - b) F'(s) - (1 - a)) / tau`` and
    ``dc/dw = a b g' + c (1 - b) / tau``, each step's gradients come from three sums over sectors of
    ``Y = H_m D_m``: ``sum Y``, ``sum Y a`` and ``sum Y b``. So neither memory nor time is spent on tables
    in the forward pass (which a recomputed walk runs twice), and the tables only ever exist for one block.
    The gradients of ``s`` and ``w`` come back as transposed views of ``(J, N)`` tensors.
    """

    #: rows per block of the forward sweep (scratch: ``2 FORWARD_GROUP + 1`` rows of 32 per row, and
    #: ``FORWARD_GROUP + 1`` more with weights)
    FORWARD_BLOCK = 2048
    #: steps per group (logistics evaluated together) in the forward sweep
    FORWARD_GROUP = 4
    #: rows per block of the backward (its transient memory: ``4 J + 6 BACKWARD_GROUP + 4`` rows of 32
    #: per row)
    BACKWARD_BLOCK = 1024
    #: steps per group in the backward
    BACKWARD_GROUP = 4

    @staticmethod
    def forward(ctx, s, w, weights, p0, tau, rounding, hard_forward):
        visible, newly = _live_union(s, w, weights, p0, tau, _DELTA[rounding], rounding if hard_forward else None)
        ctx.tau, ctx.delta = tau, _DELTA[rounding]
        ctx.save_for_backward(s, w, weights, p0)
        return visible, newly

    @staticmethod
    def backward(ctx, grad_visible, grad_newly):
        s, w, weights, p0 = ctx.saved_tensors
        want_newly = weights is not None and grad_newly is not None and grad_newly.numel() > 0
        keep_gn = want_newly and ctx.needs_input_grad[2]
        want_s, want_w, want_p0 = ctx.needs_input_grad[0], ctx.needs_input_grad[1], ctx.needs_input_grad[3]
        if not (want_s or want_w or keep_gn or want_p0):
            return None, None, None, None, None, None, None
        layout = _LiveSteps(w)
        if layout.dense:
            grads = _union_backward(s, w, weights, p0, grad_visible, grad_newly, ctx.tau, ctx.delta,
                                    want_s, want_w, keep_gn, want_p0)
        else:
            grads = layout.backward(s, w, weights, p0, grad_visible, grad_newly, ctx.tau, ctx.delta,
                                    want_s, want_w, keep_gn, want_p0)
        return (*grads, None, None, None)


def _union_backward(s, w, weights, p0, grad_visible, grad_newly, tau, delta, want_s, want_w, keep_gn, want_p0):
    """:class:`SectorUnion`'s backward for widths ``w >= 0``: ``(gs, gw, gweights, gp0)`` (``None`` where
    not wanted)."""
    N, J = s.shape
    inv_tau = 1.0 / tau
    want_newly = weights is not None and grad_newly is not None and grad_newly.numel() > 0
    want_sw = want_s or want_w
    if J == 0:  # visible = p0
        gp0 = (s.new_zeros(N, SECTORS) if grad_visible is None else grad_visible.clone()) if want_p0 else None
        gweights = s.new_zeros(N, SECTORS) if keep_gn else None
        return s.new_zeros(N, 0) if want_s else None, s.new_zeros(N, 0) if want_w else None, gweights, gp0
    gsT = s.new_empty(J, N) if want_s else None
    gwT = s.new_empty(J, N) if want_w else None
    gweights = s.new_empty(N, SECTORS) if keep_gn else None
    gp0 = s.new_empty(N, SECTORS) if want_p0 else None
    group = max(1, min(SectorUnion.BACKWARD_GROUP, J))
    K = _sector_offsets(s, tau)
    make = lambda B: _Plan(s, B, J, group, tau, True, want_newly, keep_gn, want_s, want_sw)  # noqa: E731
    for r, plan in _plans(N, SectorUnion.BACKWARD_BLOCK, make):
        _load(plan, s, w, p0, r, tau, delta)
        _sweep(plan, K, tau, store=True)
        S = _scan(plan, grad_visible, grad_newly, weights, r, want_newly, keep_gn, want_sw, want_p0)
        if want_sw:
            s1, sa, sb = plan.sums.unbind(1)  # (J, B)
            g = plan.gate[:, 0]
            s1_b = torch.sub(s1, sb)  # sum Y (1 - b)
            if want_w:
                # gw = -(g' sum Y + g / tau sum Y (1 - b)), g' = (1 - g^2) / tau
                torch.mul(g, g, out=gwT[:, r]).sub_(1).mul_(s1).sub_(s1_b.mul(g)).mul_(inv_tau)
            if want_s:
                # gs = -g / tau (F' sum Y (1 - b) - sum Y (1 - a))
                torch.mul(s1_b, plan.dF, out=gsT[:, r]).sub_(s1).add_(sa).mul_(g).mul_(-inv_tau)
        if keep_gn:
            gweights[r] = plan.gwt.t()
        if want_p0:
            gp0[r] = S.t()
    return None if gsT is None else gsT.t(), None if gwT is None else gwT.t(), gweights, gp0


class _LiveSteps:
    """Where a union's live steps are: those with a width ``w >= 0``. A negative width covers nothing
    (it is clamped to 0, where the gate ``tanh(w / tau)`` is 0) and gets no gradient, so only live steps
    are swept: rows are sorted by their number of live steps (most first) and each row's live steps are
    moved to the front, in order ("newly" depends on it); rows with the same count form one dense
    segment. On typical frames most samples occlude nothing (their intervals are narrowed below zero by
    ``sector_epsilon``), so the sweeps shrink several-fold.

    ``dense``: every step is live (use the plain sweeps). Otherwise ``rows`` ``(L,)`` are the rows with a
    live step, sorted, ``steps`` ``(L, J)`` each sorted row's step order and ``segments`` a list of
    ``(start, stop, count)`` ranges of sorted rows swept together over their first ``count`` steps. Ranges of rows with fewer
    live steps are merged into the one before (their extra steps are dead: no coverage, no gradient)
    while the padding costs less than a segment's per-step overhead: ``rows * extra < MERGE_ROWS * count``.
    """

    #: padding (row-steps) worth one step of fixed per-operation overhead when merging segments
    MERGE_ROWS = 1500

    def __init__(self, w: torch.Tensor) -> None:
        live = w >= 0
        self.dense = bool(live.all())
        if self.dense:
            return
        J = w.shape[1]
        counts = live.sum(1)
        rows = counts.nonzero()[:, 0]
        counts = counts.index_select(0, rows)
        order = torch.argsort(counts, descending=True, stable=True)
        self.rows, counts = rows.index_select(0, order), counts.index_select(0, order)
        # Each row's live steps first, in order (then its dead ones): step j goes to the number of live
        # steps before it, or past all live steps by the number of dead ones before it.
        lv = live.index_select(0, self.rows).to(torch.float32)  # (L, J)
        before = lv @ torch.ones(J, J, dtype=lv.dtype, device=lv.device).triu()  # live steps up to j
        j1 = torch.arange(1, J + 1, dtype=lv.dtype, device=lv.device)
        dest = torch.where(lv > 0, before - 1, (j1 - before).add_(counts[:, None] - 1)).long()
        steps = torch.arange(J, device=w.device).expand(len(self.rows), J)
        self.steps = torch.empty_like(dest).scatter_(1, dest, steps)
        values, lengths = torch.unique_consecutive(counts, return_counts=True)
        self.segments, start = [], 0
        for count, length in zip(values.tolist(), lengths.tolist()):
            top = self.segments[-1] if self.segments else None
            if top is not None and length * (top[2] - count) < self.MERGE_ROWS * count:
                self.segments[-1] = (top[0], start + length, top[2])
            else:
                self.segments.append((start, start + length, count))
            start += length

    def take(self, x: torch.Tensor | None, start: int, stop: int, count: int | None = None):
        """Rows ``start:stop`` of the sorted layout of ``x`` ``(N, ...)`` (with ``count``: the first
        ``count`` steps, live ones first, of ``x`` ``(N, J)``)."""
        if x is None:
            return None
        x = x.index_select(0, self.rows[start:stop])
        return x if count is None else x.gather(1, self.steps[start:stop, :count])

    def put(self, out: torch.Tensor, value: torch.Tensor, start: int, stop: int, steps: bool) -> None:
        """Writes sorted rows ``start:stop`` (their live steps when ``steps``) back into ``out``."""
        rows = self.rows[start:stop]
        if steps:
            out[rows[:, None], self.steps[start:stop, :value.shape[1]]] = value
        else:
            out[rows] = value

    def forward(self, s, w, weights, p0, sweep):
        """``sweep(s, w, weights, p0) -> (visible, newly)`` over the live segments (widths >= 0)."""
        N, J = s.shape
        s, w = s.contiguous(), w.contiguous()  # (the walk passes transposed views: row gathers are slow)
        visible = torch.ones(N, SECTORS, dtype=s.dtype, device=s.device) if p0 is None else p0.clone()
        newly = s.new_zeros(N, J) if weights is not None else s.new_zeros(N, 0)
        for start, stop, count in self.segments:
            ws = self.take(w, start, stop, count).clamp_min_(0)  # merged rows' extra (dead) steps: zero width
            vis, new = sweep(self.take(s, start, stop, count), ws, self.take(weights, start, stop),
                             self.take(p0, start, stop))
            self.put(visible, vis, start, stop, False)
            if weights is not None:
                self.put(newly, new, start, stop, True)
        return visible, newly

    def backward(self, s, w, weights, p0, grad_visible, grad_newly, tau, delta, want_s, want_w, keep_gn, want_p0):
        N, J = s.shape
        s, w = s.contiguous(), w.contiguous()
        gs = s.new_zeros(N, J) if want_s else None
        gw = s.new_zeros(N, J) if want_w else None
        gweights = s.new_zeros(N, SECTORS) if keep_gn else None
        gp0 = None
        if want_p0:  # rows without live steps pass grad_visible through
            gp0 = s.new_zeros(N, SECTORS) if grad_visible is None else grad_visible.clone()
        want_newly = weights is not None and grad_newly is not None and grad_newly.numel() > 0
        for start, stop, count in self.segments:
            ws = self.take(w, start, stop, count)
            grads = _union_backward(
                self.take(s, start, stop, count), ws.clamp_min(0),
                self.take(weights, start, stop), self.take(p0, start, stop), self.take(grad_visible, start, stop),
                self.take(grad_newly, start, stop, count) if want_newly else None, tau, delta,
                want_s, want_w, keep_gn, want_p0)
            if want_w:  # a dead step (negative width) gets no gradient
                grads = (grads[0], grads[1].masked_fill_(ws < 0, 0.0), *grads[2:])
            for out, value, steps in ((gs, grads[0], True), (gw, grads[1], True), (gweights, grads[2], False),
                                      (gp0, grads[3], False)):
                if out is not None:
                    self.put(out, value, start, stop, steps)
        return gs, gw, gweights, gp0


def _live_union(s, w, weights, p0, tau, delta, rounding=None):
    """The soft union's forward (or, with ``rounding``, the straight-through one: hard coverage) over live
    steps only (``w >= 0``; see :class:`_LiveSteps`)."""
    if rounding is None:
        sweep = lambda s, w, weights, p0: _soft_sweep(s, w, weights, p0, tau, delta)  # noqa: E731
    else:
        sweep = lambda s, w, weights, p0: _hard_sweep(s, w, weights, p0, rounding)  # noqa: E731
    layout = _LiveSteps(w)
    if layout.dense:
        return sweep(s, w, weights, p0)
    return layout.forward(s, w, weights, p0, sweep)


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
        return _live_union(s, w, weights, p0, float(tau), _DELTA[rounding],
                           rounding if mode == "straight_through" else None)
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
