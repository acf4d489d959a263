"""Temporal accumulation: reprojection against closed forms (a still camera, a sideways translation of a
fronto-parallel plane, a disocclusion), the running mean against the mean over seeds, gradients."""
import math

import pytest
import torch

from torch_ao import BitmaskAO, GTAO, GBuffer, PinholeCamera
from torch_ao.examples import example_gbuffer
from torch_ao.fitted import FittedPipeline
from torch_ao.temporal import TemporalAO, accumulate_still, reproject


def plane_gbuffer(depth=2.0, H=12, W=16, dtype=torch.float64):
    cam = PinholeCamera.from_fov(60.0, H, W, dtype=dtype)
    return GBuffer(depth=torch.full((1, 1, H, W), depth, dtype=dtype), camera=cam)


def translation(dx):
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = dx
    return T


def test_a_still_camera_reads_the_history_back_exactly():
    gb = example_gbuffer(18, 24).to(dtype=torch.float64)
    history = torch.rand(1, 3, 18, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    for kwargs in ({}, {"current_to_previous": torch.eye(4, dtype=torch.float64)},
                   {"motion": torch.zeros(1, 2, 18, 24, dtype=torch.float64)}):
        warped, valid = reproject(history, gb.depth, gb, **kwargs)
        assert torch.equal(valid, gb.valid)
        torch.testing.assert_close(warped[valid.expand_as(warped)], history[valid.expand_as(history)], atol=1e-12, rtol=0)


def test_a_sideways_move_shifts_the_plane_by_fx_dx_over_z():
    gb = plane_gbuffer(depth=2.0)
    fx = float(gb.camera.fx)
    dx = 2 * 2.0 / fx  # two pixels: a point at u lies at u + 2 in the previous view
    history = torch.arange(16, dtype=torch.float64).expand(1, 1, 12, 16).clone()
    warped, valid = reproject(history, gb.depth, gb, current_to_previous=translation(dx))
    assert valid[..., :14].all() and not valid[..., 14:].any()  # the last two columns come from off screen
    torch.testing.assert_close(warped[..., :14], history[..., 2:], atol=1e-9, rtol=0)
    # the same move as motion vectors
    motion = torch.zeros(1, 2, 12, 16, dtype=torch.float64)
    motion[:, 0] = 2.0
    warped_mv, valid_mv = reproject(history, gb.depth, gb, motion=motion)
    assert torch.equal(valid_mv, valid)
    torch.testing.assert_close(warped_mv, warped, atol=1e-9, rtol=0)


def test_a_disoccluded_pixel_starts_again():
    gb = plane_gbuffer(depth=2.0)
    previous = gb.depth.clone()
    previous[..., 4:8, 5:9] = 1.5  # an occluder in front, gone now
    previous[..., 0, 0] = math.inf  # background before
    warped, valid = reproject(torch.ones_like(gb.depth), previous, gb)
    expected = torch.ones_like(gb.valid)
    # bilinear taps at pixel centres are the pixel itself: exactly the changed texels fail
    expected[..., 4:8, 5:9] = False
    expected[..., 0, 0] = False
    assert torch.equal(valid, expected)
    assert (warped[~valid] == 0).all()
    # within the tolerance: kept
    _, kept = reproject(torch.ones_like(gb.depth), gb.depth * 1.04, gb, depth_tolerance=0.05)
    assert kept.all()


@pytest.mark.parametrize("make", [lambda: BitmaskAO(preset="high", trainable=False),
                                  lambda: FittedPipeline("gtao", {"preset": "high"}, denoiser=True)])
def test_a_still_camera_accumulates_the_mean_over_seeds(make):
    gb = example_gbuffer(24, 32)
    temporal = TemporalAO(make(), frames=4)
    with torch.no_grad():
        outs = [temporal(gb).visibility for _ in range(4)]
        still = accumulate_still(make(), gb, 4).visibility
        singles = [BitmaskAO(preset="high", trainable=False, seed=s)(gb).visibility for s in range(4)] \
            if isinstance(temporal.module, BitmaskAO) else None
    torch.testing.assert_close(outs[-1], still, atol=1e-6, rtol=0)
    assert (outs[0] - outs[-1]).abs().max() > 1e-3  # the seeds differ: the mean is not one frame
    if singles is not None:
        torch.testing.assert_close(still, torch.stack(singles).mean(0), atol=1e-6, rtol=0)
    # the module's own seed is left as it was
    assert temporal.module is not None and all(m.sampling.seed == 0 for m in temporal.modules() if hasattr(m, "sampling"))


def test_once_full_it_is_an_exponential_average_of_weight_one_over_frames():
    gb = example_gbuffer(16, 20)
    temporal = TemporalAO(GTAO(preset="high", trainable=False), frames=2)
    with torch.no_grad():
        a = temporal(gb).visibility
        b = temporal(gb).visibility
        c = temporal(gb).visibility  # seed 0 again: (b + frame0) / 2
    torch.testing.assert_close(c, 0.5 * b + 0.5 * a, atol=1e-6, rtol=0)
    temporal.reset()
    with torch.no_grad():
        torch.testing.assert_close(temporal(gb).visibility, a, atol=0, rtol=0)


def test_gradients_reach_the_current_frame_with_weight_one_over_n():
    gb = example_gbuffer(12, 16)
    method = BitmaskAO(preset="high", mode="soft", backend="torch")
    temporal = TemporalAO(method, frames=4)
    with torch.no_grad():
        temporal(gb)
    out = temporal(gb).visibility.sum()
    out.backward()
    g_temporal = method.radius.grad.clone()
    method.radius.grad = None
    single = BitmaskAO(preset="high", mode="soft", backend="torch", seed=1)
    single.load_state_dict(method.state_dict())
    single(gb).visibility.sum().backward()
    torch.testing.assert_close(g_temporal, 0.5 * single.radius.grad, rtol=1e-6, atol=0)


def test_bad_arguments_are_named():
    gb = plane_gbuffer()
    with pytest.raises(ValueError, match="frames"):
        TemporalAO(GTAO(), frames=0)
    with pytest.raises(TypeError, match="module"):
        TemporalAO(torch.nn.Identity())
    with pytest.raises(ValueError, match="current_to_previous"):
        reproject(gb.depth, gb.depth, gb, current_to_previous=torch.eye(3))
    with pytest.raises(ValueError, match="motion"):
        reproject(gb.depth, gb.depth, gb, motion=torch.zeros(1, 3, 12, 16))
    with pytest.raises(ValueError, match="one of them"):
        reproject(gb.depth, gb.depth, gb, current_to_previous=torch.eye(4), motion=torch.zeros(1, 2, 12, 16))
    with pytest.raises(ValueError, match="history_depth"):
        reproject(gb.depth, gb.depth[..., :3], gb)
