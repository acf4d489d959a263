"""Scratch buffers of the blocked soft union: one set per block size, reused by every block and step.

Both sweeps (:mod:`.sweeps`) work on blocks of ``B`` rows in a sector-major layout: a block's step
inputs are ``(J, B)`` (or ``(J, 1, B)``, to broadcast over sectors) and its per-sector tensors
``(32, B)``, so sums over sectors are adds of rows. The buffers are allocated once per call and block
size (fresh ``(N, 32)`` tensors per step cost page faults and cache misses), and the views each group of
steps works on are built with them, not per step. The logistics of a group of ``Q`` consecutive steps
are evaluated together (fewer, larger ops); the visibility update is one ``(32, B)`` op per step.
"""
from __future__ import annotations

import torch

from .rule import SECTORS
from .sweeps import WINDOW_MAX, floor_window_width


class _StepGroup:
    """Views of one group of ``q`` consecutive steps ``steps`` (a ``slice`` of ``range(J)``) of a scratch:
    ``after_start`` (``a``), ``within_count`` (``b``), ``coverage`` (``c = a b g``), ``ungated`` (``a b``,
    or ``None``), each ``(q, 32, B)``; the group's rows of the loaded inputs; ``floor_scratch`` ``(q, B)``
    and ``end_arg`` ``(q, 1, B)`` for :func:`.sweeps._logistics`."""

    def __init__(self, scratch, steps, after_start, within_count, coverage, ungated, floor_scratch, end_arg):
        self.steps, self.q = steps, steps.stop - steps.start
        self.after_start, self.within_count, self.coverage, self.ungated = after_start, within_count, coverage, ungated
        self.coverage_rows = list(coverage.unbind(0))
        self.ungated_rows = None if ungated is None else list(ungated.unbind(0))
        self.start_arg, self.shifted_width, self.gate = (scratch.start_arg[steps], scratch.shifted_width[steps],
                                                          scratch.gate[steps])
        self.floor_scratch, self.end_arg = floor_scratch, end_arg
        self.floor_slope = None if scratch.floor_slope is None else scratch.floor_slope[steps]
        self.floor_s = None if scratch.floor_s is None else scratch.floor_s[steps]  # None: from the complements


def _step_groups(J: int, Q: int) -> list[slice]:
    return [slice(j0, min(j0 + Q, J)) for j0 in range(0, J, Q)]


class _Scratch:
    """The loaded inputs of a block of ``B`` rows and ``J`` steps (:func:`.sweeps.load_block`):
    ``start_arg`` ``(J, 1, B)``, ``shifted_width`` ``(J, B)``, ``gate`` ``(J, 1, B)``, ``visible``
    ``(32, B)``; on the window path of the smooth floor ``floor_s`` ``(J, B)`` and its logistics
    ``floor_terms``; ``floor_slope`` ``(J, B)`` (``F'(s)``) when ``slope``."""

    tables = None

    def __init__(self, like: torch.Tensor, B: int, J: int, tau: float, slope: bool, newly: bool):
        self._empty = lambda *shape: like.new_empty(shape)
        e = self._empty
        width = floor_window_width(tau)
        self.windowed = width <= WINDOW_MAX
        self.floor_s = e(J, B) if self.windowed else None
        self.floor_terms = e((2 if slope else 1) * width * J * B) if self.windowed else None
        self.start_arg, self.shifted_width, self.gate = e(J, 1, B), e(J, B), e(J, 1, B)
        self.visible = e(SECTORS, B)
        self.weights = e(SECTORS, B) if newly else None
        self.floor_slope = e(J, B) if slope else None
        self.groups: list[_StepGroup] = []


class ForwardScratch(_Scratch):
    """Forward sweep buffers for ``B`` rows, ``J`` steps in groups of ``Q``: one group's ``a`` and ``b``
    at a time (``c`` overwrites ``b``) and, with ``newly``, the per-sector ``weights`` ``(32, B)``, the
    group's newly covered shares ``c_j P_j`` (``grp.shares``) and ``newly`` ``(J, B)``."""

    def __init__(self, like: torch.Tensor, B: int, J: int, Q: int, tau: float, newly: bool):
        super().__init__(like, B, J, tau, slope=False, newly=newly)
        e = self._empty
        self.newly = e(J, B) if newly else None
        floor_scratch, end_arg = e(Q, B), e(Q, 1, B)
        after_start, within_count = e(Q, SECTORS, B), e(Q, SECTORS, B)
        shares = e(Q, SECTORS, B) if newly else None
        for steps in _step_groups(J, Q):
            q = steps.stop - steps.start
            grp = _StepGroup(self, steps, after_start[:q], within_count[:q], within_count[:q], None,
                             floor_scratch[:q], end_arg[:q])
            if newly:
                grp.shares, grp.share_rows = shares[:q], list(shares[:q].unbind(0))
            self.groups.append(grp)


class BackwardScratch(_Scratch):
    """Backward buffers for ``B`` rows, ``J`` steps in groups of ``Q``: the tables ``(J, 4, 32, B)``
    (``a_j``, ``b_j``, ``H_j = a_j b_j P_j``, ``c_j``) of the forward sweep, and the reverse scan's
    (:func:`.sweeps.reverse_scan`): a group's ``S_m`` ``(Q + 1, 32, B)`` (``grp.grad_visible_rows``) and
    ``D_m`` (``grp.keep_grad``; the ``S_{m+1}`` themselves without ``newly``); with ``sums`` the products
    ``Y, Y a, Y b`` (``grp.terms`` ``(q, 3, 32, B)``) and their sums over sectors ``sector_sums``
    ``(J, 3, B)``; with ``newly``, ``weights`` and ``grad_newly`` ``(J, B)``; with ``want_weights``,
    ``grad_weights`` ``(32, B)`` and ``gn_gate`` ``(J, B)``; with ``slope``, ``floor_slope``."""

    def __init__(self, like: torch.Tensor, B: int, J: int, Q: int, tau: float, newly: bool, want_weights: bool,
                 slope: bool, sums: bool):
        super().__init__(like, B, J, tau, slope=slope, newly=newly)
        e = self._empty
        self.grad_newly = e(J, B) if newly else None
        ungated = e(Q, SECTORS, B)
        floor_scratch, end_arg = e(Q, B), e(Q, 1, B)
        self.tables = e(J, 4, SECTORS, B)
        self.ab_visible_rows = list(self.tables[:, 2].unbind(0))
        self.grad_visible = e(Q + 1, SECTORS, B)  # S_{m0} .. S_{m1} of a group
        keep_grad = e(Q, SECTORS, B) if newly else None
        terms = e(Q, 3, SECTORS, B) if sums else None
        self.sector_sums = e(J, 3, B) if sums else None
        self.grad_weights = e(SECTORS, B) if want_weights else None
        self.gn_gate = e(J, B) if want_weights else None
        for steps in _step_groups(J, Q):
            q = steps.stop - steps.start
            grp = _StepGroup(self, steps, self.tables[steps, 0], self.tables[steps, 1], self.tables[steps, 3],
                             ungated[:q], floor_scratch[:q], end_arg[:q])
            grp.ab_visible, grp.a_and_b = self.tables[steps, 2], self.tables[steps, :2]
            grp.grad_visible_rows = list(self.grad_visible[:q + 1].unbind(0))
            grp.keep_grad = self.grad_visible[1:q + 1] if keep_grad is None else keep_grad[:q]
            grp.keep_grad_rows = list(grp.keep_grad.unbind(0))
            if terms is not None:
                grp.terms, grp.y, grp.y_keepdim, grp.y_ab = terms[:q], terms[:q, 0], terms[:q, :1], terms[:q, 1:]
                grp.sector_sums = self.sector_sums[steps]
            self.groups.append(grp)


def blocks(N: int, block: int, make):
    """``(rows, scratch)`` for each block of ``block`` rows of ``N`` (``rows`` a ``slice``), with one
    ``make(B)`` scratch per distinct block size ``B``."""
    made = {}
    for start in range(0, N, block):
        B = min(block, N - start)
        if B not in made:
            made[B] = make(B)
        yield slice(start, start + B), made[B]
