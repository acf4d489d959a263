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
sensor with a field of view (``perspective``, ``thinlens``), as a :class:`LookAt` that renders Mitsuba's
camera rays: Mitsuba cameras look down their local ``+Z`` with ``+Y`` up; ``x_fov`` (horizontal) is
turned into the vertical field of view at the film's size (``LookAt.film``); the FOV's ``fov_axis``
(``LookAt.fov_axis``, read with Mitsuba's parser) says what another image size keeps; the principal point
offsets (fractions of the film added to its sample position) become ``LookAt.principal_offset``
(negated: the optical axis crosses the film at ``0.5 - offset``). A film with a crop window is refused.

Files the scene names (``<include filename>``, ``<path value>``, every ``filename``: shapes, textures,
spectra), after substituting its ``<default>`` parameters, must be inside the scene file's folder
(relative names are taken relative to it), unless ``allow_outside_paths=True``
(:mod:`~torch_ao.io.confine`): they are checked, included files too, before Mitsuba reads anything.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import torch

from ..checks import install_hint
from ..scene import LookAt, Mesh, Sphere
from .confine import confined_path, scene_root
from .trimesh_file import one_line

__all__ = ["load_mitsuba_file", "check_scene_references", "SEGMENTS"]

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


def _fov_axis(mi, path: Path, sensor) -> str:
    """The axis the sensor's field of view was given on (Mitsuba's ``fov_axis``, default ``"x"``;
    ``"diagonal"`` for a ``focal_length``), read with Mitsuba's own parser (``mitsuba.parser``); ``"x"``
    where this Mitsuba has none."""
    parser = getattr(mi, "parser", None)
    if parser is None:
        return "x"
    config = parser.ParserConfig(mi.variant())
    state = parser.parse_file(config, str(path))
    parser.transform_all(config, state)
    sensors = [n.props for n in state.nodes if n.type == mi.ObjectType.Sensor]
    props = next((q for q in sensors if sensor.id() and q.id() == sensor.id()), sensors[0] if sensors else None)
    if props is None or "fov" not in props:
        return "diagonal" if props is not None and "focal_length" in props else "x"
    return str(props["fov_axis"]).lower() if "fov_axis" in props else "x"


def _camera(mi, path: Path, sensor) -> LookAt | None:
    """The sensor as a :class:`LookAt` carrying its film size, ``fov_axis`` and principal point offset;
    ``None`` for a sensor without a field of view (orthographic, radiance meters...)."""
    params = mi.traverse(sensor)
    if "x_fov" not in params.keys():
        return None
    width, height = (int(x) for x in np.asarray(params["film.size"]).reshape(-1)[:2])
    crop = tuple(int(x) for x in np.asarray(params["film.crop_size"]).reshape(-1)[:2])
    if crop != (width, height):
        raise ValueError(f"scene: {path}: the film's crop window ({crop[0]}x{crop[1]} of {width}x{height}) is not "
                         "supported; render the whole film (its width and height)")
    M = np.asarray(sensor.world_transform().matrix, dtype=np.float64)
    R = M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0)
    x_fov = math.radians(float(np.asarray(params["x_fov"]).reshape(-1)[0]))
    fov_y = math.degrees(2 * math.atan(math.tan(x_fov / 2) * height / width))
    # Mitsuba adds the offsets to the film sample (0..1, y down): the axis passes the film at 0.5 - offset
    offset = tuple(-float(np.asarray(params[f"principal_point_offset_{k}"]).reshape(-1)[0])
                   if f"principal_point_offset_{k}" in params.keys() else 0.0 for k in "xy")
    eye = M[:3, 3]
    return LookAt(eye=eye.tolist(), target=(eye + R[:, 2]).tolist(), up=R[:, 1].tolist(), fov_y_degrees=fov_y,
                  film=(width, height), fov_axis=_fov_axis(mi, path, sensor), principal_offset=offset)


def _references(root: ET.Element):
    """``(what, file name)`` of every file reference of a parsed Mitsuba document, as written."""
    for node in root.iter():
        if node.tag == "include" and "filename" in node.attrib:
            yield "<include filename>", node.attrib["filename"]
        elif node.tag == "path" and "value" in node.attrib:
            yield "<path value>", node.attrib["value"]
        elif node.tag == "string" and node.attrib.get("name", "").endswith("filename") and "value" in node.attrib:
            yield f"<string name={node.attrib['name']!r}>", node.attrib["value"]
        elif "filename" in node.attrib and node.tag != "include":
            yield f"<{node.tag} filename>", node.attrib["filename"]


def _substituted(text: str, defaults: list[tuple[str, str]]) -> list[str]:
    """``text`` with Mitsuba's ``$name`` parameters replaced (plain string replacement, as Mitsuba
    does), with the defaults taken in their order and longest name first (every result is checked)."""
    out = []
    for order in (defaults, sorted(defaults, key=lambda kv: -len(kv[0]))):
        value = text
        for name, replacement in order:
            value = value.replace("$" + name, replacement)
        out.append(value)
    return out


def check_scene_references(path: str | Path, *, allow_outside_paths: bool = False) -> None:
    """Refuse (:class:`~torch_ao.io.confine.OutsidePathError`, naming the file and the
    reference) a Mitsuba scene file that names a file outside its folder, directly or through an
    ``<include>``, a ``<default>`` parameter or a symbolic link; ``ValueError`` for a file that is
    not XML. Reads the scene file and the files it includes, nothing else."""
    path = Path(path)
    root = scene_root(path)
    pending, seen = [(path, [])], set()
    while pending:
        file, inherited = pending.pop()
        if file in seen:
            continue
        seen.add(file)
        try:
            doc = ET.parse(file).getroot()
        except (ET.ParseError, OSError) as err:
            raise ValueError(f"scene: cannot read {file} as a Mitsuba 3 scene ({one_line(err)})") from None
        defaults = inherited + [(d.attrib["name"], d.attrib.get("value", "")) for d in doc.iter("default")
                                if "name" in d.attrib]
        for what, reference in _references(doc):
            for value in dict.fromkeys(_substituted(reference, defaults)):
                if "$" in value and not allow_outside_paths:
                    raise ValueError(f"scene: {file}: {what} {reference!r} uses a parameter without a <default>")
                target = confined_path(file, value, what if value == reference else f"{what} {reference!r} =",
                                       root=root, allow_outside=allow_outside_paths)
                if what == "<include filename>" and target.is_file():
                    pending.append((target, defaults))


def load_mitsuba_file(path: str | Path, *, allow_outside_paths: bool = False) -> tuple[list, LookAt | None]:
    """Read a Mitsuba 3 scene file: ``(objects, camera)`` (see the module docstring).

    Raises ``FileNotFoundError`` for a missing file, ``ValueError`` (one line naming the file) for a
    file Mitsuba cannot load, without shapes, or with a shape this tracer cannot represent, and
    ``ImportError`` naming the extra when ``mitsuba`` is missing. Files the scene names must be inside
    its folder unless ``allow_outside_paths`` (:func:`check_scene_references`).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene: no such file: {path}")
    check_scene_references(path, allow_outside_paths=allow_outside_paths)
    mi = _mitsuba()
    try:
        scene = mi.load_file(str(path))
    except Exception as err:  # Mitsuba raises RuntimeError with a multi-line parser message
        raise ValueError(f"scene: cannot read {path} as a Mitsuba 3 scene ({one_line(err)})") from None
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
    return objects, (_camera(mi, path, sensors[0]) if sensors else None)
