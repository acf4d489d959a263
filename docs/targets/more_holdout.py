"""Score fitted pipelines on more held-out views than their fit did (no refit): docs/accuracy.md, "Fitted pipelines against the strongest GTAO".

The views are the built-in scenes' randomised views with the given seeds (never training seeds, which are 1, 2...),
at 320x180, 1024 spp, R = 0.5, with the back-face layer (rendered into the cache on first use). Prints the same
tables as ``table.py`` (per-scene mean PSNR, each bitmask pipeline against the strongest GTAO fit).

    PYTHONPATH=. python docs/targets/more_holdout.py --seeds 1003,1004,1005 --cache refs \\
        --bitmask docs/targets/{backface_edge,exact_backface_edge}/params.json --gtao docs/targets/{gtao,gtao_edge}/params.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from torch_ao.datasets import HOLDOUT_SEED, TRAIN_SCENES, reference_views
from torch_ao.fit import evaluate
from torch_ao.fitted import FittedPipeline, load_fitted

sys.path.insert(0, str(Path(__file__).parent))
import table  # noqa: E402  (the tables and the targets' verdict)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", required=True, help=f"comma-separated held-out seeds (>= {HOLDOUT_SEED})")
    p.add_argument("--bitmask", nargs="+", required=True)
    p.add_argument("--gtao", nargs="+", required=True)
    p.add_argument("--cache", default=None)
    p.add_argument("--size", default="320x180")
    args = p.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    if min(seeds) < HOLDOUT_SEED:
        raise SystemExit(f"error: --seeds: held-out seeds start at {HOLDOUT_SEED}; lower ones are training views")
    w, h = (int(x) for x in args.size.split("x"))
    views = reference_views(TRAIN_SCENES, seeds, height=h, width=w, spp=1024, max_distance=0.5, cache_dir=args.cache,
                            backface=True)
    with torch.no_grad():
        scored = lambda pipeline: evaluate(pipeline, views, per_view=True)["views"]
        fits = {Path(f).parent.name: scored(load_fitted(f)) for f in args.bitmask}
        gtao = {f"GTAO {Path(f).parent.name}": scored(load_fitted(f)) for f in args.gtao}
        default = scored(starting_pipeline(args.gtao[0]))
    print(f"held-out seeds {', '.join(map(str, seeds))}: {len(views)} views")
    table.report(fits, gtao, default)


def starting_pipeline(path: str) -> FittedPipeline:
    """The fitted pipeline's method, options and denoiser at the method's default parameters and radius R (the
    first step's radius), as ``torch-ao fit`` scores its "default" row."""
    data = json.loads(Path(path).read_text())
    return FittedPipeline.from_dict({**data, "parameters": {"radius": data["history"][0]["radius"][0]}}, source=path)


if __name__ == "__main__":
    main()
