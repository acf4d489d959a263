"""The fused kernels' gradients are first order: with ``create_graph=True`` they are the same gradients, and
differentiating them again raises, naming the AO layer, instead of giving the 0 that autograd would take for a
backward run outside its graph (every kernel Function's backward: ``kernels.frame.first_order``)."""
import pytest
import torch

import torch_ao
from torch_ao.examples import example_gbuffer

from kernel_cases import KERNEL_CALLS

def _gradients(module, gb, light, create_graph):
    depth = gb.depth.detach().clone().requires_grad_(True)
    frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=gb.normals, light=light, mask=gb.mask,
                             backface_depth=gb.depth * 1.3)
    out = module(frame)
    loss = sum((t * torch.linspace(0.5, 1.5, t.numel()).reshape(t.shape)).sum()
               for t in (out.visibility, out.indirect) if t is not None)
    (grad,) = torch.autograd.grad(loss, depth, create_graph=create_graph)
    return depth, grad


@pytest.mark.parametrize("name", sorted(KERNEL_CALLS))
def test_a_second_derivative_through_a_kernel_raises(name):
    gb = example_gbuffer(12, 16)
    light = torch.linspace(0.2, 1.0, 3 * 12 * 16).reshape(1, 3, 12, 16)
    module = KERNEL_CALLS[name]()
    _, plain = _gradients(module, gb, light, create_graph=False)
    depth, grad = _gradients(module, gb, light, create_graph=True)
    finite = torch.isfinite(plain)
    assert bool(plain[finite].abs().max() > 0)  # a gradient to differentiate
    assert torch.equal(torch.isfinite(grad), finite) and torch.equal(grad.detach()[finite], plain[finite])
    penalty = grad[finite].square().sum()
    with pytest.raises(RuntimeError, match="first order"):
        torch.autograd.grad(penalty, depth, retain_graph=True, allow_unused=True)
    with pytest.raises(RuntimeError, match="first order"):
        penalty.backward()
