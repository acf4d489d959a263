"""The ``"ssilvb_glsl"`` variant's indirect light backward in the hard kernel (walk_grad.h's ``hard_grad_block`` of
``GlslAccumulator``, through ``torch_ao_kernels::hard_record``/``hard_backward``).

The masks (so each step's weight) have no derivative and the shader's texels are floored, so the light's gradients
go to the light, the normals (the pixel's own and the senders') and the positions (so depth and intrinsics); none to
the radius or the thickness (the tensor path's autograd gives them none either). Against the tensor-op walk's
autograd: ``"ieee"`` numerics in float64, ``"mesa"`` in float32 (its quirks are float32 roundings: in float64
another pixel's mask differs); values within 1e-5, gradients within 1e-4 relative, in SIMD and scalar lanes; one
directional derivative against central differences; dispatch takes the kernel when a gradient is asked for.

The normals are an explicit, perturbed buffer: with normals made from depth a nearest-fetched sample lies within
rounding of its sender's tangent plane, and the facing factor sits on its kink (tests/test_kernels_hard_gbuffer.py).
On these frames and settings no mask flips between float32 and float64 (hard values agree to 1e-6)."""
import pytest
import torch

from kernel_agreement import relative_error
from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import dispatch
from torch_ao.kernels.bitmask import kernel_covers
from torch_ao.methods.bitmask import SSILVB
from torch_ao.thickness import BackfaceThickness, LinearThickness

SETTINGS = [
    dict(slices=3, steps=4, glsl_numerics="ieee"),
    # (radius 0.8: with 0.6 and 4 slices one sample of this frame lies within float32 rounding of a sector edge,
    # its mask flips between float32 and float64 and the light there moves by 0.07)
    dict(slices=4, steps=5, radius=0.8, thickness=0.3, rounding="round", glsl_numerics="ieee"),
    dict(slices=2, steps=5, jitter=False, rounding="floor", thickness=0.0, glsl_numerics="mesa"),
    # hitThickness read at each sample's texel: the back-face layer, the linear model in depth
    dict(slices=3, steps=4, thickness=BackfaceThickness(0.8, 0.05), glsl_numerics="ieee"),
    dict(slices=3, steps=4, thickness=LinearThickness(0.05, 0.1), glsl_numerics="mesa"),
]


def leaves(dtype: torch.dtype, intrinsics: bool = False):
    """A small rough frame's depth, perturbed unit normals, light (and intrinsics), as leaves in ``dtype``."""
    gb0 = rough_gbuffer(18, 24)
    g = torch.Generator().manual_seed(3)
    normals = gb0.view_normals().double() + 0.3 * torch.randn(2, 3, 18, 24, generator=g, dtype=torch.float64)
    normals = torch.nn.functional.normalize(normals, dim=1)
    light = torch.rand(2, 3, 18, 24, generator=g, dtype=torch.float64)
    K = gb0.camera.intrinsics.double()
    return [x.to(dtype).clone().requires_grad_(x is not K or intrinsics)
            for x in (gb0.depth.double(), normals, light, K)], gb0.camera


def light_and_grads(dtype, backend, setting, lanes="simd", intrinsics=False):
    (depth, normals, light, K), cam = leaves(dtype, intrinsics)
    gb = GBuffer(depth=depth, normals=normals, light=light, camera=PinholeCamera(K, cam.height, cam.width),
                 backface_depth=1.2 * depth.detach())
    module = SSILVB(mode="hard", backend=backend, variant="ssilvb_glsl", **setting).to(dtype)
    if backend == "kernel":
        assert kernel_covers(module, gb) is None
    if lanes == "scalar":  # the CUDA thread's arithmetic, on the CPU
        from torch_ao.kernels.bitmask import module_thickness, ssilvb_glsl_hard, thickness_options
        out = ssilvb_glsl_hard(gb, gb.view_normals(module.normals_method), slices=module.slices, steps=module.steps,
                               radius=module.radius, **thickness_options(module_thickness(module, gb)), jitter=module.jitter,
                               rounding=module.rounding, numerics=module.glsl_numerics, indirect=True, lanes="scalar")
    else:
        out = module(gb)
    weights = torch.linspace(-0.5, 1.5, out.indirect.numel(), dtype=torch.float64).view_as(out.indirect).to(dtype)
    targets = [depth, normals, light] + ([K] if intrinsics else [])
    grads = torch.autograd.grad((out.indirect * weights).sum(), targets)
    return out.indirect.detach().double(), [g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_light_and_gradients_agree_with_the_tensor_walk(built, setting, lanes):
    s = SETTINGS[setting]
    reference = torch.float64 if s["glsl_numerics"] == "ieee" else torch.float32
    ref, ref_grads = light_and_grads(reference, "torch", s, intrinsics=True)
    out, grads = light_and_grads(torch.float32, "kernel", s, lanes, intrinsics=True)
    assert ref.abs().max() > 0.01
    assert (out - ref).abs().max() <= 1e-5
    for name, g, r in zip(("depth", "normals", "light", "intrinsics"), grads, ref_grads):
        assert r.abs().max() > 0, name  # (every leaf has a gradient)
        assert relative_error(g, r) <= 1e-4, (name, relative_error(g, r))


@pytest.mark.parametrize("name", ["depth", "normals", "light"])
def test_a_directional_derivative_matches_central_differences(built, name):
    """d/d eps of the weighted light at x + eps v: the kernel's backward against the float64 tensor walk's central
    difference (the light is linear in the light; normals and depth move within the masks' flats at eps)."""
    setting = SETTINGS[0]
    base, cam = leaves(torch.float64)
    base = [x.detach() for x in base]
    index = ("depth", "normals", "light").index(name)
    v = torch.randn(base[index].shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    v = torch.where(torch.isfinite(base[index]), v, 0.0)

    def weighted(xs, dtype, backend):
        depth, normals, light, K = [x.to(dtype) for x in xs]
        gb = GBuffer(depth=depth, normals=normals, light=light, camera=PinholeCamera(K, cam.height, cam.width))
        out = SSILVB(mode="hard", backend=backend, variant="ssilvb_glsl", **setting).to(dtype)(gb).indirect
        return (out * torch.linspace(-0.5, 1.5, out.numel(), dtype=dtype).view_as(out)).sum()

    eps = 1e-6
    moved = [[x + sign * eps * v if k == index else x for k, x in enumerate(base)] for sign in (1, -1)]
    with torch.no_grad():
        central = (weighted(moved[0], torch.float64, "torch") - weighted(moved[1], torch.float64, "torch")) / (2 * eps)
    leaf = base[index].float().clone().requires_grad_()
    xs = [leaf if k == index else x.float() for k, x in enumerate(base)]
    assert kernel_covers(SSILVB(mode="hard", variant="ssilvb_glsl", **setting),
                         GBuffer(depth=xs[0], normals=xs[1], light=xs[2], camera=cam)) is None
    (g,) = torch.autograd.grad(weighted(xs, torch.float32, "kernel"), [leaf])
    along = float((g.double() * torch.where(torch.isfinite(g), v, 0.0)).nan_to_num().sum())
    assert abs(central) > 1e-3
    assert abs(along - float(central)) <= 1e-4 * abs(float(central)) + 1e-6, (along, float(central))


def test_dispatch_takes_the_kernel_when_a_gradient_is_asked_for(built, monkeypatch):
    (depth, normals, light, K), cam = leaves(torch.float32)
    calls = []
    entries = list(dispatch.KERNELS["bitmask"])
    hard_covers, hard_run = entries[0]  # (the hard kernel: tried first)
    entries[0] = (hard_covers, lambda *a: calls.append("hard") or hard_run(*a))
    monkeypatch.setitem(dispatch.KERNELS, "bitmask", tuple(entries))
    gb = GBuffer(depth=depth, normals=normals, light=light, camera=cam)
    module = SSILVB(mode="hard", variant="ssilvb_glsl", slices=3, steps=4)  # (backend "auto")
    assert kernel_covers(module, gb) is None
    g_light, g_depth = torch.autograd.grad(module(gb).indirect.sum(), [light, depth])
    assert calls == ["hard"] and g_light.abs().sum() > 0 and g_depth[torch.isfinite(g_depth)].abs().sum() > 0
    # what it still does not cover falls back with its reason
    assert "straight-through gradient" in kernel_covers(SSILVB(mode="straight_through", variant="ssilvb_glsl"), gb)
