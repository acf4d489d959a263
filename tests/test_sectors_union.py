"""SectorUnion's blocked sweeps: block and group sizes, both smooth-floor paths, gradient combinations,
input layouts and float32 accuracy (the plain-autograd reference is :func:`soft_coverage`)."""
import itertools

import pytest
import torch

from sector_reference import plain_union
from torch_ao.sectors import SectorUnion, sector_interval, sector_union
from torch_ao.sectors.soft_union import UnionBlocks
from torch_ao.sectors.hard_union import coverage_union
from torch_ao.sectors.live_steps import LiveSteps
from torch_ao.sectors.sweeps import expm1_tanh


def _inputs(N, J, seed, dtype=torch.float64, spread=0.4, zero_widths=True):
    g = torch.Generator().manual_seed(seed)
    lo = torch.rand(N, J, generator=g, dtype=dtype)
    hi = (lo + spread * torch.rand(N, J, generator=g, dtype=dtype)).clamp(max=1)
    s, w = sector_interval(lo, hi)
    if zero_widths:  # (not for gradcheck: finite differences cross the clamp of w at 0)
        w[::3, 1] = 0
    weights = torch.rand(N, 32, generator=g, dtype=dtype)
    p0 = torch.rand(N, 32, generator=g, dtype=dtype)
    return s, w, weights, p0


def _union_and_grads(s, w, weights, p0, tau, rounding, gv, gn):
    leaves = [x.clone().requires_grad_() for x in (s, w, weights, p0)]
    vis, newly = SectorUnion.apply(*leaves, tau, rounding, False)
    grads = torch.autograd.grad((vis * gv).sum() + (newly * gn).sum(), leaves)
    return (vis.detach(), newly.detach()) + grads


@pytest.mark.parametrize("tau", [0.05, 0.4])  # smooth floor from its own window / from the complements of a
def test_union_matches_plain_autograd_both_floor_paths(tau):
    s, w, weights, p0 = _inputs(9, 7, 1)
    gv = torch.randn(9, 32, dtype=torch.float64)
    gn = torch.randn(9, 7, dtype=torch.float64)
    got = _union_and_grads(s, w, weights, p0, tau, "round", gv, gn)
    leaves = [x.clone().requires_grad_() for x in (s, w, weights, p0)]
    vis, newly = plain_union(*leaves, tau, "round")
    ref = (vis, newly) + torch.autograd.grad((vis * gv).sum() + (newly * gn).sum(), leaves)
    for a, b in zip(got, ref):
        assert torch.allclose(a, b.detach(), rtol=1e-9, atol=1e-10), (a - b).abs().max()
    leaves = [x.requires_grad_() for x in _inputs(6, 5, 7, zero_widths=False)]
    assert torch.autograd.gradcheck(lambda *x: SectorUnion.apply(*x, tau, "floor", False), leaves)


@pytest.mark.parametrize("tau", [0.05, 0.25])
def test_union_block_and_group_sizes_agree(tau, monkeypatch):
    # N = 37 and J = 11 are not multiples of the block and group sizes (partial last block and group)
    s, w, weights, p0 = _inputs(37, 11, 2)
    gv = torch.randn(37, 32, dtype=torch.float64)
    gn = torch.randn(37, 11, dtype=torch.float64)
    outs = []
    for fb, fg, bb, bg in [(4096, 4, 4096, 4), (5, 3, 8, 2), (1, 1, 1, 1), (16, 16, 7, 11), (37, 4, 36, 5)]:
        monkeypatch.setattr(UnionBlocks, "FORWARD_BLOCK", fb)
        monkeypatch.setattr(UnionBlocks, "FORWARD_GROUP", fg)
        monkeypatch.setattr(UnionBlocks, "BACKWARD_BLOCK", bb)
        monkeypatch.setattr(UnionBlocks, "BACKWARD_GROUP", bg)
        outs.append(_union_and_grads(s, w, weights, p0, tau, "ceil", gv, gn))
    for other in outs[1:]:
        for a, b in zip(outs[0], other):
            assert torch.allclose(a, b, rtol=1e-10, atol=1e-12), (a - b).abs().max()


def test_union_gradient_combinations():
    """Every combination of optional inputs, inputs needing gradients and missing output gradients."""
    N, J, tau = 5, 6, 0.3
    S, W, WT, P0 = _inputs(N, J, 3)
    g = torch.Generator().manual_seed(4)
    GV = torch.randn(N, 32, generator=g, dtype=torch.float64)
    GN = torch.randn(N, J, generator=g, dtype=torch.float64)
    checked = 0
    for rs, rw, has_wt, rwt, has_p0, rp0, use_gv, use_gn in itertools.product([0, 1], repeat=8):
        if (rwt and not has_wt) or (rp0 and not has_p0) or (use_gn and not has_wt) or not (use_gv or use_gn):
            continue
        s, w = S.clone().requires_grad_(bool(rs)), W.clone().requires_grad_(bool(rw))
        wt = WT.clone().requires_grad_(bool(rwt)) if has_wt else None
        p0 = P0.clone().requires_grad_(bool(rp0)) if has_p0 else None
        leaves = [x for x in (s, w, wt, p0) if x is not None and x.requires_grad]
        if not leaves:
            continue
        vis, newly = SectorUnion.apply(s, w, wt, p0, tau, "ceil", False)
        vis_ref, newly_ref = plain_union(s, w, wt, p0, tau, "ceil")
        assert torch.allclose(vis, vis_ref) and torch.allclose(newly, newly_ref)
        outs, refs, grads = [], [], []
        if use_gv:
            outs.append(vis), refs.append(vis_ref), grads.append(GV)
        if use_gn:
            outs.append(newly), refs.append(newly_ref), grads.append(GN)
        got = torch.autograd.grad(outs, leaves, grads, allow_unused=True)
        refs = [r if r.requires_grad else r.detach().requires_grad_() for r in refs]
        want = torch.autograd.grad(refs, leaves, grads, allow_unused=True)
        for a, b in zip(got, want):
            a = torch.zeros_like(b) if a is None else a
            b = torch.zeros_like(a) if b is None else b
            assert torch.allclose(a, b, atol=1e-10)
        checked += 1
    assert checked == 76


def test_union_transposed_inputs_and_no_grad_path():
    # the walk passes (N, J) views of (J, N) tensors
    s, w, weights, p0 = _inputs(20, 9, 5, dtype=torch.float32)
    sT, wT = s.t().contiguous().t(), w.t().contiguous().t()
    assert not sT.is_contiguous()
    with torch.no_grad():
        vis, newly = sector_union(s, w, mode="soft", tau=0.2, weights=weights, p0=p0)
    vis2, newly2 = SectorUnion.apply(sT.requires_grad_(), wT.requires_grad_(), weights, p0, 0.2, "ceil", False)
    assert torch.equal(vis, vis2.detach()) and torch.equal(newly, newly2.detach())
    gs, gw = torch.autograd.grad(vis2.sum() + newly2.sum(), (sT, wT))
    s2, w2 = s.clone().requires_grad_(), w.clone().requires_grad_()
    v3, n3 = SectorUnion.apply(s2, w2, weights, p0, 0.2, "ceil", False)
    gs_ref, gw_ref = torch.autograd.grad(v3.sum() + n3.sum(), (s2, w2))
    assert torch.equal(gs, gs_ref) and torch.equal(gw, gw_ref)


@pytest.mark.parametrize("tau", [0.01, 0.15, 0.25])
def test_union_float32_accuracy(tau):
    """float32 against the same union in float64: the smooth floor must keep the precision of a small
    F(s) (a floor formed as 32 - sum a, or from arguments (k + 1) / tau - s / tau, is ~10x worse here)."""
    N, J = 2048, 16
    g = torch.Generator().manual_seed(6)
    s = torch.rand(N, J, generator=g) * 28
    s[::5, 2] = torch.rand(N, generator=g)[::5] * 0.5  # small F(s)
    w = torch.rand(N, J, generator=g) * 4
    weights = torch.rand(N, 32, generator=g)
    gv, gn = torch.randn(N, 32, generator=g), torch.randn(N, J, generator=g)
    leaves32 = [x.clone().requires_grad_() for x in (s, w, weights)]
    leaves64 = [x.double().requires_grad_() for x in (s, w, weights)]
    res = []
    for leaves, dt in ((leaves32, torch.float32), (leaves64, torch.float64)):
        vis, newly = SectorUnion.apply(*leaves, None, tau, "round", False)
        grads = torch.autograd.grad((vis * gv.to(dt)).sum() + (newly * gn.to(dt)).sum(), leaves)
        res.append([x.detach().double() for x in (vis, newly) + grads])
    bound = 2e-6 / tau  # float32 rounding amplified by 1 / tau
    for a, b in zip(*res):
        assert float((a - b).abs().max() / b.abs().max()) < bound


def test_expm1_tanh():
    x = torch.cat([torch.logspace(-12, 2, 20001, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)])
    for dtype in (torch.float32, torch.float64):
        xx = x.to(dtype)
        ref = torch.tanh(xx.double())
        got = expm1_tanh(xx.clone()).double()
        assert got[-1] == 0
        rel = ((got - ref).abs() / ref.clamp_min(1e-300)).max()
        assert rel < 3 * torch.finfo(dtype).eps


@pytest.mark.parametrize("N, J", [(0, 4), (5, 0), (0, 0)])
def test_union_empty_shapes(N, J):
    s, w = torch.rand(N, J, requires_grad=True), torch.rand(N, J, requires_grad=True)
    weights, p0 = torch.rand(N, 32, requires_grad=True), torch.rand(N, 32, requires_grad=True)
    vis, newly = sector_union(s, w, mode="soft", tau=0.25, weights=weights, p0=p0)
    assert vis.shape == (N, 32) and newly.shape == (N, J)
    if J == 0:
        assert torch.equal(vis, p0)
    grads = torch.autograd.grad(vis.sum() + newly.sum(), (s, w, weights, p0), allow_unused=True)
    for g, x in zip(grads, (s, w, weights, p0)):
        assert g is None or g.shape == x.shape
    assert grads[3] is not None
    if J == 0:  # visible = p0
        assert torch.equal(grads[3], torch.ones(N, 32))


def _sparse_inputs(N, J, seed, live_fraction):
    """Inputs where only some steps are live: the others have negative widths (empty intervals)."""
    s, w, weights, p0 = _inputs(N, J, seed)
    g = torch.Generator().manual_seed(seed + 100)
    dead = torch.rand(N, J, generator=g, dtype=torch.float64) > live_fraction
    dead[: N // 4] = True  # rows without any live step
    dead[N // 4: N // 4 + 3] = False  # and rows with every step live
    return s, torch.where(dead, -0.5 - torch.rand(N, J, generator=g, dtype=torch.float64), w), weights, p0


@pytest.mark.parametrize("merge_rows", [0, 1500, 10 ** 9])  # exact segments, the default, one padded segment
@pytest.mark.parametrize("with_weights", [False, True])
def test_union_sweeps_live_steps_only(merge_rows, with_weights, monkeypatch):
    monkeypatch.setattr(LiveSteps, "MERGE_ROWS", merge_rows)
    s, w, weights, p0 = _sparse_inputs(40, 9, 3, live_fraction=0.3)
    weights = weights if with_weights else None
    layout = LiveSteps(w)
    assert not layout.dense and len(layout.rows) < 40
    if merge_rows == 10 ** 9:
        assert len(layout.segments) == 1
    gv = torch.randn(40, 32, dtype=torch.float64)
    gn = torch.randn(40, 9, dtype=torch.float64)
    leaves = [None if x is None else x.clone().requires_grad_() for x in (s, w, weights, p0)]
    vis, newly = SectorUnion.apply(*leaves, 0.25, "ceil", False)
    loss = (vis * gv).sum() + ((newly * gn).sum() if with_weights else 0)
    got = [vis, newly] + list(torch.autograd.grad(loss, [x for x in leaves if x is not None]))
    # plain autograd of the same union with the widths clamped at zero: dead steps cover nothing and
    # (the clamp's derivative) get no gradient
    leaves = [None if x is None else x.clone().requires_grad_() for x in (s, w, weights, p0)]
    vis, newly = plain_union(leaves[0], leaves[1].clamp_min(0), leaves[2], leaves[3], 0.25, "ceil")
    loss = (vis * gv).sum() + ((newly * gn).sum() if with_weights else 0)
    ref = [vis, newly] + list(torch.autograd.grad(loss, [x for x in leaves if x is not None]))
    for a, b in zip(got, ref):
        assert torch.allclose(a.detach(), b.detach(), rtol=1e-9, atol=1e-10), (a - b).abs().max()
    gw = got[3]
    assert torch.all(gw[w < 0] == 0) and gw[w >= 0].abs().max() > 0
    # the no-grad path (no SectorUnion) gives the same values
    vis0, newly0 = sector_union(s, w, mode="soft", tau=0.25, weights=weights, p0=p0)
    assert torch.allclose(vis0, got[0].detach(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("with_weights", [False, True])
def test_straight_through_forward_over_live_steps_is_the_hard_rule(with_weights):
    s, w, weights, p0 = _sparse_inputs(40, 9, 4, live_fraction=0.3)
    weights = weights if with_weights else None
    vis, newly = sector_union(s, w, mode="straight_through", rounding="round", weights=weights, p0=p0)
    ref_vis, ref_newly = coverage_union(s, w.clamp_min(0), weights, p0, "round")
    assert torch.equal(vis, ref_vis) and torch.equal(newly, ref_newly)
    assert (ref_vis != p0).any()
