"""The soft / straight-through kernel of bitmask AO's ``"hdrp"`` variant (soft.h's SoftAccumulator with
``SectorAngles::hdrp``: HDRP's slice frame ``gamma = -sign(n_p . T) fast_acos(cos n)`` and its angles
``fast_acos(cos_view)``, bitmask.h's sample_angles and angle_slopes) against the float64 tensor-op walk, by the
checks and tolerances of the ``"default"`` variant's tests (imported): values within 1e-5 (a straight-through
forward: within one sector of one slice), the radius, thickness and scale gradients within 1e-4 relative
(tests/test_kernels_soft.py, tests/test_kernels_thickness_layers.py), the G-buffer's (depth, normals, the back-face
layer) within 1e-4 relative (tests/test_kernels_soft_gbuffer.py), in SIMD and scalar lanes; the straight-through
forward is the hard kernel's bit for bit; dispatch takes the kernel."""
import pytest
import torch

from kernel_calls import count_kernel_calls
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from test_kernels_soft import assert_agrees_with_the_float64_walk
from test_kernels_soft_gbuffer import assert_central_differences, assert_gbuffer_gradients_agree
from test_kernels_thickness_layers import SOFT_SETTINGS, assert_layer_agrees, assert_layer_gbuffer_gradients_agree
from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.methods.bitmask import BitmaskAO

# (the variant's defaults: screen azimuth, sector_epsilon 0.) No tau below 0.25 in soft mode: there HDRP's angles
# (fast_acos, steep near |cos| = 1) pass float32's rounding of the inputs on more than the default variant's atan2
# do. Setting 4 at tau = 0.1: the kernel is 2.7e-5 from the float64 tensor walk on one pixel of the rough frame, where
# the float32 tensor walk is the same 2.7e-5 off (4.3e-5 at its worst pixel); at tau = 0.2, 1.05e-5 (1.9e-5).
# The G-buffer's gradients leave setting 4 out: one pixel of the rough frame lies at a kink of its walk (there the
# float64 walk's own central differences of the normal are 2-25 % from its autograd) that float32 passes on the other
# side, 1.6e-4 relative in the normals' gradient (with slices=3: 3e-5, but a value 2.9e-5 off, as at tau = 0.1).
SETTINGS = [
    dict(mode="soft", slices=3, steps=4),
    dict(mode="soft", slices=3, steps=3, weighting="cosine", tau=0.5),
    dict(mode="straight_through", slices=3, steps=4, weighting="cosine"),
    dict(mode="straight_through", slices=3, steps=3, fetch="nearest", border="clamp", rounding="floor", seed=3),
    dict(mode="soft", slices=2, steps=4, border="clamp", thickness=0.9, radius=0.6, tau=0.25, weighting="cosine",
         azimuth="view"),
    dict(mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware", noise="hilbert_r2", stagger=True),
    dict(mode="straight_through", slices=3, steps=3, fetch="edge_aware", border="clamp", tau=0.2, sector_epsilon=0.01),
]
HDRP = [dict(variant="hdrp", **s) for s in SETTINGS]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(HDRP)))
def test_values_and_parameter_gradients_equal_the_float64_tensor_walk(built, lanes, setting):
    assert_agrees_with_the_float64_walk(FRAMES["rough"](), HDRP[setting], lanes)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 1, 2, 3, 5, 6])
def test_gbuffer_gradients_equal_the_float64_tensor_walk(built, lanes, setting):
    assert_gbuffer_gradients_agree(FRAMES["rough"](), HDRP[setting], lanes)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 2])
@pytest.mark.parametrize("model", ["backface", "linear"])
def test_a_layer_and_its_gradients_equal_the_float64_tensor_walk(built, model, setting, lanes):
    """The back-face layer (read as depth is: its taps move with the radius) and the linear model (the sample's
    depth): values, the radius', scale's and offset's gradients, and the G-buffer's with the back-face depth's."""
    settings = dict(variant="hdrp", **SOFT_SETTINGS[setting])
    assert_layer_agrees(model, settings, lanes)
    assert_layer_gbuffer_gradients_agree(model, settings, lanes)


@pytest.mark.parametrize("mode, weighting", [("soft", "uniform"), ("soft", "cosine"), ("straight_through", "uniform")])
def test_gradients_match_central_differences(built, mode, weighting):
    """The kernel's derivative along random directions of depth and normals against central differences of the
    float64 tensor-op forward (tests/test_kernels_soft_gbuffer.py's check), on the frame of
    tests/test_kernels_hdrp_grad.py's: no slice there has its normal within 1e-6 of V in cosine, where the tensor walk's
    safe_fast_acos (and so the kernel) gives HDRP's slice angle no slope and it has one (on the 8 x 10 floor and wall
    of the default variant's check, whose wall faces the camera, the float64 walk's own autograd is 1.86 along a
    direction whose central difference is 2.44). Straight-through: with uniform weights (its cosine weights weigh the
    hard coverage of its forward, so the soft forward's differences are not its gradient there)."""
    assert_central_differences(rough_gbuffer(20, 28, seed=6), mode, dict(variant="hdrp", weighting=weighting))


def test_straight_through_forward_is_the_hard_kernels_visibility_bit_for_bit(built):
    """The two accumulators measure a sample by one sector rule (bitmask.h's sample_angles, sample_interval)."""
    gb = rough_gbuffer()
    for settings in (dict(slices=3, steps=4, rounding="round"), dict(slices=3, steps=3, weighting="cosine")):
        with torch.no_grad():
            hard = BitmaskAO(variant="hdrp", mode="hard", backend="kernel", **settings)(gb).visibility
        straight = BitmaskAO(variant="hdrp", mode="straight_through", backend="kernel", **settings)(gb).visibility
        assert straight.requires_grad
        if settings.get("weighting") == "cosine":  # (the soft kernel's cosine weights: a few ulp of the hard one's)
            assert (straight.detach() - hard).abs().max() <= 1e-6
        else:
            assert torch.equal(straight.detach(), hard)


def test_kernel_covers_and_dispatch_takes_the_kernel(built, monkeypatch):
    gb = example_gbuffer(12, 16)
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)
    for frame in (gb, graph):
        for mode in ("soft", "straight_through"):
            for weighting in ("uniform", "cosine"):
                assert soft_module.kernel_covers(BitmaskAO(variant="hdrp", mode=mode, weighting=weighting), frame) is None
    assert "variant" in soft_module.kernel_covers(BitmaskAO(variant="ssilvb_glsl", mode="soft"), gb)
    calls = count_kernel_calls(monkeypatch, "bitmask")
    module = BitmaskAO(variant="hdrp", mode="soft", slices=2, steps=3, weighting="cosine", fetch="edge_aware")
    vis = module(graph).visibility
    g_depth, g_radius = torch.autograd.grad(vis.sum(), [graph.depth, module.radius])
    assert calls == [1] and g_depth.abs().sum() > 0 and g_radius != 0
