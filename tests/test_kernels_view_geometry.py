"""The kernels' one-pass view geometry (geometry_cpu.cpp: ``torch_ao_kernels::view_geometry`` and its backward,
:func:`torch_ao.kernels.frame.view_geometry`) against the tensor ops it stands for (``GBuffer.positions``,
``GBuffer.view_normals`` of a G-buffer with normals): values and gradients to depth and normals, on frames with
background, normals facing away from the camera, huge and short normals, and two cameras; where it applies
and where the tensor ops run; a kernel call with G-buffer gradients through it."""
import math

import pytest
import torch

from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401 (the fixture, the skip)
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels.frame import view_geometry, walk_inputs
from torch_ao.methods.gtao import GTAO


def awkward_gbuffer() -> GBuffer:
    """rough_gbuffer's depth (background holes, two cameras) with given normals: random directions (half of them
    facing away from the camera), a huge one (1e20, whose square overflows), a short one and a non-finite one on
    background (GBuffer refuses normals shorter than 1e-6 on valid pixels)."""
    gb = rough_gbuffer()
    g = torch.Generator().manual_seed(3)
    normals = torch.randn(gb.depth.shape[0], 3, *gb.depth.shape[2:], generator=g)
    normals[0, :, 11, 10] = torch.tensor([2e-6, -3e-6, 1e-6])
    normals[1, :, 12, 40] = torch.tensor([-1e20, 3e20, 5e19])
    normals[1, :, 0, 0] = math.nan  # (a background pixel: its normal is never read)
    return GBuffer(depth=gb.depth, normals=normals, camera=gb.camera)


def geometry_and_grads(gb0: GBuffer, fused: bool):
    """Positions and view normals ``(B,H,W,3)`` as walk_inputs hands them to a kernel, and the gradients of a
    weighted sum of them (and of the depth and inverse depth) to the depth and the normals."""
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.normals.detach().clone().requires_grad_()
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera)
    with gb.one_call():
        if fused:
            view_geometry(gb, "improved")
        positions, unit, inverse, depth_nan, valid, _ = walk_inputs(gb, gb.view_normals("improved"))
    weights = [torch.linspace(-1.0, 2.0, x.numel()).view_as(x) for x in (positions, unit, inverse, depth_nan)]
    loss = sum((torch.where(torch.isfinite(x), x, 0.0) * w).sum()
               for x, w in zip((positions, unit, inverse, depth_nan), weights))
    grads = torch.autograd.grad(loss, [depth, normals])
    return positions.detach(), unit.detach(), grads


def test_values_and_gradients_equal_the_tensor_ops(built):
    gb = awkward_gbuffer()
    pos, unit, (g_depth, g_normals) = geometry_and_grads(gb, fused=False)
    pos_f, unit_f, (g_depth_f, g_normals_f) = geometry_and_grads(gb, fused=True)
    torch.testing.assert_close(pos_f, pos, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(unit_f, unit, rtol=1e-6, atol=1e-6)
    assert torch.isfinite(g_depth_f).all() and torch.isfinite(g_normals_f).all()
    torch.testing.assert_close(g_depth_f, g_depth, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(g_normals_f, g_normals, rtol=1e-5, atol=1e-5)
    # the awkward pixels were there to be met: a flipped normal, the scaled ones unit length, none on background
    flipped = (unit_f * gb.normals.permute(0, 2, 3, 1)).sum(-1) < 0
    assert flipped[gb.valid[:, 0]].any() and (~flipped[gb.valid[:, 0]]).any()
    torch.testing.assert_close(unit_f[1, 12, 40].norm(), torch.tensor(1.0))
    torch.testing.assert_close(unit_f[0, 11, 10].norm(), torch.tensor(1.0))
    assert (g_normals_f[~gb.valid.expand(-1, 3, -1, -1)] == 0).all()


def test_it_applies_only_where_a_kernel_call_records_gradients(built):
    gb0 = awkward_gbuffer()

    def fused(gb: GBuffer, **kwargs) -> bool:
        with torch.set_grad_enabled(kwargs.get("grad", True)), gb.one_call():
            view_geometry(gb, "improved")
            node = gb.view_normals("improved").grad_fn
        return node is not None and any("ViewGeometry" in type(f).__name__ for f, _ in node.next_functions)

    depth = gb0.depth.clone().requires_grad_()
    assert fused(GBuffer(depth=depth, normals=gb0.normals, camera=gb0.camera))
    assert not fused(GBuffer(depth=depth, normals=gb0.normals, camera=gb0.camera), grad=False)
    assert not fused(GBuffer(depth=gb0.depth, normals=gb0.normals, camera=gb0.camera))  # (cached once per G-buffer)
    camera64 = gb0.camera.to(dtype=torch.float64)
    assert not fused(GBuffer(depth=depth.double(), normals=gb0.normals.double(), camera=camera64))
    assert not fused(GBuffer(depth=depth, camera=gb0.camera))  # normals from depth
    intrinsics = gb0.camera.intrinsics.clone().requires_grad_()
    camera = type(gb0.camera)(intrinsics, gb0.camera.height, gb0.camera.width)
    assert not fused(GBuffer(depth=depth, normals=gb0.normals, camera=camera))
    gb = GBuffer(depth=depth, normals=gb0.normals, camera=gb0.camera)
    with gb.one_call():  # (within a call, once: the first call's buffers stand)
        first = gb.positions()
        view_geometry(gb, "improved")
        assert gb.positions() is first


def test_a_kernel_call_with_gbuffer_gradients_goes_through_it(built):
    gb0 = awkward_gbuffer()
    grads = {}
    for backend in ("kernel", "torch"):
        depth, normals = gb0.depth.clone().requires_grad_(), gb0.normals.clone().requires_grad_()
        gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera)
        vis = GTAO(slices=3, steps=4, backend=backend)(gb).visibility
        if backend == "kernel":
            seen, stack = set(), [vis.grad_fn]
            while stack:
                f = stack.pop()
                if f is not None and f not in seen:
                    seen.add(f)
                    stack.extend(g for g, _ in f.next_functions)
            assert "_ViewGeometryBackward" in {type(f).__name__ for f in seen}
        grads[backend] = torch.autograd.grad(vis.sum(), [depth, normals])
    for kernel, tensor in zip(grads["kernel"], grads["torch"]):
        torch.testing.assert_close(kernel, tensor, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("name", ["depth", "normals", "valid", "intrinsics"])
def test_bad_inputs_name_the_argument(built, name):
    gb = awkward_gbuffer()
    B, _, H, W = gb.depth.shape
    args = dict(depth=gb.depth.contiguous(), normals=gb.normals.contiguous(), valid=gb.valid.contiguous(),
                intrinsics=torch.ones(B, 4))
    args[name] = args[name][..., :-1] if name != "intrinsics" else torch.ones(B, 3)
    with pytest.raises(RuntimeError, match=name):
        torch.ops.torch_ao_kernels.view_geometry(**args)


def test_scale_derivative_equals_its_tensor_ops(built):
    """torch_ao_kernels::scale_derivative (float32 CPU pairs, one pass) against frame.scale_derivative's tensor
    ops (the definition, run here on float64 copies): NaN inputs on invalid pixels are left out, three channels and
    one per pixel, any number of threads."""
    from torch_ao.kernels.frame import scale_derivative

    g = torch.Generator().manual_seed(5)
    valid = torch.rand(2, 37, 301, generator=g) > 0.2  # (more pixels than one of the op's pieces)
    positions = torch.where(valid[..., None], torch.randn(2, 37, 301, 3, generator=g), torch.nan)
    depth = torch.where(valid, torch.rand(2, 37, 301, generator=g) + 0.5, torch.nan)
    g_pos, g_depth = torch.randn(2, 37, 301, 3, generator=g), torch.randn(2, 37, 301, generator=g)
    pairs = ((g_pos, positions), (g_depth, depth), (g_depth, -1.0 / depth))
    fused = scale_derivative(valid, *pairs)
    reference = scale_derivative(valid, *((a.double(), b.double()) for a, b in pairs))
    assert fused.dtype == torch.float64 and torch.isfinite(fused)
    torch.testing.assert_close(fused, reference, rtol=1e-12, atol=1e-12)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert scale_derivative(valid, *pairs).item() == fused.item()
    finally:
        torch.set_num_threads(threads)
    empty = torch.zeros(1, 0, 4)
    assert scale_derivative(valid[:1, :0], (empty, empty[..., 0:0])).item() == 0.0
    with pytest.raises(RuntimeError, match="channels per valid pixel"):  # (a pair of another size)
        scale_derivative(valid, (g_pos, depth))
