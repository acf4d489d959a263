"""Which pipeline should ``torch-ao fit`` fit by default? Every candidate (method, variant, thickness model,
fetch, with the denoiser) at its default parameters, hard mode, on the views ``torch-ao fit`` uses: the
fit scenes' training views, their held-out views, and the held-out scenes' views, reported separately.

    python benchmarks/pipeline_candidates.py                  # 160x96, 256 spp: torch-ao fit's views
    python benchmarks/pipeline_candidates.py --size 96x72 --spp 64 --train-views 1

Prints a Markdown table: mean PSNR (dB) per view group and the median forward time per view (ms).
"""
from __future__ import annotations

import argparse

import torch

from torch_ao.datasets import HOLDOUT_SEED, parse_scenes, reference_views, train_and_holdout_views
from torch_ao.fit import evaluate
from torch_ao.fitted import FittedPipeline
from torch_ao.methods import DEFAULT_PRESET

#: (label, method, options): the shipped pipeline first
CANDIDATES = (
    ("bitmask cosine (shipped)", "bitmask", {"weighting": "cosine"}),
    ("bitmask cosine edge_aware", "bitmask", {"weighting": "cosine", "fetch": "edge_aware"}),
    ("bitmask cosine backface", "bitmask", {"weighting": "cosine", "thickness_model": "backface"}),
    ("bitmask cosine backface edge_aware", "bitmask",
     {"weighting": "cosine", "thickness_model": "backface", "fetch": "edge_aware"}),
    ("bitmask exact", "bitmask", {"variant": "exact"}),
    ("bitmask exact backface edge_aware", "bitmask",
     {"variant": "exact", "thickness_model": "backface", "fetch": "edge_aware"}),
    ("gtao", "gtao", {}),
    ("gtao edge_aware", "gtao", {"fetch": "edge_aware"}),
)


def fit_view_groups(size: str = "160x96", spp: int = 256, train_views: int = 2) -> dict:
    """``torch-ao fit``'s views at ``size`` (``"WxH"``), in three groups ``{label: [FitView]}``: the fit scenes'
    ``train_views`` training views, their held-out views, and the held-out scenes' views (R = 1, back-face
    layers, ``spp`` rays per pixel)."""
    w, h = (int(x) for x in size.split("x"))
    common = dict(height=h, width=w, spp=spp, max_distance=1.0, backface=True, device=torch.device("cpu"))
    train, held = train_and_holdout_views(parse_scenes("fit"), train_views, 1, **common)
    other = reference_views(parse_scenes("heldout"), [HOLDOUT_SEED], **common)
    return {"fit scenes, training views": train, "fit scenes, held-out views": held, "held-out scenes": other}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="160x96")
    p.add_argument("--spp", type=int, default=256)
    p.add_argument("--train-views", type=int, default=2)
    p.add_argument("--preset", default=DEFAULT_PRESET)
    p.add_argument("--repeats", type=int, default=1)
    args = p.parse_args()
    groups = fit_view_groups(args.size, args.spp, args.train_views)
    print(f"| pipeline (+ denoiser, `{args.preset}`) | " + " | ".join(groups) + " | ms |")
    print("| --- |" + " ---: |" * (len(groups) + 1))
    for label, method, options in CANDIDATES:
        pipe = FittedPipeline(method, {"preset": args.preset, "radius": 1.0, **options}, denoiser=True)
        with torch.no_grad():
            scores = {g: evaluate(pipe, views, repeats=args.repeats) for g, views in groups.items()}
        ms = 1000 * sorted(s["seconds"] for s in scores.values())[1]
        print(f"| {label} | " + " | ".join(f"{s['psnr']:.2f}" for s in scores.values()) + f" | {ms:.1f} |", flush=True)


if __name__ == "__main__":
    main()
