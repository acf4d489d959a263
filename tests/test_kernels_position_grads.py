"""Gradients through a position buffer read between texels (``fetch="bilinear"`` or ``"edge_aware"``) in the CPU
kernels: ``walk.h``'s ``Sample::position_motion`` (the read's d / d su, sv: the radius' and the intrinsics' path) and
``walk_grad.h``'s ``scatter_position_taps`` (its four taps' positions, through their depths too), in every backward:
the hard walk's (cosine weights, bent normals, indirect light), the soft and straight-through one's, the exact
union's and the horizon walks'. Against the tensor path's autograd in float64, on tests/test_kernels_position_reads.py's
frame, whose buffer is not the unprojected depth (a kernel that differentiated the depth fetch sent its gradient to
the depth instead). The kernel must run: ``backend="kernel"`` raises where no kernel covers a call."""
import dataclasses

import pytest
import torch

import torch_ao
from kernel_agreement import relative_error, upstream_weights, use_scalar_lanes_in_every_kernel
from test_kernels import built  # noqa: F401  (the fixture)
from test_kernels_position_reads import moved_positions

MODULES = {
    "BitmaskAO hard cosine, bent normals": lambda backend, fetch: torch_ao.BitmaskAO(
        mode="hard", weighting="cosine", bent_normals=True, fetch=fetch, backend=backend),
    "SSILVB hard": lambda backend, fetch: torch_ao.SSILVB(mode="hard", fetch=fetch, backend=backend),
    "BitmaskAO soft": lambda backend, fetch: torch_ao.BitmaskAO(mode="soft", tau=0.3, fetch=fetch, backend=backend),
    "SSILVB soft, bent normals": lambda backend, fetch: torch_ao.SSILVB(
        mode="soft", tau=0.3, bent_normals=True, fetch=fetch, backend=backend),
    "BitmaskAO straight-through": lambda backend, fetch: torch_ao.BitmaskAO(
        mode="straight_through", tau=0.3, fetch=fetch, backend=backend),
    "BitmaskAO exact": lambda backend, fetch: torch_ao.BitmaskAO(variant="exact", fetch=fetch, backend=backend),
    "BitmaskAO exact, sector union": lambda backend, fetch: torch_ao.BitmaskAO(
        variant="exact", union="sectors", mode="hard", fetch=fetch, backend=backend),
    "GTAO": lambda backend, fetch: torch_ao.GTAO(fetch=fetch, bent_normals=True, backend=backend),
    "HBAO": lambda backend, fetch: torch_ao.HBAO(fetch=fetch, backend=backend),
    "SSAO": lambda backend, fetch: torch_ao.SSAO(fetch=fetch, backend=backend),
    "UE4SSAO": lambda backend, fetch: torch_ao.UE4SSAO(fetch=fetch, backend=backend),
}
# PSSAO is left out: its gradient to a position buffer is float32-limited in the tensor path itself (float32 against
# float64: 8 % relative on this frame, 22 % with the normals given, with the nearest fetch too), so neither path's
# float32 gradient is a reference for the other's.
#: the tolerance of a module's gradients where float32 alone is farther from float64 than 2e-4: UE4 SSAO's float32
#: tensor walk is 4.8e-4 off in the position gradient and 1.1e-3 in the radius' (its depth gradient 3.9e-4); the exact
#: geometry's hard sectors 1.5e-3 (a sector that float32 rounds the other way weighs its cosine share elsewhere)
TOLERANCE = {"UE4SSAO": 2e-3, "BitmaskAO exact, sector union": 2e-3}


def _loss(out) -> torch.Tensor:
    total = (out.visibility * upstream_weights(out.visibility)).sum()
    for field in ("indirect", "bent_normal"):
        value = getattr(out, field, None)
        if value is not None:
            total = total + (value * upstream_weights(value)).sum()
    return total


def _gradients(name: str, fetch: str, dtype: torch.dtype, backend: str, intrinsics: bool = False):
    """d loss / d the position buffer and d loss / d the radius (float64), of the module in ``dtype``; with
    ``intrinsics``, d loss / d the camera's intrinsics ``(B,3,3)`` in place of the radius'."""
    gb, _ = moved_positions()
    gb = gb.to(dtype)
    position = gb.position.detach().clone().requires_grad_()
    camera = gb.camera
    if intrinsics:
        camera = dataclasses.replace(camera, intrinsics=camera.intrinsics.detach().clone().requires_grad_())
    graded = torch_ao.GBuffer(depth=None, camera=camera, position=position, light=gb.light)
    module = MODULES[name](backend, fetch).to(dtype)
    loss = _loss(module(graded))
    other = camera.intrinsics if intrinsics else getattr(module, "radius", None)
    if other is None:
        return torch.autograd.grad(loss, [position])[0].double(), None
    g_position, g_other = torch.autograd.grad(loss, [position, other], allow_unused=True)
    if intrinsics:
        return g_position.double(), g_other.double()
    return g_position.double(), None if g_other is None else float(g_other)


@pytest.mark.parametrize("fetch", ["bilinear", "edge_aware"])
@pytest.mark.parametrize("name", MODULES)
def test_a_position_buffers_gradient_equals_the_float64_tensor_walk(built, name, fetch):
    reference, ref_radius = _gradients(name, fetch, torch.float64, "torch")
    kernel, radius = _gradients(name, fetch, torch.float32, "kernel")
    tolerance = TOLERANCE.get(name, 2e-4)
    assert reference.abs().sum() > 0
    assert relative_error(kernel, reference) <= tolerance, relative_error(kernel, reference)
    if ref_radius is not None and ref_radius != 0:  # (the radius' gradient, by its own path or Euler's identity)
        assert radius is not None and abs(radius - ref_radius) <= tolerance * abs(ref_radius), (radius, ref_radius)


@pytest.mark.parametrize("name", ["BitmaskAO soft", "GTAO"])
def test_scalar_lanes_give_the_simd_lanes_gradient(built, name, monkeypatch):
    simd, _ = _gradients(name, "edge_aware", torch.float32, "kernel")
    use_scalar_lanes_in_every_kernel(monkeypatch)
    scalar, _ = _gradients(name, "edge_aware", torch.float32, "kernel")
    assert relative_error(scalar, simd) <= 1e-5


@pytest.mark.parametrize("fetch", ["bilinear", "edge_aware"])
@pytest.mark.parametrize("name", ["BitmaskAO soft", "SSILVB hard", "GTAO"])
def test_the_intrinsics_move_the_read_only_where_it_unprojects(built, name, fetch):
    """With a position buffer the intrinsics move where each step samples (the read's motion), and the read itself
    only where the edge-aware fetch unprojects its one texel's depth (walk.h's unprojected_lanes)."""
    reference, ref_intrinsics = _gradients(name, fetch, torch.float64, "torch", intrinsics=True)
    kernel, intrinsics = _gradients(name, fetch, torch.float32, "kernel", intrinsics=True)
    assert ref_intrinsics.abs().sum() > 0
    assert relative_error(kernel, reference) <= 2e-4
    assert relative_error(intrinsics, ref_intrinsics) <= 2e-4, relative_error(intrinsics, ref_intrinsics)
