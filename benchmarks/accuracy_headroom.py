"""Where the back-face pipeline's remaining error is: what more samples, a still camera's temporal accumulation,
other step distributions and other scalar parameters would give, on ``torch-ao fit``'s views.

Every row is a pipeline (a method + ``Denoiser()``, hard mode) at fixed parameters, scored by mean PSNR (dB)
against the ray-traced references in the three view groups of ``pipeline_candidates.py`` (the fit scenes'
training views, their held-out views, the held-out scenes). ``--study``:

* ``presets``: the back-face pipeline (fitted at ``high_steps``), its scalar-thickness form and the exact + back-face + edge-aware pipeline at
  ``high`` ... ``reference``:
  how much of the error is sampling (what converged sampling would reach);
* ``temporal``: the mean of ``N`` frames whose per-pixel noise differs (seeds ``0 .. N-1``) before the denoiser:
  a still camera's temporal accumulation after ``N`` frames, each frame at the preset's cost;
* ``steps``: the same sample count split into slices x steps, and denser steps near the pixel (``step_power``);
* ``resolution``: more samples on a half- or quarter-resolution walk (``preset@half``), upsampled;
* ``grid``: the scalar-thickness pipeline's thickness and radius on a grid (is the fit's optimum the defaults'?).

    OMP_NUM_THREADS=1 python benchmarks/accuracy_headroom.py --study presets temporal steps resolution grid
"""
from __future__ import annotations

import argparse
import itertools

import numpy as np
import torch

from pipeline_candidates import fit_view_groups
from torch_ao.fit import set_mode
from torch_ao.fitted import FittedPipeline
from torch_ao.metrics import error_metrics
from torch_ao.temporal import accumulate_still

#: torch-ao fit's pipeline with the values its default run fits at high_steps (docs/accuracy.md's headroom tables)
BACKFACE = ("bitmask cosine backface edge_aware, fitted at high_steps", "bitmask",
           {"weighting": "cosine", "fetch": "edge_aware", "thickness_model": "backface", "radius": 0.974,
            "thickness_scale": 0.816, "thickness": 0.165})
SCALAR = ("bitmask cosine edge_aware, one scalar thickness", "bitmask", {"weighting": "cosine", "fetch": "edge_aware"})
EXACT = ("bitmask exact backface edge_aware", "bitmask",
         {"variant": "exact", "thickness_model": "backface", "fetch": "edge_aware"})
GTAO = ("gtao", "gtao", {})


def score(method: str, options: dict, groups: dict, frames: int = 1) -> list[float]:
    """Mean PSNR per group of ``method(**options)`` + ``Denoiser()``, the method's output accumulated over
    ``frames`` still frames (:func:`~torch_ao.accumulate_still`) before the denoiser (the denoiser is linear in its input: the same as denoising
    each frame and averaging)."""
    pipe = FittedPipeline(method, {"radius": 1.0, **options}, denoiser=True)
    set_mode(pipe, "hard")
    scores = []
    for views in groups.values():
        psnr = []
        for view in views:
            with torch.no_grad():
                vis = pipe.denoiser(accumulate_still(pipe.method, view.gbuffer, frames).visibility, view.gbuffer).visibility
            psnr.append(error_metrics(vis, view.reference, view.gbuffer.valid)["psnr"])
        scores.append(float(np.mean(psnr)))
    return scores


def table(title: str, header: str, rows, groups: dict) -> None:
    print(f"\n{title}\n\n| {header} | " + " | ".join(groups) + " |")
    print("| --- | --- |" + " ---: |" * len(groups))
    for label, setting, method, options, frames in rows:
        print(f"| {label} | {setting} | " + " | ".join(f"{s:.2f}" for s in score(method, options, groups, frames)) + " |",
              flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="160x96")
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--study", nargs="+", default=["presets", "temporal", "steps", "resolution", "grid"],
                   choices=("presets", "temporal", "steps", "resolution", "grid"))
    args = p.parse_args()
    groups = fit_view_groups(args.size, args.spp)
    if "presets" in args.study:
        presets = ("high", "high_steps", "ultra", "extreme", "reference")
        table("Presets (slices x steps): high 3x3, high_steps 2x5, ultra 9x3, extreme 16x8, reference 32x32",
              "pipeline | preset", [(label, preset, m, {"preset": preset, **o}, 1)
                                    for label, m, o in (BACKFACE, SCALAR, EXACT, GTAO) for preset in presets], groups)
    if "temporal" in args.study:
        table("A still camera's temporal accumulation at `high`: the mean of N frames of different noise",
              "pipeline | frames", [(label, f"{n} ({noise})", m, {"preset": "high", "noise": noise, **o}, n)
                                    for label, m, o in (BACKFACE, EXACT, GTAO) for noise in ("ign", "hilbert_r2")
                                    for n in (1, 4, 8, 16)], groups)
    if "steps" in args.study:
        table("About `high`'s samples split differently, and denser steps near the pixel", "pipeline | slices x steps, step_power",
              [(label, f"{a}x{b}, {power:g}", m, {"slices": a, "steps": b, "step_power": power, **o}, 1)
               for label, m, o in (BACKFACE, EXACT) for (a, b), power in itertools.product(((3, 3), (2, 5), (1, 9)), (1.0, 1.5, 2.0))],
              groups)
    if "resolution" in args.study:
        table("More samples on a reduced-resolution walk", "pipeline | preset",
              [(label, preset, m, {"preset": preset, **o}, 1) for label, m, o in (BACKFACE, EXACT)
               for preset in ("ultra@half", "extreme@half", "extreme@quarter", "reference@quarter", "reference@half")],
              groups)
    if "grid" in args.study:
        label, m, o = SCALAR
        table("The scalar-thickness pipeline's parameters at `high` (defaults: thickness 0.5, radius 1)",
              "pipeline | thickness, radius",
              [(label, f"{t:g}, {r:g}", m, {"preset": "high", "thickness": t, **o, "radius": r}, 1)
               for t, r in itertools.product((0.2, 0.35, 0.5, 0.8), (0.85, 1.0, 1.2))], groups)


if __name__ == "__main__":
    main()
