"""Slices drawn by the projected normal's density (``slice_sampling="projected_normal"``) in the bitmask family's
kernels: walk.h's ``walked_slice`` draws each slice's azimuth and its estimator weight, and every sector accumulator
(hard, cosine, indirect light, bent normals, the exact union, soft and straight-through) weighs the slice's sums by
it, as the tensor walk's march does. Values against the tensor path, in SIMD and scalar lanes; a gradient through
such slices (the azimuths and weights follow the normals) runs on the tensor path."""
import pytest
import torch

import torch_ao
from kernel_agreement import assert_values_agree, use_scalar_lanes_in_every_kernel
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


def test_a_gradient_through_such_slices_runs_on_the_tensor_path():
    gb = _frame()
    graded = torch_ao.GBuffer(depth=gb.depth.clone().requires_grad_(), camera=gb.camera, light=gb.light)
    for options in (dict(mode="hard"), dict(mode="soft"), dict(variant="exact")):
        with pytest.raises(ValueError, match="slice_sampling='projected_normal'"):
            torch_ao.BitmaskAO(slice_sampling="projected_normal", backend="kernel", **options)(graded)
    # hard masks alone have no parameter gradient: trainable parameters keep the kernel
    assert torch_ao.BitmaskAO(slice_sampling="projected_normal", backend="kernel")(gb).visibility.shape == gb.depth.shape
    with pytest.raises(ValueError, match="slice_sampling='projected_normal'"):
        torch_ao.BitmaskAO(slice_sampling="projected_normal", mode="soft", backend="kernel")(gb)  # (the radius')
