"""Optional NVIDIA Warp backend for triangle meshes (PyPI ``warp-lang``; the ``warp`` extra).

One code path for CPU and CUDA: the meshes go into one ``warp.Mesh`` (a BVH) on the tracer's device
and rays are intersected with ``warp.mesh_query_ray`` in place on torch tensors (shared memory, no
copies), in float32. Triangles are two-sided, as in the other paths.
"""
from __future__ import annotations

import logging

import torch

from ..checks import install_hint
from .primitives import _Triangles

try:
    import warp as wp
except ImportError:  # pragma: no cover - exercised where warp-lang is missing
    wp = None

__all__ = ["warp_available", "WarpTriangles"]

_FAR = 1e37  # "no limit" in float32


def warp_available() -> bool:
    """True when ``warp`` (PyPI ``warp-lang``) imports."""
    return wp is not None


if wp is not None:
    @wp.kernel
    def _closest_kernel(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                        tmax: wp.array(dtype=float), t: wp.array(dtype=float), face: wp.array(dtype=wp.int32)):
        i = wp.tid()
        q = wp.mesh_query_ray(mesh, o[i], d[i], tmax[i])
        if q.result:
            t[i] = q.t
            face[i] = q.face
        else:
            t[i] = wp.inf
            face[i] = 0

    @wp.kernel
    def _occluded_kernel(mesh: wp.uint64, o: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                         tmax: wp.array(dtype=float), hit: wp.array(dtype=wp.int32)):
        i = wp.tid()
        # any hit would do; Warp's query finds the closest, which costs a little more
        hit[i] = wp.where(wp.mesh_query_ray(mesh, o[i], d[i], tmax[i]).result, 1, 0)


def _device(device: torch.device) -> str:
    return "cpu" if device.type == "cpu" else f"cuda:{device.index or 0}"


class WarpTriangles(_Triangles):
    """All meshes of a scene in one ``warp.Mesh`` on ``device``; ``closest`` returns global triangle indices."""

    def __init__(self, meshes, obj_of_mesh, device, dtype):
        if wp is None:
            raise ImportError(f"meshes: the Warp backend needs warp-lang: {install_hint('warp', 'warp-lang')}")
        self.device = torch.device(device)
        # Warp's start-up banner and kernel-load lines are info; without a GPU in use, its missing-driver warning is noise
        wp.config.log_level = logging.WARNING if self.device.type == "cuda" else logging.ERROR
        wp.init()  # once per process; later calls return at once
        self._wp_device = _device(self.device)
        self._concatenate(meshes, obj_of_mesh, self.device, dtype)
        self._points = wp.from_torch(self.vertices.to(torch.float32).contiguous(), dtype=wp.vec3)
        self._indices = wp.from_torch(self.faces.to(torch.int32).reshape(-1).contiguous(), dtype=wp.int32)
        self._mesh = wp.Mesh(points=self._points, indices=self._indices)

    def _rays(self, o, d, tmax):
        n = o.shape[0]
        o32 = o.to(self.device, torch.float32).contiguous()
        d32 = d.to(self.device, torch.float32).contiguous()
        if isinstance(tmax, torch.Tensor):
            tm = tmax.to(self.device, torch.float32).expand(n).clamp_max(_FAR).contiguous()
        else:
            tm = torch.full((n,), min(float(tmax), _FAR), dtype=torch.float32, device=self.device)
        return n, [self._mesh.id, wp.from_torch(o32, dtype=wp.vec3), wp.from_torch(d32, dtype=wp.vec3), wp.from_torch(tm)]

    def closest(self, o, d, tmax):
        n, inputs = self._rays(o, d, tmax)
        t = torch.empty(n, dtype=torch.float32, device=self.device)
        face = torch.empty(n, dtype=torch.int32, device=self.device)
        wp.launch(_closest_kernel, dim=n, inputs=inputs + [wp.from_torch(t), wp.from_torch(face)], device=self._wp_device)
        t = t.to(o.device, o.dtype)
        return torch.where(t < tmax, t, float("inf")), face.to(o.device, torch.long)

    def occluded(self, o, d, tmax):
        n, inputs = self._rays(o, d, tmax)
        hit = torch.empty(n, dtype=torch.int32, device=self.device)
        wp.launch(_occluded_kernel, dim=n, inputs=inputs + [wp.from_torch(hit)], device=self._wp_device)
        return hit.to(o.device).bool()
