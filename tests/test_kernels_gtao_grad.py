"""GTAO's backward through the one walk (walk_grad_cpu.cpp: the walk in dual lanes, lanes_dual.h) against
the tensor-op walk's autograd: gradients of depth (through positions, normals and inverse depth), of given
normals and of the radius, on SIMD and scalar lanes."""
import pytest
import torch

from torch_ao.examples import example_gbuffer
from torch_ao.gbuffer import GBuffer
from torch_ao.kernels import gtao_covers, hbao_covers
from torch_ao.kernels.gtao import gtao_sums
from torch_ao.methods.gtao import GTAO
from torch_ao.methods.hbao import HBAO

from test_kernels import built, pytestmark, rough_gbuffer  # noqa: F401

SETTINGS = [
    dict(slices=4, steps=4),
    dict(slices=3, steps=5, radius=0.6, falloff_range=0.5, bent_normals=True),
    dict(slices=2, steps=5, jitter=False, step_power=2.0, min_step_px=2.0, final_power=1.7),
    dict(slices=2, steps=4, azimuth="screen", search_scale=1.5, max_radius_px=8.0, step_power=1.5),
    dict(slices=3, steps=3, noise="hilbert_r2", stagger=True, seed=4),
]
FRAMES = {"example": lambda: example_gbuffer(24, 40), "rough": lambda: rough_gbuffer(20, 28)}


def _weights(out: torch.Tensor) -> torch.Tensor:
    """A fixed upstream gradient that is not uniform (every pixel and channel weighs differently)."""
    return torch.linspace(0.5, 1.5, out.numel(), dtype=out.dtype).view_as(out)


def _gradients(gb0: GBuffer, backend: str, given_normals: bool, **options):
    """d(loss)/d(depth, normals, radius, final_power) for loss = weighted visibility (+ bent normal)."""
    depth = gb0.depth.detach().clone().requires_grad_(True)
    normals = None
    if given_normals:
        normals = gb0.view_normals().detach().clone().requires_grad_(True)
    gb = GBuffer(depth=depth, normals=normals, camera=gb0.camera)
    module = GTAO(backend=backend, **options)
    module.falloff_range.requires_grad_(False)  # its gradient is the tensor path's (test_uncovered_gradients_say_why)
    out = module(gb)
    loss = (out.visibility * _weights(out.visibility)).sum()
    if out.bent_normal is not None:
        loss = loss + (out.bent_normal * _weights(out.bent_normal)).sum()
    loss.backward()
    grads = {"depth": depth.grad, "radius": module.radius.grad, "final_power": module.final_power.grad}
    if given_normals:
        grads["normals"] = normals.grad
    return out.visibility.detach(), grads


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    finite = torch.isfinite(b)
    return float((a - b)[finite].norm() / b[finite].norm().clamp_min(1e-30))


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("frame", sorted(FRAMES))
@pytest.mark.parametrize("setting", range(len(SETTINGS)))
def test_gtao_kernel_gradients_equal_the_tensor_walk(built, monkeypatch, lanes, frame, setting):
    import torch_ao.kernels.gtao as kernel_gtao

    monkeypatch.setattr(kernel_gtao, "gtao_sums", _with_lanes(kernel_gtao.gtao_sums, lanes))
    gb, options = FRAMES[frame](), SETTINGS[setting]
    given = setting % 2 == 1  # normals given (their gradient) or reconstructed from depth
    reference_out, reference = _gradients(gb, "torch", given, **options)
    out, grads = _gradients(gb, "kernel", given, **options)
    assert torch.allclose(out, reference_out, atol=1e-5)
    assert reference["depth"].abs().max() > 1e-2  # the loss depends on the depth: the comparison means something
    for name in reference:
        assert _relative(grads[name], reference[name]) < 1e-4, name


def _with_lanes(fn, lanes):
    def run(*args, **kwargs):
        kwargs["lanes"] = lanes
        return fn(*args, **kwargs)
    return run


def test_gradient_calls_run_on_the_kernel(built):
    gb = example_gbuffer(12, 20)
    depth = gb.depth.clone().requires_grad_(True)
    gb = GBuffer(depth=depth, camera=gb.camera)
    module = GTAO(slices=2, steps=3, backend="kernel")
    assert gtao_covers(module, gb) is None
    out = module(gb).visibility
    assert out.grad_fn is not None
    out.sum().backward()
    assert torch.isfinite(depth.grad).all() and depth.grad.abs().max() > 0


@pytest.mark.parametrize("make, reason", [
    (lambda: GTAO(fetch="nearest"), "covers 'bilinear', 'drop'"),
    (lambda: GTAO(border="clamp"), "covers 'bilinear', 'drop'"),
    (lambda: GTAO(variant="hdrp"), "exact variant"),
    (lambda: GTAO(falloff_range=0.5, trainable=True), "parameter other than"),
    (lambda: HBAO(trainable=False), "exact variant"),
])
def test_uncovered_gradients_say_why(make, reason):
    gb = example_gbuffer(8, 12)
    gb = GBuffer(depth=gb.depth.clone().requires_grad_(True), camera=gb.camera)
    module = make()
    covers = hbao_covers if isinstance(module, HBAO) else gtao_covers
    assert reason in covers(module, gb)


def test_gtao_sums_refuses_an_uncovered_gradient():
    gb = example_gbuffer(8, 12)
    gb = GBuffer(depth=gb.depth.clone().requires_grad_(True), camera=gb.camera)
    with pytest.raises(ValueError, match="gbuffer: gradients through the kernel"):
        gtao_sums(gb, gb.view_normals(), variant="exact", slices=2, steps=2, walk_radius=0.5, radius=0.5,
                  fetch="nearest")


def test_threads_scatter_into_their_own_images(built):
    gb = rough_gbuffer(20, 28)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        _, one = _gradients(gb, "kernel", True, slices=3, steps=4)
        torch.set_num_threads(3)
        _, three = _gradients(gb, "kernel", True, slices=3, steps=4)
    finally:
        torch.set_num_threads(before)
    for name in one:
        assert torch.allclose(one[name], three[name], rtol=1e-5, atol=1e-6), name


def test_zero_normals_give_the_tensor_paths_finite_gradients():
    """Depths of 2e14 reconstruct zero normals in float32: the projected normal has zero length and
    atan2(0, 0) its angle. The dual walk takes no derivative there (as torch's norm at 0), instead of
    sqrt's and atan2's 0/0, and gives the tensor path's gradients."""
    from stability_cases import extreme_camera

    gb = extreme_camera(1.0, 0.0, 2e14, torch.float32)
    assert not bool(gb.view_normals("improved").abs().amax())  # (the case: every normal is zero)
    grads = []
    for backend in ("kernel", "torch"):
        depth = gb.depth.clone().requires_grad_(True)
        GTAO(backend=backend)(GBuffer(depth, gb.camera)).visibility.sum().backward()
        grads.append(depth.grad)
    assert bool(torch.isfinite(grads[0]).all())
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-30)
