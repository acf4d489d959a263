"""Mitsuba 3 scene files (``.xml``) as scenes, through Mitsuba's own loader (PyPI ``mitsuba``;
the ``mitsuba`` extra). Only the geometry, the diffuse albedo and the first camera are
taken; emitters and other materials are ignored (the scene gets the default :class:`Light`).

Shapes (one object id each, in the order of the shapes' ids):

* triangle meshes (``obj``, ``ply``, ``serialized``, ``rectangle``, ``cube``...): the mesh Mitsuba
  loaded, in world space;
* ``sphere``: an exact :class:`Sphere` (centre and radius from its ``to_world``);
* ``cylinder`` (open, no caps, as in Mitsuba) and ``disk``: tessellated into :data:`SEGMENTS`
  segments (the largest gap to the exact surface is ``r (1 - cos(pi / SEGMENTS))``, 5e-4 ``r``);
* anything else (curves, SDF grids, instances...) is refused, naming the shape.

Albedo: a diffuse BSDF's constant ``reflectance`` (clamped to ``[0, 1]``), else 0.8. Camera: the first
sensor with a field of view (``perspective``, ``thinlens``): Mitsuba cameras look down their local
``+Z`` with ``+Y`` up, and ``x_fov`` is horizontal, turned into the vertical field of view with the
film's aspect ratio.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..checks import install_hint
from .meshfile import _one_line
from .scene import LookAt, Mesh, Sphere

__all__ = ["load_mitsuba_file", "SEGMENTS"]

#: Segments of a tessellated Mitsuba ``cylinder`` or ``disk``.
SEGMENTS = 96


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError:
        raise ImportError(f"scene: Mitsuba 3 scene files need mitsuba: {install_hint('mitsuba', 'mitsuba')}") from None
    if mi.variant() is None:  # leave a variant the caller chose alone
        mi.set_variant("scalar_rgb")
    return mi


def _local_surface(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's local unit ``cylinder`` (radius 1 about ``Z``, ``0 <= z <= 1``, open) or ``disk``
    (radius 1 in ``z = 0``) as ``(vertices (V,3), faces (F,3))``."""
    a = np.arange(SEGMENTS) * 2 * np.pi / SEGMENTS
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], -1)
    i, j = np.arange(SEGMENTS), (np.arange(SEGMENTS) + 1) % SEGMENTS
    if kind == "cylinder":
        top = ring + [0.0, 0.0, 1.0]
        faces = np.concatenate([np.stack([i, j, SEGMENTS + j], -1), np.stack([i, SEGMENTS + j, SEGMENTS + i], -1)])
        return np.concatenate([ring, top]), faces
    return np.concatenate([ring, [[0.0, 0.0, 0.0]]]), np.stack([np.full_like(i, SEGMENTS), i, j], -1)


def _albedo(params) -> tuple[float, float, float]:
    if "bsdf.reflectance.value" not in params.keys():
        return (0.8, 0.8, 0.8)
    value = np.asarray(params["bsdf.reflectance.value"], dtype=np.float64).reshape(-1)
    if value.size == 1:
        value = np.repeat(value, 3)
    return tuple(float(x) for x in np.clip(value[:3], 0.0, 1.0))


def _camera(mi, sensor) -> LookAt | None:
    params = mi.traverse(sensor)
    if "x_fov" not in params.keys():
        return None
    M = np.asarray(sensor.world_transform().matrix, dtype=np.float64)
    R = M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0)
    width, height = (int(x) for x in np.asarray(params["film.size"]).reshape(-1)[:2])
    x_fov = math.radians(float(np.asarray(params["x_fov"]).reshape(-1)[0]))
    fov_y = math.degrees(2 * math.atan(math.tan(x_fov / 2) * height / width))
    eye = M[:3, 3]
    return LookAt(eye=eye.tolist(), target=(eye + R[:, 2]).tolist(), up=R[:, 1].tolist(), fov_y_degrees=fov_y)


def load_mitsuba_file(path: str | Path) -> tuple[list, LookAt | None]:
    """Read a Mitsuba 3 scene file: ``(objects, camera)`` (see the module docstring).

    Raises ``FileNotFoundError`` for a missing file, ``ValueError`` (one line naming the file) for a
    file Mitsuba cannot load, without shapes, or with a shape this tracer cannot represent, and
    ``ImportError`` naming the extra when ``mitsuba`` is missing.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene: no such file: {path}")
    mi = _mitsuba()
    try:
        scene = mi.load_file(str(path))
    except Exception as err:  # Mitsuba raises RuntimeError with a multi-line parser message
        raise ValueError(f"scene: cannot read {path} as a Mitsuba 3 scene ({_one_line(err)})") from None
    objects = []
    for shape in sorted(scene.shapes(), key=lambda s: s.id()):
        params = mi.traverse(shape)
        albedo, name = _albedo(params), f"{path.name}:{shape.id()}"
        kind = shape.class_name()
        if shape.is_mesh():
            v = np.asarray(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
            f = np.asarray(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
            objects.append(Mesh(albedo=albedo, vertices=torch.from_numpy(v), faces=torch.from_numpy(f), name=name))
            continue
        M = np.asarray(params["to_world"].matrix, dtype=np.float64) if "to_world" in params.keys() else None
        if M is not None and kind == "Sphere":
            objects.append(Sphere(albedo=albedo, center=M[:3, 3].tolist(),
                                  radius=float(np.linalg.norm(M[:3, 0]))))
        elif M is not None and kind in ("Cylinder", "Disk"):
            v, f = _local_surface(kind.lower())
            v = v @ M[:3, :3].T + M[:3, 3]
            objects.append(Mesh(albedo=albedo, vertices=torch.from_numpy(v), faces=torch.from_numpy(f), name=name))
        else:
            raise ValueError(f"scene: {path}: shape {shape.id()!r} ({kind}) is not supported "
                             "(meshes, spheres, cylinders and disks are)")
    if not objects:
        raise ValueError(f"scene: {path} has no shapes")
    sensors = scene.sensors()
    return objects, (_camera(mi, sensors[0]) if sensors else None)
