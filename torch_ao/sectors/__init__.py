"""Visibility-bitmask sectors: hard 32-bit masks (bit for bit as the shaders) and soft, differentiable coverage.

Modules, one concept each:

* :mod:`.rule` -- the sector rule of one step: interval, hard counts and masks (ceil/round/floor),
  popcount, soft coverage. Read it beside the bitmask blog's ``UpdatePartitions``.
* :mod:`.union` -- :func:`sector_union`, the entry point: the union over a slice's steps in any mode.
* :mod:`.hard_union` -- the hard unions (integer masks; the same rule on float visibility).
* :mod:`.soft_union` -- :class:`SectorUnion`, the soft union's custom autograd function (its module
  docstring derives the forward and the backward's reverse scan).
* :mod:`.live_steps`, :mod:`.blocks`, :mod:`.sweeps` -- the soft union's engine: which steps are
  swept, the per-block scratch buffers, and the forward sweep and reverse scan over one block.
"""
from . import rule, soft_union, union
from .rule import (ROUNDINGS, SECTORS, bits_to_mask, hard_count, hard_coverage, hard_mask, mask_bits, popcount32,
                   sector_interval, soft_coverage, soft_floor)
from .soft_union import SectorUnion
from .union import MODES, sector_union

__all__ = [*rule.__all__, *soft_union.__all__, *union.__all__]
