"""ops.channel_norm / normalize_channels: the channels' Euclidean norm of (B,C,H,W) images without torch's slow
strided norm, against F.normalize (values, gradients), where torch's overflows, at zero vectors, in both layouts."""
import pytest
import torch
import torch.nn.functional as F

from torch_ao.ops import channel_norm, normalize_channels


def _image(dtype, layout):
    x = torch.randn(2, 3, 5, 7, dtype=dtype, generator=torch.Generator().manual_seed(0))
    x[0, :, 1, 1] = 0.0  # a zero vector
    return x.contiguous(memory_format=torch.channels_last) if layout == "channels_last" else x


@pytest.mark.parametrize("layout", ["contiguous", "channels_last"])
def test_values_and_gradients_are_f_normalize(layout):
    x = _image(torch.float64, layout)
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    mine, torchs = normalize_channels(a), F.normalize(b, dim=1, eps=1e-12)
    assert torch.allclose(mine, torchs, rtol=1e-14, atol=1e-15)
    weights = torch.randn_like(mine)
    (mine * weights).sum().backward()
    (torchs * weights).sum().backward()
    assert torch.isfinite(a.grad).all()  # (at the zero vector x / eps's: weights / eps, as torch's)
    assert torch.allclose(a.grad, b.grad, rtol=1e-12, atol=1e-14)
    assert torch.allclose(channel_norm(x), x.norm(dim=1, keepdim=True), rtol=1e-15, atol=0)


@pytest.mark.parametrize("layout", ["contiguous", "channels_last"])
def test_gradcheck_and_gradgradcheck(layout):
    """The closed-form backward, and autograd of it (second derivatives), against finite differences (the
    clamped vectors' gradient, ``g / eps``, is the test above's: differences cannot be taken under ``eps``)."""
    x = _image(torch.float64, layout)[:, :, 2:4, 2:5].clone().requires_grad_()
    assert torch.autograd.gradcheck(normalize_channels, (x,))
    assert torch.autograd.gradgradcheck(normalize_channels, (x,))


@pytest.mark.parametrize("dtype, big", [(torch.float32, 1e30), (torch.float64, 1e200)])
def test_no_overflow_or_underflow_where_squares_would(dtype, big):
    x = torch.zeros(1, 3, 1, 2, dtype=dtype)
    x[0, :, 0, 0] = torch.tensor([3.0, 4.0, 0.0], dtype=dtype) * big
    x[0, :, 0, 1] = torch.tensor([3.0, 4.0, 0.0], dtype=dtype) / big
    assert torch.allclose(channel_norm(x).flatten(), torch.tensor([5 * big, 5 / big], dtype=dtype), rtol=1e-6)
    assert torch.allclose(normalize_channels(x)[0, :, 0, 0], torch.tensor([0.6, 0.8, 0.0], dtype=dtype))
