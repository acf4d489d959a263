"""Bitmask AO's error against the screen-space truth and the ray-traced reference, preset by preset.

For each built-in scene, one view is ray-traced (cosine-weighted AO within ``R``) and its screen-space
truth computed for the same depth buffer and a fixed scalar thickness (``torch_ao.screen_truth``: rays
tested against the depth buffer as surfaces of that thickness, the back face at depth + thickness).
Each configuration of bitmask AO then runs in hard mode at every preset; the table gives its MAE and
mean signed error (bias) against both. Renders are cached in ``--cache``.

    python benchmarks/bitmask_convergence.py                       # fence and stairs, 96x54, R = 0.5
    python benchmarks/bitmask_convergence.py --size 320x180 --scenes fence,stairs,poles --thickness 0.1
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from torch_ao.methods.base import PRESETS
from torch_ao.methods.bitmask import BitmaskAO
from torch_ao.reference import get_scene, render_reference
from torch_ao.screen_truth import screen_space_truth

CONFIGS = {
    "default (uniform sectors, ceil)": dict(),
    "default, cosine": dict(weighting="cosine"),
    "+ union=exact": dict(weighting="cosine", union="exact"),
    "+ clip_to_radius": dict(weighting="cosine", union="exact", clip_to_radius=True),
    "+ sample_extent=sphere": dict(weighting="cosine", union="exact", clip_to_radius=True, sample_extent="sphere"),
    "variant=exact (+ thickness_direction=depth)": dict(variant="exact"),
}


def views(scene: str, size: tuple[int, int], radius: float, thickness: float, rays: int, cache: Path):
    W, H = size
    path = cache / f"{scene}-{W}x{H}-R{radius:g}-t{thickness:g}-r{rays}.pt"
    if path.exists():
        return torch.load(path, weights_only=False)
    t0 = time.perf_counter()
    ref = render_reference(get_scene(scene), height=H, width=W, spp=256, max_distance=radius, progress=False,
                           uniform=False)
    t1 = time.perf_counter()
    truth = screen_space_truth(ref.gbuffer, radius, thickness, rays=rays)
    print(f"{scene}: reference {t1 - t0:.0f} s, screen-space truth {time.perf_counter() - t1:.0f} s", file=sys.stderr)
    out = (ref.gbuffer, ref.ao, truth.visibility, truth.stderr)
    cache.mkdir(parents=True, exist_ok=True)
    torch.save(out, path)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="fence,stairs")
    p.add_argument("--size", default="96x54")
    p.add_argument("--radius", type=float, default=0.5)
    p.add_argument("--thickness", type=float, default=0.25)
    p.add_argument("--rays", type=int, default=1024, help="rays per pixel of the screen-space truth")
    p.add_argument("--presets", default=",".join(PRESETS))
    p.add_argument("--configs", default=",".join(str(i) for i in range(len(CONFIGS))),
                   help="indices into the configurations (0..%d)" % (len(CONFIGS) - 1))
    p.add_argument("--cache", default=str(Path.home() / ".cache" / "torch_ao" / "bitmask_convergence"))
    args = p.parse_args(argv)
    size = tuple(int(x) for x in args.size.split("x"))
    names = list(CONFIGS)
    for scene in args.scenes.split(","):
        gb, ref, truth, se = views(scene, size, args.radius, args.thickness, args.rays, Path(args.cache))
        valid = gb.valid
        print(f"\n### {scene} {args.size}, R = {args.radius:g}, thickness = {args.thickness:g} "
              f"(truth: mean stderr {float(se[valid].mean()):.4f}; truth vs ray-traced MAE "
              f"{float((truth - ref)[valid].abs().mean()):.4f})\n")
        presets = args.presets.split(",")
        print("| configuration | " + " | ".join(presets) + " |")
        print("| --- |" + " ---: |" * len(presets))
        for i in map(int, args.configs.split(",")):
            cells_t, cells_r = [], []
            for preset in presets:
                with torch.no_grad():
                    vis = BitmaskAO(preset=preset, radius=args.radius, thickness=args.thickness, **CONFIGS[names[i]])(gb).visibility
                e_t, e_r = (vis - truth)[valid], (vis - ref)[valid]
                cells_t.append(f"{float(e_t.abs().mean()):.4f} ({float(e_t.mean()):+.4f})")
                cells_r.append(f"{float(e_r.abs().mean()):.4f}")
            print(f"| {names[i]}: vs truth MAE (bias) | " + " | ".join(cells_t) + " |")
            print(f"| {names[i]}: vs ray-traced MAE | " + " | ".join(cells_r) + " |")


if __name__ == "__main__":
    main()
