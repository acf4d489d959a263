"""The hard bitmask kernel (the one walk, SIMD and scalar lanes) against the tensor-op walk, by the
tolerance of tests/kernel_agreement.py."""
import math
import shutil

import pytest
import torch

from torch_ao.camera import PinholeCamera
from torch_ao.examples import crease_gbuffer, example_gbuffer, floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import KernelUnavailable, bitmask_hard, cpu_kernels, kernel_covers
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import LinearThickness

from kernel_agreement import assert_masks_agree, degenerate, use_scalar_lanes

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="the kernels need a C++ compiler")


@pytest.fixture(scope="module")
def built():
    try:
        return cpu_kernels()
    except KernelUnavailable as exc:  # a compiler is there: a failed build is a failure
        pytest.fail(str(exc))


def rough_gbuffer(height=40, width=56, batch=2, seed=0) -> GBuffer:
    """Bumpy depth with background holes, two images with different focal lengths (normals from depth)."""
    g = torch.Generator().manual_seed(seed)
    v, u = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    depth = 2.0 + 0.6 * torch.sin(9 * u + 4 * v) * torch.cos(7 * v) + 0.05 * torch.rand(batch, 1, height, width, generator=g)
    depth[:, :, :5, :9] = math.inf  # background
    depth[1, 0, 20:26, 30:37] = 0.0
    cam = PinholeCamera.from_fov(torch.tensor([55.0, 70.0]), height, width, batch_size=batch)
    return GBuffer(depth=depth.to(torch.float32), camera=cam)


def kernel_of(module: BitmaskAO, gb: GBuffer, lanes: str = "simd") -> torch.Tensor:
    return bitmask_hard(gb, gb.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                        radius=module.radius.item(), thickness=module.thickness.item(), step_power=module.step_power,
                        min_step_px=module.min_step_px, jitter=module.jitter, seed=module.seed, noise=module.noise,
                        stagger=module.stagger, fetch=module.fetch,
                        border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                        variant=module.variant, lanes=lanes)


FRAMES = {
    "example": lambda: example_gbuffer(54, 96),
    "floor_wall": lambda: floor_wall_gbuffer(48, 48, pitch_degrees=-50.0)[0],
    "crease": lambda: crease_gbuffer(40, 40),
    "rough": rough_gbuffer,
    "tiny": lambda: example_gbuffer(6, 11),  # narrower than one vector of pixels
}
SETTINGS = [
    dict(slices=4, steps=4),
    dict(slices=3, steps=6, radius=0.6, thickness=0.2),
    dict(slices=2, steps=5, jitter=False, rounding="round", step_power=2.0, min_step_px=2.0),
    dict(slices=3, steps=3, fetch="nearest", border="clamp", rounding="floor", seed=3),
    dict(slices=2, steps=4, border="clamp", sector_epsilon=0.0, thickness=3.0),
    dict(slices=3, steps=4, noise="hilbert_r2", stagger=True, seed=2),
    dict(slices=2, steps=3, stagger=True, jitter=False),
    dict(slices=3, steps=4, azimuth="screen", seed=1),
]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_kernel_agrees_with_the_tensor_walk(built, frame, setting, lanes):
    gb = FRAMES[frame]()
    module = BitmaskAO(mode="hard", backend="torch", **SETTINGS[setting])
    with torch.no_grad():
        reference = module(gb).visibility
        out = kernel_of(module, gb, lanes)
    assert reference.min() < 1  # something is occluded: the comparison means something
    if frame != "rough" and degenerate(SETTINGS[setting]):
        # (each side of each slice may take its own sector: kernel_agreement.degenerate)
        assert_masks_agree(out, reference, gb.valid, module.slices, share=0.0, sectors=2 * module.slices)
    else:
        assert_masks_agree(out, reference, gb.valid, module.slices)


#: the "exact" variant's segment geometry (back point, clip, the sphere's extent) with the sector union
SEGMENT_SETTINGS = [
    dict(slices=3, steps=4, clip_to_radius=True, radius=0.6, thickness=1.5),
    dict(slices=2, steps=5, thickness_direction="depth", sample_extent="sphere", border="clamp", seed=1),
    dict(slices=3, steps=4, variant="exact", union="sectors", azimuth="screen", weighting="uniform"),
]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SEGMENT_SETTINGS)))
def test_the_exact_variants_segment_geometry_with_the_sector_union(built, frame, setting, lanes, monkeypatch):
    if lanes == "scalar":
        import torch_ao.kernels.bitmask as bitmask
        import torch_ao.kernels.launch as launch

        use_scalar_lanes(monkeypatch, bitmask), use_scalar_lanes(monkeypatch, launch)
    gb = FRAMES[frame]()
    options = SEGMENT_SETTINGS[setting]
    module = BitmaskAO(mode="hard", backend="torch", **options)
    with torch.no_grad():
        reference = module(gb).visibility
        out = BitmaskAO(mode="hard", backend="kernel", **options)(gb).visibility
        plain = BitmaskAO(mode="hard", backend="torch", **{k: v for k, v in options.items() if k in SETTINGS[0]})(gb)
    assert reference.min() < 1 and not torch.equal(reference, plain.visibility)  # (the geometry changes the masks)
    if frame != "rough" and degenerate({"sector_epsilon": module.sector_epsilon}):  # (the exact variant's 0)
        assert_masks_agree(out, reference, gb.valid, module.slices, share=0.0, sectors=2 * module.slices)
    else:
        assert_masks_agree(out, reference, gb.valid, module.slices)


def test_background_is_unoccluded_and_batch_images_are_independent(built):
    gb = rough_gbuffer()
    module = BitmaskAO(mode="hard", slices=3, steps=4)
    out = kernel_of(module, gb)
    assert torch.equal(out[~gb.valid], torch.ones_like(out[~gb.valid]))
    one = GBuffer(depth=gb.depth[1:], camera=PinholeCamera(gb.camera.intrinsics[1:], gb.camera.height, gb.camera.width))
    assert torch.equal(kernel_of(module, one), out[1:])


def test_flat_plane_is_unoccluded(built):
    gb = floor_wall_gbuffer(40, 40, wall_distance=100.0)[0]  # the wall is far outside the radius
    out = kernel_of(BitmaskAO(mode="hard", slices=4, steps=6), gb)
    assert torch.equal(out, torch.ones_like(out))


class _UnreadThickness(LinearThickness):
    """A model the kernels cannot read (a user's, not of ``ThicknessLayer``'s form)."""

    kernel_read = None


def test_kernel_covers_names_what_it_does_not_cover():
    gb = example_gbuffer(8, 8)
    assert kernel_covers(BitmaskAO(mode="hard"), gb) is None
    # (cosine weights and indirect light are covered since the kernel has them: see test_kernels_glsl.py)
    cases = {"mode": BitmaskAO(mode="soft"),
             "straight-through gradient": BitmaskAO(weighting="cosine", indirect=True, mode="straight_through"),
             "ambient": BitmaskAO(ambient=lambda d: d),
             "thickness model": BitmaskAO(thickness=_UnreadThickness()),
             "union": BitmaskAO(union="exact")}
    for word, module in cases.items():
        assert word in kernel_covers(module, gb), word
    # the "exact" variant's segment geometry runs in this kernel with the sector union (its union: the exact kernels)
    for module in (BitmaskAO(mode="hard", variant="exact", union="sectors"), BitmaskAO(mode="hard", clip_to_radius=True),
                   BitmaskAO(mode="hard", thickness_direction="depth"), BitmaskAO(mode="hard", sample_extent="sphere")):
        assert kernel_covers(module, gb) is None
    assert "union" in kernel_covers(BitmaskAO(mode="hard", variant="exact"), gb)
    # slices drawn by the projected normal's density: in the CPU kernels, with their gradients (the weights')
    assert kernel_covers(BitmaskAO(slice_sampling="projected_normal", weighting="cosine"), gb) is None
    graded = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)
    assert kernel_covers(BitmaskAO(slice_sampling="projected_normal"), graded) is None
    assert "float64" in kernel_covers(BitmaskAO(mode="hard"), gb.to(dtype=torch.float64))
    # hard masks have no gradient: covered with autograd on; straight-through only without a gradient
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera)
    assert kernel_covers(BitmaskAO(mode="hard"), graph) is None
    assert "gradient" in kernel_covers(BitmaskAO(mode="straight_through"), graph)
    with torch.no_grad():  # (its values are hard mode's, whatever the outputs)
        assert kernel_covers(BitmaskAO(mode="straight_through"), graph) is None
        assert kernel_covers(BitmaskAO(weighting="cosine", indirect=True, mode="straight_through"), graph) is None


# ------------------------------------------------------------------------------- dispatch
def test_auto_backend_runs_the_kernel_with_the_tensor_paths_numbers(built, monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    calls = []
    real = dispatch.bitmask_hard
    monkeypatch.setattr(dispatch, "bitmask_hard", lambda *a, **k: calls.append(1) or real(*a, **k))
    gb = rough_gbuffer()
    auto = BitmaskAO(slices=3, steps=4)(gb)  # autograd on, trainable parameters: hard masks have no gradient
    assert calls == [1] and auto.indirect is None and auto.bent_normal is None
    assert_masks_agree(auto.visibility, BitmaskAO(slices=3, steps=4, backend="torch")(gb).visibility, gb.valid, 3)
    BitmaskAO(slices=3, steps=4, mode="soft")(gb)  # the soft kernel's (tests/test_kernels_soft.py)
    assert calls == [1]


def test_torch_backend_never_calls_the_kernel(monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    def refuse(*args, **kwargs):
        raise AssertionError("the kernel was called")

    monkeypatch.setattr(dispatch, "bitmask_hard", refuse)
    out = BitmaskAO(slices=2, steps=3, backend="torch")(example_gbuffer(16, 24)).visibility
    assert out.shape == (1, 1, 16, 24) and out.min() < 1


def test_kernel_backend_refuses_a_call_it_does_not_cover():
    from torch_ao.methods.ssao import SSAO

    gb = example_gbuffer(8, 8)
    with pytest.raises(ValueError, match="backend.*float64"):
        SSAO(backend="kernel")(gb.to(dtype=torch.float64))
    with pytest.raises(ValueError, match="backend: expected one of"):
        BitmaskAO(backend="cuda")


def test_a_kernel_that_cannot_be_built_falls_back_with_one_warning(monkeypatch):
    import warnings

    import torch_ao.kernels.dispatch as dispatch

    def unavailable(*args, **kwargs):
        raise KernelUnavailable("the C++ kernels could not be built (no compiler)")

    monkeypatch.setattr(dispatch, "bitmask_hard", unavailable)
    monkeypatch.setattr(dispatch, "_warned", set())
    gb = example_gbuffer(16, 24)
    expected = BitmaskAO(slices=2, steps=3, backend="torch")(gb).visibility
    for backend in ("auto", "kernel"):  # never an error, whatever was asked
        with pytest.warns(RuntimeWarning, match="no compiler.*tensor-op walk"):
            out = BitmaskAO(slices=2, steps=3, backend=backend)(gb).visibility
        assert torch.equal(out, expected)
        monkeypatch.setattr(dispatch, "_warned", set())
    with pytest.warns(RuntimeWarning):
        BitmaskAO(slices=2, steps=3)(gb)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.equal(BitmaskAO(slices=2, steps=3)(gb).visibility, expected)  # warned once


def test_packed_settings_take_parameters_as_tensors():
    """A 0-d tensor among the settings (a parameter, which a CUDA call must not read back) packs to the float its
    value would, and leaves the numbers kept for later calls as they were."""
    from torch_ao.kernels.launch import packed_settings, walk_settings

    def packed(radius, thickness):
        settings = walk_settings(slices=2, steps=3, radius=radius, jitter=True, seed=0, fetch="bilinear", border="drop")
        return packed_settings(settings, [1, 0], [thickness, 0.01, 1.0], "cpu")

    ints, floats = packed(0.7, 0.1)
    for radius, thickness in ((torch.tensor(0.7), 0.1), (0.7, torch.tensor(0.1, dtype=torch.float64)),
                              (torch.tensor(0.7, requires_grad=True), torch.tensor(0.1))):
        ints_t, floats_t = packed(radius, thickness)
        assert torch.equal(ints_t, ints) and torch.equal(floats_t, floats)
    packed(torch.tensor(0.7), torch.tensor(0.1))  # (its numbers, with zeros where the tensors go, are kept)
    assert torch.equal(packed(0.0, 0.0)[1], floats.index_put((torch.tensor([0, 4]),), torch.zeros(2)))
