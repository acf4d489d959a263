"""Denoiser: noise goes down on a plane, depth edges survive (unlike a Gaussian blur), background is
excluded, temporal blend, gradients."""
import math

import pytest
import torch
from kornia.filters import gaussian_blur2d

from torch_ao import GBuffer, PinholeCamera
from torch_ao.denoise import Denoiser, denoise
from torch_ao.examples import plane_gbuffer


def _mae(a, b, valid):
    return float((a - b)[valid].abs().mean())


def test_noisy_plane_gets_closer_to_clean():
    gb = plane_gbuffer(48, 64)
    valid = gb.valid
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    clean = (0.6 + 0.3 * torch.sin(u / 15.0) * torch.cos(v / 13.0))[None, None]  # smooth AO
    g = torch.Generator().manual_seed(0)
    noisy = (clean + 0.15 * (torch.rand(clean.shape, generator=g) - 0.5) * 2).clamp(0, 1)
    out = denoise(noisy, gb, kernel_size=7, sigma_space=2.0)
    before, after = _mae(noisy, clean, valid), _mae(out.visibility, clean, valid)
    assert after < 0.5 * before, (before, after)
    assert out.visibility.shape == noisy.shape and out.indirect is None


def _step_gbuffer(H=32, W=48):
    """Left half at depth 1, right half at depth 3 (a fronto-parallel depth discontinuity)."""
    cam = PinholeCamera.from_fov(60.0, height=H, width=W)
    depth = torch.ones(1, 1, H, W)
    depth[..., W // 2:] = 3.0
    normals = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(1, 3, H, W).contiguous()
    return GBuffer(depth=depth, camera=cam, normals=normals)


def test_depth_edge_preserved_unlike_gaussian():
    H, W = 32, 48
    gb = _step_gbuffer(H, W)
    clean = torch.ones(1, 1, H, W)
    clean[..., W // 2:] = 0.3
    out = denoise(clean, gb, kernel_size=7, sigma_space=2.0).visibility
    blurred = gaussian_blur2d(clean, (7, 7), (2.0, 2.0), border_type="reflect")
    band = torch.zeros_like(gb.valid)
    band[..., W // 2 - 3: W // 2 + 3] = True
    err_bilateral = _mae(out, clean, band)
    err_gauss = _mae(blurred, clean, band)
    assert err_bilateral < 1e-3 and err_gauss > 0.1, (err_bilateral, err_gauss)
    # With noise, still denoised on each side without bleeding across the edge.
    g = torch.Generator().manual_seed(1)
    noisy = clean + 0.1 * torch.randn(clean.shape, generator=g)
    out = denoise(noisy, gb, kernel_size=7, sigma_space=2.0).visibility
    assert _mae(out, clean, gb.valid) < 0.6 * _mae(noisy, clean, gb.valid)
    assert _mae(out, clean, band) < 0.5 * _mae(blurred, clean, band)


def test_background_excluded_and_kept():
    H, W = 24, 32
    gb0 = plane_gbuffer(H, W)
    depth = gb0.depth.clone()
    depth[..., :, : W // 2] = math.inf
    gb = GBuffer(depth=depth, camera=gb0.camera)
    vis = torch.full((1, 1, H, W), 0.5)
    vis[~gb.valid] = 1.0  # background visibility 1 must not leak into the valid half
    ind = torch.rand(1, 3, H, W)
    out = denoise(vis, gb, indirect=ind)
    assert torch.allclose(out.visibility[gb.valid], torch.tensor(0.5))
    assert torch.equal(out.visibility[~gb.valid], vis[~gb.valid])
    assert out.indirect.shape == (1, 3, H, W)
    assert torch.equal(out.indirect[:, :, ~gb.valid[0, 0]], ind[:, :, ~gb.valid[0, 0]])
    # All background: returned unchanged, no NaN.
    gb_bg = GBuffer(depth=torch.full((1, 1, H, W), math.inf), camera=gb0.camera)
    out = denoise(torch.ones(1, 1, H, W), gb_bg)
    assert torch.equal(out.visibility, torch.ones(1, 1, H, W))


def test_scale_free_guide():
    """Scaling the scene (depth x 10) gives the same result: the guide is normalised."""
    gb = _step_gbuffer()
    gb10 = GBuffer(depth=gb.depth * 10, camera=gb.camera, normals=gb.normals)
    x = torch.rand(1, 1, *gb.depth.shape[-2:], generator=torch.Generator().manual_seed(3))
    assert torch.allclose(denoise(x, gb).visibility, denoise(x, gb10).visibility, atol=1e-6)


def test_temporal_blend_reduces_noise_and_resets():
    gb = plane_gbuffer(24, 32)
    clean = torch.full((1, 1, 24, 32), 0.7)
    g = torch.Generator().manual_seed(2)
    den = Denoiser(kernel_size=1, temporal=True, alpha=0.2)
    outs = [den(clean + 0.2 * torch.randn(clean.shape, generator=g), gb).visibility for _ in range(30)]
    assert _mae(outs[-1], clean, gb.valid) < 0.5 * _mae(outs[0], clean, gb.valid)
    den.reset()
    x = torch.rand(clean.shape, generator=g)
    assert torch.allclose(den(x, gb).visibility[gb.valid], x[gb.valid])  # kernel 1, no history: identity


def test_gradients_and_errors():
    gb = plane_gbuffer(6, 8, dtype=torch.float64)
    x = torch.rand(1, 1, 6, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: denoise(t, gb, kernel_size=3).visibility, (x,))
    with pytest.raises(ValueError, match="kernel_size"):
        Denoiser(kernel_size=4)
    with pytest.raises(ValueError, match="guide"):
        denoise(x, gb, guide="colour")
    with pytest.raises(ValueError, match="visibility"):
        denoise(torch.rand(1, 2, 6, 8), gb)


@pytest.mark.parametrize("kwargs, message", [
    ({"kernel_size": 0}, "kernel_size: expected an integer >= 1"),
    ({"kernel_size": True}, "kernel_size: expected an integer"),
    ({"kernel_size": 6}, "kernel_size: expected an odd integer"),
    ({"sigma_space": 0.0}, "sigma_space: expected a number > 0"),
    ({"sigma_depth": float("nan")}, "sigma_depth: expected a finite number"),
    ({"alpha": 1.5}, "alpha: expected a number <= 1"),
    ({"alpha": 0.0}, "alpha: expected a number > 0"),
])
def test_bad_options_name_the_argument(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Denoiser(**kwargs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("k, sigma, channels, guide_channels", [(5, 1.5, 5, 4), (3, 0.8, 1, 1), (7, 2.0, 2, 3)])
def test_weights_equal_kornia_joint_bilateral_blur(dtype, k, sigma, channels, guide_channels):
    from kornia.filters import joint_bilateral_blur
    from torch_ao.denoise import apply_weights, bilateral_weights

    g = torch.Generator().manual_seed(k)
    x = torch.rand(2, channels, 13, 17, generator=g, dtype=dtype)
    guide = 2 * torch.randn(2, guide_channels, 13, 17, generator=g, dtype=dtype)
    ours = apply_weights(x, bilateral_weights(guide, k, sigma))
    theirs = joint_bilateral_blur(x, guide, (k, k), 1.0, (sigma, sigma), border_type="reflect",
                                  color_distance_type="l2")
    assert ours.dtype == dtype
    assert (ours - theirs).abs().max() < 1e-6


def test_masked_filter_equals_kornia_on_value_and_mask():
    """The valid-only filter is kornia's filter of ``[value * valid, valid]``, divided."""
    from kornia.filters import joint_bilateral_blur
    from torch_ao.denoise import spatial_filter

    g = torch.Generator().manual_seed(5)
    x = torch.rand(2, 4, 12, 16, generator=g)
    valid = torch.rand(2, 1, 12, 16, generator=g) > 0.3
    guide = torch.randn(2, 4, 12, 16, generator=g)
    out = joint_bilateral_blur(torch.cat((x * valid, valid.float()), 1), guide, (5, 5), 1.0, (1.5, 1.5),
                               border_type="reflect", color_distance_type="l2")
    expected = torch.where(valid, out[:, :-1] / out[:, -1:], -1.0)
    assert (spatial_filter(x, valid, guide, fill=-1.0) - expected).abs().max() < 1e-6


def test_weights_and_filter_gradients_against_finite_differences():
    from torch_ao.denoise import apply_weights, bilateral_weights

    g = torch.Generator().manual_seed(7)
    x = torch.rand(2, 2, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    guide = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    valid = torch.rand(2, 1, 5, 6, generator=g) > 0.3
    assert torch.autograd.gradcheck(lambda a, b: apply_weights(a, bilateral_weights(b, 3, 1.0, valid)), (x, guide))
    assert torch.autograd.gradgradcheck(lambda a, b: apply_weights(a, bilateral_weights(b, 3, 1.0)), (x, guide))


def test_weights_cached_per_gbuffer_and_in_the_graph_for_a_differentiable_guide():
    gb = plane_gbuffer(8, 10, dtype=torch.float64)
    x = torch.rand(1, 1, 8, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(8))
    first = denoise(x, gb, kernel_size=3).visibility
    keys = [key for key in gb._derived if key[0] == "denoise_weights"]
    assert len(keys) == 1
    cached = gb._derived[keys[0]]
    assert torch.equal(denoise(x, gb, kernel_size=3).visibility, first)
    assert gb._derived[keys[0]] is cached  # reused, not recomputed
    # A G-buffer whose depth needs gradients: the weights are recomputed in the graph.
    depth = (gb.depth * (1 + 0.3 * torch.rand(gb.depth.shape, dtype=torch.float64,
                                              generator=torch.Generator().manual_seed(9)))).requires_grad_()
    fn = lambda d: denoise(x, GBuffer(depth=d, camera=gb.camera, normals=gb.normals), kernel_size=3,
                           sigma_depth=0.1).visibility
    assert torch.autograd.gradcheck(fn, (depth,))
    assert depth.grad is None and fn(depth).sum().grad_fn is not None


def test_weights_bad_shapes_raise():
    from torch_ao.denoise import apply_weights, bilateral_weights

    with pytest.raises(ValueError, match="kernel_size: expected an odd integer"):
        bilateral_weights(torch.zeros(1, 1, 8, 8), 4, 1.0)
    with pytest.raises(ValueError, match="kernel_size"):
        bilateral_weights(torch.zeros(1, 1, 2, 8), 5, 1.0)  # a reflect padding of 2 needs a side > 2
    with pytest.raises(ValueError, match="weights: expected shape"):
        apply_weights(torch.zeros(1, 1, 8, 8), torch.zeros(1, 16, 8, 8))
