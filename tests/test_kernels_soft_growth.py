"""A thickness growth (``thickness_growth``: the thickness times ``1 + g |sample - pixel|``) in the soft /
straight-through kernel (soft.h): values within 1e-5 of the float64 tensor walk, and the gradients of the growth,
the radius, the model's offset and scale (the forward's derivative channels) and of depth, normals and the
back-face depth (the G-buffer backward) within 1e-4 relative of its autograd, in SIMD and scalar lanes; the
growth's gradient against central differences of the kernel's own loss; a fitted growth at 0 and below 0."""
import math

import pytest
import torch

from kernel_agreement import assert_values_agree
from test_kernels import FRAMES, built, pytestmark  # noqa: F401 (the fixture, the skip)
from test_kernels_thickness_layers import _backface
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import bitmask_soft
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.kernels.bitmask import module_thickness
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import BackfaceThickness, LinearThickness, ScalarThickness

MODELS = {  # model -> (its thickness with a growth, the parameters with a gradient)
    "scalar": (lambda: ScalarThickness(0.3, growth=0.7), ("radius", "thickness", "thickness_growth")),
    "backface": (lambda: BackfaceThickness(0.8, 0.1, growth=0.5),
                 ("radius", "thickness_scale", "thickness", "thickness_growth")),
    "linear": (lambda: LinearThickness(0.02, 0.15, growth=0.4),
               ("radius", "thickness_slope", "thickness", "thickness_growth")),
}
SETTINGS = [
    dict(mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware"),  # torch-ao fit's sectors and fetch
    dict(mode="soft", slices=2, steps=3, tau=0.1, border="clamp"),
    dict(mode="straight_through", slices=3, steps=3, weighting="cosine", fetch="bilinear"),
    dict(mode="soft", slices=2, steps=4, fetch="nearest", rounding="round"),
    dict(mode="soft", slices=3, steps=3, variant="hdrp", weighting="cosine"),
]


def _weights(vis: torch.Tensor) -> torch.Tensor:
    return torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).view_as(vis)


def _kernel(module: BitmaskAO, gb: GBuffer, lanes: str) -> torch.Tensor:
    """The soft kernel's visibility in ``lanes`` with ``module``'s options and thickness model."""
    form = module_thickness(module, gb)
    return bitmask_soft(gb, gb.view_normals(), slices=module.slices, steps=module.steps, radius=module.radius,
                        thickness=form.offset, layer=form.layer, layer_scale=form.scale, thickness_read=form.read,
                        thickness_growth=form.growth, tau=module.tau, weighting=module.weighting,
                        straight_through=module.mode != "soft", min_step_px=module.min_step_px, fetch=module.fetch,
                        border=module.border, rounding=module.rounding, sector_epsilon=module.sector_epsilon,
                        azimuth=module.azimuth, variant=module.variant, lanes=lanes)


def _run(model: str, settings: dict, dtype: torch.dtype, lanes: str | None, gbuffer_grads: bool):
    """The visibility and the gradients of a weighted sum of it: the model's parameters and, with
    ``gbuffer_grads``, depth, normals and the back-face depth (which makes the kernel's G-buffer backward run); the
    tensor walk in ``dtype`` (``lanes=None``) or the kernel in ``lanes``."""
    gb0 = _backface(FRAMES["rough"]()).to(dtype=dtype)
    make, names = MODELS[model]
    module = BitmaskAO(thickness=make(), backend="torch", **settings).to(dtype)
    leaves = {n: getattr(module, n) for n in names}
    gb = gb0
    if gbuffer_grads:
        depth = gb0.depth.detach().clone().requires_grad_()
        normals = gb0.view_normals().detach().clone().requires_grad_()
        back = gb0.backface_depth.detach().clone().requires_grad_()
        gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera, backface_depth=back)
        leaves.update(depth=depth, normals=normals, backface_depth=back)
    if lanes is None:
        vis = module(gb).visibility
    else:
        assert soft_module.kernel_covers(module, gb) is None
        vis = _kernel(module, gb, lanes)
    grads = torch.autograd.grad((vis * _weights(vis)).sum(), list(leaves.values()), allow_unused=True)
    return vis.detach().double(), {n: torch.zeros(()) if g is None else g.double() for n, g in zip(leaves, grads)}


def assert_growth_agrees(model: str, settings: dict, lanes: str, gbuffer_grads: bool) -> dict:
    """The kernel (float32, in ``lanes``) against the float64 tensor walk: values within 1e-5 (straight-through:
    within one cosine-weighted sector of one slice), each gradient within 1e-4 relative (its norm over the finite
    entries); the largest errors measured."""
    want_vis, want = _run(model, settings, torch.float64, None, gbuffer_grads)
    got_vis, got = _run(model, settings, torch.float32, lanes, gbuffer_grads)
    valid = torch.isfinite(FRAMES["rough"]().depth)
    if settings["mode"] == "soft":
        assert (got_vis - want_vis).abs().max() <= 1e-5
    else:
        assert_values_agree(got_vis, want_vis, valid, bound=math.pi / 2 / (32 * settings["slices"]) + 1e-6)
    errors = {"value": float((got_vis - want_vis).abs().max())}
    for name, w in want.items():
        finite = torch.isfinite(w)
        if name == "radius" and settings.get("fetch") == "nearest":  # (a nearest texel does not move with the radius)
            assert abs(float(got[name])) <= 1e-6 * abs(float(got["thickness"]))
            continue
        if name == "backface_depth" and model != "backface":
            assert got[name].abs().max() == 0
            continue
        assert w[finite].abs().max() > 1e-3, name  # (each gradient means something)
        error = float((got[name] - w)[finite].norm() / w[finite].norm())
        assert error <= 1e-4, (name, error)
        errors[name] = error
    return errors


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
@pytest.mark.parametrize("model", sorted(MODELS))
def test_growth_and_the_parameters_gradients_equal_the_float64_tensor_walk(built, model, setting, lanes):
    """The forward's derivative channels: d visibility / d the growth, the radius (the step's motion moves
    |delta| too), the offset and the scale."""
    assert_growth_agrees(model, SETTINGS[setting], lanes, gbuffer_grads=False)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", [0, 2, 4])
@pytest.mark.parametrize("model", sorted(MODELS))
def test_growth_with_gbuffer_gradients_equals_the_float64_tensor_walk(built, model, setting, lanes):
    """The G-buffer backward: d / d depth, normals and the back-face depth (|delta| moves with every one of them)
    and the parameters' through Euler's identity (the growth is per world unit)."""
    assert_growth_agrees(model, SETTINGS[setting], lanes, gbuffer_grads=True)


def _loss(module: BitmaskAO, gb: GBuffer) -> torch.Tensor:
    vis = module(gb).visibility
    return (vis.double() * _weights(vis.double())).sum()


@pytest.mark.parametrize("gbuffer_grads", [False, True])
def test_growth_gradient_matches_central_differences(built, gbuffer_grads):
    """d loss / d thickness_growth of the kernel (with or without the G-buffer's gradients asked for) against the
    central difference of its own loss (float64 sums of a float32 walk; h = 1e-2 per world unit)."""
    gb = FRAMES["example"]()
    module = BitmaskAO(thickness=0.2, thickness_growth=1.5, mode="soft", slices=3, steps=4, weighting="cosine",
                       fetch="edge_aware", backend="kernel")
    graph = GBuffer(depth=gb.depth.clone().requires_grad_(gbuffer_grads), camera=gb.camera)
    (g,) = torch.autograd.grad(_loss(module, graph), [module.thickness_growth])
    h = 1e-2
    with torch.no_grad():
        losses = []
        for sign in (1, -1):
            module.thickness_growth.fill_(1.5 + sign * h)
            losses.append(float(_loss(module, gb)))
    assert abs(float(g)) > 1e-1
    assert float(g) == pytest.approx((losses[0] - losses[1]) / (2 * h), rel=2e-2)


@pytest.mark.parametrize("growth", [0.0, -0.2])
@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_a_fitted_growth_at_or_below_zero_is_the_tensor_walks(built, growth, mode):
    """A fit moves the growth parameter anywhere, through 0 and below it: the kernels multiply by
    ``1 + g |delta|`` for any g, as the tensor walk does (hard: masks as tests/kernel_agreement.py's; soft: values
    within 1e-5 and the growth's gradient within 1e-4 relative, which is not 0 at g = 0)."""
    gb = FRAMES["rough"]()
    modules = {}
    for backend in ("torch", "kernel"):
        modules[backend] = BitmaskAO(thickness=0.3, thickness_growth=0.5, mode=mode, slices=3, steps=4,
                                     backend=backend)
        with torch.no_grad():
            modules[backend].thickness_growth.fill_(growth)
    if mode == "hard":
        with torch.no_grad():
            want, got = (modules[b](gb).visibility for b in ("torch", "kernel"))
        assert_values_agree(got, want, gb.valid, bound=1 / (32 * 3) + 1e-6)
        plain = BitmaskAO(thickness=0.3, mode=mode, slices=3, steps=4, backend="kernel")(gb).visibility
        assert (growth == 0) == bool(torch.equal(got, plain))
        return
    (g_want,), (g_got,) = (torch.autograd.grad(_loss(modules[b], gb), [modules[b].thickness_growth])
                           for b in ("torch", "kernel"))
    with torch.no_grad():
        assert (modules["kernel"](gb).visibility - modules["torch"](gb).visibility).abs().max() <= 1e-5
    assert abs(float(g_want)) > 1e-2
    assert float(g_got) == pytest.approx(float(g_want), rel=1e-4)
