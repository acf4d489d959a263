"""The ``"ssilvb_glsl"`` variant in soft and straight-through mode in the kernel (soft_glsl.h: the shader's walk and
horizons with the soft union carried across slices; walk_grad.h's ``soft_grad_block`` of it, the slices walked back
last to first) against the tensor-op walk's autograd.

``"ieee"`` numerics against the float64 walk; ``"mesa"`` against the float32 walk (its quirks are float32
roundings), whose ``acos`` slopes are then cut as the float64 walk's are, beyond 1 - 1e-6 (``ops.clamped_gradient``
cuts them beyond 1 - 1e-4 in float32; the kernel follows the float64 rule): the variant's projected-normal angle is an ``acos`` of a cosine that is often within 1e-4 of 1 (a normal
facing the camera in the slice's plane), where its slope amplifies float32 rounding: on the rough frame the float32
tensor walk itself is 1.5e-5 from the float64 one in visibility and 2.5e-4 (relative) in the normals' gradient. So the
kernel (float32) is held to the float64 walk within 1e-5 / 1e-4, or within 1.5 times the float32 walk's own distance
from it where that is larger (measured: the kernel's is at most the float32 walk's). Also: with the thickness'
gradients alone, without any, against central differences of the float64 walk, and dispatch."""
import pytest
import torch

from kernel_agreement import assert_directional_derivatives, relative_error, use_scalar_lanes
from kernel_calls import count_kernel_calls
from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao import ops
from torch_ao.examples import floor_wall_gbuffer
from torch_ao.methods import bitmask_glsl
from torch_ao.gbuffer import GBuffer
import torch_ao.kernels.soft_bitmask as soft_module
import torch_ao.kernels.soft_glsl as glsl_module
from torch_ao.kernels import dispatch
from torch_ao.methods.bitmask import SSILVB, BitmaskAO
from torch_ao.thickness import BackfaceThickness, LinearThickness

SETTINGS = [
    dict(mode="soft", slices=3, steps=4),
    dict(mode="straight_through", slices=3, steps=4, tau=0.2),
    dict(mode="soft", slices=2, steps=5, jitter=False, rounding="floor", glsl_numerics="mesa", tau=0.3),
    # hitThickness read at each sample's texel: the back-face layer, the linear model in depth
    dict(mode="soft", slices=3, steps=4, thickness=lambda: BackfaceThickness(0.8, 0.05)),
    dict(mode="straight_through", slices=4, steps=3, rounding="round", thickness=lambda: LinearThickness(0.05, 0.1),
         glsl_numerics="mesa"),
    # a thickness growth (t times 1 + g |sample - pixel|): with a scalar, with the back-face layer
    dict(mode="soft", slices=3, steps=4, thickness_growth=0.6),
    dict(mode="straight_through", slices=3, steps=4, thickness=lambda: BackfaceThickness(0.8, 0.05, growth=0.5)),
]


def _leaves(dtype: torch.dtype):
    """A small rough frame's depth, perturbed unit normals and a light, as leaves in ``dtype`` (perturbed: with
    normals made from depth a nearest-fetched sender lies within rounding of its own tangent plane, on the facing
    factor's kink: tests/test_kernels_hard_gbuffer.py)."""
    gb0 = rough_gbuffer(18, 24)
    g = torch.Generator().manual_seed(3)
    normals = gb0.view_normals().double() + 0.3 * torch.randn(2, 3, 18, 24, generator=g, dtype=torch.float64)
    normals = torch.nn.functional.normalize(normals, dim=1)
    light = torch.rand(2, 3, 18, 24, generator=g, dtype=torch.float64)
    return [x.to(dtype).clone().requires_grad_() for x in (gb0.depth.double(), normals, light)], gb0.camera


def _module(setting: dict, backend: str, dtype: torch.dtype) -> SSILVB:
    setting = dict(setting)
    thickness = setting.pop("thickness", 0.3)
    return SSILVB(backend=backend, variant="ssilvb_glsl", thickness=thickness() if callable(thickness) else thickness,
                  trainable=True, **setting).to(dtype)


def _loss(out) -> torch.Tensor:
    """A loss weighing every pixel's visibility and light differently."""
    return sum((x * torch.linspace(-0.5, 1.5, x.numel(), dtype=x.dtype).view_as(x)).sum()
               for x in (out.visibility, out.indirect))


def _run(dtype, backend, setting, gbuffer=True):
    """Visibility, light and d loss / d (depth, normals, light, then the thickness model's parameters)."""
    (depth, normals, light), camera = _leaves(dtype)
    if not gbuffer:
        depth, normals, light = (x.detach() for x in (depth, normals, light))
    gb = GBuffer(depth=depth, normals=normals, light=light, camera=camera, backface_depth=1.2 * depth.detach())
    module = _module(setting, backend, dtype)
    if backend == "kernel":
        assert glsl_module.glsl_soft_covers(module, gb) is None
    out = module(gb)
    # (the thickness model's: the radius has none, the shader's texels are floored)
    parameters = [p for name, p in module.named_parameters() if p.requires_grad and name != "radius"]
    wrt = ([depth, normals, light] if gbuffer else []) + parameters
    grads = [g.double() for g in torch.autograd.grad(_loss(out), wrt)]
    return out.visibility.detach().double(), out.indirect.detach().double(), grads


def _clamped_as_float64(fn, x):
    """ops.clamped_gradient with the float64 walk's cut (1 - 1e-6) in any dtype."""
    value = fn(x)
    if not x.requires_grad:
        return value
    soft = fn(x.clamp(-1 + 1e-6, 1 - 1e-6))
    return value.detach() + (soft - soft.detach())


def _within(kernel: float, float32_walk: float, bound: float) -> bool:
    """The kernel's distance from the float64 walk within ``bound``, or within 1.5 times the float32 walk's."""
    return kernel <= max(bound, 1.5 * float32_walk)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_values_and_gradients_agree_with_the_tensor_walk(built, setting, lanes, monkeypatch):
    """Measured (ieee, 3 settings): visibility within 1.8e-5 of the float64 walk (the float32 walk: 1.8e-5), the light
    4e-7; gradients of depth 6.9e-5 relative (6.9e-5), normals 2.3e-4 (2.5e-4), the light 2.4e-7, the thickness' 1.1e-5;
    mesa (2 settings) against the float32 walk: within 3.4e-6 relative."""
    if lanes == "scalar":
        use_scalar_lanes(monkeypatch, soft_module)  # (the walk with gradients: soft_bitmask.gbuffer_walk)
    s = SETTINGS[setting]
    reference = torch.float64 if s.get("glsl_numerics", "ieee") == "ieee" else torch.float32
    if reference == torch.float32:
        for module in (ops, bitmask_glsl):
            monkeypatch.setattr(module, "clamped_gradient", _clamped_as_float64)
    vis0, light0, grads0 = _run(reference, "torch", s)
    vis, light, grads = _run(torch.float32, "kernel", s)
    vis32, light32, grads32 = _run(torch.float32, "torch", s) if reference == torch.float64 else (vis0, light0, grads0)
    assert light0.abs().max() > 0.05 and vis0.min() < 0.9
    assert _within(float((vis - vis0).abs().max()), float((vis32 - vis0).abs().max()), 1e-5)
    assert _within(float((light - light0).abs().max()), float((light32 - light0).abs().max()), 1e-5)
    names = ["depth", "normals", "light"] + [f"thickness {k}" for k in range(len(grads0) - 3)]
    for name, g, g0, g32 in zip(names, grads, grads0, grads32):
        assert g0.abs().sum() > 0, name
        assert _within(relative_error(g, g0), relative_error(g32, g0), 1e-4), (name, relative_error(g, g0),
                                                                              relative_error(g32, g0))


@pytest.mark.parametrize("setting", [0, 1, 3, 5, 6])
def test_thickness_gradients_alone_agree_with_the_tensor_walk(built, setting):
    """With no G-buffer gradient asked for, the thickness model's parameters get theirs through the backward's walk."""
    _, _, grads0 = _run(torch.float64, "torch", SETTINGS[setting], gbuffer=False)
    _, _, grads = _run(torch.float32, "kernel", SETTINGS[setting], gbuffer=False)
    for g, g0 in zip(grads, grads0):
        assert g0.abs().sum() > 0 and relative_error(g, g0) <= 1e-4, (g, g0)


def test_without_a_gradient_the_forward_agrees_with_the_tensor_walk(built):
    """Soft mode against the float64 walk; straight-through mode equals the hard kernel (its values)."""
    with torch.no_grad():
        (depth, normals, light), camera = _leaves(torch.float32)
        gb = GBuffer(depth=depth, normals=normals, light=light, camera=camera)
        (depth, normals, light), camera = _leaves(torch.float64)
        gb64 = GBuffer(depth=depth, normals=normals, light=light, camera=camera)
        soft = _module(SETTINGS[0], "kernel", torch.float32)(gb)
        ref = _module(SETTINGS[0], "torch", torch.float64)(gb64)
        assert (soft.visibility.double() - ref.visibility).abs().max() <= 3e-5
        assert (soft.indirect.double() - ref.indirect).abs().max() <= 1e-5
        straight = _module(SETTINGS[1], "kernel", torch.float32)(gb)
        hard = _module(dict(SETTINGS[1], mode="hard"), "kernel", torch.float32)(gb)
        assert torch.equal(straight.visibility, hard.visibility) and torch.equal(straight.indirect, hard.indirect)
        assert not torch.equal(soft.visibility, hard.visibility)


def test_gradients_match_central_differences_on_a_small_frame(built):
    """The kernel's derivative of the loss along random directions of depth, normals and the light against central
    differences (eps = 1e-6) of the float64 tensor-op forward, on an 8x10 frame of a floor meeting a wall."""
    gb0 = floor_wall_gbuffer(8, 10, wall_distance=1.0)[0]
    setting = dict(mode="soft", slices=2, steps=3, tau=0.5, radius=0.8, thickness=0.4)
    g = torch.Generator().manual_seed(2)
    light0 = torch.rand(1, 3, 8, 10, generator=g, dtype=torch.float64)
    normals0 = torch.nn.functional.normalize(gb0.view_normals().double() + 0.2 * torch.randn(
        1, 3, 8, 10, generator=g, dtype=torch.float64), dim=1)

    def tensor_walk(depth, normals, light):
        gb = GBuffer(depth=depth, normals=normals, light=light, camera=gb0.camera.to(dtype=torch.float64))
        return _loss(SSILVB(backend="torch", variant="ssilvb_glsl", **setting).double()(gb))

    leaves = [x.float().requires_grad_() for x in (gb0.depth.double(), normals0, light0)]
    module = SSILVB(backend="kernel", variant="ssilvb_glsl", **setting)
    grads = torch.autograd.grad(_loss(module(GBuffer(depth=leaves[0], normals=leaves[1], light=leaves[2],
                                                     camera=gb0.camera))), leaves)
    assert_directional_derivatives(grads, [x.double() for x in leaves], tensor_walk, lambda: [
        torch.randn(x.shape, generator=g, dtype=torch.float64) for x in leaves], eps=1e-6)


def test_the_module_runs_the_glsl_soft_kernel(built, monkeypatch):
    """BitmaskAO and SSILVB of the variant in soft mode, and straight-through with a gradient, go to this kernel."""
    (depth, normals, light), camera = _leaves(torch.float32)
    gb = GBuffer(depth=depth, normals=normals, light=light, camera=camera)
    calls = count_kernel_calls(monkeypatch, "bitmask", glsl_module.glsl_soft_covers)
    out = SSILVB(mode="straight_through", variant="ssilvb_glsl", slices=2, steps=3)(gb)
    g_depth, g_light = torch.autograd.grad(out.indirect.sum(), [depth, light])
    vis = BitmaskAO(mode="soft", variant="ssilvb_glsl", slices=2, steps=3)(gb).visibility
    assert calls == [1, 1] and g_depth.abs().sum() > 0 and g_light.abs().sum() > 0 and vis.min() < 1
    big = BitmaskAO(mode="soft", variant="ssilvb_glsl", slices=glsl_module.GLSL_MAX_SLICES + 1, steps=2)
    assert "slices=17" in glsl_module.glsl_soft_covers(big, gb)
    with pytest.raises(ValueError, match="backend"):
        dispatch.kernel_forward(big, gb, "kernel")
