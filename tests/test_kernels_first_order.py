"""The fused kernels' gradients are first order: with ``create_graph=True`` they are the same gradients, and
differentiating them again raises, naming the AO layer, instead of giving the 0 that autograd would take for a
backward run outside its graph (every kernel Function's backward: ``kernels.frame.first_order``)."""
import pytest
import torch

import torch_ao
from torch_ao.examples import example_gbuffer
from torch_ao.thickness import BackfaceThickness

MODULES = {
    "gtao": lambda: torch_ao.GTAO(slices=2, steps=3),
    "hbao": lambda: torch_ao.HBAO(slices=2, steps=3),
    "ue4_ssao": lambda: torch_ao.UE4SSAO(slices=2, steps=3),
    "pssao": lambda: torch_ao.PSSAO(slices=2, steps=3),
    "ssao": lambda: torch_ao.SSAO(slices=2, steps=3, softness=0.05),
    "bitmask_hard_cosine": lambda: torch_ao.BitmaskAO(mode="hard", weighting="cosine", slices=2, steps=3),
    "bitmask_soft": lambda: torch_ao.BitmaskAO(mode="soft", slices=2, steps=3),
    "bitmask_straight_through": lambda: torch_ao.BitmaskAO(mode="straight_through", slices=2, steps=3),
    "bitmask_soft_exact_backface": lambda: torch_ao.BitmaskAO(variant="exact", mode="soft", slices=2, steps=3,
                                                              thickness=BackfaceThickness()),
    "ssilvb_soft": lambda: torch_ao.SSILVB(mode="soft", slices=2, steps=3),
    "glsl_soft": lambda: torch_ao.BitmaskAO(variant="ssilvb_glsl", mode="soft", slices=2, steps=3),
}


def _gradients(module, gb, light, create_graph):
    depth = gb.depth.detach().clone().requires_grad_(True)
    frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=gb.normals, light=light, mask=gb.mask,
                             backface_depth=gb.depth * 1.3)
    out = module(frame)
    loss = sum((t * torch.linspace(0.5, 1.5, t.numel()).reshape(t.shape)).sum()
               for t in (out.visibility, out.indirect) if t is not None)
    (grad,) = torch.autograd.grad(loss, depth, create_graph=create_graph)
    return depth, grad


@pytest.mark.parametrize("name", sorted(MODULES))
def test_a_second_derivative_through_a_kernel_raises(name):
    gb = example_gbuffer(12, 16)
    light = torch.linspace(0.2, 1.0, 3 * 12 * 16).reshape(1, 3, 12, 16)
    module = MODULES[name]()
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
