"""The sector rule: which of a slice's 32 sectors one step occludes, as hard bits and as soft coverage.

A slice's hemisphere is split into ``SECTORS = 32`` equal sectors. One step of the slice walk occludes
the interval ``[min, max]`` of ``[0, 1]`` (its front and back angles mapped across the hemisphere). The
bitmask blog's ``UpdatePartitions`` and the SSILVB GLSL article's ``updateSectors`` turn it into bits::

    start = uint(min * 32)                  # s = 32 min (sector units), floored; s >= 0
    count = ceil((max - min) * 32)          # w = 32 (max - min); the blog also names round and floor
    bits  = count > 0 ? (0xFFFFFFFF >> (32 - count)) << start : 0      # truncated to 32 bits
    mask |= bits

The slice's AO is ``1 - bitCount(mask) / 32`` (the blog's ``ComputeAO``); the sectors a step newly
occludes are ``bits & ~mask`` (the blog's ``ComputeGI``). The rounding says how much of a sector the
interval must cover: ceil, touch it; round (the blog's C# ``OccludeSectors``), half of it; floor, all of it.

Sector ``k`` is on iff ``floor(s) <= k`` and ``n = k - floor(s) < count``. For an integer ``n``:
``n < ceil(w) <=> n < w``, ``n < round(w) <=> n + 1/2 < w`` and ``n < floor(w) <=> n + 1 <= w`` (ties
aside). So with ``delta = 0, 1/2, 1`` (ceil, round, floor), sector ``k`` is on iff ``s < k + 1`` and
``w - (k - floor(s)) - delta > 0``. :func:`soft_coverage` replaces each test by a logistic of temperature
``tau`` (in sector units) and ``floor(s)`` by a smooth staircase; it tends to the hard rule as ``tau -> 0``.

Hard masks are 32-bit values held in ``int64`` tensors (torch has no ``uint32`` arithmetic).
"""
from __future__ import annotations

import torch

from ..checks import check_choice, check_float

__all__ = [
    "SECTORS",
    "ROUNDINGS",
    "sector_interval",
    "hard_count",
    "hard_mask",
    "popcount32",
    "mask_bits",
    "bits_to_mask",
    "hard_coverage",
    "soft_floor",
    "soft_coverage",
]

SECTORS = 32
ROUNDINGS = ("ceil", "round", "floor")
_OFFSET = {"ceil": 0.0, "round": 0.5, "floor": 1.0}
_FULL = 0xFFFFFFFF


def rounding_offset(rounding: str) -> float:
    """``delta`` of the rule for ``rounding`` (``"ceil"`` 0, ``"round"`` 1/2, ``"floor"`` 1); raises
    ``ValueError`` naming ``rounding`` otherwise."""
    return _OFFSET[check_choice("rounding", rounding, ROUNDINGS)]


def sector_interval(min_h: torch.Tensor, max_h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Start and width ``(s, w) = (32 min, 32 (max - min))`` in sector units of the intervals
    ``[min_h, max_h]`` (any shape, in ``[0, 1]``), as ``UpdatePartitions`` computes them."""
    return min_h * SECTORS, (max_h - min_h) * SECTORS


def hard_count(w: torch.Tensor, rounding: str = "ceil") -> torch.Tensor:
    """Number of sectors ``ceil(w)``, ``round(w)`` (ties to even, as HLSL ``round``) or ``floor(w)`` of
    widths ``w`` (any shape, sector units), as ``int64`` clamped to ``[0, 32]``."""
    check_choice("rounding", rounding, ROUNDINGS)
    fn = {"ceil": torch.ceil, "round": torch.round, "floor": torch.floor}[rounding]
    return fn(w.detach()).clamp(0, SECTORS).to(torch.int64)


def hard_mask(s: torch.Tensor, w: torch.Tensor, rounding: str = "ceil") -> torch.Tensor:
    """32-bit sector masks (``int64``, the shape of ``s``) of the intervals starting at ``s`` with widths
    ``w`` (sector units): ``UpdatePartitions`` / ``updateSectors`` bit for bit, with ``count`` by
    ``rounding``. A start past sector 31 shifts every bit out (as the shaders' 32-bit shift)."""
    start = torch.floor(s.detach()).clamp(0, 63).to(torch.int64)
    count = hard_count(w, rounding)
    full = torch.full_like(count, _FULL)
    run = torch.where(count > 0, full >> (SECTORS - count).clamp(0, SECTORS), torch.zeros_like(count))
    return (run << start) & _FULL


def popcount32(x: torch.Tensor) -> torch.Tensor:
    """Number of set bits (``int64``, the shape of ``x``) of 32-bit values in an integer tensor: the
    SSILVB GLSL article's ``bitCount`` (the bit-twiddling population count)."""
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
    """Sector indices ``lo .. hi - 1`` ``(hi - lo,)`` in the dtype and device of ``like``."""
    return torch.arange(lo, hi, dtype=like.dtype, device=like.device)


def hard_coverage(s: torch.Tensor, w: torch.Tensor, rounding: str = "ceil") -> torch.Tensor:
    """Float 0/1 coverage ``(..., 32)`` of the intervals ``(s, w)`` ``(...)``: :func:`mask_bits` of
    :func:`hard_mask`, evaluated per sector (``floor(s) <= k < floor(s) + count``)."""
    k = _sectors(s)
    start = torch.floor(s.detach())[..., None]
    count = hard_count(w, rounding).to(s.dtype)[..., None]
    n = k - start
    return ((n >= 0) & (n < count)).to(s.dtype)


def soft_floor(s: torch.Tensor, tau: float) -> torch.Tensor:
    """Smooth ``floor(s)`` on ``[0, 32]`` (the shape of ``s``): ``sum_{m=1..32} sigmoid((s - m) / tau)``."""
    m = _sectors(s, 1, SECTORS + 1)
    return torch.sigmoid((s[..., None] - m) / tau).sum(-1)


def soft_coverage(s: torch.Tensor, w: torch.Tensor, tau: float, rounding: str = "ceil") -> torch.Tensor:
    """Soft coverage ``(..., 32)`` in ``[0, 1]`` of the intervals ``(s, w)`` ``(...)`` (sector units),
    differentiable by autograd: per sector ``k``

        a_k = sigmoid((k + 1 - s) / tau)                     # s < k + 1
        b_k = sigmoid((w - (k - F(s)) - delta) / tau)        # k - floor(s) < count, F = soft_floor
        c_k = a_k b_k tanh(w / tau)                          # the gate: a zero width covers nothing

    with ``w`` clamped at 0. ``tau -> 0`` gives :func:`hard_coverage`. This is the plain definition; the
    blocked union (:mod:`.soft_union`) evaluates the same formula without a per-step graph.
    """
    delta = rounding_offset(rounding)
    check_float("tau", tau, 0.0, open_minimum=True)
    k = _sectors(s)
    F = soft_floor(s, tau)
    w = w.clamp_min(0)
    a = torch.sigmoid((k + 1 - s[..., None]) / tau)
    b = torch.sigmoid((w[..., None] - k + F[..., None] - delta) / tau)
    return a * b * torch.tanh(w / tau)[..., None]
