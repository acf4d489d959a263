"""Batched ray intersection with a :class:`~torch_ao.scene.Scene`, in torch (CPU or CUDA).

Rays are ``origins (N,3)``, unit ``directions (N,3)`` and ``tmax (N,)`` (or a float; ``inf`` allowed);
a ray hits at distance ``t`` with ``0 < t < tmax``. Primitives of one kind are intersected together
over all rays of a chunk (``(N, P)`` tensors, no Python loop over rays); the loop is over the few
primitive kinds. Triangle meshes go to Embree (:mod:`.embree`, optional ``embreex``) or, for small
meshes, to a chunked pure-torch Moller-Trumbore test.
"""
from __future__ import annotations

import torch

from ..checks import check_choice, install_hint
from ..scene import Box, Cylinder, Mesh, Plane, Scene, Sphere
from .primitives import _INF, Hit, _Boxes, _Cylinders, _Group, _Planes, _Spheres, _t, _TorchTriangles, _Triangles

__all__ = ["Tracer", "Hit", "TORCH_MAX_TRIANGLES"]

#: Triangle tracers: see :class:`Tracer`.
MESH_BACKENDS = ("auto", "embree", "warp", "torch")

#: Largest total triangle count the pure-torch mesh path accepts when Embree is unavailable.
TORCH_MAX_TRIANGLES = 20_000

class Tracer:
    """Intersects rays with a scene on ``device`` in ``dtype``.

    Args:
        scene: the :class:`Scene`.
        mesh_backend: ``"auto"`` (on a CUDA device Warp when ``warp-lang`` imports; else Embree
            when ``embreex`` imports; else torch for meshes up to :data:`TORCH_MAX_TRIANGLES`
            triangles, else an error naming the package), ``"embree"`` (CPU; rays on another device
            are copied), ``"warp"`` (NVIDIA Warp's BVH, CPU or CUDA, in place on torch tensors) or
            ``"torch"``. On the CPU Embree is 3-4x faster than Warp for AO rays (Warp's CPU kernels
            run on one thread; ``python benchmarks/bench_tracer.py``).
    """

    def __init__(self, scene: Scene, device=None, dtype: torch.dtype = torch.float32, mesh_backend: str = "auto"):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene: expected a torch_ao.reference.Scene, got {type(scene).__name__}")
        check_choice("mesh_backend", mesh_backend, MESH_BACKENDS)
        self.scene = scene
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.dtype = dtype
        self.scale = scene.scale
        self.block = 1 << 14 if self.device.type == "cpu" else 1 << 20
        objs = scene.objects
        self.albedo = _t([o.albedo for o in objs], self.device, dtype)  # (O,3)
        self.object_id = torch.tensor([o.object_id for o in objs], dtype=torch.long, device=self.device)
        self.groups: list[_Group] = []
        for kind, cls in ((Plane, _Planes), (Sphere, _Spheres), (Box, _Boxes), (Cylinder, _Cylinders)):
            idx = [i for i, o in enumerate(objs) if type(o) is kind]
            if idx:
                self.groups.append(cls([objs[i] for i in idx], torch.tensor(idx, device=self.device), self.device, dtype))
        mesh_idx = [i for i, o in enumerate(objs) if isinstance(o, Mesh)]
        self.mesh_backend = None
        if mesh_idx:
            meshes = [objs[i] for i in mesh_idx]
            self.mesh_backend = _choose_backend(mesh_backend, sum(m.faces.shape[0] for m in meshes), self.device)
            if self.mesh_backend == "warp":
                from .warp_mesh import WarpTriangles

                self.groups.append(WarpTriangles(meshes, mesh_idx, self.device, dtype))
            elif self.mesh_backend == "embree":
                from .embree import EmbreeTriangles

                self.groups.append(EmbreeTriangles(meshes, mesh_idx, self.device, dtype))
            else:
                self.groups.append(_TorchTriangles(meshes, mesh_idx, self.device, dtype))
        # each object's group and, for analytic objects (one primitive each), its index in the group
        self._group_of = torch.full((len(objs),), -1, dtype=torch.long, device=self.device)
        self._prim_of = torch.zeros(len(objs), dtype=torch.long, device=self.device)
        for g, group in enumerate(self.groups):
            self._group_of[group.obj] = g
            if not isinstance(group, _Triangles):
                self._prim_of[group.obj] = torch.arange(group.obj.numel(), device=self.device)

    #: rays intersected at once inside a call: 2**14 on CPU (blocks stay in cache, about 2x faster
    #: than 2**18), 2**20 on GPUs
    block = 1 << 14

    def intersect(self, o: torch.Tensor, d: torch.Tensor, tmax=_INF) -> Hit:
        """Closest hits of rays ``o, d (N,3)`` within ``tmax`` (float or ``(N,)``)."""
        if o.shape[0] > self.block:
            parts = [self.intersect(o[s:s + self.block], d[s:s + self.block], _slice(tmax, s, self.block))
                     for s in range(0, o.shape[0], self.block)]
            return Hit(torch.cat([h.t for h in parts]), torch.cat([h.obj for h in parts]), torch.cat([h.normal for h in parts]))
        N = o.shape[0]
        tbest = torch.full((N,), _INF, dtype=o.dtype, device=o.device)
        gbest = torch.full((N,), -1, dtype=torch.long, device=o.device)
        ibest = torch.zeros(N, dtype=torch.long, device=o.device)
        for g, group in enumerate(self.groups):
            t, idx = group.closest(o, d, tmax)
            better = t < tbest
            tbest = torch.where(better, t, tbest)
            gbest = torch.where(better, g, gbest)
            ibest = torch.where(better, idx, ibest)
        obj = torch.full((N,), -1, dtype=torch.long, device=o.device)
        normal = torch.zeros_like(o)
        p = o + tbest.clamp_max(torch.finfo(o.dtype).max)[:, None] * d
        for g, group in enumerate(self.groups):
            sel = (gbest == g).nonzero()[:, 0]
            if sel.numel() == 0:
                continue
            idx = ibest[sel]
            obj[sel] = group.obj[idx]
            normal[sel] = torch.nn.functional.normalize(group.normal(p[sel], idx), dim=-1, eps=1e-30)
        return Hit(tbest, obj, normal)

    def occluded(self, o: torch.Tensor, d: torch.Tensor, tmax=_INF) -> torch.Tensor:
        """``(N,)`` bool: does the ray hit anything with ``0 < t < tmax``."""
        if o.shape[0] > self.block:
            return torch.cat([self.occluded(o[s:s + self.block], d[s:s + self.block], _slice(tmax, s, self.block))
                              for s in range(0, o.shape[0], self.block)])
        hit = torch.zeros(o.shape[0], dtype=torch.bool, device=o.device)
        for group in self.groups:
            hit |= group.occluded(o, d, tmax)
        return hit

    def exit_distance(self, o: torch.Tensor, d: torch.Tensor, hit: Hit) -> torch.Tensor:
        """``(N,)`` distance along each ray ``o + t d`` at which it leaves the object it hit first.

        Spheres, boxes and cylinders: the far root (closed form). Planes: ``inf`` (nothing behind
        an infinite plane is reachable from the camera's side, so it acts as a half-space). Meshes:
        the next hit of the same object along the ray, among its own triangles (other objects are
        ignored); when there is none (an open surface) the entry distance (a sheet, zero
        thickness). Misses: ``inf``.
        """
        out = torch.full_like(hit.t, _INF)
        group_of = torch.where(hit.hit, self._group_of[hit.obj.clamp_min(0)], -1)
        for g, group in enumerate(self.groups):
            sel = (group_of == g).nonzero()[:, 0]
            if sel.numel() == 0:
                continue
            obj, t = hit.obj[sel], hit.t[sel]
            eps = self._eps(o[sel] + t[:, None] * d[sel], t)
            out[sel] = group.exit(o[sel], d[sel], t, self._prim_of[obj], obj, eps)
        return out

    def _eps(self, p: torch.Tensor, distance: torch.Tensor | None = None, rel: float = 1e-4) -> torch.Tensor:
        """``(N,)`` offsets against self-intersection at points ``p (N,3)``:
        ``rel * (1e-2 * scene.scale + max|p| + distance)``, relative to the scene size, the point's
        magnitude (float rounding of ``p``) and the primary ray's length."""
        mag = p.abs().amax(-1)
        if distance is not None:
            mag = mag + distance
        return rel * (1e-2 * self.scale + mag)

    def offset(self, p: torch.Tensor, n: torch.Tensor, distance: torch.Tensor | None = None, rel: float = 1e-4) -> torch.Tensor:
        """Origins ``p + eps * n`` against self-intersection (``eps`` of :meth:`_eps`); ``n`` on the
        side rays leave from."""
        return p + self._eps(p, distance, rel)[:, None] * n


def _slice(tmax, start: int, size: int):
    return tmax[start:start + size] if isinstance(tmax, torch.Tensor) and tmax.dim() > 0 else tmax


def _choose_backend(requested: str, triangles: int, device: torch.device) -> str:
    if requested == "torch":
        return "torch"
    from .embree import embree_available
    from .warp_mesh import warp_available

    if requested == "warp" or (requested == "auto" and device.type == "cuda" and warp_available()):
        if not warp_available():
            raise ImportError(f"mesh_backend='warp' needs warp-lang: {install_hint('warp', 'warp-lang')}")
        return "warp"

    if embree_available():
        return "embree"
    if requested == "embree":
        raise ImportError(f"mesh_backend='embree' needs embreex: {install_hint('mesh', 'embreex')}")
    if triangles > TORCH_MAX_TRIANGLES:
        raise ImportError(
            f"meshes: {triangles} triangles is too many for the pure-torch tracer (limit {TORCH_MAX_TRIANGLES}); "
            f"install Embree: {install_hint('mesh', 'embreex')}, or pass mesh_backend='torch' to force it"
        )
    return "torch"
