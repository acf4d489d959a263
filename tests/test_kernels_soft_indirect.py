"""Indirect light of the soft / straight-through kernel (``SSILVB(mode="soft" | "straight_through")``: soft.h's
forward sends each step's light times the share it newly occludes; its backward runs the reverse scan with each
step's gain, soft_union's ``D_m = S_{m+1} - gn_m omega``, and replays each step's light for the gradients of its
light, its sender's normal, its position and the pixel's normal) against the tensor-op walk's autograd in float64:
the visibility and the light within 1e-5 (straight-through's hard sectors on 99.9 % of the pixels), gradients of
depth, normals, the light, radius and thickness within 1e-4 relative, in SIMD and scalar lanes; with the parameters'
gradients alone and with none; directional derivatives against central differences; and that the module's call runs
the kernel.

The gradients of the nearest fetch and of a clamped border are not compared, their values are: a nearest sample sits
on the facing factor's kink (tests/test_kernels_hard_gbuffer.py), and a clamped sample past the edge lands on the edge
texel, for a pixel on the edge next to its own, where the sender's direction is that of a near-zero offset (measured,
a rough-frame pixel on the edge: the float64 tensor walk's autograd -0.043, its own central differences 0.057 at eps
1e-4 to 1e-6)."""
import pytest
import torch

from kernel_agreement import assert_values_agree, relative_error, use_scalar_lanes
from kernel_calls import count_kernel_calls
from test_kernels import FRAMES, built, pytestmark  # noqa: F401 (the fixture, the skip)
from test_kernels_soft import _one_sector
from torch_ao.camera import PinholeCamera
from torch_ao.examples import floor_wall_gbuffer
from torch_ao.gbuffer import GBuffer
import torch_ao.kernels.soft_bitmask as soft_module
from torch_ao.methods.bitmask import SSILVB
from torch_ao.thickness import BackfaceThickness

#: soft and straight-through, uniform and cosine, bilinear and edge-aware fetches, the hdrp variant, bent normals
#: beside the light, the back-face layer
INDIRECT_SETTINGS = [dict(mode="soft", slices=3, steps=4),
                     dict(mode="soft", slices=3, steps=4, weighting="cosine", fetch="edge_aware"),
                     dict(mode="straight_through", slices=3, steps=3, weighting="cosine", tau=0.2, rounding="round"),
                     dict(mode="soft", slices=2, steps=3, variant="hdrp", weighting="cosine", bent_normals=True),
                     dict(mode="straight_through", slices=2, steps=3, variant="hdrp", azimuth="screen"),
                     dict(mode="soft", slices=2, steps=5, tau=0.2, bent_normals=True, noise="hilbert_r2", stagger=True),
                     dict(mode="soft", slices=3, steps=3, weighting="cosine", thickness="backface")]


def _module(settings: dict, backend: str, dtype: torch.dtype) -> SSILVB:
    settings = dict(settings)
    if settings.get("thickness") == "backface":
        settings["thickness"] = BackfaceThickness(0.8, 0.15)
    return SSILVB(backend=backend, **settings).to(dtype)


def _gbuffer(gb0: GBuffer, dtype: torch.dtype, grad: bool):
    """The rough frame with a random light (and a back-face layer 0.3 behind), its depth, normals and light leaves."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_(grad)
    normals = gb0.view_normals().detach().clone().requires_grad_(grad)
    light = torch.rand(gb0.depth.shape[0], 3, *gb0.depth.shape[-2:], generator=torch.Generator().manual_seed(1),
                       dtype=torch.float64).to(dtype).requires_grad_(grad)
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera, light=light,
                 backface_depth=gb0.depth.detach() + 0.3)
    return gb, [depth, normals, light]


def _loss(out) -> torch.Tensor:
    """A loss weighing every pixel's visibility, light (and bent normal) differently."""
    parts = [out.visibility, out.indirect] + ([out.bent_normal] if out.bent_normal is not None else [])
    return sum((x * torch.linspace(-0.5, 1.5, x.numel(), dtype=x.dtype).view_as(x)).sum() for x in parts)


def _values_and_grads(dtype: torch.dtype, backend: str, settings: dict, gbuffer: bool = True):
    """Visibility, light and d loss / d (depth, normals, light, radius, thickness) (with ``gbuffer`` False only the
    parameters'): the tensor path (``backend="torch"``) or the kernel."""
    gb, leaves = _gbuffer(FRAMES["rough"](), dtype, gbuffer)
    module = _module(settings, backend, dtype)
    if backend == "kernel":
        assert soft_module.kernel_covers(module, gb) is None
    out = module(gb)
    wrt = (leaves if gbuffer else []) + [module.radius, module.thickness]  # (the back-face model's offset too)
    grads = torch.autograd.grad(_loss(out), wrt, allow_unused=True)
    grads = [None] * 3 * (not gbuffer) + [None if g is None else g.double() for g in grads]
    return out.visibility.detach().double(), out.indirect.detach().double(), grads


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(INDIRECT_SETTINGS)))
def test_indirect_light_and_gradients_equal_the_float64_tensor_walk(built, lanes, setting, monkeypatch):
    """Measured (14 cases): the light within 6.4e-7 on 99.9 % of the pixels; gradients of depth within 3.3e-5
    relative, normals 1.9e-5, the light 1.6e-6, radius 6.4e-6, thickness 2.2e-5."""
    if lanes == "scalar":
        use_scalar_lanes(monkeypatch, soft_module)
    settings = INDIRECT_SETTINGS[setting]
    vis0, light0, grads0 = _values_and_grads(torch.float64, "torch", settings)
    vis, light, grads = _values_and_grads(torch.float32, "kernel", settings)
    valid = FRAMES["rough"]().valid
    assert light0.abs().max() > 0.05
    assert_values_agree(vis, vis0, valid, bound=_one_sector(settings["slices"]))
    assert_values_agree(light, light0, valid, bound=0.05)
    trim = 1e-3 if settings["mode"] == "straight_through" else 0.0  # (a pixel whose hard sectors flipped)
    for name, g, g0 in zip(("depth", "normals", "light", "radius", "thickness"), grads, grads0):
        assert g0.abs().sum() > 0, name
        assert relative_error(g, g0, trim if g0.dim() else 0.0) <= 1e-4, (name, relative_error(g, g0, trim))


@pytest.mark.parametrize("setting", [0, 2, 6])
def test_parameter_gradients_alone_equal_the_float64_tensor_walk(built, setting):
    """With no G-buffer gradient asked for, radius and thickness still get theirs through the backward's walk."""
    settings = INDIRECT_SETTINGS[setting]
    _, _, grads0 = _values_and_grads(torch.float64, "torch", settings, gbuffer=False)
    _, _, grads = _values_and_grads(torch.float32, "kernel", settings, gbuffer=False)
    for name, g, g0 in zip(("radius", "thickness"), grads[3:], grads0[3:]):
        assert g0 != 0 and abs(float(g - g0)) <= 1e-4 * abs(float(g0)), (name, float(g), float(g0))


def test_without_a_gradient_the_forward_equals_the_tensor_walk(built):
    """Every fetch, the nearest one too, and a clamped border."""
    for settings in (INDIRECT_SETTINGS[0], INDIRECT_SETTINGS[2], dict(mode="soft", slices=3, steps=4, border="clamp"),
                     dict(mode="straight_through", slices=2, steps=3, fetch="nearest", border="clamp")):
        with torch.no_grad():
            gb, _ = _gbuffer(FRAMES["rough"](), torch.float64, False)
            ref = _module(settings, "torch", torch.float64)(gb)
            gb, _ = _gbuffer(FRAMES["rough"](), torch.float32, False)
            out = _module(settings, "kernel", torch.float32)(gb)
        assert ref.indirect.abs().max() > 0.05
        assert_values_agree(out.indirect.double(), ref.indirect, gb.valid, bound=0.05)
        assert torch.equal(out.indirect[~gb.valid.expand_as(out.indirect)], torch.zeros(()).expand(
            int((~gb.valid.expand_as(out.indirect)).sum())))  # (background: no light)


@pytest.mark.parametrize("setting", [0, 1])
def test_intrinsics_gradients_equal_the_float64_tensor_walk(built, setting):
    """The light's samples move with the intrinsics (where they sample on screen: their positions, the senders'
    normals and light read there): the intrinsics' gradients per image, the depth's and radius' beside them, within
    1e-4 relative (measured: 3.9e-7, 1.7e-5, 2.5e-7)."""
    def grads(dtype, backend):
        gb0 = FRAMES["rough"]().to(dtype=dtype)
        depth = gb0.depth.detach().clone().requires_grad_()
        K = gb0.camera.intrinsics.detach().clone().requires_grad_()
        _, (_, _, light) = _gbuffer(gb0, dtype, False)
        gb = GBuffer(depth=depth, normals=gb0.view_normals().detach(), light=light,
                     camera=PinholeCamera(K, gb0.camera.height, gb0.camera.width))
        module = _module(INDIRECT_SETTINGS[setting], backend, dtype)
        return [g.double() for g in torch.autograd.grad(_loss(module(gb)), [K, depth, module.radius])]

    reference, kernel = grads(torch.float64, "torch"), grads(torch.float32, "kernel")
    assert reference[0].abs().max() > 1e-2
    for name, g, g0 in zip(("intrinsics", "depth", "radius"), kernel, reference):
        assert relative_error(g, g0) <= 1e-4, (name, relative_error(g, g0))


def test_gradients_match_central_differences_on_a_small_frame(built):
    """gradcheck's fast mode by hand: the soft kernel's derivative of the loss along random directions of depth,
    normals and the light against central differences (eps = 1e-6) of the float64 tensor-op forward, on an 8x10
    frame of a floor meeting a wall with clamped borders."""
    gb0 = floor_wall_gbuffer(8, 10, wall_distance=1.0)[0]
    settings = dict(mode="soft", slices=2, steps=3, tau=0.5, border="clamp", radius=0.8, thickness=0.4)
    light0 = torch.rand(1, 3, 8, 10, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def tensor_walk(depth, normals, light):
        gb = GBuffer(depth=depth, normals=normals, light=light, camera=gb0.camera.to(dtype=torch.float64))
        return _loss(SSILVB(backend="torch", **settings).double()(gb))

    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    light = light0.float().requires_grad_()
    out = SSILVB(backend="kernel", **settings)(GBuffer(depth=depth, normals=normals, light=light, camera=gb0.camera))
    leaves = [depth, normals, light]
    grads = torch.autograd.grad(_loss(out), leaves)
    eps, g = 1e-6, torch.Generator().manual_seed(1)
    for _ in range(4):
        u = [torch.randn(x.shape, generator=g, dtype=torch.float64) for x in leaves]
        with torch.no_grad():
            at = [x.double() for x in leaves]
            numerical = float(tensor_walk(*(x + eps * d for x, d in zip(at, u)))
                              - tensor_walk(*(x - eps * d for x, d in zip(at, u)))) / (2 * eps)
        terms = torch.cat([(gr.double() * d).flatten() for gr, d in zip(grads, u)])
        terms = terms[torch.isfinite(terms)]
        analytical, scale = float(terms.sum()), float(terms.abs().sum())
        assert abs(numerical) > 1e-2
        assert abs(analytical - numerical) <= 1e-4 * scale, (analytical, numerical, scale)


def test_the_module_runs_the_soft_kernel_for_indirect_light(built, monkeypatch):
    gb, (depth, _, light) = _gbuffer(FRAMES["rough"](), torch.float32, True)
    for mode in ("soft", "straight_through"):
        assert soft_module.kernel_covers(SSILVB(mode=mode), gb) is None
    calls = count_kernel_calls(monkeypatch, "bitmask")
    out = SSILVB(mode="soft", slices=2, steps=3)(gb)
    g_depth, g_light = torch.autograd.grad(out.indirect.sum(), [depth, light])
    assert calls == [1] and g_depth.abs().sum() > 0 and g_light.abs().sum() > 0
