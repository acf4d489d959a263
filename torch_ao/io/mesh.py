"""Scenes from a user's mesh files: OBJ, PLY, STL, OFF, glTF/GLB... through trimesh.

* One :class:`~torch_ao.scene.Mesh` (one object id) per file, except glTF/GLB files,
  which give one per node that carries triangles (in the order of the node names), placed by the
  node's world transform.
* A glTF file's first perspective camera (``cameras``, on a node of the default scene, with its
  parents' transforms) becomes the scene's view: glTF cameras look down their local ``-Z`` with
  ``+Y`` up, the library's view convention, and ``yfov`` is the vertical field of view. A file whose
  cameras are all orthographic is refused, naming the camera (the tracer is perspective only).
* Without a camera, the view frames the meshes' bounding sphere from the front right, above
  (:func:`frame_view`).
* World space is the files' own (glTF: metres, ``+Y`` up) turned so that the file's up axis
  (``up_axis``, one of :data:`UP_AXES`; STL and many OBJ files are ``"z"`` up) is the library's
  ``+Y`` (:func:`up_axis_rotation`); an optional ground plane ``y = h``.

Errors (a missing file, a format trimesh cannot read, a file without triangles, a glTF without
meshes) are one-line messages that name the file: ``FileNotFoundError`` or ``ValueError``.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..checks import check_choice, check_float
from ..scene import LookAt, Mesh, Plane, Scene, Vec3
from .mitsuba import load_mitsuba_file
from .trimesh_file import GLTF_SUFFIXES, gltf_json, normalize_vertices, one_line, read_trimesh

__all__ = ["load_mesh_file", "mesh_scene", "frame_view", "gltf_camera", "UP_AXES", "up_axis_rotation"]


#: The up axes a mesh file may have (``up_axis``, ``torch-ao render --up-axis``).
UP_AXES = ("y", "z", "x", "-y", "-z", "-x")
#: Rows of the rotation taking each up axis to ``+Y``: proper rotations (no mirror, so triangle winding
#: and handedness are kept). ``"z"`` is Blender's and most CAD tools' convention, turned as Blender's
#: glTF exporter turns it: ``(x, y, z) -> (x, z, -y)``, so the front (``-Y``) faces ``+Z``.
_UP_ROWS = {"y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
            "x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)), "-y": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
            "-z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)), "-x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1))}


def up_axis_rotation(up_axis: str) -> torch.Tensor:
    """``(3,3)`` float64 rotation ``R`` taking a file whose up direction is ``up_axis`` (one of
    :data:`UP_AXES`) to the library's ``+Y`` up: world points are ``R @ p_file``."""
    check_choice("up_axis", up_axis, UP_AXES)
    return torch.tensor(_UP_ROWS[up_axis], dtype=torch.float64)


# ---------------------------------------------------------------------------------------- glTF camera
def _node_matrix(node: dict) -> np.ndarray:
    """A glTF node's local ``(4,4)`` transform: ``matrix`` (column-major) or ``T * R * S``."""
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    M = np.eye(4)
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    M[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    M[:3, :3] *= np.asarray(node.get("scale", (1.0, 1.0, 1.0)), dtype=np.float64)
    M[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return M


def _camera_type(camera) -> str | None:
    return camera.get("type") if isinstance(camera, dict) else None


def _yfov(camera: dict, index: int, path: Path) -> float:
    """``cameras[index].perspective.yfov`` (radians) of a perspective glTF camera, checked: a number in
    ``(0, pi)`` (``ValueError`` naming the file and the key otherwise)."""
    key = f"cameras[{index}].perspective.yfov"
    perspective = camera.get("perspective")
    if not isinstance(perspective, dict) or "yfov" not in perspective:
        raise ValueError(f"mesh: {path}: {key}: a perspective camera needs its 'perspective' block with 'yfov'")
    try:
        return check_float(key, perspective["yfov"], 0.0, math.pi, open_minimum=True, open_maximum=True)
    except ValueError as err:
        raise ValueError(f"mesh: {path}: {err} (radians)") from None


def gltf_camera(path: str | Path) -> LookAt | None:
    """The first perspective camera of a glTF/GLB file's default scene as a :class:`LookAt`, or ``None``.

    The camera node's world transform (parents included; scale removed) gives the eye (its
    origin), the viewing direction (its ``-Z`` axis) and ``up`` (its ``+Y`` axis); ``yfov``
    (radians) the vertical field of view. Orthographic cameras cannot be rendered: they are passed
    over for a perspective one, and a scene whose cameras are all orthographic is refused
    (``ValueError`` naming the first of them).
    """
    path = Path(path)
    header = gltf_json(path)
    try:
        return _first_camera(header, path)
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as err:
        if str(path) in str(err):
            raise
        raise ValueError(f"mesh: {path}: malformed glTF scene graph ({one_line(err)})") from None


def _first_camera(header: dict, path: Path) -> LookAt | None:
    """:func:`gltf_camera` on the parsed JSON (malformed parts raise whatever they raise; the caller
    names the file)."""
    if not isinstance(header, dict):
        raise ValueError(f"mesh: {path}: expected a JSON object, got {type(header).__name__}")
    nodes, cameras = header.get("nodes", []), header.get("cameras", [])
    scenes = header.get("scenes", [])
    roots = scenes[header.get("scene", 0)].get("nodes", []) if scenes else range(len(nodes))
    stack = [(int(i), np.eye(4)) for i in reversed(list(roots))]
    seen, orthographic = set(), None
    while stack:
        i, parent = stack.pop()
        if i in seen or not 0 <= i < len(nodes):
            continue
        seen.add(i)
        node = nodes[i]
        world = parent @ _node_matrix(node)
        if not np.isfinite(world).all():
            raise ValueError(f"mesh: {path}: nodes[{i}]: non-finite transform")
        cam = node.get("camera")
        if orthographic is None and isinstance(cam, int) and 0 <= cam < len(cameras) \
                and _camera_type(cameras[cam]) == "orthographic":
            orthographic = (cam, cameras[cam].get("name"), node.get("name", f"nodes[{i}]"))
        if isinstance(cam, int) and 0 <= cam < len(cameras) and _camera_type(cameras[cam]) == "perspective":
            yfov = _yfov(cameras[cam], cam, path)
            R = world[:3, :3] / np.linalg.norm(world[:3, :3], axis=0)
            eye = world[:3, 3]
            return LookAt(eye=eye.tolist(), target=(eye - R[:, 2]).tolist(), up=R[:, 1].tolist(),
                          fov_y_degrees=math.degrees(yfov))
        stack.extend((int(c), world) for c in reversed(node.get("children", [])))
    if orthographic is not None:
        cam, name, node_name = orthographic
        named = f" {name!r}" if name else ""
        raise ValueError(f"camera: {path}: cameras[{cam}]{named} (node {node_name!r}) is an orthographic camera, which "
                         "torch_ao cannot render; only perspective cameras are supported (add one, or delete the camera "
                         "to frame the meshes)")
    return None


# ---------------------------------------------------------------------------------------- meshes
def load_mesh_file(path: str | Path, *, albedo: Vec3 = (0.8, 0.8, 0.8), normalize: bool = False,
                   up_axis: str = "y", allow_outside_paths: bool = False) -> tuple[list[Mesh], LookAt | None]:
    """Read a mesh file: ``(meshes, camera)``.

    Args:
        path: OBJ, PLY, STL, OFF, glTF/GLB or any other format trimesh reads.
        albedo: linear RGB of every mesh of the file.
        normalize: scale the file's meshes together to a largest extent of 1, resting on ``y = 0``,
            centred on the ``y`` axis (a glTF camera moves with them).
        up_axis: the file's up direction, one of :data:`UP_AXES` (``"z"`` for most STL files and
            Z-up OBJ exports); the meshes (and a glTF camera) are turned so that it becomes ``+Y``
            (:func:`up_axis_rotation`), before ``normalize``.
        allow_outside_paths: let the file name files (materials, glTF buffers and images) outside its
            folder; by default they are refused (:mod:`~torch_ao.io.confine`).
    Returns:
        one :class:`Mesh` per file (all parts concatenated) or, for glTF/GLB, one per node with
        triangles (node-name order, world transforms applied; names ``"file.glb:node"``), and the
        file's glTF camera (:func:`gltf_camera`) or ``None``.
    """
    path = Path(path)
    R = up_axis_rotation(up_axis)
    if path.suffix.lower() in GLTF_SUFFIXES:
        parts, camera = _gltf_parts(path, allow_outside_paths), gltf_camera(path)
    else:
        mesh = Mesh.load(path, albedo=albedo, allow_outside_paths=allow_outside_paths)
        parts, camera = [(mesh.name, mesh.vertices, mesh.faces)], None
    verts = [torch.as_tensor(v, dtype=torch.float64) @ R.T for _, v, _ in parts]
    offset, scale = torch.zeros(3, dtype=torch.float64), 1.0
    if normalize:
        _, offset, scale = normalize_vertices(torch.cat(verts), path)
        verts = [(v - offset) / scale for v in verts]
    if camera is not None and (normalize or up_axis != "y"):
        eye, target, up = (R @ torch.tensor(x, dtype=torch.float64) for x in (camera.eye, camera.target, camera.up))
        eye_n = (eye - offset) / scale
        camera = dataclasses.replace(camera, eye=eye_n.tolist(), target=(eye_n + target - eye).tolist(), up=up.tolist())
    meshes = [Mesh(albedo=albedo, vertices=v, faces=torch.as_tensor(f).long(), name=name)
              for (name, _, f), v in zip(parts, verts)]
    return meshes, camera


def _gltf_parts(path: Path, allow_outside_paths: bool) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name "file.glb:node", world vertices (V,3), faces (F,3))`` of each glTF node with triangles."""
    scene = read_trimesh(path, process=False, allow_outside_paths=allow_outside_paths)
    parts = []
    graph = getattr(scene, "graph", None)
    for node in sorted(graph.nodes_geometry) if graph is not None else []:
        matrix, geom_name = graph[node]
        geom = scene.geometry[geom_name]
        faces = getattr(geom, "faces", None)
        if faces is None or len(faces) == 0:
            continue  # points or lines
        v = np.asarray(geom.vertices, dtype=np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        parts.append((f"{path.name}:{node}", v, np.asarray(faces)))
    if not parts:
        raise ValueError(f"mesh: {path} has no meshes (no node of its scene carries triangles)")
    return parts


def frame_view(lo: Vec3, hi: Vec3, fov_y_degrees: float = 60.0) -> LookAt:
    """A view of the box ``[lo, hi]``: looks at its centre from the front right (``+X, +Y, +Z``),
    far enough that its bounding sphere fits the vertical field of view."""
    lo, hi = torch.as_tensor(lo, dtype=torch.float64), torch.as_tensor(hi, dtype=torch.float64)
    centre = (lo + hi) / 2
    radius = max(float((hi - lo).norm()) / 2, 1e-6)
    direction = torch.tensor([0.55, 0.45, 1.0], dtype=torch.float64)
    distance = 1.05 * radius / math.sin(math.radians(fov_y_degrees) / 2)
    eye = centre + distance * direction / direction.norm()
    return LookAt(eye=eye.tolist(), target=centre.tolist(), fov_y_degrees=fov_y_degrees)


def mesh_scene(paths: Sequence[str | Path], *, ground_plane: float | bool | None = None,
               normalize: bool = False, up_axis: str = "y", progress: bool = False,
               allow_outside_paths: bool = False) -> Scene:
    """A scene made of mesh files (and Mitsuba 3 scene files) alone.

    Args:
        paths: one or more mesh files (:func:`load_mesh_file`) or Mitsuba 3 ``.xml`` scene files
            (:func:`~torch_ao.io.mitsuba.load_mitsuba_file`); object ids 1, 2, ... in
            file order (glTF: one per node, Mitsuba: one per shape), then the ground plane.
        ground_plane: ``None``/``False`` for none, ``True`` for a plane ``y = min y`` of the meshes
            (they rest on it), or a height ``h`` for the plane ``y = h`` (world units).
        normalize: normalise each file (see :func:`load_mesh_file`).
        up_axis: the mesh files' up direction, one of :data:`UP_AXES` (see :func:`load_mesh_file`);
            not for Mitsuba files (their cameras and shapes are placed in one world already).
        progress: a tqdm bar over the files (triangles read so far).
        allow_outside_paths: let the files name files outside their folders (Mitsuba includes and
            shapes, glTF buffers, materials); by default refused (:mod:`~torch_ao.io.confine`).
    Returns:
        a :class:`Scene` whose view is the first file camera found (glTF or Mitsuba), else :func:`frame_view` of the
        meshes; its ``description`` says which.
    """
    from tqdm.auto import tqdm

    paths = [Path(p) for p in paths]
    check_choice("up_axis", up_axis, UP_AXES)
    if not paths:
        raise ValueError("paths: expected at least one mesh file")
    meshes, view, source = [], None, ""  # meshes: every object read (Mitsuba spheres too)
    bar = tqdm(paths, desc="load meshes", unit="file", disable=not progress, leave=False)
    for path in bar:
        if path.suffix.lower() == ".xml":
            if normalize:
                raise ValueError(f"normalize: not for Mitsuba scene files ({path.name})")
            if up_axis != "y":
                raise ValueError(f"up_axis: not for Mitsuba scene files ({path.name}); it turns mesh files only")
            found, camera = load_mitsuba_file(path, allow_outside_paths=allow_outside_paths)
        else:
            found, camera = load_mesh_file(path, normalize=normalize, up_axis=up_axis,
                                           allow_outside_paths=allow_outside_paths)
        meshes += found
        if view is None and camera is not None:
            view, source = camera, f"camera of {path.name}"
        bar.set_postfix(triangles=sum(m.faces.shape[0] for m in meshes if isinstance(m, Mesh)))
    bar.close()
    names = ", ".join(p.name for p in paths)
    scene = Scene(meshes, name=paths[0].stem if len(paths) == 1 else "meshes")
    lo, hi = scene.bounds()
    if view is None:
        view, source = frame_view(lo, hi), "framing the meshes"
    if ground_plane is not None and ground_plane is not False:
        height = float(lo[1]) if ground_plane is True else check_float("ground_plane", ground_plane)
        scene = scene.add(Plane(point=(0.0, height, 0.0), normal=(0.0, 1.0, 0.0)))
    scene.view, scene.description = view, f"{len(meshes)} meshes from {names}; view: {source}"
    return scene
