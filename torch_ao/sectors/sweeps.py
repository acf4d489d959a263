"""The blocked soft union's passes over one block of rows: loading the inputs, the logistics of a group
of steps, the forward sweep and the backward's reverse scan (the formulas are derived in
:mod:`.soft_union`; the buffers they work in are :mod:`.blocks`).

Per block of ``B`` rows, step ``j``'s coverage of sector ``k`` is ``c = a b g`` with

    a = sigmoid(K_k + start_arg_j),  K_k = (k + 1) / tau,  start_arg = -s / tau
    b = sigmoid(end_arg_j - K_k),    end_arg = (w - delta + 1 + F(s)) / tau
    g = tanh(w / tau)

(:func:`torch_ao.sectors.rule.soft_coverage` written out), every logistic argument clamped to ``+-CLAMP``:
beyond it a logistic is within ``sigmoid(-30) ~ 1e-13`` of 0 or 1, and no subnormal floats appear
(they are ~100x slower on CPUs).

The smooth floor ``F(s) = sum_{m=1..32} sigmoid((s - m) / tau)`` takes one of two paths. For
``tau > 0.1`` its terms are the complements of ``a``: ``F = sum_k (1 - a_k)`` and
``F' = sum_k a_k (1 - a_k) / tau``, at no extra logistics. For smaller ``tau`` the arguments of ``a``,
``(k + 1) / tau - s / tau``, lose the precision of a small ``F`` in float32; its own narrow window of
logistics (``W <= WINDOW_MAX`` integers around ``s``, :func:`_floor_window_into`) keeps it.
"""
from __future__ import annotations

import math

import torch

from .rule import SECTORS, _sectors

CLAMP = 30.0  # logistic arguments are clamped to +-CLAMP (sigmoid(-30) ~ 9e-14)
TINY = 1e-30  # per-sector visibilities below this are flushed to 0 (no subnormals)
#: widest window of the smooth floor's own logistics (reached at tau = 0.1); for a larger tau the
#: floor comes from the complements of ``a`` instead
WINDOW_MAX = 8


def write_into(op, *args, out: torch.Tensor, **kwargs) -> torch.Tensor:
    """``op(*args, **kwargs)`` written into the scratch view ``out``, and returned: eagerly with ``out=`` (no
    temporary); while compiling out of place and copied in (dynamo does not trace ``out=`` into a
    non-contiguous view, and the compiled graph fuses the copy)."""
    if torch.compiler.is_compiling():
        return out.copy_(op(*args, **kwargs))
    return op(*args, out=out, **kwargs)


def _floor_reach(tau: float) -> int:
    return int(math.ceil(CLAMP * tau)) + 1


def floor_window_width(tau: float) -> int:
    """Number ``W`` of integers in the smooth floor's window at temperature ``tau``."""
    return min(2 * _floor_reach(tau), SECTORS)


def sector_ends(like: torch.Tensor, tau: float) -> torch.Tensor:
    """``K_k = (k + 1) / tau`` ``(32, 1)``: the sectors' upper edges over ``tau``."""
    return ((_sectors(like) + 1) * (1.0 / tau))[:, None]


def expm1_tanh(x: torch.Tensor) -> torch.Tensor:
    """``tanh(x)`` for ``x >= 0``, in place: ``-expm1(-2x) / (2 + expm1(-2x))`` (within 2 ulp; faster)."""
    t = x.mul_(-2).expm1_()
    return t.div_(t.add(2)).neg_()


def _floor_window_into(starts, tau, terms, floor_s, floor_slope):
    """Smooth floor ``F(s)`` of the contiguous ``starts`` into ``floor_s`` (and ``F' tau`` into
    ``floor_slope`` unless ``None``), summed over a window of ``W`` consecutive integers
    ``lo .. lo + W - 1`` inside ``[1, 32]`` that holds every integer within ``CLAMP * tau`` of ``s``: the
    integers ``1 .. lo - 1`` count fully (their logistic is within ``sigmoid(-CLAMP)`` of 1) and those above
    the window not at all, so it costs ``O(W)`` per entry, not ``O(32)``. The ``W`` logistic terms are laid
    out ``(W, M)`` in the flat buffer ``terms`` (``2 W M`` entries with ``floor_slope``)."""
    reach = _floor_reach(tau)
    width = floor_window_width(tau)
    inv_tau = 1.0 / tau
    flat = starts.reshape(-1)
    M = flat.numel()
    lo = torch.floor(flat).sub_(reach - 1).clamp_(1, SECTORS - width + 1)
    z = torch.sub(flat, lo).mul_(inv_tau)
    offsets = torch.arange(width, dtype=starts.dtype, device=starts.device).mul_(inv_tau)[:, None]
    x = write_into(torch.sub, z, offsets, out=terms[:width * M].view(width, M)).clamp_(-CLAMP, CLAMP).sigmoid_()
    write_into(torch.sum, x, 0, out=floor_s.view(M)).add_(lo.sub_(1))
    if floor_slope is not None:
        y = write_into(torch.sub, 1, x, out=terms[width * M:2 * width * M].view(width, M)).mul_(x)
        write_into(torch.sum, y, 0, out=floor_slope.view(M))


def load_block(scratch, s, w, p0, rows, tau, delta):
    """Copies the inputs of ``rows`` (a ``slice`` of ``s, w`` ``(N, J)``, ``p0`` ``(N, 32)`` or ``None``)
    into ``scratch``, steps first: ``start_arg = -s / tau``, ``shifted_width = w - delta + 1``, the gate
    ``tanh(w / tau)``, ``visible = p0`` (or 1) and, on the window path, ``F(s)`` (and ``F' tau``)."""
    inv_tau = 1.0 / tau
    write_into(torch.mul, s[rows].t(), -inv_tau, out=scratch.start_arg[:, 0])
    if scratch.windowed:
        _floor_window_into(s[rows].t().contiguous(), tau, scratch.floor_terms, scratch.floor_s, scratch.floor_slope)
    write_into(torch.add, w[rows].t(), 1 - delta, out=scratch.shifted_width)
    expm1_tanh(write_into(torch.mul, w[rows].t(), inv_tau, out=scratch.gate[:, 0]))
    if p0 is None:
        scratch.visible.fill_(1)
    else:
        scratch.visible.copy_(p0[rows].t())


def _logistics(grp, ends, inv_tau):
    """A group's ``a`` and ``b`` ``(q, 32, B)`` into ``grp.after_start`` and ``grp.within_count``, and on
    the complements path ``F = sum_k (1 - a_k)`` (and ``F' tau``)."""
    a, b = grp.after_start, grp.within_count
    write_into(torch.add, ends, grp.start_arg, out=a).clamp_(-CLAMP, CLAMP).sigmoid_()
    floor_s = grp.floor_s
    if floor_s is None:
        # a sum of the complements, not 32 - sum a (that loses the precision of a small F); b's buffer
        # is the scratch
        not_a = write_into(torch.sub, 1, a, out=b)
        floor_s = write_into(torch.sum, not_a, 1, out=grp.floor_scratch)
        if grp.floor_slope is not None:  # F'(s) tau = sum_k a_k (1 - a_k)
            write_into(torch.sum, not_a.mul_(a), 1, out=grp.floor_slope)
    write_into(torch.add, grp.shifted_width, floor_s, out=grp.end_arg[:, 0]).mul_(inv_tau)
    write_into(torch.sub, grp.end_arg, ends, out=b).clamp_(-CLAMP, CLAMP).sigmoid_()


def sweep(scratch, ends, tau):
    """The forward sweep over one loaded block, in place: per group of steps :func:`_logistics` and
    ``c = a b g``, then per step ``P <- P - c_j P`` and the flush of tiny values.

    Forward scratch: ``scratch.visible`` ends as the block's visibility ``(32, B)`` and, with weights,
    ``scratch.newly`` ``(J, B)`` receives ``sum_k weights_k c_jk P_jk``. Backward scratch: step ``j``
    leaves ``a_j``, ``b_j``, ``H_j = a_j b_j P_j`` and ``c_j`` in ``scratch.tables``,
    ``scratch.floor_slope`` (if any) receives ``F'(s)``, and the last update is skipped (``visible`` is
    scratch then)."""
    inv_tau = 1.0 / tau
    P = scratch.visible
    tables = scratch.tables is not None
    newly = not tables and scratch.newly is not None
    last = scratch.shifted_width.shape[0] - 1
    for grp in scratch.groups:
        _logistics(grp, ends, inv_tau)
        if tables:
            write_into(torch.mul, grp.after_start, grp.within_count, out=grp.ungated)  # a b
            write_into(torch.mul, grp.ungated, grp.gate, out=grp.coverage)  # c = a b g
        else:
            grp.coverage.mul_(grp.after_start).mul_(grp.gate)  # c = a b g (in b's buffer)
        for i in range(grp.q):
            j = grp.steps.start + i
            if tables:
                write_into(torch.mul, grp.ungated_rows[i], P, out=scratch.ab_visible_rows[j])  # H_j = a b P_j
                if j == last:
                    break
            if newly:
                # newly covered share c_j P_j
                P.sub_(write_into(torch.mul, grp.coverage_rows[i], P, out=grp.share_rows[i]))
            else:
                P.addcmul_(grp.coverage_rows[i], P, value=-1)  # P_j (1 - c_j), in [0, P_j]
            torch.nn.functional.threshold_(P, TINY, 0.0)  # flush tiny values (no subnormals)
        if newly:
            write_into(torch.sum, grp.shares.mul_(scratch.weights), 1, out=scratch.newly[grp.steps])
    if scratch.floor_slope is not None:
        scratch.floor_slope.mul_(inv_tau)


def reverse_scan(scratch, grad_visible, grad_newly, weights, rows, wanted):
    """The backward's reverse linear scan over one block's tables, group by group (last first):

        S_J = grad_visible,  D_m = S_{m+1} - gn_m weights,  S_m = S_{m+1} - c_m D_m

    then per group ``Y = H_m D_m`` and the sums over sectors ``scratch.sector_sums[m]`` =
    (``sum Y``, ``sum Y a``, ``sum Y b``) (when ``s`` or ``w`` want a gradient);
    ``scratch.grad_weights`` ``(32, B)`` receives ``sum_m gn_m g_m H_m`` (when ``wanted.weights``).
    ``grad_newly`` is ``None`` when ``newly`` has no gradient. Returns ``S_0`` ``(32, B)``, the gradient of
    ``p0`` (computed only when ``wanted.p0``)."""
    groups = scratch.groups[::-1]
    top = groups[0].grad_visible_rows[-1]  # S_J
    if grad_visible is None:
        top.zero_()
    else:
        top.copy_(grad_visible[rows].t())
    with_newly = grad_newly is not None
    if with_newly:
        weights_t = scratch.weights.copy_(weights[rows].t())
        gn = list(scratch.grad_newly.copy_(grad_newly[rows].t()).unbind(0))
    if wanted.weights:
        gn_gate = list(write_into(torch.mul, scratch.grad_newly, scratch.gate[:, 0], out=scratch.gn_gate).unbind(0))
        grad_weights = scratch.grad_weights.zero_()
        H = scratch.ab_visible_rows
    want_sums = wanted.s or wanted.w
    S = top
    for grp in groups:
        S_rows, D_rows = grp.grad_visible_rows, grp.keep_grad_rows
        if S is not S_rows[-1]:
            S_rows[-1].copy_(S)
        for i in range(grp.q - 1, -1, -1):
            m = grp.steps.start + i
            if with_newly:
                write_into(torch.addcmul, S_rows[i + 1], weights_t, gn[m], value=-1, out=D_rows[i])
            if wanted.weights:
                grad_weights.addcmul_(H[m], gn_gate[m])
            if m > 0 or wanted.p0:
                write_into(torch.addcmul, S_rows[i + 1], grp.coverage_rows[i], D_rows[i], value=-1, out=S_rows[i])
        S = S_rows[0]
        if want_sums:
            write_into(torch.mul, grp.ab_visible, grp.keep_grad, out=grp.y)  # Y = a b P D
            write_into(torch.mul, grp.y_keepdim, grp.a_and_b, out=grp.y_ab)  # Y a, Y b
            write_into(torch.sum, grp.terms, 2, out=grp.sector_sums)
    return S
