"""ops.safe_atan2: torch's atan2 values everywhere, its gradients away from the origin (gradcheck), and a zero
gradient at the origin on every torch release (torch 2.4's own atan2 gives NaN there)."""
import torch

from torch_ao.ops import safe_atan2


def test_values_are_atan2_at_every_signed_zero_and_elsewhere():
    y = torch.tensor([0.0, -0.0, 0.0, -0.0, 1.0, -2.0, 0.0, 3e-30], dtype=torch.float64)
    x = torch.tensor([0.0, 0.0, -0.0, -0.0, 0.0, -1.0, -4.0, 1e-30], dtype=torch.float64)
    got, want = safe_atan2(y, x), torch.atan2(y, x)
    assert torch.equal(got, want) and torch.equal(torch.signbit(got), torch.signbit(want))


def test_gradient_is_zero_at_the_origin_and_atan2s_elsewhere():
    y = torch.tensor([0.0, 0.7, -0.2], dtype=torch.float64, requires_grad=True)
    x = torch.tensor([0.0, -0.3, 0.5], dtype=torch.float64, requires_grad=True)
    gy, gx = torch.autograd.grad(safe_atan2(y, x).sum(), [y, x])
    r2 = (x * x + y * y).detach()
    assert torch.equal(gy[0], torch.zeros((), dtype=torch.float64)) and torch.equal(gx[0], gy[0])
    torch.testing.assert_close(gy[1:], (x / r2)[1:].detach(), rtol=1e-12, atol=0)
    torch.testing.assert_close(gx[1:], (-y / r2)[1:].detach(), rtol=1e-12, atol=0)
    assert torch.autograd.gradcheck(safe_atan2, (y[1:].detach().requires_grad_(), x[1:].detach().requires_grad_()))
