"""The ray-primitive intersections of :class:`~torch_ao.reference.tracer.Tracer`: one group per primitive
kind, each intersecting all its primitives with all rays of a chunk (``(N, P)`` tensors), closed-form
hits and exits side by side; :class:`Hit`, and the triangle group that the Embree and Warp backends
(:mod:`.embree`, :mod:`.warp_mesh`) and the chunked pure-torch Moller-Trumbore test implement.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass

import torch

__all__ = ["Hit"]

_INF = float("inf")


@dataclass
class Hit:
    """Closest hits of ``N`` rays: ``t (N,)`` (``inf`` = miss), ``obj (N,)`` long object index into
    ``scene.objects`` (``-1`` = miss) and unit world ``normal (N,3)`` (arbitrary side; zeros on misses)."""

    t: torch.Tensor
    obj: torch.Tensor
    normal: torch.Tensor

    @property
    def hit(self) -> torch.Tensor:
        return self.obj >= 0


def _t(x, device, dtype):
    return torch.as_tensor(x, dtype=dtype, device=device)


class _Group(abc.ABC):
    """Primitives of one kind. ``closest`` -> ``(t (N,), idx (N,))``; ``normal`` of winners."""

    obj: torch.Tensor  # (P,) object index of each primitive

    @abc.abstractmethod
    def closest(self, o, d, tmax):
        """``(t (N,), idx (N,))`` of the nearest hit of each ray before ``tmax``."""

    def occluded(self, o, d, tmax):
        return self.closest(o, d, tmax)[0] < tmax

    @abc.abstractmethod
    def exit(self, o, d, t, prim, obj, eps):
        """``(M,)`` distances along rays ``o + s d`` at which each leaves the object ``obj (M,)``
        (object index) it entered at ``t (M,)``; ``prim (M,)`` is the primitive's index in this
        group, ``eps (M,)`` a step past the entry against finding it again."""


def _reduce(t: torch.Tensor, tmax) -> tuple[torch.Tensor, torch.Tensor]:
    """``t (N,P)`` with ``inf`` for misses -> closest ``(t, idx)`` below ``tmax``."""
    tbest, idx = t.min(dim=1)
    tmax = tmax if isinstance(tmax, float) else tmax
    tbest = torch.where(tbest < tmax, tbest, torch.full_like(tbest, _INF))
    return tbest, idx


class _Planes(_Group):
    def __init__(self, planes, obj, device, dtype):
        self.n = _t([p.normal for p in planes], device, dtype)  # (P,3)
        self.off = (_t([p.point for p in planes], torch.device("cpu"), torch.float64)
                    * _t([p.normal for p in planes], torch.device("cpu"), torch.float64)).sum(1).to(device, dtype)
        self.obj = obj

    def closest(self, o, d, tmax):
        denom = d @ self.n.T
        t = (self.off - o @ self.n.T).div_(denom)
        t = torch.where(t > 0, t, _INF)
        return _reduce(t, tmax)

    def normal(self, p, idx):
        return self.n[idx]

    def exit(self, o, d, t, prim, obj, eps):
        # nothing behind an infinite plane is reachable from the camera's side: a half-space
        return torch.full_like(t, _INF)


def _sphere_roots(oc, d, r2):
    """Entry and exit distances ``(t0, t1)`` of rays with unit ``d`` and ``oc = origin - centre``
    (broadcast over leading dims, last dim 3) through spheres of squared radius ``r2``, and
    whether the line meets the sphere."""
    b = (oc * d).sum(-1)  # d . (o - c)
    perp = oc - b[..., None] * d  # closest approach vector, numerically stable
    disc = r2 - (perp * perp).sum(-1)
    sq = disc.clamp_min(0).sqrt_()
    return -b - sq, sq - b, disc >= 0


class _Spheres(_Group):
    def __init__(self, spheres, obj, device, dtype):
        self.c = _t([s.center for s in spheres], device, dtype)
        self.r2 = _t([s.radius ** 2 for s in spheres], device, dtype)
        self.obj = obj

    def closest(self, o, d, tmax):
        t0, t1, ok = _sphere_roots(o[:, None, :] - self.c, d[:, None, :], self.r2)
        t = torch.where(t0 > 0, t0, t1)
        t = torch.where(ok & (t > 0), t, _INF)
        return _reduce(t, tmax)

    def exit(self, o, d, t, prim, obj, eps):
        return _sphere_roots(o - self.c[prim], d, self.r2[prim])[1]

    def normal(self, p, idx):
        return p - self.c[idx]


def _slabs(ol, inv, h, dim):
    """Entry and exit distances ``(tn, tf)`` through boxes ``|x_k| <= h_k`` of rays with local
    origins ``ol`` and reciprocal local directions ``inv``; the 3 axes along ``dim``. NaN only
    when a direction component is exactly 0 with the origin exactly on that slab: a miss."""
    t1 = (-h - ol).mul_(inv)
    t2 = (h - ol).mul_(inv)
    lx, ly, lz = torch.minimum(t1, t2).unbind(dim)  # pairwise max/min: faster than amax/amin over 3
    hx, hy, hz = torch.maximum(t1, t2).unbind(dim)
    return torch.maximum(torch.maximum(lx, ly), lz), torch.minimum(torch.minimum(hx, hy), hz)


class _Boxes(_Group):
    def __init__(self, boxes, obj, device, dtype):
        R = torch.stack([b.rotation for b in boxes])  # (P,3,3) columns = local axes
        c = torch.tensor([b.center for b in boxes], dtype=torch.float64)
        self.P = len(boxes)
        self.R = R.to(device, dtype)
        # axis-major: column k*P + p is local axis k of box p, so o @ Rcat gives (N, 3P) local coords
        self.Rcat = R.permute(1, 2, 0).reshape(3, 3 * self.P).to(device, dtype)
        self.c = c.to(device, dtype)
        self.cl = torch.einsum("pi,pij->jp", c, R).reshape(-1).to(device, dtype)  # (3P,)
        self.h = _t([b.half_extents for b in boxes], device, dtype)  # (P,3)
        self.h_axis_major = self.h.T.contiguous()  # (3,P)
        self.obj = obj

    def closest(self, o, d, tmax):
        N, P = o.shape[0], self.P
        ol = (o @ self.Rcat).sub_(self.cl).view(N, 3, P)  # local coordinates, axis-major
        inv = (d @ self.Rcat).reciprocal_().view(N, 3, P)
        tn, tf = _slabs(ol, inv, self.h_axis_major, dim=1)
        t = torch.where(tn > 0, tn, tf)
        t = torch.where((tn <= tf) & (t > 0), t, _INF)
        return _reduce(t, tmax)

    def exit(self, o, d, t, prim, obj, eps):
        R = self.R[prim]
        ol = torch.einsum("mi,mij->mj", o - self.c[prim], R)
        inv = torch.einsum("mi,mij->mj", d, R).reciprocal_()
        return _slabs(ol, inv, self.h[prim], dim=-1)[1]

    def normal(self, p, idx):
        R = self.R[idx]  # (M,3,3)
        pl = torch.einsum("mi,mij->mj", p - self.c[idx], R)
        h = self.h[idx]
        axis = (pl.abs() / h).argmax(-1)
        nl = torch.zeros_like(pl).scatter_(1, axis[:, None], 1.0) * torch.sign(pl)
        return torch.einsum("mij,mj->mi", R, nl)


def _cylinder_interval(oc, d, a, r2, h, da):
    """Entry and exit distances ``(tn, tf)`` and ``miss`` of rays with unit ``d`` and
    ``oc = origin - centre`` through capped cylinders (unit axis ``a``, squared radius ``r2``,
    half height ``h``), broadcast over leading dims (last dim 3 for vectors); ``da = d . a``."""
    oa = (oc * a).sum(-1)
    op = oc - oa[..., None] * a
    dp = d - da[..., None] * a
    A = (dp * dp).sum(-1)
    B = (op * dp).sum(-1)
    C = (op * op).sum(-1) - r2
    disc = B * B - A * C
    sq = disc.clamp_min(0).sqrt_()
    parallel = A < 1e-12
    Asafe = torch.where(parallel, torch.ones_like(A), A)
    c_near = torch.where(parallel, torch.where(C < 0, -_INF, _INF), (-B - sq) / Asafe)
    c_far = torch.where(parallel, torch.where(C < 0, _INF, -_INF), (-B + sq) / Asafe)
    miss = (disc < 0) & ~parallel
    inv = da.reciprocal()
    s1 = (-h - oa) * inv
    s2 = (h - oa) * inv
    return torch.maximum(c_near, torch.fmin(s1, s2)), torch.minimum(c_far, torch.fmax(s1, s2)), miss


class _Cylinders(_Group):
    def __init__(self, cyls, obj, device, dtype):
        self.c = _t([c.center for c in cyls], device, dtype)
        self.a = _t([c.axis for c in cyls], device, dtype)
        self.r2 = _t([c.radius ** 2 for c in cyls], device, dtype)
        self.r = _t([c.radius for c in cyls], device, dtype)
        self.h = _t([c.half_height for c in cyls], device, dtype)
        self.obj = obj

    def closest(self, o, d, tmax):
        tn, tf, miss = _cylinder_interval(o[:, None, :] - self.c, d[:, None, :], self.a, self.r2, self.h, d @ self.a.T)
        t = torch.where(tn > 0, tn, tf)
        t = torch.where(~miss & (tn <= tf) & (t > 0), t, _INF)
        return _reduce(t, tmax)

    def exit(self, o, d, t, prim, obj, eps):
        a = self.a[prim]
        return _cylinder_interval(o - self.c[prim], d, a, self.r2[prim], self.h[prim], (d * a).sum(-1))[1]

    def normal(self, p, idx):
        a = self.a[idx]
        q = p - self.c[idx]
        qa = (q * a).sum(-1, keepdim=True)
        radial = q - qa * a
        side = (radial.norm(dim=-1) / self.r[idx] - 1) > (qa.abs()[:, 0] / self.h[idx] - 1)
        return torch.where(side[:, None], radial, a * torch.sign(qa))


class _Triangles(_Group):
    """Triangle meshes: ``closest`` returns global triangle indices; ``obj`` maps them to objects.
    Subclasses are built as ``cls(meshes, obj_of_mesh, device, dtype)`` and call :meth:`_remember`."""

    def _remember(self, meshes, obj_of_mesh, device, dtype) -> None:
        self._source = (list(meshes), [int(i) for i in obj_of_mesh], device, dtype)
        self._single = {}  # object index -> a group of that object's mesh alone, built on demand

    def exit(self, o, d, t, prim, obj, eps):
        """The next hit of the same object along the ray, found among that object's triangles
        alone (so faces of other objects that coincide with its own, such as a floor under a box,
        cannot hide its exit); ``t`` itself when there is none: an open surface, a sheet."""
        meshes, objs, device, dtype = self._source
        out = t.clone()
        start = t + eps
        for k in obj.unique().tolist():
            sel = (obj == k).nonzero()[:, 0]
            if len(objs) == 1:
                group = self
            else:
                if k not in self._single:
                    self._single[k] = type(self)([meshes[objs.index(k)]], [k], device, dtype)
                group = self._single[k]
            th, _ = group.closest(o[sel] + start[sel, None] * d[sel], d[sel], _INF)
            out[sel] = torch.where(torch.isfinite(th), start[sel] + th, t[sel])
        return out

    def _concatenate(self, meshes, obj_of_mesh, device, dtype) -> None:
        """All meshes as one indexed mesh: ``vertices (V,3)`` in ``dtype``, ``faces (F,3)`` long
        global indices, ``obj (F,)`` each triangle's object index."""
        self._remember(meshes, obj_of_mesh, device, dtype)
        starts = torch.tensor([0] + [m.vertices.shape[0] for m in meshes]).cumsum(0)
        self.vertices = torch.cat([m.vertices for m in meshes]).to(device, dtype)
        self.faces = torch.cat([m.faces + int(s) for m, s in zip(meshes, starts)]).to(device)
        self.obj = torch.cat([torch.full((m.faces.shape[0],), int(oi), dtype=torch.long)
                              for m, oi in zip(meshes, obj_of_mesh)]).to(device)

    def normal(self, p, idx):
        v0, v1, v2 = self.vertices[self.faces[idx]].unbind(1)
        return torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)


class _TorchTriangles(_Triangles):
    """Moller-Trumbore over ``(N, T)`` blocks, after culling rays that miss each mesh's bounds."""

    def __init__(self, meshes, obj_of_mesh, device, dtype, block: int = 1 << 22):
        self._remember(meshes, obj_of_mesh, device, dtype)
        self.meshes = []
        tri_all, tri_obj = [], []
        for m, oi in zip(meshes, obj_of_mesh):
            tri = m.triangles  # (T,3,3) float64
            start = sum(x.shape[0] for x in tri_all)
            tri_all.append(tri)
            tri_obj.append(torch.full((tri.shape[0],), int(oi), dtype=torch.long))
            lo, hi = m.bounds()
            pad = 1e-6 * float((hi - lo).max()) + 1e-9
            self.meshes.append((start, tri.shape[0], (lo - pad).to(device, dtype), (hi + pad).to(device, dtype)))
        tri = torch.cat(tri_all)
        self.v0 = tri[:, 0].to(device, dtype)
        self.e1 = (tri[:, 1] - tri[:, 0]).to(device, dtype)
        self.e2 = (tri[:, 2] - tri[:, 0]).to(device, dtype)
        self.obj = torch.cat(tri_obj).to(device)
        self.block = block

    def closest(self, o, d, tmax):
        N = o.shape[0]
        tbest = torch.full((N,), _INF, dtype=o.dtype, device=o.device)
        ibest = torch.zeros(N, dtype=torch.long, device=o.device)
        for start, count, lo, hi in self.meshes:
            inv = d.reciprocal()
            t1, t2 = (lo - o) * inv, (hi - o) * inv
            tn = torch.fmin(t1, t2).amax(-1)
            tf = torch.fmax(t1, t2).amin(-1)
            sel = ((tn <= tf) & (tf > 0) & (tn < (tmax if isinstance(tmax, float) else tmax))).nonzero()[:, 0]
            if sel.numel() == 0:
                continue
            os_, ds_ = o[sel], d[sel]
            tsel = tbest[sel]
            isel = ibest[sel]
            step = max(1, self.block // max(1, sel.numel()))
            for k in range(start, start + count, step):
                e = min(k + step, start + count)
                t = self._mt(os_, ds_, self.v0[k:e], self.e1[k:e], self.e2[k:e])
                tk, ik = t.min(dim=1)
                better = tk < tsel
                tsel = torch.where(better, tk, tsel)
                isel = torch.where(better, ik + k, isel)
            tbest[sel] = tsel
            ibest[sel] = isel
        tbest = torch.where(tbest < tmax, tbest, _INF)
        return tbest, ibest

    @staticmethod
    def _mt(o, d, v0, e1, e2):
        """``(N, T)`` hit distances (``inf`` = miss); two-sided."""
        pvec = torch.linalg.cross(d[:, None, :], e2[None], dim=-1)  # (N,T,3)
        det = (pvec * e1).sum(-1)
        inv_det = det.reciprocal()
        tvec = o[:, None, :] - v0
        u = (tvec * pvec).sum(-1) * inv_det
        qvec = torch.linalg.cross(tvec, e1[None].expand_as(tvec), dim=-1)
        v = (qvec * d[:, None, :]).sum(-1) * inv_det
        t = (qvec * e2).sum(-1) * inv_det
        # barycentric slack of a few ulps: without it a ray through a shared edge can miss both
        # triangles by rounding (Moller-Trumbore is not watertight)
        tol = 64 * torch.finfo(o.dtype).eps
        ok = (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t > 0) & (det.abs() > 0)
        return torch.where(ok, t, _INF)

    def normal(self, p, idx):
        return torch.linalg.cross(self.e1[idx], self.e2[idx], dim=-1)
