"""Optional Intel Embree backend for triangle meshes (PyPI ``embreex``; ``pip install torch-ao[mesh]``).

Embree works in float32 on the CPU; rays on another device are copied to the CPU and back.
Triangles are two-sided (Embree's default), so back faces occlude, as in the torch path.
"""
from __future__ import annotations

import numpy as np
import torch

from .tracer import _Triangles

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
    """All meshes of a scene in one Embree scene; ``closest`` returns global triangle indices.

    Meshes are handed to Embree indexed (float32 vertices, int32 faces) and normals are computed
    from the same arrays, so memory is about ``12 V + 12 F`` bytes plus Embree's BVH, with no
    per-triangle copies."""

    def __init__(self, meshes, obj_of_mesh, device, dtype):
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:
            raise ImportError("meshes: the Embree backend needs embreex: pip install torch-ao[mesh] (or pip install embreex)") from None
        self._scene = rtcore_scene.EmbreeScene()
        self._keep = []
        offsets, verts, faces, objs = [], [], [], []
        start = vstart = 0
        for m, oi in zip(meshes, obj_of_mesh):
            v = np.ascontiguousarray(m.vertices.numpy(), dtype=np.float32)
            f = np.ascontiguousarray(m.faces.numpy(), dtype=np.int32)
            self._keep.append(TriangleMesh(self._scene, v, f))
            offsets.append(start)
            verts.append(m.vertices.to(dtype))
            faces.append(torch.from_numpy(f) + vstart)
            objs.append(torch.full((f.shape[0],), int(oi), dtype=torch.long))
            start += f.shape[0]
            vstart += v.shape[0]
        self._offsets = np.asarray(offsets, dtype=np.int64)
        self.vertices = torch.cat(verts).to(device)
        self.faces = torch.cat(faces).to(device)
        self.obj = torch.cat(objs).to(device)

    @staticmethod
    def _dists(tmax, n: int) -> np.ndarray:
        if isinstance(tmax, torch.Tensor):
            return np.minimum(_np(tmax.expand(n)), _FAR)
        return np.full(n, min(float(tmax), float(_FAR)), dtype=np.float32)

    def closest(self, o, d, tmax):
        res = self._scene.run(_np(o), _np(d), dists=self._dists(tmax, o.shape[0]), output=1)
        geom = res["geomID"]
        hit = geom >= 0
        t = np.where(hit, res["tfar"], np.inf).astype(np.float64)
        idx = np.where(hit, self._offsets[np.maximum(geom, 0)] + res["primID"], 0)
        t = torch.from_numpy(t).to(o.device, o.dtype)
        t = torch.where(t < tmax, t, float("inf"))
        return t, torch.from_numpy(idx).to(o.device)

    def occluded(self, o, d, tmax):
        res = self._scene.run(_np(o), _np(d), dists=self._dists(tmax, o.shape[0]), query="OCCLUDED")
        return torch.from_numpy(np.asarray(res) >= 0).to(o.device)

    def normal(self, p, idx):
        v0, v1, v2 = self.vertices[self.faces[idx]].unbind(1)
        return torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)
