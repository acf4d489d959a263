"""Back-face depth (``render_reference(backface=True)``): the view-axis depth at which each camera ray
leaves the object it hit first.

Closed forms, for a camera at ``(0, 0, D)`` looking down ``-Z`` (view space = world space shifted by
``D``): the view ray through a pixel is ``s * (x, y, -1)`` with ``s`` the view-axis depth, i.e. the
world point ``(s x, s y, D - s)``.

* sphere of radius ``r`` at the origin: ``s^2 (x^2 + y^2 + 1) - 2 D s + D^2 - r^2 = 0``; the front depth
  is the smaller root, the exit depth the larger.
* axis-aligned box ``|X| <= hx, |Y| <= hy, |Z| <= hz``: the ray leaves through the first far slab it
  crosses: ``min(D + hz, hx / |x|, hy / |y|)``.
* cylinder of radius ``r`` about the ``Y`` axis, half height ``h``: side ``(s x)^2 + (D - s)^2 = r^2``
  (larger root), caps ``h / |y|``: the exit is the smaller of the two.
"""
from __future__ import annotations

import math

import pytest
import torch

from torch_ao.reference import (
    Box, Cylinder, Mesh, Plane, Scene, Sphere, embree_available, icosphere, look_at, render_reference,
)

D = 5.0
BACKENDS = ["torch"] + (["embree"] if embree_available() else [])


def _render(objects, backend="torch", H=49, W=65, fov=40.0):  # odd: a pixel on the axis
    views = look_at((0, 0, D), (0, 0, 0), fov_y_degrees=fov, height=H, width=W)
    ref = render_reference(Scene(objects), views, spp=2, uniform=False, backface=True, progress=False,
                           mesh_backend=backend, dtype=torch.float64)
    rays = ref.gbuffer.camera.pixel_rays()[0].double()  # (3,H,W), z = -1
    return ref, rays[0], rays[1]


def _quadratic_roots(a, b, c):
    """Roots of ``a s^2 + b s + c`` (``b < 0`` here), smaller first; NaN where there are none."""
    disc = b * b - 4 * a * c
    sq = torch.sqrt(disc.clamp_min(0))
    return torch.where(disc >= 0, (-b - sq) / (2 * a), math.nan), torch.where(disc >= 0, (-b + sq) / (2 * a), math.nan)


def test_sphere_front_and_exit_depth_closed_form():
    r = 1.2
    ref, x, y = _render([Sphere(center=(0, 0, 0), radius=r)])
    front, back = _quadratic_roots(x * x + y * y + 1, torch.full_like(x, -2 * D), torch.full_like(x, D * D - r * r))
    gb = ref.gbuffer
    hit = gb.valid[0, 0]
    inside = torch.isfinite(front)
    assert hit.sum() > 500
    # silhouette pixels may go either way by rounding; everywhere else hit <=> the closed form says so
    clear = (x * x + y * y + 1) * (D * D - r * r) < D * D * 0.99
    assert torch.equal(hit[clear], inside[clear])
    assert torch.allclose(gb.depth[0, 0][hit].double(), front[hit], rtol=1e-9, atol=1e-9)
    assert torch.allclose(ref.backface_depth[0, 0][hit].double(), back[hit], rtol=1e-9, atol=1e-9)
    assert bool(torch.isinf(ref.backface_depth[0, 0][~hit]).all())  # background
    # through the centre the sphere is 2r thick
    assert float((ref.backface_depth - gb.depth)[0, 0, 24, 32]) == pytest.approx(2 * r, rel=1e-12)


@pytest.mark.parametrize("kind", ["box", "box mesh"])
def test_box_exit_depth_closed_form(kind):
    h = (0.9, 0.6, 0.4)
    if kind == "box":
        obj = Box(center=(0, 0, 0), half_extents=h)
    else:  # the same box as 12 triangles: the mesh path (next hit of the same object)
        trimesh = pytest.importorskip("trimesh")
        tm = trimesh.creation.box(extents=[2 * e for e in h])
        obj = Mesh(vertices=torch.as_tensor(tm.vertices), faces=torch.as_tensor(tm.faces))
    # a floor mesh whose plane holds the box's bottom face: the rays that leave through the bottom
    # meet the floor at the same distance, which must not hide the box's own exit
    floor = Mesh(vertices=torch.tensor([[-9, -h[1], -9], [9, -h[1], -9], [9, -h[1], 9], [-9, -h[1], 9]], dtype=torch.float64),
                 faces=torch.tensor([[0, 1, 2], [0, 2, 3]]))
    for backend in (BACKENDS if kind == "box mesh" else ["torch"]):
        ref, x, y = _render([obj, floor], backend)
        hit = ref.gbuffer.object_id[0, 0] == 1
        with torch.no_grad():
            exit_ = torch.minimum(torch.full_like(x, D + h[2]), torch.minimum(h[0] / x.abs(), h[1] / y.abs()))
        tol = 1e-9 if kind == "box" else 2e-5  # Embree traces in float32
        assert hit.sum() > 300
        assert torch.allclose(ref.gbuffer.depth[0, 0][hit].double(), torch.full_like(x, D - h[2])[hit], atol=tol * 10)
        assert torch.allclose(ref.backface_depth[0, 0][hit].double(), exit_[hit], rtol=tol, atol=tol), backend
        # some rays leave through the back face, some through the sides, some through the bottom
        back = (exit_ == D + h[2]) & hit
        assert 0 < int(back.sum()) < int(hit.sum())
        assert int(((exit_ == h[1] / y.abs()) & (y < 0) & hit).sum()) > 10


def test_cylinder_exit_depth_closed_form():
    r, hh = 0.7, 0.5
    ref, x, y = _render([Cylinder(center=(0, 0, 0), axis=(0, 1, 0), radius=r, half_height=hh)])
    hit = ref.gbuffer.valid[0, 0]
    _, side = _quadratic_roots(x * x + 1, torch.full_like(x, -2 * D), torch.full_like(x, D * D - r * r))
    exit_ = torch.minimum(side, hh / y.abs())
    assert hit.sum() > 200
    through_cap = (hh / y.abs() < side) & hit
    assert 0 < int(through_cap.sum()) < int(hit.sum())
    assert torch.allclose(ref.backface_depth[0, 0][hit].double(), exit_[hit], rtol=1e-9, atol=1e-9)


def test_planes_are_half_spaces_and_open_meshes_are_sheets():
    quad = Mesh(vertices=torch.tensor([[-1, -1, 0.5], [1, -1, 0.5], [1, 1, 0.5], [-1, 1, 0.5]], dtype=torch.float64),
                faces=torch.tensor([[0, 1, 2], [0, 2, 3]]))
    ref, _, _ = _render([Plane(point=(0, 0, -1), normal=(0, 0, 1)), quad])
    oid, depth, back = ref.gbuffer.object_id[0, 0], ref.gbuffer.depth[0, 0], ref.backface_depth[0, 0]
    assert (oid == 1).any() and (oid == 2).any()
    assert bool(torch.isinf(back[oid == 1]).all())
    assert torch.equal(back[oid == 2], depth[oid == 2])


@pytest.mark.parametrize("backend", BACKENDS)
def test_mesh_sphere_matches_the_analytic_sphere_within_tessellation(backend):
    """Icosphere with vertices on the sphere of radius ``r``: it contains the sphere of radius
    ``r - s`` (``s = r (1 - cos a)``, ``a`` the largest angle between a face's centroid direction and
    its corners) and lies inside the sphere of radius ``r``, so a ray at distance ``b < r - s`` from
    the centre leaves the mesh between the two spheres' exits: within
    ``sqrt(r^2 - b^2) - sqrt((r - s)^2 - b^2)`` along the ray, that over ``|(x, y, -1)|`` in depth.
    A box mesh inside the sphere mesh checks that other objects do not stop the exit query."""
    r = 1.2
    v, f = icosphere(4 if backend == "embree" else 3, radius=r)  # the torch path is slow on many triangles
    tri = v[f]
    c = torch.nn.functional.normalize(tri.mean(1), dim=-1)
    cos_a = (torch.nn.functional.normalize(tri, dim=-1) * c[:, None]).sum(-1).min()
    s = r * (1 - float(cos_a))
    corners = [[x, y, z] for x in (-.3, .3) for y in (-.3, .3) for z in (-.3, .3)]
    inner = Mesh(vertices=torch.tensor(corners, dtype=torch.float64),
                 faces=torch.tensor([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                                     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]))
    mesh_ref, x, y = _render([Mesh(vertices=v, faces=f), inner], backend)
    exact_ref, _, _ = _render([Sphere(center=(0, 0, 0), radius=r)])
    n = torch.sqrt(x * x + y * y + 1)
    b = D * torch.sqrt(x * x + y * y) / n  # distance of the pixel's ray from the centre
    judged = (b < r - s) & mesh_ref.gbuffer.valid[0, 0]
    assert judged.sum() > 500
    bound = (torch.sqrt(r * r - b * b) - torch.sqrt(((r - s) ** 2 - b * b).clamp_min(0))) / n
    err = (mesh_ref.backface_depth - exact_ref.backface_depth)[0, 0].double()
    assert bool((err[judged] <= 2e-5).all())  # the mesh is inside the sphere
    assert bool((-err[judged] <= bound[judged] + 2e-5).all())
    assert float(err[judged].abs().max()) > 0.2 * s  # a real tessellation error, not the analytic sphere again
    # the inner box is never the first hit, and does not stop the exit query
    assert not bool((mesh_ref.gbuffer.object_id == 2).any())


def test_backface_depth_saved(tmp_path):
    from torch_ao.io import load_gbuffer

    ref, _, _ = _render([Sphere(center=(0, 0, 0), radius=1.0)], H=12, W=16)
    gb, _ = load_gbuffer(ref.save(tmp_path / "s.npz"))
    assert torch.allclose(gb.backface_depth.double(), ref.backface_depth.double(), equal_nan=False)
