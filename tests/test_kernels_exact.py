"""The exact union's kernel (``BitmaskAO(variant="exact")``: the one walk with bitmask.h's ExactAccumulator,
the edge-aware fetch, the sphere's extent, the back-face thickness layer) against the tensor-op walk, in
SIMD and scalar lanes, by the tolerance of tests/kernel_agreement.py."""
import pytest
import torch

from kernel_agreement import assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401  (built: the fixture)
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import exact_covers, kernel_forward
from torch_ao.kernels.bitmask import exact_hard, module_thickness, thickness_options
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import BackfaceThickness


def with_backface(gb: GBuffer, depth: float = 0.3) -> GBuffer:
    """``gb`` with a back-face layer ``depth`` behind every surface, thicker where the frame is further."""
    return GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, backface_depth=gb.depth * (1 + depth))


SETTINGS = [
    dict(slices=3, steps=4),  # the variant's defaults: cosine, along the ray, clipped, sphere extent, edge-aware
    dict(slices=2, steps=6, fetch="bilinear", radius=0.6, thickness=0.2, jitter=False),
    dict(slices=3, steps=3, weighting="uniform", thickness_direction="view", clip_to_radius=False,
         sample_extent="radius", fetch="nearest", border="clamp", seed=2),
    dict(slices=2, steps=5, thickness=BackfaceThickness(scale=0.8, thickness=0.05)),
    dict(slices=4, steps=3, thickness=BackfaceThickness(), step_power=2.0, min_step_px=1.0, sector_epsilon=0.01),
    dict(slices=3, steps=4, noise="hilbert_r2", stagger=True, seed=3),
    dict(slices=3, steps=4, azimuth="screen", thickness=BackfaceThickness()),
]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_exact_kernel_agrees_with_the_tensor_walk(built, frame, setting, lanes):
    gb = with_backface(FRAMES[frame]())
    module = BitmaskAO(variant="exact", backend="torch", trainable=False, **SETTINGS[setting])
    with torch.no_grad():
        reference = module(gb).visibility
        assert exact_covers(module, gb) is None
        out = kernel_forward(module, gb, "kernel")["visibility"] if lanes == "simd" else _scalar(module, gb)
    assert reference.min() < 0.9  # something is occluded: the comparison means something
    assert_values_agree(out, reference, gb.valid, bound=0.05)


def _scalar(module, gb):
    return exact_hard(gb, gb.view_normals(), slices=module.slices, steps=module.steps, radius=float(module.radius),
                      **thickness_options(module_thickness(module, gb)), step_power=module.step_power, min_step_px=module.min_step_px, jitter=module.jitter,
                      seed=module.seed, noise=module.noise, stagger=module.stagger, fetch=module.fetch,
                      border=module.border, weighting=module.weighting,
                      thickness_direction=module.thickness_direction, clip_to_radius=module.clip_to_radius,
                      sample_extent=module.sample_extent, sector_epsilon=module.sector_epsilon, azimuth=module.azimuth,
                      lanes="scalar")


def test_the_edge_aware_fetch_is_what_the_kernel_reads():
    """On a frame with depth edges the edge-aware fetch changes the visibility (so the agreement above
    tests it), and the kernel follows the fetch it is given."""
    gb = FRAMES["rough"]()
    with torch.no_grad():
        edge = BitmaskAO(variant="exact", slices=3, steps=4, backend="kernel", trainable=False)(gb).visibility
        bilinear = BitmaskAO(variant="exact", slices=3, steps=4, fetch="bilinear", backend="kernel",
                             trainable=False)(gb).visibility
    assert (edge - bilinear).abs().max() > 0.01


def test_auto_runs_the_exact_kernel_without_a_gradient_and_its_gradients_kernels_with_one(built, monkeypatch):
    import torch_ao.kernels.dispatch as dispatch

    calls = []
    monkeypatch.setattr(dispatch, "KERNELS", dict(dispatch.KERNELS, bitmask=tuple(
        (covers, (lambda m, g, run=run: calls.append(run.__name__) or run(m, g))) for covers, run in dispatch.KERNELS["bitmask"])))
    gb = with_backface(FRAMES["example"]())
    module = BitmaskAO(variant="exact", slices=2, steps=3, thickness=BackfaceThickness())
    with torch.no_grad():
        module(gb)
    assert calls == ["exact_forward"]
    out = module(gb).visibility  # trainable thickness and radius: the exact union has a gradient in hard mode
    assert out.requires_grad and calls == ["exact_forward", "exact_soft_forward"]
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera, backface_depth=gb.backface_depth)
    assert module(graph).visibility.requires_grad and calls[2:] == ["exact_soft_forward"]  # (its exact_backward)
    intrinsics = gb.camera.intrinsics.clone().requires_grad_()
    moving = GBuffer(depth=gb.depth, camera=PinholeCamera(intrinsics, gb.camera.height, gb.camera.width),
                     backface_depth=gb.backface_depth)
    assert module(moving).visibility.requires_grad and calls[3:] == ["exact_soft_forward"]  # (the intrinsics' too)


def test_exact_covers_names_what_it_does_not_cover():
    gb = with_backface(FRAMES["example"]())
    with torch.no_grad():
        assert exact_covers(BitmaskAO(variant="exact", trainable=False), gb) is None
        assert exact_covers(BitmaskAO(union="exact", trainable=False), gb) is None  # the union alone, default variant
        assert exact_covers(BitmaskAO(variant="exact", thickness_growth=0.5, trainable=False), gb) is None
        assert exact_covers(BitmaskAO(variant="exact", slice_sampling="projected_normal", trainable=False), gb) is None
        cases = {"union": BitmaskAO(trainable=False), "mode": BitmaskAO(variant="exact", mode="soft", trainable=False),
                 "steps=40": BitmaskAO(variant="exact", steps=40, trainable=False),
                 "float64": BitmaskAO(variant="exact", trainable=False)}
        for word, module in cases.items():
            frame = gb.to(dtype=torch.float64) if word == "float64" else gb
            reason = exact_covers(module, frame)
            assert reason is not None and word in reason, (word, reason)
    assert "gradient" in exact_covers(BitmaskAO(variant="exact"), gb)


def test_a_footprint_clamped_onto_the_pixel_is_not_an_occluder(built):
    """float32 kernel against the float64 tensor walk on a tilted plane with the clamped border: a corner
    pixel's samples beyond the image read its own texel back through the inverse depth, a few ulp off its
    position, which must not occlude (walk.sample.MIN_OFFSET); in float64 it is exact."""
    from torch_ao.examples import plane_gbuffer

    for distance in torch.linspace(1.0, 20.0, 12).tolist():
        gb = plane_gbuffer(8, 10, tilt_degrees=35.0, distance=distance)
        options = dict(variant="exact", border="clamp", fetch="bilinear", slices=3, steps=4, radius=1.0)
        with torch.no_grad():
            out = BitmaskAO(backend="kernel", **options)(gb).visibility.double()
            reference = BitmaskAO(backend="torch", **options).double()(gb.to(dtype=torch.float64)).visibility
        assert (out - reference).abs().max() < 1e-2, distance
