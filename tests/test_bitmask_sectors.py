"""Sector masks: hard integer rule (bit for bit), soft coverage, the custom-autograd union."""

import pytest
import torch

from sector_reference import plain_union
from torch_ao.sectors.soft_union import UnionBlocks
from torch_ao.sectors import (ROUNDINGS, SectorUnion, bits_to_mask, hard_coverage, hard_mask, mask_bits, popcount32,
                              sector_interval, sector_union, soft_coverage)


def _mask(lo, hi, rounding):
    s, w = sector_interval(torch.tensor([lo], dtype=torch.float64), torch.tensor([hi], dtype=torch.float64))
    return int(hard_mask(s, w, rounding)[0])


# (min, max) in [0,1] -> expected masks for ceil / round / floor, worked out by hand:
# start = floor(32 min), count = ceil|round|floor(32 (max - min)), bits = (2^count - 1) << start (32 bits).
CASES = [
    ((0.1, 0.2), (0b1111 << 3, 0b111 << 3, 0b111 << 3)),          # s=3.2, w=3.2
    ((0.5, 0.5 + 2.6 / 32), (0b111 << 16, 0b111 << 16, 0b11 << 16)),  # s=16, w=2.6
    ((31.5 / 32, 1.0), (1 << 31, 0, 0)),                          # s=31.5, w=0.5 (round: ties to even)
    ((0.0, 1.0), (0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFF)),            # the whole half circle
    ((20 / 32, 1.0), (0xFFF00000, 0xFFF00000, 0xFFF00000)),        # s=20, w=12
    ((10.75 / 32, 30.5 / 32), ((1 << 20) - 1 << 10, (1 << 20) - 1 << 10, (1 << 19) - 1 << 10)),  # w=19.75
    ((0.3, 0.3), (0, 0, 0)),                                      # zero width
    ((1.0, 1.0), (0, 0, 0)),                                      # start 32, nothing
]


@pytest.mark.parametrize("interval,expected", CASES)
def test_hard_masks_by_hand(interval, expected):
    for rounding, want in zip(ROUNDINGS, expected):
        got = _mask(*interval, rounding)
        assert got == want, f"{interval} {rounding}: {got:#034b} != {want:#034b}"
        assert int(popcount32(torch.tensor([got]))[0]) == bin(want).count("1")


def test_truncation_to_32_bits():
    # start 30, count 5 -> only bits 30 and 31 survive
    s, w = torch.tensor([30.0]), torch.tensor([4.5])
    assert int(hard_mask(s, w, "ceil")[0]) == 0xC0000000


def test_bits_roundtrip_and_popcount_random():
    g = torch.Generator().manual_seed(0)
    m = torch.randint(0, 2**32, (1000,), generator=g, dtype=torch.int64)
    assert torch.equal(bits_to_mask(mask_bits(m)), m)
    assert torch.equal(popcount32(m), torch.tensor([bin(int(x)).count("1") for x in m]))


@pytest.mark.parametrize("rounding", ROUNDINGS)
def test_hard_coverage_equals_mask_bits(rounding):
    g = torch.Generator().manual_seed(1)
    lo = torch.rand(4000, generator=g)
    hi = (lo + torch.rand(4000, generator=g) ** 2).clamp(max=1)
    s, w = sector_interval(lo, hi)
    assert torch.equal(hard_coverage(s, w, rounding), mask_bits(hard_mask(s, w, rounding)))


@pytest.mark.parametrize("rounding", ROUNDINGS)
def test_hard_unions_agree_and_count_newly_occluded_bits(rounding):
    """The integer-mask union (hard mode) and the same rule on float visibility (the straight-through
    forward) agree for a 0/1 ``p0``, and ``newly`` is the weighted count of ``bits & ~mask`` per step."""
    from torch_ao.sectors.hard_union import coverage_union, mask_union

    g = torch.Generator().manual_seed(5)
    N, J = 300, 6
    lo = torch.rand(N, J, generator=g, dtype=torch.float64)
    hi = (lo + 0.3 * torch.rand(N, J, generator=g, dtype=torch.float64)).clamp(max=1)
    s, w = sector_interval(lo, hi)
    weights = torch.rand(N, 32, generator=g, dtype=torch.float64)
    p0 = (torch.rand(N, 32, generator=g) < 0.8).double()
    for start in (None, p0):
        vis, newly = mask_union(s, w, rounding, weights, start)
        vis_f, newly_f = coverage_union(s, w, weights, start, rounding)
        assert torch.equal(vis, vis_f) and torch.allclose(newly, newly_f, rtol=0, atol=1e-12)
    # by hand for one row: walk the masks as Python ints
    row = 7
    occ = sum(1 << k for k in range(32) if p0[row, k] == 0)
    for j in range(J):
        bits = int(hard_mask(s[row, j:j + 1], w[row, j:j + 1], rounding)[0])
        want = sum(float(weights[row, k]) for k in range(32) if (bits & ~occ) >> k & 1)
        assert abs(float(newly[row, j]) - want) < 1e-12
        occ |= bits
    assert torch.equal(vis[row], torch.tensor([0.0 if occ >> k & 1 else 1.0 for k in range(32)], dtype=torch.float64))


def test_soft_zero_width_covers_nothing():
    s = torch.tensor([0.0, 3.0, 3.5, 31.999, 32.0])
    w = torch.zeros(5)
    for rounding in ROUNDINGS:
        for tau in (1.0, 0.1, 1e-6):
            assert soft_coverage(s, w, tau, rounding).abs().max() == 0


def test_soft_to_hard_convergence_table():
    """Mean |soft - hard| over random intervals for tau = 1e-1 ... 1e-6 (printed; decreasing to ~0)."""
    g = torch.Generator().manual_seed(2)
    lo = torch.rand(20000, generator=g, dtype=torch.float64)
    hi = (lo + torch.rand(20000, generator=g, dtype=torch.float64) ** 2).clamp(max=1)
    s, w = sector_interval(lo, hi)
    print("\nsoft -> hard: mean |coverage_soft - coverage_hard| per sector")
    print("tau      " + "  ".join(f"{r:>9s}" for r in ROUNDINGS))
    table = {}
    for tau in (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6):
        row = []
        for rounding in ROUNDINGS:
            row.append(float((soft_coverage(s, w, tau, rounding) - hard_coverage(s, w, rounding)).abs().mean()))
        table[tau] = row
        print(f"{tau:7.0e}  " + "  ".join(f"{x:9.2e}" for x in row))
    for j in range(3):
        col = [table[t][j] for t in sorted(table, reverse=True)]
        assert all(b <= a + 1e-12 for a, b in zip(col, col[1:])), col
        assert col[-1] < 1e-5
    assert table[1e-1][0] > 1e-3  # the soft mask is really soft at tau = 0.1


@pytest.mark.parametrize("block", [1, 4, None])
@pytest.mark.parametrize("rounding", ROUNDINGS)
def test_union_matches_plain_autograd_and_gradcheck(rounding, block, monkeypatch):
    # block: rows per block of the backward's table rebuild (None: the default, one block here)
    if block is not None:
        monkeypatch.setattr(UnionBlocks, "BACKWARD_BLOCK", block)
    g = torch.Generator().manual_seed(3)
    N, J = 6, 5
    lo = torch.rand(N, J, generator=g, dtype=torch.float64)
    hi = (lo + 0.4 * torch.rand(N, J, generator=g, dtype=torch.float64)).clamp(max=1)
    s, w = sector_interval(lo, hi)
    s.requires_grad_()
    w.requires_grad_()
    weights = torch.rand(N, 32, generator=g, dtype=torch.float64, requires_grad=True)
    p0 = torch.rand(N, 32, generator=g, dtype=torch.float64, requires_grad=True)
    vis, newly = SectorUnion.apply(s, w, weights, p0, 0.4, rounding, False)
    vis_ref, newly_ref = plain_union(s, w, weights, p0, 0.4, rounding)
    assert torch.allclose(vis, vis_ref) and torch.allclose(newly, newly_ref)
    gv, gn = torch.randn_like(vis), torch.randn_like(newly)
    grads = torch.autograd.grad((vis * gv).sum() + (newly * gn).sum(), (s, w, weights, p0))
    grads_ref = torch.autograd.grad((vis_ref * gv).sum() + (newly_ref * gn).sum(), (s, w, weights, p0))
    for a, b in zip(grads, grads_ref):
        assert torch.allclose(a, b, atol=1e-10)
    assert torch.autograd.gradcheck(lambda s, w, wt, p: SectorUnion.apply(s, w, wt, p, 0.4, rounding, False),
                                    (s, w, weights, p0))


def test_union_stiff_tau_is_finite_and_straight_through_forward_is_hard():
    g = torch.Generator().manual_seed(4)
    N, J = 200, 8
    lo = torch.rand(N, J, generator=g)
    hi = (lo + torch.rand(N, J, generator=g) * 0.3).clamp(max=1)
    lo[:, 0] = 0.0
    hi[:, 1] = lo[:, 1]  # zero widths
    s, w = sector_interval(lo, hi)
    s.requires_grad_()
    w.requires_grad_()
    weights = torch.full((N, 32), 1 / 32)
    hard_vis, hard_newly = sector_union(s, w, mode="hard", weights=weights)
    for tau in (1e-1, 1e-3, 1e-6):
        for mode in ("soft", "straight_through"):
            vis, newly = sector_union(s, w, mode=mode, tau=tau, weights=weights)
            assert ((vis >= 0) & (vis <= 1)).all()
            gs, gw = torch.autograd.grad(vis.sum() + newly.sum(), (s, w))
            assert torch.isfinite(gs).all() and torch.isfinite(gw).all()
            if mode == "straight_through":
                assert torch.equal(vis, hard_vis) and torch.allclose(newly, hard_newly)
    vis, _ = sector_union(s, w, mode="soft", tau=1e-6, weights=weights)
    assert (vis - hard_vis).abs().max() < 1e-4


def test_union_rejects_bad_options():
    s = torch.zeros(2, 3)
    with pytest.raises(ValueError, match="mode"):
        sector_union(s, s, mode="fuzzy")
    with pytest.raises(ValueError, match="rounding"):
        sector_union(s, s, rounding="nearest")
    with pytest.raises(ValueError, match="tau"):
        sector_union(s, s, mode="soft", tau=0.0)
