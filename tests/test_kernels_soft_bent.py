"""Bent normals of the soft / straight-through kernel (soft.h: the visible sectors' direction sum in the forward;
its backward the same reverse scan as the visibility's, seeded by both outputs' upstream gradients) against the
tensor-op walk's autograd in float64: the visibility and the bent normals within 1e-5 (straight-through's hard
sectors on 99.9 % of the pixels, the others one flipped sector apart), gradients of depth, normals,
radius and thickness within 1e-4 relative (the loss weighs both outputs), in SIMD and scalar lanes; with the
parameters' gradients alone and with none; directional derivatives against central differences; and that the
module's call runs the kernel."""
import pytest
import torch

from kernel_agreement import assert_values_agree, relative_error
from kernel_calls import count_kernel_calls
from test_kernels import FRAMES, built, pytestmark  # noqa: F401 (the fixture, the skip)
from test_kernels_soft import SETTINGS, _one_sector
from torch_ao.examples import floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import soft_outputs
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.methods.bitmask import BitmaskAO

#: the most a flipped sector of one slice turns a bent normal on the rough frame (measured: 0.018)
FLIPPED_BENT = 0.05
#: SETTINGS' soft and straight-through cases, uniform and cosine, every fetch and border, and the hdrp variant's
BENT_SETTINGS = [SETTINGS[0], SETTINGS[2], SETTINGS[4], SETTINGS[5], SETTINGS[7], SETTINGS[8],
                 dict(mode="soft", slices=2, steps=3, variant="hdrp", weighting="cosine"),
                 dict(mode="straight_through", slices=3, steps=4, variant="hdrp", azimuth="screen")]


def _outputs(gb: GBuffer, normals: torch.Tensor, m: BitmaskAO, lanes: str):
    """The kernel's visibility and bent normals with ``m``'s options (its radius and thickness parameters)."""
    return soft_outputs(gb, normals, slices=m.slices, steps=m.steps, radius=m.radius, thickness=m.thickness,
                        tau=m.tau, weighting=m.weighting, straight_through=m.mode != "soft", bent_normals=True,
                        step_power=m.step_power, min_step_px=m.min_step_px, jitter=m.jitter, seed=m.seed,
                        noise=m.noise, stagger=m.stagger, fetch=m.fetch, border=m.border, rounding=m.rounding,
                        sector_epsilon=m.sector_epsilon, azimuth=m.azimuth, variant=m.variant, lanes=lanes)


def _loss(vis: torch.Tensor, bent: torch.Tensor) -> torch.Tensor:
    """A loss weighing every pixel's visibility and bent normal differently."""
    return ((vis * torch.linspace(0.5, 1.5, vis.numel(), dtype=vis.dtype).view_as(vis)).sum()
            + (bent * torch.linspace(-1.0, 1.0, bent.numel(), dtype=bent.dtype).view_as(bent)).sum())


def _values_and_grads(gb0: GBuffer, dtype: torch.dtype, lanes: str | None, settings: dict, gbuffer: bool = True):
    """Visibility, bent normals and d loss / d (depth, normals, radius, thickness) (with ``gbuffer`` False the
    G-buffer wants none): the tensor path in ``dtype`` (``lanes=None``) or the kernel (float32) in ``lanes``."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_(gbuffer)
    normals = gb0.view_normals().detach().clone().requires_grad_(gbuffer)
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera)
    module = BitmaskAO(backend="torch", bent_normals=True, **settings).to(dtype)
    if lanes is None:
        out = module(gb)
        vis, bent = out.visibility, out.bent_normal
    else:
        vis, _, bent = _outputs(gb, gb.view_normals(), module, lanes)  # (as the module: its background normal)
    wrt = ([depth, normals] if gbuffer else []) + [module.radius, module.thickness]
    grads = torch.autograd.grad(_loss(vis, bent), wrt, allow_unused=True)
    grads = [None, None] * (not gbuffer) + [None if g is None else g.double() for g in grads]
    return vis.detach().double(), bent.detach().double(), grads


def _assert_scalar_close(got, want, name):
    if want is None:  # a nearest fetch does not move with the radius: Euler's identity gives ~0
        assert abs(float(got)) <= 1e-4, name
    else:
        assert want != 0 and abs(float(got - want)) <= 1e-4 * abs(float(want)), (name, float(got), float(want))


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(BENT_SETTINGS)))
def test_bent_normals_and_gradients_equal_the_float64_tensor_walk(built, lanes, setting):
    """Measured (16 cases): values within 3e-6 on 99.9 % of the pixels; gradients of depth within 6.4e-5 relative,
    normals 2.7e-5, radius 4.9e-5, thickness 9.4e-6."""
    settings = BENT_SETTINGS[setting]
    vis0, bent0, grads0 = _values_and_grads(FRAMES["rough"](), torch.float64, None, settings)
    vis, bent, grads = _values_and_grads(FRAMES["rough"](), torch.float32, lanes, settings)
    valid = FRAMES["rough"]().valid
    assert vis0.min() < 1 and (bent0 - FRAMES["rough"]().view_normals().double()).abs().max() > 0.1
    assert_values_agree(vis, vis0, valid, bound=_one_sector(settings["slices"]))
    assert_values_agree(bent, bent0, valid, bound=FLIPPED_BENT)
    # (a pixel whose hard sectors flipped normalises another sum: straight-through leaves out its 0.1 %)
    trim = 1e-3 if settings["mode"] == "straight_through" else 0.0
    for name, g, g0 in zip(("depth", "normals"), grads[:2], grads0[:2]):
        assert g0.abs().sum() > 0 and relative_error(g, g0, trim) <= 1e-4, (name, relative_error(g, g0, trim))
    for name, g, g0 in zip(("radius", "thickness"), grads[2:], grads0[2:]):
        _assert_scalar_close(g, g0, name)


@pytest.mark.parametrize("setting", [0, 4, 6])
def test_parameter_gradients_alone_equal_the_float64_tensor_walk(built, setting):
    """With no G-buffer gradient asked for, radius and thickness still get theirs through the backward's walk."""
    settings = BENT_SETTINGS[setting]
    _, _, grads0 = _values_and_grads(FRAMES["rough"](), torch.float64, None, settings, gbuffer=False)
    _, _, grads = _values_and_grads(FRAMES["rough"](), torch.float32, "simd", settings, gbuffer=False)
    for name, g, g0 in zip(("radius", "thickness"), grads[2:], grads0[2:]):
        _assert_scalar_close(g, g0, name)


def test_without_a_gradient_the_forward_equals_the_tensor_walk(built):
    gb = FRAMES["rough"]()
    for settings in (SETTINGS[0], SETTINGS[8]):
        with torch.no_grad():
            ref = BitmaskAO(backend="torch", bent_normals=True, **settings).double()(gb.to(dtype=torch.float64))
            out = BitmaskAO(backend="kernel", bent_normals=True, **settings)(gb)
        assert_values_agree(out.bent_normal.double(), ref.bent_normal, gb.valid, bound=FLIPPED_BENT)
        assert torch.equal(out.bent_normal[~gb.valid.expand_as(out.bent_normal)],
                           gb.view_normals()[~gb.valid.expand_as(out.bent_normal)])  # (background: the normal)


def test_gradients_match_central_differences_on_a_small_frame(built):
    """gradcheck's fast mode by hand: the soft kernel's derivative of the loss along random directions of depth and
    normals against central differences (eps = 1e-6) of the float64 tensor-op forward, on an 8x10 frame of a floor
    meeting a wall with clamped borders. (Straight-through has no such check: its bent normal is the hard sum's
    direction, whose normalisation its gradient takes at the hard sum, not at the soft one.)"""
    gb0 = floor_wall_gbuffer(8, 10, wall_distance=1.0)[0]
    settings = dict(slices=2, steps=3, tau=0.5, border="clamp", radius=0.8, thickness=0.4, bent_normals=True)

    def tensor_walk(depth, normals):
        out = BitmaskAO(backend="torch", mode="soft", **settings).double()(
            GBuffer(depth=depth, normals=normals, camera=gb0.camera.to(dtype=torch.float64)))
        return _loss(out.visibility, out.bent_normal)

    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    out = BitmaskAO(backend="kernel", mode="soft", **settings)(GBuffer(depth=depth, normals=normals, camera=gb0.camera))
    g_depth, g_normals = torch.autograd.grad(_loss(out.visibility, out.bent_normal), [depth, normals])
    eps, g = 1e-6, torch.Generator().manual_seed(1)
    for _ in range(4):
        u_depth = torch.randn(depth.shape, generator=g, dtype=torch.float64)
        u_normals = torch.randn(normals.shape, generator=g, dtype=torch.float64)
        with torch.no_grad():
            d64, n64 = depth.double(), normals.double()
            numerical = float(tensor_walk(d64 + eps * u_depth, n64 + eps * u_normals)
                              - tensor_walk(d64 - eps * u_depth, n64 - eps * u_normals)) / (2 * eps)
        terms = torch.cat(((g_depth.double() * u_depth).flatten(), (g_normals.double() * u_normals).flatten()))
        terms = terms[torch.isfinite(terms)]
        analytical, scale = float(terms.sum()), float(terms.abs().sum())
        assert abs(numerical) > 1e-2
        assert abs(analytical - numerical) <= 1e-4 * scale, (analytical, numerical, scale)


def test_the_module_runs_the_soft_kernel_for_bent_normals(built, monkeypatch):
    gb = FRAMES["rough"]()
    depth = gb.depth.clone().requires_grad_()
    graph = GBuffer(depth=depth, normals=gb.view_normals(), camera=gb.camera)
    for mode in ("soft", "straight_through"):
        assert soft_module.kernel_covers(BitmaskAO(mode=mode, bent_normals=True), graph) is None
    calls = count_kernel_calls(monkeypatch, "bitmask")
    out = BitmaskAO(mode="soft", slices=2, steps=3, bent_normals=True)(graph)
    (g_depth,) = torch.autograd.grad(out.bent_normal.sum(), [depth])
    assert calls == [1] and g_depth.abs().sum() > 0
