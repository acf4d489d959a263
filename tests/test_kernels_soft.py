"""The soft / straight-through bitmask walk (walk.h with soft.h) against the tensor-op walk: values to 1e-5,
gradients of radius and thickness to 1e-4 relative, in both lane types; finite differences; the hard limit;
what it does not cover."""
import math
import warnings

import pytest
import torch

from kernel_agreement import assert_values_agree
from kernel_calls import count_kernel_calls, on_threads
from test_kernels import FRAMES, built, kernel_of, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import KernelUnavailable, bitmask_soft
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.methods.bitmask import BitmaskAO


SETTINGS = [
    dict(mode="soft", slices=3, steps=4),
    dict(mode="soft", slices=3, steps=3, weighting="cosine", tau=0.5),
    dict(mode="straight_through", slices=3, steps=4, weighting="cosine"),
    dict(mode="soft", slices=2, steps=5, tau=0.05, jitter=False, rounding="round", step_power=2.0, min_step_px=2.0),
    dict(mode="straight_through", slices=3, steps=3, fetch="nearest", border="clamp", rounding="floor", seed=3),
    dict(mode="soft", slices=2, steps=4, border="clamp", sector_epsilon=0.0, thickness=0.9, radius=0.6, tau=0.1,
         weighting="cosine"),
    dict(mode="soft", slices=3, steps=3, noise="hilbert_r2", stagger=True, seed=1),
    dict(mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware"),  # torch-ao fit's pipeline with one scalar thickness
    dict(mode="straight_through", slices=3, steps=3, fetch="edge_aware", border="clamp", tau=0.2),
    dict(mode="soft", slices=2, steps=4, tau=1.5),  # a temperature whose sector window (soft.h) still leaves some out
    dict(mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware", azimuth="screen"),
]


def _loss_weights(vis: torch.Tensor) -> torch.Tensor:
    """Per-pixel weights of the test loss (not uniform, so that every pixel's gradient counts differently)."""
    return torch.linspace(0.5, 1.5, vis.numel()).view_as(vis)


def _one_sector(slices: int) -> float:
    """The most one flipped cosine-weighted sector of one slice moves the visibility: a sector's weight is at
    most pi/2 times the uniform 1/32 (the weight's density peaks at pi/2 times its mean)."""
    return (math.pi / 2) / (32 * slices) + 1e-6


def visibility_and_grads(gb: GBuffer, backend: str, **settings):
    module = BitmaskAO(backend=backend, **settings)
    vis = module(gb).visibility
    loss = (vis * _loss_weights(vis)).sum()
    grads = torch.autograd.grad(loss, [module.radius, module.thickness], allow_unused=True)
    return vis.detach(), [torch.zeros(()) if g is None else g for g in grads]


@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_values_and_gradients_equal_the_tensor_walk(built, frame, setting):
    gb = FRAMES[frame]()
    settings = SETTINGS[setting]
    reference, (ref_radius, ref_thickness) = visibility_and_grads(gb, "torch", **settings)
    out, (radius, thickness) = visibility_and_grads(gb, "kernel", **settings)
    assert out.shape == reference.shape and out.dtype == reference.dtype
    assert reference.min() < 1  # something is occluded: the comparison means something
    # The walk's float32 operations are not the tensor walk's in the same order (slice directions, the
    # radius' slope of a step as radius_px / radius): a few ulp apart, which the 1/tau^2 terms of a small
    # tau amplify (measured: up to 3e-6 in a value at tau = 0.05, 1.6e-5 relative in a radius gradient).
    if settings["mode"] == "soft":
        assert (out - reference).abs().max() <= 1e-5
    else:  # a hard forward: a sector at the edge of rounding may flip (kernel_agreement)
        assert_values_agree(out, reference, gb.valid, bound=_one_sector(settings["slices"]))
    assert ref_thickness != 0
    for got, want in ((radius, ref_radius), (thickness, ref_thickness)):
        assert abs(got - want) <= 1e-4 * abs(want) + 1e-7, (got, want)
    if settings.get("fetch") != "nearest":  # (a nearest fetch does not move with the radius)
        assert ref_radius != 0


def test_hard_mode_with_cosine_weights_equals_the_tensor_walk(built):
    """The hard kernel has uniform sectors only; this kernel's straight-through forward covers hard mode with
    cosine weights: the same masks, the cosine weights without trigonometry (to a few ulp of torch's)."""
    for frame in ("example", "rough"):
        gb = FRAMES[frame]()
        settings = dict(mode="hard", weighting="cosine", slices=3, steps=4)
        reference = BitmaskAO(backend="torch", **settings)(gb).visibility
        out = BitmaskAO(backend="kernel", **settings)(gb).visibility
        assert not out.requires_grad and reference.min() < 1
        assert_values_agree(out, reference, gb.valid, atol=1e-6, bound=_one_sector(settings["slices"]))


def test_straight_through_forward_is_the_hard_kernels_visibility_bit_for_bit(built):
    gb = rough_gbuffer()
    settings = dict(slices=3, steps=4, rounding="round")
    hard = kernel_of(BitmaskAO(mode="hard", **settings), gb)
    straight = BitmaskAO(mode="straight_through", backend="kernel", **settings)(gb).visibility
    assert straight.requires_grad and torch.equal(straight.detach(), hard)


@pytest.mark.parametrize("weighting", ["uniform", "cosine"])
def test_gradients_match_finite_differences(built, weighting):
    """Central differences of the kernel's own float32 forward (h = 2e-3 world units; the smooth masks at
    tau = 0.5 keep the truncation error well below the 2 % tolerance, float32 rounding of the mean below 1e-6).
    Clamped borders: with ``border="drop"`` a sample leaving the image jumps from occluding to not, a step
    in the forward that finite differences see and the gradient (rightly) does not."""
    gb = example_gbuffer(32, 48)
    normals = gb.view_normals()
    args = dict(slices=3, steps=4, tau=0.5, weighting=weighting, border="clamp")
    radius, thickness = torch.tensor(0.8, requires_grad=True), torch.tensor(0.4, requires_grad=True)
    vis = bitmask_soft(gb, normals, radius=radius, thickness=thickness, **args)
    g_radius, g_thickness = torch.autograd.grad(vis.mean(), [radius, thickness])
    h = 2e-3
    with torch.no_grad():
        mean = lambda r, t: bitmask_soft(gb, normals, radius=torch.tensor(r), thickness=torch.tensor(t),  # noqa: E731
                                         **args).double().mean().item()
        fd_radius = (mean(0.8 + h, 0.4) - mean(0.8 - h, 0.4)) / (2 * h)
        fd_thickness = (mean(0.8, 0.4 + h) - mean(0.8, 0.4 - h)) / (2 * h)
    assert abs(fd_radius) > 1e-3 and abs(fd_thickness) > 1e-3
    assert g_radius.item() == pytest.approx(fd_radius, rel=2e-2)
    assert g_thickness.item() == pytest.approx(fd_thickness, rel=2e-2)


def test_soft_tends_to_hard_as_tau_goes_to_zero(built):
    gb = rough_gbuffer()
    settings = dict(slices=3, steps=4)
    hard = kernel_of(BitmaskAO(mode="hard", **settings), gb)
    errors = []
    with torch.no_grad():
        for tau in (0.5, 0.1, 0.02, 0.005):
            soft = BitmaskAO(mode="soft", tau=tau, backend="kernel", **settings)(gb).visibility
            errors.append((soft - hard).abs().mean().item())
    assert all(a > b for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 2e-3 and errors[0] > 10 * errors[-1], errors


def test_background_is_unoccluded_and_batch_images_are_independent(built):
    from torch_ao.camera import PinholeCamera

    gb = rough_gbuffer()
    module = BitmaskAO(mode="soft", slices=3, steps=4, weighting="cosine", backend="kernel")
    out = module(gb).visibility.detach()
    assert torch.equal(out[~gb.valid], torch.ones_like(out[~gb.valid]))
    one = GBuffer(depth=gb.depth[1:], camera=PinholeCamera(gb.camera.intrinsics[1:], gb.camera.height, gb.camera.width))
    assert torch.equal(module(one).visibility.detach(), out[1:])


def test_backward_is_deterministic_across_thread_counts(built):
    gb = rough_gbuffer()
    grads = on_threads(lambda: visibility_and_grads(gb, "kernel", mode="soft", slices=3, steps=4)[1])
    assert all(torch.equal(a, b) for a, b in zip(*grads))


# ------------------------------------------------------------------------------- what it covers
def test_kernel_covers_names_what_it_does_not_cover():
    gb = example_gbuffer(8, 8)
    covers = soft_module.kernel_covers
    for mode in ("soft", "straight_through"):
        for weighting in ("uniform", "cosine"):
            assert covers(BitmaskAO(mode=mode, weighting=weighting), gb) is None
    assert covers(BitmaskAO(mode="hard", weighting="cosine"), gb) is None  # (uniform: the hard kernel's first)
    ids = GBuffer(depth=gb.depth, camera=gb.camera, object_id=torch.zeros(gb.depth.shape, dtype=torch.int64))
    assert covers(BitmaskAO(mode="soft", thickness=torch.ones(3)), ids) is None  # (the table's gradient: autograd's)
    assert covers(BitmaskAO(mode="soft", thickness=torch.ones(3), thickness_growth=0.5), ids) is None
    assert covers(BitmaskAO(mode="soft", indirect=True, bent_normals=True), gb) is None
    assert "ssilvb_glsl" in covers(BitmaskAO(mode="soft", variant="ssilvb_glsl"), gb)
    assert "float64" in covers(BitmaskAO(mode="soft"), gb.to(dtype=torch.float64))
    assert covers(BitmaskAO(mode="soft", fetch="edge_aware"), gb) is None
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)
    assert covers(BitmaskAO(mode="soft", fetch="edge_aware"), graph) is None
    # (G-buffer gradients: tests/test_kernels_soft_gbuffer.py)


def test_auto_backend_runs_the_soft_kernel(built, monkeypatch):
    calls = count_kernel_calls(monkeypatch, "bitmask")
    gb = rough_gbuffer()
    auto = BitmaskAO(mode="soft", slices=3, steps=4)(gb).visibility
    assert calls == [1] and auto.requires_grad
    reference = BitmaskAO(mode="soft", slices=3, steps=4, backend="torch")(gb).visibility
    assert (auto - reference).abs().max() <= 1e-6
    BitmaskAO(mode="hard", slices=3, steps=4)(gb)  # the hard kernel's
    assert calls == [1]


def test_a_soft_kernel_that_cannot_be_built_falls_back_with_one_warning(monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    def unavailable(*args, **kwargs):
        raise KernelUnavailable("the C++ kernels could not be built (no compiler)")

    monkeypatch.setattr(soft_module, "cpu_kernels", unavailable)
    monkeypatch.setattr(dispatch, "_warned", set())
    gb = example_gbuffer(16, 24)
    expected = BitmaskAO(mode="soft", slices=2, steps=3, backend="torch")(gb).visibility
    with pytest.warns(RuntimeWarning, match="no compiler.*tensor-op walk"):
        out = BitmaskAO(mode="soft", slices=2, steps=3, backend="kernel")(gb).visibility
    assert torch.equal(out, expected) and out.requires_grad
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        BitmaskAO(mode="soft", slices=2, steps=3)(gb)  # warned once


@pytest.mark.slow
def test_compiled_module_runs_the_kernel_with_eager_values_and_gradients(built):
    """``torch.compile`` traces the op as one graph node (its fake shapes) and its registered backward."""
    gb = example_gbuffer(24, 32)
    module = BitmaskAO(mode="soft", slices=2, steps=3, weighting="cosine")
    compiled = torch.compile(module, dynamic=False)
    out = compiled(gb).visibility
    grads = torch.autograd.grad(out.sum(), [module.radius, module.thickness])
    eager = module(gb).visibility
    assert torch.equal(out, eager)
    assert all(torch.equal(a, b) for a, b in zip(grads, torch.autograd.grad(eager.sum(), [module.radius, module.thickness])))


# ------------------------------------------------------------------------------- both lane types, float64
def _kernel_visibility_and_grads(gb: GBuffer, lanes: str, **settings):
    """The soft walk in ``lanes`` (``"simd"``, or ``"scalar"``: the CUDA thread's walk) with the module's options."""
    m = BitmaskAO(backend="kernel", **settings)
    radius, thickness = m.radius.detach().clone().requires_grad_(), m.thickness.detach().clone().requires_grad_()
    vis = bitmask_soft(gb, gb.view_normals(m.normals_method), slices=m.slices, steps=m.steps, radius=radius,
                       thickness=thickness, tau=m.tau, weighting=m.weighting, straight_through=m.mode != "soft",
                       step_power=m.step_power, min_step_px=m.min_step_px, jitter=m.jitter, seed=m.seed, noise=m.noise,
                       stagger=m.stagger, fetch=m.fetch, border=m.border, rounding=m.rounding,
                       sector_epsilon=m.sector_epsilon, azimuth=m.azimuth, variant=m.variant, lanes=lanes)
    loss = (vis * _loss_weights(vis)).sum()
    return vis.detach(), torch.autograd.grad(loss, [radius, thickness])


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 1, 2, 4, 5, 7, 8])
def test_both_lane_types_equal_the_float64_tensor_walk(built, lanes, setting):
    """Values within 1e-5 and radius / thickness gradients within 1e-4 relative of the float64 tensor walk
    (its autograd), in SIMD lanes and in the scalar lanes that the CUDA kernel compiles. (Setting 3, without
    jitter, puts steps on texel boundaries, where float32 and float64 floor differently: there the float32
    tensor walk itself is 0.33 from the float64 one on 62 pixels; the float32 test above covers it.)"""
    assert_agrees_with_the_float64_walk(FRAMES["rough"](), SETTINGS[setting], lanes)


def assert_agrees_with_the_float64_walk(gb: GBuffer, settings: dict, lanes: str) -> dict:
    """The kernel's values and radius / thickness gradients in ``lanes`` against the float64 tensor walk's (the
    tolerances of the test above); the largest errors measured (value, relative radius and thickness gradients)."""
    module = BitmaskAO(backend="torch", **settings).double()
    g64 = gb.to(dtype=torch.float64)
    reference = module(g64).visibility
    loss = (reference * _loss_weights(reference)).sum()
    ref_radius, ref_thickness = (torch.zeros((), dtype=torch.float64) if g is None else g for g in
                                 torch.autograd.grad(loss, [module.radius, module.thickness], allow_unused=True))
    out, (radius, thickness) = _kernel_visibility_and_grads(gb, lanes, **settings)
    assert reference.min() < 1 and ref_thickness != 0
    if settings["mode"] == "straight_through" and settings.get("weighting") != "cosine":
        # hard coverage: a sector edge within float32 rounding of an angle flips in one of the two walks
        assert_values_agree(out.double(), reference.detach(), gb.valid, bound=1 / (32 * settings["slices"]) + 1e-6)
    else:
        assert (out.double() - reference.detach()).abs().max() <= 1e-5
    for got, want in ((radius, ref_radius), (thickness, ref_thickness)):
        assert abs(float(got) - float(want)) <= 1e-4 * abs(float(want)) + 1e-7, (float(got), float(want))
    if settings.get("fetch") != "nearest":
        assert ref_radius != 0
    return {"value": float((out.double() - reference.detach()).abs().max()),
            **{name: abs(float(got) - float(want)) / max(abs(float(want)), 1e-30)
               for name, got, want in (("radius", radius, ref_radius), ("thickness", thickness, ref_thickness))}}
