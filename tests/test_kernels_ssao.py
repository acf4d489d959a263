"""The SSAO family's kernels (UE4SSAO's wedge pairs, PSSAO's pixel offsets: the one walk with ssao.h's
accumulators, SIMD and scalar lanes) against the tensor-op walk run in float64, by tolerance.

The kernel computes in float32 and the reference in float64: the visibilities agree within ATOL on all but
SHARE of the valid pixels, and within BOUND everywhere. What differs is one decision taken at rounding: a
step within rounding of a texel's edge (the nearest fetch picks its neighbour), or, with border="clamp" and
the bilinear fetch, a corner pixel whose clamped samples land on its own texel: its bilinear unprojection
is exact in float64 (a zero offset: no occluder) and a few ulps off in float32 (a valid sample), as the
tensor walk itself run in float32 gives (the kernel agrees with that to 3e-6 there)."""
import dataclasses

import pytest
import torch

from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import pssao_covers, ue4_ssao_covers
from torch_ao.kernels.ssao import pssao_forward, ue4_ssao_forward
from torch_ao.methods.pssao import PSSAO
from torch_ao.methods.ue4_ssao import UE4SSAO

from kernel_calls import count_kernel_calls
from kernel_agreement import assert_values_agree
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401,E402

#: float32 against float64: UE4's x = (1 - angle) / (weight + 0.001) amplifies rounding up to 1000 times
ATOL = 1e-4
#: one pair or one sample read from the neighbouring texel moves one direction's share
BOUND = 0.35
#: the share of valid pixels within ATOL (the four corners of the 40 x 40 crease frame are 0.25 %)
SHARE = 0.995

UE4_SETTINGS = [
    dict(),  # UE4's 3 offsets, nearest, clamp, jitter
    dict(sample_set="ue4_6", steps=2, seed=3, final_power=2.0, intensity=0.5),
    dict(sample_set="uniform", slices=4, steps=3, fetch="bilinear", border="drop"),
    dict(sample_set="uniform", slices=5, steps=2, fetch="edge_aware", accurate_angle=True, radius=0.6),
    dict(flat_softness=0.02, jitter=False, fade_distance=0.2, flat_surface_bias=0.05),
    dict(sample_set="ue4_6", steps=3, fetch="bilinear", border="clamp", accurate_angle=True, flat_softness=0.01),
]
PSSAO_SETTINGS = [
    dict(),  # the gist's 8 x 8, nearest, drop
    dict(normalize="directions", slices=6, steps=5, fetch="bilinear"),
    dict(slices=5, steps=4, border="clamp", distance_bias=0.5),
    dict(slices=12, steps=6, fetch="edge_aware", normalize="directions"),
]


def _reference(make, gb):
    """The tensor walk's visibility on a float64 copy of the G-buffer."""
    with torch.no_grad():
        return make(backend="torch")(gb.to(dtype=torch.float64)).visibility


#: (method, its kernel's covers and forward, settings) of each kernel
KERNEL_CASES = {"ue4_ssao": (UE4SSAO, ue4_ssao_covers, ue4_ssao_forward, UE4_SETTINGS),
                "pssao": (PSSAO, pssao_covers, pssao_forward, PSSAO_SETTINGS)}


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("method, setting", [(m, k) for m, case in KERNEL_CASES.items() for k in range(len(case[3]))])
def test_kernel_equals_the_tensor_walk(built, method, frame, setting, lanes):
    cls, covers, forward, settings = KERNEL_CASES[method]
    gb, options = FRAMES[frame](), settings[setting]
    reference = _reference(lambda **kw: cls(**options, **kw), gb)
    module = cls(**options, backend="kernel")
    with torch.no_grad():
        assert covers(module, gb) is None
        out = forward(module, gb, lanes=lanes)["visibility"]
    assert reference.min() < 0.99  # something is occluded: the comparison means something
    assert_values_agree(out.double(), reference, gb.valid, atol=ATOL, bound=BOUND, share=SHARE)


def test_the_module_runs_the_kernel_and_its_images_are_independent(built):
    gb = rough_gbuffer()
    with torch.no_grad():
        for make in (lambda: UE4SSAO(backend="kernel"), lambda: PSSAO(backend="kernel")):
            out = make()(gb).visibility
            one = GBuffer(depth=gb.depth[1:], camera=type(gb.camera)(gb.camera.intrinsics[1:], gb.camera.height,
                                                                     gb.camera.width))
            assert torch.equal(make()(one).visibility, out[1:])
            assert torch.equal(out[~gb.valid], torch.ones(int((~gb.valid).sum())))  # background: unoccluded


# ------------------------------------------------------------------------------- what the kernels cover
def test_kernel_covers_names_what_it_does_not_cover():
    gb = example_gbuffer(8, 8)
    with torch.no_grad():
        assert ue4_ssao_covers(UE4SSAO(), gb) is None
        assert pssao_covers(PSSAO(), gb) is None
        assert "float64" in ue4_ssao_covers(UE4SSAO(), gb.to(dtype=torch.float64))
        assert "float64" in pssao_covers(PSSAO(), gb.to(dtype=torch.float64))
        module = PSSAO()
        module.values = dict(module.values, new_option=1)  # an option added to the module later
        assert "new_option" in pssao_covers(module, gb)
        positions = GBuffer(depth=gb.depth, camera=gb.camera, position=gb.positions())
        assert ue4_ssao_covers(UE4SSAO(fetch="bilinear"), positions) is None  # (no gradient: its taps interpolated)
        assert ue4_ssao_covers(UE4SSAO(), positions) is None  # nearest reads the texel's position
    # autograd on: the kernel's backward gives the G-buffer's, the fade distance's and the distance bias'
    # gradients and the intrinsics', not UE4's radius' (a buffer)
    assert ue4_ssao_covers(UE4SSAO(), gb) is None and pssao_covers(PSSAO(), gb) is None
    depth = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)
    assert pssao_covers(PSSAO(trainable=False), depth) is None
    module = UE4SSAO(fetch="bilinear", flat_softness=0.05)  # (its radius and flat-surface bias: parameters)
    assert module.radius.requires_grad and ue4_ssao_covers(module, gb) is None
    camera = dataclasses.replace(gb.camera, intrinsics=gb.camera.intrinsics.clone().requires_grad_(True))
    assert pssao_covers(PSSAO(), GBuffer(depth=gb.depth, camera=camera)) is None



def test_auto_runs_the_kernel_without_gradients_and_the_tensor_walk_with(built, monkeypatch):
    calls = count_kernel_calls(monkeypatch, "ue4_ssao")
    gb = rough_gbuffer()
    module = UE4SSAO(steps=2)
    with torch.no_grad():
        auto = module(gb).visibility
        reference = UE4SSAO(steps=2, backend="torch")(gb).visibility
    assert calls == [1]
    assert_values_agree(auto, reference, gb.valid, atol=ATOL, bound=BOUND)
    # autograd on: the kernel with its backward (the fade distance's gradient from the walk; the final power's
    # and intensity's, applied after the kernel's sums, by autograd), as the tensor path's
    tensor = UE4SSAO(steps=2, final_power=1.5, intensity=0.7, backend="torch")
    module = UE4SSAO(steps=2, final_power=1.5, intensity=0.7)
    for m in (module, tensor):
        graph = m(gb).visibility
        assert graph.requires_grad
        graph.sum().backward()
    assert calls == [1, 1]
    for name in ("fade_distance", "final_power", "intensity"):
        mine, theirs = getattr(module, name).grad, getattr(tensor, name).grad
        assert theirs.abs() > 0 and torch.allclose(mine, theirs, rtol=1e-3), name


def test_kernel_backend_refuses_a_call_it_does_not_cover_and_auto_falls_back(monkeypatch):
    gb = example_gbuffer(12, 16)
    with pytest.raises(ValueError, match="backend.*float64"):
        UE4SSAO(backend="kernel")(gb.to(dtype=torch.float64))
    with torch.no_grad(), pytest.raises(ValueError, match="backend.*float64"):
        PSSAO(backend="kernel")(gb.to(dtype=torch.float64))
    calls = count_kernel_calls(monkeypatch, "pssao")
    with torch.no_grad():
        out = PSSAO()(gb.to(dtype=torch.float64)).visibility  # auto: the tensor path
        assert calls == [] and out.dtype == torch.float64
        assert torch.equal(out, PSSAO(backend="torch")(gb.to(dtype=torch.float64)).visibility)
