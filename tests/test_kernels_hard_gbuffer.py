"""The hard sector kernel's G-buffer gradients (walk_grad.h's hard_grad_block: ``torch_ao_kernels::hard_backward``).

Hard masks have no derivative, but the cosine weights and the bent normals' directions follow the slice, so hard
``BitmaskAO`` with cosine weights or bent normals has gradients to the normals (and, through the view vector,
to a position buffer); the depth's is zero (scaling a pixel's depth moves it along its own ray). Indirect light
(``SSILVB``) has gradients to the light, the senders' normals and positions, and the radius. Against the tensor-op
walk's autograd in float64 on the rough frame: values within 1e-5, gradients within 1e-4 relative, in SIMD and
scalar lanes; directional derivatives against central differences; what it covers.

Indirect light's gradients are not compared with the nearest fetch: a sample's position is then its texel's, and
the sender's normal is made of its neighbours' positions, so the sample lies within rounding of the sender's
tangent plane and the facing factor ``clamp(dot(n, -l), 0, 1)`` sits on its kink (measured: the float32 and
float64 tensor walks 2-7 % apart, the left and right central differences of the float64 one 7x apart)."""
import pytest
import torch

from kernel_agreement import (assert_directional_derivatives, assert_hard_gradients_agree, position_gradients,
                              relative_error, use_scalar_lanes)
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import dispatch
from torch_ao.kernels.bitmask import kernel_covers
from torch_ao.methods.bitmask import SSILVB, BitmaskAO
from torch_ao.thickness import BackfaceThickness

SETTINGS = [
    dict(weighting="cosine"),
    dict(weighting="cosine", bent_normals=True, fetch="edge_aware", border="clamp"),
    dict(bent_normals=True, fetch="nearest", rounding="round", thickness=0.3),
    dict(weighting="cosine", noise="hilbert_r2", stagger=True, step_power=2.0, thickness=BackfaceThickness()),
    # (seed 2: with seeds 0 and 1 one sample of this frame lies within float32 rounding of a sector edge and its mask
    # flips, along view directions as well; a flipped sector moves the pixel's values by up to 0.03)
    dict(weighting="cosine", bent_normals=True, azimuth="screen", fetch="edge_aware", seed=2),
    # the "exact" variant's segment geometry with the sector union
    dict(weighting="cosine", bent_normals=True, clip_to_radius=True, thickness_direction="depth", sample_extent="sphere"),
    dict(variant="exact", union="sectors", bent_normals=True),
]


def outputs_and_grads(gb0: GBuffer, dtype: torch.dtype, backend: str, setting: dict, lanes: str = "simd"):
    """The visibility (and bent normals), and the gradients of a weighted sum of them with respect to depth and
    normals."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera, backface_depth=gb0.depth.detach() * 1.3)
    module = BitmaskAO(mode="hard", slices=3, steps=4, backend=backend, **setting).to(dtype)
    if backend == "kernel":
        assert kernel_covers(module, gb) is None
    out = module(gb)
    values = [out.visibility] + ([out.bent_normal] if out.bent_normal is not None else [])
    loss = sum((v * torch.linspace(-0.5, 1.5, v.numel(), dtype=dtype).view_as(v)).sum() for v in values)
    grads = torch.autograd.grad(loss, [depth, normals])
    return torch.cat(values, 1).detach().double(), [g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    if lanes == "scalar":  # the CUDA thread's walk (what tao_hard_backward compiles), on the CPU
        import torch_ao.kernels.bitmask as bitmask
        use_scalar_lanes(monkeypatch, bitmask)
    gb = FRAMES["rough"]()
    ref, (ref_depth, ref_normals) = outputs_and_grads(gb, torch.float64, "torch", SETTINGS[setting])
    out, (depth, normals) = outputs_and_grads(gb, torch.float32, "kernel", SETTINGS[setting])
    assert (out - ref).abs().max() <= 1e-5
    assert_hard_gradients_agree(depth, normals, ref_depth, ref_normals)


def test_position_buffer_gradient_equals_the_tensor_walk(built):
    """A position buffer (nearest fetch): the view vector, so the slices, follow it."""
    def loss(gb, dtype, backend):
        module = BitmaskAO(mode="hard", slices=3, steps=4, weighting="cosine", bent_normals=True, fetch="nearest",
                           backend=backend).to(dtype)
        out = module(gb)
        return out.visibility.sum() + out.bent_normal[:, 2].sum()

    grads = position_gradients(FRAMES["rough"](), loss)
    assert grads[0].abs().sum() > 0
    assert relative_error(grads[1], grads[0]) <= 1e-4


def test_gradients_match_central_differences(built):
    """The kernel's derivative along random directions of the normals against central differences (eps = 1e-7)
    of the float64 tensor-op forward on a small frame (no sector edge is crossed at that eps: the masks stay)."""
    gb0 = rough_gbuffer(28, 40, seed=5)
    normals0 = gb0.view_normals().detach()
    settings = dict(mode="hard", slices=2, steps=3, weighting="cosine", bent_normals=True)

    def tensor_walk(normals):
        out = BitmaskAO(backend="torch", **settings).double()(
            GBuffer(depth=gb0.depth.double(), normals=normals, camera=gb0.camera.to(dtype=torch.float64)))
        return out.visibility.sum() + (out.bent_normal * torch.linspace(-1, 1, 3, dtype=torch.float64).view(1, 3, 1, 1)).sum()

    normals = normals0.clone().requires_grad_()
    out = BitmaskAO(backend="kernel", **settings)(GBuffer(depth=gb0.depth, normals=normals, camera=gb0.camera))
    loss = out.visibility.sum() + (out.bent_normal * torch.linspace(-1, 1, 3).view(1, 3, 1, 1)).sum()
    grads = torch.autograd.grad(loss, [normals])
    g = torch.Generator().manual_seed(2)
    assert_directional_derivatives(grads, [normals0.double()], tensor_walk,
                                   lambda: [torch.randn(normals0.shape, generator=g, dtype=torch.float64)])


INDIRECT = [
    dict(weighting="cosine", fetch="edge_aware", bent_normals=True),
    dict(weighting="uniform", fetch="edge_aware", rounding="round"),
    dict(weighting="cosine", sector_epsilon=0.05),
    dict(weighting="cosine", azimuth="screen", seed=2),  # (seed 2: as SETTINGS' screen directions)
    dict(variant="exact", union="sectors", fetch="bilinear"),
]


def indirect_and_grads(gb0: GBuffer, dtype: torch.dtype, backend: str, setting: dict, intrinsics: bool = False):
    """SSILVB's visibility and indirect light in hard mode, and the gradients of a weighted sum of them with respect
    to depth, normals, the light and the radius (and with ``intrinsics`` the camera's (B, 3, 3))."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    light = torch.rand(gb0.depth.shape[0], 3, *gb0.depth.shape[-2:], generator=torch.Generator().manual_seed(1),
                       dtype=torch.float64).to(dtype).requires_grad_()
    K = gb0.camera.intrinsics.detach().clone().requires_grad_(intrinsics)
    module = SSILVB(mode="hard", slices=3, steps=4, backend=backend, **setting).to(dtype)
    gb = GBuffer(depth=depth, normals=normals, camera=PinholeCamera(K, gb0.camera.height, gb0.camera.width),
                 light=light)
    if backend == "kernel":
        assert kernel_covers(module, gb) is None
    out = module(gb)
    values = torch.cat([out.visibility, out.indirect], 1)
    loss = (values * torch.linspace(-0.5, 1.5, values.numel(), dtype=dtype).view_as(values)).sum()
    grads = torch.autograd.grad(loss, [depth, normals, light, module.radius] + ([K] if intrinsics else []))
    return values.detach().double(), [g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(INDIRECT)))
def test_indirect_light_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    """Measured: at most 2.7e-6 relative."""
    if lanes == "scalar":
        import torch_ao.kernels.bitmask as bitmask
        use_scalar_lanes(monkeypatch, bitmask)
    gb = FRAMES["rough"]()
    ref, ref_grads = indirect_and_grads(gb, torch.float64, "torch", INDIRECT[setting])
    out, grads = indirect_and_grads(gb, torch.float32, "kernel", INDIRECT[setting])
    assert ref[:, 1:].abs().max() > 0.01 and (out - ref).abs().max() <= 1e-5
    for name, g, r in zip(("depth", "normals", "light", "radius"), grads, ref_grads):
        assert r.abs().sum() > 0, name
        assert relative_error(g, r) <= 1e-4, (name, relative_error(g, r))


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(INDIRECT)))
def test_indirect_light_intrinsics_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    """Indirect light's samples move with the intrinsics (where they sample on screen: their positions, the
    senders' normals and light; a bilinear fetch's unprojection): the backward chains them by hand (walk.h's
    PlacementAdjoint, unprojection_camera, Sample::gather_slope), within 1e-4 relative of the float64 tensor walk."""
    if lanes == "scalar":
        import torch_ao.kernels.bitmask as bitmask
        use_scalar_lanes(monkeypatch, bitmask)
    gb = FRAMES["rough"]()
    _, ref_grads = indirect_and_grads(gb, torch.float64, "torch", INDIRECT[setting], intrinsics=True)
    _, grads = indirect_and_grads(gb, torch.float32, "kernel", INDIRECT[setting], intrinsics=True)
    assert ref_grads[-1].abs().max() > 1e-3
    for name, g, r in zip(("depth", "normals", "light", "radius", "intrinsics"), grads, ref_grads):
        assert relative_error(g, r) <= 1e-4, (name, relative_error(g, r))


def test_indirect_light_gradients_match_central_differences(built):
    """Directional derivatives along random directions of the normals and the light against central differences
    (eps = 1e-7) of the float64 tensor forward, edge-aware fetch (no sample exactly in its sender's plane). Not along
    the depth: moving every sample's angle flips some sector of some mask at any eps, a jump in the hard forward
    (the depth's gradient is compared with the float64 tensor walk's above)."""
    gb0 = rough_gbuffer(28, 40, seed=6)
    settings = dict(mode="hard", slices=2, steps=3, weighting="cosine", fetch="edge_aware")
    light0 = torch.rand(2, 3, 28, 40, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    base = [gb0.depth.double(), gb0.view_normals().detach().double(), light0]

    def tensor_walk(depth, normals, light):
        out = SSILVB(backend="torch", **settings).double()(
            GBuffer(depth=depth, normals=normals, light=light, camera=gb0.camera.to(dtype=torch.float64)))
        return out.indirect.sum()

    leaves = [x.float().clone().requires_grad_() for x in base]
    out = SSILVB(backend="kernel", **settings)(GBuffer(depth=leaves[0], normals=leaves[1], light=leaves[2],
                                                       camera=gb0.camera))
    grads = torch.autograd.grad(out.indirect.sum(), leaves)
    surface = torch.isfinite(gb0.depth) & (gb0.depth > 0)
    g = torch.Generator().manual_seed(3)

    def directions():  # (normals and light; the depth stays)
        us = [torch.where(surface, torch.randn(x.shape, generator=g, dtype=torch.float64), 0.0) for x in base]
        return [torch.zeros_like(us[0])] + us[1:]

    assert_directional_derivatives(grads, base, tensor_walk, directions)


@pytest.mark.parametrize("setting", [0, 1])
def test_intrinsics_gradients_equal_the_float64_tensor_walk(built, setting):
    """The slice's weights read the pixel's position, not the intrinsics (they move only the steps on screen, and
    the masks have no gradient): the intrinsics' gradient is the positions' own, chained by autograd through
    walk_inputs' unprojection. Cosine weights and bent normals, against the float64 tensor walk, on the pixels the
    walk computes (the background's bent normal is the G-buffer's own normal, filled in by the tensor path with
    that normal's history)."""
    def grads(dtype, backend):
        gb0 = FRAMES["rough"]().to(dtype=dtype)
        intrinsics = gb0.camera.intrinsics.detach().clone().requires_grad_()
        gb = GBuffer(depth=gb0.depth, camera=PinholeCamera(intrinsics, gb0.camera.height, gb0.camera.width))
        module = BitmaskAO(mode="hard", slices=3, steps=4, backend=backend, **SETTINGS[setting]).to(dtype)
        if backend == "kernel":
            assert kernel_covers(module, gb) is None
        out = module(gb)
        values = [out.visibility] + ([out.bent_normal] if out.bent_normal is not None else [])
        loss = sum((v * torch.linspace(-0.5, 1.5, v.numel(), dtype=dtype).view_as(v) * gb.valid).sum() for v in values)
        return torch.autograd.grad(loss, [intrinsics])[0].double()

    reference = grads(torch.float64, "torch")
    assert reference.abs().max() > 1e-3
    assert relative_error(grads(torch.float32, "kernel"), reference) <= 1e-4


# ------------------------------------------------------------------------------- what it covers
def test_the_auto_backend_takes_the_kernel(built, monkeypatch):
    gb = FRAMES["rough"]()
    depth = gb.depth.clone().requires_grad_()
    graph = GBuffer(depth=depth, camera=gb.camera)  # (normals from depth: their gradient reaches it)
    calls = []
    entries = list(dispatch.KERNELS["bitmask"])
    hard_covers, hard_run = entries[0]  # (the hard kernel: tried first)
    entries[0] = (hard_covers, lambda *a: calls.append("hard") or hard_run(*a))
    monkeypatch.setitem(dispatch.KERNELS, "bitmask", tuple(entries))
    module = BitmaskAO(mode="hard", slices=2, steps=3, weighting="cosine")
    (g_depth,) = torch.autograd.grad(module(graph).visibility.sum(), [depth])
    assert calls == ["hard"] and torch.isfinite(g_depth).all()
    light = GBuffer(depth=depth, camera=gb.camera, light=torch.rand(2, 3, *gb.depth.shape[-2:]))
    assert kernel_covers(SSILVB(mode="hard", slices=2, steps=3), light) is None  # (indirect light: the kernel's)
    assert kernel_covers(SSILVB(variant="ssilvb_glsl", slices=3, steps=3), light) is None  # (the shader's: its own)
    intrinsics = gb.camera.intrinsics.clone().requires_grad_()
    moving = GBuffer(depth=gb.depth, camera=PinholeCamera(intrinsics, gb.camera.height, gb.camera.width),
                     light=light.light)
    assert kernel_covers(module, moving) is None
    (g_fx,) = torch.autograd.grad(module(moving).visibility.sum(), [intrinsics])  # (the kernel: through the positions)
    assert calls == ["hard", "hard"] and g_fx.abs().sum() > 0
    assert kernel_covers(SSILVB(mode="hard", slices=2, steps=3), moving) is None


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
def test_bent_normals_of_the_background_pass_their_gradient_on(built, lanes, monkeypatch):
    """A background pixel's bent normal is its own normal (the view-facing default there, which follows the
    intrinsics): its gradient reaches the intrinsics through it, also where every pixel of a kernel's block is
    background (one pixel a block in scalar lanes, the CUDA thread's)."""
    if lanes == "scalar":
        import torch_ao.kernels.bitmask as bitmask
        use_scalar_lanes(monkeypatch, bitmask)

    def grads(dtype, backend):
        gb0 = FRAMES["rough"]().to(dtype=dtype)
        K = gb0.camera.intrinsics.detach().clone().requires_grad_()
        gb = GBuffer(depth=gb0.depth, camera=PinholeCamera(K, gb0.camera.height, gb0.camera.width))
        out = BitmaskAO(mode="hard", slices=3, steps=4, bent_normals=True, backend=backend).to(dtype)(gb)
        loss = (out.bent_normal * torch.linspace(-0.5, 1.5, out.bent_normal.numel(), dtype=dtype).view_as(
            out.bent_normal)).sum()
        return torch.autograd.grad(loss, [K])[0].double()

    assert (~FRAMES["rough"]().valid).sum() > 0
    reference = grads(torch.float64, "torch")
    assert relative_error(grads(torch.float32, "kernel"), reference) <= 1e-4
