"""``torch.compile(module)`` gives the module's own numbers: every method in hard mode, soft and straight-through
``BitmaskAO`` with gradients, a half-resolution walk (slow: compiles)."""
import pytest
import torch

import torch_ao
from torch_ao.examples import example_gbuffer
from torch_ao.thickness import BackfaceThickness

from kernel_cases import KERNEL_CALLS

pytestmark = pytest.mark.slow

# small walks keep Inductor's compile time (it unrolls the slice and step loops) to tens of seconds
METHODS = {
    "ssao": lambda: torch_ao.SSAO(radius=1.0, slices=2, steps=2),  # 8 kernel samples, as the others walk 2 x 2
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
# backward graphs of every slice x step. Inductor's code generation for one case (about 2 minutes of
# compiling on a 2-core CPU); the others run the same traced graphs without it (aot_eager).
SOFT_CASES = [(variant, mode, "inductor" if (variant, mode) == ("default", "soft") else "aot_eager")
              for variant in ("default", "exact") for mode in ("soft", "straight_through")]


@pytest.mark.parametrize("variant,mode,backend", SOFT_CASES, ids=[f"{v}-{m}-{b}" for v, m, b in SOFT_CASES])
def test_compiled_soft_bitmask_matches_eager_with_gradients(variant, mode, backend):
    from torch._dynamo.utils import counters

    torch._dynamo.reset()
    counters.clear()
    gb = example_gbuffer(12, 16)
    module = torch_ao.BitmaskAO(variant=variant, mode=mode, slices=2, steps=2, backend="torch")
    compiled = torch.compile(module, backend=backend, dynamic=False)

    def run(fn):
        depth = gb.depth.detach().clone().requires_grad_(True)
        frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=gb.normals, mask=gb.mask)
        vis = fn(frame).visibility
        weights = torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).reshape(vis.shape)
        grads = torch.autograd.grad((vis * weights).sum(), (depth, module.radius, module.thickness))
        return vis.detach(), grads

    vis_e, grads_e = run(module)
    vis_c, grads_c = run(compiled)
    # the walk compiled, forward and backward, as one graph (no graph break)
    assert counters["stats"]["unique_graphs"] == 1, counters["stats"]
    assert torch.allclose(vis_c, vis_e, atol=1e-5, rtol=0), (vis_c - vis_e).abs().max()
    for name, ge, gc in zip(("depth", "radius", "thickness"), grads_e, grads_c):
        assert bool(ge.abs().max() > 0), name  # a gradient to compare
        scale = ge.abs().max()
        assert float((gc - ge).abs().max() / scale) <= 1e-4, (name, float((gc - ge).abs().max() / scale))


@pytest.mark.parametrize("method", ["exact", "hard", "glsl_soft"])
def test_compiled_kernel_gbuffer_gradients_match_eager(method):
    """The exact union's, the hard cosine and the ssilvb_glsl shader's soft kernels with depth gradients (their
    backwards: exact_backward, hard_record + hard_backward, soft_backward) under torch.compile (aot_eager): eager's
    values and gradients."""
    torch._dynamo.reset()
    gb = example_gbuffer(12, 16)
    module = {"exact": lambda: torch_ao.BitmaskAO(variant="exact", mode="soft", thickness=BackfaceThickness(), slices=2,
                                                  steps=2),
              "hard": lambda: torch_ao.BitmaskAO(mode="hard", weighting="cosine", slices=2, steps=2),
              "glsl_soft": lambda: torch_ao.BitmaskAO(variant="ssilvb_glsl", mode="soft", slices=2, steps=2)}[method]()
    compiled = torch.compile(module, backend="aot_eager", dynamic=False)

    def run(fn):
        depth = gb.depth.detach().clone().requires_grad_(True)
        frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, mask=gb.mask, backface_depth=gb.depth * 1.3)
        vis = fn(frame).visibility
        (grad,) = torch.autograd.grad((vis * torch.linspace(0.5, 1.5, vis.numel()).reshape(vis.shape)).sum(), depth)
        return vis.detach(), grad

    (vis_e, grad_e), (vis_c, grad_c) = run(module), run(compiled)
    assert torch.allclose(vis_c, vis_e, atol=1e-6, rtol=0)
    finite = torch.isfinite(grad_e)
    assert bool(grad_e[finite].abs().max() > 0)
    assert float((grad_c - grad_e)[finite].abs().max() / grad_e[finite].abs().max()) <= 1e-5


def _sky_frame():
    """8 x 12, a grazing floor and a wall under a background sky (the walk's all-pixel path must keep it)."""
    from torch_ao.examples import floor_wall_gbuffer

    gb, _ = floor_wall_gbuffer(8, 12, wall_distance=0.5, camera_height=1.0, pitch_degrees=-5.0)
    assert not bool(gb.valid.all())
    return gb


def _breaks(module, gb):
    torch._dynamo.reset()
    explained = torch._dynamo.explain(module)(gb)
    return explained.graph_count, [(b.reason.splitlines()[0], b.user_stack[-1].filename if b.user_stack else "")
                                   for b in explained.break_reasons]


# every method's tensor walk at 2 slices x 2 steps (SSAO: 8 kernel samples), with gradients enabled (the soft
# union's autograd Function is traced as well as its backward)
NO_BREAK_MODULES = {
    "gtao": lambda: torch_ao.GTAO(slices=2, steps=2, backend="torch"),
    "hbao": lambda: torch_ao.HBAO(slices=2, steps=2, backend="torch"),
    "bitmask_hard": lambda: torch_ao.BitmaskAO(mode="hard", slices=2, steps=2, backend="torch"),
    "bitmask_hard_exact": lambda: torch_ao.BitmaskAO(variant="exact", mode="hard", slices=2, steps=2, backend="torch"),
    "bitmask_soft": lambda: torch_ao.BitmaskAO(mode="soft", slices=2, steps=2, backend="torch"),
    "bitmask_soft_exact": lambda: torch_ao.BitmaskAO(variant="exact", mode="soft", slices=2, steps=2, backend="torch"),
    "bitmask_straight_through": lambda: torch_ao.BitmaskAO(mode="straight_through", slices=2, steps=2,
                                                           backend="torch"),
    "bitmask_straight_through_exact": lambda: torch_ao.BitmaskAO(variant="exact", mode="straight_through", slices=2,
                                                                 steps=2, backend="torch"),
    "ssao": lambda: torch_ao.SSAO(radius=1.0, slices=2, steps=2, backend="torch"),
    "ue4_ssao": lambda: torch_ao.UE4SSAO(slices=2, steps=2, backend="torch"),
    "pssao": lambda: torch_ao.PSSAO(slices=2, steps=2, backend="torch"),
}


@pytest.mark.parametrize("name", sorted(NO_BREAK_MODULES))
def test_walk_traces_as_one_graph(name):
    """The tensor walk traces whole: no graph break (the soft union takes every step, dead ones at zero
    width, instead of its data-dependent live-step layout)."""
    graphs, breaks = _breaks(NO_BREAK_MODULES[name](), _sky_frame())
    assert breaks == [] and graphs == 1, breaks


@pytest.mark.parametrize("name", sorted(KERNEL_CALLS))
def test_kernel_call_compiles_as_one_graph_with_eager_values_and_gradients(name):
    """``torch.compile`` of a module whose call runs a fused kernel: one graph and no graph break, forward and
    backward (the kernels' fake shapes trace them; their libraries load while tracing, not in the graph), and
    eager's values and gradients to depth, normals, light and every parameter (aot_eager: the traced graphs
    without Inductor's code generation)."""
    from torch._dynamo.utils import counters

    gb = example_gbuffer(12, 16)
    light = torch.linspace(0.2, 1.0, 3 * 12 * 16).reshape(1, 3, 12, 16)
    results = []
    for compiled in (False, True):
        torch._dynamo.reset()
        counters.clear()
        torch.manual_seed(0)
        module = KERNEL_CALLS[name]()
        run = torch.compile(module, backend="aot_eager", dynamic=False) if compiled else module
        inputs = [t.detach().clone().requires_grad_(True) for t in (gb.depth, gb.normals, light)]
        frame = torch_ao.GBuffer(depth=inputs[0], camera=gb.camera, normals=inputs[1], light=inputs[2], mask=gb.mask,
                                 backface_depth=gb.depth * 1.3)
        out = run(frame)
        loss = sum((t * torch.linspace(0.5, 1.5, t.numel()).reshape(t.shape)).sum()
                   for t in (out.visibility, out.indirect) if t is not None)
        params = dict(module.named_parameters())
        wanted = [*inputs, *params.values()]
        grads = torch.autograd.grad(loss, wanted, allow_unused=True)
        results.append((out.visibility.detach(), grads))
        if compiled:
            assert counters["stats"]["unique_graphs"] == 1 and not counters["graph_break"], (
                counters["stats"], dict(counters["graph_break"]))
    (v0, g0), (v1, g1) = results
    assert torch.allclose(v1, v0, atol=1e-6, rtol=0), (v1 - v0).abs().max()
    names = ["depth", "normals", "light", *params]
    # a G-buffer gradient to compare (hard cosine sectors: the normals'; depth moves only their rounding)
    assert max(float(g[torch.isfinite(g)].abs().max()) for g in g0[:2] if g is not None) > 1e-3
    for n, a, b in zip(names, g0, g1):
        assert (a is None) == (b is None), n
        if a is not None:
            finite = torch.isfinite(a)
            assert torch.equal(finite, torch.isfinite(b)), n
            error = float((b - a)[finite].abs().max())
            assert error <= 1e-5 * float(a[finite].abs().max()) + 1e-7, (n, error)


def test_compiled_call_falls_back_to_the_tensor_walk_where_the_kernels_cannot_be_built(monkeypatch):
    """Where the C++ kernels cannot be built, a compiled call takes the tensor walk as an eager one does: the
    KernelUnavailable raised in the traced code is caught by the dispatch, not turned into a compile error."""
    from torch_ao.kernels import build

    def unavailable():
        raise build.KernelUnavailable("the C++ kernels could not be built (test)")

    monkeypatch.setattr(build, "_load_forwards", unavailable)
    monkeypatch.setattr(build, "_load_backwards", unavailable)
    torch._dynamo.reset()
    gb = example_gbuffer(12, 16)
    with torch.no_grad():
        with pytest.warns(RuntimeWarning, match=r"could not be built \(test\); using the tensor-op walk"):
            compiled = torch.compile(torch_ao.GTAO(slices=2, steps=2), backend="aot_eager", dynamic=False)(gb)
        tensor_walk = torch_ao.GTAO(slices=2, steps=2, backend="torch")(gb)
    assert torch.equal(compiled.visibility, tensor_walk.visibility)


EVERY_PIXEL_MODULES = {
    "gtao": lambda: torch_ao.GTAO(slices=2, steps=2, backend="torch", falloff_range=0.3),
    "bitmask_soft": lambda: torch_ao.BitmaskAO(mode="soft", slices=2, steps=2, backend="torch"),
    "bitmask_straight_through": lambda: torch_ao.BitmaskAO(mode="straight_through", slices=2, steps=2,
                                                           backend="torch"),
}


@pytest.mark.parametrize("name", sorted(EVERY_PIXEL_MODULES))
def test_compiled_walk_over_every_pixel_keeps_values_background_and_gradients(name):
    """Under torch.compile the walk queries every pixel (no data-dependent list of valid ones): the values
    and gradients (depth and every parameter: radius and thickness, or falloff range and final power) equal
    eager, the background stays 1 with zero gradient (aot_eager: the traced graphs without Inductor's code
    generation)."""
    gb = _sky_frame()
    results = []
    for compiled in (False, True):
        torch._dynamo.reset()
        module = EVERY_PIXEL_MODULES[name]().double()
        depth = gb.depth.double().clone().requires_grad_(True)
        g = torch_ao.GBuffer(depth, gb.camera.to(dtype=torch.float64), normals=gb.normals.double())
        run = torch.compile(module, backend="aot_eager", dynamic=False) if compiled else module
        vis = run(g).visibility
        (vis * torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).reshape(vis.shape)).sum().backward()
        results.append((vis.detach(), depth.grad, {n: p.grad for n, p in module.named_parameters()}))
    (v0, d0, p0), (v1, d1, p1) = results
    bg = ~gb.valid
    assert torch.equal(v1[bg], torch.ones_like(v1[bg])) and torch.equal(d1[bg], torch.zeros_like(d1[bg]))
    assert bool(torch.isfinite(d1).all()) and float(d1.abs().sum()) > 0
    assert torch.allclose(v1, v0, atol=1e-12) and torch.allclose(d1, d0, atol=1e-10)
    assert "radius" in p0 and sorted(p1) == sorted(p0)
    for n in p0:
        assert p0[n] is not None and p1[n] is not None, n
        assert bool(p0[n].abs().max() > 0), n  # a gradient to compare
        assert torch.allclose(p1[n], p0[n], atol=1e-10), (n, p1[n], p0[n])


def test_gtao_second_call_on_the_same_gbuffer_reuses_the_graph():
    """The G-buffer's derived-buffer cache is not consulted while compiling, so calling again on the same
    G-buffer (a fit's views) reuses the one compiled graph instead of recompiling the walk."""
    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    torch._dynamo.reset()
    gb = _sky_frame()
    compiled = torch.compile(torch_ao.GTAO(slices=2, steps=2, backend="torch"), backend=backend, dynamic=False)
    with torch.no_grad():
        first = compiled(gb).visibility
        second = compiled(gb).visibility
    assert len(graphs) == 1 and torch.equal(first, second)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("method", ["bitmask", "soft"])
def test_compiled_cuda_kernels_match_eager(method):
    """On a CUDA G-buffer, ``torch.compile`` (Inductor, which writes Triton kernels for the ops around the walk)
    of a module whose walk is a CUDA kernel gives eager's numbers: hard bitmask AO forward, and soft bitmask AO
    with depth and normal gradients."""
    torch._dynamo.reset()
    gb = example_gbuffer(48, 64).to(device="cuda")
    soft = method == "soft"
    module = torch_ao.BitmaskAO(mode="soft" if soft else "hard", slices=3, steps=4, backend="kernel").cuda()
    compiled = torch.compile(module, dynamic=False)

    def run(fn):
        depth = gb.depth.detach().clone().requires_grad_(soft)
        normals = gb.normals.detach().clone().requires_grad_(soft)
        vis = fn(torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=normals, mask=gb.mask)).visibility
        if not soft:
            return vis.detach(), ()
        weights = torch.linspace(0.5, 1.5, vis.numel(), device=vis.device).reshape(vis.shape)
        return vis.detach(), torch.autograd.grad((vis * weights).sum(), (depth, normals))

    (vis_e, grads_e), (vis_c, grads_c) = run(module), run(compiled)
    assert torch.allclose(vis_c, vis_e, atol=1e-6, rtol=0), (vis_c - vis_e).abs().max()
    for ge, gc in zip(grads_e, grads_c):
        finite = torch.isfinite(ge)
        assert bool(ge[finite].abs().max() > 0)
        # Inductor rounds the positions and normals it computes from depth its own way, and the backward adds its
        # taps' gradients atomically in no fixed order: 2.3e-5 of the largest on an H200
        assert float((gc - ge)[finite].abs().max() / ge[finite].abs().max()) <= 1e-4
