"""Counter-based random numbers and stratified hemisphere sampling for the references.

Random numbers are a hash of ``(seed, stream, ray key)``, so a render is reproducible for a seed
whatever the chunk size or device.

Stratification with an honest error: the ``spp`` samples of a pixel form ``G`` independent groups
of ``n = spp / G`` samples; each group is a jittered grid over the unit square (``nx * ny >= n``
cells, ``n`` consecutive cells from a random offset, so every sample is uniform and the group mean
unbiased). Group means are i.i.d., so ``std(group means) / sqrt(G)`` is an unbiased standard error
that also credits the variance reduction of stratification.
"""
from __future__ import annotations

import math

import torch

__all__ = ["uniform", "stream_constants", "group_grid", "stratified_square", "choose_groups", "cosine_hemisphere", "uniform_hemisphere", "frame"]

_M32 = 0xFFFFFFFF


def _mix(x: torch.Tensor) -> torch.Tensor:
    """lowbias32 integer hash on int64 tensors holding 32-bit values."""
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _M32
    x = x ^ (x >> 15)
    x = (x * 0x846CA68B) & _M32
    return x ^ (x >> 16)


def stream_constants(seed: int, stream: int) -> tuple[int, int]:
    """The two 32-bit constants that :func:`uniform` mixes into the keys of ``(seed, stream)``."""
    s = int(_mix(torch.tensor(((seed * 0x9E3779B9) ^ (stream * 0x85EBCA6B) ^ 0x27D4EB2F) & _M32, dtype=torch.int64)))
    return s, int(_mix(torch.tensor(s ^ ((seed >> 32) & _M32), dtype=torch.int64)))


def uniform(key: torch.Tensor, seed: int, stream: int, dtype=torch.float32) -> torch.Tensor:
    """Uniform ``[0, 1)`` numbers, one per int64 ``key``, for ``(seed, stream)``."""
    s, s2 = stream_constants(seed, stream)
    h = _mix((key & _M32) ^ s)
    h = _mix(h ^ ((key >> 32) & _M32) ^ s2)
    return (h >> 8).to(dtype) * (1.0 / (1 << 24))


#: Most AO rays per pixel a reference takes: its standard error is then about 0.002 (0.5 / sqrt(spp));
#: more only runs for hours (time grows linearly with it).
MAX_SPP = 1 << 16


def choose_groups(spp: int, max_groups: int = 16) -> int:
    """The number of independent groups: the largest divisor of ``spp`` in ``[2, max_groups]``."""
    if isinstance(spp, bool) or not isinstance(spp, int) or not 2 <= spp <= MAX_SPP:
        raise ValueError(f"spp: expected an integer in [2, {MAX_SPP}] (samples per pixel), got {spp!r}")
    for g in range(min(max_groups, spp), 1, -1):
        if spp % g == 0:
            return g
    near = [s for s in range(spp - 8, spp + 9) if s >= 2 and any(s % g == 0 for g in range(2, max_groups + 1))]
    raise ValueError(
        f"spp: {spp} has no divisor between 2 and {max_groups}, needed for the standard error "
        f"(independent groups of stratified samples); use e.g. {min(near, key=lambda s: abs(s - spp))}"
    )


def group_grid(spp: int, groups: int) -> tuple[int, int, int]:
    """``(n, nx, ny)``: samples per group and the ``nx x ny`` jitter grid they fill."""
    n = spp // groups
    nx = max(1, int(math.isqrt(n)))
    return n, nx, -(-n // nx)


def stratified_square(pixel_key: torch.Tensor, spp: int, groups: int, seed: int, stream: int, dtype=torch.float32):
    """``(u1, u2)`` each ``(M, spp)`` for pixels ``pixel_key (M,)`` (int64, unique per pixel).

    Sample ``j`` belongs to group ``j // n``; within a group the samples fill consecutive cells of an
    ``nx x ny`` grid from a random offset, each jittered uniformly inside its cell.
    """
    n, nx, ny = group_grid(spp, groups)
    cells = nx * ny
    dev = pixel_key.device
    j = torch.arange(spp, device=dev)
    key = pixel_key[:, None] * spp + j  # (M, spp) unique sample key
    gkey = pixel_key[:, None] * groups + (j // n)  # (M, spp) group key
    offset = (uniform(gkey, seed, stream + 2, torch.float64) * cells).long().clamp_max(cells - 1)
    cell = (j % n + offset) % cells
    cx, cy = cell % nx, cell // nx
    u1 = (cx.to(dtype) + uniform(key, seed, stream, dtype)) / nx
    u2 = (cy.to(dtype) + uniform(key, seed, stream + 1, dtype)) / ny
    return u1.clamp_max(1 - 1e-7), u2.clamp_max(1 - 1e-7)


def frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Tangent ``t`` and bitangent ``b`` with ``(t, b, n)`` orthonormal, for unit ``n (...,3)``
    (Duff et al. 2017, branchless)."""
    x, y, z = n.unbind(-1)
    s = torch.where(z >= 0, 1.0, -1.0).to(n.dtype)
    a = -1.0 / (s + z)
    b = x * y * a
    t = torch.stack((1 + s * x * x * a, s * b, -s * x), -1)
    bt = torch.stack((b, s + y * y * a, -y), -1)
    return t, bt


def cosine_hemisphere(u1: torch.Tensor, u2: torch.Tensor) -> torch.Tensor:
    """Local directions ``(...,3)`` with pdf ``cos(theta) / pi`` (z = normal)."""
    r = u1.sqrt()
    phi = (2 * math.pi) * u2
    return torch.stack((r * phi.cos(), r * phi.sin(), (1 - u1).clamp_min(0).sqrt()), -1)


def uniform_hemisphere(u1: torch.Tensor, u2: torch.Tensor) -> torch.Tensor:
    """Local directions ``(...,3)`` with pdf ``1 / (2 pi)`` (z = normal)."""
    z = u1
    r = (1 - z * z).clamp_min(0).sqrt()
    phi = (2 * math.pi) * u2
    return torch.stack((r * phi.cos(), r * phi.sin(), z), -1)
