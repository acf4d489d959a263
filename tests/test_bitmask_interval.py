"""The default bitmask variant's per-sample interval (front to back angle) and its hand-written backward."""

import pytest
import torch

from torch_ao.methods.bitmask import SectorInterval, _sector_interval


def _inputs(thickness_per_row: bool, n: int = 7, steps: int = 3):
    torch.manual_seed(0)
    rows = n * steps
    # Samples from slightly below the tangent plane to nearly behind the pixel (some clamped at the ends).
    angle = torch.linspace(-0.5, 3.0, rows, dtype=torch.float64)
    dist = 0.3 + torch.rand(rows, dtype=torch.float64)
    along_view, along_tangent = dist * torch.cos(angle), dist * torch.sin(angle)
    thickness = (0.1 + torch.rand(rows, dtype=torch.float64)) if thickness_per_row else torch.tensor(0.4, dtype=torch.float64)
    gamma = (torch.rand(n, dtype=torch.float64) - 0.5) * 2.0
    return [t.requires_grad_(True) for t in (along_view, along_tangent, thickness, gamma)]


@pytest.mark.parametrize("side", [1, -1])
@pytest.mark.parametrize("epsilon", [0.0, 0.01, 3.0])
@pytest.mark.parametrize("thickness_per_row", [False, True])
@pytest.mark.parametrize("sparse", [False, True])
def test_sector_interval_backward_matches_autograd(side, epsilon, thickness_per_row, sparse):
    inputs = _inputs(thickness_per_row)
    ours = SectorInterval.apply(*inputs, side, epsilon)
    plain = _sector_interval(*inputs, side, epsilon)
    for a, b in zip(ours, plain):
        assert torch.equal(a, b)
    weights = [torch.linspace(-1, 2, ours[0].shape[0], dtype=torch.float64), torch.linspace(3, -1, ours[0].shape[0], dtype=torch.float64)]
    if sparse:  # most rows without a gradient (empty intervals): the backward works on the others only
        weights = [w * (torch.arange(w.shape[0]) % 5 == 2) for w in weights]
    g_ours = torch.autograd.grad(sum((w * a).sum() for w, a in zip(weights, ours)), inputs)
    g_plain = torch.autograd.grad(sum((w * a).sum() for w, a in zip(weights, plain)), inputs)
    for a, b in zip(g_ours, g_plain):
        assert a.shape == b.shape
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    assert all(g.abs().max() > 0 for g in g_ours)
    assert torch.autograd.gradcheck(lambda *x: SectorInterval.apply(*x, side, epsilon), inputs)


def test_sector_interval_values_by_hand():
    # A sample straight along the tangent (90 degrees from V) with a thin back: a flat normal (gamma = 0)
    # puts the front at the hemisphere's edge for side +1: x = (pi/2 + pi/2) / pi = 1.
    av = torch.tensor([0.0, 1.0])
    at = torch.tensor([1.0, 1.0])
    start, width = _sector_interval(av, at, torch.tensor(1.0), torch.tensor([0.0, 0.0]), 1, 0.0)
    # row 0: front 90 deg -> x = 1, back atan2(1, -1) = 135 deg -> x = 1.25 -> clamped 1: empty interval at 32
    # row 1: front 45 deg -> x = 0.75, back atan2(1, 0) = 90 deg -> x = 1: [24, 32]
    assert torch.allclose(start, torch.tensor([32.0, 24.0])) and torch.allclose(width, torch.tensor([0.0, 8.0]))
