"""Ray-traced G-buffer, ground-truth AO and one-bounce indirect light for a batch of views.

Quantities (per pixel ``x`` with camera-facing geometric normal ``n``, hemisphere ``H(n)``,
``V_R(x, w) = 1`` when the ray ``x + t w`` hits nothing for ``0 < t < R``):

* ``ao`` (cosine-weighted visibility): ``(1/pi) * integral_H V_R(x,w) cos(w,n) dw``;
  cosine-distributed rays, estimate = fraction unoccluded.
* ``ao_uniform``: ``(1/(2 pi)) * integral_H V_R(x,w) dw``; uniformly distributed rays.
* ``light`` (direct): outgoing diffuse radiance ``albedo / pi * E(x)`` with direct irradiance
  ``E = intensity * max(0, n.l) * shadow`` (directional) or ``intensity * max(0, n.l) / r^2 * shadow``
  (point), the shadow ray traced; RGB.
* ``indirect`` (optional): one-bounce incident light, irradiance-like and *without the receiver's
  albedo*: ``(1/pi) * integral_H L_in(x,w) cos(w,n) dw`` where ``L_in(x,w)`` is the ``light`` value
  (outgoing direct radiance ``albedo_y / pi * E(y)``, ``E`` with ``y``'s normal turned towards ``x``)
  of the first hit ``y`` within ``R``, and 0 when the ray escapes. Estimated with the cosine rays as
  the mean of ``L_in``. This is the quantity SSILVB's ``indirect`` approximates from the ``light``
  buffer (the receiver's albedo multiplies it afterwards, if at all).

* ``backface_depth`` (optional): the view-axis depth at which each pixel's camera ray leaves the
  object it hit first (the exit depth; what an engine's front-face-culled depth pass of that object
  gives), ``inf`` on background. Closed forms for spheres, boxes and cylinders; ``inf`` for planes
  (half-spaces: nothing behind them is reachable); for meshes the next hit of the same object along
  the ray (other objects ignored), or the front depth itself when there is none (an open surface: zero thickness).
  See :meth:`Tracer.exit_distance`.

Background pixels: depth ``inf``, ``mask`` False, ``ao = 1``, errors 0, light/indirect 0.
Every estimate comes with its Monte Carlo standard error (``*_stderr``), from independent groups of
stratified samples (:mod:`.sampling`).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import torch

from ..camera import PinholeCamera
from ..checks import check_choice
from ..gbuffer import GBuffer
from . import ao_kernel, sampling
from ..scene import Scene
from .tracer import Tracer
from .views import Views, look_at

__all__ = ["Reference", "render_reference", "default_views"]

_AO_STREAM, _UNIFORM_STREAM = 0, 16


@dataclass
class Reference:
    """A rendered reference. Images are ``(B,C,H,W)`` on the render device.

    ``gbuffer`` holds depth (``inf`` on background), view-space ``normals`` facing the camera,
    ``light`` (direct outgoing radiance), ``mask`` and ``object_id`` (0 = background).
    ``ao``/``ao_uniform`` are visibilities in ``[0, 1]`` (1 = unoccluded); ``indirect`` is ``None``
    unless requested; ``ao_uniform`` is ``None`` when ``uniform=False``.
    """

    gbuffer: GBuffer
    albedo: torch.Tensor
    position: torch.Tensor
    ao: torch.Tensor
    ao_stderr: torch.Tensor
    ao_uniform: torch.Tensor | None
    ao_uniform_stderr: torch.Tensor | None
    indirect: torch.Tensor | None
    indirect_stderr: torch.Tensor | None
    max_distance: float
    spp: int
    seed: int
    world_to_view: torch.Tensor
    backface_depth: torch.Tensor | None = None
    extra: dict = field(default_factory=dict)

    def arrays(self) -> dict:
        """The non-G-buffer arrays under their file keys (see :func:`torch_ao.io.save_npz`)."""
        out = {"ao": self.ao, "ao_stderr": self.ao_stderr, "albedo": self.albedo, "position": self.position,
               "max_distance": float(self.max_distance), "spp": self.spp, "seed": self.seed,
               "world_to_view": self.world_to_view, "tracer_version": TRACER_VERSION}
        if self.ao_uniform is not None:
            out["ao_uniform"], out["ao_uniform_stderr"] = self.ao_uniform, self.ao_uniform_stderr
        if self.indirect is not None:
            out["indirect_reference"], out["indirect_reference_stderr"] = self.indirect, self.indirect_stderr
        if self.backface_depth is not None:
            out["backface_depth"] = self.backface_depth
        return out

    def save(self, path: str | os.PathLike, *, keep_existing: bool = False):
        """Write the library's ``.npz`` file atomically; returns its path. ``keep_existing``: a file another
        writer put there meanwhile stands (:func:`~torch_ao.io.save_npz`)."""
        from ..io import save_npz

        return save_npz(path, self.gbuffer, keep_existing=keep_existing, **self.arrays())


#: Version of what the tracer renders: raised whenever a change alters a rendered file's values (the
#: reference cache's file names hold it, with the library's version, so older renders are not reused).
TRACER_VERSION = 1


def default_views(scene: Scene, height: int, width: int) -> Views:
    """The scene's default look-at view at ``height x width`` (a file camera's FOV refitted to that size
    on its ``fov_axis``, its principal point offset kept: :class:`~torch_ao.scene.LookAt`)."""
    v = scene.view
    return look_at(v.eye, v.target, v.up, v.fov_y_at(width, height), height=height, width=width,
                   principal_offset=v.principal_offset)


def _check_args(spp, max_distance, seed, chunk_rays):
    groups = sampling.choose_groups(spp)
    try:
        R = float(max_distance)
    except (TypeError, ValueError):
        raise TypeError(f"max_distance: expected a number (inf allowed), got {max_distance!r}") from None
    if math.isnan(R) or R <= 0:
        raise ValueError(f"max_distance: expected a value > 0 (inf allowed), got {max_distance!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    if isinstance(chunk_rays, bool) or not isinstance(chunk_rays, int) or chunk_rays < 1:
        raise ValueError(f"chunk_rays: expected a positive integer, got {chunk_rays!r}")
    return groups, R


def _direct_irradiance(tracer: Tracer, p, n, distance) -> torch.Tensor:
    """``(N,3)`` direct irradiance at points ``p`` with unit normals ``n`` (shadow rays traced)."""
    light = tracer.scene.light
    dev, dt = p.device, p.dtype
    I = torch.tensor(light.intensity, device=dev, dtype=dt)
    if light.kind == "directional":
        l = torch.tensor(light.direction, device=dev, dtype=dt).expand_as(p)
        falloff = torch.ones(p.shape[0], device=dev, dtype=dt)
        tmax = float("inf")
    else:
        v = torch.tensor(light.position, device=dev, dtype=dt) - p
        r = v.norm(dim=-1).clamp_min(1e-12)
        l = v / r[:, None]
        falloff = 1 / (r * r)
        tmax = None
    cos = (n * l).sum(-1)
    lit = cos > 0
    sel = lit.nonzero()[:, 0]
    if sel.numel():
        o = tracer.offset(p[sel], n[sel], distance[sel])
        tm = tmax if tmax is not None else (torch.tensor(light.position, device=dev, dtype=dt) - o).norm(dim=-1)
        lit[sel] = ~tracer.occluded(o, l[sel], tm)
    return (cos.clamp_min(0) * falloff * lit)[:, None] * I


def _world_basis(n):
    t, b = sampling.frame(n)
    return t, b


def _to_world(local, t, b, n):
    """Local ``(m, k, 3)`` directions in the frames of ``(m,3)`` normals -> world ``(m,k,3)``."""
    return local[..., :1] * t[:, None] + local[..., 1:2] * b[:, None] + local[..., 2:] * n[:, None]


def _ao_occlusion(tracer: Tracer, backend: str, org, t, b, n, key, spp: int, groups: int, seed: int, stream: int,
                  cosine: bool, R: float) -> torch.Tensor:
    """``(m, spp)`` bool occlusion within ``R`` of the stratified samples of ``(seed, stream)`` of
    pixels ``key (m,)`` with ray origins ``org (m,3)`` and frames ``t, b, n (m,3)``, on the cosine
    (``cosine``) or uniform hemisphere: the C++ kernel where ``backend`` allows and it applies."""
    occl = ao_kernel.occlusion(tracer, backend, org, t, b, n, key, spp, groups, seed, stream, cosine, R)
    if occl is None:
        u1, u2 = sampling.stratified_square(key, spp, groups, seed, stream, org.dtype)
        hemisphere = sampling.cosine_hemisphere if cosine else sampling.uniform_hemisphere
        dirs = _to_world(hemisphere(u1, u2), t, b, n).reshape(-1, 3)
        occl = tracer.occluded(org[:, None, :].expand(-1, spp, 3).reshape(-1, 3), dirs, R)
    return occl


def _group_stats(x: torch.Tensor, groups: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``x (m, spp[, C])`` -> mean and standard error over ``groups`` independent group means."""
    m, spp = x.shape[:2]
    g = x.reshape(m, groups, spp // groups, *x.shape[2:]).mean(2)
    return g.mean(1), (g.var(1, unbiased=True) / groups).sqrt()


def render_reference(
    scene: Scene,
    views: Views | PinholeCamera | None = None,
    *,
    world_to_view: torch.Tensor | None = None,
    height: int | None = None,
    width: int | None = None,
    spp: int = 256,
    max_distance: float = float("inf"),
    seed: int = 0,
    chunk_rays: int = 1 << 18,
    progress: bool = True,
    indirect: bool = False,
    uniform: bool = True,
    backface: bool = False,
    device=None,
    dtype: torch.dtype = torch.float32,
    mesh_backend: str = "auto",
    backend: str = "auto",
) -> Reference:
    """Ray-trace the G-buffer and reference AO (and optionally one-bounce indirect light).

    Args:
        scene: a :class:`~torch_ao.scene.Scene` (e.g. ``get_scene("stairs")``).
        views: a :class:`Views` (``look_at(...)``), a ``PinholeCamera`` with ``world_to_view
            (B,4,4)``, or ``None`` for the scene's default view at ``height x width`` (each, when
            ``None``, the view's ``film`` size: a Mitsuba file camera's).
        spp: samples per pixel for each AO weighting (>= 2, with a divisor in [2, 16]: the samples
            form that many independent stratified groups for the standard error).
        max_distance: AO ray length ``R`` in world units (``inf`` allowed); also bounds indirect rays.
        seed: reproducible randomness (same seed, same numbers, whatever ``chunk_rays``/device).
        chunk_rays: rays traced at once (memory is proportional to it).
        progress: show a tqdm progress bar.
        indirect: also render one-bounce indirect light (costs closest hits + shadow rays).
        uniform: also render uniform-weighted visibility (another ``spp`` rays per pixel).
        backface: also render ``backface_depth`` ``(B,1,H,W)``, the exit depth of each pixel's
            first-hit object (see the module docstring).
        device, dtype: where and in what precision rays are traced.
        mesh_backend: ``"auto"``, ``"embree"`` or ``"torch"`` (see :class:`Tracer`).
        backend: how AO rays (without ``indirect``) are traced: ``"auto"`` (the C++ kernel of
            :mod:`.ao_kernel` for CPU float32 renders of analytic scenes, else tensor ops),
            ``"kernel"`` (that kernel, or an error where it does not apply) or ``"torch"`` (tensor
            ops). The kernel draws the same samples; it can differ from the tensor path only in a ray
            grazing an edge (docs/performance.md).
    Returns:
        a :class:`Reference`.
    """
    groups, R = _check_args(spp, max_distance, seed, chunk_rays)
    check_choice("backend", backend, ao_kernel.BACKENDS)
    if isinstance(views, PinholeCamera):
        if world_to_view is None:
            raise ValueError("world_to_view: needed (B,4,4) when views is a PinholeCamera")
        views = Views(views, world_to_view)
    elif views is None:
        film = scene.view.film or (None, None)  # a scene file camera's image size
        width, height = width or film[0], height or film[1]
        if height is None or width is None:
            raise ValueError("height/width: needed when no views are given (the scene's default view is used) "
                             "and its view has no film size")
        views = default_views(scene, height, width)
    elif not isinstance(views, Views):
        raise TypeError(f"views: expected a Views, a PinholeCamera or None, got {type(views).__name__}")
    device = torch.device(device) if device is not None else torch.device("cpu")
    tracer = Tracer(scene, device=device, dtype=dtype, mesh_backend=mesh_backend)
    cam = views.camera.to(device=device, dtype=torch.float64)
    B, H, W = views.batch_size, cam.height, cam.width

    # ---------------------------------------------------------------- primary rays
    M = views.world_to_view.to(device)
    Rw = M[:, :3, :3]
    eye = -torch.einsum("bji,bj->bi", Rw, M[:, :3, 3])
    dview = cam.pixel_rays()  # (B,3,H,W), z = -1
    dworld = torch.einsum("bji,bjhw->bihw", Rw, dview)
    scale_depth = dview.norm(dim=1, keepdim=True)  # depth = t / |dview|
    d = torch.nn.functional.normalize(dworld, dim=1).permute(0, 2, 3, 1).reshape(-1, 3).to(dtype)
    o = eye[:, None, :].expand(B, H * W, 3).reshape(-1, 3).to(dtype)
    npix = B * H * W
    total = npix  # rays for the progress bar, refined below
    bar = _progress(progress, total)
    t_prim = torch.empty(npix, dtype=dtype, device=device)
    obj = torch.empty(npix, dtype=torch.long, device=device)
    nrm = torch.empty(npix, 3, dtype=dtype, device=device)
    t_exit = torch.empty(npix, dtype=dtype, device=device) if backface else None
    for s in range(0, npix, chunk_rays):
        sl = slice(s, s + chunk_rays)
        hit = tracer.intersect(o[sl], d[sl])
        t_prim[sl], obj[sl], nrm[sl] = hit.t, hit.obj, hit.normal
        if backface:
            t_exit[sl] = tracer.exit_distance(o[sl], d[sl], hit)
        bar.update(hit.t.shape[0])
    valid = obj >= 0
    flip = torch.where((nrm * d).sum(-1) > 0, -1.0, 1.0).to(dtype)
    nrm = nrm * flip[:, None]  # face the camera
    idx = valid.nonzero()[:, 0]
    p = o[idx] + t_prim[idx, None] * d[idx]
    n = nrm[idx]
    tp = t_prim[idx]
    alb = tracer.albedo[obj[idx]]
    nvalid = idx.numel()
    rays_per_pixel = 1 + spp * (2 if uniform else 1) + (2 * spp if indirect else 0)
    bar.total = npix + nvalid * rays_per_pixel
    bar.refresh()

    # ---------------------------------------------------------------- direct light
    E = torch.empty(nvalid, 3, dtype=dtype, device=device)
    for s in range(0, nvalid, chunk_rays):
        E[s:s + chunk_rays] = _direct_irradiance(tracer, p[s:s + chunk_rays], n[s:s + chunk_rays], tp[s:s + chunk_rays])
        bar.update(E[s:s + chunk_rays].shape[0])
    light_valid = alb / math.pi * E

    # ---------------------------------------------------------------- AO (+ indirect)
    ao = torch.ones(nvalid, dtype=dtype, device=device)
    ao_se = torch.zeros_like(ao)
    aou = torch.ones_like(ao) if uniform else None
    aou_se = torch.zeros_like(ao) if uniform else None
    ind = torch.zeros(nvalid, 3, dtype=dtype, device=device) if indirect else None
    ind_se = torch.zeros_like(ind) if indirect else None
    px_per_chunk = max(1, chunk_rays // spp)
    for s in range(0, nvalid, px_per_chunk):
        sl = slice(s, s + px_per_chunk)
        ps, ns, ts = p[sl], n[sl], tp[sl]
        m = ps.shape[0]
        key = idx[sl]
        tb, bb = _world_basis(ns)
        org = tracer.offset(ps, ns, ts)
        if indirect:
            o_rep = org[:, None, :].expand(m, spp, 3).reshape(-1, 3)
            u1, u2 = sampling.stratified_square(key, spp, groups, seed, _AO_STREAM, dtype)
            dirs = _to_world(sampling.cosine_hemisphere(u1, u2), tb, bb, ns).reshape(-1, 3)
            hit = tracer.intersect(o_rep, dirs, R)
            occl = hit.hit
            Lin = torch.zeros(m * spp, 3, dtype=dtype, device=device)
            hsel = occl.nonzero()[:, 0]
            if hsel.numel():
                q = o_rep[hsel] + hit.t[hsel, None] * dirs[hsel]
                nq = hit.normal[hsel]
                nq = nq * torch.where((nq * dirs[hsel]).sum(-1) > 0, -1.0, 1.0).to(dtype)[:, None]
                Eq = _direct_irradiance(tracer, q, nq, hit.t[hsel] + ts.repeat_interleave(spp)[hsel])
                Lin[hsel] = tracer.albedo[hit.obj[hsel]] / math.pi * Eq
            ind[sl], ind_se[sl] = _group_stats(Lin.view(m, spp, 3), groups)
            bar.update(m * spp)
        else:
            occl = _ao_occlusion(tracer, backend, org, tb, bb, ns, key, spp, groups, seed, _AO_STREAM, True, R)
        ao[sl], ao_se[sl] = _group_stats((~occl).to(dtype).view(m, spp), groups)
        bar.update(m * spp)
        if uniform:
            occl = _ao_occlusion(tracer, backend, org, tb, bb, ns, key, spp, groups, seed, _UNIFORM_STREAM, False, R)
            aou[sl], aou_se[sl] = _group_stats((~occl).to(dtype).view(m, spp), groups)
            bar.update(m * spp)
    bar.close()

    # ---------------------------------------------------------------- images
    def image(values, fill, C):
        out = torch.full((npix, C), fill, dtype=dtype, device=device)
        out[idx] = values.reshape(nvalid, C)
        return out.view(B, H, W, C).permute(0, 3, 1, 2).contiguous()

    mask = valid.view(B, 1, H, W)

    def view_depth(t):  # distance along the unit camera ray -> view-axis depth, inf on background
        return torch.where(mask, t.view(B, 1, H, W).double() / scale_depth, float("inf")).to(dtype)

    depth = view_depth(t_prim)
    Rv = Rw.to(dtype)
    n_view = torch.einsum("bij,bjhw->bihw", Rv, image(n, 0.0, 3))
    n_view = torch.where(mask, n_view, torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device).view(1, 3, 1, 1))
    position = torch.where(mask, dview.to(dtype) * torch.where(mask, depth, 0.0), 0.0)
    oid = torch.zeros(npix, dtype=torch.long, device=device)
    oid[idx] = tracer.object_id[obj[idx]]
    gb = GBuffer(depth=depth, camera=views.camera.to(device=device, dtype=dtype), normals=n_view,
                 light=image(light_valid, 0.0, 3), mask=mask, object_id=oid.view(B, 1, H, W))
    return Reference(
        gbuffer=gb, albedo=image(alb, 0.0, 3), position=position,
        ao=image(ao, 1.0, 1), ao_stderr=image(ao_se, 0.0, 1),
        ao_uniform=image(aou, 1.0, 1) if uniform else None,
        ao_uniform_stderr=image(aou_se, 0.0, 1) if uniform else None,
        indirect=image(ind, 0.0, 3) if indirect else None,
        indirect_stderr=image(ind_se, 0.0, 3) if indirect else None,
        max_distance=R, spp=spp, seed=seed, world_to_view=views.world_to_view.clone(),
        backface_depth=view_depth(t_exit) if backface else None,
    )


def _progress(enabled: bool, total: int):
    from tqdm.auto import tqdm

    return tqdm(total=total, disable=not enabled, unit="ray", unit_scale=True, desc="render", leave=False)
