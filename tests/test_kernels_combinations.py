"""Random combinations of a module's options, each run by its kernel (``backend="kernel"``, float32) and by the
tensor-op walk (``backend="torch"``) in float64: the outputs and the gradients of depth (or a position buffer, every
fifth call), normals, light, the camera's intrinsics (every fourth call) and every trainable parameter agree, every
seventh call at half resolution (the walk on the 2x2-decimated frame, upsampled). The
other kernel tests pick their settings by hand; these draw them (a fixed seed), so that options meet that no
hand-picked setting combines. Bitmask AO draws a thickness model in two calls of five (back-face layer, map, per
object, linear, the net's map), read from a G-buffer that carries object ids and a back-face layer in every call.

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
  than 1e-3; float64's central differences lie between them). A sum over those kinks is then any of many values (the
  intrinsics' gradient of one call of 3,000 was 26 % off, the float32 walk's 7 %), so PSSAO's calls take normals of
  their own, the depth's turned by about a degree, off the kink.

So 0.2 % of a gradient's entries may miss, the gradient as a whole stays within 1 %, and a parameter's gradient (a
sum over the frame) within 1e-3, or, where a pixel sits within float32's rounding of a kink in that parameter (the
radius, where a segment's end meets the radius' sphere), between the float64 walk's one-sided difference quotients
a step of 1e-6 of it to either side. Such an event moves a gradient at a pixel's own entries and at the taps of the
sample it concerns: a step within float32's rounding of a texel's edge (a nearest or edge-aware fetch reads the other
texel, and the gradient moves from one tap to another: the sample's old and new taps), or a hard mask's sector that
flipped. So beyond the 0.2 %, each pixel whose value is off, and one more that the values do not show, may move 9
entries a channel; and where the per-pixel values or gradients show such an event, a sum over the frame (a
parameter's gradient, the intrinsics') moves by that pixel's share: within 5e-3 there (seen: 2.2e-3, the radius
with a step at a texel edge; 4.2e-3, the intrinsics with `GTAO(variant="hdrp")`'s projected normal below). Jitter
stays on: without it, steps land on texel edges, where float32 and float64 floor differently
(tests/test_kernels_soft_gbuffer.py covers that against the float32 walk).

Branches and float32's conditioning make the rest of the values. Where a call's value is a branch's within float32's
rounding of its threshold, or moves by more than its tolerance with its inputs' last bit, the kernel and the float32
tensor walk round to different values, so "three times the float32 walk's movement" does not bound it there. Seen
over 528 more drawn calls (slow test below), at 1 to 5 entries of a call: `GTAO(variant="hdrp")` at one pixel, where
the kernel's value took one of two values 2.3e-5 apart as the normals were nudged in their last bit while the
float64 walk's moved by 6e-8. That is HDRP's projected normal angle, ``n = sign(n . T) GTAOFastAcos(cos n)``, at a
slice whose ``n`` is near 0 (-3.2e-4 rad at the pixel of calls 1562 and 1946): float32 holds no cosine between 1 and
1 - 6e-8, and the square root in the fast acos turns those two into n = 0 or 3.5e-4 (the tensor walk takes cos n from
atan2's angle, the kernel from the projected normal's components, so their float32 values can land on either); and
`UE4SSAO` with a bilinear fetch, whose value at a few pixels is ill-conditioned in float32 (nudging the depth in its
last bit moved the float32 walk's error there between -3e-5 and 8e-5, and the kernel's with it), so that one input's
float32 walk can be close where the kernel is not. So 0.1 % of an output's entries may miss the value tolerance,
each by at most 1e-3, or, for a hard or straight-through mask, by a sector of one slice (the rule for hard masks: a
cosine-weighted sector's share is at most pi / 2 of a uniform one's; the bent normal, which that sector turns, twice
that, seen 1.6 times). Each such pixel is an event of the gradients' rule above, and the 1 % bound on a whole
gradient is taken over the entries that no event moved.

A gradient that is zero in theory (a hard mask's visibility through the depth, where only the normals turn the
cosine weights; a nearest fetch's light and the radius) reads the rounding of its terms: such a gradient, or a
parameter's whose reference is zero, is held to 1e-6 of the call's largest gradient entry (a parameter's: of the
largest entry's sum over the frame)."""
import dataclasses
import itertools
import math
import random
import sys
import warnings

import pytest
import torch

from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao import GTAO, HBAO, PSSAO, SSAO, SSILVB, UE4SSAO, BitmaskAO
from torch_ao.gbuffer import GBuffer
from torch_ao.thickness import BackfaceThickness, LinearThickness, MapThickness, NetThickness, ObjectThickness

CALLS = 72  # (about 10 s)
MORE_CALLS = 600  # the slow test's: calls CALLS to MORE_CALLS (about a minute)
VALUE_TOL = 1e-5  # outputs: absolute
VALUE_OFF_SHARE = 0.001  # the share of an output's entries that may miss VALUE_TOL (a branch within rounding)
VALUE_OFF_MOST = 1e-3  # ... and by how much at most
GRAD_TOL = 1e-4  # a gradient's entries: relative to its largest
OFF_SHARE = 0.002  # the share of a gradient's entries that may miss GRAD_TOL (a value within rounding of a kink)
FLIP_ENTRIES = 9  # ... and an event's entries a channel (a pixel's own, and a sample's old and new four taps)
SCALAR_TOL = 1e-3  # a parameter's gradient: relative (it sums every entry's, those beside a kink too)
EVENT_SCALAR_TOL = 5e-3  # ... where the per-pixel values or gradients show an event (a pixel's share of the sum)
ZERO_TOL = 1e-6  # a gradient zero in theory: relative to the call's largest gradient entry
KINK_STEP = 1e-6  # a parameter's difference quotients: the step, relative to the parameter (float32's rounding)
HEIGHT, WIDTH, BATCH = 24, 40, 2  # every call's frame (rough_gbuffer)
PER_PIXEL = ("depth", "position", "normals", "light")  # the G-buffer's images (their gradients a pixel's)


def _thickness_model(rng: random.Random):
    """A thickness model in place of a scalar thickness. Each reads what every call's G-buffer carries
    (drawn_gbuffer: object ids, a back-face layer); the map varies across the frame, so that the walk reads it at
    its samples, not at the pixel."""
    kind = rng.choice(["backface", "map", "object", "linear", "net"])
    if kind == "backface":
        return BackfaceThickness(scale=rng.choice([0.8, 1.2]), thickness=rng.choice([0.0, 0.05]))
    if kind == "map":
        u = torch.linspace(0, 1, WIDTH).view(1, 1, 1, WIDTH)
        return MapThickness((0.05 + 0.6 * torch.sin(12 * u) ** 2).expand(BATCH, 1, HEIGHT, WIDTH).contiguous())
    if kind == "object":
        return ObjectThickness(torch.tensor([0.05, 0.8]))
    if kind == "linear":
        return LinearThickness(rng.choice([0.02, 0.1]), rng.choice([0.05, 0.15]))
    with torch.random.fork_rng():  # (the net's initial weights)
        torch.manual_seed(rng.randrange(100))
        return NetThickness(scale=1.0, init=0.3, thickness=0.05)


def drawn_gbuffer(seed: int, tilted: bool = False) -> GBuffer:
    """rough_gbuffer's frame with two objects (split by a diagonal) and a back-face layer behind every surface;
    ``tilted``: with normals of their own, the depth's turned by about 1 degree at random (PSSAO's: see the module
    docstring)."""
    gb = rough_gbuffer(HEIGHT, WIDTH, batch=BATCH, seed=seed)
    v, u = torch.meshgrid(torch.arange(HEIGHT), torch.arange(WIDTH), indexing="ij")
    ids = (u * HEIGHT + v * WIDTH > HEIGHT * WIDTH).to(torch.int64).expand(BATCH, 1, HEIGHT, WIDTH).contiguous()
    normals = None
    if tilted:
        turn = 0.02 * torch.randn(BATCH, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(seed))
        normals = torch.nn.functional.normalize(gb.view_normals() + turn, dim=1)
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=normals, object_id=ids,
                   backface_depth=gb.depth * 1.02 + 0.3)


def _bitmask(rng: random.Random, common: dict) -> dict:
    variant = rng.choice(["default", "hdrp", "exact"])
    o = dict(common, mode=rng.choice(["soft", "straight_through", "hard"]), variant=variant,
             weighting=rng.choice(["uniform", "cosine"]), fetch=rng.choice(["nearest", "bilinear", "edge_aware"]),
             border=rng.choice(["drop", "clamp"]), tau=rng.choice([0.2, 0.3, 0.5]),
             thickness=rng.choice([0.1, 0.4, 1.0]), noise=rng.choice(["ign", "hilbert_r2"]),
             stagger=rng.random() < 0.3)
    if rng.random() < 0.4:
        o["thickness"] = _thickness_model(rng)
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
                          device: str = "cpu", shift: tuple[str, float] | None = None, inputs: tuple[str, ...] = ()):
    """The module's outputs that carry a gradient (float64, on the CPU), the gradients of a fixed random weighting
    of them with respect to the G-buffer (depth, or with ``"position"`` in ``inputs`` a position buffer; normals;
    light; with ``"intrinsics"`` in ``inputs`` the camera's) and the trainable parameters (None where unused; names
    in order), computed on ``device``, and that weighted sum (the loss). ``shift``: a parameter's name and what to
    add to it."""
    gb0 = gb0.to(device=device, dtype=dtype)
    leaves = {}
    if "position" in inputs:
        leaves["position"] = gb0.positions().detach().clone().requires_grad_()
    else:
        leaves["depth"] = gb0.depth.detach().clone().requires_grad_()
    leaves["normals"] = gb0.view_normals().detach().clone().requires_grad_()
    leaves["light"] = light0.to(device=device, dtype=dtype).clone().requires_grad_()
    camera = gb0.camera
    if "intrinsics" in inputs:
        camera = dataclasses.replace(camera, intrinsics=camera.intrinsics.detach().clone().requires_grad_())
        leaves["intrinsics"] = camera.intrinsics
    module = cls(backend=backend, **options).to(device=device, dtype=dtype)
    if shift is not None:
        with torch.no_grad():
            getattr(module, shift[0]).add_(shift[1])
    out = module(GBuffer(depth=leaves.get("depth", gb0.depth), position=leaves.get("position"),
                         normals=leaves["normals"], light=leaves["light"], camera=camera, object_id=gb0.object_id,
                         backface_depth=gb0.backface_depth))
    weights = torch.Generator().manual_seed(1)
    values, loss = {}, 0.0
    for name in ("visibility", "bent_normal", "indirect"):
        value = getattr(out, name, None)
        if isinstance(value, torch.Tensor) and value.requires_grad:
            w = torch.rand(value.shape, generator=weights, dtype=torch.float64).to(device=device, dtype=dtype)
            loss = loss + (value * w).sum()
            values[name] = value.detach().double().cpu()
    names, params = zip(*[(n, p) for n, p in module.named_parameters() if p.requires_grad])
    grads = torch.autograd.grad(loss, [*leaves.values(), *params], allow_unused=True)
    grads = {n: None if g is None else g.double().cpu() for n, g in zip((*leaves, *names), grads)}
    return values, grads, float(loss.detach())


def _distance(a: torch.Tensor | None, b: torch.Tensor | None) -> float:
    a, b = (torch.zeros(()) if x is None else x for x in (a, b))
    return float((a - b).norm())


def _call(index: int):
    """Call ``index``'s module class, options, frame seed and the G-buffer inputs beyond depth, normals and light
    whose gradients it compares (outputs_and_gradients' ``inputs``)."""
    rng = random.Random(1000 + index)
    cls, options = draw(rng)
    if index % 7 == 5:  # (the walk on the 2x2-decimated frame, upsampled)
        options = dict(options, resolution="half")
    inputs = (("position",) if index % 5 == 4 else ()) + (("intrinsics",) if index % 4 == 2 else ())
    return cls, options, index % 3, inputs


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
    cls, options, seed, inputs = _call(index)
    gb = drawn_gbuffer(seed, tilted=cls is PSSAO)
    light = torch.rand(BATCH, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(seed))
    ref, ref_grads, _ = outputs_and_gradients(cls, options, gb, light, torch.float64, "torch", inputs=inputs)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # (a kernel that cannot be built must not fall back here)
        got, got_grads, _ = outputs_and_gradients(cls, options, gb, light, torch.float32, "kernel", device,
                                                  inputs=inputs)
    ref32, ref32_grads, _ = outputs_and_gradients(cls, options, gb, light, torch.float32, "torch", inputs=inputs)
    assert got.keys() == ref.keys() and ref  # (the same outputs on the graph: hard masks are off it)
    # a hard mask's value: a sector of one slice may flip (its largest cosine weight: pi / 2 of a uniform one's), and
    # turn the bent normal by twice that at most (seen: 1.6 times)
    hard = cls in (BitmaskAO, SSILVB) and options["mode"] != "soft"
    sector = math.pi / 2 / (32 * options["slices"]) if hard else 0.0
    flipped = torch.zeros(BATCH, 1, HEIGHT, WIDTH, dtype=torch.bool)  # the pixels where some output is off
    for name in ref:
        moved = float((ref32[name] - ref[name]).abs().max())
        err = (got[name] - ref[name]).abs()
        off = err > max(VALUE_TOL, 3 * moved)
        flipped |= off.any(1, keepdim=True)
        most = max(VALUE_OFF_MOST, (2 if name == "bent_normal" else 1) * sector, 3 * moved)
        assert float(off.double().mean()) <= VALUE_OFF_SHARE, (cls.__name__, options, name, float(err.max()), moved)
        assert float(err.max()) <= most, (cls.__name__, options, name, float(err.max()))
    assert ref_grads["position" if "position" in inputs else "depth"].abs().sum() > 0
    # the scalar parameters' gradients (and the intrinsics') are sums over the frame: their rounding is absolute, at
    # the largest one's scale; a gradient zero in theory reads its terms' rounding, at the scale of the call's largest
    # entry of a per-pixel gradient
    scale = max((float(g.abs()) for g in ref_grads.values() if g is not None and g.dim() == 0), default=0.0)
    images = [g for n, g in ref_grads.items() if g is not None and n in PER_PIXEL]
    zero_floor = ZERO_TOL * max(float(g.abs().max()) for g in images)
    scalar_floor = ZERO_TOL * max(float(g.abs().sum()) for g in images)
    events = int(flipped.sum()) + 1  # (each pixel whose value is off, and one the values do not show)
    event_seen = bool(flipped.any())  # (and any per-pixel gradient's entry off: they come first in ref_grads)
    for name, ref_grad in ref_grads.items():
        got_grad, ref32_grad = got_grads[name], ref32_grads[name]
        if ref_grad is None:  # (an input or setting the walk does not read: none, or a parameter's rounding)
            if name in PER_PIXEL or name == "intrinsics":
                assert got_grad is None, (cls.__name__, options, name)
            else:  # (a nearest fetch's radius: Euler's identity sums to the rounding of 0)
                assert got_grad is None or float(got_grad.abs()) <= max(1e-4 * scale, scalar_floor), \
                    (cls.__name__, options, name, float(got_grad))
            continue
        if name not in PER_PIXEL:  # (a parameter's, the intrinsics': sums over the frame)
            err, moved = _distance(got_grad, ref_grad), _distance(ref32_grad, ref_grad)
            size = _distance(ref_grad, None)
            bound = max((EVENT_SCALAR_TOL if event_seen else SCALAR_TOL) * size, 3 * moved, 1e-6 * scale, scalar_floor)
            if err > bound and ref_grad.dim() == 0:  # (a pixel within float32's rounding of a kink: its other side)
                low, high = _difference_quotients(cls, options, gb, light, name)
                assert low - bound <= float(got_grad) <= high + bound, \
                    (cls.__name__, options, name, float(got_grad), float(ref_grad), low, high)
            else:
                assert err <= bound, (cls.__name__, options, name, err, moved, size)
            continue
        assert got_grad is not None, (cls.__name__, options, name)
        moved = (ref32_grad - ref_grad).abs()
        allowed = GRAD_TOL * float(ref_grad.abs().max()) + 3 * float(moved.max()) + zero_floor + 1e-12
        off = (got_grad - ref_grad).abs() > allowed
        flips = FLIP_ENTRIES * ref_grad.shape[1] * events
        event_seen |= bool(off.any())
        assert int(off.sum()) <= OFF_SHARE * off.numel() + flips, (cls.__name__, options, name, int(off.sum()), flips)
        kept = ~off  # (the whole gradient's bound, over the entries that are not beside a kink or a branch)
        assert _distance(got_grad[kept], ref_grad[kept]) <= max(1e-2 * _distance(ref_grad[kept], None),
                                                                3 * float(moved[kept].norm()),
                                                                zero_floor * float(kept.sum()) ** 0.5), \
            (cls.__name__, options, name)


def _difference_quotients(cls, options: dict, gb: GBuffer, light: torch.Tensor, name: str) -> tuple[float, float]:
    """The float64 tensor walk's one-sided difference quotients of the loss in parameter ``name``, a step of
    KINK_STEP of it to each side (the least and the largest): a kink within the kernel's float32 rounding lies
    between them, and any derivative on either side of it within their interval."""
    value = float(getattr(cls(**options), name).detach())
    step = KINK_STEP * max(abs(value), 1.0)
    if options.get("mode") == "straight_through":  # (its gradients are the soft walk's)
        options = dict(options, mode="soft")
    loss = [outputs_and_gradients(cls, options, gb, light, torch.float64, "torch", shift=(name, d))[2]
            for d in (-step, 0.0, step)]
    quotients = ((loss[1] - loss[0]) / step, (loss[2] - loss[1]) / step)
    return min(quotients), max(quotients)


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
