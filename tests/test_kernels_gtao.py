"""The horizon kernels (GTAO's three variants, HBAO: the one walk with horizon.h's accumulators, SIMD and
scalar lanes) against the tensor-op walk, by the tolerance of tests/kernel_agreement.py."""
import warnings

import pytest
import torch

import torch_ao
from torch_ao.camera import PinholeCamera
from torch_ao.examples import example_gbuffer, floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import KernelUnavailable, gtao_covers, hbao_covers
from torch_ao.methods.gtao import GTAO
from torch_ao.methods.hbao import HBAO

from kernel_calls import count_kernel_calls
from kernel_agreement import ATOL, assert_values_agree

# the frames of the hard bitmask kernel's tests, and its build fixture
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401,E402

GTAO_SETTINGS = [
    dict(slices=4, steps=4),
    dict(slices=3, steps=6, radius=0.6, falloff_range=0.5, bent_normals=True),
    dict(slices=2, steps=5, jitter=False, step_power=2.0, min_step_px=2.0, normalize="none", final_power=1.7),
    dict(slices=3, steps=3, fetch="nearest", border="clamp", seed=3, multibounce=True, albedo=0.3, bent_normals=True),
    dict(slices=2, steps=4, azimuth="screen", search_scale=1.5, max_radius_px=8.0, step_power=1.5),
    dict(variant="hdrp", slices=3, steps=4, bent_normals=True),
    dict(variant="hdrp", slices=2, steps=3, projected_normal_weight=False, max_radius_px=6.0),
    dict(variant="ue4", slices=2, steps=4, thickness_heuristic=0.6, final_power=0.8),
    dict(slices=3, steps=4, noise="hilbert_r2", stagger=True, seed=1, bent_normals=True),
    dict(variant="hdrp", slices=2, steps=3, noise="hilbert_r2", stagger=True),
    dict(slices=4, steps=5, fetch="edge_aware", bent_normals=True),
    dict(variant="hdrp", slices=3, steps=4, fetch="edge_aware", border="clamp"),
    dict(variant="ue4", slices=2, steps=4, fetch="edge_aware"),
    # slices drawn by the projected normal's density, each weighted by its azimuth's estimator weight
    dict(slices=4, steps=4, slice_sampling="projected_normal", bent_normals=True),
    dict(variant="hdrp", azimuth="view", slices=3, steps=4, slice_sampling="projected_normal", fetch="nearest",
         border="clamp"),
    dict(variant="ue4", azimuth="view", slices=3, steps=4, slice_sampling="projected_normal", noise="hilbert_r2"),
]
HBAO_SETTINGS = [
    dict(slices=4, steps=4),
    dict(slices=3, steps=5, falloff="quadratic", accumulate="max", radius=0.7),
    dict(slices=5, steps=3, elevation="view", jitter=False),
    dict(slices=4, steps=4, fetch="nearest", border="clamp", azimuth="view", angle_bias=0.3, step_power=2.0, seed=2),
    dict(slices=3, steps=3, noise="hilbert_r2", stagger=True),
    dict(slices=4, steps=4, fetch="edge_aware", accumulate="max"),
]


def _both(make, gb):
    with torch.no_grad():
        return make(backend="torch")(gb), make(backend="kernel")(gb)


def _assert_agrees(reference: torch.Tensor, out: torch.Tensor, gb: GBuffer) -> None:
    # a flipped horizon comparison (HBAO's rise) moves one direction's share of the visibility
    assert_values_agree(out, reference, gb.valid, atol=1e-4 if out.shape[1] == 3 else ATOL, bound=0.25)


@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(GTAO_SETTINGS)))
def test_gtao_kernel_equals_the_tensor_walk(built, frame, setting):
    gb, options = FRAMES[frame](), GTAO_SETTINGS[setting]
    reference, out = _both(lambda **kw: GTAO(**options, **kw), gb)
    assert reference.visibility.min() < 0.99  # something is occluded: the comparison means something
    _assert_agrees(reference.visibility, out.visibility, gb)
    assert (out.bent_normal is None) == (not options.get("bent_normals", False))
    if out.bent_normal is not None:
        _assert_agrees(reference.bent_normal, out.bent_normal, gb)
        assert not torch.equal(out.bent_normal, gb.view_normals())  # bent somewhere


@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(HBAO_SETTINGS)))
def test_hbao_kernel_equals_the_tensor_walk(built, frame, setting):
    gb = FRAMES[frame]()
    reference, out = _both(lambda **kw: HBAO(**HBAO_SETTINGS[setting], **kw), gb)
    assert reference.visibility.min() < 0.99
    _assert_agrees(reference.visibility, out.visibility, gb)


@pytest.mark.parametrize("frame", ["example", "rough", "tiny"])
def test_scalar_lanes_the_cuda_builds_arithmetic_agree_with_simd_lanes(built, frame):
    """The CUDA kernel compiles the same walk in float lanes; on the CPU, those lanes give the SIMD
    lanes' sums for every variant."""
    from torch_ao.kernels.gtao import gtao_sums, hbao_sums

    gb = FRAMES[frame]()
    normals = gb.view_normals()
    for variant in ("exact", "hdrp", "ue4"):
        options = dict(variant=variant, slices=3, steps=4, walk_radius=1.0, radius=1.0, bent_normals=True)
        simd, scalar = (gtao_sums(gb, normals, **options, lanes=lanes) for lanes in ("simd", "scalar"))
        assert simd.shape == (gb.depth.shape[0], 5, *gb.depth.shape[-2:])
        assert_values_agree(scalar, simd, gb.valid, atol=1e-4)
    simd, scalar = (hbao_sums(gb, normals, slices=4, steps=4, radius=1.0, angle_bias=0.1, lanes=lanes)
                    for lanes in ("simd", "scalar"))
    assert_values_agree(scalar, simd, gb.valid, bound=0.5)
    with pytest.raises(ValueError, match="lanes: expected one of"):
        hbao_sums(gb, normals, slices=4, steps=4, radius=1.0, angle_bias=0.1, lanes="cuda")


def test_background_keeps_visibility_one_and_its_normal_and_images_are_independent(built):
    gb = rough_gbuffer()
    with torch.no_grad():
        out = GTAO(slices=3, steps=4, bent_normals=True, backend="kernel")(gb)
        one = GBuffer(depth=gb.depth[1:], camera=PinholeCamera(gb.camera.intrinsics[1:], gb.camera.height, gb.camera.width))
        alone = GTAO(slices=3, steps=4, bent_normals=True, backend="kernel")(one)
    background = ~gb.valid[:, 0]
    assert torch.equal(out.visibility[:, 0][background], torch.ones(int(background.sum())))
    normals = gb.view_normals().permute(0, 2, 3, 1)
    assert torch.equal(out.bent_normal.permute(0, 2, 3, 1)[background], normals[background])
    assert torch.equal(alone.visibility, out.visibility[1:]) and torch.equal(alone.bent_normal, out.bent_normal[1:])


def test_a_plane_is_unoccluded_exactly_and_bends_nothing(built):
    gb = floor_wall_gbuffer(40, 40, wall_distance=100.0)[0]  # the wall is far outside the radius
    with torch.no_grad():
        out = GTAO(slices=4, steps=6, bent_normals=True, backend="kernel")(gb)
        hbao = HBAO(slices=4, steps=6, backend="kernel")(gb)
    # normalize="exact": 1 on a plane (to float rounding: a sample on the plane can sit an ulp above it)
    assert (1 - out.visibility).abs().max() <= 1e-6
    # the cosine-weighted mean direction of an unoccluded hemisphere is its normal
    assert (out.bent_normal - gb.view_normals()).abs().max() < 1e-5
    assert torch.equal(hbao.visibility, torch.ones_like(hbao.visibility))  # the angle bias keeps a plane clear


# ------------------------------------------------------------------------------- what the kernel covers
def test_kernel_covers_names_what_it_does_not_cover():
    gb = example_gbuffer(8, 8)
    with torch.no_grad():
        for variant in ("exact", "hdrp", "ue4"):
            assert gtao_covers(GTAO(variant=variant, bent_normals=True, multibounce=True), gb) is None
        assert hbao_covers(HBAO(falloff="quadratic", elevation="view"), gb) is None
        assert gtao_covers(GTAO(slice_sampling="projected_normal"), gb) is None
        assert "float64" in gtao_covers(GTAO(), gb.to(dtype=torch.float64))
        assert "float64" in hbao_covers(HBAO(), gb.to(dtype=torch.float64))
        module = GTAO()
        module.values = dict(module.values, new_option=1)  # an option added to the module later
        assert "new_option" in gtao_covers(module, gb)
        positions = GBuffer(depth=gb.depth, camera=gb.camera, position=gb.positions())
        assert gtao_covers(GTAO(), positions) is None  # (its taps interpolated; with a gradient: the tensor path)
        assert gtao_covers(GTAO(fetch="nearest"), positions) is None  # nearest reads the texel's position
        # the edge-aware fetch interpolates depth too: not of a position buffer
        assert gtao_covers(GTAO(fetch="edge_aware"), gb) is None and hbao_covers(HBAO(fetch="edge_aware"), gb) is None
        assert gtao_covers(GTAO(fetch="edge_aware"), positions) is None
        # a reduced resolution is a smaller G-buffer to the kernel
        assert gtao_covers(GTAO(preset="high@half"), gb) is None
    # gradients: the horizon accumulators' backward (tests/test_kernels_walk_grad.py)
    assert gtao_covers(GTAO(), gb) is None  # the trainable radius and final power, autograd on
    assert gtao_covers(GTAO(variant="hdrp"), gb) is None
    assert gtao_covers(GTAO(variant="ue4"), gb) is None
    assert gtao_covers(GTAO(trainable=False), gb) is None
    assert hbao_covers(HBAO(trainable=False), GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)) is None



def test_auto_runs_the_kernel_with_and_without_gradients(built, monkeypatch):
    calls = count_kernel_calls(monkeypatch, "gtao")
    gb = rough_gbuffer()
    module = GTAO(slices=3, steps=4, bent_normals=True)
    with torch.no_grad():
        auto = module(gb)
    assert calls == [1]
    reference = GTAO(slices=3, steps=4, bent_normals=True, backend="torch")(gb)
    assert (auto.visibility - reference.visibility).abs().max() <= 1e-6
    graph = module(gb)  # autograd on, trainable radius: the kernel's backward
    assert calls == [1, 1] and graph.visibility.requires_grad
    graph.visibility.sum().backward()
    torch_radius = GTAO(slices=3, steps=4, bent_normals=True, backend="torch")
    torch_radius(gb).visibility.sum().backward()
    assert module.radius.grad.abs() > 0
    assert torch.allclose(module.radius.grad, torch_radius.radius.grad, rtol=1e-4)
    variant = GTAO(slices=3, steps=4, variant="ue4")
    variant(gb).visibility.sum().backward()  # ue4's radius too (its epsilon's term in Euler's identity)
    assert calls == [1, 1, 1] and variant.radius.grad.abs() > 0


def test_torch_backend_never_calls_the_kernels(monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    def refuse(*args):
        raise AssertionError("the kernel was called")

    for name in ("gtao", "hbao"):
        monkeypatch.setitem(dispatch.KERNELS, name, ((dispatch.KERNELS[name][0][0], refuse),))
    with torch.no_grad():
        assert GTAO(slices=2, steps=3, backend="torch")(example_gbuffer(16, 24)).visibility.min() < 1
        assert HBAO(slices=2, steps=3, backend="torch")(example_gbuffer(16, 24)).visibility.min() < 1


def test_kernel_backend_refuses_a_call_it_does_not_cover():
    gb = example_gbuffer(8, 8)
    with torch.no_grad(), pytest.raises(ValueError, match="backend.*float64"):
        HBAO(backend="kernel")(gb.to(dtype=torch.float64))


def test_a_kernel_that_cannot_be_built_falls_back_with_one_warning(monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    def unavailable(*args):
        raise KernelUnavailable("the C++ kernels could not be built (no compiler)")

    monkeypatch.setitem(dispatch.KERNELS, "gtao", ((dispatch.KERNELS["gtao"][0][0], unavailable),))
    monkeypatch.setattr(dispatch, "_warned", set())
    gb = example_gbuffer(16, 24)
    with torch.no_grad():
        expected = GTAO(slices=2, steps=3, backend="torch")(gb).visibility
        with pytest.warns(RuntimeWarning, match="no compiler.*tensor-op walk"):
            out = GTAO(slices=2, steps=3, backend="kernel")(gb).visibility
        assert torch.equal(out, expected)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert torch.equal(GTAO(slices=2, steps=3)(gb).visibility, expected)  # warned once


@pytest.mark.slow  # Inductor compiles the finish (10-30 s)
@pytest.mark.parametrize("make", [lambda: torch_ao.GTAO(slices=3, steps=4, bent_normals=True, final_power=1.5),
                                  lambda: torch_ao.HBAO(slices=3, steps=4)], ids=["gtao", "hbao"])
def test_compiled_kernel_path_equals_eager(built, make):
    gb = example_gbuffer(24, 40)
    module = make()  # backend auto, no gradient: the kernel, one graph node, and the finish compiled
    torch._dynamo.reset()
    with torch.no_grad():
        eager = module(gb)
        compiled = torch.compile(module, dynamic=False)(gb)
    for field in ("visibility", "bent_normal"):
        a, b = getattr(eager, field), getattr(compiled, field)
        assert (a is None) == (b is None)
        if a is not None:
            assert (a - b).abs().max() <= 1e-6, field
