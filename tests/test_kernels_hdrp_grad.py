"""The hard kernel's G-buffer gradients of bitmask AO's ``"hdrp"`` variant (walk_grad.h's ``hard_grad_block`` of
``BitmaskAccumulator`` with ``SectorAngles::hdrp``: the slice ended again in the tangents of the walked slice's angle,
HDRP's frame ``gamma = -sign(n_p . T) fast_acos(cos n)`` evaluated in them by bitmask.h's ``hdrp_slice_angle``).

Hard masks have no derivative; the cosine weights, the bent normals' directions and (through the visibility) the
constant ambient follow HDRP's slice frame, and indirect light also its light, senders and samples. Against the
tensor-op walk's autograd in float64 (the specification): values within 1e-5, gradients within 1e-4 relative (depth,
normals, light, radius, intrinsics, a position buffer), SIMD and scalar lanes; directional derivatives against
central differences; dispatch takes the kernel with a gradient asked for. The tensor walk's ``safe_fast_acos`` has no
slope where ``1 - |cos n| < 1e-6`` (float64); the kernel's none there either. As in
tests/test_kernels_hard_gbuffer.py, indirect light is compared with bilinear and edge-aware fetches only."""
import warnings

import pytest
import torch

from kernel_agreement import (assert_directional_derivatives, assert_hard_gradients_agree, position_gradients,
                              relative_error, use_scalar_lanes)
from test_kernels import FRAMES, built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao.camera import PinholeCamera
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import bitmask, dispatch
from torch_ao.kernels.bitmask import kernel_covers
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.thickness import BackfaceThickness

SETTINGS = [
    dict(weighting="cosine"),
    dict(weighting="cosine", bent_normals=True, fetch="edge_aware", border="clamp", ambient=(0.2, 0.5, 1.0)),
    dict(bent_normals=True, fetch="nearest", rounding="round", thickness=0.3),
    dict(weighting="cosine", noise="hilbert_r2", stagger=True, step_power=2.0, thickness=BackfaceThickness()),
    dict(weighting="cosine", bent_normals=True, azimuth="view", fetch="edge_aware", sector_epsilon=0.01),
]
INDIRECT = [
    dict(weighting="cosine", fetch="edge_aware", bent_normals=True),
    dict(weighting="uniform", fetch="edge_aware", rounding="round"),
    dict(weighting="cosine", azimuth="view", sector_epsilon=0.05),
]


def outputs_and_grads(gb0: GBuffer, dtype: torch.dtype, backend: str, setting: dict, indirect: bool = False):
    """The hdrp variant's outputs in hard mode (visibility, and the indirect light, bent normals, ambient asked for)
    and the gradients of a weighted sum of them to depth, normals, the intrinsics (B, 3, 3) and, with indirect
    light, the light and the radius."""
    gb0 = gb0.to(dtype=dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    K = gb0.camera.intrinsics.detach().clone().requires_grad_()
    light = torch.rand(gb0.depth.shape[0], 3, *gb0.depth.shape[-2:], generator=torch.Generator().manual_seed(1),
                       dtype=torch.float64).to(dtype).requires_grad_(indirect)
    module = BitmaskAO(variant="hdrp", mode="hard", slices=3, steps=4, backend=backend, indirect=indirect,
                       **setting).to(dtype)
    gb = GBuffer(depth=depth, normals=normals, camera=PinholeCamera(K, gb0.camera.height, gb0.camera.width),
                 backface_depth=gb0.depth.detach() * 1.3, light=light)
    if backend == "kernel":
        assert kernel_covers(module, gb) is None
    out = module(gb)
    values = torch.cat([v for v in (out.visibility, out.indirect, out.bent_normal, out.ambient) if v is not None], 1)
    # (on the pixels the walk computes: the background's bent normal is the G-buffer's own normal, which the tensor
    # path fills in with that normal's history; tests/test_kernels_hard_gbuffer.py's intrinsics test)
    weights = torch.linspace(-0.5, 1.5, values.numel(), dtype=dtype).view_as(values) * gb.valid
    loss = (values * weights).sum()
    leaves = [depth, normals, K] + ([light, module.radius] if indirect else [])
    grads = torch.autograd.grad(loss, leaves)
    return values.detach().double(), [g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    if lanes == "scalar":
        use_scalar_lanes(monkeypatch, bitmask)  # (what tao_record_hard / tao_hard_backward compile)
    gb = FRAMES["rough"]()
    ref, (ref_depth, ref_normals, ref_K) = outputs_and_grads(gb, torch.float64, "torch", SETTINGS[setting])
    out, (depth, normals, K) = outputs_and_grads(gb, torch.float32, "kernel", SETTINGS[setting])
    assert (out - ref).abs().max() <= 1e-5
    assert_hard_gradients_agree(depth, normals, ref_depth, ref_normals)
    assert ref_K.abs().max() > 1e-3 and relative_error(K, ref_K) <= 1e-4, relative_error(K, ref_K)


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("setting", range(len(INDIRECT)))
def test_indirect_light_gradients_equal_the_float64_tensor_walk(built, setting, lanes, monkeypatch):
    if lanes == "scalar":
        use_scalar_lanes(monkeypatch, bitmask)  # (what tao_record_hard / tao_hard_backward compile)
    gb = FRAMES["rough"]()
    ref, ref_grads = outputs_and_grads(gb, torch.float64, "torch", INDIRECT[setting], indirect=True)
    out, grads = outputs_and_grads(gb, torch.float32, "kernel", INDIRECT[setting], indirect=True)
    assert ref[:, 1:4].abs().max() > 0.01 and (out - ref).abs().max() <= 1e-5
    for name, g, r in zip(("depth", "normals", "intrinsics", "light", "radius"), grads, ref_grads):
        assert r.abs().sum() > 0, name
        assert relative_error(g, r) <= 1e-4, (name, relative_error(g, r))


def test_position_buffer_gradient_equals_the_tensor_walk(built):
    """A position buffer (nearest fetch): the view vector, so HDRP's slice frame, follows it."""
    def loss(gb, dtype, backend):
        module = BitmaskAO(variant="hdrp", mode="hard", slices=3, steps=4, weighting="cosine", bent_normals=True,
                           fetch="nearest", backend=backend).to(dtype)
        out = module(gb)
        return out.visibility.sum() + out.bent_normal[:, 2].sum()

    grads = position_gradients(FRAMES["rough"](), loss)
    assert grads[0].abs().sum() > 0
    assert relative_error(grads[1], grads[0]) <= 1e-4


def test_gradients_match_central_differences(built, monkeypatch):
    """The kernel's derivative along random directions of the normals and the light against central differences
    (eps = 1e-7) of the float64 tensor-op forward on a small frame (no sector edge is crossed at that eps). On a frame
    where no slice's normal lies within 1e-6 of V in cosine (|gamma| > 1.5e-3 and < pi - 1.5e-3): there the tensor
    walk's ``safe_fast_acos`` (and so the kernel) gives the slice angle no slope, where the angle has one (-1 as
    1 - |cos n| -> 0): on the 28 x 40 frame of tests/test_kernels_hard_gbuffer.py two slices do, and the bent normal's
    directional derivative differs from the central difference by 12 %."""
    import math

    from torch_ao.methods.bitmask import HDRPAccumulator

    gammas = []
    slice_frame = HDRPAccumulator.slice_frame
    monkeypatch.setattr(HDRPAccumulator, "slice_frame",
                        lambda self, q, geom: gammas.append(slice_frame(self, q, geom)) or gammas[-1])
    gb0 = rough_gbuffer(20, 28, seed=6)
    settings = dict(variant="hdrp", mode="hard", slices=2, steps=3, weighting="cosine", bent_normals=True,
                    indirect=True, fetch="edge_aware")
    light0 = torch.rand(2, 3, 20, 28, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    base = [gb0.view_normals().detach().double(), light0]
    bent_weights = torch.linspace(-1, 1, 3, dtype=torch.float64).view(1, 3, 1, 1)

    def weighted(out):
        return out.visibility.sum() + out.indirect.sum() + (out.bent_normal * bent_weights.to(out.visibility)).sum()

    def tensor_walk(normals, light):
        return weighted(BitmaskAO(backend="torch", **settings).double()(
            GBuffer(depth=gb0.depth.double(), normals=normals, light=light, camera=gb0.camera.to(dtype=torch.float64))))

    with torch.no_grad():
        tensor_walk(*base)
    angles = torch.cat([gamma.abs().flatten() for gamma, _, _ in gammas])
    assert angles.numel() > 1000 and 1.5e-3 < angles.min() and angles.max() < math.pi - 1.5e-3
    leaves = [x.float().clone().requires_grad_() for x in base]
    out = BitmaskAO(backend="kernel", **settings)(GBuffer(depth=gb0.depth, normals=leaves[0], light=leaves[1],
                                                          camera=gb0.camera))
    grads = torch.autograd.grad(weighted(out), leaves)
    surface = torch.isfinite(gb0.depth) & (gb0.depth > 0)
    g = torch.Generator().manual_seed(2)
    assert_directional_derivatives(grads, base, tensor_walk, lambda: [
        torch.where(surface, torch.randn(x.shape, generator=g, dtype=torch.float64), 0.0) for x in base])


def test_dispatch_takes_the_kernel_when_a_gradient_is_asked_for(built, monkeypatch):
    calls = []
    entries = list(dispatch.KERNELS["bitmask"])
    hard_covers, hard_run = entries[0]  # (the hard kernel: tried first)
    entries[0] = (hard_covers, lambda *a: calls.append("hard") or hard_run(*a))
    monkeypatch.setitem(dispatch.KERNELS, "bitmask", tuple(entries))
    gb0 = FRAMES["rough"]()
    depth = gb0.depth.clone().requires_grad_()
    light = torch.rand(2, 3, *gb0.depth.shape[-2:]).requires_grad_()
    gb = GBuffer(depth=depth, camera=gb0.camera, light=light)  # (normals from depth: their gradient reaches it)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (a kernel that could not be built would fall back with a warning)
        for backend in ("auto", "kernel"):
            module = BitmaskAO(variant="hdrp", mode="hard", slices=2, steps=3, weighting="cosine", bent_normals=True,
                               indirect=True, ambient=(0.2, 0.5, 1.0), backend=backend)
            assert kernel_covers(module, gb) is None
            out = module(gb)
            loss = out.visibility.sum() + out.indirect.sum() + out.bent_normal.sum() + out.ambient.sum()
            g_depth, g_light, g_radius = torch.autograd.grad(loss, [depth, light, module.radius])
            assert torch.isfinite(g_depth).all() and g_depth.abs().sum() > 0
            assert g_light.abs().sum() > 0 and g_radius != 0
    assert calls == ["hard", "hard"]
