"""Ray-traced references: closed forms judged against the reported standard error, honesty of the
error, reproducibility, torch vs Embree, and input errors.

Closed forms for a point on a floor at distance ``d`` from an infinite vertical wall, max distance
``R``, ``k = min(d / R, 1)`` (the wall blocks directions ``w`` with ``w_x >= k``):

* cosine-weighted: ``1 - (acos(k) - k sqrt(1 - k^2)) / pi`` (the blocked segment ``x >= k`` of the
  projected unit disc, over the disc's area ``pi``);
* uniform-weighted: the blocked set ``{w_x >= k}`` is a spherical cap of area ``2 pi (1 - k)`` on the
  whole sphere, cut in half by the floor (the cap is symmetric in ``w_y``, the floor's normal), so
  ``pi (1 - k)`` of the hemisphere's ``2 pi``: visibility ``1 - (1 - k) / 2 = (1 + k) / 2``.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torch_ao.reference import (
    Box, Light, LookAt, Mesh, Plane, Scene, embree_available, get_scene, look_at, render_reference,
)


def cos_visibility(k):
    k = np.minimum(k, 1.0)
    return 1 - (np.arccos(k) - k * np.sqrt(1 - k * k)) / np.pi


def uniform_visibility(k):
    return (1 + np.minimum(k, 1.0)) / 2


def _quadrature(k: float, cosine: bool, n: int = 200_000) -> float:
    """Independent check: integrate over the polar angle (midpoint rule); for each ``theta`` the
    blocked azimuths are ``|phi| <= acos(k / sin(theta))`` (``w_x = sin(theta) cos(phi) >= k``)."""
    theta = (np.arange(n) + 0.5) * (np.pi / 2 / n)
    s = np.sin(theta)
    blocked_phi = np.where(s > k, 2 * np.arccos(np.clip(k / np.maximum(s, 1e-300), -1, 1)), 0.0)
    weight = np.cos(theta) * s / np.pi if cosine else s / (2 * np.pi)
    return 1 - float(np.sum(blocked_phi * weight) * (np.pi / 2 / n))


@pytest.mark.parametrize("k", [0.0, 0.1, 0.37, 0.5, 0.8, 0.99, 1.0])
def test_wall_closed_forms_match_quadrature(k):
    assert abs(_quadrature(k, cosine=True) - cos_visibility(k)) < 1e-6
    assert abs(_quadrature(k, cosine=False) - uniform_visibility(k)) < 1e-6


def _world_positions(ref) -> torch.Tensor:
    M = ref.world_to_view[0].to(ref.position.dtype)
    pv = ref.position[0].reshape(3, -1)
    return (M[:3, :3].T @ (pv - M[:3, 3:4])).reshape(ref.position.shape[1:])


def _judge(value, stderr, expected, spp, frac=0.99):
    """Per pixel within 4 standard errors (+ one sample's weight) for ``frac`` of the pixels, and
    the mean error within 4 of its own standard error."""
    value, stderr = value.double(), stderr.double()
    expected = torch.as_tensor(expected, dtype=torch.float64)
    err = value - expected
    ok = err.abs() <= 4 * stderr + 1.0 / spp
    assert ok.double().mean() >= frac, f"only {ok.double().mean():.4f} of pixels within 4 stderr"
    mean_se = stderr.pow(2).sum().sqrt() / err.numel()
    assert err.mean().abs() <= 4 * mean_se + 1e-9, f"mean error {err.mean():.2e} vs its stderr {mean_se:.2e}"


def _wall_scene(light_dir=(1.0, 1.0, 0.0)) -> Scene:
    objs = [Plane(point=(0, 0, 0), normal=(0, 1, 0), albedo=(0.5, 0.6, 0.7), object_id=1),
            Plane(point=(0, 0, 0), normal=(1, 0, 0), albedo=(0.8, 0.4, 0.2), object_id=2)]
    view = LookAt(eye=(1.5, 2.0, 1.5), target=(1.5, 0.0, 0.0), up=(0, 0, -1), fov_y_degrees=80)
    return Scene(objs, Light("directional", direction=light_dir, intensity=(2.0, 2.0, 2.0)), view)


@pytest.mark.parametrize("R", [math.inf, 1.0, 0.6])
def test_wall_visibility_matches_closed_forms(R):
    spp = 64
    ref = render_reference(_wall_scene(), height=36, width=48, spp=spp, max_distance=R, seed=1, progress=False)
    pw = _world_positions(ref)
    floor = (ref.gbuffer.object_id[0, 0] == 1) & (pw[0] > 1e-3)
    assert floor.sum() > 500
    d = pw[0][floor].numpy()
    k = d / R if math.isfinite(R) else np.zeros_like(d)
    _judge(ref.ao[0, 0][floor], ref.ao_stderr[0, 0][floor], cos_visibility(k), spp)
    _judge(ref.ao_uniform[0, 0][floor], ref.ao_uniform_stderr[0, 0][floor], uniform_visibility(k), spp)
    if not math.isfinite(R):  # R = inf: exactly half of either weighting
        assert abs(float(ref.ao[0, 0][floor].mean()) - 0.5) < 0.01


def test_indirect_from_lit_wall_matches_closed_form():
    """Directional light along (1,1,0): the wall (albedo a_w) is unshadowed with irradiance
    ``I cos 45``, so it leaves radiance ``L = a_w / pi * I / sqrt 2`` everywhere; a floor point then
    receives ``(1/pi) int L cos = L * (1 - cos_visibility(k))`` (no receiver albedo)."""
    spp, R = 64, 1.5
    scene = _wall_scene()
    ref = render_reference(scene, height=30, width=40, spp=spp, max_distance=R, seed=3, progress=False,
                           indirect=True, uniform=False)
    pw = _world_positions(ref)
    floor = (ref.gbuffer.object_id[0, 0] == 1) & (pw[0] > 1e-3)
    wall = ref.gbuffer.object_id[0, 0] == 2
    I = 2.0 / math.sqrt(2)
    L_wall = torch.tensor([0.8, 0.4, 0.2], dtype=torch.float64) / math.pi * I
    L_floor = torch.tensor([0.5, 0.6, 0.7], dtype=torch.float64) / math.pi * I
    light = ref.gbuffer.light[0].double()
    assert torch.allclose(light[:, floor].T, L_floor.expand(int(floor.sum()), 3), rtol=1e-5)
    if wall.any():
        assert torch.allclose(light[:, wall].T, L_wall.expand(int(wall.sum()), 3), rtol=1e-5)
    k = pw[0][floor].numpy() / R
    blocked = torch.from_numpy(1 - cos_visibility(k))
    for c in range(3):
        _judge(ref.indirect[0, c][floor], ref.indirect_stderr[0, c][floor], L_wall[c] * blocked, spp)
    assert ref.ao_uniform is None


@pytest.mark.parametrize("R", [math.inf, 0.5])
def test_infinite_plane_sees_everything(R):
    ref = render_reference(get_scene("infinite_plane"), height=24, width=32, spp=16, max_distance=R, progress=False)
    valid = ref.gbuffer.valid
    assert valid.float().mean() > 0.4
    for v, se in ((ref.ao, ref.ao_stderr), (ref.ao_uniform, ref.ao_uniform_stderr)):
        assert bool((v[valid] == 1).all()) and bool((se[valid] == 0).all())


def test_closed_box_sees_nothing_at_infinite_distance():
    ref = render_reference(get_scene("closed_box"), height=24, width=32, spp=16, progress=False)
    valid = ref.gbuffer.valid
    assert bool(valid.all())  # the camera is inside: every pixel sees a wall
    assert bool((ref.ao == 0).all()) and bool((ref.ao_uniform == 0).all())
    assert bool((ref.ao_stderr == 0).all())
    # and with a short R the walls far away stop counting
    short = render_reference(get_scene("closed_box"), height=24, width=32, spp=16, max_distance=0.05, progress=False)
    assert float(short.ao.mean()) > 0.5


def test_primary_depth_normals_positions_of_a_plane():
    h = 1.7
    scene = Scene([Plane(point=(0, h, 0), normal=(0, -1, 0))])  # a ceiling, seen from below
    views = look_at([(0.3, 0.0, 2.0), (-1.0, 0.5, 0.0)], [(0.0, 1.0, -1.0), (0.0, 1.7, -3.0)], fov_y_degrees=[60.0, 40.0],
                    height=20, width=30)
    ref = render_reference(scene, views, spp=2, progress=False, dtype=torch.float64)
    gb = ref.gbuffer
    M = views.world_to_view
    for b in range(2):
        R, t = M[b, :3, :3], M[b, :3, 3]
        n_view = R @ torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)  # plane n.x = -h in world
        c = -h + n_view @ t  # in view space: n_view . p = c
        dview = views.camera.to(dtype=torch.float64).pixel_rays()[b]  # (3,H,W), z = -1
        denom = torch.einsum("i,ihw->hw", n_view, dview)
        depth = c / denom
        expected_valid = (depth > 0) & torch.isfinite(depth)
        assert torch.equal(gb.valid[b, 0], expected_valid)
        assert torch.allclose(gb.depth[b, 0][expected_valid], depth[expected_valid], rtol=1e-9)
        facing = n_view if n_view[2] > 0 else -n_view
        nb = gb.normals[b][:, expected_valid].T
        assert torch.allclose(nb, (-n_view).expand_as(nb), atol=1e-9) or torch.allclose(nb, facing.expand_as(nb), atol=1e-9)
        # normals face the camera: n . (p - eye) < 0
        assert bool(((gb.normals[b] * ref.position[b]).sum(0)[expected_valid] < 0).all())
    assert torch.allclose(ref.position, gb.camera.unproject(torch.where(gb.valid, gb.depth, 0.0)), atol=1e-9)


@pytest.mark.parametrize("scene_name", ["wall", "room_corner"])
def test_standard_error_is_honest(scene_name):
    """The spread of independent renders (different seeds) matches the reported standard error."""
    scene = _wall_scene() if scene_name == "wall" else get_scene(scene_name)
    renders = [render_reference(scene, height=24, width=32, spp=48, max_distance=1.0, seed=s, progress=False)
               for s in range(8)]
    valid = renders[0].gbuffer.valid
    for key in ("ao", "ao_uniform"):
        vals = torch.stack([getattr(r, key)[valid] for r in renders]).double()
        ses = torch.stack([getattr(r, key + "_stderr")[valid] for r in renders]).double()
        busy = vals.var(0) > 0
        assert busy.sum() > 200
        ratio = math.sqrt(float(vals.var(0)[busy].mean() / ses.pow(2).mean(0)[busy].mean()))
        assert 0.8 <= ratio <= 1.25, f"{key}: empirical / reported error = {ratio:.3f}"


def test_reproducible_with_seed_and_independent_of_chunking():
    scene = get_scene("fence")
    a = render_reference(scene, height=12, width=16, spp=8, max_distance=0.5, seed=7, progress=False)
    b = render_reference(scene, height=12, width=16, spp=8, max_distance=0.5, seed=7, progress=False, chunk_rays=37)
    c = render_reference(scene, height=12, width=16, spp=8, max_distance=0.5, seed=8, progress=False)
    assert torch.equal(a.ao, b.ao) and torch.equal(a.ao_uniform, b.ao_uniform) and torch.equal(a.gbuffer.depth, b.gbuffer.depth)
    assert not torch.equal(a.ao, c.ao)


def test_batched_views_match_single_views():
    scene = get_scene("room_corner")
    eyes = torch.tensor([[2.5, 1.5, 2.5], [3.0, 1.0, 1.0]])
    both = render_reference(scene, look_at(eyes, (0.8, 0.3, 0.8), height=10, width=14), spp=4, max_distance=0.3, progress=False)
    one = render_reference(scene, look_at(eyes[1], (0.8, 0.3, 0.8), height=10, width=14), spp=4, max_distance=0.3, progress=False)
    assert torch.equal(both.gbuffer.depth[1:], one.gbuffer.depth)
    assert torch.equal(both.gbuffer.object_id[1:], one.gbuffer.object_id)
    assert both.ao.shape == (2, 1, 10, 14)


def _small_mesh_scene() -> Scene:
    from torch_ao.reference import icosphere, torus

    v, f = torus(0.5, 0.18, 16, 8)
    v[:, 1] += 0.18
    vs, fs = icosphere(1, 0.25, (0.9, 0.25, 0.2))
    return Scene([Plane(), Mesh(vertices=v, faces=f), Mesh(vertices=vs, faces=fs), Box(center=(-0.9, 0.2, 0), half_extents=(0.2, 0.2, 0.2))],
                 view=LookAt(eye=(0.5, 1.6, 2.2), target=(0.2, 0.1, 0.0), fov_y_degrees=50))


def test_torch_and_embree_mesh_paths_agree():
    if not embree_available():
        pytest.skip("embreex is not importable (pip install embreex): cannot compare against Embree")
    spp = 32
    kw = dict(height=27, width=48, spp=spp, max_distance=0.8, seed=5, progress=False)
    a = render_reference(_small_mesh_scene(), mesh_backend="torch", **kw)
    b = render_reference(_small_mesh_scene(), mesh_backend="embree", **kw)
    same = a.gbuffer.object_id == b.gbuffer.object_id
    assert same.double().mean() > 0.995
    v = a.gbuffer.valid & b.gbuffer.valid & same
    assert torch.allclose(a.gbuffer.depth[v], b.gbuffer.depth[v], rtol=1e-4)
    se = (a.ao_stderr.pow(2) + b.ao_stderr.pow(2)).sqrt()
    _judge(a.ao[v], se[v], b.ao[v].double(), spp)
    mesh_px = (a.gbuffer.object_id == 2) & v
    assert mesh_px.sum() > 50 and float(a.ao[mesh_px].mean()) < 0.95


def test_mesh_torch_path_matches_analytic_box():
    """A box as 12 triangles renders like the analytic Box (same seed: same rays)."""
    corners = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float64) * 0.3
    corners[:, 1] += 0.3
    faces = torch.tensor([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                          [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    view = LookAt(eye=(1.0, 1.2, 1.5), target=(0, 0.2, 0), fov_y_degrees=50)
    mesh = Scene([Plane(), Mesh(vertices=corners, faces=faces)], view=view)
    box = Scene([Plane(), Box(center=(0, 0.3, 0), half_extents=(0.3, 0.3, 0.3))], view=view)
    kw = dict(height=24, width=32, spp=16, max_distance=0.5, seed=2, progress=False)
    a, b = render_reference(mesh, mesh_backend="torch", **kw), render_reference(box, **kw)
    assert torch.equal(a.gbuffer.object_id, b.gbuffer.object_id)
    assert torch.allclose(a.gbuffer.normals, b.gbuffer.normals, atol=1e-4)
    assert (a.ao - b.ao).abs().max() <= 2 / 16 + 1e-6


def test_large_mesh_without_embree_names_the_package(monkeypatch):
    import torch_ao.reference.embree as emb
    import torch_ao.reference.tracer as tr

    monkeypatch.setattr(emb, "embree_available", lambda: False)
    monkeypatch.setattr(tr, "TORCH_MAX_TRIANGLES", 10)
    with pytest.raises(ImportError, match="pip install"):
        render_reference(_small_mesh_scene(), height=4, width=4, spp=2, progress=False)
    with pytest.raises(ImportError, match="embreex"):
        render_reference(_small_mesh_scene(), height=4, width=4, spp=2, progress=False, mesh_backend="embree")


@pytest.mark.parametrize("kwargs, match", [
    (dict(spp=17), "spp"), (dict(spp=1), "spp"), (dict(spp=2.5), "spp"),
    (dict(max_distance=-1.0), "max_distance"), (dict(max_distance=float("nan")), "max_distance"),
    (dict(seed=-3), "seed"), (dict(chunk_rays=0), "chunk_rays"), (dict(mesh_backend="optix"), "mesh_backend"),
    (dict(backend="gpu"), "backend"),
])
def test_bad_render_arguments(kwargs, match):
    args = dict(height=4, width=4, spp=4, progress=False)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        render_reference(get_scene("sphere_on_plane"), **args)


def test_bad_scene_and_view_inputs():
    with pytest.raises(ValueError, match="height/width"):
        render_reference(get_scene("stairs"), spp=4)
    with pytest.raises(TypeError, match="views"):
        render_reference(get_scene("stairs"), views="front", spp=4)
    with pytest.raises(ValueError, match="scene: unknown scene 'nope'"):
        get_scene("nope")
    with pytest.raises(ValueError, match="half_extents"):
        Box(half_extents=(1, -1, 1))
    with pytest.raises(ValueError, match="faces"):
        Mesh(vertices=torch.zeros(3, 3), faces=torch.tensor([[0, 1, 5]]))
    with pytest.raises(ValueError, match="albedo"):
        Plane(albedo=(2, 0, 0))
    with pytest.raises(ValueError, match="eye/target"):
        look_at((0, 0, 0), (0, 0, 0), height=4, width=4)
    with pytest.raises(ValueError, match="up"):
        look_at((0, 0, 0), (0, 1, 0), up=(0, 1, 0), height=4, width=4)
    with pytest.raises(FileNotFoundError, match="mesh"):
        Mesh.load("/nonexistent/bunny.obj")


def _every_primitive_scene() -> Scene:
    """A plane floor and wall, a sphere, a rotated box and a tilted capped cylinder close together."""
    from torch_ao.reference import Cylinder, Sphere, rotation_y

    return Scene([Plane(), Plane(point=(0, 0, -0.8), normal=(0, 0, 1)), Sphere(center=(-0.5, 0.3, 0.1), radius=0.3),
                  Box(center=(0.4, 0.25, -0.2), half_extents=(0.25, 0.25, 0.15), rotation=rotation_y(0.6)),
                  Cylinder(center=(0.0, 0.5, 0.4), axis=(0.3, 0.9, 0.3), radius=0.08, half_height=0.5)],
                 view=LookAt(eye=(0.3, 1.4, 2.0), target=(0.0, 0.2, -0.1), fov_y_degrees=55))


def _flipped_rays(a, b, spp: int) -> int:
    return int(round(float((a.double() - b.double()).abs().sum()) * spp))


@pytest.mark.parametrize("scene_name, R", [("every primitive", math.inf), ("every primitive", 0.7),
                                           ("every primitive", 0.3), ("fence", 1.0), ("poles", 1.0)])
def test_kernel_and_tensor_paths_trace_the_same_rays(scene_name, R):
    """The C++ AO pass draws the tensor path's samples and directions; a ray may differ only where a
    hit test grazes (BLAS dot products), so of the ~50k rays of each weighting at most a few flip."""
    scene = _every_primitive_scene() if scene_name == "every primitive" else get_scene(scene_name, 3)
    spp = 32
    kw = dict(height=36, width=48, spp=spp, max_distance=R, seed=3, progress=False, uniform=True)
    a = render_reference(scene, backend="torch", **kw)
    b = render_reference(scene, backend="kernel", **kw)
    valid = a.gbuffer.valid
    for key in ("ao", "ao_uniform"):  # there is occlusion to get right
        assert float((getattr(a, key)[valid] < 1).double().mean()) > 0.05
    rays = int(valid.sum()) * spp
    for key in ("ao", "ao_uniform"):
        flipped = _flipped_rays(getattr(a, key), getattr(b, key), spp)
        assert flipped <= max(2, rays // 20_000), f"{key}: {flipped} of {rays} rays differ"
    assert torch.equal(a.gbuffer.depth, b.gbuffer.depth)


def test_kernel_backend_refuses_what_it_does_not_cover():
    with pytest.raises(ValueError, match="backend"):
        render_reference(_small_mesh_scene(), height=4, width=4, spp=2, progress=False, backend="kernel")
    with pytest.raises(ValueError, match="backend"):
        render_reference(get_scene("fence"), height=4, width=4, spp=2, progress=False, backend="kernel",
                         dtype=torch.float64)


def test_unbuildable_kernel_falls_back_with_one_warning(monkeypatch):
    from torch_ao.kernels import KernelUnavailable
    from torch_ao.reference import ao_kernel

    def broken():
        raise KernelUnavailable("no compiler (test)")

    monkeypatch.setattr(ao_kernel, "_ops", broken)
    ao_kernel._available.cache_clear()
    try:
        kw = dict(height=12, width=16, spp=8, max_distance=0.5, seed=7, progress=False)
        with pytest.warns(UserWarning, match="no compiler") as record:
            a = render_reference(get_scene("fence"), **kw)
            render_reference(get_scene("fence"), **kw)
        assert len([w for w in record if "no compiler" in str(w.message)]) == 1
        with pytest.raises(KernelUnavailable):
            render_reference(get_scene("fence"), backend="kernel", **kw)
    finally:
        ao_kernel._available.cache_clear()
    assert torch.equal(a.ao, render_reference(get_scene("fence"), backend="torch", **kw).ao)
