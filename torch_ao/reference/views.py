"""Batched views for the tracer: a :class:`~torch_ao.camera.PinholeCamera` plus world->view transforms.

View space is the library's OpenGL convention (camera looks down ``-Z``, ``+Y`` up); pixel centres
are at integer ``(u, v)`` with row 0 at the top (see :mod:`torch_ao.camera`).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..camera import PinholeCamera

__all__ = ["Views", "look_at", "look_at_matrix"]


def _vecs(name: str, x, batch: int | None = None) -> torch.Tensor:
    t = torch.as_tensor(x, dtype=torch.float64)
    if t.dim() == 1:
        t = t.unsqueeze(0)
    if t.dim() != 2 or t.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (3,) or (B,3), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: expected finite values")
    return t


def look_at_matrix(eye, target, up=(0.0, 1.0, 0.0)) -> torch.Tensor:
    """``(B,4,4)`` float64 world->view matrices (OpenGL ``gluLookAt``) for ``(3,)`` or ``(B,3)`` inputs."""
    eye, target, up = _vecs("eye", eye), _vecs("target", target), _vecs("up", up)
    B = max(eye.shape[0], target.shape[0], up.shape[0])
    try:
        eye, target, up = (x.expand(B, 3) for x in (eye, target, up))
    except RuntimeError:
        raise ValueError(f"eye/target/up: batch sizes {eye.shape[0]}, {target.shape[0]}, {up.shape[0]} do not broadcast") from None
    f = target - eye
    if bool((f.norm(dim=1) < 1e-12).any()):
        raise ValueError("eye/target: eye and target must differ")
    f = f / f.norm(dim=1, keepdim=True)
    s = torch.linalg.cross(f, up, dim=1)
    if bool((s.norm(dim=1) < 1e-9 * up.norm(dim=1)).any()):
        raise ValueError("up: must not be parallel to the viewing direction (target - eye)")
    s = s / s.norm(dim=1, keepdim=True)
    u = torch.linalg.cross(s, f, dim=1)
    M = torch.zeros(B, 4, 4, dtype=torch.float64)
    M[:, 0, :3], M[:, 1, :3], M[:, 2, :3] = s, u, -f
    M[:, :3, 3] = -torch.einsum("bij,bj->bi", M[:, :3, :3], eye)
    M[:, 3, 3] = 1
    return M


@dataclass(frozen=True)
class Views:
    """``camera`` (batch B) and ``world_to_view (B,4,4)`` rigid transforms (float64)."""

    camera: PinholeCamera
    world_to_view: torch.Tensor

    def __post_init__(self) -> None:
        if not isinstance(self.camera, PinholeCamera):
            raise TypeError(f"camera: expected a torch_ao.PinholeCamera, got {type(self.camera).__name__}")
        M = torch.as_tensor(self.world_to_view, dtype=torch.float64)
        if M.dim() == 2:
            M = M.unsqueeze(0)
        if M.dim() != 3 or M.shape[1:] != (4, 4):
            raise ValueError(f"world_to_view: expected shape (B,4,4) or (4,4), got {tuple(M.shape)}")
        R = M[:, :3, :3]
        if not bool(torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=M.dtype).expand_as(R), atol=1e-5)):
            raise ValueError("world_to_view: the 3x3 block must be a rotation (no scale or shear)")
        B = max(M.shape[0], self.camera.batch_size)
        if M.shape[0] not in (1, B):
            raise ValueError(f"world_to_view: {M.shape[0]} matrices for a camera batch of {self.camera.batch_size}")
        object.__setattr__(self, "world_to_view", M.expand(B, 4, 4).cpu())
        object.__setattr__(self, "camera", self.camera.expand(B))

    @property
    def batch_size(self) -> int:
        return self.world_to_view.shape[0]

    @property
    def eye(self) -> torch.Tensor:
        """``(B,3)`` camera positions in world space."""
        R, t = self.world_to_view[:, :3, :3], self.world_to_view[:, :3, 3]
        return -torch.einsum("bji,bj->bi", R, t)


def look_at(eye, target, up=(0.0, 1.0, 0.0), fov_y_degrees=60.0, *, height: int, width: int,
            principal_offset: tuple[float, float] = (0.0, 0.0)) -> Views:
    """Views from look-at parameters (``(3,)`` or ``(B,3)``) and vertical fov (float or ``(B,)``).

    ``principal_offset``: ``(dx, dy)``, the principal point's offset from the image centre in fractions
    of the width and height (``+x`` right, ``+y`` down; ``fov_y_degrees`` is then the FOV of the centred
    camera with the same focal length): ``cx = (W - 1) / 2 + dx W``, ``cy = (H - 1) / 2 + dy H``.
    """
    M = look_at_matrix(eye, target, up)
    fov = torch.as_tensor(fov_y_degrees, dtype=torch.float64).reshape(-1)
    B = max(M.shape[0], fov.numel())
    cam = PinholeCamera.from_fov(fov, height, width, batch_size=B)
    dx, dy = (float(x) for x in principal_offset)
    if dx or dy:
        K = cam.intrinsics.clone()
        K[:, 0, 2] += dx * width
        K[:, 1, 2] += dy * height
        cam = PinholeCamera(K, height, width)
    return Views(cam, M.expand(B, 4, 4))
