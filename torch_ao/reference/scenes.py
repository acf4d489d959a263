"""Built-in procedural scenes that stress screen-space AO, and their registry.

Each builder takes a ``torch.Generator`` or ``None``: ``None`` gives the documented default
parameters, a generator gives a randomised variant (sizes, placements, albedo, light and camera),
for training. Use :func:`get_scene`\\ ``(name, seed=None)`` and :data:`SCENES`.
The ground is ``y = 0`` and ``+Y`` is up; lengths are in metres-like units.

The ``mesh_*`` scenes are real meshes from Debian's ``assimp-testmodels`` package (in
:data:`MESH_DIR`), each normalised to unit size and resting on a floor; their randomised variants
are orbit cameras around the mesh. :func:`scene_unavailable` says when a scene's files are missing.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from ..scene import Box, Cylinder, Light, LookAt, Mesh, Plane, Scene, Sphere, rotation_y

__all__ = ["SCENES", "SceneInfo", "get_scene", "list_scenes", "icosphere", "torus", "MESH_DIR", "MESH_SCENES",
           "scene_unavailable"]


class _P:
    """Parameter source: defaults when ``rng`` is None, uniform draws otherwise."""

    def __init__(self, rng: torch.Generator | None):
        self.rng = rng

    def u(self, lo: float, hi: float, default: float) -> float:
        if self.rng is None:
            return default
        return lo + (hi - lo) * float(torch.rand((), generator=self.rng, dtype=torch.float64))

    def i(self, lo: int, hi: int, default: int) -> int:
        if self.rng is None:
            return default
        return int(torch.randint(lo, hi + 1, (), generator=self.rng))

    def albedo(self, default=(0.8, 0.8, 0.8)) -> tuple[float, float, float]:
        if self.rng is None:
            return default
        base = self.u(0.3, 0.9, 0.6)
        return tuple(min(1.0, max(0.05, base + self.u(-0.15, 0.15, 0.0))) for _ in range(3))

    def light(self) -> Light:
        az, el = self.u(0, 2 * math.pi, 0.6), self.u(0.35, 1.3, 0.9)
        return Light("directional", direction=(math.cos(el) * math.cos(az), math.sin(el), math.cos(el) * math.sin(az)),
                     intensity=(3.0, 3.0, 3.0))

    def orbit(self, target, radius, elevation_deg, azimuth_deg, fov, jitter=15.0) -> LookAt:
        el = math.radians(self.u(elevation_deg - jitter / 2, elevation_deg + jitter / 2, elevation_deg))
        az = math.radians(self.u(azimuth_deg - jitter, azimuth_deg + jitter, azimuth_deg))
        r = radius * self.u(0.85, 1.15, 1.0)
        tx, ty, tz = target
        eye = (tx + r * math.cos(el) * math.sin(az), ty + r * math.sin(el), tz + r * math.cos(el) * math.cos(az))
        return LookAt(eye=eye, target=target, fov_y_degrees=fov)


def _floor(p: _P, y: float = 0.0) -> Plane:
    return Plane(point=(0, y, 0), normal=(0, 1, 0), albedo=p.albedo((0.75, 0.75, 0.75)))


def sphere_on_plane(rng=None) -> Scene:
    p = _P(rng)
    r = p.u(0.3, 1.5, 1.0)
    x, z = p.u(-0.5, 0.5, 0.0), p.u(-0.5, 0.5, 0.0)
    objs = [_floor(p), Sphere(center=(x, r, z), radius=r, albedo=p.albedo((0.8, 0.3, 0.3)))]
    return Scene(objs, p.light(), p.orbit((x, 0.4 * r, z), 4.5 * r, 25, 20, 50), "sphere_on_plane",
                 "a sphere resting on an infinite floor: contact crease, smooth occlusion")


def fence(rng=None) -> Scene:
    p = _P(rng)
    n = p.i(6, 16, 10)
    width, gap = p.u(0.03, 0.15, 0.08), p.u(0.05, 0.3, 0.15)
    height, depth = p.u(0.8, 2.0, 1.2), p.u(0.02, 0.06, 0.03)
    wall_dist = p.u(0.05, 0.6, 0.25)
    pitch = width + gap
    x0 = -pitch * (n - 1) / 2
    albedo = p.albedo((0.6, 0.45, 0.3))
    objs = [_floor(p), Plane(point=(0, 0, -wall_dist - depth), normal=(0, 0, 1), albedo=p.albedo((0.85, 0.85, 0.8)))]
    for i in range(n):
        objs.append(Box(center=(x0 + i * pitch, height / 2, 0.0), half_extents=(width / 2, height / 2, depth), albedo=albedo))
    objs.append(Box(center=(0, 0.75 * height, depth + 0.02), half_extents=(pitch * n / 2, 0.04, 0.02), albedo=albedo))
    return Scene(objs, p.light(), p.orbit((0, 0.45 * height, 0), 2.2 * max(1.0, pitch * n / 2), 15, 25, 55),
                 "fence", "thin slats (a fence) in front of a wall: thin occluders, small gaps, depth discontinuities")


def room_corner(rng=None) -> Scene:
    p = _P(rng)
    objs = [_floor(p), Plane(point=(0, 0, 0), normal=(1, 0, 0), albedo=p.albedo((0.8, 0.8, 0.75))),
            Plane(point=(0, 0, 0), normal=(0, 0, 1), albedo=p.albedo((0.75, 0.8, 0.8)))]
    sizes = [(0.5, 0.5, 0.5), (0.25, 0.35, 0.2), (0.12, 0.12, 0.12), (0.06, 0.2, 0.06)]
    places = [(0.6, 0.6), (1.5, 0.4), (0.9, 1.4), (0.25, 1.1)]
    for (sx, sy, sz), (px, pz) in zip(sizes, places):
        k = p.u(0.6, 1.6, 1.0)
        hx, hy, hz = sx * k, sy * k, sz * k
        x, z = px + p.u(-0.15, 0.15, 0.0) + hx, pz + p.u(-0.15, 0.15, 0.0) + hz
        objs.append(Box(center=(x, hy, z), half_extents=(hx, hy, hz), rotation=rotation_y(p.u(-0.5, 0.5, 0.2)),
                        albedo=p.albedo((0.7, 0.7, 0.9))))
    return Scene(objs, p.light(), p.orbit((0.9, 0.3, 0.9), 3.2, 30, 45, 60), "room_corner",
                 "a room corner (floor and two walls) with boxes of several sizes: creases and corners")


def stairs(rng=None) -> Scene:
    p = _P(rng)
    n = p.i(4, 10, 6)
    rise, run, width = p.u(0.1, 0.25, 0.17), p.u(0.2, 0.4, 0.28), p.u(0.8, 2.0, 1.2)
    albedo = p.albedo((0.7, 0.65, 0.6))
    objs = [_floor(p), Plane(point=(-width / 2, 0, 0), normal=(1, 0, 0), albedo=p.albedo((0.8, 0.8, 0.8)))]
    for i in range(n):
        h = rise * (i + 1)
        objs.append(Box(center=(0.0, h / 2, -run * (i + 0.5)), half_extents=(width / 2, h / 2, run / 2), albedo=albedo))
    mid = (0.0, rise * n / 2, -run * n / 2)
    return Scene(objs, p.light(), p.orbit(mid, 2.0 + 0.4 * n * run, 25, 35, 55), "stairs",
                 "a flight of stairs against a side wall: repeated concave steps")


def floating(rng=None) -> Scene:
    p = _P(rng)
    h = p.u(0.02, 1.0, 0.25)
    kind = p.i(0, 2, 0)
    albedo = p.albedo((0.3, 0.6, 0.8))
    if kind == 0:
        obj = Box(center=(0, h + 0.3, 0), half_extents=(0.6, 0.3, 0.4), rotation=rotation_y(p.u(0, math.pi, 0.4)), albedo=albedo)
    elif kind == 1:
        obj = Sphere(center=(0, h + 0.5, 0), radius=0.5, albedo=albedo)
    else:
        obj = Cylinder(center=(0, h + 0.15, 0), axis=(0, 1, 0), radius=0.6, half_height=0.15, albedo=albedo)
    return Scene([_floor(p), obj], p.light(), p.orbit((0, 0.3, 0), 3.5, 20, 30, 50), "floating",
                 "an object floating above the ground: a gap screen-space methods fill in, soft contact shadow")


def poles(rng=None) -> Scene:
    p = _P(rng)
    albedo = p.albedo((0.55, 0.4, 0.3))
    seat_h, leg_r = p.u(0.35, 0.6, 0.45), p.u(0.01, 0.04, 0.02)
    half = p.u(0.18, 0.3, 0.22)
    objs = [_floor(p), Box(center=(0, seat_h, 0), half_extents=(half, 0.025, half), albedo=albedo),
            Box(center=(0, seat_h + 0.25, -half + 0.02), half_extents=(half, 0.25, 0.02), albedo=albedo)]
    for sx in (-1, 1):
        for sz in (-1, 1):
            objs.append(Cylinder(center=(sx * (half - 0.03), seat_h / 2, sz * (half - 0.03)), axis=(0, 1, 0),
                                 radius=leg_r, half_height=seat_h / 2, albedo=albedo))
    n = p.i(3, 8, 5)
    for i in range(n):
        a = 2 * math.pi * i / n + p.u(-0.3, 0.3, 0.0)
        d = p.u(0.6, 1.4, 0.9)
        hgt = p.u(0.6, 2.0, 1.4)
        objs.append(Cylinder(center=(d * math.cos(a), hgt / 2, d * math.sin(a)), axis=(0, 1, 0),
                             radius=p.u(0.008, 0.05, 0.025), half_height=hgt / 2, albedo=p.albedo((0.6, 0.6, 0.65))))
    return Scene(objs, p.light(), p.orbit((0, 0.35, 0), 2.6, 25, 20, 55), "poles",
                 "thin poles and chair legs: occluders thinner than a pixel's thickness estimate")


def grazing_floor(rng=None) -> Scene:
    p = _P(rng)
    height = p.u(0.15, 0.6, 0.3)
    objs = [_floor(p)]
    n = p.i(4, 12, 8)
    g = torch.Generator().manual_seed(1234) if rng is None else rng
    for i in range(n):
        dist = 3 * 1.6 ** (i * 8 / n)
        x = (float(torch.rand((), generator=g)) - 0.5) * dist
        s = 0.15 * dist ** 0.7
        objs.append(Box(center=(x, s, -dist), half_extents=(s, s, s), rotation=rotation_y(float(torch.rand((), generator=g)) * 3),
                        albedo=p.albedo((0.7, 0.7, 0.7))))
    view = LookAt(eye=(0, height, 2.0), target=(0, height * p.u(0.3, 0.9, 0.6), -10.0), fov_y_degrees=p.u(45, 75, 60))
    return Scene(objs, p.light(), view, "grazing_floor",
                 "a floor seen at grazing angles running to a far horizon: foreshortening, huge pixel footprints")


def large_depth_range(rng=None) -> Scene:
    p = _P(rng)
    near = p.u(0.2, 0.5, 0.3)
    objs = [_floor(p),
            Sphere(center=(0.3 * near, 1.5 - 0.35 * near, 2.0 - near), radius=0.25 * near, albedo=p.albedo((0.9, 0.4, 0.2))),
            Box(center=(0.8, 0.5, -8.0), half_extents=(0.5, 0.5, 0.5), albedo=p.albedo((0.5, 0.7, 0.5))),
            Box(center=(-15.0, 10.0, -150.0), half_extents=(8.0, 10.0, 8.0), albedo=p.albedo((0.6, 0.6, 0.7))),
            Sphere(center=(40.0, 30.0, -600.0), radius=30.0, albedo=p.albedo((0.7, 0.7, 0.5))),
            Box(center=(-200.0, 100.0, -2000.0), half_extents=(150.0, 100.0, 80.0), albedo=p.albedo((0.6, 0.6, 0.6)))]
    view = LookAt(eye=(0, 1.5, 2.0), target=(0, 1.2, -20.0), fov_y_degrees=p.u(50, 70, 60))
    return Scene(objs, p.light(), view, "large_depth_range",
                 "objects from 0.1 to 2000 units away: depth precision and radius-in-pixels extremes")


def infinite_wall(rng=None, distance: float | None = None) -> Scene:
    """Floor ``y = 0`` and an infinite wall ``x = 0`` facing ``+x``; the camera sees the floor at
    ``x`` from about 0 to 4 (closed-form visibility, see the module docs of the tests)."""
    p = _P(rng)
    objs = [Plane(point=(0, 0, 0), normal=(0, 1, 0), albedo=(0.8, 0.8, 0.8)),
            Plane(point=(0, 0, 0), normal=(1, 0, 0), albedo=(0.8, 0.8, 0.8))]
    view = LookAt(eye=(2.0, 3.0, 2.0), target=(p.u(1.5, 2.5, 2.0), 0.0, 0.0), up=(0, 0, -1), fov_y_degrees=70)
    return Scene(objs, p.light(), view, "infinite_wall", "a floor meeting an infinite wall: the closed-form AO test")


def infinite_plane(rng=None) -> Scene:
    p = _P(rng)
    return Scene([Plane(point=(0, 0, 0), normal=(0, 1, 0), albedo=(0.8, 0.8, 0.8))], p.light(),
                 LookAt(eye=(0, 2.0, 3.0), target=(0, 0, 0), fov_y_degrees=60), "infinite_plane",
                 "a lone infinite plane: visibility 1 everywhere")


def closed_box(rng=None) -> Scene:
    p = _P(rng)
    hx, hy, hz = p.u(1.5, 3, 2.0), p.u(1.0, 2.0, 1.25), p.u(1.5, 3, 2.0)
    objs = [Box(center=(0, hy, 0), half_extents=(hx, hy, hz), albedo=p.albedo((0.8, 0.8, 0.8))),
            Box(center=(0.3, 0.2, -0.3), half_extents=(0.2, 0.2, 0.2), rotation=rotation_y(p.u(0, 1.5, 0.5)),
                albedo=p.albedo((0.4, 0.6, 0.8)))]
    light = Light("point", position=(0, 1.8 * hy, 0), intensity=(4.0, 4.0, 4.0))
    view = LookAt(eye=(-0.6 * hx, 1.6 * hy, 0.8 * hz), target=(0.3, 0.0, -0.3), fov_y_degrees=80)
    return Scene(objs, light, view, "closed_box", "the inside of a closed box (a room) lit by a point light: visibility 0 at R = inf")


def icosphere(subdivisions: int = 2, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """``(vertices (V,3), faces (F,3))`` of a subdivided icosahedron (``20 * 4**subdivisions`` faces)."""
    t = (1 + 5 ** 0.5) / 2
    v = torch.tensor([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                      [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=torch.float64)
    f = torch.tensor([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                      [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                      [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    for _ in range(subdivisions):
        edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(1).values
        uniq, inv = torch.unique(edges, dim=0, return_inverse=True)
        mids = len(v) + inv.view(3, -1).T  # (F,3) midpoints of edges 01, 12, 20
        v = torch.cat([v, (v[uniq[:, 0]] + v[uniq[:, 1]]) / 2])
        a, b, c = f.unbind(1)
        ab, bc, ca = mids.unbind(1)
        f = torch.cat([torch.stack(x, 1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    v = v / v.norm(dim=1, keepdim=True) * radius + torch.tensor(center, dtype=torch.float64)
    return v, f


def torus(major: float = 0.6, minor: float = 0.2, n_major: int = 32, n_minor: int = 12, center=(0.0, 0.0, 0.0)):
    """``(vertices, faces)`` of a torus around ``+Y`` (``2 * n_major * n_minor`` faces)."""
    i = torch.arange(n_major, dtype=torch.float64)[:, None] * (2 * math.pi / n_major)
    j = torch.arange(n_minor, dtype=torch.float64)[None, :] * (2 * math.pi / n_minor)
    r = major + minor * torch.cos(j)
    v = torch.stack([r * torch.cos(i), (minor * torch.sin(j)).expand(n_major, n_minor), r * torch.sin(i)], -1).reshape(-1, 3)
    a = torch.arange(n_major)[:, None] * n_minor + torch.arange(n_minor)[None]
    b = ((torch.arange(n_major)[:, None] + 1) % n_major) * n_minor + torch.arange(n_minor)[None]
    c = torch.arange(n_major)[:, None] * n_minor + (torch.arange(n_minor)[None] + 1) % n_minor
    d = ((torch.arange(n_major)[:, None] + 1) % n_major) * n_minor + (torch.arange(n_minor)[None] + 1) % n_minor
    f = torch.cat([torch.stack([a, b, d], -1).reshape(-1, 3), torch.stack([a, d, c], -1).reshape(-1, 3)])
    return v + torch.tensor(center, dtype=torch.float64), f


def mesh_on_floor(rng=None) -> Scene:
    p = _P(rng)
    tilt = p.u(0, 0.8, 0.5)
    v, f = torus(0.6, p.u(0.1, 0.3, 0.2), 32, 12)
    c, s = math.cos(tilt), math.sin(tilt)
    R = torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)
    v = v @ R.T
    v[:, 1] -= float(v[:, 1].min())
    vs, fs = icosphere(2, 0.25, (1.0, 0.25, 0.3))
    objs = [_floor(p), Mesh(vertices=v, faces=f, albedo=p.albedo((0.8, 0.7, 0.3)), name="torus"),
            Mesh(vertices=vs, faces=fs, albedo=p.albedo((0.3, 0.7, 0.8)), name="icosphere")]
    return Scene(objs, p.light(), p.orbit((0.3, 0.3, 0.0), 3.0, 30, 20, 50), "mesh_on_floor",
                 "triangle meshes (a tilted torus, an icosphere) on a floor; --mesh files are added here too")


#: Folder of Debian's assimp-testmodels meshes (``$TORCH_AO_MESH_DIR`` when set).
MESH_DIR = Path(os.environ.get("TORCH_AO_MESH_DIR") or "/usr/share/assimp/models")

#: Built-in mesh scenes: name -> (file under :data:`MESH_DIR`, description). Small files (at most
#: a few thousand triangles) that load in well under a second. The spider, duck, engine and wuson
#: models are kept out of this set (they are for independent checks).
MESH_SCENES: dict[str, tuple[str, str]] = {
    "mesh_empty_mat": ("OBJ/empty_mat.obj", "assimp-testmodels OBJ/empty_mat.obj on a floor: a faceted solid"),
    "mesh_sphere_hole": ("STL/sphereWithHole.stl", "assimp-testmodels STL/sphereWithHole.stl on a floor: a sphere with a hole into it"),
    "mesh_3dsmax": ("STL/3DSMaxExport.STL", "assimp-testmodels STL/3DSMaxExport.STL on a floor: a curved exported model"),
    "mesh_box_longline": ("OBJ/box_longline.obj", "assimp-testmodels OBJ/box_longline.obj on a floor: a box, sharp contact edges"),
    "mesh_concave": ("OBJ/concave_polygon.obj", "assimp-testmodels OBJ/concave_polygon.obj on a floor: a concave polygon shape"),
    "mesh_regr01": ("OBJ/regr01.obj", "assimp-testmodels OBJ/regr01.obj on a floor: a detailed model with creases"),
    "mesh_clearcoat": ("glTF2/ClearCoat-glTF/ClearCoatTest.gltf", "assimp-testmodels glTF2 ClearCoatTest on a floor: "
                       "rows of spheres and plates"),
}


def scene_unavailable(name: str) -> str | None:
    """Why built-in scene ``name`` cannot be built here (its mesh file is missing), else ``None``."""
    if name not in MESH_SCENES:
        return None
    path = MESH_DIR / MESH_SCENES[name][0]
    if path.exists():
        return None
    return (f"scene {name!r} needs {path}, which is missing: install Debian's assimp-testmodels package "
            "(apt-get install assimp-testmodels), or set TORCH_AO_MESH_DIR to a copy of its models folder")


def _mesh_builder(name: str) -> Callable[..., Scene]:
    def build(rng=None) -> Scene:
        """The mesh on a floor; ``rng``: an orbit camera drawn from it (azimuth uniform, elevation
        15-50 degrees, distance 0.9-1.3 times the one that frames the bounding sphere), else the
        mesh's framing view."""
        from ..io.mesh import mesh_scene

        why = scene_unavailable(name)
        if why is not None:
            raise FileNotFoundError(why)
        scene = mesh_scene([MESH_DIR / MESH_SCENES[name][0]], ground_plane=True, normalize=True)
        scene.name, scene.description = name, MESH_SCENES[name][1]
        if rng is not None:
            lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in _object_bounds(scene))
            centre, r = (lo + hi) / 2, float((hi - lo).norm()) / 2
            az = 2 * math.pi * float(torch.rand((), generator=rng, dtype=torch.float64))
            el = math.radians(15 + 35 * float(torch.rand((), generator=rng, dtype=torch.float64)))
            d = (0.9 + 0.4 * float(torch.rand((), generator=rng, dtype=torch.float64))) * r / math.sin(math.radians(30))
            eye = centre + d * torch.tensor([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)],
                                            dtype=torch.float64)
            scene.view = LookAt(eye=eye.tolist(), target=centre.tolist(), fov_y_degrees=60.0)
        return scene

    build.__name__ = name
    return build


def _object_bounds(scene: Scene):
    """Bounds of the scene's meshes (the floor plane is unbounded and left out)."""
    boxes = [b for b in (o.bounds() for o in scene.objects if isinstance(o, Mesh)) if b is not None]
    return torch.stack([b[0] for b in boxes]).min(0).values, torch.stack([b[1] for b in boxes]).max(0).values


@dataclass(frozen=True)
class SceneInfo:
    name: str
    builder: Callable[..., Scene]
    description: str


def _info(builder) -> SceneInfo:
    return SceneInfo(builder.__name__, builder, builder().description)


#: Registry of built-in scenes by name.
SCENES: dict[str, SceneInfo] = {i.name: i for i in map(_info, (
    sphere_on_plane, fence, room_corner, stairs, floating, poles, grazing_floor, large_depth_range,
    mesh_on_floor, infinite_wall, infinite_plane, closed_box))}
SCENES.update({name: SceneInfo(name, _mesh_builder(name), description) for name, (_, description) in MESH_SCENES.items()})


def list_scenes() -> list[tuple[str, str]]:
    """``[(name, one-line description)]`` of the built-in scenes."""
    return [(i.name, i.description) for i in SCENES.values()]


def get_scene(name: str, seed: int | torch.Generator | None = None) -> Scene:
    """A built-in scene: default parameters when ``seed`` is None, else a randomised variant."""
    if name not in SCENES:
        raise ValueError(f"scene: unknown scene {name!r}; built-in scenes: {', '.join(SCENES)}")
    why = scene_unavailable(name)
    if why is not None:
        raise FileNotFoundError(f"scene: {why}")
    if seed is None:
        rng = None
    elif isinstance(seed, torch.Generator):
        rng = seed
    elif isinstance(seed, int) and not isinstance(seed, bool):
        rng = torch.Generator().manual_seed(seed)
    else:
        raise TypeError(f"seed: expected None, an int or a torch.Generator, got {type(seed).__name__}")
    return SCENES[name].builder(rng)
