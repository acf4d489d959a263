"""``torch.compile(module)`` gives the module's own numbers: every method in hard mode, soft and straight-through
``BitmaskAO`` with gradients, a half-resolution walk (slow: compiles)."""
import pytest
import torch

import torch_ao
from torch_ao.examples import example_gbuffer

pytestmark = pytest.mark.slow

# small walks keep Inductor's compile time (it unrolls the slice and step loops) to tens of seconds
METHODS = {
    "ssao": lambda: torch_ao.SSAO(radius=1.0),
    "hbao": lambda: torch_ao.HBAO(slices=2, steps=2, backend="torch"),  # the kernel's: test_kernels_gtao.py
    "ue4_ssao": lambda: torch_ao.UE4SSAO(slices=2, steps=2),
    "gtao": lambda: torch_ao.GTAO(slices=2, steps=2, backend="torch"),
    "pssao": lambda: torch_ao.PSSAO(slices=2, steps=2),
    "ssilvb": lambda: torch_ao.SSILVB(mode="hard", slices=2, steps=2),
    "bitmask_torch": lambda: torch_ao.BitmaskAO(mode="hard", slices=2, steps=2, backend="torch"),
    # the walk on the decimated frame and kornia's joint bilateral upsample
    "gtao_half": lambda: torch_ao.GTAO(slices=2, steps=2, resolution="half"),
}


def _eager_and_compiled(module, gb):
    torch._dynamo.reset()
    with torch.no_grad():
        eager = module(gb)
        compiled = torch.compile(module, dynamic=False)(gb)
    return eager, compiled


@pytest.mark.parametrize("name", sorted(METHODS))
def test_compiled_module_matches_eager(name):
    gb = example_gbuffer(24, 40)
    eager, compiled = _eager_and_compiled(METHODS[name](), gb)
    for field in ("visibility", "indirect", "bent_normal"):
        a, b = getattr(eager, field), getattr(compiled, field)
        assert (a is None) == (b is None), field
        if a is None:
            continue
        if name == "bitmask_torch":
            # Hard masks: Inductor evaluates cos/sin with SLEEF where eager torch calls MKL's vector math
            # (the last bit differs for ~30% of angles) and reduces norms in its own order, so a sample
            # lying on a sector boundary can flip one sector: whole sectors only, on few pixels.
            step = 1 / (32 * 2)
            diff = (a - b).abs()
            assert torch.allclose(diff / step, (diff / step).round(), atol=1e-4)
            assert (diff > 0).float().mean() <= 0.02 and diff.max() <= 2 * step + 1e-6
        else:
            assert torch.allclose(a, b, atol=2e-5, rtol=1e-5), (name, field, (a - b).abs().max())


def test_compiled_bitmask_with_the_kernel_is_bit_identical():
    gb = example_gbuffer(24, 40)
    module = torch_ao.BitmaskAO(mode="hard", slices=3, steps=4)  # backend auto: the kernel, one graph node
    eager, compiled = _eager_and_compiled(module, gb)
    assert torch.equal(eager.visibility, compiled.visibility)
    reference = torch_ao.BitmaskAO(mode="hard", slices=3, steps=4, backend="torch")(gb).visibility
    assert torch.equal(compiled.visibility, reference)


# Soft and straight-through BitmaskAO under torch.compile: forward values and gradients (to depth, normals
# by way of depth, radius and thickness) against eager. Tiny frame and walk: Inductor compiles forward and
# backward graphs of every slice x step.
SOFT_CASES = [(variant, mode) for variant in ("default", "exact") for mode in ("soft", "straight_through")]


@pytest.mark.parametrize("variant,mode", SOFT_CASES, ids=[f"{v}-{m}" for v, m in SOFT_CASES])
def test_compiled_soft_bitmask_matches_eager_with_gradients(variant, mode):
    from torch._dynamo.utils import counters

    torch._dynamo.reset()
    counters.clear()
    gb = example_gbuffer(12, 16)
    module = torch_ao.BitmaskAO(variant=variant, mode=mode, slices=2, steps=2, backend="torch")
    compiled = torch.compile(module, dynamic=False)

    def run(fn):
        depth = gb.depth.detach().clone().requires_grad_(True)
        frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=gb.normals, mask=gb.mask)
        vis = fn(frame).visibility
        weights = torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).reshape(vis.shape)
        grads = torch.autograd.grad((vis * weights).sum(), (depth, module.radius, module.thickness))
        return vis.detach(), grads

    vis_e, grads_e = run(module)
    vis_c, grads_c = run(compiled)
    # Inductor compiled the walk (in pieces: the flat list of valid pixels, nonzero, breaks the graph)
    assert counters["stats"]["unique_graphs"] >= 1
    assert torch.allclose(vis_c, vis_e, atol=1e-5, rtol=0), (vis_c - vis_e).abs().max()
    for name, ge, gc in zip(("depth", "radius", "thickness"), grads_e, grads_c):
        assert bool(ge.abs().max() > 0), name  # a gradient to compare
        scale = ge.abs().max()
        assert float((gc - ge).abs().max() / scale) <= 1e-4, (name, float((gc - ge).abs().max() / scale))
