"""Scene description: analytic primitives, triangle meshes, a light and a default view.

World space is right-handed with ``+Y`` up (the built-in scenes put the ground at ``y = 0``).
Lengths are in world units; albedo is linear RGB in ``[0, 1]``.

Every object is two-sided: a ray hits its front or back face alike (back faces occlude), and the
G-buffer flips normals to face the camera. Primitives:

* :class:`Plane` - an infinite plane through ``point`` with unit ``normal``.
* :class:`Sphere` - ``center``, ``radius``.
* :class:`Box` - an oriented box: ``center``, ``half_extents`` and a ``rotation`` whose columns are
  the box's local axes in world space.
* :class:`Cylinder` - a capped cylinder: ``center``, unit ``axis``, ``radius``, ``half_height``.
* :class:`Mesh` - triangles ``vertices (V,3)`` and ``faces (F,3)``; :meth:`Mesh.load` reads OBJ, PLY,
  GLB... through trimesh (imported only when a file is loaded).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence, Union

import torch

__all__ = [
    "Plane", "Sphere", "Box", "Cylinder", "Mesh", "Light", "LookAt", "Scene", "Primitive", "FOV_AXES",
    "rotation_y", "rotation_from_axis_angle",
]

Vec3 = Union[Sequence[float], torch.Tensor]


def _vec3(name: str, value, *, unit: bool = False) -> tuple[float, float, float]:
    try:
        t = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name}: expected 3 numbers, got {value!r}") from None
    if t.numel() != 3:
        raise ValueError(f"{name}: expected 3 numbers, got {t.numel()}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: expected finite values, got {t.tolist()}")
    if unit:
        n = float(t.norm())
        if n < 1e-12:
            raise ValueError(f"{name}: expected a non-zero vector")
        t = t / n
    return tuple(float(x) for x in t)


def _positive(name: str, value) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: expected a finite value > 0, got {value!r}")
    return v


def _albedo(value) -> tuple[float, float, float]:
    if isinstance(value, (int, float)):
        value = (value, value, value)
    a = _vec3("albedo", value)
    if min(a) < 0 or max(a) > 1:
        raise ValueError(f"albedo: expected RGB values in [0, 1], got {a}")
    return a


def rotation_from_axis_angle(axis: Vec3, angle: float) -> torch.Tensor:
    """``(3,3)`` float64 rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    x, y, z = _vec3("axis", axis, unit=True)
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    return torch.tensor([
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ], dtype=torch.float64)


def rotation_y(angle: float) -> torch.Tensor:
    """``(3,3)`` rotation by ``angle`` radians about ``+Y``."""
    return rotation_from_axis_angle((0, 1, 0), angle)


@dataclass
class _Object:
    albedo: Vec3 = (0.8, 0.8, 0.8)
    object_id: int | None = None  # None: assigned by the Scene (1, 2, ...); 0 is background

    def _check_common(self) -> None:
        self.albedo = _albedo(self.albedo)
        if self.object_id is not None:
            if isinstance(self.object_id, bool) or not isinstance(self.object_id, int) or self.object_id < 1:
                raise ValueError(f"object_id: expected an integer >= 1 (0 is background), got {self.object_id!r}")

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Axis-aligned ``(lo, hi)`` float64 bounds, or ``None`` when unbounded."""
        return None


@dataclass
class Plane(_Object):
    """Infinite two-sided plane through ``point`` with normal ``normal`` (normalised)."""

    point: Vec3 = (0.0, 0.0, 0.0)
    normal: Vec3 = (0.0, 1.0, 0.0)

    def __post_init__(self) -> None:
        self._check_common()
        self.point = _vec3("point", self.point)
        self.normal = _vec3("normal", self.normal, unit=True)


@dataclass
class Sphere(_Object):
    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 1.0

    def __post_init__(self) -> None:
        self._check_common()
        self.center = _vec3("center", self.center)
        self.radius = _positive("radius", self.radius)

    def bounds(self):
        c = torch.tensor(self.center, dtype=torch.float64)
        return c - self.radius, c + self.radius


@dataclass
class Box(_Object):
    """Oriented box. ``rotation`` ``(3,3)``: columns are the local x, y, z axes in world space."""

    center: Vec3 = (0.0, 0.0, 0.0)
    half_extents: Vec3 = (0.5, 0.5, 0.5)
    rotation: torch.Tensor | None = None

    def __post_init__(self) -> None:
        self._check_common()
        self.center = _vec3("center", self.center)
        self.half_extents = _vec3("half_extents", self.half_extents)
        if min(self.half_extents) <= 0:
            raise ValueError(f"half_extents: expected values > 0, got {self.half_extents}")
        R = torch.eye(3, dtype=torch.float64) if self.rotation is None else torch.as_tensor(self.rotation, dtype=torch.float64)
        if R.shape != (3, 3) or not bool(torch.allclose(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-6)):
            raise ValueError("rotation: expected an orthonormal (3,3) matrix")
        self.rotation = R

    def bounds(self):
        c = torch.tensor(self.center, dtype=torch.float64)
        r = self.rotation.abs() @ torch.tensor(self.half_extents, dtype=torch.float64)
        return c - r, c + r


@dataclass
class Cylinder(_Object):
    """Capped cylinder around unit ``axis`` through ``center``; length ``2 * half_height``."""

    center: Vec3 = (0.0, 0.0, 0.0)
    axis: Vec3 = (0.0, 1.0, 0.0)
    radius: float = 0.5
    half_height: float = 0.5

    def __post_init__(self) -> None:
        self._check_common()
        self.center = _vec3("center", self.center)
        self.axis = _vec3("axis", self.axis, unit=True)
        self.radius = _positive("radius", self.radius)
        self.half_height = _positive("half_height", self.half_height)

    def bounds(self):
        c = torch.tensor(self.center, dtype=torch.float64)
        a = torch.tensor(self.axis, dtype=torch.float64)
        r = a.abs() * self.half_height + self.radius * torch.sqrt((1 - a * a).clamp_min(0))
        return c - r, c + r


@dataclass
class Mesh(_Object):
    """Triangle mesh: ``vertices (V,3)`` float, ``faces (F,3)`` integer indices into vertices."""

    vertices: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    faces: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3, dtype=torch.long))
    name: str = "mesh"

    def __post_init__(self) -> None:
        self._check_common()
        v = torch.as_tensor(self.vertices, dtype=torch.float64)
        f = torch.as_tensor(self.faces)
        if v.dim() != 2 or v.shape[1] != 3:
            raise ValueError(f"vertices: expected shape (V,3), got {tuple(v.shape)}")
        if f.dim() != 2 or f.shape[1] != 3 or f.is_floating_point():
            raise ValueError(f"faces: expected an integer tensor of shape (F,3), got {tuple(f.shape)} {f.dtype}")
        if f.shape[0] == 0:
            raise ValueError(f"faces: mesh {self.name!r} has no triangles")
        if not bool(torch.isfinite(v).all()):
            raise ValueError(f"vertices: mesh {self.name!r} has non-finite vertices")
        f = f.long()
        if int(f.min()) < 0 or int(f.max()) >= v.shape[0]:
            raise ValueError(f"faces: indices must be in [0, {v.shape[0]}) for mesh {self.name!r}")
        self.vertices, self.faces = v, f

    @property
    def triangles(self) -> torch.Tensor:
        """``(F, 3, 3)`` float64 corner positions."""
        return self.vertices[self.faces]

    def bounds(self):
        return self.vertices.min(0).values, self.vertices.max(0).values

    @classmethod
    def load(cls, path, *, albedo: Vec3 = (0.8, 0.8, 0.8), object_id: int | None = None,
             normalize: bool = False, allow_outside_paths: bool = False) -> "Mesh":
        """Read a mesh file (OBJ, PLY, GLB, STL, OFF...) with trimesh; all parts are concatenated.

        ``normalize=True`` scales the mesh to a largest extent of 1 and rests it on ``y = 0``
        centred on the ``y`` axis. Files the mesh file names (materials, textures) must be inside its
        folder unless ``allow_outside_paths`` (:mod:`~torch_ao.io.confine`).
        """
        from pathlib import Path

        from .io.trimesh_file import normalize_vertices, read_trimesh

        path = Path(path)
        tm = read_trimesh(path, force="mesh", process=False, allow_outside_paths=allow_outside_paths)
        if not hasattr(tm, "faces") or len(tm.faces) == 0:
            raise ValueError(f"mesh: {path} has no triangles")
        v = torch.as_tensor(tm.vertices, dtype=torch.float64)
        if normalize:
            v = normalize_vertices(v, path)[0]
        return cls(albedo=albedo, object_id=object_id, vertices=v, faces=torch.as_tensor(tm.faces).long(), name=path.name)


Primitive = Union[Plane, Sphere, Box, Cylinder, Mesh]


@dataclass
class Light:
    """Scene light for the direct-light buffer.

    ``kind="directional"``: ``direction`` points *towards* the light (from the surface); irradiance
    on a surface facing it is ``intensity`` (RGB, W/m^2-like units).
    ``kind="point"``: at ``position``; irradiance at distance ``r`` facing it is ``intensity / r^2``.
    """

    kind: str = "directional"
    direction: Vec3 = (0.4, 1.0, 0.3)
    position: Vec3 = (0.0, 5.0, 0.0)
    intensity: Vec3 = (3.0, 3.0, 3.0)

    def __post_init__(self) -> None:
        if self.kind not in ("directional", "point"):
            raise ValueError(f"light kind: expected 'directional' or 'point', got {self.kind!r}")
        self.direction = _vec3("light direction", self.direction, unit=True)
        self.position = _vec3("light position", self.position)
        self.intensity = _vec3("light intensity", self.intensity)
        if min(self.intensity) < 0:
            raise ValueError(f"light intensity: expected values >= 0, got {self.intensity}")


#: What a :class:`LookAt`'s field of view is held on when it is rendered at another image size than its
#: ``film`` (Mitsuba's ``fov_axis``): the horizontal (``"x"``) or vertical (``"y"``) extent, the
#: ``"diagonal"``, or the ``"smaller"``/``"larger"`` side of each image.
FOV_AXES = ("x", "y", "diagonal", "smaller", "larger")


def _axis(fov_axis: str, width: int, height: int) -> str:
    """``fov_axis`` with ``"smaller"``/``"larger"`` resolved for a ``width x height`` image (as Mitsuba: a
    square image's smaller side is ``x``)."""
    if fov_axis == "smaller":
        return "y" if width > height else "x"
    if fov_axis == "larger":
        return "x" if width > height else "y"
    return fov_axis


def _half_tangent_per_vertical(axis: str, width: int, height: int) -> float:
    """``tan(fov_axis / 2) / tan(fov_y / 2)`` of a centred pinhole with square pixels, ``axis`` resolved."""
    return {"x": width / height, "y": 1.0, "diagonal": math.hypot(width, height) / height}[axis]


@dataclass
class LookAt:
    """A default view: ``eye``, ``target``, ``up`` and vertical field of view in degrees.

    A file's camera made for an image size also carries (all optional):

    * ``film``: ``(width, height)`` in pixels, the size rendered when no other is asked for (``torch-ao
      render`` without ``--width``/``--height``); ``fov_y_degrees`` is the vertical FOV at that size;
    * ``fov_axis`` (one of :data:`FOV_AXES`): at another size, the FOV along this axis is kept
      (:meth:`fov_y_at`), as Mitsuba does; without ``film`` the vertical FOV is kept;
    * ``principal_offset``: ``(dx, dy)``, the principal point's offset from the image centre in
      fractions of the image's width and height (``+x`` right, ``+y`` down): pixel
      ``cx = (W - 1) / 2 + dx W``, ``cy = (H - 1) / 2 + dy H`` at every size.
    """

    eye: Vec3 = (0.0, 1.0, 4.0)
    target: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 = (0.0, 1.0, 0.0)
    fov_y_degrees: float = 60.0
    film: tuple[int, int] | None = None
    fov_axis: str = "y"
    principal_offset: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        self.eye = _vec3("eye", self.eye)
        self.target = _vec3("target", self.target)
        self.up = _vec3("up", self.up, unit=True)
        if not (0 < float(self.fov_y_degrees) < 180):
            raise ValueError(f"fov: expected degrees in (0, 180), got {self.fov_y_degrees}")
        self.fov_y_degrees = float(self.fov_y_degrees)
        if self.film is not None:
            film = tuple(self.film)
            if len(film) != 2 or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in film):
                raise ValueError(f"film: expected (width, height) as two positive integers, got {self.film!r}")
            self.film = film
        if self.fov_axis not in FOV_AXES:
            raise ValueError(f"fov_axis: expected one of {FOV_AXES}, got {self.fov_axis!r}")
        offset = tuple(float(x) for x in self.principal_offset)
        if len(offset) != 2 or not all(math.isfinite(x) for x in offset):
            raise ValueError(f"principal_offset: expected two finite numbers, got {self.principal_offset!r}")
        self.principal_offset = offset

    def fov_y_at(self, width: int, height: int) -> float:
        """The vertical field of view (degrees) of this view rendered at ``width x height``: the FOV
        along ``fov_axis`` at ``film`` is kept (``fov_y_degrees`` itself without ``film``)."""
        if self.film is None or (width, height) == self.film:
            return self.fov_y_degrees
        w0, h0 = self.film
        half = math.tan(math.radians(self.fov_y_degrees) / 2)
        half *= _half_tangent_per_vertical(_axis(self.fov_axis, w0, h0), w0, h0)
        half /= _half_tangent_per_vertical(_axis(self.fov_axis, width, height), width, height)
        return math.degrees(2 * math.atan(half))


@dataclass
class Scene:
    """Objects (ids 1, 2, ... unless given; 0 is background), a light and a default view.

    ``scale`` is a characteristic length of the scene (the extent of its bounded objects, at least 1
    when it has none); ray-origin offsets against self-intersection are relative to it.
    """

    objects: list
    light: Light = field(default_factory=Light)
    view: LookAt = field(default_factory=LookAt)
    name: str = "custom"
    description: str = ""

    def __post_init__(self) -> None:
        self.objects = list(self.objects)
        if not self.objects:
            raise ValueError("objects: a scene needs at least one object")
        used = set()
        for obj in self.objects:
            if not isinstance(obj, (Plane, Sphere, Box, Cylinder, Mesh)):
                raise TypeError(f"objects: expected Plane, Sphere, Box, Cylinder or Mesh, got {type(obj).__name__}")
            if obj.object_id is not None:
                used.add(obj.object_id)
        next_id = 1
        for obj in self.objects:
            if obj.object_id is None:
                while next_id in used:
                    next_id += 1
                obj.object_id = next_id
                used.add(next_id)
        if not isinstance(self.light, Light):
            raise TypeError(f"light: expected a Light, got {type(self.light).__name__}")
        if not isinstance(self.view, LookAt):
            raise TypeError(f"view: expected a LookAt, got {type(self.view).__name__}")

    def add(self, obj: Primitive) -> "Scene":
        """A new scene with ``obj`` appended (ids re-assigned for objects without one)."""
        return Scene(self.objects + [obj], self.light, self.view, self.name, self.description)

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Axis-aligned ``(lo, hi)`` float64 bounds of the bounded objects, ``None`` when there are none."""
        boxes = [b for b in (o.bounds() for o in self.objects) if b is not None]
        if not boxes:
            return None
        return torch.stack([b[0] for b in boxes]).min(0).values, torch.stack([b[1] for b in boxes]).max(0).values

    @property
    def scale(self) -> float:
        box = self.bounds()
        return 1.0 if box is None else max(float((box[1] - box[0]).max()), 1e-3)
