"""Samples on a decision's boundary: the kernels decide as the tensor walk, because the rule puts the boundary where
rounding does not reach, or both compute its inputs alike.

- The nearest fetch on a tie between two texels. Without jitter, slices at round screen angles with whole-pixel
  steps put samples exactly half-way between texels (a step of 1 pixel along 60 degrees moves 0.5 pixel across), and
  an ulp in the step's direction picked the texel: `GTAO(variant="ue4", jitter=False)` differed from the tensor
  walk by up to 0.043 on 1.2 % of the pixels. A coordinate within 1/512 texel above a tie reads the lower texel.
- The ``"ssilvb_glsl"`` back horizon straight behind an occluder (a back-face layer with no exit, capped at 1e6):
  its cosine rounds to -1 or just below. With ``glsl_numerics="ieee"`` a cosine beyond +-1 is taken at +-1, so
  the kernel's dot product and torch's need not round alike (they differed by half a slice's visibility).
- A sample off the slice, in the plane of the view vector and the slice's normal (the border's clamp puts off-screen
  steps into the pixel's own column, which that plane holds when the slice's tangent is V x the camera's y): its
  tangent coordinate is 0 but for rounding, whose sign made its back angle +pi or -pi and so decided which half of
  the hemisphere it occludes (visibility 0.094 against 0.94). Within ``MIN_OFFSET`` of the depth it is taken as +0.
- The ``"ssilvb_glsl"`` sample on the pixel's own texel with ``thickness_growth``: its thickness is the ungrown
  one (``|sample - pixel|`` is 0), not one grown with the stand-in direction's length, whose rounding decided
  Mesa's back cosine (visibility 1.5 apart).
"""
import math

import pytest
import torch

import torch_ao
from torch_ao.camera import PinholeCamera
from torch_ao.examples import floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.thickness import BackfaceThickness
from torch_ao.walk.fetch import NEAREST_TIE, Footprint
from torch_ao.walk.sample import MIN_OFFSET, slice_coordinates
from kernel_agreement import use_scalar_lanes
from test_kernels import built, rough_gbuffer  # noqa: F401  (the fixture: the C++ kernels built)


def rough(height: int, width: int, batch: int, seed: int) -> GBuffer:
    """tests/test_kernels.py's bumpy depth, background in the top left, one focal length."""
    v, u = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    noise = torch.rand(batch, 1, height, width, generator=torch.Generator().manual_seed(seed))
    depth = 2.0 + 0.6 * torch.sin(9 * u + 4 * v) * torch.cos(7 * v) + 0.05 * noise
    depth[:, :, :5, :9] = math.inf
    return GBuffer(depth=depth, camera=PinholeCamera.from_fov(55.0, height, width, batch_size=batch))


def visibility(module_for, gb: GBuffer, backend: str) -> torch.Tensor:
    with torch.no_grad():
        return module_for(backend)(gb).visibility


def assert_backends_agree(module_for, gb: GBuffer, lanes: str, monkeypatch, atol: float = 0.0):
    if lanes == "scalar":
        from torch_ao.kernels import bitmask, launch

        for module in (bitmask, launch):
            use_scalar_lanes(monkeypatch, module)
    reference, kernel = visibility(module_for, gb, "torch"), visibility(module_for, gb, "kernel")
    differ = (kernel - reference).abs() > atol
    assert not bool(differ.any()), (int(differ.sum()), float((kernel - reference).abs().max()))
    return reference


def test_a_nearest_fetch_on_a_tie_reads_the_lower_texel():
    frame = type("F", (), {"shape": (1, 5, 8)})()
    batch = torch.zeros(3, dtype=torch.int64)
    su = torch.tensor([2.5, 2.5 + NEAREST_TIE / 2, 2.5 + 2 * NEAREST_TIE], dtype=torch.float32)
    footprint, _ = Footprint.at(frame, batch, su, torch.tensor([1.5, 1.0, 0.5 - 1e-6]), "nearest")
    assert footprint.index.tolist() == [1 * 8 + 2, 1 * 8 + 2, 0 * 8 + 3]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
def test_ue4_gtao_without_jitter_reads_the_tensor_walks_texels(built, lanes, monkeypatch):
    gb = rough(32, 35, 2, seed=80)
    reference = assert_backends_agree(
        lambda backend: torch_ao.GTAO(variant="ue4", slices=6, steps=10, jitter=False, backend=backend),
        gb, lanes, monkeypatch, atol=1e-5)
    assert reference[gb.valid].min() < 0.8  # (something is occluded)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
def test_glsl_back_horizon_of_an_occluder_with_no_exit(built, lanes, monkeypatch):
    gb = rough(24, 32, 1, seed=72)
    no_exit = torch.rand(1, 1, 24, 32, generator=torch.Generator().manual_seed(1)) < 0.2
    gb = GBuffer(depth=gb.depth, camera=gb.camera, backface_depth=torch.where(no_exit, math.inf, gb.depth + 0.3))
    reference = assert_backends_agree(
        lambda backend: torch_ao.BitmaskAO(variant="ssilvb_glsl", mode="hard", slices=2, steps=1, backend=backend,
                                           thickness=BackfaceThickness(0.68, 0.0)), gb, lanes, monkeypatch)
    assert reference[gb.valid].min() < 1.0


@pytest.mark.parametrize("numerics", ["mesa", "ieee"])
@pytest.mark.parametrize("lanes", ["simd", "scalar"])
def test_glsl_own_texel_with_thickness_growth(built, numerics, lanes, monkeypatch):
    fw = floor_wall_gbuffer(37, 33, wall_distance=1.0, pitch_degrees=-50.0, light_direction=(0.3, 0.8, 0.5))[0]
    noise = torch.rand(fw.depth.shape, generator=torch.Generator().manual_seed(21))
    gb = GBuffer(depth=fw.depth * (1 + 1e-3 * noise), camera=fw.camera, light=fw.light)
    reference = assert_backends_agree(
        lambda backend: torch_ao.SSILVB(variant="ssilvb_glsl", mode="hard", slices=2, steps=8, radius=1.195,
                                        step_power=0.5, rounding="round", thickness=0.5, thickness_growth=1.17,
                                        glsl_numerics=numerics, backend=backend), gb, lanes, monkeypatch)
    assert 0.0 < float(reference[gb.valid].mean()) < 1.5


def test_glsl_ieee_back_horizon_is_continuous_in_the_thickness():
    """Straight behind (thickness huge) the back cosine is -1 up to rounding: ``"ieee"`` occludes the half circle as
    it does for every large finite thickness, never nothing (as a cosine rounded below -1 would under Mesa's NaN)."""
    gb = rough(24, 32, 1, seed=72)
    values = []
    for thickness in (1e3, 1e5, 1e7):
        with torch.no_grad():
            values.append(torch_ao.BitmaskAO(variant="ssilvb_glsl", mode="hard", slices=2, steps=3,
                                             thickness=thickness)(gb).visibility)
    assert torch.equal(values[0], values[1]) and torch.equal(values[1], values[2])
    assert values[0][gb.valid].min() < 1.0


def test_a_tangent_coordinate_within_the_offset_is_positive_zero_without_gradient():
    depth = torch.full((4,), 2.0, dtype=torch.float64)
    view = torch.tensor([[0.0, 0.0, 1.0]] * 4, dtype=torch.float64)
    tangent = torch.tensor([[1.0, 0.0, 0.0]] * 4, dtype=torch.float64)
    across = torch.tensor([-1e-9, 1e-9, -3 * MIN_OFFSET, 3 * MIN_OFFSET], dtype=torch.float64)
    delta = torch.stack((across, torch.zeros(4, dtype=torch.float64), torch.full((4,), -0.5, dtype=torch.float64)), -1)
    delta.requires_grad_(True)
    along_view, snapped = slice_coordinates(delta, view, tangent, 1, depth)
    assert along_view.tolist() == [-0.5] * 4
    assert snapped.tolist() == [0.0, 0.0, -3 * MIN_OFFSET, 3 * MIN_OFFSET]
    assert not torch.signbit(snapped[:2]).any()  # +0: atan2(+0, -x) = +pi, on the sample's own side
    snapped.sum().backward()
    assert delta.grad[:, 0].tolist() == [0.0, 0.0, 1.0, 1.0]


OFF_SLICE = dict(slices=1, steps=2, radius=0.529, jitter=False, fetch="nearest", border="clamp", thickness=0.38)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
def test_a_sample_clamped_into_the_pixels_column_occludes_its_own_side(built, lanes, monkeypatch):
    gb = rough_gbuffer(35, 52, batch=2, seed=87)
    reference = assert_backends_agree(
        lambda backend: torch_ao.BitmaskAO(mode="hard", backend=backend, **OFF_SLICE), gb, lanes, monkeypatch)
    # the pixel where the sign of the rounding decided (a fraction of the half hemisphere on one side, all of it on
    # the other): float64 takes the same side as float32
    with torch.no_grad():
        wide = torch_ao.BitmaskAO(mode="hard", backend="torch", **OFF_SLICE).double()(gb.to(torch.float64)).visibility
    assert torch.equal(wide.float(), reference)
    assert float(reference[0, 0, 11, 51]) == pytest.approx(0.09375)  # (the +0 side: 3 sectors of 32 visible)
