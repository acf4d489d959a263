"""SSAO's kernel (the walk's hemisphere placement with ssao.h's HemisphereAccumulator, SIMD and scalar lanes)
against the tensor path (methods/ssao.py, the specification) run in float64: values, gradients (depth, given
normals, intrinsics, radius, bias), central finite differences, and which calls the dispatch sends to it.

The kernel computes in float32. Its visibility agrees with the float64 tensor path within ATOL on >= 99.9 % of
the valid pixels; what may differ beyond is one decision taken at rounding (a kernel point projected within
rounding of a texel's edge, which the nearest fetch reads from the neighbour, or a depth comparison within
rounding of the bias), which moves one sample's share 1/K: BOUND. With softness > 0 the logistic's slope
1 / (4 softness) amplifies the float32 rounding of the depths (about 1e-7 of them); at softness 0.1 that stays
within ATOL. Measured: 4 of 162 024 comparisons beyond ATOL, two pixels of the rough frame with the edge-aware
fetch (SIMD and scalar lanes), up to 0.024: the edge-aware tap choice decided at rounding, where the kernel gives
the float32 tensor path's value."""
import dataclasses

import pytest
import torch

from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import ssao_covers
from torch_ao.kernels.ssao import ssao_forward
from torch_ao.kernels.walk_grad import MAX_CUDA_STEPS
from torch_ao.methods.ssao import SSAO

from kernel_agreement import (assert_depth_gradient_matches_central_differences, assert_values_agree, relative_error,
                              upstream_weights)
from kernel_calls import count_kernel_calls
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401

ATOL = 1e-5
SHARE = 0.999
#: one kernel point of the default 18 decided the other way at rounding
BOUND = 1.0 / 18 + 1e-6

#: every fetch, both borders, jitter on and off, the hard step and the logistic
SETTINGS = [
    dict(),  # 18 points, bilinear, drop, jitter
    dict(fetch="nearest", border="clamp", seed=3),
    dict(fetch="edge_aware", jitter=False, radius=0.3),
    dict(fetch="nearest", border="drop", samples=12, bias=0.05),
    dict(fetch="bilinear", border="clamp", samples=9, softness=0.1, radius=0.5),
    dict(fetch="edge_aware", border="drop", softness=0.1, jitter=False),
]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_kernel_equals_the_tensor_path(built, setting, frame, lanes):
    gb, options = FRAMES[frame](), SETTINGS[setting]
    with torch.no_grad():
        reference = SSAO(backend="torch", **options)(gb.to(dtype=torch.float64)).visibility
        module = SSAO(backend="kernel", **options)
        assert ssao_covers(module, gb) is None
        out = ssao_forward(module, gb, lanes=lanes)["visibility"]
    assert reference.min() < 0.95  # something is occluded: the comparison means something
    assert torch.equal(out[~gb.valid], torch.ones(int((~gb.valid).sum())))  # background: unoccluded
    assert_values_agree(out.double(), reference, gb.valid, atol=ATOL, bound=BOUND, share=SHARE)


# ------------------------------------------------------------------------------------------------ gradients
#: (options, frame): the logistic on the rough frame (no ties); the hard step, where only the range check carries
#: gradients, on the example frame: the check is active (< 1) only where a surface is more than the radius in
#: front of the pixel, at its objects' silhouettes (the rough frame's smooth surface has none); every fetch and
#: border; the most kernel points a CUDA thread's backward replays
GRADIENT_CASES = {
    "soft-bilinear": (dict(fetch="bilinear", border="drop", softness=0.05), "rough"),
    "soft-nearest-clamp": (dict(softness=0.1, bias=0.05, samples=9), "rough"),
    "soft-edge-aware-still": (dict(fetch="edge_aware", jitter=False, softness=0.05, radius=0.5), "rough"),
    "hard-bilinear-clamp": (dict(fetch="bilinear", border="clamp", radius=0.2, jitter=False), "example"),
    "hard-nearest": (dict(radius=0.1), "example"),
    "hard-edge-aware": (dict(fetch="edge_aware", border="drop", radius=0.3), "example"),
    "soft-most": (dict(fetch="bilinear", samples=MAX_CUDA_STEPS, softness=0.05, radius=0.3), "rough"),
}
GRADIENT_FRAMES = {"rough": lambda: rough_gbuffer(20, 28), "example": lambda: example_gbuffer(24, 40)}


def _gradients(gb0: GBuffer, options: dict, backend: str, dtype: torch.dtype, lanes: str = "simd"):
    """The visibility and d(weighted visibility) / d(depth, given normals, intrinsics, every parameter)."""
    depth = gb0.depth.detach().to(dtype).clone().requires_grad_(True)
    normals = gb0.view_normals().detach().to(dtype).clone().requires_grad_(True)
    camera = dataclasses.replace(gb0.camera, intrinsics=gb0.camera.intrinsics.to(dtype).clone().requires_grad_(True))
    gb = GBuffer(depth=depth, normals=normals, camera=camera)
    module = SSAO(backend=backend, **options)
    parameters = dict(module.named_parameters())
    if backend == "kernel":
        assert ssao_covers(module, gb) is None
        out = ssao_forward(module, gb, lanes=lanes)["visibility"]
    else:
        out = module(gb).visibility
    (out * upstream_weights(out)).sum().backward()
    grads = {"depth": depth.grad, "normals": normals.grad, "intrinsics": camera.intrinsics.grad}
    grads |= {name: p.grad for name, p in parameters.items()}
    return out.detach().double(), {name: g.double() for name, g in grads.items()}


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("case", sorted(GRADIENT_CASES))
def test_kernel_gradients_equal_the_tensor_path(built, case, lanes):
    """Against the tensor path's autograd in float64, except on the planar example frame, whose samples of the
    pixel's own plane are tied with the bias' comparison: there in float32, which rounds as the kernel does.
    The radius' gradient is Euler's sum of the G-buffer's, the bias' and the softness' terms (walk_grad.py),
    which cancel to it: it carries their float32 rounding, up to 2e-4 of itself. (The bilinear fetch with the
    clamped border on the rough frame is left to the forward test: with 32 points one pixel of its bottom row
    reads a point clamped onto its own texel, a zero offset in float64 and a valid sample in float32, where the
    kernel gives the float32 tensor path's value, 0.012 off.)"""
    options, frame = GRADIENT_CASES[case]
    gb = GRADIENT_FRAMES[frame]()
    reference_out, reference = _gradients(gb, options, "torch", torch.float64 if frame == "rough" else torch.float32)
    out, grads = _gradients(gb, options, "kernel", torch.float32, lanes)
    assert torch.allclose(out, reference_out, atol=2e-5)
    assert set(grads) == set(reference) == {"depth", "normals", "intrinsics", "radius"} | (
        {"bias"} if options.get("softness") else set())
    for name in reference:
        assert reference[name].abs().max() > 1e-3, name  # every gradient is there: the comparison means something
        assert relative_error(grads[name], reference[name]) < (2e-4 if name == "radius" else 1e-4), name


@pytest.mark.slow
@pytest.mark.parametrize("case", ["soft-bilinear", "soft-nearest-clamp", "soft-edge-aware-still"])
def test_kernel_gradient_matches_finite_differences(built, case):
    """The kernel's float32 depth gradient against central differences (1e-6) of the tensor path's float64
    forward on a small rough frame (no ties), normals given, every 5th pixel."""
    options, _ = GRADIENT_CASES[case]
    gb = rough_gbuffer(10, 12)
    assert_depth_gradient_matches_central_differences(
        lambda backend: SSAO(backend=backend, trainable=False, **options), gb, gb.view_normals().detach(), every=5)


# ------------------------------------------------------------------------------------------------ dispatch
def test_auto_runs_the_kernel_with_and_without_gradients(built, monkeypatch):
    calls = count_kernel_calls(monkeypatch, "ssao")
    gb = rough_gbuffer(20, 28)
    with torch.no_grad():
        auto = SSAO()(gb).visibility
        reference = SSAO(backend="torch")(gb).visibility
    assert calls == [1]
    assert_values_agree(auto, reference, gb.valid, atol=ATOL, bound=BOUND)
    module, tensor = SSAO(softness=0.05), SSAO(softness=0.05, backend="torch")
    for m in (module, tensor):
        out = m(gb).visibility
        assert out.requires_grad
        out.sum().backward()
    assert calls == [1, 1]
    for name in ("radius", "bias"):
        mine, theirs = getattr(module, name).grad, getattr(tensor, name).grad
        assert theirs.abs() > 0 and torch.allclose(mine, theirs, rtol=1e-3), name


def test_kernel_backend_runs_the_kernel_and_images_are_independent(built, monkeypatch):
    calls = count_kernel_calls(monkeypatch, "ssao")
    gb = rough_gbuffer()
    with torch.no_grad():
        out = SSAO(backend="kernel")(gb).visibility
        one = GBuffer(depth=gb.depth[1:], camera=type(gb.camera)(gb.camera.intrinsics[1:], gb.camera.height,
                                                                 gb.camera.width))
        assert torch.equal(SSAO(backend="kernel")(one).visibility, out[1:])
    assert calls == [1, 1]


def test_covers_names_what_it_does_not_cover_and_auto_falls_back(built, monkeypatch):
    gb = example_gbuffer(12, 16)
    with torch.no_grad():
        assert ssao_covers(SSAO(), gb) is None
        assert "float64" in ssao_covers(SSAO(), gb.to(dtype=torch.float64))
        module = SSAO()
        module.values = dict(module.values, new_option=1)  # an option added to the module later
        assert "new_option" in ssao_covers(module, gb)
        positions = GBuffer(depth=gb.depth, camera=gb.camera, position=gb.positions())
        assert ssao_covers(SSAO(fetch="bilinear"), positions) is None  # (no gradient: its taps interpolated)
        assert ssao_covers(SSAO(fetch="nearest"), positions) is None  # nearest reads the texel's position
    with pytest.raises(ValueError, match="backend.*float64"):
        SSAO(backend="kernel")(gb.to(dtype=torch.float64))
    calls = count_kernel_calls(monkeypatch, "ssao")
    with torch.no_grad():
        out = SSAO()(gb.to(dtype=torch.float64)).visibility  # auto: the tensor path
    assert calls == [] and out.dtype == torch.float64
    assert torch.equal(out, SSAO(backend="torch")(gb.to(dtype=torch.float64)).visibility)
