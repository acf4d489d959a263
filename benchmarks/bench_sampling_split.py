"""Slice/step splits and per-pixel noise at a fixed sample count (about the high preset's 3 slices x 3 steps x 2
sides), measured against the built-in scenes' ray-traced references (PSNR, dB; higher is better), raw and after
``Denoiser()``.

    OMP_NUM_THREADS=1 python benchmarks/bench_sampling_split.py --height 72 --width 96
    OMP_NUM_THREADS=1 python benchmarks/bench_sampling_split.py --scenes fit --height 96 --width 128 \\
        --splits 3x3 --step-powers 1 --noises ign,hilbert_r2 \\
        --slice-samplings uniform,projected_normal --staggers off,on [--target converged]
"""
from __future__ import annotations

import argparse
import functools
import math

import torch

from torch_ao import Denoiser
from torch_ao.datasets import parse_scenes
from torch_ao.methods import get_method
from torch_ao.views import load_bench_views



def psnr(pred, ref, mask=None):
    err = (pred - ref) ** 2
    mse = err.mean() if mask is None else err[mask.expand_as(err)].mean()
    return -10.0 * math.log10(max(float(mse), 1e-12))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="procedural", help="built-in scenes and sets (fit, heldout, ...), comma-separated")
    p.add_argument("--methods", default="bitmask,gtao",
                   help="methods, comma-separated; bitmask_cosine is bitmask with weighting='cosine' (torch-ao fit's)")
    p.add_argument("--height", type=int, default=72)
    p.add_argument("--width", type=int, default=96)
    p.add_argument("--spp", type=int, default=64, help="rays per pixel of the references")
    p.add_argument("--step-powers", default="1,2")
    p.add_argument("--splits", default="3x3,2x5,1x9,5x2,9x1", help="slices x steps, comma-separated")
    p.add_argument("--jitter", default="on", choices=("on", "off"), help="per-pixel rotation and step offsets")
    p.add_argument("--noises", default="ign", help="per-pixel noise kinds (the noise option), comma-separated")
    p.add_argument("--slice-samplings", default="uniform", help="slice direction densities (the slice_sampling option)")
    p.add_argument("--staggers", default="off", help="step stagger across half-slices: off, on or off,on")
    p.add_argument("--seeds", default="0", help="noise seeds; each PSNR is the mean over them")
    p.add_argument("--target", default="reference", choices=("reference", "converged"),
                   help="score against the ray-traced reference, or against the same method at the reference "
                        "preset (32x32: its own limit, so that only the sampling error is scored)")
    a = p.parse_args(argv)
    torch.set_grad_enabled(False)
    views = load_bench_views(parse_scenes(a.scenes), height=a.height, width=a.width, spp=a.spp, progress=False, log=None)
    denoiser = Denoiser()
    limits: dict = {}

    def target(method, cls, view):
        if a.target == "reference":
            return view.reference
        if (method, view.name) not in limits:
            limits[method, view.name] = cls(preset="reference", radius=1.0)(view.gbuffer).visibility
        return limits[method, view.name]

    print(f"jitter {a.jitter}; target {a.target}; seeds {a.seeds}; per scene: raw / denoised\n\n| method | slices x steps | step_power | noise | slice_sampling | stagger | "
          + " | ".join(v.name for v in views) + " | mean | mean denoised |")
    print("| --- " * (8 + len(views)) + "|")
    for method in a.methods.split(","):
        cls = get_method(method.removesuffix("_cosine"))
        if method.endswith("_cosine"):
            cls = functools.partial(cls, weighting="cosine")
        for sp in map(float, a.step_powers.split(",")):
            for slices, steps in (tuple(map(int, x.split("x"))) for x in a.splits.split(",")):
                for noise, sampling, stagger in ((n, d, t) for n in a.noises.split(",")
                                                 for d in a.slice_samplings.split(",") for t in a.staggers.split(",")):
                    seeds = [int(x) for x in a.seeds.split(",")]
                    raw, den = [0.0] * len(views), [0.0] * len(views)
                    for seed in seeds:
                        m = cls(slices=slices, steps=steps, step_power=sp, radius=1.0, jitter=a.jitter == "on",
                                noise=noise, slice_sampling=sampling, stagger=stagger == "on", seed=seed)
                        for i, v in enumerate(views):
                            out = m(v.gbuffer)
                            vis = out.visibility if hasattr(out, "visibility") else out
                            mask = v.gbuffer.mask if getattr(v.gbuffer, "mask", None) is not None else None
                            ref = target(method, cls, v)
                            raw[i] += psnr(vis, ref, mask) / len(seeds)
                            den[i] += psnr(denoiser(vis, v.gbuffer).visibility, ref, mask) / len(seeds)
                    print(f"| {method} | {slices}x{steps} | {sp:g} | {noise} | {sampling} | {stagger} | "
                          + " | ".join(f"{x:.2f} / {y:.2f}" for x, y in zip(raw, den))
                          + f" | {sum(raw)/len(raw):.2f} | {sum(den)/len(den):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
