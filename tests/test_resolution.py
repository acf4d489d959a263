"""Walking at half (and quarter) resolution: the decimated G-buffer, the depth-aware upsample, every method
at ``@half``, closed forms, no bleeding across a depth edge, gradients against finite differences."""
import math

import pytest
import torch

import torch_ao
from test_horizon_analytic import _errors, floor_wall_case
from torch_ao.camera import PinholeCamera
from torch_ao.examples import example_gbuffer, plane_gbuffer, planes_gbuffer
from torch_ao.methods import METHODS, get_method
from torch_ao.methods.common import PRESET_NAMES, split_preset
from torch_ao.resolution import RANGE_FLOOR, downsample_gbuffer, reduced_forward, upsample


def step_gbuffer(height=21, width=33, dtype=torch.float64):
    """Two planes facing the camera: depth 2 on the left (x <= 0), depth 4 behind it on the right."""
    cam = PinholeCamera.from_fov(60.0, height, width)
    return planes_gbuffer([((0, 0, 1), -2.0, [((1, 0, 0), 0.0)]), ((0, 0, 1), -4.0, None)], cam, dtype=dtype)


# ------------------------------------------------------------------------------------ the decimated frame
@pytest.mark.parametrize("factor", [2, 4])
@pytest.mark.parametrize("size", [(24, 32), (23, 37)])
def test_downsampled_frame_is_the_same_scene_at_the_picked_texels(factor, size):
    gb = plane_gbuffer(*size, tilt_degrees=60.0, dtype=torch.float64)
    low = downsample_gbuffer(gb, factor)
    H, W = size
    assert low.depth.shape == (1, 1, math.ceil(H / factor), math.ceil(W / factor))
    assert (low.camera.height, low.camera.width) == tuple(low.depth.shape[-2:])
    # the smaller camera unprojects each kept texel to the point the full camera does
    assert torch.allclose(low.positions(), gb.positions()[..., ::factor, ::factor], atol=1e-12, rtol=0)
    assert torch.equal(low.normals, gb.normals[..., ::factor, ::factor])
    assert torch.equal(low.object_id, gb.object_id[..., ::factor, ::factor])
    assert torch.allclose(low.camera.fx * factor, gb.camera.fx)


# ------------------------------------------------------------------------------------ the upsample
@pytest.mark.parametrize("factor", [2, 4])
@pytest.mark.parametrize("size", [(16, 20), (15, 21)])
def test_upsample_of_a_constant_is_that_constant(factor, size):
    gb = plane_gbuffer(*size, tilt_degrees=75.0, dtype=torch.float64)
    low = downsample_gbuffer(gb, factor)
    up = upsample(torch.full_like(low.depth, 0.37), low.valid, gb, factor)
    assert up.shape == gb.depth.shape and bool((~gb.valid).any()) and int(gb.valid.sum()) > 100  # sky above
    assert float((up - 0.37)[gb.valid].abs().max()) < 1e-14
    assert bool((up[~gb.valid] == 0).all())


def test_upsample_does_not_bleed_across_a_depth_edge():
    gb = step_gbuffer()
    low = downsample_gbuffer(gb, 2)
    near_low, far = low.depth < 3, gb.depth > 3
    assert int(near_low.sum()) > 20 and int((~near_low).sum()) > 20
    outs = [upsample(torch.where(near_low, torch.full_like(low.depth, v), torch.full_like(low.depth, 0.5)),
                     low.valid, gb, 2) for v in (0.0, 1.0)]
    # the near side's values (0 or 1) reach the far side only through the spatial floor's weight
    assert float((outs[0] - outs[1]).abs()[far].max()) < 2 * RANGE_FLOOR
    assert float((outs[0] - 0.5).abs()[far].max()) < 2 * RANGE_FLOOR
    assert float((outs[0] - 0.0).abs()[~far].max()) < 2 * RANGE_FLOOR  # nor the far side's onto the near


def test_step_frame_end_to_end_no_leak_either_way():
    """GTAO@half on the step: the far plane is dark next to the edge (the near plane occludes it), the near
    plane is unoccluded; neither value crosses the edge in the upsample."""
    gb = step_gbuffer(dtype=torch.float32)
    with torch.no_grad():
        low = downsample_gbuffer(gb, 2, normals=gb.view_normals())
        walked = torch_ao.GTAO(preset="high", jitter=False, radius=3.0)(low).visibility
        up = torch_ao.GTAO(preset="high@half", jitter=False, radius=3.0)(gb).visibility
    far_low, far = low.depth > 3, gb.depth > 3
    edge = int(far[0, 0, 10].nonzero()[0])  # first far column (the same in every row)
    edge_low = int(far_low[0, 0, 5].nonzero()[0])
    assert float((1 - walked[~far_low]).abs().max()) < 1e-5  # nothing occludes the near plane
    dark = walked[0, 0, :, edge_low:edge_low + 2]
    assert float(dark.max()) < 0.9
    # the far pixels next to the edge: as dark as their own side's texels, not lifted toward 1
    assert float(up[0, 0, :, edge:edge + 3].max()) <= float(dark.max()) + 2 * RANGE_FLOOR
    # the near pixels next to the edge stay 1
    assert float((1 - up[0, 0, :, edge - 3:edge]).abs().max()) < 2 * RANGE_FLOOR


def test_upsample_gradients_match_finite_differences():
    gb = step_gbuffer(9, 11)
    low = downsample_gbuffer(gb, 2)
    values = torch.rand(low.depth.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    depth = gb.depth.clone()

    def f(vals, d):
        frame = torch_ao.GBuffer(depth=d, camera=gb.camera, normals=gb.normals)
        return upsample(vals, low.valid, frame, 2)

    assert torch.autograd.gradcheck(f, (values.requires_grad_(), depth.requires_grad_()), eps=1e-6, atol=1e-7)


# ------------------------------------------------------------------------------------ methods at @half
PLANE_METHODS = [("gtao", {}, 1e-6), ("hbao", {}, 0.0), ("pssao", {}, 1e-6), ("ssao", {}, 0.0),
                 ("bitmask", {}, 0.0), ("bitmask", {"variant": "exact", "mode": "soft"}, 1e-3)]


@pytest.mark.parametrize("name,options,tol", PLANE_METHODS)
@pytest.mark.parametrize("tilt", [0.0, 60.0])
def test_plane_stays_unoccluded_at_half_resolution(name, options, tol, tilt):
    gb = plane_gbuffer(23, 31, tilt_degrees=tilt)
    with torch.no_grad():
        full = get_method(name)(preset="high", **options)(gb).visibility
        half = get_method(name)(preset="high@half", **options)(gb).visibility
    assert half.shape == (1, 1, 23, 31)
    # as exact as the full-resolution walk (the upsample of a constant is that constant)
    assert float((1 - half).abs().max()) <= max(tol, float((1 - full).abs().max())) + 1e-6


def test_floor_next_to_wall_closed_form_at_half_resolution_small():
    R = 1.0
    gb, ref, mask, _ = floor_wall_case(48, 48, R)
    with torch.no_grad():
        half = torch_ao.GTAO(slices=24, steps=32, radius=R, jitter=False, search_scale=1.5, resolution="half")(gb).visibility
    mae, bias = _errors(half, ref, mask)
    assert mae < 0.009 and abs(bias) < 0.009  # measured 0.0075 (full resolution: 0.0051)


@pytest.mark.slow
def test_floor_next_to_wall_keeps_the_closed_form_at_half_resolution():
    R = 1.0
    gb, ref, mask, _ = floor_wall_case(96, 96, R)
    assert int(mask.sum()) > 1000
    with torch.no_grad():
        full = torch_ao.GTAO(slices=24, steps=32, radius=R, jitter=False, search_scale=1.5)(gb).visibility
        half = torch_ao.GTAO(slices=24, steps=32, radius=R, jitter=False, search_scale=1.5, resolution="half")(gb).visibility
    mae_full, _ = _errors(full, ref, mask)
    mae_half, bias_half = _errors(half, ref, mask)
    # measured: full 0.0055, half 0.0057 (the walk at 48x48 sees the same floor and wall)
    assert mae_half < 0.007 and abs(bias_half) < 0.007 and mae_half < mae_full + 0.001


@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_at_half_is_its_walk_on_the_decimated_frame_upsampled(name):
    cls = get_method(name)
    gb = example_gbuffer(23, 35)
    if gb.light is None:
        gb = torch_ao.GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals,
                              light=torch.full_like(gb.depth, 0.5).expand(-1, 3, -1, -1), mask=gb.mask)
    with torch.no_grad():
        module = cls(preset="high@half")
        assert module.resolution == "half" and (module.slices, module.steps) == (3, 3)
        out = module(gb)
        manual = reduced_forward(cls(preset="high"), gb, 2, module.normals_method)
        explicit = cls(preset="high", resolution="half")(gb)
        full_wins = cls(preset="high@half", resolution="full")(gb)
        plain = cls(preset="high")(gb)
    assert out.visibility.shape == (1, 1, 23, 35)
    assert bool(torch.isfinite(out.visibility).all()) and 0 <= float(out.visibility.min()) <= float(out.visibility.max()) <= 1
    assert torch.equal(out.visibility, manual.visibility) and torch.equal(out.visibility, explicit.visibility)
    assert torch.equal(full_wins.visibility, plain.visibility)
    assert bool((out.visibility[~gb.valid] == 1).all())
    for field in ("indirect", "bent_normal", "ambient"):
        a, b = getattr(out, field), getattr(plain, field)
        assert (a is None) == (b is None), field
        if a is not None:
            assert a.shape == b.shape and bool(torch.isfinite(a).all())


def test_half_bent_normals_and_indirect_light():
    gb = example_gbuffer(20, 28)
    light = torch.rand(1, 3, 20, 28, generator=torch.Generator().manual_seed(1))
    gb = torch_ao.GBuffer(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=light, mask=gb.mask)
    with torch.no_grad():
        out = torch_ao.BitmaskAO(preset="medium@half", indirect=True, bent_normals=True)(gb)
    assert out.indirect.shape == (1, 3, 20, 28) and float(out.indirect.min()) >= 0
    n = out.bent_normal.norm(dim=1)
    assert torch.allclose(n[gb.valid[:, 0]], torch.ones_like(n[gb.valid[:, 0]]), atol=1e-5)


def test_batched_half_equals_each_view_alone():
    a, b = example_gbuffer(17, 25), plane_gbuffer(17, 25, tilt_degrees=70.0)
    both = torch_ao.GBuffer(depth=torch.cat((a.depth, b.depth)), camera=a.camera,
                            normals=torch.cat((a.view_normals(), b.view_normals())))
    module = torch_ao.GTAO(preset="medium@half")
    with torch.no_grad():
        out = module(both).visibility
        one = module(torch_ao.GBuffer(depth=a.depth, camera=a.camera, normals=a.view_normals())).visibility
        two = module(torch_ao.GBuffer(depth=b.depth, camera=a.camera, normals=b.view_normals())).visibility
    assert torch.allclose(out, torch.cat((one, two)), atol=1e-6)


def test_quarter_resolution_runs_on_odd_sizes():
    gb = example_gbuffer(29, 43)
    with torch.no_grad():
        out = torch_ao.HBAO(preset="high@quarter")(gb).visibility
    assert out.shape == (1, 1, 29, 43) and bool(torch.isfinite(out).all())
    assert 0 <= float(out.min()) and float(out.max()) <= 1 and float(out[gb.valid].std()) > 0


def test_kernel_backend_runs_at_half():
    from torch_ao.kernels import kernel_covers

    gb = example_gbuffer(24, 40)
    module = torch_ao.BitmaskAO(preset="high@half", backend="kernel")
    assert kernel_covers(module, downsample_gbuffer(gb, 2)) is None  # the kernel takes the smaller frame
    with torch.no_grad():
        kernel = module(gb).visibility
        torch_path = torch_ao.BitmaskAO(preset="high@half", backend="torch")(gb).visibility
    assert kernel.shape == (1, 1, 24, 40)
    assert torch.allclose(kernel, torch_path, atol=1e-6)


# ------------------------------------------------------------------------------------ gradients
def _soft_half(**extra):
    return torch_ao.BitmaskAO(variant="exact", mode="soft", preset="medium@half", jitter=False, **extra).double()


def test_half_gradients_to_radius_thickness_and_depth_match_finite_differences():
    gb = example_gbuffer(14, 18).to(dtype=torch.float64)
    module = _soft_half(radius=1.5, thickness=0.4)
    weights = torch.linspace(0.5, 1.5, 14 * 18, dtype=torch.float64).reshape(1, 1, 14, 18)

    def loss(depth):
        frame = torch_ao.GBuffer(depth=depth, camera=gb.camera, normals=gb.normals, mask=gb.mask)
        return (module(frame).visibility * weights).sum()

    depth = gb.depth.clone().requires_grad_(True)
    value = loss(depth)
    g_depth, g_radius, g_thickness = torch.autograd.grad(value, (depth, module.radius, module.thickness))
    eps = 1e-6
    for param, grad in ((module.radius, g_radius), (module.thickness, g_thickness)):
        with torch.no_grad():
            base = param.detach().clone()
            param.copy_(base + eps)
            up = loss(gb.depth)
            param.copy_(base - eps)
            down = loss(gb.depth)
            param.copy_(base)
        fd = (up - down) / (2 * eps)
        assert abs(float(grad)) > 1e-3
        assert float(grad) == pytest.approx(float(fd), rel=1e-4, abs=1e-8)
    # depth: a picked texel (walked and guiding) and an in-between pixel (guide only)
    for (i, j) in ((6, 8), (7, 9)):
        bump = torch.zeros_like(gb.depth)
        bump[0, 0, i, j] = eps
        with torch.no_grad():
            fd = (loss(gb.depth + bump) - loss(gb.depth - bump)) / (2 * eps)
        assert abs(float(g_depth[0, 0, i, j])) > 1e-3
        assert float(g_depth[0, 0, i, j]) == pytest.approx(float(fd), rel=1e-4, abs=1e-7), (i, j)


# ------------------------------------------------------------------------------------ options
def test_preset_names_and_bad_input():
    assert split_preset("high@half") == ("high", "half") and split_preset("Ultra") == ("ultra", None)
    assert "high@half" in PRESET_NAMES and "reference@quarter" in PRESET_NAMES
    with pytest.raises(ValueError, match="preset"):
        torch_ao.GTAO(preset="high@double")
    with pytest.raises(ValueError, match="preset"):
        torch_ao.GTAO(preset="huge@half")
    with pytest.raises(ValueError, match="resolution"):
        torch_ao.GTAO(resolution="twice")
    assert torch_ao.GTAO().resolution == "full" and torch_ao.GTAO(preset="low@full").resolution == "full"


@pytest.mark.parametrize("backend", ["torch", "kernel"])
@pytest.mark.parametrize("resolution,f", [("half", 2), ("quarter", 4)])
def test_a_per_pixel_thickness_map_at_full_resolution_is_picked_as_the_gbuffer(backend, resolution, f):
    gb = example_gbuffer(23, 41)
    full_map = 0.05 + 0.5 * torch.rand((1, 1, 23, 41), generator=torch.Generator().manual_seed(3))
    full_map.requires_grad_(True)
    options = dict(variant="exact", mode="hard", resolution=resolution, backend=backend)
    full = torch_ao.BitmaskAO(thickness=full_map, **options)(gb).visibility
    with torch.no_grad():
        walked = torch_ao.BitmaskAO(thickness=full_map.detach()[..., ::f, ::f], **options)(gb).visibility
        by_hand = reduced_forward(torch_ao.BitmaskAO(thickness=full_map.detach()[..., ::f, ::f], variant="exact",
                                                     mode="hard", backend=backend), gb, f)
        other = torch_ao.BitmaskAO(thickness=full_map.detach() + 0.3, **options)(gb).visibility
    assert torch.equal(full.detach(), walked) and torch.equal(walked, by_hand.visibility)
    assert not torch.equal(walked, other)  # (the map is read)
    with pytest.raises(ValueError, match=r"thickness: map of shape .* \(nor its full-resolution frame"):
        torch_ao.BitmaskAO(thickness=torch.rand(1, 1, 22, 41), **options)(gb)


def test_a_full_resolution_thickness_map_is_fitted_at_the_texels_the_walk_reads():
    gb = example_gbuffer(23, 41)
    module = torch_ao.BitmaskAO(variant="exact", mode="soft", resolution="half", jitter=False,
                                thickness=torch.full((1, 1, 23, 41), 0.2))
    module(gb).visibility.sum().backward()
    grad = module.thickness.grad[0, 0]
    picked = torch.zeros_like(grad, dtype=torch.bool)
    picked[::2, ::2] = True
    assert grad[picked].abs().sum() > 0 and bool((grad[~picked] == 0).all())
