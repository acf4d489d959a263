"""Extreme G-buffers for the stability matrix (issue 7). Each maker returns a GBuffer."""
from __future__ import annotations

import math

import torch

from torch_ao.camera import PinholeCamera
from torch_ao.examples import floor_wall_gbuffer, plane_gbuffer, planes_gbuffer
from torch_ao.gbuffer import GBuffer


def _with(gb: GBuffer, **changes) -> GBuffer:
    args = dict(depth=gb.depth, camera=gb.camera, normals=gb.normals, light=gb.light, mask=gb.mask, object_id=gb.object_id)
    args.update(changes)
    return GBuffer(**args)


def _light(gb: GBuffer) -> torch.Tensor:
    torch.manual_seed(0)
    return torch.rand(gb.depth.shape[0], 3, *gb.depth.shape[-2:], dtype=gb.depth.dtype)


def scene(h=12, w=16, dtype=torch.float64) -> GBuffer:
    """A floor meeting a wall, with a light buffer: the everyday case."""
    gb, _ = floor_wall_gbuffer(h, w, dtype=dtype, light_direction=(0.3, 0.8, 0.5))
    return gb


def depth_range(dtype=torch.float64) -> GBuffer:
    """Depth from 1e-4 to 1e6 in one frame (a plane spanning the range, rows logarithmic)."""
    gb = scene(12, 16, dtype)
    d = torch.logspace(-4, 6, 12, dtype=dtype)[:, None].expand(12, 16)
    return _with(gb, depth=d[None, None].clone(), light=_light(gb))


def grazing(dtype=torch.float64) -> GBuffer:
    """A plane seen 0.1 degrees from edge-on (normals nearly perpendicular to the view)."""
    gb = plane_gbuffer(12, 16, tilt_degrees=89.9, distance=2.0, fov_y_degrees=20.0, dtype=dtype)
    return _with(gb, light=_light(gb))


def perpendicular_normals(dtype=torch.float64) -> GBuffer:
    gb = scene(12, 16, dtype)
    n = torch.zeros_like(gb.normals)
    n[:, 0] = 1.0  # along +X: perpendicular to the view axis
    return _with(gb, normals=n, light=_light(gb))


def back_facing_normals(dtype=torch.float64) -> GBuffer:
    gb = scene(12, 16, dtype)
    return _with(gb, normals=-gb.normals, light=_light(gb))


def discontinuity(dtype=torch.float64) -> GBuffer:
    """Depth jumps by 1e5 between the left and right halves."""
    gb = scene(12, 16, dtype)
    d = gb.depth.clone()
    d[..., 8:] = d[..., 8:] + 1e5
    return _with(gb, depth=d, light=_light(gb))


def single_pixel(dtype=torch.float64) -> GBuffer:
    gb = scene(12, 16, dtype)
    mask = torch.zeros_like(gb.valid)
    mask[..., 5, 7] = True
    return _with(gb, mask=mask, light=_light(gb))


def tiny(h, w, dtype=torch.float64) -> GBuffer:
    cam = PinholeCamera.from_fov(60.0, h, w)
    depth = (torch.rand(1, 1, h, w, dtype=dtype, generator=torch.Generator().manual_seed(h * 31 + w)) + 1.0)
    gb = GBuffer(depth, cam.to(dtype=dtype))
    return _with(gb, light=_light(gb))


def all_background(kind: str, dtype=torch.float64) -> GBuffer:
    gb = scene(8, 10, dtype)
    if kind == "mask":
        return _with(gb, mask=torch.zeros_like(gb.valid))
    value = {"inf": math.inf, "zero": 0.0, "nan": math.nan}[kind]
    return _with(gb, depth=torch.full_like(gb.depth, value))


def mixed_batch(n: int, dtype=torch.float64) -> GBuffer:
    """Batch of ``n`` with different content per item (plane tilts, background, a wall)."""
    items = []
    for i in range(n):
        if i % 3 == 0:
            items.append(scene(12, 16, dtype))
        else:
            items.append(plane_gbuffer(12, 16, tilt_degrees=20.0 + 7 * i, dtype=dtype))
    depth = torch.cat([g.depth for g in items])
    depth[1::4, :, :4] = math.inf  # some background in some items
    normals = torch.cat([g.normals for g in items])
    gb = GBuffer(depth, items[0].camera, normals=normals)
    return _with(gb, light=_light(gb))


def camera(fov: float = 60.0, principal=(0.5, 0.5), dtype=torch.float64) -> GBuffer:
    """The floor/wall scene seen through a camera of field of view ``fov`` and principal point at
    ``principal`` (fractions of the image; (0.5, 0.5) is centred)."""
    h, w = 12, 16
    f = 0.5 * h / math.tan(math.radians(fov) / 2)
    K = torch.tensor([[[f, 0, principal[0] * (w - 1)], [0, f, principal[1] * (h - 1)], [0, 0, 1.0]]], dtype=dtype)
    cam = PinholeCamera(K, h, w)
    floor = ((0.0, 1.0, 0.3), -1.5, None)
    wall = ((1.0, 0.0, 0.2), 1.0, None)
    gb = planes_gbuffer([floor, wall], cam, dtype=dtype)
    return _with(gb, light=_light(gb))


def sky(value: float, dtype=torch.float64) -> GBuffer:
    """The floor/wall scene with its top three rows at depth ``value`` (an engine's sky: FLT_MAX, 1e20...)."""
    gb = scene(12, 16, dtype)
    d = gb.depth.clone()
    d[..., :3, :] = value
    return _with(gb, depth=d, normals=None, light=_light(gb))


def scaled(factor: float, dtype=torch.float64) -> GBuffer:
    """The floor/wall scene with every depth times ``factor`` (normals reconstructed)."""
    gb = scene(12, 16, dtype)
    return _with(gb, depth=gb.depth * factor, normals=None, light=_light(gb))


def extreme_camera(focal_ratio: float, principal_offset: float, depth_scale: float, dtype=torch.float64) -> GBuffer:
    """The floor/wall depths times ``depth_scale`` seen through focal lengths ``focal_ratio`` times the image
    width and a principal point ``principal_offset`` widths right of the centre (the camera's bounds)."""
    gb = scene(12, 16, dtype)
    K = gb.camera.intrinsics.clone()
    K[:, 0, 0] = K[:, 1, 1] = focal_ratio * 16
    K[:, 0, 2] += principal_offset * 16
    return _with(gb, depth=gb.depth * depth_scale, camera=PinholeCamera(K, 12, 16), normals=None, light=_light(gb))


FRAMES = {
    "scene": lambda dtype=torch.float64: scene(12, 16, dtype),
    "depth_range": depth_range,
    "grazing": grazing,
    "perpendicular_normals": perpendicular_normals,
    "back_facing_normals": back_facing_normals,
    "discontinuity": discontinuity,
    "single_pixel": single_pixel,
    "1x1": lambda dtype=torch.float64: tiny(1, 1, dtype),
    "1xN": lambda dtype=torch.float64: tiny(1, 9, dtype),
    "Nx1": lambda dtype=torch.float64: tiny(9, 1, dtype),
    "odd": lambda dtype=torch.float64: tiny(7, 13, dtype),
    "bg_inf": lambda dtype=torch.float64: all_background("inf", dtype),
    "bg_zero": lambda dtype=torch.float64: all_background("zero", dtype),
    "bg_nan": lambda dtype=torch.float64: all_background("nan", dtype),
    "bg_mask": lambda dtype=torch.float64: all_background("mask", dtype),
    "batch16": lambda dtype=torch.float64: mixed_batch(16, dtype),
    "fov1": lambda dtype=torch.float64: camera(1.0, dtype=dtype),
    "fov170": lambda dtype=torch.float64: camera(170.0, dtype=dtype),
    "off_centre": lambda dtype=torch.float64: camera(60.0, (-1.5, 2.5), dtype),
    # engine backgrounds and the largest depths and widest cameras the library takes (float32: the walk's
    # squares overflow first there)
    "sky_fltmax": lambda dtype=torch.float32: sky(torch.finfo(torch.float32).max, dtype),
    "sky_1e20": lambda dtype=torch.float32: sky(1e20, dtype),
    "depth_1e14": lambda dtype=torch.float32: scaled(1e14, dtype),
    "depth_1e19": lambda dtype=torch.float32: scaled(1e19, dtype),
    "widest_camera_far": lambda dtype=torch.float32: extreme_camera(1e-3, 4.0, 2e14, dtype),
    "narrowest_camera_far": lambda dtype=torch.float32: extreme_camera(1e9, 0.0, 2e14, dtype),
}
