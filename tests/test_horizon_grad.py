"""Horizon-family methods: gradients (central finite differences, float64), batching, background,
functional twins and input errors."""
import math

import pytest
import torch

from torch_ao.camera import PinholeCamera
from torch_ao.examples import crease_gbuffer, floor_wall_gbuffer, plane_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.methods.gtao import GTAO, gtao
from torch_ao.methods.hbao import HBAO, hbao
from torch_ao.methods.pssao import PSSAO, pssao
from torch_ao.methods.ssao import SSAO, ssao
from torch_ao.methods.ue4_ssao import UE4SSAO, ue4_ssao


# Smooth settings for derivative checks: bilinear fetch, no jitter, and each method's continuous
# options (GTAO exact with a falloff ramp instead of the hard cut, HBAO's incremental sum, soft
# comparisons for SSAO and UE4's flat-surface test). Hard thresholds are piecewise constant: their
# gradient is zero almost everywhere, which finite differences cannot check.
SMOOTH = dict(jitter=True, fetch="bilinear", border="drop", slices=3, steps=4)
GRAD_CASES = [
    ("gtao-exact", GTAO, dict(variant="exact", falloff_range=0.5, final_power=1.3, multibounce=True, albedo=0.6, radius=0.9)),
    ("gtao-hdrp", GTAO, dict(variant="hdrp", radius=0.9, normalize="exact")),
    ("gtao-ue4", GTAO, dict(variant="ue4", radius=0.9, thickness_heuristic=0.7)),
    ("hbao", HBAO, dict(radius=0.9, angle_bias=0.1)),
    ("hbao-quadratic-view", HBAO, dict(radius=0.9, falloff="quadratic", elevation="view", angle_bias=0.05)),
    ("ue4_ssao", UE4SSAO, dict(radius=0.9, flat_softness=0.02, accurate_angle=True, final_power=1.5, intensity=0.8)),
    ("pssao", PSSAO, dict(distance_bias=0.7)),
    ("ssao", SSAO, dict(radius=0.9, softness=0.05, samples=12)),
]
IDS = [c[0] for c in GRAD_CASES]


def make_module(cls, options):
    opts = dict(SMOOTH)
    if cls is PSSAO:
        opts = dict(slices=4, steps=4, fetch="bilinear")
    if cls is SSAO:
        opts.pop("slices"), opts.pop("steps")
    if cls is UE4SSAO:
        opts["sample_set"] = "uniform"
    opts.update(options)
    return cls(**opts).double()


def scene(dtype=torch.float64):
    """A crease and a floor next to a wall, 12 x 16, with depth and normals jittered by a few percent.

    The jitter puts the check at a generic point: on exact planes many samples tie (a max over equal
    values, ``n . delta = 0`` at a clamp), where the one-sided autograd derivative and a central
    difference legitimately differ."""
    g = torch.Generator().manual_seed(11)
    out = []
    for gb in (crease_gbuffer(12, 16, dtype=dtype), floor_wall_gbuffer(12, 16, wall_distance=0.5, dtype=dtype)[0]):
        depth = gb.depth * (1 + 0.03 * torch.rand(gb.depth.shape, generator=g, dtype=dtype))
        normals = gb.normals + 0.05 * torch.randn(gb.normals.shape, generator=g, dtype=dtype)
        out.append(GBuffer(depth=depth, camera=gb.camera, normals=normals / normals.norm(dim=1, keepdim=True)))
    return out


def weighted_sum(module, depth, normals, camera):
    out = module(GBuffer(depth=depth, camera=camera, normals=normals)).visibility
    w = torch.linspace(0.5, 1.5, out.numel(), dtype=out.dtype).reshape(out.shape)
    return (out * w).sum()


@pytest.mark.parametrize("name,cls,options", GRAD_CASES, ids=IDS)
def test_gradients_match_central_differences(name, cls, options):
    gb = scene()[0]
    module = make_module(cls, options)
    depth = gb.depth.clone().requires_grad_(True)
    normals = gb.normals.clone().requires_grad_(True)
    loss = weighted_sum(module, depth, normals, gb.camera)
    params = dict(module.named_parameters())
    loss.backward()
    assert params, "every method has at least one float parameter"
    g = torch.Generator().manual_seed(7)
    eps = 1e-6
    # Directional derivatives along random directions for depth and normals.
    inputs = ((depth, depth.grad),) if cls is UE4SSAO else ((depth, depth.grad), (normals, normals.grad))
    if cls is UE4SSAO:
        assert normals.grad is None  # the normal-less method
    for x, grad in inputs:
        assert grad is not None and bool(torch.isfinite(grad).all())
        for _ in range(2):
            v = torch.randn(x.shape, generator=g, dtype=x.dtype)
            with torch.no_grad():
                args = lambda t: (t, normals) if x is depth else (depth, t)
                fd = (weighted_sum(module, *args(x + eps * v), gb.camera)
                      - weighted_sum(module, *args(x - eps * v), gb.camera)) / (2 * eps)
            an = (grad * v).sum()
            assert abs(an - fd) <= 1e-5 + 1e-4 * abs(fd), (name, float(an), float(fd))
    # Every float parameter, one by one.
    for pname, p in params.items():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), pname
        with torch.no_grad():
            p0 = p.clone()
            p.copy_(p0 + eps)
            up = weighted_sum(module, depth, normals, gb.camera)
            p.copy_(p0 - eps)
            down = weighted_sum(module, depth, normals, gb.camera)
            p.copy_(p0)
        fd = (up - down) / (2 * eps)
        assert abs(p.grad - fd) <= 1e-5 + 1e-4 * abs(fd), (name, pname, float(p.grad), float(fd))


@pytest.mark.parametrize("name,cls,options", GRAD_CASES, ids=IDS)
def test_gradients_reach_inputs_and_parameters_on_the_default_settings(name, cls, options):
    """With each method's own defaults (hard thresholds included) gradients exist, are finite, and
    are non-zero for depth and every parameter that shapes the result."""
    _, gb = scene(torch.float32)
    module = cls(**options) if cls is not SSAO else cls(**{k: v for k, v in options.items() if k != "softness"})
    depth = gb.depth.clone().requires_grad_(True)
    normals = gb.normals.clone().requires_grad_(True)
    module(GBuffer(depth=depth, camera=gb.camera, normals=normals)).visibility.sum().backward()
    assert bool(torch.isfinite(depth.grad).all()) and float(depth.grad.abs().sum()) > 0
    if cls is not UE4SSAO:  # the normal-less method
        assert bool(torch.isfinite(normals.grad).all()) and float(normals.grad.abs().sum()) > 0
    for pname, p in module.named_parameters():
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()), pname


def test_gtao_exact_bent_normals_have_gradients():
    gb = scene()[0]
    module = make_module(GTAO, dict(bent_normals=True, falloff_range=0.5))
    depth = gb.depth.clone().requires_grad_(True)
    out = module(GBuffer(depth=depth, camera=gb.camera, normals=gb.normals))
    out.bent_normal[:, 0].sum().backward()
    assert bool(torch.isfinite(depth.grad).all()) and float(depth.grad.abs().sum()) > 0


# ---------------------------------------------------------------------------------------------
# Batching, background, functional twins
# ---------------------------------------------------------------------------------------------
ALL = [(GTAO, {}), (GTAO, dict(variant="hdrp")), (GTAO, dict(variant="ue4", bent_normals=True)), (HBAO, {}),
       (UE4SSAO, {}), (PSSAO, {}), (SSAO, dict(samples=16))]
ALL_IDS = ["gtao", "gtao-hdrp", "gtao-ue4", "hbao", "ue4_ssao", "pssao", "ssao"]


@pytest.mark.parametrize("cls,options", ALL, ids=ALL_IDS)
def test_batch_equals_items_one_by_one(cls, options):
    a = crease_gbuffer(16, 20)
    b = plane_gbuffer(16, 20, tilt_degrees=50.0, fov_y_degrees=60.0)
    c, _ = floor_wall_gbuffer(16, 20)
    items = [a, b, c]
    batch = GBuffer(depth=torch.cat([g.depth for g in items]), camera=a.camera,
                    normals=torch.cat([g.normals for g in items]))
    module = cls(slices=2, steps=3, **options) if cls is not SSAO else cls(**options)
    with torch.no_grad():
        out = module(batch)
        for i, g in enumerate(items):
            one = module(g)
            assert torch.allclose(out.visibility[i : i + 1], one.visibility, atol=1e-6)
            if one.bent_normal is not None:
                assert torch.allclose(out.bent_normal[i : i + 1], one.bent_normal, atol=1e-5)


@pytest.mark.parametrize("cls,options", ALL, ids=ALL_IDS)
def test_all_background_returns_ones_and_zero_gradients(cls, options):
    cam = PinholeCamera.from_fov(60.0, 8, 10)
    depth = torch.full((2, 1, 8, 10), math.inf)
    depth[1, 0, :4] = 0.0  # zero is background too
    depth[1, 0, 4:] = math.nan
    depth.requires_grad_(True)
    module = cls(**options)
    out = module(GBuffer(depth=depth, camera=cam))
    assert torch.equal(out.visibility, torch.ones(2, 1, 8, 10))
    out.visibility.sum().backward()
    assert depth.grad is None or (bool(torch.isfinite(depth.grad).all()) and float(depth.grad.abs().sum()) == 0)
    for pname, p in module.named_parameters():
        assert p.grad is None or float(p.grad.abs().sum()) == 0, pname


@pytest.mark.parametrize("cls,options", ALL, ids=ALL_IDS)
def test_partial_background_has_no_nan(cls, options):
    gb, _ = floor_wall_gbuffer(16, 20)
    depth = gb.depth.clone()
    depth[..., :5, :] = math.inf  # a sky band over the wall's top
    depth.requires_grad_(True)
    module = cls(**options)
    out = module(GBuffer(depth=depth, camera=gb.camera))  # normals reconstructed from depth
    assert bool(torch.isfinite(out.visibility).all())
    assert bool((out.visibility[..., :5, :] == 1).all())
    out.visibility.sum().backward()
    assert bool(torch.isfinite(depth.grad).all())
    assert float(depth.grad[..., :5, :].abs().sum()) == 0


@pytest.mark.parametrize("fn,cls,params", [
    (gtao, GTAO, dict(radius=0.8, falloff_range=0.3, final_power=1.2)),
    (hbao, HBAO, dict(radius=0.8, angle_bias=0.2)),
    (ue4_ssao, UE4SSAO, dict(radius=0.8, fade_distance=0.5, flat_surface_bias=0.01, final_power=1.2, intensity=0.9)),
    (pssao, PSSAO, dict(distance_bias=0.8)),
    (ssao, SSAO, dict(radius=0.8, bias=0.01)),
], ids=["gtao", "hbao", "ue4_ssao", "pssao", "ssao"])
def test_functional_twin_matches_module_and_passes_gradients(fn, cls, params):
    gb = crease_gbuffer(12, 14)
    options = dict(slices=2, steps=3, **(dict(softness=0.05) if cls is SSAO else {}))
    expected = cls(**params, **options)(gb).visibility
    tensors = {k: torch.tensor(v, requires_grad=True) for k, v in params.items()}
    out = fn(gb, **tensors, **options)
    assert torch.allclose(out.visibility, expected, atol=1e-7)
    out.visibility.sum().backward()
    grads = {k: t.grad for k, t in tensors.items() if t.grad is not None}
    assert all(bool(torch.isfinite(g).all()) for g in grads.values())
    assert any(float(g.abs()) > 0 for g in grads.values())
    # Every tensor that shapes the result is connected (UE4 SSAO's radius only moves nearest fetches).
    assert set(grads) >= set(params) - ({"radius"} if cls is UE4SSAO else set())


def test_float16_input_is_computed_in_float32():
    gb = crease_gbuffer(10, 12)
    half = GBuffer(depth=gb.depth.half(), camera=gb.camera, normals=gb.normals.half())
    out = GTAO(slices=2, steps=2)(half).visibility
    assert out.dtype == torch.float32 and bool(torch.isfinite(out).all())


# ---------------------------------------------------------------------------------------------
# Errors name the argument
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make,match", [
    (lambda: GTAO(variant="xegtao"), "variant"),
    (lambda: GTAO(normalize="sum"), "normalize"),
    (lambda: GTAO(radius=-1.0), "radius"),
    (lambda: GTAO(radius=float("nan")), "radius"),
    (lambda: GTAO(slices=0), "slices"),
    (lambda: GTAO(steps=2.5), "steps"),
    (lambda: GTAO(falloff_range=1.5), "falloff_range"),
    (lambda: GTAO(final_power=0.0), "final_power"),
    (lambda: GTAO(albedo=-0.1), "albedo"),
    (lambda: GTAO(search_scale=0.5), "search_scale"),
    (lambda: GTAO(fetch="cubic"), "fetch"),
    (lambda: GTAO(variant="hdrp", max_radius_px=-3), "max_radius_px"),
    (lambda: HBAO(falloff="cubic"), "falloff"),
    (lambda: HBAO(accumulate="sum"), "accumulate"),
    (lambda: HBAO(elevation="world"), "elevation"),
    (lambda: HBAO(angle_bias=2.0), "angle_bias"),
    (lambda: UE4SSAO(sample_set="ue4_9"), "sample_set"),
    (lambda: UE4SSAO(fade_distance=0.0), "fade_distance"),
    (lambda: UE4SSAO(azimuth="view"), "azimuth"),
    (lambda: UE4SSAO(flat_softness=-1.0), "flat_softness"),
    (lambda: PSSAO(normalize="pixels"), "normalize"),
    (lambda: PSSAO(jitter=True), "jitter"),
    (lambda: PSSAO(distance_bias=0.0), "distance_bias"),
    (lambda: SSAO(samples=0), "samples"),
    (lambda: SSAO(step_power=2.0), "step_power"),
    (lambda: SSAO(border="wrap"), "border"),
    (lambda: gtao(crease_gbuffer(8, 8), radius=torch.ones(3)), "radius"),
])
def test_bad_arguments_raise_clear_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize("cls", [GTAO, HBAO, UE4SSAO, PSSAO, SSAO])
def test_forward_needs_a_gbuffer(cls):
    with pytest.raises(TypeError, match="gbuffer"):
        cls()(torch.ones(1, 1, 4, 4))


@pytest.mark.parametrize("cls,options", ALL, ids=ALL_IDS)
def test_chunked_recomputed_walk_equals_the_whole_frame(cls, options):
    gb = crease_gbuffer(12, 14)
    results = []
    for mem in ({}, dict(chunk_size=37, recompute=True)):
        module = cls(slices=2, steps=3, **options, **mem) if cls is not SSAO else cls(**options, **mem)
        depth = gb.depth.clone().requires_grad_(True)
        out = module(GBuffer(depth=depth, camera=gb.camera, normals=gb.normals))
        loss = out.visibility.sum() + (out.bent_normal.sum() if out.bent_normal is not None else 0)
        loss.backward()
        results.append((out.visibility.detach(), depth.grad))
    assert torch.allclose(results[0][0], results[1][0], atol=1e-6)
    assert torch.allclose(results[0][1], results[1][1], atol=1e-5)


@pytest.mark.parametrize("variant", ["hdrp", "ue4"])
def test_fast_acos_at_plus_minus_one_has_finite_gradients(variant):
    from torch_ao.ops import fast_acos

    x = torch.tensor([1.0, -1.0, 0.5], requires_grad=True)
    (fast_acos(x) * torch.tensor([0.0, 1.0, 1.0])).sum().backward()
    assert bool(torch.isfinite(x.grad).all())
    # A plane facing the camera through the centre pixel: V = n exactly, so cos(n) = 1 there.
    gb = plane_gbuffer(9, 9, tilt_degrees=0.0, dtype=torch.float64)
    depth, normals = gb.depth.clone().requires_grad_(True), gb.normals.clone().requires_grad_(True)
    GTAO(variant=variant, slices=2, steps=2, jitter=False)(GBuffer(depth, gb.camera, normals=normals)).visibility.sum().backward()
    assert bool(torch.isfinite(depth.grad).all()) and bool(torch.isfinite(normals.grad).all())


@pytest.mark.parametrize("cls", [GTAO, HBAO, UE4SSAO, PSSAO, SSAO])
def test_options_describe_the_signature_and_unused_options_are_refused(cls):
    import inspect

    options = cls.options()
    assert list(inspect.signature(cls).parameters) == list(options)
    for name, opt in options.items():
        assert opt.help and inspect.signature(cls).parameters[name].default == opt.default
    fitted = {n for n, o in options.items() if o.fitted}
    assert {n for n, _ in cls().named_parameters()} == fitted - _FROZEN_BY_DEFAULT.get(cls, set())
    if cls is PSSAO:
        for name in ("radius", "seed", "jitter", "azimuth"):
            with pytest.raises(ValueError, match=name):
                PSSAO(**{name: options.get(name, None) or 1})


# unused by the default variant (ue4 / multibounce only), or without a gradient at the default (falloff_range 0,
# SSAO's and UE4's hard comparisons, UE4's radius with its nearest fetch)
_FROZEN_BY_DEFAULT = {GTAO: {"thickness_heuristic", "albedo", "falloff_range"}, SSAO: {"bias"},
                      UE4SSAO: {"radius", "flat_surface_bias"}}


def test_sampling_configuration_validates_each_field():
    from torch_ao.methods.common import Sampling

    assert Sampling().fetch == "bilinear"
    for field, bad in (("fetch", "cubic"), ("slices", 0), ("step_power", 0.0), ("jitter", 1), ("azimuth", "x")):
        with pytest.raises(ValueError, match=field):
            Sampling(**{field: bad})
