"""Slices drawn by the projected normal's density (``slice_sampling="projected_normal"``) in the bitmask family's
kernels: walk.h's ``walked_slice`` draws each slice's azimuth and its estimator weight, and every sector accumulator
(hard, cosine, indirect light, bent normals, the exact union, soft and straight-through) weighs the slice's sums by
it, as the tensor walk's march does. Values against the tensor path, in SIMD and scalar lanes. Gradients: a slice's
azimuth and weight follow the pixel's normal and view vector, so every backward draws the slices again in dual lanes
of the pixel's own position, normal and depth (walk_grad.h's density_azimuth: the 32 bins in the 3 tangents of the
normal's components, chained) and differentiates the weight's product with the slice's sums: against the float64
tensor walk's autograd, and along random directions against central differences."""
import pytest
import torch

import torch_ao
from torch_ao.camera import PinholeCamera
from torch_ao.thickness import BackfaceThickness
from kernel_agreement import (assert_directional_derivatives, assert_values_agree, relative_error,
                             use_scalar_lanes_in_every_kernel)
from test_kernels import built, rough_gbuffer  # noqa: F401  (built: the fixture)

CASES = {
    "hard": dict(mode="hard"),
    "hard cosine, bent normals": dict(mode="hard", weighting="cosine", bent_normals=True),
    "hdrp": dict(variant="hdrp", azimuth="view"),
    "geometry of exact, sector union": dict(variant="exact", union="sectors"),
    "soft cosine, bent normals": dict(mode="soft", weighting="cosine", bent_normals=True),
    "straight-through": dict(mode="straight_through"),
    "exact": dict(variant="exact"),
    "exact, soft mode": dict(variant="exact", mode="soft"),
}


def _frame():
    gb = rough_gbuffer()
    light = torch.rand(2, 3, *gb.depth.shape[-2:], generator=torch.Generator().manual_seed(1))
    return torch_ao.GBuffer(depth=gb.depth, camera=gb.camera, light=light)


#: each case as BitmaskAO and, but for the exact union (visibility alone), as SSILVB (indirect light)
RUNS = [(name, False) for name in CASES] + [(name, True) for name in CASES if not name.startswith("exact")]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("name, indirect", RUNS)
def test_slices_drawn_by_the_projected_normal_are_the_tensor_walks(built, name, indirect, lanes, monkeypatch):
    if lanes == "scalar":
        use_scalar_lanes_in_every_kernel(monkeypatch)
    gb = _frame()
    make = torch_ao.SSILVB if indirect else torch_ao.BitmaskAO
    with torch.no_grad():
        reference = make(slice_sampling="projected_normal", backend="torch", **CASES[name])(gb)
        kernel = make(slice_sampling="projected_normal", backend="kernel", **CASES[name])(gb)
        uniform = make(backend="kernel", **CASES[name])(gb)
    assert (reference.visibility - uniform.visibility).abs().max() > 0.05  # (the slices are drawn otherwise)
    # (hard masks may flip a sector on a rounding: one slice's weighted sector, bound)
    assert_values_agree(kernel.visibility, reference.visibility, gb.valid, atol=1e-5, bound=0.2)
    for field in ("indirect", "bent_normal"):
        if getattr(reference, field) is not None:
            assert_values_agree(getattr(kernel, field), getattr(reference, field), gb.valid, atol=1e-5, bound=0.2)


#: gradient cases: (module, options); every call with slice_sampling="projected_normal"
GRADIENT_CASES = {
    "hard": (torch_ao.BitmaskAO, dict(mode="hard")),
    "hard cosine, bent normals, edge-aware": (torch_ao.BitmaskAO, dict(mode="hard", weighting="cosine",
                                                                         bent_normals=True, fetch="edge_aware")),
    "hard indirect, cosine": (torch_ao.SSILVB, dict(mode="hard", weighting="cosine", azimuth="view")),
    "geometry of exact, sector union, indirect": (torch_ao.SSILVB, dict(variant="exact", union="sectors",
                                                                        azimuth="view")),
    "soft": (torch_ao.BitmaskAO, dict(mode="soft")),
    "soft cosine, bent normals": (torch_ao.BitmaskAO, dict(mode="soft", weighting="cosine", bent_normals=True)),
    "straight-through, back-face layer": (torch_ao.BitmaskAO, dict(mode="straight_through", thickness="backface")),
    "soft hdrp": (torch_ao.BitmaskAO, dict(mode="soft", variant="hdrp", azimuth="view")),
    "soft indirect, cosine, edge-aware": (torch_ao.SSILVB, dict(mode="soft", weighting="cosine", fetch="edge_aware",
                                                                azimuth="view")),
    "exact": (torch_ao.BitmaskAO, dict(variant="exact")),
    "exact, soft mode, back-face layer": (torch_ao.BitmaskAO, dict(variant="exact", mode="soft",
                                                                   thickness="backface")),
}


def _values_and_grads(name: str, dtype: torch.dtype, backend: str):
    """The outputs (visibility, light, bent normals) and the gradients of a loss weighing each of them differently
    with respect to depth, normals, the light (indirect), the intrinsics, the radius and the thickness model's
    parameters (``None`` where the tensor path has none)."""
    make, options = GRADIENT_CASES[name]
    options = dict(options)
    if options.get("thickness") == "backface":
        options["thickness"] = BackfaceThickness(0.8, 0.15)
    gb0 = _frame().to(dtype)
    depth = gb0.depth.detach().clone().requires_grad_()
    normals = gb0.view_normals().detach().clone().requires_grad_()
    light = gb0.light.detach().clone().requires_grad_()
    K = gb0.camera.intrinsics.detach().clone().requires_grad_()
    gb = torch_ao.GBuffer(depth=depth, normals=normals, light=light, backface_depth=gb0.depth.detach() + 0.3,
                          camera=PinholeCamera(K, gb0.camera.height, gb0.camera.width))
    module = make(slice_sampling="projected_normal", backend=backend, **options).to(dtype)
    out = module(gb)
    parts = [x for x in (out.visibility, out.indirect, out.bent_normal) if x is not None]
    loss = sum((x * torch.linspace(-0.5, 1.5, x.numel(), dtype=dtype).view_as(x)).sum() for x in parts)
    leaves = [depth, normals] + ([light] if make is torch_ao.SSILVB else []) + [K]
    leaves += [p for p in module.parameters() if p.requires_grad]
    grads = torch.autograd.grad(loss, leaves, allow_unused=True)
    return torch.cat(parts, 1).detach().double(), [None if g is None else g.double() for g in grads]


@pytest.mark.parametrize("lanes", ["simd", "scalar"])
@pytest.mark.parametrize("name", list(GRADIENT_CASES))
def test_gradients_through_such_slices_equal_the_float64_tensor_walk(built, name, lanes, monkeypatch):
    """Measured: every gradient within 6.1e-5 relative (the depth's of hard visibility alone, which follows the view
    vector's direction only, is 0 in both up to rounding); a pixel whose quantile falls on a bin's edge in float32
    takes the next bin's weight (one of the rough frame's 4480 pixels in "soft hdrp"), so the largest 0.1 % of the
    differences are left out."""
    if lanes == "scalar":
        use_scalar_lanes_in_every_kernel(monkeypatch)
    gb = _frame()
    ref, ref_grads = _values_and_grads(name, torch.float64, "torch")
    out, grads = _values_and_grads(name, torch.float32, "kernel")  # (backend="kernel": a kernel or a ValueError)
    assert_values_agree(out, ref, gb.valid, atol=1e-5, bound=0.2)
    assert len(grads) == len(ref_grads)
    scale = ref_grads[1].norm()  # (the normals' gradient: every case has one)
    assert scale > 0
    for k, (g, r) in enumerate(zip(grads, ref_grads)):
        if r is None or r.norm() <= 1e-9 * scale:  # (none, or 0 up to rounding: the kernel's as small)
            assert g is None or g.norm() <= 1e-6 * scale, (k, None if g is None else float(g.norm()))
            continue
        assert relative_error(g, r, trim=1e-3) <= 1e-4, (k, relative_error(g, r, trim=1e-3))


def test_gradients_through_such_slices_match_central_differences(built):
    """The soft kernel's derivative along random directions of the normals and the depth against central differences
    of the float64 tensor forward on a small frame (eps 1e-7: no quantile crosses a bin's edge)."""
    gb0 = rough_gbuffer(28, 40, seed=5)
    settings = dict(mode="soft", slices=3, steps=3, weighting="cosine", slice_sampling="projected_normal")
    normals0 = gb0.view_normals().detach()

    def tensor_walk(depth, normals):
        return torch_ao.BitmaskAO(backend="torch", **settings).double()(
            torch_ao.GBuffer(depth=depth, normals=normals, camera=gb0.camera.to(dtype=torch.float64))).visibility.sum()

    depth, normals = gb0.depth.clone().requires_grad_(), normals0.clone().requires_grad_()
    out = torch_ao.BitmaskAO(backend="kernel", **settings)(torch_ao.GBuffer(depth=depth, normals=normals,
                                                                            camera=gb0.camera))
    grads = torch.autograd.grad(out.visibility.sum(), [depth, normals])
    g = torch.Generator().manual_seed(3)
    assert_directional_derivatives(grads, [gb0.depth.double(), normals0.double()], tensor_walk,
                                   lambda: [torch.randn(gb0.depth.shape, generator=g, dtype=torch.float64) * 0.01 *
                                            gb0.valid,  # (the background's depth stays)
                                            torch.randn(normals0.shape, generator=g, dtype=torch.float64)])
