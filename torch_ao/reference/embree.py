"""Optional Intel Embree backend for triangle meshes (PyPI ``embreex``; the ``mesh`` extra).

Embree works in float32 on the CPU; rays on another device are copied to the CPU and back.
Triangles are two-sided (Embree's default), so back faces occlude, as in the torch path.
"""
from __future__ import annotations

import numpy as np
import torch

from ..checks import install_hint
from .primitives import _Triangles

__all__ = ["embree_available", "EmbreeTriangles"]

_FAR = np.float32(1e37)  # Embree's "no limit"


def embree_available() -> bool:
    """True when ``embreex`` imports."""
    try:
        import embreex.mesh_construction  # noqa: F401
        import embreex.rtcore_scene  # noqa: F401
    except ImportError:
        return False
    return True


def _np(x: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to("cpu", torch.float32).numpy())


class EmbreeTriangles(_Triangles):
    """All meshes of a scene as one Embree mesh; ``closest`` returns global triangle indices.

    The mesh goes to Embree indexed (float32 vertices, int32 faces) and normals are computed from
    the same indices, so memory is about ``12 V + 12 F`` bytes for Embree plus its BVH, with no
    per-triangle copies."""

    def __init__(self, meshes, obj_of_mesh, device, dtype):
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:
            raise ImportError(f"meshes: the Embree backend needs embreex: {install_hint('mesh', 'embreex')}") from None
        self._concatenate(meshes, obj_of_mesh, device, dtype)
        self._scene = rtcore_scene.EmbreeScene()
        self._mesh = TriangleMesh(self._scene, _np(self.vertices), np.ascontiguousarray(self.faces.cpu().numpy(), dtype=np.int32))

    @staticmethod
    def _dists(tmax, n: int) -> np.ndarray:
        if isinstance(tmax, torch.Tensor):
            return np.minimum(_np(tmax.expand(n)), _FAR)
        return np.full(n, min(float(tmax), float(_FAR)), dtype=np.float32)

    def closest(self, o, d, tmax):
        res = self._scene.run(_np(o), _np(d), dists=self._dists(tmax, o.shape[0]), output=1)
        hit = res["geomID"] >= 0
        t = np.where(hit, res["tfar"], np.inf).astype(np.float64)
        idx = np.where(hit, res["primID"], 0).astype(np.int64)
        t = torch.from_numpy(t).to(o.device, o.dtype)
        t = torch.where(t < tmax, t, float("inf"))
        return t, torch.from_numpy(idx).to(o.device)

    def occluded(self, o, d, tmax):
        res = self._scene.run(_np(o), _np(d), dists=self._dists(tmax, o.shape[0]), query="OCCLUDED")
        return torch.from_numpy(np.asarray(res) >= 0).to(o.device)

