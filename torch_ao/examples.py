"""Small analytic G-buffers made of planes, for examples, tests and the default of ``torch-ao ao``.

Each plane is ``dot(n, x) = c`` in view space; a pixel sees the nearest plane hit in front of the
camera (optionally limited to half-spaces so that a wall can end). These are exact, cheap, and
independent of the ray tracer in :mod:`torch_ao.reference`, so the screen-space methods can be
checked against closed forms on their own.
"""
from __future__ import annotations

import math

import torch

from .camera import PinholeCamera
from .gbuffer import GBuffer

__all__ = ["planes_gbuffer", "plane_gbuffer", "floor_wall_gbuffer", "crease_gbuffer", "example_gbuffer"]


def _rotation_x(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)


def planes_gbuffer(
    planes: list[tuple[tuple[float, float, float], float, list | None]],
    camera: PinholeCamera,
    *,
    dtype: torch.dtype = torch.float32,
    light_direction: tuple[float, float, float] | None = None,
    albedo: list[tuple[float, float, float]] | None = None,
) -> GBuffer:
    """Ray-cast a union of (clipped) planes in view space.

    Args:
        planes: ``[(normal, offset, clips), ...]``: points ``x`` with ``dot(normal, x) = offset``,
            kept where every clip ``(n2, c2)`` has ``dot(n2, x) <= c2`` (``clips`` may be None).
        camera: batch-1 camera.
        light_direction: optional view-space direction *toward* a directional light; fills
            ``light = albedo * max(0, n . l)`` (no shadows).
        albedo: per-plane RGB used for ``light`` (default white).
    """
    rays = camera.pixel_rays().to(torch.float64)[0].permute(1, 2, 0)  # (H,W,3), z = -1
    best_t = torch.full(rays.shape[:2], math.inf, dtype=torch.float64)
    best_n = torch.zeros_like(rays)
    best_id = torch.zeros(rays.shape[:2], dtype=torch.long)
    for i, (normal, offset, clips) in enumerate(planes):
        n = torch.tensor(normal, dtype=torch.float64)
        n = n / n.norm()
        denom = rays @ n
        t = torch.where(denom.abs() > 1e-12, offset / torch.where(denom.abs() > 1e-12, denom, torch.ones_like(denom)), torch.full_like(denom, math.inf))
        hit = rays * t[..., None]
        ok = (t > 0) & torch.isfinite(t)
        for n2, c2 in clips or []:
            ok &= hit @ torch.tensor(n2, dtype=torch.float64) <= c2 + 1e-9
        closer = ok & (t < best_t)
        best_t = torch.where(closer, t, best_t)
        face = torch.where((denom < 0)[..., None], n.expand_as(rays), -n.expand_as(rays))
        best_n = torch.where(closer[..., None], face, best_n)
        best_id = torch.where(closer, torch.full_like(best_id, i + 1), best_id)
    depth = best_t  # rays have z = -1, so t is the view-axis depth
    valid = torch.isfinite(depth)
    normals = torch.where(valid[..., None], best_n, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    light = None
    if light_direction is not None:
        l = torch.tensor(light_direction, dtype=torch.float64)
        l = l / l.norm()
        table = torch.tensor([(1.0, 1.0, 1.0)] + list(albedo or [(1.0, 1.0, 1.0)] * len(planes)), dtype=torch.float64)
        light = table[best_id] * (normals @ l).clamp_min(0)[..., None] * valid[..., None]
        light = light.permute(2, 0, 1)[None].to(dtype)
    return GBuffer(
        depth=depth[None, None].to(dtype),
        camera=camera.to(dtype=dtype),
        normals=normals.permute(2, 0, 1)[None].to(dtype),
        light=light,
        object_id=best_id[None, None],
    )


def plane_gbuffer(height: int = 48, width: int = 64, tilt_degrees: float = 60.0, distance: float = 4.0,
                  fov_y_degrees: float = 60.0, dtype: torch.dtype = torch.float32) -> GBuffer:
    """An infinite plane through ``(0, 0, -distance)``, its normal tilted ``tilt_degrees`` from
    the view axis toward +Y (0 = facing the camera)."""
    n = _rotation_x(math.radians(tilt_degrees)) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    cam = PinholeCamera.from_fov(fov_y_degrees, height, width)
    return planes_gbuffer([(tuple(n.tolist()), -distance * float(n[2]), None)], cam, dtype=dtype)


def floor_wall_gbuffer(height: int = 64, width: int = 64, wall_distance: float = 1.0, camera_height: float = 3.0,
                       fov_y_degrees: float = 60.0, pitch_degrees: float = -60.0, dtype: torch.dtype = torch.float32,
                       light_direction=None) -> tuple[GBuffer, torch.Tensor]:
    """A floor ``y = 0`` and an infinite wall ``x = wall_distance`` (world), seen from a camera at
    height ``camera_height`` above the origin pitched down by ``-pitch_degrees``.

    Returns the G-buffer and ``(B,1,H,W)`` each pixel's distance to the wall along the floor
    (``nan`` off the floor), for the closed form ``1 - (acos(k) - k sqrt(1-k^2)) / pi``.
    """
    R = _rotation_x(math.radians(pitch_degrees))  # world -> view rotation is R^T
    eye = torch.tensor([0.0, camera_height, 0.0], dtype=torch.float64)

    def world_plane(n_world, c_world):
        n = torch.tensor(n_world, dtype=torch.float64)
        n_view = R.T @ n
        return tuple(n_view.tolist()), float(c_world - n @ eye)

    floor_n, floor_c = world_plane((0.0, 1.0, 0.0), 0.0)
    wall_n, wall_c = world_plane((1.0, 0.0, 0.0), wall_distance)
    cam = PinholeCamera.from_fov(fov_y_degrees, height, width)
    gb = planes_gbuffer(
        [(floor_n, floor_c, [(wall_n, wall_c)]), (wall_n, wall_c, [(tuple(-x for x in floor_n), -floor_c)])],
        cam, dtype=dtype, light_direction=light_direction,
    )
    pos = gb.positions().to(torch.float64)[0].permute(1, 2, 0)
    world = pos @ R.T + eye
    on_floor = (gb.object_id[0, 0] == 1) & gb.valid[0, 0]
    dist = torch.where(on_floor, wall_distance - world[..., 0], torch.full_like(world[..., 0], math.nan))
    return gb, dist[None, None].to(dtype)


def crease_gbuffer(height: int = 48, width: int = 48, fov_y_degrees: float = 60.0, dtype=torch.float32) -> GBuffer:
    """A right-angle concave crease (two half-planes meeting along a vertical line in front of the camera)."""
    s = 1 / math.sqrt(2)
    cam = PinholeCamera.from_fov(fov_y_degrees, height, width)
    # Planes x*s + z*s = -3s (left) and -x*s + z*s = -3s (right) meet at x = 0, z = -3.
    left = ((s, 0.0, s), -3 * s, [((1.0, 0.0, 0.0), 0.0)])
    right = ((-s, 0.0, s), -3 * s, [((-1.0, 0.0, 0.0), 0.0)])
    return planes_gbuffer([left, right], cam, dtype=dtype)


def example_gbuffer(height: int = 180, width: int = 320) -> GBuffer:
    """The built-in example of ``torch-ao ao``: a floor meeting a wall, lit from the upper left."""
    gb, _ = floor_wall_gbuffer(height, width, wall_distance=2.0, camera_height=2.5, pitch_degrees=-35.0,
                               light_direction=(-0.4, 0.8, 0.45))
    return gb
