"""Random combinations of a module's options, each run by its kernel (``backend="kernel"``, float32) and by the
tensor-op walk (``backend="torch"``) in float64: the outputs and the gradients of depth, normals, light and every
trainable parameter agree. The other kernel tests pick their settings by hand; these draw them (a fixed seed), so
that options meet that no hand-picked setting combines.

The tolerances are the kernel tests': values within 1e-5, each gradient entry within 1e-4 of the gradient's largest.
Where the tensor walk itself moves more than that between float32 and float64 on the same call, three times that
movement: a nearest fetch's texel, a sector edge or the border's test can fall the other way in float32 (as the
kernels round), and the gradient moves to other entries with it.

Kinks make the rest. A value within float32's rounding of a kink takes one one-sided derivative in the kernel and the
other in the tensor walk, in float32 as in float64:

* one pixel of the drawn calls lies on a segment's end at the radius' sphere (``BitmaskAO(variant="exact")``: d
  visibility / d its own depth -0.398 against -0.414, the float64 walk's one-sided differences -0.396 and -0.414);
* PSSAO's ``max(n . d, 0)`` sits on its kink at every pixel whose given normal was built from a neighbour's texel,
  where ``n . d`` is 0 up to rounding (40 % of the depth gradient's entries differ between float32 and float64 by more
  than 1e-3; float64's central differences lie between them).

So 0.2 % of a gradient's entries may miss, the gradient as a whole stays within 1 %, and a parameter's gradient (a
sum over the frame) within 1e-3. Jitter stays on: without it, steps land on texel edges, where float32 and float64
floor differently (tests/test_kernels_soft_gbuffer.py covers that against the float32 walk).

Branches and float32's conditioning make the rest of the values. Where a call's value is a branch's within float32's
rounding of its threshold, or moves by more than its tolerance with its inputs' last bit, the kernel and the float32
tensor walk round to different values, so "three times the float32 walk's movement" does not bound it there. Seen
over 528 more drawn calls (slow test below), at 1 to 5 entries of a call: `GTAO(variant="hdrp")` at one pixel, where
the kernel's value took one of two values 2.3e-5 apart as the normals were nudged in their last bit while the
float64 walk's moved by 6e-8 (a branch whose threshold that pixel sits within float32's rounding of; which of HDRP's
branches was not identified: the normal is 66 degrees from the view vector, the fetch, the border, the falloff and
the step count do not change it; without the projected normal's weight, or with the other noise, it is gone); and
`UE4SSAO` with a bilinear fetch, whose value at a few pixels is ill-conditioned in float32 (nudging the depth in its
last bit moved the float32 walk's error there between -3e-5 and 8e-5, and the kernel's with it), so that one input's
float32 walk can be close where the kernel is not. So 0.1 % of an output's entries may miss the value tolerance,
each by at most 1e-3, and a gradient's entries at those pixels (the other side's derivative) are among the 0.2 % it
may miss; the 1 % bound on the whole gradient is taken over its other entries.

A gradient that is zero in theory (a hard mask's visibility through the depth, where only the normals turn the
cosine weights; a nearest fetch's light and the radius) reads the rounding of its terms: such a gradient, or a
parameter's whose reference is zero, is held to 1e-6 of the call's largest gradient entry (a parameter's: of the
largest entry's sum over the frame)."""
import itertools
import random
import sys
import warnings

import pytest
import torch

from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao import GTAO, HBAO, PSSAO, SSAO, SSILVB, UE4SSAO, BitmaskAO
from torch_ao.gbuffer import GBuffer

CALLS = 72  # (about 10 s)
MORE_CALLS = 600  # the slow test's: calls CALLS to MORE_CALLS (about a minute)
VALUE_TOL = 1e-5  # outputs: absolute
VALUE_OFF_SHARE = 0.001  # the share of an output's entries that may miss VALUE_TOL (a branch within rounding)
VALUE_OFF_MOST = 1e-3  # ... and by how much at most
GRAD_TOL = 1e-4  # a gradient's entries: relative to its largest
OFF_SHARE = 0.002  # the share of a gradient's entries that may miss GRAD_TOL (a value within rounding of a kink)
SCALAR_TOL = 1e-3  # a parameter's gradient: relative (it sums every entry's, those beside a kink too)
ZERO_TOL = 1e-6  # a gradient zero in theory: relative to the call's largest gradient entry


def _bitmask(rng: random.Random, common: dict) -> dict:
    variant = rng.choice(["default", "hdrp", "exact"])
    o = dict(common, mode=rng.choice(["soft", "straight_through", "hard"]), variant=variant,
             weighting=rng.choice(["uniform", "cosine"]), fetch=rng.choice(["nearest", "bilinear", "edge_aware"]),
             border=rng.choice(["drop", "clamp"]), tau=rng.choice([0.2, 0.3, 0.5]),
             thickness=rng.choice([0.1, 0.4, 1.0]), noise=rng.choice(["ign", "hilbert_r2"]),
             stagger=rng.random() < 0.3)
    if variant != "hdrp":  # (HDRP's rule takes its own azimuth and no sphere extent)
        o["azimuth"] = rng.choice(["view", "screen"])
        o["sample_extent"] = rng.choice(["radius", "sphere"])
    if variant != "exact":  # (the exact union gives the visibility alone and grows no thickness)
        o.update(bent_normals=rng.random() < 0.3, indirect=rng.random() < 0.3)
        if rng.random() < 0.25:
            o["thickness_growth"] = 0.2
        if o["mode"] == "hard" and o["weighting"] == "uniform":  # (uniform hard masks carry no gradient: the light)
            o["indirect"] = True
    return o


def draw(rng: random.Random) -> tuple[type, dict]:
    """A module class and its options."""
    kind = rng.choice(["bitmask", "bitmask", "bitmask", "glsl", "gtao", "gtao", "hbao", "ue4ssao", "pssao", "ssao"])
    common = dict(slices=rng.choice([2, 3, 4]), steps=rng.choice([2, 3, 4, 6]))
    if kind == "pssao":
        return PSSAO, dict(common, fetch=rng.choice(["nearest", "bilinear"]), border=rng.choice(["drop", "clamp"]),
                           distance_bias=rng.choice([0.5, 1.0]))
    common.update(seed=rng.randrange(5), radius=rng.choice([0.5, 0.8, 1.3]))
    if kind == "bitmask":
        return BitmaskAO, _bitmask(rng, common)
    if kind == "glsl":  # (the article's shader: its own step placement, noise and thickness rule)
        return SSILVB, dict(common, variant="ssilvb_glsl", mode=rng.choice(["soft", "straight_through", "hard"]),
                            slices=rng.choice([3, 4, 5]), tau=rng.choice([0.2, 0.5]), thickness=rng.choice([0.1, 0.5]))
    if kind == "gtao":
        return GTAO, dict(common, variant=rng.choice(["exact", "hdrp", "ue4"]),
                          fetch=rng.choice(["nearest", "bilinear", "edge_aware"]), border=rng.choice(["drop", "clamp"]),
                          falloff_range=rng.choice([0.0, 0.3]), bent_normals=rng.random() < 0.3,
                          multibounce=rng.random() < 0.3, stagger=rng.random() < 0.3)
    if kind == "hbao":
        return HBAO, dict(common, fetch=rng.choice(["nearest", "bilinear"]), border=rng.choice(["drop", "clamp"]),
                          falloff=rng.choice(["linear", "quadratic"]), accumulate=rng.choice(["incremental", "max"]),
                          azimuth=rng.choice(["view", "screen"]), stagger=rng.random() < 0.3)
    if kind == "ssao":  # (the hemisphere kernel with its soft occlusion test: the step's gradient is 0)
        return SSAO, dict(common, fetch=rng.choice(["nearest", "bilinear"]), border=rng.choice(["drop", "clamp"]),
                          samples=rng.choice([8, 16]), bias=rng.choice([0.025, 0.05]), softness=rng.choice([0.02, 0.05]))
    return UE4SSAO, dict(common, fetch=rng.choice(["nearest", "bilinear"]), border=rng.choice(["drop", "clamp"]),
                         flat_softness=rng.choice([0.0, 0.05]))


def outputs_and_gradients(cls, options: dict, gb0: GBuffer, light0: torch.Tensor, dtype, backend: str,
                          device: str = "cpu"):
    """The module's outputs that carry a gradient (float64, on the CPU) and the gradients of a fixed random weighting
    of them with respect to depth, normals, light and the trainable parameters (None where unused; names in order),
    computed on ``device``."""
    gb0 = gb0.to(device=device, dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    light = light0.to(device=device, dtype=dtype).clone().requires_grad_()
    module = cls(backend=backend, **options).to(device=device, dtype=dtype)
    out = module(GBuffer(depth=depth, normals=normals, light=light, camera=gb0.camera))
    weights = torch.Generator().manual_seed(1)
    values, loss = {}, 0.0
    for name in ("visibility", "bent_normal", "indirect"):
        value = getattr(out, name, None)
        if isinstance(value, torch.Tensor) and value.requires_grad:
            w = torch.rand(value.shape, generator=weights, dtype=torch.float64).to(device=device, dtype=dtype)
            loss = loss + (value * w).sum()
            values[name] = value.detach().double().cpu()
    names, params = zip(*[(n, p) for n, p in module.named_parameters() if p.requires_grad])
    grads = torch.autograd.grad(loss, [depth, normals, light, *params], allow_unused=True)
    grads = {n: None if g is None else g.double().cpu() for n, g in zip(("depth", "normals", "light", *names), grads)}
    return values, grads


def _distance(a: torch.Tensor | None, b: torch.Tensor | None) -> float:
    a, b = (torch.zeros(()) if x is None else x for x in (a, b))
    return float((a - b).norm())


def _call(index: int):
    rng = random.Random(1000 + index)
    cls, options = draw(rng)
    return cls, options, index % 3


@pytest.mark.parametrize("index", range(CALLS))
def test_kernel_agrees_with_the_tensor_walk_on_drawn_options(built, index):
    assert_agrees_on_drawn_options(index, "cpu")


@pytest.mark.slow
@pytest.mark.parametrize("lanes", ["simd", "scalar"])
def test_kernel_agrees_with_the_tensor_walk_on_many_more_drawn_options(built, lanes, monkeypatch):
    """Calls CALLS to MORE_CALLS, in the CPU's vector lanes or, ``scalar``, every kernel in the scalar lanes: one pixel
    at a time through walk_pixel, the CUDA thread's body (lanes_scalar.h, the lanes NVRTC compiles)."""
    if lanes == "scalar":
        from torch_ao.kernels import bitmask, frame, launch, soft_bitmask, soft_exact, walk_grad  # noqa: F401

        patched, switch = set(), frame.scalar_lanes
        for module in list(sys.modules.values()):  # (each kernel module imports the switch by name)
            if getattr(module, "scalar_lanes", None) is switch:
                monkeypatch.setattr(module, "scalar_lanes", lambda lanes: True)
                patched.add(module.__name__.rsplit(".", 1)[-1])
        assert {"launch", "bitmask", "soft_bitmask", "soft_exact", "walk_grad"} <= patched, patched
    for index in range(CALLS, MORE_CALLS):
        try:
            assert_agrees_on_drawn_options(index, "cpu")
        except AssertionError as error:
            raise AssertionError(f"drawn call {index}: {error}") from error


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("index", range(CALLS))
def test_cuda_kernel_agrees_with_the_tensor_walk_on_drawn_options(built, index):
    """The same calls on a CUDA G-buffer (the walk's CUDA kernels and their backwards), against the float64 tensor
    walk on the CPU, by the same tolerances (the GPU's float32 rounds as differently from float64 as the CPU's)."""
    assert_agrees_on_drawn_options(index, "cuda")


def assert_agrees_on_drawn_options(index: int, device: str) -> None:
    """Call ``index``'s kernel on ``device`` against the tensor walk on the CPU (the tolerances of the module
    docstring)."""
    cls, options, seed = _call(index)
    gb = rough_gbuffer(24, 40, batch=2, seed=seed)
    light = torch.rand(2, 3, 24, 40, generator=torch.Generator().manual_seed(seed))
    ref, ref_grads = outputs_and_gradients(cls, options, gb, light, torch.float64, "torch")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # (a kernel that cannot be built must not fall back here)
        got, got_grads = outputs_and_gradients(cls, options, gb, light, torch.float32, "kernel", device)
    ref32, ref32_grads = outputs_and_gradients(cls, options, gb, light, torch.float32, "torch")
    assert got.keys() == ref.keys() and ref  # (the same outputs on the graph: hard masks are off it)
    for name in ref:
        moved = float((ref32[name] - ref[name]).abs().max())
        err = (got[name] - ref[name]).abs()
        off = err > max(VALUE_TOL, 3 * moved)
        assert float(off.double().mean()) <= VALUE_OFF_SHARE, (cls.__name__, options, name, float(err.max()), moved)
        assert float(err.max()) <= max(VALUE_OFF_MOST, 3 * moved), (cls.__name__, options, name, float(err.max()))
    assert ref_grads["depth"].abs().sum() > 0
    # the scalar parameters' gradients are sums over the frame: their rounding is absolute, at the largest one's scale;
    # a gradient zero in theory reads its terms' rounding, at the scale of the call's largest gradient entry
    scale = max((float(g.abs()) for g in ref_grads.values() if g is not None and g.dim() == 0), default=0.0)
    largest = max(float(g.abs().max()) for g in ref_grads.values() if g is not None and g.dim() > 0)
    zero_floor = ZERO_TOL * largest
    scalar_floor = ZERO_TOL * max(float(g.abs().sum()) for g in ref_grads.values() if g is not None and g.dim() > 0)
    for name, ref_grad in ref_grads.items():
        got_grad, ref32_grad = got_grads[name], ref32_grads[name]
        if ref_grad is None:  # (an input or setting the walk does not read: none, or a parameter's rounding)
            if name in ("depth", "normals", "light"):
                assert got_grad is None, (cls.__name__, options, name)
            else:  # (a nearest fetch's radius: Euler's identity sums to the rounding of 0)
                assert got_grad is None or float(got_grad.abs()) <= max(1e-4 * scale, scalar_floor), \
                    (cls.__name__, options, name, float(got_grad))
            continue
        if ref_grad.dim() == 0:
            err, moved = _distance(got_grad, ref_grad), _distance(ref32_grad, ref_grad)
            size = _distance(ref_grad, None)
            assert err <= max(SCALAR_TOL * size, 3 * moved, 1e-6 * scale, scalar_floor), \
                (cls.__name__, options, name, err, moved, size)
            continue
        assert got_grad is not None, (cls.__name__, options, name)
        moved = (ref32_grad - ref_grad).abs()
        allowed = GRAD_TOL * float(ref_grad.abs().max()) + 3 * float(moved.max()) + zero_floor + 1e-12
        off = (got_grad - ref_grad).abs() > allowed
        assert float(off.double().mean()) <= OFF_SHARE, (cls.__name__, options, name, float(off.double().mean()))
        kept = ~off  # (the whole gradient's bound, over the entries that are not beside a kink or a branch)
        assert _distance(got_grad[kept], ref_grad[kept]) <= max(1e-2 * _distance(ref_grad[kept], None),
                                                                3 * float(moved[kept].norm()),
                                                                zero_floor * float(kept.sum()) ** 0.5), \
            (cls.__name__, options, name)


GRAPH_CASES = [
    (BitmaskAO, dict(indirect=True, bent_normals=True, weighting="cosine", fetch="edge_aware", ambient=(0.1, 0.2, 0.3))),
    (BitmaskAO, dict(indirect=True, bent_normals=True, fetch="nearest")),
    (BitmaskAO, dict(indirect=True, variant="hdrp")),
    (BitmaskAO, dict(indirect=True, bent_normals=True, slice_sampling="projected_normal")),
    (BitmaskAO, dict(variant="exact")),
    (SSILVB, dict(variant="ssilvb_glsl")),
]


@pytest.mark.parametrize("mode", ["hard", "soft", "straight_through"])
@pytest.mark.parametrize("case", range(len(GRAPH_CASES)))
def test_kernel_outputs_are_on_the_graph_where_the_tensor_walks_are(built, case, mode):
    """Which outputs require a gradient, with the depth, the light and the parameters each requiring one or not: one
    kernel call gives every output, but each is on the graph only where its tensor-path twin is (a hard mask has no
    gradient; a visibility reads no light; a nearest fetch's light does not move with the radius)."""
    cls, options = GRAPH_CASES[case]
    gb = rough_gbuffer(24, 40, batch=2, seed=0)
    fields = ("visibility", "indirect", "bent_normal", "ambient")
    for depth_grad, light_grad, trainable in itertools.product((False, True), repeat=3):
        on_graph = {}
        for backend in ("torch", "kernel"):
            depth = gb.depth.clone().requires_grad_(depth_grad)
            light = torch.rand(2, 3, 24, 40, generator=torch.Generator().manual_seed(0)).requires_grad_(light_grad)
            module = cls(backend=backend, mode=mode, slices=4, steps=3, trainable=trainable, **options)
            out = module(GBuffer(depth=depth, light=light, camera=gb.camera))
            on_graph[backend] = {name: getattr(out, name).requires_grad for name in fields
                                 if getattr(out, name, None) is not None}
        assert on_graph["kernel"] == on_graph["torch"], (depth_grad, light_grad, trainable)
