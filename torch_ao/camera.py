"""Pinhole camera: intrinsics, OpenGL projection, depth <-> view-space positions.

Conventions (see DESIGN.md):

* Pixel ``(u, v)`` = (column, row); the *centre* of pixel ``(i, j)`` is at ``(u, v) = (i, j)``
  (kornia / OpenCV convention) and row 0 is the top of the image.
* View space is right-handed OpenGL: the camera looks down ``-Z``, ``+Y`` is up, ``+X`` right.
* ``depth`` is the positive distance along the view axis: ``z_view = -depth``.

So a pixel ``(u, v)`` with depth ``d`` is the view-space point
``((u - cx) / fx * d, -(v - cy) / fy * d, -d)``. kornia does the OpenCV unprojection
(``+Y`` down, ``+Z`` forward); we flip Y and Z.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.depth import depth_to_3d_v2

from .checks import to_arguments

__all__ = ["PinholeCamera", "pixels_to_view", "view_to_pixels", "MIN_FOCAL_RATIO", "MAX_FOCAL_RATIO",
           "MAX_PRINCIPAL_OFFSET"]

#: Focal lengths ``fx``, ``fy`` below this times the image's larger side are refused: a centred camera's
#: field of view across that side would exceed 179.88 degrees, and view-space positions (``(u - cx) / fx * depth``) would
#: be thousands of times their depth, which overflows float32 squares.
MIN_FOCAL_RATIO = 1e-3
#: ... and above this times the larger side (a field of view under 6e-8 degrees, offsets that vanish).
MAX_FOCAL_RATIO = 1e9
#: The principal point ``cx``, ``cy`` must lie within this many image sizes (the larger side) of the image's
#: centre (off-axis crops of a wider view put it outside the image, a few sizes away at most).
MAX_PRINCIPAL_OFFSET = 4.0

# Flips an OpenCV camera frame (x right, y down, z forward) into OpenGL view space.
_CV_TO_GL = (1.0, -1.0, -1.0)


def _check_intrinsics(K: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``K`` as ``(B,3,3)``, or an error naming the first entry out of range. The values are checked on K's device
    and read back once (on a GPU, one wait); only a refused camera's message reads more."""
    if not isinstance(K, torch.Tensor):
        raise TypeError(f"intrinsics: expected a torch.Tensor of shape (B,3,3), got {type(K).__name__}")
    if K.dim() == 2:
        K = K.unsqueeze(0)
    if K.dim() != 3 or K.shape[-2:] != (3, 3):
        raise ValueError(f"intrinsics: expected shape (B,3,3) or (3,3), got {tuple(K.shape)}")
    if not K.is_floating_point():
        raise TypeError(f"intrinsics: expected a floating-point tensor, got {K.dtype}")
    with torch.no_grad():
        ok = torch.isfinite(K).all()
        for _, bad, _ in _out_of_range(K, height, width):
            ok = ok & ~bad.any()
    if not bool(ok):
        _refuse(K, height, width)
    return K


def _out_of_range(K: torch.Tensor, height: int, width: int):
    """Per intrinsic, its error's message, ``(B,)`` bool where it lies outside what a real camera of this image size
    has (see :data:`MIN_FOCAL_RATIO`, :data:`MAX_FOCAL_RATIO`, :data:`MAX_PRINCIPAL_OFFSET`), and its ``(B,)`` values."""
    size = max(height, width)
    lo, hi = MIN_FOCAL_RATIO * size, MAX_FOCAL_RATIO * size
    for name, value in (("fx", K[:, 0, 0]), ("fy", K[:, 1, 1])):
        yield (f"intrinsics: {name} must be in [{lo:g}, {hi:g}] pixels for a {width}x{height} image (a field of view "
               f"across the larger side between 6e-8 and 179.88 degrees), got", ~((value >= lo) & (value <= hi)), value)
    for name, value, extent in (("cx", K[:, 0, 2], width), ("cy", K[:, 1, 2], height)):
        centre, reach = (extent - 1) / 2, MAX_PRINCIPAL_OFFSET * size
        yield (f"intrinsics: {name} must be within {reach:g} pixels of the image centre {centre:g}, got",
               ~((value - centre).abs() <= reach), value)


def _refuse(K: torch.Tensor, height: int, width: int) -> None:
    """Raise the error of the first check that ``K`` fails."""
    if not bool(torch.isfinite(K).all()):
        raise ValueError("intrinsics: every entry must be finite")
    if bool((K[:, 0, 0] <= 0).any()) or bool((K[:, 1, 1] <= 0).any()):
        raise ValueError("intrinsics: focal lengths K[:,0,0] and K[:,1,1] must be > 0")
    for message, bad, value in _out_of_range(K, height, width):
        if bool(bad.any()):
            raise ValueError(f"{message} {float(value[bad][0]):g}")


def _check_size(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")


@dataclass(frozen=True)
class PinholeCamera:
    """A batch of pinhole cameras sharing one image size.

    Attributes:
        intrinsics: ``(B, 3, 3)`` kornia-style matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``
            in pixels.
        height, width: image size in pixels.

    Shape:
        - ``intrinsics``: ``(B, 3, 3)`` (pixels); ``fx``, ``fy``, ``cx``, ``cy``: ``(B,)``, the dtype of the intrinsics.
        - :meth:`unproject`: depth ``(B, 1, H, W)`` (world units) -> view-space positions ``(B, 3, H, W)`` (world
          units, OpenGL axes: the camera looks down -Z); :meth:`pixel_rays`: ``(B, 3, H, W)``.
        - :meth:`pixel_to_view`: pixel ``u``, ``v`` (pixels) and depth of one shape ``(...)`` -> points ``(..., 3)``;
          :meth:`view_to_pixel` the inverse. Results take the input's dtype.
    """

    intrinsics: torch.Tensor
    height: int
    width: int

    def __post_init__(self) -> None:
        for name in ("height", "width"):
            _check_size(name, getattr(self, name))
        object.__setattr__(self, "intrinsics", _check_intrinsics(self.intrinsics, self.height, self.width))

    @classmethod
    def _of_checked(cls, intrinsics: torch.Tensor, height: int, width: int) -> "PinholeCamera":
        """A camera of intrinsics already checked for this image size (a checked camera's, moved, converted between
        float32 and float64, or expanded), without checking them again."""
        camera = object.__new__(cls)
        for name, value in (("intrinsics", intrinsics), ("height", height), ("width", width)):
            object.__setattr__(camera, name, value)
        return camera

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_fov(
        cls,
        fov_y_degrees: float | torch.Tensor,
        height: int,
        width: int,
        batch_size: int = 1,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> "PinholeCamera":
        """Centred camera with square pixels and vertical field of view ``fov_y_degrees``.

        ``fov_y_degrees`` may be a float or a ``(B,)`` tensor (one per view).
        """
        _check_size("height", height)
        _check_size("width", width)
        fov = torch.as_tensor(fov_y_degrees, dtype=dtype, device=device).reshape(-1)
        if not bool((torch.isfinite(fov) & (fov > 0) & (fov < 180)).all()):
            raise ValueError(f"fov_y_degrees: expected values in (0, 180), got {fov.tolist()}")
        if fov.numel() == 1:
            fov = fov.expand(batch_size)
        elif batch_size not in (1, fov.numel()):
            raise ValueError(f"fov_y_degrees: {fov.numel()} values for batch_size={batch_size}")
        f = 0.5 * height / torch.tan(torch.deg2rad(fov) * 0.5)
        K = torch.zeros(fov.numel(), 3, 3, dtype=dtype, device=device)
        K[:, 0, 0] = f
        K[:, 1, 1] = f
        K[:, 0, 2] = (width - 1) * 0.5
        K[:, 1, 2] = (height - 1) * 0.5
        K[:, 2, 2] = 1.0
        return cls(K, height, width)

    @classmethod
    def from_opengl_projection(cls, projection: torch.Tensor, height: int, width: int) -> "PinholeCamera":
        """Inverse of :meth:`opengl_projection` (reads the 2x3 upper-left block)."""
        P = projection if projection.dim() == 3 else projection.unsqueeze(0)
        if P.shape[-2:] != (4, 4):
            raise ValueError(f"projection: expected shape (B,4,4) or (4,4), got {tuple(projection.shape)}")
        K = torch.zeros(P.shape[0], 3, 3, dtype=P.dtype, device=P.device)
        K[:, 0, 0] = P[:, 0, 0] * width / 2
        K[:, 1, 1] = P[:, 1, 1] * height / 2
        K[:, 0, 2] = ((1 - P[:, 0, 2]) * width - 1) / 2
        K[:, 1, 2] = ((1 + P[:, 1, 2]) * height - 1) / 2
        K[:, 2, 2] = 1.0
        return cls(K, height, width)

    # ------------------------------------------------------------------ properties
    @property
    def batch_size(self) -> int:
        return self.intrinsics.shape[0]

    @property
    def fx(self) -> torch.Tensor:
        return self.intrinsics[:, 0, 0]

    @property
    def fy(self) -> torch.Tensor:
        return self.intrinsics[:, 1, 1]

    @property
    def cx(self) -> torch.Tensor:
        return self.intrinsics[:, 0, 2]

    @property
    def cy(self) -> torch.Tensor:
        return self.intrinsics[:, 1, 2]

    @property
    def fov_y_degrees(self) -> torch.Tensor:
        """``(B,)`` vertical field of view of a centred camera."""
        return torch.rad2deg(2 * torch.atan(0.5 * self.height / self.fy))

    def to(self, device=None, dtype=None) -> "PinholeCamera":
        """A copy on ``device`` (and in ``dtype``); as ``Tensor.to``, ``camera.to(torch.float64)`` changes the dtype
        alone."""
        device, dtype = to_arguments(device, dtype)
        K = self.intrinsics.to(device=device, dtype=dtype)
        if K.dtype in (torch.float32, torch.float64):  # (every range holds in both: fx <= 1e9 x 16384 pixels)
            return PinholeCamera._of_checked(K, self.height, self.width)
        return PinholeCamera(K, self.height, self.width)

    def expand(self, batch_size: int) -> "PinholeCamera":
        """The same camera repeated to ``batch_size`` views (a no-op when sizes match)."""
        if self.batch_size == batch_size:
            return self
        if self.batch_size != 1:
            raise ValueError(f"camera: batch of {self.batch_size} cannot serve a batch of {batch_size}")
        return PinholeCamera._of_checked(self.intrinsics.expand(batch_size, 3, 3), self.height, self.width)

    # ------------------------------------------------------------------ projection matrices
    def opengl_projection(self, near: float = 0.01, far: float = 1000.0) -> torch.Tensor:
        """``(B, 4, 4)`` OpenGL projection matrix (clip = P @ view), NDC y up, pixel centres at +0.5."""
        if not (0 < near < far):
            raise ValueError(f"near/far: expected 0 < near < far, got near={near}, far={far}")
        B = self.batch_size
        P = torch.zeros(B, 4, 4, dtype=self.intrinsics.dtype, device=self.intrinsics.device)
        P[:, 0, 0] = 2 * self.fx / self.width
        P[:, 1, 1] = 2 * self.fy / self.height
        P[:, 0, 2] = 1 - (2 * self.cx + 1) / self.width
        P[:, 1, 2] = (2 * self.cy + 1) / self.height - 1
        P[:, 2, 2] = -(far + near) / (far - near)
        P[:, 2, 3] = -2 * far * near / (far - near)
        P[:, 3, 2] = -1.0
        return P

    # ------------------------------------------------------------------ points
    def unproject(self, depth: torch.Tensor) -> torch.Tensor:
        """View-space positions ``(B, 3, H, W)`` of a depth map ``(B, 1, H, W)`` (kornia)."""
        K = self.intrinsics.expand(depth.shape[0], 3, 3).to(depth.dtype)
        points_cv = depth_to_3d_v2(depth[:, 0], K)  # (B, H, W, 3) in OpenCV axes
        flip = depth.new_tensor(_CV_TO_GL)
        return (points_cv * flip).permute(0, 3, 1, 2)

    def pixel_to_view(self, u: torch.Tensor, v: torch.Tensor, depth: torch.Tensor, batch_index: torch.Tensor | None = None) -> torch.Tensor:
        """View-space points ``(..., 3)`` for pixel coordinates and depths of equal shape.

        ``batch_index`` selects the camera of each point (default: broadcast over a leading B axis).
        """
        return pixels_to_view(u, v, depth, *self._per_point(batch_index, u))

    def view_to_pixel(self, points: torch.Tensor, batch_index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Pixel ``u``, ``v`` and ``depth`` of view-space points ``(..., 3)``."""
        depth = -points[..., 2]
        u, v = view_to_pixels(points, depth, *self._per_point(batch_index, depth))
        return u, v, depth

    def pixel_rays(self) -> torch.Tensor:
        """``(B, 3, H, W)`` view-space directions (not normalised) with ``z = -1`` through pixel centres."""
        ones = torch.ones(self.batch_size, 1, self.height, self.width, dtype=self.intrinsics.dtype, device=self.intrinsics.device)
        return self.unproject(ones)

    def _per_point(self, batch_index, like: torch.Tensor):
        params = (self.fx, self.fy, self.cx, self.cy)
        if batch_index is not None:
            return tuple(p.to(like.dtype)[batch_index] for p in params)
        shape = (-1,) + (1,) * (like.dim() - 1)
        if self.batch_size == 1:
            return tuple(p.to(like.dtype).reshape(()) for p in params)
        return tuple(p.to(like.dtype).reshape(shape) for p in params)


def pixels_to_view(u: torch.Tensor, v: torch.Tensor, depth: torch.Tensor, fx, fy, cx, cy) -> torch.Tensor:
    """View-space points ``(..., 3)`` at pixel coordinates ``u``, ``v`` and positive ``depth`` (equal
    shapes ``(...)``; intrinsics in pixels, broadcastable): ``((u - cx) / fx d, -(v - cy) / fy d, -d)``."""
    return torch.stack(((u - cx) / fx * depth, -(v - cy) / fy * depth, -depth), dim=-1)


def view_to_pixels(points: torch.Tensor, depth: torch.Tensor, fx, fy, cx, cy) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates ``u``, ``v`` ``(...)`` of view-space ``points`` ``(..., 3)`` seen at ``depth``
    ``(...)`` (normally ``-z``; a caller may pass a clamped one): the inverse of :func:`pixels_to_view`."""
    return points[..., 0] / depth * fx + cx, -points[..., 1] / depth * fy + cy
