"""Bitmask AO's error against the screen-space truth and the ray-traced reference, preset by preset.

For each built-in scene, one view is ray-traced (cosine-weighted AO within ``R``) and its screen-space
truth computed for the same depth buffer and a fixed thickness (``torch_ao.screen_truth``: rays tested
against the depth buffer as surfaces of that thickness, the back face at depth + thickness): a scalar, or
with ``--thickness backface`` each object's own, from its traced exit depth (``BackfaceThickness``).
Each configuration of bitmask AO then runs in hard mode at every preset; the table gives its MAE and
mean signed error (bias) against both. Renders are cached in ``--cache``.

With ``--fetch`` both the methods and the truth read the depth buffer that way (``edge_aware``: no
bilinear skirts across depth edges). Each table's header gives the truth against the ray-traced AO.

    python benchmarks/bitmask_convergence.py                       # fence and stairs, 96x54, R = 0.5
    python benchmarks/bitmask_convergence.py --size 320x180 --scenes fence,stairs,poles --thickness 0.1
    python benchmarks/bitmask_convergence.py --scenes all --configs 1,5 --fetch edge_aware
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import math

import torch

from torch_ao.gbuffer import GBuffer
from torch_ao.io import load_gbuffer, save_npz
from torch_ao.methods.base import PRESETS
from torch_ao.metrics import error_metrics
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.reference import Tracer, get_scene, render_reference
from torch_ao.screen_truth import screen_space_truth
from torch_ao.thickness import BackfaceThickness
from torch_ao.walk import FETCH_MODES

CONFIGS = {
    "default (uniform sectors, ceil)": dict(),
    "default, cosine": dict(weighting="cosine"),
    "+ union=exact": dict(weighting="cosine", union="exact"),
    "+ clip_to_radius": dict(weighting="cosine", union="exact", clip_to_radius=True),
    "+ sample_extent=sphere": dict(weighting="cosine", union="exact", clip_to_radius=True, sample_extent="sphere"),
    "variant=exact (+ thickness_direction=depth, min_step_px=0.25)": dict(variant="exact"),
}


ALL_SCENES = ("sphere_on_plane", "fence", "room_corner", "stairs", "floating", "poles")


def backface_depth(scene, ref) -> torch.Tensor:
    """``(B,1,H,W)`` depth where each camera ray leaves the object it first hit (``inf``: an open surface,
    or another object first), traced again from just behind the first hit."""
    tracer = Tracer(scene)
    M = ref.world_to_view.double()
    Rw = M[:, :3, :3]
    eye = -torch.einsum("bji,bj->bi", Rw, M[:, :3, 3])
    dview = ref.gbuffer.camera.to(dtype=torch.float64).pixel_rays()
    d = torch.nn.functional.normalize(torch.einsum("bji,bjhw->bihw", Rw, dview), dim=1).permute(0, 2, 3, 1).reshape(-1, 3).float()
    o = eye[:, None, :].expand(-1, d.shape[0] // eye.shape[0], 3).reshape(-1, 3).float()
    first = tracer.intersect(o, d)
    eps = 1e-4 * first.t.clamp(max=1e6)
    second = tracer.intersect(o + (first.t + eps)[:, None] * d, d)
    same = first.hit & second.hit & (second.obj == first.obj)
    t_exit = torch.where(same, first.t + eps + second.t, torch.full_like(first.t, math.inf))
    depth = t_exit.view(ref.gbuffer.depth.shape[0], 1, *ref.gbuffer.depth.shape[-2:]) / dview.norm(dim=1, keepdim=True).float()
    return torch.where(ref.gbuffer.valid, torch.maximum(depth, ref.gbuffer.depth), ref.gbuffer.depth)


def views(scene: str, size: tuple[int, int], radius: float, thickness: str, rays: int, cache: Path,
          fetch: str = "bilinear"):
    """The G-buffer (with ``backface_depth``), the ray-traced AO, the screen-space truth (read with
    ``fetch``) and its stderr. The render is shared by the truths of every fetch."""
    W, H = size
    stem = f"{scene}-{W}x{H}-R{radius:g}-t{thickness}-r{rays}"
    path = cache / f"{stem}{'' if fetch == 'bilinear' else '-' + fetch}.npz"
    if path.exists():
        return _read(path)
    t0 = time.perf_counter()
    rendered = (_read(p) for p in sorted(cache.glob(f"{scene}-{W}x{H}-R{radius:g}-t*-r*.npz")))
    found = next((r[:2] for r in rendered if r[0].backface_depth is not None), None)
    if found is not None:
        gb, ref_ao = found
    else:
        built = get_scene(scene)
        ref = render_reference(built, height=H, width=W, spp=256, max_distance=radius, progress=False, uniform=False)
        g = ref.gbuffer
        gb = GBuffer(g.depth, g.camera, normals=g.normals, light=g.light, mask=g.mask, object_id=g.object_id,
                     backface_depth=backface_depth(built, ref))
        ref_ao = ref.ao
    t1 = time.perf_counter()
    if thickness == "backface":
        truth = screen_space_truth(gb, radius, backface_depth=gb.backface_depth, rays=rays, fetch=fetch)
    else:
        truth = screen_space_truth(gb, radius, float(thickness), rays=rays, fetch=fetch)
    print(f"{scene}: reference {t1 - t0:.0f} s, screen-space truth ({fetch}) {time.perf_counter() - t1:.0f} s",
          file=sys.stderr)
    save_npz(path, gb, ao=ref_ao, truth=truth.visibility, truth_stderr=truth.stderr)
    return gb, ref_ao, truth.visibility, truth.stderr


def _read(path: Path):
    """``(G-buffer, reference AO, screen-space truth, its stderr)`` of a cached ``.npz`` (no pickles)."""
    gb, extras = load_gbuffer(path)
    return gb, extras["ao"], extras["truth"], extras["truth_stderr"]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="fence,stairs", help="comma-separated built-in scenes, or 'all' (the six)")
    p.add_argument("--size", default="96x54")
    p.add_argument("--radius", type=float, default=0.5)
    p.add_argument("--thickness", default="0.25", help="a scalar (world units), or 'backface': each occluder's "
                   "own thickness from the traced back-face depth (BackfaceThickness, and the truth with it)")
    p.add_argument("--rays", type=int, default=1024, help="rays per pixel of the screen-space truth")
    p.add_argument("--presets", default=",".join(PRESETS))
    p.add_argument("--fetch", default="bilinear", choices=FETCH_MODES,
                   help="depth fetch of the methods and of the screen-space truth")
    p.add_argument("--configs", default=",".join(str(i) for i in range(len(CONFIGS))),
                   help="indices into the configurations (0..%d)" % (len(CONFIGS) - 1))
    p.add_argument("--cache", default=str(Path.home() / ".cache" / "torch_ao" / "bitmask_convergence"))
    args = p.parse_args(argv)
    size = tuple(int(x) for x in args.size.split("x"))
    names = list(CONFIGS)
    scenes = ALL_SCENES if args.scenes == "all" else args.scenes.split(",")
    for scene in scenes:
        gb, ref, truth, se = views(scene, size, args.radius, args.thickness, args.rays, Path(args.cache), args.fetch)
        valid = gb.valid
        e = (truth - ref)[valid]
        db = error_metrics(truth, ref, valid)["psnr"]
        print(f"\n### {scene} {args.size}, R = {args.radius:g}, thickness = {args.thickness}, fetch = {args.fetch} "
              f"(truth: mean stderr {float(se[valid].mean()):.4f}; truth vs ray-traced MAE "
              f"{float(e.abs().mean()):.4f}, bias {float(e.mean()):+.4f}, {db:.1f} dB)\n")
        presets = args.presets.split(",")
        print("| configuration | " + " | ".join(presets) + " |")
        print("| --- |" + " ---: |" * len(presets))
        for i in map(int, args.configs.split(",")):
            cells_t, cells_r = [], []
            for preset in presets:
                with torch.no_grad():
                    model = BackfaceThickness() if args.thickness == "backface" else float(args.thickness)
                    vis = BitmaskAO(preset=preset, radius=args.radius, thickness=model, fetch=args.fetch,
                                    **CONFIGS[names[i]])(gb).visibility
                e_t, e_r = (vis - truth)[valid], (vis - ref)[valid]
                cells_t.append(f"{float(e_t.abs().mean()):.4f} ({float(e_t.mean()):+.4f})")
                cells_r.append(f"{float(e_r.abs().mean()):.4f} ({error_metrics(vis, ref, valid)['psnr']:.1f} dB)")
            print(f"| {names[i]}: vs truth MAE (bias) | " + " | ".join(cells_t) + " |")
            print(f"| {names[i]}: vs ray-traced MAE (PSNR) | " + " | ".join(cells_r) + " |")


if __name__ == "__main__":
    main()
