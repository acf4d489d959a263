"""The error split of fitted pipelines on the held-out views (docs/accuracy.md, "Fitted pipelines against the strongest GTAO").

For each ``params.json``: the screen-space truth of the view's depth buffer with the pipeline's *fitted*
thickness model (and its fetch) against the ray-traced reference (what the screen cannot know), the
pipeline (hard mode, with its denoiser) against that truth (what the estimator adds), and the total.

    PYTHONPATH=. python docs/targets/split_error.py docs/targets/{bitmask,backface}/params.json --scenes sphere_on_plane,fence,poles

Truths are cached under ``$TORCH_AO_CACHE/targets_truths``; the views are the seed-1000 built-in views at
320x180, 1024 spp, R = 0.5 (the same files as the fits, with their back-face layer).
"""
from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import torch

from torch_ao.datasets import HOLDOUT_SEED, default_cache_dir, reference_view
from torch_ao.fit import set_mode
from torch_ao.fitted import load_fitted
from torch_ao.screen_truth import screen_space_truth, split_error
from torch_ao.thickness import BACKFACE_CAP, BackfaceThickness, LinearThickness


def texel_thickness(pipeline, gbuffer):
    """The fitted model's thickness of every texel ``(B,1,H,W)`` (world units), or the scalar / ``(K,)``
    table as the truth takes it."""
    method = pipeline.method
    model = method.thickness_model
    if isinstance(model, BackfaceThickness):
        layer = (gbuffer.backface_depth - gbuffer.safe_depth).nan_to_num(nan=BACKFACE_CAP).clamp(0, BACKFACE_CAP)
        t = method.thickness_scale.detach() * layer + method.thickness.detach()
        return torch.where(gbuffer.valid, t, torch.zeros_like(t))
    if isinstance(model, LinearThickness):
        t = method.thickness.detach() + method.thickness_slope.detach() * gbuffer.safe_depth
        return torch.where(gbuffer.valid, t, torch.zeros_like(t))
    return method.thickness.detach()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("params", nargs="+")
    p.add_argument("--scenes", default="sphere_on_plane,fence,poles")
    p.add_argument("--rays", type=int, default=256)
    args = p.parse_args()
    cache = default_cache_dir()
    print("| pipeline | scene | truth vs reference (screen) | pipeline vs truth (estimator) | pipeline vs reference (total) |")
    print("| --- | --- | ---: | ---: | ---: |")
    for path in args.params:
        pipeline = load_fitted(path)
        set_mode(pipeline, "hard")
        fetch = pipeline.options.get("fetch", "bilinear")
        radius = float(pipeline.options.get("radius", pipeline.method.radius.detach()))
        for scene in args.scenes.split(","):
            view = reference_view(scene, HOLDOUT_SEED, height=180, width=320, spp=1024, max_distance=0.5,
                                  backface=True)
            gb = view.gbuffer
            T = texel_thickness(pipeline, gb)
            key = hashlib.sha1(repr((scene, args.rays, fetch, T.numpy().tobytes() if T.dim() else float(T))).encode()).hexdigest()[:16]
            file = cache / "targets_truths" / f"{scene}-{key}.pt"
            if file.exists():
                truth = torch.load(file)
            else:
                truth = screen_space_truth(gb, radius=0.5, thickness=T, rays=args.rays, fetch=fetch).visibility
                file.parent.mkdir(parents=True, exist_ok=True)
                torch.save(truth, file)
            with torch.no_grad():
                out = pipeline(gb).visibility
            s = split_error(out, truth, view.reference, gb.valid)[0]
            cells = [f"{m['psnr']:.2f} dB (bias {m['bias']:+.3f})" for m in (s.screen, s.estimator, s.total)]
            print(f"| {Path(path).parent.name} (R {radius:.3g}) | {scene} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
