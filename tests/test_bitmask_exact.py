"""The exact geometry behind bitmask AO's converging options: each option against a closed form or a
brute-force count, and what it removes."""
import math

import pytest
import torch

from torch_ao.examples import floor_wall_gbuffer, plane_gbuffer
from torch_ao.intervals import back_point, clip_to_sphere, sphere_stretch, union_measure
from torch_ao.methods.bitmask import BitmaskAO, bitmask_ao
from torch_ao.methods.bitmask_common import _cosine_measure, cosine_sector_weights
from torch_ao.sectors import sector_union

D = torch.float64


def _grid_union(start, width, size, density, n=20001):
    """Brute force: the measure of the union of the intervals on a fine grid of ``[0, size]``."""
    x = torch.linspace(0, size, n, dtype=D)
    covered = ((x >= start[..., None]) & (x <= (start + width)[..., None]) & (width[..., None] > 0)).any(-2)
    return (covered * density(x)).sum(-1, keepdim=True) * (size / (n - 1))


def test_union_measure_matches_a_brute_force_count():
    g = torch.Generator().manual_seed(0)
    start = torch.rand(64, 12, generator=g, dtype=D) * 36 - 2  # some reach beyond [0, 32]
    width = torch.rand(64, 12, generator=g, dtype=D) * 6 - 1  # some empty
    exact = union_measure(start, width, 32.0)
    assert torch.allclose(exact, _grid_union(start, width, 32.0, torch.ones_like), atol=5e-3)
    # the cosine measure: its density is |n_p| cos(theta - gamma) |sin theta| dtheta/dx
    gamma, length = torch.rand(64, generator=g, dtype=D) * 2 - 1, torch.rand(64, generator=g, dtype=D)

    def density(x):
        theta = gamma[:, None] - math.pi / 2 + math.pi * x / 32
        return length[:, None] * torch.cos(theta - gamma[:, None]) * theta.sin().abs() * (math.pi / 32)

    cosine = union_measure(start, width, 32.0, _cosine_measure(gamma, length))
    assert torch.allclose(cosine, _grid_union(start, width, 32.0, density), atol=5e-4)


def test_union_measure_equals_the_sector_union_on_whole_sectors():
    # Intervals on sector boundaries: quantisation changes nothing, so both unions agree exactly.
    g = torch.Generator().manual_seed(1)
    start = torch.randint(0, 32, (50, 10), generator=g).to(D)
    width = torch.randint(-1, 6, (50, 10), generator=g).to(D)
    gamma, length = torch.rand(50, generator=g, dtype=D) - 0.5, torch.rand(50, generator=g, dtype=D)
    weights = cosine_sector_weights(gamma, length)
    visible, _ = sector_union(start, width, mode="hard", rounding="ceil")
    assert torch.allclose(((1 - visible) * weights).sum(-1, keepdim=True),
                          union_measure(start, width, 32.0, _cosine_measure(gamma, length)), atol=1e-12)


def test_exact_union_removes_the_ceil_quantisation_of_tiny_intervals():
    # 32 steps, each occluding 0.01 sector in a different sector: ceil counts 32 whole sectors (the
    # whole slice), the exact union 0.32 sectors.
    start = (torch.arange(32, dtype=D) + 0.3)[None]
    width = torch.full_like(start, 0.01)
    visible, _ = sector_union(start, width, mode="hard", rounding="ceil")
    assert float((1 - visible).sum()) == 32
    assert float(union_measure(start, width, 32.0)) == pytest.approx(0.32, abs=1e-12)


def test_union_measure_gradient_is_the_boundary_density():
    # d(measure)/d(end) is the density at the end where that end is exposed, 0 where it is covered.
    start = torch.tensor([[2.0, 3.0, 10.0]], dtype=D, requires_grad=True)
    width = torch.tensor([[4.0, 1.0, 2.0]], dtype=D, requires_grad=True)
    union_measure(start, width, 32.0).sum().backward()
    # moving a start moves both ends (-1 + 1); the covered interval [3, 4] has no exposed end
    assert start.grad.tolist() == [[0.0, 0.0, 0.0]]
    assert width.grad.tolist() == [[1.0, 0.0, 1.0]]


def test_clip_to_sphere_matches_a_brute_force_march():
    g = torch.Generator().manual_seed(2)
    fv, ft, bv, bt = (torch.randn(4000, generator=g, dtype=D) * 1.5 for _ in range(4))
    R = torch.tensor(1.0, dtype=D)
    cfv, cft, cbv, cbt, inside = clip_to_sphere(fv, ft, bv, bt, R)
    u = torch.linspace(0, 1, 4001, dtype=D)
    ins = ((fv[:, None] + u * (bv - fv)[:, None]) ** 2 + (ft[:, None] + u * (bt - ft)[:, None]) ** 2) <= 1
    assert torch.equal(ins.any(1), inside)
    ev, et = bv - fv, bt - ft
    par = lambda pv, pt: ((pv - fv) * ev + (pt - ft) * et) / (ev * ev + et * et)  # noqa: E731
    idx = torch.arange(4001)
    first = torch.where(ins, idx, 10**6).min(1).values.to(D) / 4000
    last = torch.where(ins, idx, -1).max(1).values.to(D) / 4000
    assert (par(cfv, cft) - first)[inside].abs().max() < 3e-4
    assert (par(cbv, cbt) - last)[inside].abs().max() < 3e-4
    # clipped ends lie within the sphere
    assert float(((cfv**2 + cft**2)[inside]).max()) <= 1 + 1e-9 and float(((cbv**2 + cbt**2)[inside]).max()) <= 1 + 1e-9


def test_back_point_along_the_camera_ray_is_at_depth_plus_thickness():
    # A pixel P and a sample S in the slice plane spanned by V (toward the camera) and T.
    g = torch.Generator().manual_seed(3)
    P = torch.tensor([0.3, -0.2, -3.0], dtype=D)
    V = -P / P.norm()
    T = torch.linalg.cross(V, torch.tensor([0.0, 1.0, 0.0], dtype=D))
    T = T / T.norm()
    a, b = torch.randn(50, generator=g, dtype=D) * 0.5, torch.randn(50, generator=g, dtype=D) * 0.5
    S = P + a[:, None] * V + b[:, None] * T
    t = torch.rand(50, generator=g, dtype=D)
    depth = -S[:, 2]
    B = S * ((depth + t) / depth)[:, None]  # the same camera ray, at depth + t
    bv, bt = back_point(a, b, t, "depth", pixel_distance=P.norm().expand(50), sample_depth=depth)
    assert torch.allclose(bv, (B - P) @ V, atol=1e-12) and torch.allclose(bt, (B - P) @ T, atol=1e-12)
    bv, bt = back_point(a, b, t, "view")
    assert torch.allclose(bv, a - t) and torch.equal(bt, b)


def test_sphere_stretch_is_the_sphere_silhouette():
    # The farthest camera ray (angle from P's ray) through the circle of radius R around P in a slice
    # plane, expressed as a displacement along T at P's distance: R * stretch.
    for dist, R in ((3.0, 0.5), (2.0, 1.5), (10.0, 0.1)):
        phi = torch.linspace(0, 2 * math.pi, 100001, dtype=D)
        a, b = R * torch.cos(phi), R * torch.sin(phi)  # along V (toward the camera) and T
        reach = (b * dist / (dist - a)).max()
        assert float(reach) == pytest.approx(R * float(sphere_stretch(torch.tensor([dist], dtype=D), R)), rel=1e-6)


@pytest.mark.parametrize("variant", ["exact", "default"])
def test_exact_union_on_a_plane_is_unoccluded(variant):
    for tilt in (0.0, 60.0):
        gb = plane_gbuffer(16, 20, tilt_degrees=tilt)
        out = BitmaskAO(variant=variant, union="exact", weighting="cosine", slices=3, steps=4)(gb)
        assert torch.allclose(out.visibility, torch.ones_like(out.visibility), atol=1e-4), out.visibility.min()


def test_exact_variant_gradients_match_finite_differences_float64():
    gb, _ = floor_wall_gbuffer(12, 14, wall_distance=0.6, camera_height=1.5, pitch_degrees=-40.0, dtype=D)
    opts = dict(variant="exact", slices=2, steps=3, jitter=False)

    def loss(**kw):
        return bitmask_ao(gb, **opts, **kw).visibility.sum()

    for name, value, other in (("thickness", 0.3, dict(radius=0.8)), ("radius", 0.8, dict(thickness=0.3))):
        x = torch.tensor(value, dtype=D, requires_grad=True)
        (grad,) = torch.autograd.grad(loss(**{name: x}, **other), x)
        eps = 1e-6
        with torch.no_grad():
            fd = (loss(**{name: x + eps}, **other) - loss(**{name: x - eps}, **other)) / (2 * eps)
        assert abs(float(fd)) > 1e-6, f"{name}: vacuous check"
        assert float(grad) == pytest.approx(float(fd), rel=1e-4, abs=1e-7), name


def test_exact_union_refuses_the_outputs_it_does_not_compute():
    for kwargs in (dict(indirect=True), dict(bent_normals=True), dict(ambient=(0.2, 0.2, 0.2))):
        with pytest.raises(ValueError, match="union"):
            BitmaskAO(variant="exact", **kwargs)
    with pytest.raises(ValueError, match="clip_to_radius"):
        BitmaskAO(variant="hdrp", clip_to_radius=True)
    with pytest.raises(ValueError, match="union"):
        BitmaskAO(variant="ssilvb_glsl", union="exact")
    with pytest.raises(ValueError, match="sample_extent"):
        BitmaskAO(sample_extent="far")
