r"""The soft union of a slice's steps, per sector, as a custom autograd function (:class:`SectorUnion`).

Forward. Step ``j`` (of ``J``) covers sector ``k`` by ``c_jk = a_jk b_jk g_j`` in ``[0, 1]``
(:func:`~.rule.soft_coverage`). The visibility before step ``j`` is ``P_j``; a step covers that share of
what is still visible::

    P_0 = p0,   P_{j+1} = P_j - c_j P_j,   visible = P_J = p0 prod_j (1 - c_j)
    newly_j = sum_k weights_k c_jk P_jk              (the share step j newly occludes, weighted)

the smooth form of the shaders' ``mask |= bits`` and ``bitCount(bits & ~mask)``.

Backward. With the loss ``L(visible, newly)``, ``gv = dL/dvisible`` and ``gn_j = dL/dnewly_j``, let
``S_m = dL/dP_m`` (through every later step). Each step is linear in ``P_m``, so a reverse scan gives
all of them, never dividing by ``1 - c``::

    S_J = gv,   D_m = S_{m+1} - gn_m weights,   S_m = S_{m+1} - c_m D_m,   dL/dp0 = S_0
    dL/dc_m = -P_m D_m,   dL/dweights = sum_m gn_m c_m P_m

(``D_m`` is what a share of ``P_m`` is worth kept visible rather than covered). With
``a = sigmoid((k + 1 - s) / tau)``, ``b = sigmoid((w + F(s) - delta - k) / tau)``, ``g = tanh(w / tau)``
and ``H_m = a_m b_m P_m``::

    dc/ds = c ((1 - b) F'(s) - (1 - a)) / tau,        dc/dw = a b g' + c (1 - b) / tau,   g' = (1 - g^2) / tau
    dL/ds_m = -(g / tau) (F' sum_k Y (1 - b) - sum_k Y (1 - a)),     Y = H_m D_m
    dL/dw_m = -(g' sum_k Y + (g / tau) sum_k Y (1 - b))

so each step's gradients need three sums over sectors: ``sum Y``, ``sum Y a`` and ``sum Y b``.

Memory. The forward keeps only its ``(N, J)`` inputs (no ``(N, J, 32)`` graph; a recomputed walk runs it
twice). The backward rebuilds, block by block of rows, each step's ``a``, ``b``, ``H`` and ``c`` in one
forward sweep and runs the scan over them (:mod:`.sweeps`, :mod:`.blocks`), so its tables only ever exist
for one block. Only live steps (``w >= 0``) are swept (:class:`~.live_steps.LiveSteps`).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from .blocks import BackwardScratch, ForwardScratch, blocks
from .hard_union import coverage_union
from .live_steps import LiveSteps
from .rule import SECTORS, rounding_offset
from .sweeps import load_block, reverse_scan, sector_ends, sweep, write_into

__all__ = ["SectorUnion"]


class UnionGrads(NamedTuple):
    """Gradients of the union's inputs ``s, w`` ``(N, J)``, ``weights, p0`` ``(N, 32)``; ``None`` where
    not wanted."""

    s: torch.Tensor | None
    w: torch.Tensor | None
    weights: torch.Tensor | None
    p0: torch.Tensor | None


class Wanted(NamedTuple):
    """Which of the union's inputs want a gradient."""

    s: bool
    w: bool
    weights: bool
    p0: bool


class UnionBlocks:
    """Block and group sizes of the soft union's sweeps (a plain class, so that ``torch.compile`` reads them
    as constants: dynamo cannot read attributes of an autograd Function's class while tracing)."""

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


class SectorUnion(torch.autograd.Function):
    """Union over the steps of one slice, per sector, with the newly covered share of each step.

    Inputs: ``s, w`` ``(N, J)`` interval starts and widths in sector units (step order matters for
    ``newly``; a negative width is an empty interval); ``weights`` ``(N, 32)`` per-sector weights of
    ``newly`` (or ``None``: no ``newly`` output); ``p0`` ``(N, 32)`` initial per-sector visibility (or
    ``None`` = 1); ``tau`` (sector units), ``rounding``, ``hard_forward`` (straight-through: hard coverage
    in forward, soft gradients in backward).

    Outputs: ``visible`` ``(N, 32)`` = ``p0 prod_j (1 - c_j)`` and ``newly`` ``(N, J)`` =
    ``sum_k weights_k c_jk P_jk`` (empty ``(N, 0)`` without weights). The gradients of ``s`` and ``w``
    come back as transposed views of ``(J, N)`` tensors. The module docstring derives the backward.
    """

    @staticmethod
    def forward(ctx, s, w, weights, p0, tau, rounding, hard_forward):
        delta = rounding_offset(rounding)
        visible, newly = union_forward(s, w, weights, p0, tau, delta, rounding if hard_forward else None)
        ctx.tau, ctx.delta = tau, delta
        ctx.all_steps = torch.compiler.is_compiling()
        ctx.save_for_backward(s, w, weights, p0)
        return visible, newly

    @staticmethod
    def backward(ctx, grad_visible, grad_newly):
        s, w, weights, p0 = ctx.saved_tensors
        with_newly = weights is not None and grad_newly is not None and grad_newly.numel() > 0
        need_s, need_w, need_weights, need_p0 = ctx.needs_input_grad[:4]
        wanted = Wanted(s=need_s, w=need_w, weights=with_newly and need_weights, p0=need_p0)
        if not any(wanted):
            return None, None, None, None, None, None, None
        grad_newly = grad_newly if with_newly else None
        if ctx.all_steps:
            grads = _dense_backward(s, w.clamp_min(0), weights, p0, grad_visible, grad_newly, ctx.tau, ctx.delta,
                                    wanted)
            if wanted.w:
                grads = grads._replace(w=grads.w.masked_fill(w < 0, 0.0))
            return (*grads, None, None, None)
        layout = LiveSteps(w)
        if layout.dense:
            grads = _dense_backward(s, w, weights, p0, grad_visible, grad_newly, ctx.tau, ctx.delta, wanted)
        else:
            grads = _live_backward(layout, s, w, weights, p0, grad_visible, grad_newly, ctx.tau, ctx.delta, wanted)
        return (*grads, None, None, None)


def union_forward(s, w, weights, p0, tau, delta, hard_rounding=None):
    """The soft union's forward ``(visible, newly)`` (or, with ``hard_rounding``, the straight-through
    one: :func:`~.hard_union.coverage_union`) over the live steps only; no graph, no tables. Shapes as
    :class:`SectorUnion`; ``delta`` the rounding's offset (:func:`~.rule.rounding_offset`)."""
    if hard_rounding is None:
        dense = lambda s, w, weights, p0: _dense_forward(s, w, weights, p0, tau, delta)  # noqa: E731
    else:
        dense = lambda s, w, weights, p0: coverage_union(s, w, weights, p0, hard_rounding)  # noqa: E731
    if torch.compiler.is_compiling():
        # every step, the dead ones at zero width (they cover nothing): the live-step layout has sizes
        # that depend on the data, which the compiled graph cannot have
        return dense(s, w.clamp_min(0), weights, p0)
    layout = LiveSteps(w)
    if layout.dense:
        return dense(s, w, weights, p0)
    N, J = s.shape
    s, w = s.contiguous(), w.contiguous()  # (the walk passes transposed views: row gathers are slow)
    visible = torch.ones(N, SECTORS, dtype=s.dtype, device=s.device) if p0 is None else p0.clone()
    newly = s.new_zeros(N, J) if weights is not None else s.new_zeros(N, 0)
    for start, stop, count in layout.segments:
        ws = layout.take(w, start, stop, count).clamp_min_(0)  # merged rows' extra (dead) steps: zero width
        vis, new = dense(layout.take(s, start, stop, count), ws, layout.take(weights, start, stop),
                         layout.take(p0, start, stop))
        layout.put(visible, vis, start, stop, False)
        if weights is not None:
            layout.put(newly, new, start, stop, True)
    return visible, newly


def _dense_forward(s, w, weights, p0, tau, delta):
    """The soft forward over every step (widths ``w >= 0``), in blocks of
    :attr:`UnionBlocks.FORWARD_BLOCK` rows and groups of :attr:`UnionBlocks.FORWARD_GROUP` steps."""
    N, J = s.shape
    with_newly = weights is not None
    ends = sector_ends(s, tau)
    group = max(1, min(UnionBlocks.FORWARD_GROUP, J))
    visible = s.new_empty(N, SECTORS)
    newly = s.new_empty(N, J) if with_newly else s.new_zeros(N, 0)
    make = lambda B: ForwardScratch(s, B, J, group, tau, with_newly)  # noqa: E731
    for rows, scratch in blocks(N, UnionBlocks.FORWARD_BLOCK, make):
        load_block(scratch, s, w, p0, rows, tau, delta)
        if with_newly:
            scratch.weights.copy_(weights[rows].t())
        sweep(scratch, ends, tau)
        visible[rows] = scratch.visible.t()
        if with_newly:
            newly[rows] = scratch.newly.t()
    return visible, newly


def _dense_backward(s, w, weights, p0, grad_visible, grad_newly, tau, delta, wanted: Wanted) -> UnionGrads:
    """:class:`SectorUnion`'s backward over every step (widths ``w >= 0``), in blocks of
    :attr:`UnionBlocks.BACKWARD_BLOCK` rows; ``grad_newly`` is ``None`` when ``newly`` has no gradient."""
    N, J = s.shape
    inv_tau = 1.0 / tau
    want_sums = wanted.s or wanted.w
    if J == 0:  # visible = p0
        gp0 = (s.new_zeros(N, SECTORS) if grad_visible is None else grad_visible.clone()) if wanted.p0 else None
        return UnionGrads(s=s.new_zeros(N, 0) if wanted.s else None, w=s.new_zeros(N, 0) if wanted.w else None,
                          weights=s.new_zeros(N, SECTORS) if wanted.weights else None, p0=gp0)
    gs_t = s.new_empty(J, N) if wanted.s else None
    gw_t = s.new_empty(J, N) if wanted.w else None
    gweights = s.new_empty(N, SECTORS) if wanted.weights else None
    gp0 = s.new_empty(N, SECTORS) if wanted.p0 else None
    group = max(1, min(UnionBlocks.BACKWARD_GROUP, J))
    ends = sector_ends(s, tau)
    make = lambda B: BackwardScratch(s, B, J, group, tau, grad_newly is not None, wanted.weights,  # noqa: E731
                                     wanted.s, want_sums)
    for rows, scratch in blocks(N, UnionBlocks.BACKWARD_BLOCK, make):
        load_block(scratch, s, w, p0, rows, tau, delta)
        sweep(scratch, ends, tau)
        S0 = reverse_scan(scratch, grad_visible, grad_newly, weights, rows, wanted)
        if want_sums:
            sum_y, sum_ya, sum_yb = scratch.sector_sums.unbind(1)  # (J, B)
            g = scratch.gate[:, 0]
            sum_y_not_b = torch.sub(sum_y, sum_yb)  # sum Y (1 - b)
            if wanted.w:
                # -(g' sum Y + g / tau sum Y (1 - b)), g' = (1 - g^2) / tau
                write_into(torch.mul, g, g, out=gw_t[:, rows]).sub_(1).mul_(sum_y).sub_(sum_y_not_b.mul(g)) \
                    .mul_(inv_tau)
            if wanted.s:
                # -(g / tau) (F' sum Y (1 - b) - sum Y (1 - a))
                write_into(torch.mul, sum_y_not_b, scratch.floor_slope, out=gs_t[:, rows]).sub_(sum_y).add_(sum_ya) \
                    .mul_(g).mul_(-inv_tau)
        if wanted.weights:
            gweights[rows] = scratch.grad_weights.t()
        if wanted.p0:
            gp0[rows] = S0.t()
    return UnionGrads(s=None if gs_t is None else gs_t.t(), w=None if gw_t is None else gw_t.t(),
                      weights=gweights, p0=gp0)


def _live_backward(layout: LiveSteps, s, w, weights, p0, grad_visible, grad_newly, tau, delta,
                   wanted: Wanted) -> UnionGrads:
    """:func:`_dense_backward` over the live segments of ``layout``; rows without a live step pass
    ``grad_visible`` through to ``p0``, and a dead step (negative width) gets no gradient."""
    N, J = s.shape
    s, w = s.contiguous(), w.contiguous()
    out = UnionGrads(s=s.new_zeros(N, J) if wanted.s else None, w=s.new_zeros(N, J) if wanted.w else None,
                     weights=s.new_zeros(N, SECTORS) if wanted.weights else None,
                     p0=(s.new_zeros(N, SECTORS) if grad_visible is None else grad_visible.clone())
                     if wanted.p0 else None)
    for start, stop, count in layout.segments:
        ws = layout.take(w, start, stop, count)
        grads = _dense_backward(
            layout.take(s, start, stop, count), ws.clamp_min(0), layout.take(weights, start, stop),
            layout.take(p0, start, stop), layout.take(grad_visible, start, stop),
            layout.take(grad_newly, start, stop, count), tau, delta, wanted)
        if wanted.w:
            grads.w.masked_fill_(ws < 0, 0.0)
        for total, part, per_step in ((out.s, grads.s, True), (out.w, grads.w, True),
                                      (out.weights, grads.weights, False), (out.p0, grads.p0, False)):
            if total is not None:
                layout.put(total, part, start, stop, per_step)
    return out
