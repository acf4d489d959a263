"""Where a union's live steps are, so that the soft sweeps skip the rest.

A step with a negative width covers nothing (its width is clamped to 0, where the gate ``tanh(w / tau)``
is 0) and gets no gradient. On typical frames most samples occlude nothing (the bitmask interval
narrows them below zero by ``sector_epsilon``), so sweeping only the live steps (``w >= 0``) shrinks the
sweeps several-fold.
"""
from __future__ import annotations

import torch


class LiveSteps:
    """The layout of the live steps (``w >= 0``) of widths ``w`` ``(N, J)``.

    Rows with a live step are sorted by their number of live steps (most first) and each row's live steps
    are moved to the front, in order ("newly" depends on it); rows with the same count form one dense
    segment. Ranges of rows with fewer live steps are merged into the segment before them (their extra
    steps are dead: no coverage, no gradient) while the padding costs less than a segment's per-step
    overhead: ``rows * extra < MERGE_ROWS * count``.

    ``dense``: every step is live (sweep the inputs as they are). Otherwise ``rows`` ``(L,)`` are the rows
    with a live step, sorted, ``steps`` ``(L, J)`` each sorted row's step order and ``segments`` a list of
    ``(start, stop, count)`` ranges of sorted rows swept together over their first ``count`` steps.
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
        ``count`` steps, live ones first, of ``x`` ``(N, J)``); ``None`` for ``None``."""
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
